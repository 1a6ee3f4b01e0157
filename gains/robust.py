"""The robust check: how far a gain table holds every rig of an uncertainty box.

A rig of the box differs from the design model in its parameters (any numeric model key,
e.g. ``beam.youngs_modulus``), its stack force per volt (``actuators.force_constant_n_per_v``), its
output delay (``io.delay_samples``) and its sample rate (``sample_rate_hz``). For each rig
(scenario) the check finds the largest load L such that the discrete closed loop (the rig's
full FE plane, its I/O chain, and exactly the compensator the control step runs, via the
schedule) is stable at every check load from 0 to L: the table's grid loads and midpoints,
subdivided to steps of at most ``max_step_n``, and steps of ``fine_step_n`` within
``fine_band`` of the rig's own critical load. It reports L / own Fx,cr and the pole that
limits it.

Scenarios: each box parameter alone at both ends (the screen), the 2^k corners of the k
parameters that did the most harm in the screen (the others nominal), and ``random`` draws
inside the whole box (seeded). The work is spread over processes, one BLAS thread each.
"""

from __future__ import annotations

import itertools
import math
import os
import signal
from collections.abc import Callable, Mapping
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context
from typing import Any

import numpy as np

from beamctl.config.schema import ConfigError, read_yaml
from beamctl.gains.discrete import pole_summary
from beamctl.gains.rig import RigPlane
from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import GainTable
from beamctl.models.fe import build_model
from beamctl.models.iochain import IOChain
from beamctl.models.params import ModelParameters, parameters_from_dict

Progress = Callable[[int, int, str], None]
KINDS = ("factor", "offset", "value")
SPECIAL_KEYS = ("io.delay_samples", "actuators.force_constant_n_per_v", "sample_rate_hz")


@dataclass(frozen=True)
class Range:
    """How a box parameter varies: ``factor`` multiplies the nominal value, ``offset`` adds to
    it (SI units), ``value`` replaces it."""

    kind: str
    low: float
    high: float

    def nominal(self) -> float:
        return 1.0 if self.kind == "factor" else 0.0 if self.kind == "offset" else self.low

    def to_dict(self) -> dict[str, list[float]]:
        return {self.kind: [self.low, self.high]}


@dataclass(frozen=True)
class Box:
    """The uncertainty box and how it is sampled."""

    parameters: dict[str, Range]
    corner_parameters: int | tuple[str, ...] = 5
    random: int = 24
    seed: int = 1
    max_step_n: float = 50.0
    fine_step_n: float = 10.0
    fine_band: float = 0.04

    def to_dict(self) -> dict[str, Any]:
        corners = (self.corner_parameters if isinstance(self.corner_parameters, int)
                   else list(self.corner_parameters))
        return {"parameters": {k: r.to_dict() for k, r in self.parameters.items()}, "corners": corners,
                "random": self.random, "seed": self.seed, "max_step_N": self.max_step_n,
                "fine_step_N": self.fine_step_n, "fine_band": self.fine_band}


DEFAULT_BOX = Box(parameters={
    "beam.youngs_modulus": Range("factor", 0.95, 1.05),
    "supports.rotational_stiffness": Range("factor", 0.8, 1.2),
    "supports.lateral_stiffness": Range("factor", 0.8, 1.2),
    "supports.actuator_stiffness": Range("factor", 0.8, 1.2),
    "damping.ratios": Range("factor", 0.5, 2.0),
    "actuators.force_constant_n_per_v": Range("factor", 0.8, 1.2),
    "io.delay_samples": Range("value", 0.0, 1.0),
    "sensors.strain_gauge_positions[0]": Range("offset", -1e-3, 1e-3),
    "sensors.strain_gauge_positions[1]": Range("offset", -1e-3, 1e-3),
    "sample_rate_hz": Range("factor", 0.99, 1.01),
})


# -------------------------------------------------------------------------------------------
# reading a box file


def _model_key(params: Mapping[str, Any], key: str) -> bool:
    """Whether ``key`` (``a.b`` or ``a.b[i]``) names a number of the model parameters."""
    base, _, index = key.partition("[")
    node: Any = params
    for part in base.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return False
        node = node[part]
    if index:
        if not index.endswith("]") or not index[:-1].isdigit() or not isinstance(node, list):
            return False
        i = int(index[:-1])
        return i < len(node) and isinstance(node[i], (int, float))
    return isinstance(node, (int, float)) and not isinstance(node, bool) or (
        isinstance(node, list) and all(isinstance(x, (int, float)) for x in node))


def box_from_dict(data: Any, params: ModelParameters, source: str = "") -> Box:
    """Validate a box mapping (the ``box:`` section of a file)."""
    if not isinstance(data, Mapping):
        raise ConfigError("box", data, "a mapping with parameters (and corners, random, seed)", source)
    known = {"parameters", "corners", "random", "seed", "max_step_N", "fine_step_N", "fine_band"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ConfigError(f"box.{unknown[0]}", data[unknown[0]], f"one of the known keys {sorted(known)}",
                          source)
    raw = data.get("parameters")
    if not isinstance(raw, Mapping) or not raw:
        raise ConfigError("box.parameters", raw, "a mapping of parameter keys to ranges, e.g. "
                          "'beam.youngs_modulus: {factor: [0.95, 1.05]}'", source)
    model = params.to_dict()
    ranges: dict[str, Range] = {}
    for key, spec in raw.items():
        where = f"box.parameters.{key}"
        if key not in SPECIAL_KEYS and not _model_key(model, str(key)):
            raise ConfigError(where, spec, f"a numeric model parameter (e.g. beam.youngs_modulus, "
                              f"sensors.strain_gauge_positions[0]) or one of {', '.join(SPECIAL_KEYS)}",
                              source)
        if not isinstance(spec, Mapping) or len(spec) != 1 or next(iter(spec)) not in KINDS:
            raise ConfigError(where, spec, f"one of {{{', '.join(k + ': [low, high]' for k in KINDS)}}}",
                              source)
        kind, bounds = next(iter(spec.items()))
        ok = (isinstance(bounds, list) and len(bounds) == 2 and all(
            isinstance(b, (int, float)) and not isinstance(b, bool) and math.isfinite(b) for b in bounds)
            and bounds[0] <= bounds[1])
        if not ok:
            raise ConfigError(f"{where}.{kind}", bounds, "[low, high], two finite numbers, low <= high",
                              source)
        low, high = float(bounds[0]), float(bounds[1])
        if kind == "factor" and low <= 0:
            raise ConfigError(f"{where}.{kind}", bounds, "factors > 0", source)
        if key in ("actuators.force_constant_n_per_v", "sample_rate_hz") and kind != "factor":
            raise ConfigError(where, spec, "{factor: [low, high]} (relative to the design's value)", source)
        if key == "io.delay_samples" and low < 0:
            raise ConfigError(f"{where}.{kind}", bounds, "delays >= 0 samples", source)
        ranges[str(key)] = Range(kind, low, high)
    corners = data.get("corners", 5)
    if isinstance(corners, bool) or not (isinstance(corners, int) and 0 <= corners <= 8 or (
            isinstance(corners, list) and all(c in ranges for c in corners) and len(corners) <= 8)):
        raise ConfigError("box.corners", corners, "a number of parameters 0..8 (the most harmful in the "
                          "screen) or a list of at most 8 keys of box.parameters", source)
    numbers = {}
    for key, default, low in (("random", 24, 0), ("seed", 1, 0)):
        value = data.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ConfigError(f"box.{key}", value, f"an integer >= {low}", source)
        numbers[key] = value
    steps = {}
    for key, default in (("max_step_N", 50.0), ("fine_step_N", 10.0), ("fine_band", 0.04)):
        value = data.get(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= (
                50.0 if key == "max_step_N" else 1e9):
            raise ConfigError(f"box.{key}", value, "a number > 0" + (" and <= 50 (N)" if key == "max_step_N"
                                                                       else ""), source)
        steps[key] = float(value)
    return Box(parameters=ranges, corner_parameters=corners if isinstance(corners, int) else tuple(corners),
               random=numbers["random"], seed=numbers["seed"], max_step_n=steps["max_step_N"],
               fine_step_n=steps["fine_step_N"], fine_band=steps["fine_band"])


def load_box(path: str, params: ModelParameters) -> Box:
    data = read_yaml(path)
    if set(data) != {"box"}:
        raise ConfigError("box", sorted(data), "a file with one top-level key, box", str(path))
    return box_from_dict(data["box"], params, str(path))


# -------------------------------------------------------------------------------------------
# one scenario


@dataclass(frozen=True)
class Limit:
    """The least stable pole where the check stopped (or, if it never did, at the end)."""

    load_n: float
    spectral_radius: float
    frequency_hz: float
    min_damping: float


@dataclass(frozen=True)
class ScenarioResult:
    name: str
    parameters: dict[str, float]
    held_load_n: float | None           # None: unstable already at 0 N
    critical_load_n: float
    ratio: float
    limit: Limit
    points: int

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "parameters": self.parameters, "held_load_N": self.held_load_n,
                "critical_load_N": self.critical_load_n, "ratio": self.ratio,
                "limit": {"load_N": self.limit.load_n, "spectral_radius": self.limit.spectral_radius,
                          "frequency_hz": self.limit.frequency_hz, "min_damping": self.limit.min_damping},
                "points": self.points}


def _set(node: dict, key: str, rng: Range, value: float) -> None:
    base, _, index = key.partition("[")
    parts = base.split(".")
    for part in parts[:-1]:
        node = node[part]
    leaf = parts[-1]

    def new(old: float) -> float:
        return old * value if rng.kind == "factor" else old + value if rng.kind == "offset" else value

    if index:
        i = int(index[:-1])
        node[leaf][i] = new(node[leaf][i])
    elif isinstance(node[leaf], list):
        node[leaf] = [new(x) for x in node[leaf]]
    else:
        node[leaf] = new(node[leaf])


@dataclass(frozen=True)
class Rig:
    """A rig of the box: its model parameters, I/O chain, sample rate and force gain."""

    params: ModelParameters
    chain: IOChain
    sample_rate_hz: float
    force_gain: float


def rig_of(table: GainTable, box: Box, values: Mapping[str, float]) -> Rig:
    """The rig that ``values`` (box key -> factor/offset/value) describe, around the table's
    design model and declared I/O chain."""
    model = table.model_parameters.to_dict()
    chain = table.design.io
    rate = table.design.sample_rate_hz
    gain = 1.0
    delay = chain.delay_samples
    for key, value in values.items():
        rng = box.parameters[key]
        if key == "io.delay_samples":
            delay = value if rng.kind == "value" else delay * value if rng.kind == "factor" else delay + value
        elif key == "actuators.force_constant_n_per_v":
            gain = value                    # a factor (checked when the box is read)
        elif key == "sample_rate_hz":
            rate = rate * value
        else:
            _set(model, key, rng, value)
    params = parameters_from_dict(model, source="robust check rig")
    return Rig(params=params, chain=IOChain(delay_samples=max(delay, 0.0), anti_alias=chain.anti_alias,
                                            reconstruction=chain.reconstruction),
               sample_rate_hz=rate, force_gain=gain)


def check_loads(table_loads: np.ndarray, critical_n: float, box: Box) -> np.ndarray:
    """The loads a scenario is checked at (ascending): grid loads and midpoints, gaps split to
    at most ``max_step_n``, and ``fine_step_n`` steps within ``fine_band`` of Fx,cr."""
    loads = np.asarray(table_loads, dtype=float)
    points = set(loads.tolist()) | set(((loads[:-1] + loads[1:]) / 2).tolist())
    ordered = sorted(points)
    full: list[float] = []
    for a, b in zip(ordered[:-1], ordered[1:], strict=True):
        pieces = max(1, math.ceil((b - a) / box.max_step_n - 1e-9))
        full.extend(a + (b - a) * np.arange(pieces) / pieces)
    full.append(ordered[-1])
    low, high = critical_n * (1 - box.fine_band), critical_n * (1 + box.fine_band)
    fine = np.arange(math.ceil(low / box.fine_step_n) * box.fine_step_n, high, box.fine_step_n)
    fine = fine[(fine >= loads[0]) & (fine <= loads[-1])]
    return np.unique(np.round(np.concatenate([full, fine]), 9))


def evaluate(table: GainTable, schedule: GainSchedule, box: Box, name: str,
             values: Mapping[str, float]) -> ScenarioResult:
    """Walk up the check loads of one scenario until the loop is unstable."""
    rig = rig_of(table, box, values)
    comp = table.compensator
    plane = RigPlane(build_model(rig.params), rig.chain, rig.sample_rate_hz, rig.force_gain)
    critical = plane.critical_load_n
    held = None
    worst = None
    loads = check_loads(table.loads_n, critical, box)
    count = 0
    for load in loads:
        m = plane.loop_matrix(load, schedule.matrices_at(load), comp.h, comp.plane_states["y"], comp.period_s)
        poles = np.linalg.eigvals(m)
        count += 1
        radius, damping = pole_summary(poles, rig.sample_rate_hz)
        z = poles[int(np.argmax(np.abs(poles)))]
        here = Limit(load_n=float(load), spectral_radius=radius,
                     frequency_hz=abs(float(np.angle(z))) * rig.sample_rate_hz / (2 * math.pi),
                     min_damping=damping)
        if radius >= 1.0:
            worst = here
            break
        held = float(load)
        if worst is None or radius > worst.spectral_radius:
            worst = here
    ratio = (held or 0.0) / critical
    return ScenarioResult(name=name, parameters={k: float(v) for k, v in values.items()}, held_load_n=held,
                          critical_load_n=critical, ratio=ratio, limit=worst, points=count)


# -------------------------------------------------------------------------------------------
# the scenarios and the parallel run

_WORKER: dict[str, Any] = {}


def _init_worker(table: GainTable, box: Box) -> None:
    # a worker process of this check: Ctrl-C at the terminal is the caller's to handle (the
    # pool is shut down from there), not a traceback from every worker
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:        # one BLAS thread per process: the processes share the cores
        from threadpoolctl import threadpool_limits
        _WORKER["limits"] = threadpool_limits(1)
    except ImportError:     # pragma: no cover - threadpoolctl is a dependency
        pass
    _WORKER["table"] = table
    _WORKER["box"] = box
    _WORKER["schedule"] = GainSchedule.from_table(table)


def _run(job: tuple[str, dict[str, float]]) -> ScenarioResult:
    name, values = job
    return evaluate(_WORKER["table"], _WORKER["schedule"], _WORKER["box"], name, values)


@dataclass
class RobustResult:
    box: Box
    scenarios: list[ScenarioResult] = field(default_factory=list)
    corner_parameters: tuple[str, ...] = ()

    @property
    def worst(self) -> ScenarioResult:
        return min(self.scenarios, key=lambda s: s.ratio)

    @property
    def worst_ratio(self) -> float:
        return self.worst.ratio

    def to_dict(self) -> dict[str, Any]:
        return {"robust": {"worst_ratio": self.worst_ratio, "worst_scenario": self.worst.to_dict(),
                           "corner_parameters": list(self.corner_parameters), "box": self.box.to_dict(),
                           "scenarios": [s.to_dict() for s in self.scenarios]}}


def _random_jobs(box: Box) -> list[tuple[str, dict[str, float]]]:
    rng = np.random.default_rng(box.seed)
    jobs = []
    keys = list(box.parameters)
    for i in range(box.random):
        draw = rng.uniform(size=len(keys))
        values = {k: box.parameters[k].low + u * (box.parameters[k].high - box.parameters[k].low)
                  for k, u in zip(keys, draw, strict=True)}
        jobs.append((f"random {i + 1}", values))
    return jobs


def robust_check(table: GainTable, box: Box = DEFAULT_BOX, *, workers: int | None = None,
                 progress: Progress | None = None) -> RobustResult:
    """Run the robust check of ``table`` over ``box`` (see the module docstring)."""
    workers = workers or min(2, os.cpu_count() or 1)
    keys = list(box.parameters)
    screen = [("nominal", {})] + [(f"{k} {end}", {k: getattr(box.parameters[k], end)})
                                   for k in keys for end in ("low", "high")
                                   if getattr(box.parameters[k], end) != box.parameters[k].nominal()]
    randoms = _random_jobs(box)
    n_corners = (2 ** box.corner_parameters if isinstance(box.corner_parameters, int)
                 else 2 ** len(box.corner_parameters))
    total = len(screen) + n_corners + len(randoms)
    result = RobustResult(box=box)
    done = 0

    def collect(jobs, pool) -> list[ScenarioResult]:
        nonlocal done
        out = []
        for r in pool.map(_run, jobs):
            out.append(r)
            done += 1
            if progress:
                progress(done, total, f"{r.name[:28]}: {r.ratio:.3f}")
        return out

    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"), initializer=_init_worker,
                             initargs=(table, box)) as pool:
        screened = collect(screen, pool)
        result.scenarios.extend(screened)
        if isinstance(box.corner_parameters, int):
            harm: dict[str, float] = {}
            for r in screened[1:]:
                for k in r.parameters:
                    harm[k] = min(harm.get(k, math.inf), r.ratio)
            chosen = tuple(sorted(harm, key=lambda k: harm[k])[:box.corner_parameters])
        else:
            chosen = tuple(box.corner_parameters)
        result.corner_parameters = chosen
        corners = [(f"corner {i + 1}",
                     {k: getattr(box.parameters[k], end) for k, end in zip(chosen, ends, strict=True)})
                   for i, ends in enumerate(itertools.product(("low", "high"), repeat=len(chosen)))]
        total = len(screen) + len(corners) + len(randoms)
        result.scenarios.extend(collect(corners + randoms, pool))
    return result
