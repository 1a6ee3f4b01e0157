"""Gain table files: one YAML file per table, written by ``beamctl gains build`` and read by
the real-time service.

The file holds the load grid, K per grid point, (C0 Phi)^-1, the sample rate and velocity
filter the gains were designed for, Q and R, the schedule settings, the model parameters
with their SHA-256, the closed-loop check, the tool version and the creation time, and a
SHA-256 over all of it. Loading checks every field; anything wrong is refused with a
GainTableError naming the field. Numbers are written in Python's shortest round-trip form,
so a table reads back bit for bit and its content hash is reproducible.

A table the controller may run has a content hash that matches, a closed-loop check, and
no unstable point in it (nor ``--force``): ``load_table`` refuses anything else unless
asked only to read it (``verify=False``, for ``beamctl gains check`` and ``show``).
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
from beamctl.gains.discrete import LoopCheck
from beamctl.gains.lqr import N_INPUTS, N_STATES, Weights
from beamctl.models.params import ModelParameters, parameters_from_dict

FORMAT = "beamctl-gain-table/2"
# earlier formats, refused with the reason and what to run
OLD_FORMATS = {"beamctl-gain-table/1": "carries no SHA-256 of its content"}
CONTENT_HASH = "sha256"
SCHEDULE_MODES = ("interpolate", "paper")


class GainTableError(ConfigError):
    """A gain table file was refused; ``key`` names the field."""


def content_sha256(data: Mapping[str, Any]) -> str:
    """SHA-256 of a table file's content: the canonical JSON (sorted keys, no spaces, numbers
    in shortest round-trip form) of every field but the ``sha256`` field itself."""
    content = {k: v for k, v in data.items() if k != CONTENT_HASH}
    canonical = json.dumps(content, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(canonical.encode()).hexdigest()


def rebuild_advice(path: str | Path) -> str:
    """What to run to replace a table file that cannot be used."""
    return (f"rebuild it with `beamctl gains build --out {path}` (with `--config` for a model other "
            f"than the paper's) and check it with `beamctl gains check {path}`")


def changed_file_message(path: str | Path) -> str:
    """Why a table whose content does not match its SHA-256 is refused, and what to run."""
    return f"the file was changed after it was built; {rebuild_advice(path)}"


@dataclass(frozen=True)
class DesignSettings:
    """What the gains were designed for."""

    sample_rate_hz: float
    velocity_cutoff_hz: float
    weights: Weights


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
    loads_n: np.ndarray            # [G], strictly increasing
    gains: np.ndarray              # [G x 4 x 12]
    c0_phi_inv: np.ndarray         # [4 x 4]
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

    @property
    def model_sha256(self) -> str:
        return self.model_parameters.digest()

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
        w = self.design.weights
        return {
            "format": FORMAT,
            "created": self.created,
            "tool_version": self.tool_version,
            "model": {"sha256": self.model_sha256, "parameters": self.model_parameters.to_dict()},
            "design": {
                "sample_rate_hz": self.design.sample_rate_hz,
                "velocity_cutoff_hz": self.design.velocity_cutoff_hz,
                "Q_diagonal": [float(x) for x in w.q],
                "R_diagonal": [float(x) for x in w.r],
            },
            "schedule": {"mode": self.schedule.mode, "load_filter_hz": self.schedule.load_filter_hz,
                         "hysteresis_N": self.schedule.hysteresis_n},
            "c0_phi_inv": self.c0_phi_inv.tolist(),
            "loads_N": [float(x) for x in self.loads_n],
            "gains": [k.tolist() for k in self.gains],
            "check": {
                "all_stable": self.all_stable,
                "forced": self.forced,
                "points": [_check_point(c) for c in self.checks],
            },
        }


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
                             f"changed after it was built; {rebuild_advice(path)}")
    if table.checked and not table.all_stable and not table.forced:
        unstable = [c.load_n for c in table.checks if not c.stable]
        raise GainTableError("check.all_stable", False,
                             f"a stable closed loop at every check point; unstable at {unstable} N "
                             f"(build with --force to write it anyway, marked as forced)")
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    header = ("# beamctl gain table: integral LQR gains K(Fx) [4 x 12] per axial load.\n"
              "# Written by `beamctl gains build`; checked on load. Do not edit by hand: the\n"
              "# SHA-256 of the content would no longer match and `beamctl run` refuses it.\n")
    p.write_text(header + yaml.safe_dump(table.to_dict(), sort_keys=False, width=120))
    return p


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
    gains = _array(data, "gains", (len(loads), N_INPUTS, N_STATES), source)
    c0_phi_inv = _array(data, "c0_phi_inv", (4, 4), source)

    sample_rate = _number(data, "design.sample_rate_hz", source)
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
    table = GainTable(
        loads_n=loads, gains=gains, c0_phi_inv=c0_phi_inv,
        design=DesignSettings(sample_rate_hz=sample_rate, velocity_cutoff_hz=cutoff,
                              weights=Weights(q=tuple(q.tolist()), r=tuple(r.tolist()))),
        schedule=ScheduleSettings(mode=mode, load_filter_hz=load_filter, hysteresis_n=hysteresis),
        model_parameters=params, checks=tuple(checks), forced=forced,
        tool_version=str(data.get("tool_version", "")), created=str(data.get("created", "")),
        intact=stored == content)
    if verify:
        if not table.intact:
            found = f"{stored[:16]}..." if isinstance(stored, str) else stored
            raise GainTableError(CONTENT_HASH, found,
                                 f"the SHA-256 of the file's content ({content[:16]}...): "
                                 f"{changed_file_message(path)}", source)
        require_checked(table, source, rebuild_advice(path))
    return table
