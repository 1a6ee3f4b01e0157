"""Build a gain table: the integral LQR at every grid load as the compensator the step runs,
the discrete closed-loop check of exactly those matrices at every grid point and every
midpoint between neighbours, and, for a table stable at every check point, the ride-through
limits of that loop per grid load, covering the same loads (gains/ridethrough.py)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import replace
from importlib import metadata

import numpy as np

from beamctl.config.schema import ConfigError
from beamctl.gains import lqg, ridethrough, robust
from beamctl.gains.compensator import Compensator, CompensatorPoint, from_integral_lqr
from beamctl.gains.defaults import (
    DEFAULT_DESIGN,
    DEFAULT_SCHEDULE,
    LQG_CHAIN,
    LQG_GRID_N,
    LQG_SAMPLE_RATE_HZ,
    LQG_SETTINGS,
    PAPER_GRID_N,
)
from beamctl.gains.discrete import LoopCheck, pole_summary, velocity_filter
from beamctl.gains.lqr import lqr_gain
from beamctl.gains.rig import RigPlane
from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import DesignSettings, GainTable, ScheduleSettings
from beamctl.models.analysis import critical_load
from beamctl.models.fe import FEModel
from beamctl.models.iochain import IOChain
from beamctl.models.modal import reduce

Progress = Callable[[int, int, str], None]


def tool_version() -> str:
    try:
        return metadata.version("beamctl")
    except metadata.PackageNotFoundError:
        return "unknown"


def check_points(loads: Sequence[float]) -> list[float]:
    """Grid points and the midpoints between neighbours, ascending."""
    loads = list(loads)
    mids = [(a + b) / 2 for a, b in zip(loads[:-1], loads[1:], strict=True)]
    return sorted(loads + mids)


def _plan_loads(loads_n: Sequence[float], schedule: ScheduleSettings) -> list[tuple[float, int | None]]:
    """(load, grid point whose matrices are used or None for the settled schedule's) of every
    check: each grid point and midpoint and, in ``paper`` mode, the ends of each gain's reach
    through the hysteresis band: gain i is still on at L_i + h/2 as the load rises and down to
    L_(i-1) - h/2 as it falls."""
    loads = [float(x) for x in loads_n]
    plan: list[tuple[float, int | None]] = [(load, None) for load in check_points(loads)]
    if schedule.mode == "paper":
        half = 0.5 * schedule.hysteresis_n
        for i in range(len(loads)):
            if half > 0 and i + 1 < len(loads):
                plan.append((loads[i] + half, i))
            if half > 0 and i > 0 and loads[i - 1] - half >= loads[0]:
                plan.append((loads[i - 1] - half, i))
    return sorted(plan, key=lambda p: p[0])


def check_plan(table: GainTable) -> list[tuple[float, float | None, CompensatorPoint]]:
    """(load, grid load whose matrices are used or None, the matrices) of every closed-loop
    check (see ``_plan_loads``): the schedule's own ``matrices_at`` where it settles, the grid
    point's matrices at the band ends."""
    schedule = GainSchedule.from_table(table)
    comp = table.compensator
    return [(load, None, schedule.matrices_at(load)) if i is None
            else (load, float(table.loads_n[i]), comp.point(i))
            for load, i in _plan_loads(table.loads_n, table.schedule)]


def nominal_rig(model: FEModel, table: GainTable, plane: str = "y") -> RigPlane:
    """The rig the design assumes: the model's FE plane with the I/O chain the design declares
    (``design.io``) at the design's rate and stack force per volt."""
    return RigPlane(model, table.design.io, table.design.sample_rate_hz, plane=plane)


def check_load(model: FEModel, axial_load: float, point: CompensatorPoint, table: GainTable,
               plane: str = "y", rig: RigPlane | None = None) -> LoopCheck:
    """The discrete closed loop at ``axial_load``: the full FE model of one bending plane
    (140 states) with the I/O chain the design declares, sampled with the delayed zero-order
    hold at the table's rate (``nominal_rig``, or ``rig``), closed by the compensator matrices
    ``point`` (gains.closedloop).

    The two planes of the circular section have the same plant spectrum and, by design, the
    same compensator block (tested): checking one plane checks both.
    """
    comp = table.compensator
    rig = rig or nominal_rig(model, table, plane)
    matrix = rig.loop_matrix(axial_load, point, comp.h, comp.plane_states[rig.plane], comp.period_s)
    radius, damping = pole_summary(np.linalg.eigvals(matrix), table.design.sample_rate_hz)
    return LoopCheck(load_n=float(axial_load), spectral_radius=radius, min_damping=damping)


def closed_loop_checks(model: FEModel, table: GainTable, progress: Progress | None = None,
                       done: int = 0, total: int | None = None) -> tuple[LoopCheck, ...]:
    """The closed-loop check of ``table`` at every load of ``check_plan``."""
    plan = check_plan(table)
    total = total if total is not None else len(plan)
    rig = nominal_rig(model, table)
    results = []
    for i, (load, gain_load, point) in enumerate(plan):
        results.append(replace(check_load(model, load, point, table, rig=rig), gain_load_n=gain_load))
        if progress:
            progress(done + i + 1, total, f"check {load:7.1f} N")
    return tuple(results)


def ride_through_rigs(model: FEModel, table: GainTable) -> tuple[list[RigPlane], list[str]]:
    """The rigs the ride-through analysis covers: the nominal rig and, where the table records a
    robust check, its worst rig (gains/robust.py); with their names."""
    rigs, names = [nominal_rig(model, table)], ["the nominal rig"]
    record = table.robust or {}
    if record.get("worst_rig") and isinstance(record.get("box"), dict):
        box = robust.box_from_dict(record["box"], table.model_parameters, "the table's robust check")
        rig = robust.rig_of(table, box, record["worst_rig"])
        rigs.append(robust.rig_plane(rig))
        names.append(f"the robust check's worst rig ({robust.describe(record['worst_rig'], box)})")
    return rigs, names


# Above this fraction of the nominal Fx,cr the ride-through is analysed every FINE_STEP_N too
# (besides the check's loads): a gap's growth rises steeply with the load there, and the engine
# takes the largest of an interval's ends, so a coarse interval would cost its lower end much of
# its limit (the survival edge in the time domain, simulation/stall.py)
FINE_FROM_FRACTION = 0.95
FINE_STEP_N = 25.0


def ride_through_plan(
        table: GainTable, critical_n: float) -> list[tuple[float, float | None, CompensatorPoint]]:
    """The loads the ride-through is analysed at: every load of the closed-loop check
    (``check_plan``) and, from FINE_FROM_FRACTION of ``critical_n`` to the table's top, every
    FINE_STEP_N (the schedule's settled matrices there), ascending."""
    plan = check_plan(table)
    schedule = GainSchedule.from_table(table)
    for load in _fine_loads(table.loads_n, {round(p[0], 6) for p in plan}, critical_n):
        plan.append((load, None, schedule.matrices_at(load)))
    return sorted(plan, key=lambda p: p[0])


def ride_through(model: FEModel, table: GainTable, progress: Progress | None = None, done: int = 0,
                 total: int | None = None) -> ridethrough.RideThrough:
    """The ride-through analysis of ``table``'s loop on the nominal rig and the robust check's
    worst rig where the table records one (``ride_through_rigs``), at every load of its
    closed-loop check and finer near and above the critical load (``ride_through_plan``;
    gains/ridethrough.py)."""
    rigs, names = ride_through_rigs(model, table)
    plan = ride_through_plan(table, critical_load(model))
    return ridethrough.analyse(rigs, table, plan, progress, done, total, rig_names=names)


def with_robust(model: FEModel, table: GainTable, record: dict,
                progress: Progress | None = None) -> GainTable:
    """``table`` with the robust check ``record`` (gains/robust.py ``table_record``) and, where it
    had a ride-through analysis, that analysis again over the nominal rig and the worst rig the
    check found (a gap the nominal rig survives can be too long for the rig the box allows)."""
    table = replace(table, robust=record)
    if table.ride_through is None or not table.all_stable:
        return table
    return replace(table, ride_through=ride_through(model, table, progress))


def _checked(model: FEModel, table: GainTable, force: bool, analyse: bool, progress: Progress | None,
             done: int, total: int) -> GainTable:
    """The table with its closed-loop check and, stable at every point and with ``analyse``,
    its ride-through limits (an unstable loop has no stationary state to ride through from)."""
    checks = closed_loop_checks(model, table, progress, done, total)
    table = replace(table, checks=checks)
    if table.all_stable and analyse:
        table = replace(table, ride_through=ride_through(model, table, progress, done + len(checks), total))
    # --force marks a table that is written in spite of an unstable point, nothing else
    return replace(table, forced=force and not table.all_stable)


def _fine_loads(loads: Sequence[float], have: set, critical_n: float) -> list[float]:
    """The loads ``ride_through_plan`` adds to the check's (``have``, rounded to 1e-6 N)."""
    top = float(loads[-1])
    start = FINE_STEP_N * math.ceil(FINE_FROM_FRACTION * critical_n / FINE_STEP_N)
    return [float(x) for x in np.arange(start, top, FINE_STEP_N) if round(float(x), 6) not in have]


def _check_steps(loads: np.ndarray, schedule: ScheduleSettings, analyse: bool, critical_n: float) -> int:
    """Progress steps of the check and the ride-through analysis."""
    plan = _plan_loads(loads, schedule)
    extra = len(_fine_loads(loads, {round(p[0], 6) for p in plan}, critical_n)) if analyse else 0
    return len(plan) + (ridethrough.steps(plan) + 2 * extra if analyse else 0)


def integral_lqr_compensator(gains: np.ndarray, c0_phi_inv: np.ndarray,
                             design: DesignSettings) -> Compensator:
    """The paper's controller for the gains K [G x 4 x 12]: (C0 Phi)^-1, the high-pass velocity
    estimate of ``design`` and K, as the compensator the step runs."""
    filt = velocity_filter(design.velocity_cutoff_hz, design.sample_rate_hz)
    return from_integral_lqr(gains, c0_phi_inv, 1.0 / design.sample_rate_hz, filt.b0, filt.b1, filt.a1,
                             filt.scale)


def build_table(model: FEModel, loads_n: Sequence[float] | None = None, mode: str = "interpolate",
                design: DesignSettings = DEFAULT_DESIGN, schedule: ScheduleSettings | None = None,
                check: bool = True, force: bool = False, progress: Progress | None = None,
                analyse_ride_through: bool = True) -> GainTable:
    """Design K(Fx) on the grid ``loads_n`` (default: 0 to 4000 N every 50 N, or the paper's
    0 to 3500 N every 500 N in ``paper`` mode), write it as the compensator the step runs and
    check the closed loop (with ``check``; stable, and unless ``analyse_ride_through`` is
    False, the ride-through limits too: a few seconds)."""
    if design.kind != "integral-lqr":
        raise ValueError(f"build_table designs integral-lqr tables, not {design.kind}")
    if loads_n is None:
        loads_n = PAPER_GRID_N if mode == "paper" else np.arange(0.0, 4000.0 + 1e-9, 50.0)
    loads = np.asarray(loads_n, dtype=float)
    if mode == "interpolate" and len(loads) < 2:
        raise ConfigError("--grid", loads.tolist(), "at least two grid points to interpolate between")
    schedule = schedule or replace(DEFAULT_SCHEDULE, mode=mode)
    reduced = reduce(model)
    total = len(loads) + (_check_steps(loads, schedule, analyse_ride_through, critical_load(model))
                          if check else 0)
    gains = np.zeros((len(loads), 4, 12))
    for i, load in enumerate(loads):
        gains[i] = lqr_gain(reduced, load, design.weights)
        if progress:
            progress(i + 1, total, f"LQR {load:7.1f} N")
    table = GainTable(loads_n=loads, compensator=integral_lqr_compensator(gains, reduced.c0_phi_inv, design),
                      c0_phi_inv=reduced.c0_phi_inv, design=design, schedule=schedule,
                      model_parameters=model.params, tool_version=tool_version(), gains=gains)
    if check:
        table = _checked(model, table, force, analyse_ride_through, progress, len(loads), total)
    return table


def build_lqg_table(model: FEModel, loads_n: Sequence[float] | None = None,
                    sample_rate_hz: float = LQG_SAMPLE_RATE_HZ, chain: IOChain = LQG_CHAIN,
                    settings: lqg.LqgSettings = LQG_SETTINGS, schedule: ScheduleSettings | None = None,
                    check: bool = True, force: bool = False, progress: Progress | None = None,
                    analyse_ride_through: bool = True) -> GainTable:
    """The delay-aware LQG (gains.lqg) at every grid load (default every 100 N to 4000 N),
    designed for ``chain``, as the compensator the step runs, with the closed-loop check on
    that chain (with ``check``; stable, and unless ``analyse_ride_through`` is False, the
    ride-through limits too)."""
    loads = np.asarray(LQG_GRID_N if loads_n is None else loads_n, dtype=float)
    if len(loads) < 2:
        raise ConfigError("--grid", loads.tolist(), "at least two grid points to interpolate between")
    schedule = schedule or DEFAULT_SCHEDULE
    if schedule.mode != "interpolate":
        raise ConfigError("--mode", schedule.mode, "'interpolate' for an lqg design (the paper's "
                          "switching belongs to the integral-lqr design)")
    reduced = reduce(model)
    total = 2 + (_check_steps(loads, schedule, analyse_ride_through, critical_load(model)) if check else 0)
    steps = iter(range(1, 3))
    comp = lqg.design(model, loads, sample_rate_hz, chain, reduced.c0_phi_inv, settings,
                      progress=(lambda plane: progress(next(steps), total, f"LQG plane {plane}"))
                      if progress else None)
    design = DesignSettings(kind="lqg", sample_rate_hz=sample_rate_hz, io=chain,
                            parameters=settings.to_dict())
    table = GainTable(loads_n=loads, compensator=comp, c0_phi_inv=reduced.c0_phi_inv, design=design,
                      schedule=schedule, model_parameters=model.params, tool_version=tool_version())
    if check:
        table = _checked(model, table, force, analyse_ride_through, progress, 2, total)
    return table
