"""Build a gain table: the integral LQR at every grid load, and the discrete closed-loop
check at every grid point and every midpoint between neighbours."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from importlib import metadata

import numpy as np

from beamctl.config.schema import ConfigError
from beamctl.gains.defaults import DEFAULT_DESIGN, DEFAULT_SCHEDULE, PAPER_GRID_N
from beamctl.gains.discrete import LoopCheck, check_load, velocity_filter
from beamctl.gains.lqr import lqr_gain
from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import DesignSettings, GainTable, ScheduleSettings
from beamctl.models.fe import FEModel
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


def check_plan(table: GainTable) -> list[tuple[float, float | None, np.ndarray]]:
    """(load, grid load whose gain is used or None, gain) of every closed-loop check: each grid
    point and midpoint with the gain the schedule settles on there and, in ``paper`` mode,
    the ends of each gain's reach through the hysteresis band: gain i is still on at
    L_i + h/2 as the load rises and down to L_(i-1) - h/2 as it falls."""
    schedule = GainSchedule(table)
    plan = [(load, None, schedule.gain_at(load)) for load in check_points(table.loads_n)]
    if table.schedule.mode == "paper":
        half = 0.5 * table.schedule.hysteresis_n
        loads = [float(x) for x in table.loads_n]
        for i, gain in enumerate(table.gains):
            if half > 0 and i + 1 < len(loads):
                plan.append((loads[i] + half, loads[i], gain))
            if half > 0 and i > 0 and loads[i - 1] - half >= loads[0]:
                plan.append((loads[i - 1] - half, loads[i], gain))
    return sorted(plan, key=lambda p: p[0])


def closed_loop_checks(model: FEModel, table: GainTable, progress: Progress | None = None,
                       done: int = 0, total: int | None = None) -> tuple[LoopCheck, ...]:
    """The closed-loop check of ``table`` at every load of ``check_plan``."""
    filt = velocity_filter(table.design.velocity_cutoff_hz, table.design.sample_rate_hz)
    plan = check_plan(table)
    total = total if total is not None else len(plan)
    results = []
    for i, (load, gain_load, gain) in enumerate(plan):
        result = check_load(model, load, gain, table.c0_phi_inv, filt)
        results.append(replace(result, gain_load_n=gain_load))
        if progress:
            progress(done + i + 1, total, f"check {load:7.1f} N")
    return tuple(results)


def build_table(model: FEModel, loads_n: Sequence[float] | None = None, mode: str = "interpolate",
                design: DesignSettings = DEFAULT_DESIGN, schedule: ScheduleSettings | None = None,
                check: bool = True, force: bool = False,
                progress: Progress | None = None) -> GainTable:
    """Design K(Fx) on the grid ``loads_n`` (default: 0 to 4000 N every 50 N, or the paper's
    0 to 3500 N every 500 N in ``paper`` mode) and check the closed loop."""
    if loads_n is None:
        loads_n = PAPER_GRID_N if mode == "paper" else np.arange(0.0, 4000.0 + 1e-9, 50.0)
    loads = np.asarray(loads_n, dtype=float)
    if mode == "interpolate" and len(loads) < 2:
        raise ConfigError("--grid", loads.tolist(), "at least two grid points to interpolate between")
    schedule = schedule or replace(DEFAULT_SCHEDULE, mode=mode)
    reduced = reduce(model)
    gains = np.zeros((len(loads), 4, 12))
    table = GainTable(loads_n=loads, gains=gains, c0_phi_inv=reduced.c0_phi_inv, design=design,
                      schedule=schedule, model_parameters=model.params, tool_version=tool_version())
    total = len(loads) + (len(check_plan(table)) if check else 0)
    for i, load in enumerate(loads):
        gains[i] = lqr_gain(reduced, load, design.weights)
        if progress:
            progress(i + 1, total, f"LQR {load:7.1f} N")
    if check:
        table = replace(table, checks=closed_loop_checks(model, table, progress, len(loads), total))
        # --force marks a table that is written in spite of an unstable point, nothing else
        table = replace(table, forced=force and not table.all_stable)
    return table
