"""Gain table files: one YAML file per table, written by ``beamctl gains build`` and read by
the real-time service.

A table is the compensator the control step runs (gains/compensator.py: per grid load the
matrices A, B, E, C, D, Ki, with H, the start map and the split of its states between the bending
planes), over a load grid, with what it was designed as and for (``design``: the kind of design,
the sample rate, the I/O chain it assumes, and the design's own parameters), (C0 Phi)^-1, the
schedule settings, the model parameters with their SHA-256, the closed-loop check, the tool
version and the creation time, and a SHA-256 over all of it. Loading checks every field; anything
wrong is refused with a GainTableError naming the field. Numbers are written in Python's
shortest round-trip form, so a table reads back bit for bit and its content hash is reproducible.

Design kinds: ``integral-lqr`` (the paper's: integral LQR gains K [G x 4 x 12] on the modal
model with a high-pass velocity estimate; the file keeps K, Q, R and the velocity filter's
cut-off under ``design``) and ``lqg`` (a model-based design; its parameters under
``design.parameters``, a free mapping).

A table the controller may run has a content hash that matches, a closed-loop check, and
no unstable point in it (nor ``--force``): ``load_table`` refuses anything else unless
asked only to read it (``verify=False``, for ``beamctl gains check`` and ``show``).

Optional, and absent from tables written before them: the compensator's strain prediction
``compensator.predict`` (P [G x 4 x n], y_hat = P x_c, with which the engine bridges a missing
sample; absent: hold the last measured strains) and the loop's ride-through limits
``ride_through`` (gains/ridethrough.py: the longest gap of missing samples and the largest extra
output delay the loop survives, and the limits the engine uses, at its worst check load and, in
tables written since, per grid load: ``max_gap_samples_per_load``, ``gap_limits_samples``,
``max_extra_delay_samples_per_load``, ``answer_budgets_periods``, one value per entry of
``loads_N``; a table with the scalars only has an answer budget that does not count the
design's own delay).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from beamctl.config.schema import ConfigError, read_yaml
from beamctl.gains.compensator import MATRICES, Compensator
from beamctl.gains.discrete import LoopCheck
from beamctl.gains.lqr import N_INPUTS, N_STATES, Weights
from beamctl.gains.ridethrough import (
    BRIDGES,
    DELAY_MARGIN,
    LEGACY_BRIDGE,
    OUTPUTS,
    RideThrough,
    answer_budget,
)
from beamctl.models.iochain import IOChain, io_chain
from beamctl.models.params import ModelParameters, parameters_from_dict

FORMAT = "beamctl-gain-table/3"
# earlier formats, refused with the reason and what to run
OLD_FORMATS = {
    "beamctl-gain-table/1": "carries no SHA-256 of its content",
    "beamctl-gain-table/2": "holds only integral LQR gains, not the compensator matrices the controller "
                            "now runs",
}
CONTENT_HASH = "sha256"
SCHEDULE_MODES = ("interpolate", "paper")
DESIGN_KINDS = ("integral-lqr", "lqg")
# the fields of ``design`` in the file besides kind, sample_rate_hz and io, per kind
_DESIGN_FIELDS = {"integral-lqr": ("velocity_cutoff_hz", "Q_diagonal", "R_diagonal", "gains"),
                  "lqg": ("parameters",)}


class GainTableError(ConfigError):
    """A gain table file was refused; ``key`` names the field."""


def content_sha256(data: Mapping[str, Any]) -> str:
    """SHA-256 of a table file's content: the canonical JSON (sorted keys, no spaces, numbers
    in shortest round-trip form) of every field but the ``sha256`` field itself."""
    content = {k: v for k, v in data.items() if k != CONTENT_HASH}
    canonical = json.dumps(content, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(canonical.encode()).hexdigest()


def rebuild_advice(path: str | Path, design: str | None = None, mode: str | None = None) -> str:
    """What to run to replace a table file that cannot be used: the build of its own design
    (``design``, ``mode`` where the file says them; the build's default is the LQG)."""
    flags = ""
    if design == "integral-lqr":
        flags = " --design integral-lqr" + (" --mode paper" if mode == "paper" else "")
    return (f"rebuild it with `beamctl gains build{flags} --out {path}` (with `--config` for a model other "
            f"than the paper's) and check it with `beamctl gains check {path}`")


def changed_file_message(path: str | Path, design: str | None = None, mode: str | None = None) -> str:
    """Why a table whose content does not match its SHA-256 is refused, and what to run."""
    return f"the file was changed after it was built; {rebuild_advice(path, design, mode)}"


@dataclass(frozen=True)
class DesignSettings:
    """What a table's compensator was designed as and for.

    ``kind``: ``integral-lqr`` (the paper's design; ``velocity_cutoff_hz`` and ``weights`` say
    how it was made) or ``lqg`` (its own design parameters in ``parameters``: plain data, i.e.
    numbers, strings, booleans, lists and mappings, written to the file as they are).
    ``io``: the I/O chain (delay, filters) the design assumes; the closed-loop check uses it.
    """

    kind: str
    sample_rate_hz: float
    io: IOChain = field(default_factory=IOChain)
    velocity_cutoff_hz: float | None = None      # integral-lqr
    weights: Weights | None = None               # integral-lqr
    parameters: Mapping[str, Any] = field(default_factory=dict)   # other kinds

    def __post_init__(self) -> None:
        if self.kind not in DESIGN_KINDS:
            raise ValueError(f"design kind {self.kind!r}: expected one of {DESIGN_KINDS}")
        if self.kind == "integral-lqr":
            if self.velocity_cutoff_hz is None or self.weights is None:
                raise ValueError("an integral-lqr design needs velocity_cutoff_hz and weights")
            if self.parameters:
                raise ValueError("an integral-lqr design keeps its parameters in velocity_cutoff_hz "
                                 "and weights, not in parameters")
        elif self.velocity_cutoff_hz is not None or self.weights is not None:
            raise ValueError(f"velocity_cutoff_hz and weights belong to integral-lqr designs, not "
                             f"{self.kind}: put the design's parameters in parameters")


@dataclass(frozen=True)
class ScheduleSettings:
    """How K(Fx) is looked up: ``interpolate`` (linear between grid points) or ``paper``
    (the gain of the grid point at or above the load, switched with a hysteresis band);
    the load-cell value is low-pass filtered at ``load_filter_hz`` first."""

    mode: str
    load_filter_hz: float
    hysteresis_n: float


@dataclass(frozen=True)
class GainTable:
    """A gain table: the compensator the control step runs, over a load grid, with its design.

    Built by a design (``gains.build.build_table`` for integral-lqr), then checked
    (``gains.build.closed_loop_checks``, stored with ``dataclasses.replace(table, checks=...)``)
    and written (``write_table``). ``gains`` is K [G x 4 x 12] of an integral-lqr design (its
    compensator is ``compensator.from_integral_lqr`` of it) and None for any other kind.
    """

    loads_n: np.ndarray            # [G], strictly increasing
    compensator: Compensator       # [G x ...] matrices, period 1 / design.sample_rate_hz
    c0_phi_inv: np.ndarray         # [4 x 4]: q = (C0 Phi)^-1 y, telemetry and monitoring
    design: DesignSettings
    schedule: ScheduleSettings
    model_parameters: ModelParameters
    checks: tuple[LoopCheck, ...] = ()
    forced: bool = False
    tool_version: str = ""
    created: str = field(default_factory=lambda: _dt.datetime.now(_dt.timezone.utc).isoformat(
        timespec="seconds"))
    # read from a file whose content matches its SHA-256 (a table built in memory: True)
    intact: bool = True
    gains: np.ndarray | None = None   # K [G x 4 x 12] of an integral-lqr design
    # the ride-through limits found when it was built (gains.ridethrough); None: not analysed
    # (built without the check, unstable, or written before the analysis existed)
    ride_through: RideThrough | None = None
    # the robust check's result on this table (gains.robust ``table_record``); None: not recorded
    robust: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        comp = self.compensator
        comp.validate_shapes()
        if comp.n_points != len(self.loads_n):
            raise ValueError(f"the compensator has {comp.n_points} grid points, the load grid "
                             f"{len(self.loads_n)}")
        if not math.isclose(comp.period_s * self.design.sample_rate_hz, 1.0, rel_tol=1e-12):
            raise ValueError(f"the compensator's period {comp.period_s} s is not 1 / the design's "
                             f"sample rate {self.design.sample_rate_hz} Hz")
        if self.design.kind == "integral-lqr":
            if self.gains is None or self.gains.shape != (len(self.loads_n), N_INPUTS, N_STATES):
                raise ValueError(f"an integral-lqr table needs its gains K [{len(self.loads_n)} x "
                                 f"{N_INPUTS} x {N_STATES}]")
        elif self.gains is not None:
            raise ValueError(f"gains K belong to integral-lqr tables, not {self.design.kind}")

    @property
    def model_sha256(self) -> str:
        return self.model_parameters.digest()

    @property
    def sha256(self) -> str:
        """The SHA-256 of the table's content: the ``sha256`` its file carries (a table read from
        a file whose content was changed afterwards: the hash of what was read)."""
        return content_sha256(self._content())

    @property
    def checked(self) -> bool:
        """The table carries the result of its closed-loop check."""
        return bool(self.checks)

    @property
    def all_stable(self) -> bool:
        """Checked, and stable at every check point."""
        return self.checked and all(c.stable for c in self.checks)

    def to_dict(self) -> dict[str, Any]:
        """The file's content, with the SHA-256 of everything else under ``sha256``."""
        content = self._content()
        return {"format": content["format"], CONTENT_HASH: content_sha256(content), **content}

    def _content(self) -> dict[str, Any]:
        d, comp = self.design, self.compensator
        design: dict[str, Any] = {"kind": d.kind, "sample_rate_hz": float(d.sample_rate_hz),
                                  "io": d.io.to_dict()}
        if d.kind == "integral-lqr":
            design.update(velocity_cutoff_hz=float(d.velocity_cutoff_hz),
                          Q_diagonal=[float(x) for x in d.weights.q],
                          R_diagonal=[float(x) for x in d.weights.r],
                          gains=np.asarray(self.gains, dtype=float).tolist())
        else:
            design["parameters"] = _plain(d.parameters)
        compensator = {"plane_states": {p: [int(i) for i in comp.plane_states[p]] for p in ("y", "z")},
                       "h": np.asarray(comp.h, dtype=float).tolist(),
                       "start": np.asarray(comp.start, dtype=float).tolist(),
                       **{m: np.asarray(getattr(comp, m), dtype=float).tolist() for m in MATRICES}}
        if comp.predict is not None:
            compensator["predict"] = np.asarray(comp.predict, dtype=float).tolist()
        content = {
            "format": FORMAT,
            "created": self.created,
            "tool_version": self.tool_version,
            "model": {"sha256": self.model_sha256, "parameters": self.model_parameters.to_dict()},
            "design": design,
            "schedule": {"mode": self.schedule.mode, "load_filter_hz": self.schedule.load_filter_hz,
                         "hysteresis_N": self.schedule.hysteresis_n},
            "c0_phi_inv": self.c0_phi_inv.tolist(),
            "loads_N": [float(x) for x in self.loads_n],
            "compensator": compensator,
            "check": {
                "all_stable": self.all_stable,
                "forced": self.forced,
                "points": [_check_point(c) for c in self.checks],
            },
        }
        if self.ride_through is not None:
            content["ride_through"] = self.ride_through.to_dict()
        if self.robust is not None:
            content["robust"] = _plain(self.robust)
        return content


def _plain(value: Any) -> Any:
    """Design parameters as plain YAML/JSON data (arrays as nested lists, numpy scalars as
    Python numbers)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _check_point(c: LoopCheck) -> dict[str, Any]:
    point = {"load_N": c.load_n, "spectral_radius": c.spectral_radius, "min_damping": c.min_damping,
             "stable": c.stable}
    if c.gain_load_n is not None:       # the gain of that grid point (paper mode's band edges)
        point["gain_load_N"] = c.gain_load_n
    return point


def require_checked(table: GainTable, source: str, advice: str) -> None:
    """Refuse to run a table whose closed-loop check is missing or failed: no check points
    (built without the check), an unstable point, or written with ``--force``. ``advice``
    says what to run instead."""
    if not table.checked:
        raise GainTableError("check.points", "none",
                             f"the result of the closed-loop check (this table was built without "
                             f"it); {advice}", source)
    unstable = [c.load_n for c in table.checks if not c.stable]
    if unstable or table.forced:
        more = " ..." if len(unstable) > 8 else ""
        found = f"unstable at {unstable[:8]}{more} N" if unstable else "stable"
        raise GainTableError("check.forced" if table.forced else "check.points",
                             found + (", written with --force" if table.forced else ""),
                             f"a closed loop stable at every check point, built without --force; "
                             f"{advice}", source)


def write_table(table: GainTable, path: str | Path) -> Path:
    """Write ``table`` as YAML. A table with an unstable check point is refused unless it
    was built with ``forced=True`` (the file then says so), and a table read from a changed
    file is refused: writing it would give the change a matching hash."""
    if not table.intact:
        raise GainTableError(CONTENT_HASH, "changed", f"a table as built, not one read from a file "
                             f"changed after it was built; "
                             f"{rebuild_advice(path, table.design.kind, table.schedule.mode)}")
    if table.checked and not table.all_stable and not table.forced:
        unstable = [c.load_n for c in table.checks if not c.stable]
        raise GainTableError("check.all_stable", False,
                             f"a stable closed loop at every check point; unstable at {unstable} N "
                             f"(build with --force to write it anyway, marked as forced)")
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    header = ("# beamctl gain table: a scheduled state-space compensator over the axial load\n"
              f"# ({table.design.kind} design). Written by `beamctl gains build`; checked on load.\n"
              "# Do not edit by hand: the SHA-256 of the content would no longer match and\n"
              "# `beamctl run` refuses it.\n")
    content = table.to_dict()
    compensator = content["compensator"]
    for name in (*MATRICES, "predict"):
        if name in compensator:
            compensator[name] = _FlowList(compensator[name])
    text = yaml.dump(content, Dumper=_TableDumper, sort_keys=False, width=120, default_flow_style=None)
    p.write_text(header + text)
    return p


class _FlowList(list):
    """A matrix stack written as one YAML flow sequence: the same data as the block style, read
    about ten times faster (config.schema.parse_yaml reads such a sequence of numbers as JSON)."""


class _TableDumper(getattr(yaml, "CSafeDumper", yaml.SafeDumper)):  # libyaml's emitter where built
    pass


_TableDumper.add_representer(
    _FlowList,
    lambda dumper, value: dumper.represent_sequence("tag:yaml.org,2002:seq", value, flow_style=True))


# ---------------------------------------------------------------------------------------------
# reading


def _field(data: dict, key: str, source: str) -> Any:
    node: Any = data
    for part in key.split("."):
        if not isinstance(node, dict) or part not in node:
            raise GainTableError(key, None, "this field (missing: truncated or not a gain table?)",
                                 source)
        node = node[part]
    return node


def _array(data: dict, key: str, shape: tuple, source: str) -> np.ndarray:
    raw = _field(data, key, source)
    try:
        arr = np.array(raw, dtype=float)
    except (TypeError, ValueError):
        raise GainTableError(key, _short(raw), f"numbers in an array of shape {shape}", source) from None
    expected = tuple(n if n is not None else arr.shape[i] if i < arr.ndim else -1
                     for i, n in enumerate(shape))
    if arr.shape != expected:
        raise GainTableError(key, f"array of shape {arr.shape}", f"shape {expected}", source)
    if not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0].tolist()
        raise GainTableError(key, f"non-finite value {arr[tuple(bad)]} at index {bad}",
                             "finite numbers only", source)
    return arr


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _number(data: dict, key: str, source: str, *, positive: bool = True) -> float:
    raw = _field(data, key, source)
    if isinstance(raw, bool) or not isinstance(raw, (int, float)) or not math.isfinite(raw) or (
            positive and raw <= 0):
        raise GainTableError(key, raw, "a finite positive number" if positive else "a finite number",
                             source)
    return float(raw)


def load_table(path: str | Path, model: ModelParameters | None = None, *,
               verify: bool = True) -> GainTable:
    """Read and validate a gain table. With ``model``, the table must have been designed for
    exactly these parameters (SHA-256 of the parameters).

    With ``verify`` (the default: a table to run) the file's content must match its SHA-256
    and carry a passed closed-loop check (``require_checked``). Without it the table is read
    as it is, for inspection, and ``intact`` says whether its content matches its hash.
    """
    source = str(path)
    try:
        data = read_yaml(path)
    except ConfigError as exc:
        raise GainTableError("", str(path), exc.expected, "") from None
    version = data.get("format")
    if isinstance(version, str) and version in OLD_FORMATS:
        raise GainTableError("format", version,
                             f"{FORMAT!r}: this table was written by an earlier beamctl and "
                             f"{OLD_FORMATS[version]}; {rebuild_advice(path)}", source)
    if version != FORMAT:
        raise GainTableError("format", version, f"{FORMAT!r} (not a beamctl gain table)", source)

    loads = _array(data, "loads_N", (None,), source)
    if loads.size == 0:
        raise GainTableError("loads_N", [], "at least one grid point", source)
    if np.any(np.diff(loads) <= 0):
        i = int(np.argmax(np.diff(loads) <= 0))
        raise GainTableError("loads_N", f"{loads[i]} then {loads[i + 1]}",
                             "a strictly increasing load grid", source)
    c0_phi_inv = _array(data, "c0_phi_inv", (4, 4), source)
    design, gains = _design(data, len(loads), source)
    compensator = _compensator(data, len(loads), 1.0 / design.sample_rate_hz, source)

    mode = _field(data, "schedule.mode", source)
    if mode not in SCHEDULE_MODES:
        raise GainTableError("schedule.mode", mode, f"one of {SCHEDULE_MODES}", source)
    if mode == "interpolate" and len(loads) < 2:
        raise GainTableError("loads_N", loads.tolist(), "at least two grid points to interpolate",
                             source)
    load_filter = _number(data, "schedule.load_filter_hz", source)
    hysteresis = _number(data, "schedule.hysteresis_N", source, positive=False)
    if hysteresis < 0:
        raise GainTableError("schedule.hysteresis_N", hysteresis, "a non-negative band in N", source)

    raw_params = _field(data, "model.parameters", source)
    try:
        params = parameters_from_dict(raw_params, source=f"{source}: model.parameters")
    except ConfigError as exc:
        raise GainTableError(f"model.parameters.{exc.key}", exc.value, exc.expected, source) from None
    stored_hash = _field(data, "model.sha256", source)
    if stored_hash != params.digest():
        raise GainTableError("model.sha256", stored_hash,
                             f"the SHA-256 of model.parameters ({params.digest()}): the parameters "
                             f"were edited after the gains were designed", source)
    if model is not None and params.digest() != model.digest():
        raise GainTableError("model.sha256", stored_hash,
                             f"the model this service runs with (SHA-256 {model.digest()}): the "
                             f"table was designed for other parameters; regenerate it with "
                             f"`beamctl gains build`", source)

    points = _field(data, "check.points", source)
    checks = []
    if not isinstance(points, list):
        raise GainTableError("check.points", _short(points), "a list of check points", source)
    for i, p in enumerate(points):
        try:
            gain_load = p.get("gain_load_N")
            checks.append(LoopCheck(load_n=float(p["load_N"]), spectral_radius=float(p["spectral_radius"]),
                                    min_damping=float(p["min_damping"]),
                                    gain_load_n=None if gain_load is None else float(gain_load)))
        except (TypeError, KeyError, ValueError, AttributeError):
            raise GainTableError(f"check.points[{i}]", _short(p),
                                 "load_N, spectral_radius and min_damping numbers (and gain_load_N "
                                 "where the gain of a grid point was checked)", source) from None
        if not all(math.isfinite(x) for x in (checks[-1].load_n, checks[-1].spectral_radius)):
            raise GainTableError(f"check.points[{i}]", _short(p), "finite numbers", source)
    forced = _field(data, "check.forced", source)
    if not isinstance(forced, bool):
        raise GainTableError("check.forced", forced, "true or false", source)

    stored = data.get(CONTENT_HASH)
    content = content_sha256(data)
    if verify and stored != content:
        # before the ride-through limits, which are checked against the design's delay: a file
        # changed after it was built is refused as that, whichever field was changed
        found = f"{stored[:16]}..." if isinstance(stored, str) else stored
        raise GainTableError(CONTENT_HASH, found,
                             f"the SHA-256 of the file's content ({content[:16]}...): "
                             f"{changed_file_message(path, design.kind, mode)}", source)
    # a changed file read for inspection: its limits are read as they are (a changed design delay
    # would make the answer budget inconsistent, which the hash has already said)
    ride_through = (_ride_through(data, source, len(loads), design.io.delay_samples,
                                  consistent=stored == content)
                    if "ride_through" in data else None)

    table = GainTable(
        loads_n=loads, compensator=compensator, c0_phi_inv=c0_phi_inv, design=design, gains=gains,
        schedule=ScheduleSettings(mode=mode, load_filter_hz=load_filter, hysteresis_n=hysteresis),
        model_parameters=params, checks=tuple(checks), forced=forced,
        tool_version=str(data.get("tool_version", "")), created=str(data.get("created", "")),
        intact=stored == content, ride_through=ride_through,
        robust=_robust(data, source) if "robust" in data else None)
    if verify:
        require_checked(table, source, rebuild_advice(path, design.kind, mode))
    return table


def _design(data: dict, n_points: int, source: str) -> tuple[DesignSettings, np.ndarray | None]:
    """The ``design`` section, and K [G x 4 x 12] for an integral-lqr design."""
    section = _field(data, "design", source)
    if not isinstance(section, dict):
        raise GainTableError("design", _short(section), "a mapping", source)
    kind = _field(data, "design.kind", source)
    if kind not in DESIGN_KINDS:
        raise GainTableError("design.kind", kind, f"one of {DESIGN_KINDS}", source)
    known = ("kind", "sample_rate_hz", "io") + _DESIGN_FIELDS[kind]
    unknown = sorted(set(section) - set(known))
    if unknown:
        raise GainTableError(f"design.{unknown[0]}", _short(section[unknown[0]]),
                             f"only the fields of a {kind} design: {', '.join(known)}", source)
    sample_rate = _number(data, "design.sample_rate_hz", source)
    raw_io = _field(data, "design.io", source)
    try:
        io = io_chain(raw_io, source, prefix="design.io")
    except ConfigError as exc:
        raise GainTableError(exc.key, exc.value, exc.expected, source) from None
    if kind != "integral-lqr":
        parameters = _field(data, "design.parameters", source)
        if not isinstance(parameters, dict):
            raise GainTableError("design.parameters", _short(parameters),
                                 "a mapping of the design's parameters", source)
        return DesignSettings(kind=kind, sample_rate_hz=sample_rate, io=io, parameters=parameters), None
    cutoff = _number(data, "design.velocity_cutoff_hz", source)
    if cutoff >= sample_rate / 2:
        raise GainTableError("design.velocity_cutoff_hz", cutoff,
                             f"a cut-off below the Nyquist frequency {sample_rate / 2:g} Hz", source)
    q = _array(data, "design.Q_diagonal", (N_STATES,), source)
    r = _array(data, "design.R_diagonal", (N_INPUTS,), source)
    if np.any(q < 0):
        raise GainTableError("design.Q_diagonal", q.tolist(), "non-negative weights", source)
    if np.any(r <= 0):
        raise GainTableError("design.R_diagonal", r.tolist(), "positive weights", source)
    gains = _array(data, "design.gains", (n_points, N_INPUTS, N_STATES), source)
    design = DesignSettings(kind=kind, sample_rate_hz=sample_rate, io=io, velocity_cutoff_hz=cutoff,
                            weights=Weights(q=tuple(q.tolist()), r=tuple(r.tolist())))
    return design, gains


def _compensator(data: dict, n_points: int, period_s: float, source: str) -> Compensator:
    """The ``compensator`` section: every matrix's shape follows from the grid and from the
    number of states n (the rows of ``start``)."""
    start = _array(data, "compensator.start", (None, 4), source)
    n = start.shape[0]
    if n == 0:
        raise GainTableError("compensator.start", [], "at least one compensator state", source)
    shapes = {"a": (n, n), "b": (n, 4), "e": (n, 4), "c": (4, n), "d": (4, 4), "ki": (4, 4)}
    matrices = {m: _array(data, f"compensator.{m}", (n_points, *shapes[m]), source) for m in MATRICES}
    predict = (_array(data, "compensator.predict", (n_points, 4, n), source)
               if "predict" in _field(data, "compensator", source) else None)
    h = _array(data, "compensator.h", (4, 4), source)
    raw = _field(data, "compensator.plane_states", source)
    expected = f"a mapping y: [...], z: [...] that splits the states 0..{n - 1} between the planes"
    if not isinstance(raw, dict) or set(raw) != {"y", "z"} or not all(
            isinstance(v, list) and all(isinstance(i, int) and not isinstance(i, bool) for i in v)
            for v in raw.values()):
        raise GainTableError("compensator.plane_states", _short(raw), expected, source)
    if sorted(raw["y"] + raw["z"]) != list(range(n)):
        raise GainTableError("compensator.plane_states", _short(raw), expected, source)
    return Compensator(**matrices, h=h, start=start, period_s=period_s,
                       plane_states={"y": list(raw["y"]), "z": list(raw["z"])}, predict=predict)


def _robust(data: dict, source: str) -> dict[str, Any]:
    """The ``robust`` section: the robust check's result, its worst ratio a positive number, the
    rigs it evaluated a count, its box a mapping of parameters."""
    section = data["robust"]
    if not isinstance(section, dict):
        raise GainTableError("robust", _short(section), "a mapping: the robust check's result", source)
    ratio = _number(data, "robust.worst_ratio", source)
    evaluated = section.get("evaluated")
    if isinstance(evaluated, bool) or not isinstance(evaluated, int) or evaluated < 1:
        raise GainTableError("robust.evaluated", evaluated, "the number of rigs the check evaluated", source)
    box = section.get("box")
    if not isinstance(box, dict) or not isinstance(box.get("parameters"), dict):
        raise GainTableError("robust.box", _short(box), "the box the check covered (its parameters)", source)
    return {**section, "worst_ratio": ratio}


def _ride_through(data: dict, source: str, n_loads: int, design_delay: float,
                  consistent: bool = True) -> RideThrough | None:
    """The ``ride_through`` section (gains/ridethrough.py): every field present and of its kind,
    the growth one curve per bridge, output and analysed load over the gap grid, and
    (``consistent``) each grid load's answer budget the design's delay plus the tolerated extra
    delay over the margin. A section of an earlier version (``growth_limit``: the relative
    criterion) is not used: None, the engine then uses its fixed limits for a table without an
    analysis (rt/controller.py)."""
    section = data["ride_through"]
    if not isinstance(section, dict):
        raise GainTableError("ride_through", _short(section), "a mapping of the ride-through analysis",
                             source)
    if "growth_limit" in section and "criterion" not in section:
        return None
    unknown = sorted(set(section) - set(RideThrough.FIELDS))
    if unknown:
        raise GainTableError(f"ride_through.{unknown[0]}", _short(section[unknown[0]]),
                             f"only the fields {', '.join(RideThrough.FIELDS)}", source)
    missing = [name for name in RideThrough.FIELDS if name not in section]
    if missing:
        raise GainTableError(f"ride_through.{missing[0]}", None, "this field of the ride-through analysis",
                             source)
    if section["criterion"] != "absolute":
        raise GainTableError("ride_through.criterion", section["criterion"], "'absolute'", source)

    def number(name: str, low: float, open_low: bool = False) -> float:
        value = _number(data, f"ride_through.{name}", source, positive=False)
        if value < low or (open_low and value == low):
            raise GainTableError(f"ride_through.{name}", value,
                                 f"a number {'>' if open_low else '>='} {low:g}", source)
        return value

    def numbers(name: str, raw, length: int | None, what: str, whole: bool = False, low: float = 0.0) -> list:
        count = "" if length is None else f"{length} "
        expected = f"a list of {count}{'whole' if whole else 'finite'} numbers >= {low:g}, {what}"
        if not isinstance(raw, list) or not raw or (length is not None and len(raw) != length):
            found = f"a list of {len(raw)} values" if isinstance(raw, list) else _short(raw)
            raise GainTableError(f"ride_through.{name}", found, expected, source)
        for i, v in enumerate(raw):
            if (isinstance(v, bool) or not isinstance(v, int if whole else (int, float))
                    or not math.isfinite(v) or v < low):
                raise GainTableError(f"ride_through.{name}", f"{v!r} at index {i}", expected, source)
        return raw

    grid = numbers("gap_grid_samples", section["gap_grid_samples"], None, "the gap lengths analysed",
                   whole=True, low=1)
    if any(b <= a for a, b in zip(grid[:-1], grid[1:], strict=True)):
        raise GainTableError("ride_through.gap_grid_samples", _short(grid), "increasing gap lengths", source)
    loads = numbers("loads_N", section["loads_N"], None, "the loads analysed")
    rigs = section["rigs"]
    if not isinstance(rigs, list) or not rigs or not all(isinstance(r, str) and r for r in rigs):
        raise GainTableError("ride_through.rigs", _short(rigs), "a list naming the rigs analysed", source)
    growth = section["growth"]
    if isinstance(growth, dict) and sorted(growth) == [LEGACY_BRIDGE]:
        # a table analysed before the catch-up (gains/ridethrough.py, "Bridges"): the hold's
        # growth, within 7 % of the catch-up's for the deflection on the shipped table, larger
        # for the voltages
        growth = {BRIDGES[0]: growth[LEGACY_BRIDGE]}
    if not isinstance(growth, dict) or sorted(growth) != sorted(BRIDGES):
        raise GainTableError("ride_through.growth", _short(growth), f"a mapping of the bridges {BRIDGES}",
                             source)
    curves = np.zeros((len(BRIDGES), len(OUTPUTS), len(loads), len(grid)))
    for b, bridge in enumerate(BRIDGES):
        part = growth[bridge]
        if not isinstance(part, dict) or sorted(part) != sorted(OUTPUTS):
            raise GainTableError(f"ride_through.growth.{bridge}", _short(part),
                                 f"a mapping of the outputs {OUTPUTS}", source)
        for o, output in enumerate(OUTPUTS):
            name = f"growth.{bridge}.{output}"
            rows = part[output]
            if not isinstance(rows, list) or len(rows) != len(loads):
                found = f"a list of {len(rows)} curves" if isinstance(rows, list) else _short(rows)
                raise GainTableError(f"ride_through.{name}", found,
                                     f"one curve per analysed load ({len(loads)})", source)
            for i, row in enumerate(rows):
                values = numbers(f"{name}[{i}]", row, len(grid), "one growth >= 1 per gap of the grid",
                                 low=1.0)
                if any(later < v for v, later in zip(values[:-1], values[1:], strict=True)):
                    raise GainTableError(f"ride_through.{name}[{i}]", _short(values),
                                         "a growth that does not fall with the gap's length", source)
                curves[b, o, i] = values
    delays = numbers("max_extra_delay_samples_per_load", section["max_extra_delay_samples_per_load"], n_loads,
                     "one per grid load (loads_N)")
    budgets = numbers("answer_budgets_periods", section["answer_budgets_periods"], n_loads,
                      "one per grid load (loads_N)")
    rt = RideThrough(confidence_sigma=number("confidence_sigma", 0.0, open_low=True), gap_grid_samples=grid,
                     loads_n=loads, rigs=rigs, growth=curves, max_extra_delay_samples_per_load=delays,
                     answer_budgets_periods=budgets,
                     delay_step_samples=number("delay_step_samples", 0.0, True),
                     delay_cap_samples=number("delay_cap_samples", 0.0, True),
                     elapsed_s=number("elapsed_s", 0.0))
    if consistent:
        for i, (delay, budget) in enumerate(zip(delays, budgets, strict=True)):
            expected = answer_budget(design_delay, delay)
            if not math.isclose(budget, expected, rel_tol=1e-12, abs_tol=1e-15):
                raise GainTableError("ride_through.answer_budgets_periods", f"{budget!r} at index {i}",
                                     f"the design's delay {design_delay:g} + "
                                     "max_extra_delay_samples_per_load "
                                     f"/ {DELAY_MARGIN:g} = {expected:g}", source)
    return rt
