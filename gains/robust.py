"""The robust check: the worst rig of an uncertainty box, found by searching it.

A rig of the box differs from the design model in its parameters (any numeric model key,
e.g. ``beam.youngs_modulus``), its stack force per volt (``actuators.force_constant_n_per_v``), its
output delay (``io.delay_samples``) and its sample rate (``sample_rate_hz``), every one of them
continuous within its range. For a rig, the **instability onset** is the lowest axial load at
which the discrete closed loop (the rig's full FE plane, its I/O chain, and exactly the
compensator the control step runs, via the schedule) is unstable; its **onset ratio** is the
onset divided by the rig's own critical load Fx,cr. A rig stable to the end of the table is
censored: its ratio (end / Fx,cr) is a lower bound.

The check minimises the onset ratio over the whole box:

1. a global search: seeded differential evolution (scipy) from a Latin hypercube, every rig
   walked up from the table's first load (in steps of ``search_step_n``, four times that below
   half the rig's own Fx,cr) and the first unstable step bisected to ``resolution_n``;
2. for each way of failing (the band of the unstable pole's frequency, BAND_NAMES), a climb of
   that band's growth rate at the worst ratio so far (one load a rig, cheap): a way of failing
   that another hides, because the other comes first nearly everywhere, has its own worst rigs;
   a rig found unstable there is walked;
3. a local refinement of the onset: a compass search (each parameter up and down by a step
   that halves when no neighbour is worse) from each of the worst distinct rigs (one per way of
   failing first), the neighbours evaluated in parallel;
4. verification of the ``verify`` worst distinct rigs found: walked from the first load at every
   grid load and midpoint in steps of at most ``max_step_n`` (``fine_step_n`` within
   ``fine_band`` of the rig's own Fx,cr), the first unstable step bisected to ``resolution_n``.

Parameters that do no harm alone (damping, stack gain, gauge placement, a delay inside the
sample) can combine into the worst rig: the search varies all of them together. It is
deterministic for a seed whatever evaluates the rigs: worker processes here, or a Dask cluster.
A search is not a proof: its coarse walks assume a loop that, going up the loads, becomes
unstable once (a window of instability narrower than a step is seen only by the verification's
fine walk), and ~2000 rigs sample a 10-parameter box.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import signal
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass, field
from multiprocessing import get_context
from typing import Any

import numpy as np

from beamctl.common.workers import WorkerDied
from beamctl.config.schema import ConfigError, dotted_get, read_yaml, refuse_renamed
from beamctl.gains.rig import RigPlane
from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import GainTable
from beamctl.models.fe import build_model
from beamctl.models.params import ModelParameters
from beamctl.models.rig import KINDS, SPECIAL_KEYS, Rig, rig_with

Progress = Callable[[int, int, str], None]
MODES = ("search", "full", "margin")


@dataclass(frozen=True)
class Range:
    """How a box parameter varies: ``factor`` multiplies the nominal value, ``offset`` adds to
    it (SI units), ``value`` replaces it."""

    kind: str
    low: float
    high: float

    def nominal(self) -> float:
        return 1.0 if self.kind == "factor" else 0.0 if self.kind == "offset" else self.low

    def at(self, u: float) -> float:
        """The value at the fraction ``u`` (0..1) of the range."""
        return self.low + u * (self.high - self.low)

    def to_dict(self) -> dict[str, list[float]]:
        return {self.kind: [self.low, self.high]}


@dataclass(frozen=True)
class Box:
    """The uncertainty box and how the search covers it (see the module docstring)."""

    parameters: dict[str, Range]
    seed: int = 1
    population: int = 40          # rigs per generation of the global search
    generations: int = 14         # generations after the first
    margin: int = 800             # rigs whose growth rates the climbs may evaluate (one load each)
    refine: int = 400             # rigs the local refinements may evaluate, together
    starts: int = 4               # local refinements at most: one per way of failing (BAND_NAMES)
    strategy: str = "rand1bin"    # scipy's differential evolution strategy
    verify: int = 4               # worst distinct rigs walked again at the fine steps
    search_step_n: float = 200.0
    resolution_n: float = 1.0
    max_step_n: float = 50.0
    fine_step_n: float = 10.0
    fine_band: float = 0.04

    @property
    def budget(self) -> int:
        """Rigs the search evaluates at most (the global part, the refinement, the verification)."""
        return (self.population * (self.generations + 1) + self.margin + len(BAND_NAMES) + self.refine
                + self.verify)

    def values(self, u: Sequence[float]) -> dict[str, float]:
        """The rig at the point ``u`` of the unit cube (one coordinate per parameter)."""
        return {k: r.at(float(x)) for (k, r), x in zip(self.parameters.items(), u, strict=True)}

    def to_dict(self) -> dict[str, Any]:
        return {"parameters": {k: r.to_dict() for k, r in self.parameters.items()}, "seed": self.seed,
                "population": self.population, "generations": self.generations, "margin": self.margin,
                "refine": self.refine,
                "starts": self.starts, "strategy": self.strategy, "verify": self.verify,
                "search_step_n": self.search_step_n,
                "resolution_n": self.resolution_n, "max_step_n": self.max_step_n,
                "fine_step_n": self.fine_step_n, "fine_band": self.fine_band}


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


# the search's settings in a box file: key -> (default, lowest, highest)
_INTEGERS = {"seed": (1, 0, 2**32 - 1), "population": (40, 5, 10_000), "generations": (14, 0, 10_000),
             "margin": (800, 0, 100_000), "refine": (400, 0, 100_000), "starts": (4, 1, 100),
             "verify": (4, 1, 100)}
STRATEGIES = ("rand1bin", "best1bin", "randtobest1bin", "currenttobest1bin", "best2bin", "rand2bin")
_LOADS = {"search_step_n": (200.0, 1.0, 500.0), "resolution_n": (1.0, 0.01, 50.0),
          "max_step_n": (50.0, 1.0, 50.0), "fine_step_n": (10.0, 0.01, 1e9), "fine_band": (0.04, 0.0, 1.0)}
# the loads' keys as box files spelled them before they were written as the study file's are
_RENAMED = {f"{key[:-2]}_N": key for key in _LOADS if key.endswith("_n")}


def box_from_dict(data: Any, params: ModelParameters, source: str = "") -> Box:
    """Validate a box mapping (the ``box:`` section of a file)."""
    if not isinstance(data, Mapping):
        raise ConfigError("box", data, "a mapping with parameters (and the search's settings)", source)
    refuse_renamed(data, _RENAMED, source, "box.")
    known = {"parameters", "strategy", *_INTEGERS, *_LOADS}
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
    settings: dict[str, Any] = {}
    for key, (default, low, high) in _INTEGERS.items():
        value = data.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise ConfigError(f"box.{key}", value, f"an integer from {low} to {high}", source)
        settings[key] = value
    for key, (default, low, high) in _LOADS.items():
        value = data.get(key, default)
        unit = "" if key == "fine_band" else " (N)"
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not low < value <= high:
            raise ConfigError(f"box.{key}", value, f"a number > {low:g} and <= {high:g}{unit}", source)
        settings[key] = float(value)
    strategy = data.get("strategy", "rand1bin")
    if strategy not in STRATEGIES:
        raise ConfigError("box.strategy", strategy, f"one of {', '.join(STRATEGIES)} (scipy's differential "
                          "evolution)", source)
    return Box(parameters=ranges, seed=settings["seed"], population=settings["population"],
               generations=settings["generations"], margin=settings["margin"], refine=settings["refine"],
               starts=settings["starts"],
               strategy=strategy, verify=settings["verify"], search_step_n=settings["search_step_n"],
               resolution_n=settings["resolution_n"], max_step_n=settings["max_step_n"],
               fine_step_n=settings["fine_step_n"], fine_band=settings["fine_band"])


def load_box(path: str, params: ModelParameters) -> Box:
    data = read_yaml(path)
    if set(data) != {"box"}:
        raise ConfigError("box", sorted(data), "a file with one top-level key, box", str(path))
    return box_from_dict(data["box"], params, str(path))


# -------------------------------------------------------------------------------------------
# one rig


def rig_of(table: GainTable, box: Box, values: Mapping[str, float]) -> Rig:
    """The rig that ``values`` (box key -> factor/offset/value) describe, around the table's
    design model and declared I/O chain (models/rig.py)."""
    return rig_with(table.model_parameters, table.design.io, table.design.sample_rate_hz,
                    {key: (box.parameters[key].kind, value) for key, value in values.items()},
                    source="robust check rig")


def check_loads(table_loads: np.ndarray, critical_n: float, box: Box) -> np.ndarray:
    """The loads of the full walk (ascending): grid loads and midpoints, gaps split to at most
    ``max_step_n``, and ``fine_step_n`` steps within ``fine_band`` of Fx,cr."""
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


def search_loads(table_loads: np.ndarray, critical_n: float, step_n: float) -> np.ndarray:
    """The loads of the search's walk: the table's first load to its last, in steps of 4
    ``step_n`` below half the rig's own Fx,cr and of ``step_n`` above it."""
    first, last = float(table_loads[0]), float(table_loads[-1])
    half = min(max(first, 0.5 * critical_n), last)
    low = np.arange(first, half, 4 * step_n)
    count = max(1, math.ceil((last - half) / step_n - 1e-9))
    return np.concatenate([low, half + (last - half) * np.arange(count + 1) / count])


# The ways a loop fails, told apart by the frequency of its unstable pole (Hz): the slow mode 1
# (below 30 Hz), the closed-loop modes 1 and 2 (30-300 Hz), mode 3 and high modes folded by the
# sampling (300-1300 Hz), mode 4, mode 5 and mode 6 folded (above 1300 Hz).
BAND_EDGES_HZ = (30.0, 300.0, 1300.0)
BAND_NAMES = ("below 30 Hz", "30-300 Hz", "300-1300 Hz", "above 1300 Hz")


@dataclass(frozen=True)
class Onset:
    """Where one rig's closed loop becomes unstable.

    ``onset_n``: the lowest load found unstable (None: stable to the end of the table, a
    censored rig); ``stable_to_n``: the load below it known stable, within the resolution (None
    when the first load is already unstable); ``ratio``: onset / own Fx,cr, or, censored, end /
    Fx,cr (a lower bound); ``pole_hz`` and ``spectral_radius``: the pole of largest magnitude at
    the onset (censored: the largest over the walk); ``points``: loads analysed. The search's walk
    also keeps, per load walked before the onset, the growth rate (1/s, ln|z| times the sample
    rate: < 0 stable) of the least stable pole in each band of BAND_NAMES (``walk_loads_n``,
    ``walk_growth``)."""

    values: dict[str, float]
    critical_load_n: float
    onset_n: float | None
    stable_to_n: float | None
    ratio: float
    pole_hz: float
    spectral_radius: float
    points: int
    mode: str = "full"
    walk_loads_n: tuple[float, ...] = ()
    walk_growth: tuple[tuple[float, ...], ...] = ()

    @property
    def censored(self) -> bool:
        return self.onset_n is None

    def growth_at(self, ratio: float) -> np.ndarray:
        """Per band, the growth rate at ``ratio`` x own Fx,cr, linear between the walk's loads
        (-inf where the walk holds nothing near)."""
        load = ratio * self.critical_load_n
        loads = np.asarray(self.walk_loads_n)
        if loads.size < 2 or not loads[0] <= load <= loads[-1]:
            return np.full(len(BAND_NAMES), -np.inf)
        growth = np.asarray(self.walk_growth)
        return np.array([np.interp(load, loads, growth[:, b]) for b in range(len(BAND_NAMES))])

    def to_dict(self) -> dict[str, Any]:
        return {"rig": dict(self.values), "onset_N": self.onset_n, "stable_to_N": self.stable_to_n,
                "critical_load_N": self.critical_load_n, "ratio": self.ratio, "censored": self.censored,
                "pole_hz": self.pole_hz, "spectral_radius": self.spectral_radius, "points": self.points,
                "walk": self.mode}


@dataclass(frozen=True)
class Refused:
    """A rig of the box that the model refuses to build (``reason``: the refusal, e.g. damping
    ratios that give a negative Rayleigh coefficient): no rig at all, so the box that holds it is
    partly invalid. Counted and named by the search, never evaluated."""

    values: dict[str, float]
    reason: str

    def to_dict(self) -> dict[str, Any]:
        return {"rig": dict(self.values), "refused": self.reason}


@dataclass(frozen=True)
class Margin:
    """The growth rate (1/s) of the least stable pole of each band of BAND_NAMES of one rig's loop
    at ``load_n`` (a fraction of its own Fx,cr): > 0 is unstable there."""

    values: dict[str, float]
    critical_load_n: float
    load_n: float
    growth: tuple[float, ...]


class _Loop:
    """The poles of one rig's closed loop at any load, summarised per band."""

    def __init__(self, plane: RigPlane, table: GainTable, schedule: GainSchedule) -> None:
        self.plane, self.table, self.schedule = plane, table, schedule
        self.points = 0

    def at(self, load: float) -> tuple[float, float, np.ndarray]:
        """(|z|, Hz) of the pole of largest magnitude, and per band the growth rate (1/s) of its
        least stable pole (-inf where a band has no pole)."""
        comp = self.table.compensator
        m = self.plane.loop_matrix(load, self.schedule.matrices_at(load), comp.h,
                                   comp.plane_states[self.plane.plane], comp.period_s)
        poles = np.linalg.eigvals(m)
        self.points += 1
        radius = np.abs(poles)
        hz = np.abs(np.angle(poles)) * self.plane.sample_rate_hz / (2 * math.pi)
        bands = np.searchsorted(BAND_EDGES_HZ, hz, side="right")
        growth = np.full(len(BAND_NAMES), -np.inf)
        with np.errstate(divide="ignore"):
            rate = np.log(radius) * self.plane.sample_rate_hz
        np.maximum.at(growth, bands, rate)
        k = int(np.argmax(radius))
        return float(radius[k]), float(hz[k]), growth


def find_onset(plane: RigPlane, table: GainTable, schedule: GainSchedule, loads: np.ndarray,
               resolution_n: float, keep_walk: bool = False):
    """Walk ``loads`` up to the first unstable one, bisect the step before it to ``resolution_n``:
    (onset, stable to, pole Hz, |z|, points, walk loads, walk growth) as in ``Onset``; the walk
    is kept only with ``keep_walk``."""
    loop = _Loop(plane, table, schedule)
    walked: list[float] = []
    growths: list[tuple[float, ...]] = []
    previous = None
    largest = (-1.0, 0.0)
    for load in (float(x) for x in loads):
        radius, hz, growth = loop.at(load)
        if radius >= 1.0:
            walk = (tuple(walked), tuple(growths))
            if previous is None:
                return load, None, hz, radius, loop.points, *walk
            a, b = previous, load
            while b - a > resolution_n:
                mid = 0.5 * (a + b)
                r, f, _ = loop.at(mid)
                if r >= 1.0:
                    b, radius, hz = mid, r, f
                else:
                    a = mid
            return b, a, hz, radius, loop.points, *walk
        previous = load
        largest = max(largest, (radius, hz))
        if keep_walk:
            walked.append(load)
            growths.append(tuple(float(g) for g in growth))
    return None, previous, largest[1], largest[0], loop.points, tuple(walked), tuple(growths)


def rig_plane(rig: Rig) -> RigPlane:
    """The plane the checks analyse of ``rig`` (its own FE model, I/O chain, rate, stack gain)."""
    return RigPlane(build_model(rig.params), rig.chain, rig.sample_rate_hz, rig.force_gain)


def evaluate(table: GainTable, schedule: GainSchedule, box: Box, values: Mapping[str, float],
             mode: str = "full", ratio: float | None = None,
             rig: Rig | None = None) -> Onset | Margin | Refused:
    """One rig (``values``: box key -> factor/offset/value): its onset, walking the check loads
    (``full``, ``check_loads``) or the coarse ones (``search``, ``search_loads``, keeping the
    walk's growth rates); or (``margin``) its growth rates at ``ratio`` x its own Fx,cr. ``rig``:
    the rig itself (models/rig.py), when the caller has built it (``values`` then only label it);
    by default the box's rig of ``values``. A rig the model refuses to build is ``Refused``."""
    if mode not in MODES:
        raise ValueError(f"mode {mode!r}: expected one of {', '.join(MODES)}")
    values = {k: float(v) for k, v in values.items()}
    try:
        plane = rig_plane(rig if rig is not None else rig_of(table, box, values))
    except ConfigError as exc:          # a point of the box the model cannot be: counted, not fatal
        return Refused(values=values, reason=str(exc))
    critical = plane.critical_load_n
    if mode == "margin":
        load = float(ratio) * critical
        return Margin(values=values, critical_load_n=critical, load_n=load,
                      growth=tuple(float(g) for g in _Loop(plane, table, schedule).at(load)[2]))
    search = mode == "search"
    loads = (search_loads(table.loads_n, critical, box.search_step_n) if search
             else check_loads(table.loads_n, critical, box))
    onset, stable_to, hz, radius, points, walked, growths = find_onset(
        plane, table, schedule, loads, box.resolution_n, keep_walk=search)
    end = onset if onset is not None else float(loads[-1])
    return Onset(values=values, critical_load_n=critical, onset_n=onset, stable_to_n=stable_to,
                 ratio=end / critical, pole_hz=hz, spectral_radius=radius, points=points, mode=mode,
                 walk_loads_n=walked, walk_growth=growths)


# -------------------------------------------------------------------------------------------
# evaluating many rigs: worker processes here, or a Dask cluster

Job = tuple[dict[str, float], str, float | None]       # a rig's values, the mode, the margin's ratio
Evaluator = Callable[[list[Job], Callable[[Any], None] | None], list[Any]]

_WORKER: dict[str, Any] = {}
_WORKER_LOCK = threading.Lock()


def _init_worker(table: GainTable, box: Box) -> None:
    # a worker process of this check (its own, spawned): Ctrl-C at the terminal is the caller's
    # to handle (the pool is shut down from there), not a traceback from every worker; one BLAS
    # thread, the processes share the cores
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from threadpoolctl import threadpool_limits

    _WORKER["limits"] = threadpool_limits(1)
    _WORKER["table"] = table
    _WORKER["box"] = box
    _WORKER["schedule"] = GainSchedule.from_table(table)


def _run(job: Job) -> Onset | Margin:
    return evaluate(_WORKER["table"], _WORKER["schedule"], _WORKER["box"], *job)


def evaluate_on_worker(job: Job, table: GainTable, box: Box) -> Onset | Margin:
    """One rig on a Dask worker (the table and box scattered once); the schedule is built once
    per worker and table. BLAS threads are the cluster's to set (OPENBLAS_NUM_THREADS=1)."""
    with _WORKER_LOCK:
        if _WORKER.get("table") is not table:
            _WORKER["table"], _WORKER["schedule"] = table, GainSchedule.from_table(table)
        schedule = _WORKER["schedule"]
    return evaluate(table, schedule, box, *job)


@contextmanager
def local_evaluator(table: GainTable, box: Box, workers: int | None = None) -> Iterator[Evaluator]:
    """Rigs evaluated in ``workers`` processes (default: the cores, at most 2 here), in the
    order given; ``workers=1`` evaluates them in this process."""
    workers = workers or min(2, os.cpu_count() or 1)
    if workers == 1:
        schedule = GainSchedule.from_table(table)

        def here(jobs, each=None):
            out = []
            for job in jobs:
                out.append(evaluate(table, schedule, box, *job))
                if each:
                    each(out[-1])
            return out

        yield here
        return
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn"), initializer=_init_worker,
                             initargs=(table, box)) as pool:
        def spread(jobs, each=None):
            futures = [pool.submit(_run, job) for job in jobs]
            out = []
            for k, future in enumerate(futures):
                try:
                    r = future.result()
                except BrokenProcessPool:
                    flight = [jobs[i][0] for i in range(k, len(futures))
                              if not futures[i].done() or futures[i].exception() is not None]
                    named = "; ".join(describe(v, box) for v in flight[:workers])
                    raise WorkerDied(f"a worker process of the robust check died (killed, out of memory, "
                                     f"or a crash) while it evaluated one of the rigs in flight: {named}"
                                     ) from None
                out.append(r)
                if each:
                    each(r)
            return out

        try:
            yield spread
        except BaseException:
            pool.shutdown(wait=False, cancel_futures=True)
            raise


def dask_evaluator(client, table: GainTable, box: Box) -> Evaluator:
    """Rigs evaluated on the Dask cluster of ``client``, in the order given."""
    shared = client.scatter([table, box], broadcast=True)

    def spread(jobs, each=None):
        futures = client.map(evaluate_on_worker, jobs, table=shared[0], box=shared[1], pure=False)
        out = []
        try:
            for f in futures:
                out.append(f.result())
                if each:
                    each(out[-1])
        finally:
            for f in futures:
                f.cancel()
        return out

    return spread


# -------------------------------------------------------------------------------------------
# the search


@dataclass
class RobustResult:
    """The search's outcome: the verified rigs (worst first) and every rig it evaluated."""

    box: Box
    verified: list[Onset] = field(default_factory=list)
    evaluated: list[Onset] = field(default_factory=list)
    margins: list[Margin] = field(default_factory=list)
    refused: list[Refused] = field(default_factory=list)
    phases: dict[str, int] = field(default_factory=dict)
    elapsed_s: float = 0.0

    @property
    def worst(self) -> Onset:
        return min(self.verified, key=lambda r: r.ratio)

    @property
    def worst_ratio(self) -> float:
        return self.worst.ratio

    @property
    def count(self) -> int:
        """Rigs evaluated: walked (search and verification) or at one load (the climbs); the
        refused ones apart (``refused``)."""
        return len(self.evaluated) + len(self.margins) + len(self.verified)

    def refused_text(self) -> str:
        """The refused rigs in a line ("" when none): how many, the first one and why."""
        if not self.refused:
            return ""
        first = self.refused[0]
        return (f"{len(self.refused)} rigs of the box are no rig the model can build (the box is partly "
                f"invalid; they were counted, not evaluated), e.g. {describe(first.values, self.box)}: "
                f"{first.reason}")

    def to_dict(self, table: GainTable | None = None) -> dict[str, Any]:
        w = self.worst
        out = {"worst_ratio": w.ratio, "worst_rig": dict(w.values), "onset_N": w.onset_n,
               "stable_to_N": w.stable_to_n, "critical_load_N": w.critical_load_n, "censored": w.censored,
               "pole_hz": w.pole_hz, "spectral_radius": w.spectral_radius, "evaluated": self.count,
               "phases": dict(self.phases), "elapsed_s": self.elapsed_s,
               "method": "differential evolution (scipy, seeded, from a Latin hypercube), compass "
                         "refinement, the worst distinct rigs walked again at the check's fine steps",
               "verified": [r.to_dict() for r in sorted(self.verified, key=lambda r: r.ratio)],
               "refused": len(self.refused), "refused_rigs": [r.to_dict() for r in self.refused[:10]],
               "box": self.box.to_dict()}
        if table is not None:
            out["worst_rig_si"] = rig_si(table, self.box, w.values)
        return {"robust": out}


def table_record(result: RobustResult, box_name: str) -> dict[str, Any]:
    """What a gain table keeps of its robust check (its ``robust`` section): the worst ratio,
    where that rig went unstable, how many rigs were searched, the box and when."""
    w = result.worst
    return {"worst_ratio": float(w.ratio), "onset_N": w.onset_n, "critical_load_N": float(w.critical_load_n),
            "censored": bool(w.censored), "worst_rig": {k: float(v) for k, v in w.values.items()},
            "evaluated": int(result.count), "refused": len(result.refused), "box_name": box_name,
            "box": result.box.to_dict(),
            "checked": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}


def robust_text(record: Mapping[str, Any] | None) -> str:
    """A table's recorded robust check in one line (``table_record``)."""
    if not record:
        return "not recorded in the table (`beamctl gains check --robust --record FILE` records it)"
    held = "held" if record["worst_ratio"] >= 1.0 else "NOT HELD"
    where = (f"stays stable to the table's end, at least {record['worst_ratio']:.4f} x its own critical load"
             if record.get("censored") else
             f"goes unstable at {record['worst_ratio']:.4f} x its own critical load")
    refused = (f"; {record['refused']} rigs of the box the model refuses to build: the box is partly invalid"
               if record.get("refused") else "")
    return (f"{held}: the worst rig of {record.get('box_name', 'its box')} {where} "
            f"({record.get('evaluated', '?')} rigs searched, {record.get('checked', 'time not recorded')}"
            f"{refused})")


def rig_si(table: GainTable, box: Box, values: Mapping[str, float]) -> dict[str, float]:
    """The rig's parameters in SI units (model keys), its delay in samples, its sample rate in
    Hz and its stack force per volt relative to the design's (``force_gain``)."""
    rig = rig_of(table, box, values)
    model = rig.params.to_dict()
    out: dict[str, float] = {}
    for key in values:
        if key == "io.delay_samples":
            out[key] = rig.chain.delay_samples
        elif key == "sample_rate_hz":
            out[key] = rig.sample_rate_hz
        elif key == "actuators.force_constant_n_per_v":
            out["actuators.force_gain"] = rig.force_gain
        else:
            base = key.partition("[")[0]
            node = dotted_get(model, key)
            if isinstance(node, list):
                for i, x in enumerate(node):
                    out[f"{base}[{i}]"] = float(x)
            else:
                out[key] = float(node)
    return out


SHORT_NAMES = {"beam.youngs_modulus": "E", "supports.rotational_stiffness": "kr",
               "supports.lateral_stiffness": "kl", "supports.actuator_stiffness": "kp",
               "damping.ratios": "damping", "actuators.force_constant_n_per_v": "stacks",
               "io.delay_samples": "delay", "sample_rate_hz": "rate",
               "sensors.strain_gauge_positions[0]": "gauge 1", "sensors.strain_gauge_positions[1]": "gauge 2"}


def describe(values: Mapping[str, float], box: Box = DEFAULT_BOX) -> str:
    """A rig in a line: ``E x1.050, kr x1.200, ..., delay 0.40, gauge 1 -1.00 mm``."""
    parts = []
    for key, v in values.items():
        name = SHORT_NAMES.get(key, key)
        kind = box.parameters[key].kind if key in box.parameters else "value"
        if kind == "factor":
            parts.append(f"{name} x{v:.3f}")
        elif kind == "offset" and key.startswith("sensors."):
            parts.append(f"{name} {v * 1e3:+.2f} mm")
        elif kind == "offset":
            parts.append(f"{name} {v:+.4g}")
        else:
            parts.append(f"{name} {v:.3g}" if key != "io.delay_samples" else f"{name} {v:.2f}")
    return ", ".join(parts) or "nominal"


def search_worst(table: GainTable, box: Box, evaluator: Evaluator,
                 progress: Progress | None = None) -> RobustResult:
    """Search ``box`` for the rig with the lowest onset ratio (see the module docstring)."""
    import time

    from scipy.optimize import differential_evolution
    from scipy.stats import qmc

    start = time.monotonic()
    dim = len(box.parameters)
    result = RobustResult(box=box)
    total = box.budget
    units: list[np.ndarray] = []            # the unit-cube point of every rig walked
    done = [0, math.inf]                    # rigs evaluated, the lowest ratio so far

    def report(r: Onset | Margin | Refused) -> None:
        done[0] += 1
        if isinstance(r, Onset):
            done[1] = min(done[1], r.ratio)
        if progress:
            progress(done[0], total, f"worst so far {done[1]:.4f}")

    def onsets(us: Sequence[np.ndarray]) -> list[float]:
        """The onset ratios of the rigs at ``us`` (the search's walk)."""
        points = [np.clip(np.asarray(u, dtype=float), 0.0, 1.0) for u in us]
        out = evaluator([(box.values(u), "search", None) for u in points], report)
        ratios = []
        for u, r in zip(points, out, strict=True):
            if isinstance(r, Refused):          # no rig there: the search is kept away from it
                result.refused.append(r)
                ratios.append(math.inf)
                continue
            result.evaluated.append(r)
            units.append(u)
            ratios.append(r.ratio)
        return ratios

    # 1. global: differential evolution over the unit cube, population from a Latin hypercube
    init = qmc.LatinHypercube(d=dim, seed=box.seed).random(box.population)
    differential_evolution(_never, [(0.0, 1.0)] * dim, maxiter=box.generations, init=init, rng=box.seed,
                           strategy=box.strategy, tol=0.0, atol=0.0, polish=False, updating="deferred",
                           workers=lambda _f, xs: onsets(list(xs)))
    result.phases["global"] = len(result.evaluated)
    if not result.evaluated:
        raise ConfigError("box", box.to_dict()["parameters"], "a box of rigs the model can build: every "
                          f"rig searched was refused ({result.refused_text()})")

    # 2. the ways of failing that the worst so far hides: for each band of BAND_NAMES, climb the
    # growth rate of its least stable pole at the worst ratio so far (x each rig's own Fx,cr),
    # from the rig where it was highest; a rig unstable there is worse than the worst so far
    worst = min(r.ratio for r in result.evaluated)
    margins = 0
    for b in range(len(BAND_NAMES)):
        growth = [r.growth_at(worst)[b] for r in result.evaluated]
        i = int(np.argmax(growth))
        if not np.isfinite(growth[i]):
            continue

        def minus_growth(us: Sequence[np.ndarray], b: int = b) -> list[float]:
            points = [np.clip(np.asarray(u, dtype=float), 0.0, 1.0) for u in us]
            out = evaluator([(box.values(u), "margin", worst) for u in points], report)
            minus = []
            for m in out:
                if isinstance(m, Refused):
                    result.refused.append(m)
                    minus.append(math.inf)
                else:
                    result.margins.append(m)
                    minus.append(-m.growth[b])
            return minus

        share = (box.margin - margins) // (len(BAND_NAMES) - b)
        x, minus, used = _compass(units[i], -growth[i], minus_growth, share, stop_below=0.0)
        margins += used
        if minus < 0.0:                     # unstable below the worst so far: walk it
            onsets([x])
    result.phases["margin"] = margins

    # 3. local: a compass search of the onset from each of the worst distinct rigs (one per way
    # of failing first, then apart in the box)
    starts = _distinct(units, [r.ratio for r in result.evaluated], box.starts, 0.25,
                       [None if r.censored else r.pole_hz for r in result.evaluated])
    used = 0
    for k, i in enumerate(starts):
        share = (box.refine - used) // (len(starts) - k)
        used += _compass(units[i], result.evaluated[i].ratio, onsets, share)[2]
    result.phases["refine"] = used

    # 4. verify the worst distinct rigs at the fine steps, walked from the first load
    chosen = _distinct(units, [r.ratio for r in result.evaluated], box.verify, 0.25,
                       [None if r.censored else r.pole_hz for r in result.evaluated])
    count = len(result.evaluated) + len(result.margins)
    total = count + len(chosen)
    verified: list[Onset] = []

    def checked(r: Onset) -> None:
        verified.append(r)
        if progress:
            progress(count + len(verified), total, f"verifying, {r.ratio:.4f}")

    result.verified = evaluator([(result.evaluated[i].values, "full", None) for i in chosen], checked)
    result.phases["verify"] = len(chosen)
    result.elapsed_s = time.monotonic() - start
    if progress:
        progress(total, total, f"worst {result.worst_ratio:.4f}")
    return result


def _distinct(units: list[np.ndarray], ratios: list[float], count: int, apart: float,
              poles_hz: list[float | None] | None = None) -> list[int]:
    """Indices of the ``count`` lowest ratios, each one a rig of its own: first the lowest rig of
    each way of failing (its pole's frequency more than a factor 2 from the others': the slow
    mode 1, the closed-loop mode 1 near 100 Hz, mode 3 near 1 kHz, mode 5 near 2.7 kHz are
    separate regions of the box; a censored rig, None, has none), then rigs more than ``apart``
    from the chosen ones in the max-norm (the worst first)."""
    order = [int(i) for i in np.argsort(ratios, kind="stable")]
    chosen: list[int] = []
    if poles_hz is not None:
        for i in order:
            if poles_hz[i] is None:
                continue
            hz = max(poles_hz[i], 1e-3)
            if all(not 0.5 < hz / max(poles_hz[j], 1e-3) < 2.0 for j in chosen):
                chosen.append(i)
            if len(chosen) == count:
                return sorted(chosen, key=lambda i: ratios[i])
    for i in order:
        if len(chosen) == count:
            break
        if i not in chosen and all(np.max(np.abs(units[i] - units[j])) > apart for j in chosen):
            chosen.append(i)
    return sorted(chosen, key=lambda i: ratios[i])


def _compass(x: np.ndarray, fx: float, batch: Callable[[list[np.ndarray]], list[float]], budget: int,
             stop_below: float = -math.inf) -> tuple[np.ndarray, float, int]:
    """A compass search from ``x`` (value ``fx``): each coordinate up and down by a step (a
    quarter of the range first), the neighbours evaluated together, and the point that takes
    every coordinate's better move at once; move to the lowest if it is lower than here and
    double the step (up to a quarter), otherwise halve it, down to 1/256; stop at a value below
    ``stop_below``. Returns (the lowest point, its value, the points evaluated)."""
    step = 0.25
    used = 0
    x = x.copy()
    while step >= 1.0 / 256 and used < budget and fx >= stop_below:
        trials, moves = [], []
        for i in range(len(x)):
            for sign in (1.0, -1.0):
                t = x.copy()
                t[i] = min(1.0, max(0.0, t[i] + sign * step))
                if t[i] != x[i]:
                    trials.append(t)
                    moves.append(i)
        trials = trials[:budget - used]
        values = batch(trials)
        used += len(trials)
        better: dict[int, int] = {}
        for k, (i, v) in enumerate(zip(moves, values, strict=False)):
            if v < fx and (i not in better or v < values[better[i]]):
                better[i] = k
        if not better:
            step /= 2
            continue
        j = min(better.values(), key=lambda k: values[k])
        x_next, f_next = trials[j], values[j]
        if len(better) > 1 and used < budget:
            combined = x.copy()
            for i, k in better.items():
                combined[i] = trials[k][i]
            (v,) = batch([combined])
            used += 1
            if v < f_next:
                x_next, f_next = combined, v
        x, fx = x_next, f_next
        step = min(0.25, 2 * step)           # a move that worked: larger steps again
    return x, fx, used


def _never(_u: np.ndarray) -> float:     # pragma: no cover - the search evaluates through its workers
    raise AssertionError("the search evaluates rigs through its evaluator")


def robust_check(table: GainTable, box: Box = DEFAULT_BOX, *, workers: int | None = None,
                 progress: Progress | None = None, client=None) -> RobustResult:
    """The robust check of ``table`` over ``box``: the search, on ``workers`` processes here or
    on the Dask cluster of ``client``."""
    if client is not None:
        return search_worst(table, box, dask_evaluator(client, table, box), progress)
    with local_evaluator(table, box, workers) as evaluator:
        return search_worst(table, box, evaluator, progress)
