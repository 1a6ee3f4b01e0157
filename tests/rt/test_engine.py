"""The compiled engine (rt/engine.py) against its specification in plain Python
(tests/rt/reference_cycle.py), and the physical facts it must keep whatever it is fed.

- Randomised sequences (seeded numpy, a few hundred of them over six gain tables): noise, large
  deflections that saturate the stacks, loads sweeping across grid points (interpolated and
  switched schedules), NaN / infinite / out-of-range strains and loads, gaps of the sequence
  within and beyond the gap limit, silences, late answers, overruns, operator stops, faults and
  re-arms, both allocations, excitation, the law off. After every call the engine's record, its
  voltages, its compensator state, its counts and its latched fault equal the reference's.
- Physical facts of the engine alone (hypothesis, any floats): no voltage outside
  [V_min, V_max]; a latched fault ramps to bias in ramp_time x rate samples and holds it; the
  first fault wins.
- At the shipped settings (the configuration's defaults, the shipped table): each fault decision
  trips at its threshold and not one sample before, on inputs of the test's own and, for the
  decisions the loop's timing makes, on a clock of the test's own.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from beamctl.gains.defaults import default_table_path, paper_table_path
from beamctl.gains.ridethrough import RideThrough
from beamctl.gains.table import load_table
from beamctl.hal.base import Sample
from beamctl.rt import engine as e
from beamctl.rt.config import controller_config
from beamctl.rt.controller import Controller, ride_through_limits
from beamctl.rt.loop import ControlLoop
from beamctl.rt.safety import Fault, State, TransitionError
from tests.rt import reference_cycle as ref
from tests.rt.fakes import ScriptedHal
from tests.rt.reference_cycle import ReferenceController

# ---------------------------------------------------------------------------------------------
# gain tables

_TABLES: dict[str, object] = {}


def _ride_through(table, seed: int, steep: bool = False) -> RideThrough:
    """A ride-through analysis of random growth curves: a grid of 1..6, 8 and 12 samples,
    analysed at every grid load and at every midpoint, each curve rising from 1 by random
    factors (``steep``: to thousands within the grid, so that the live limit moves within it as
    the spreads do; else to about 20), answer budgets of 0.1 to 0.9 periods per grid load."""
    rng = np.random.default_rng(seed)
    loads = np.asarray(table.loads_n, dtype=float)
    analysed = np.sort(np.concatenate([loads, 0.5 * (loads[1:] + loads[:-1])]))
    grid = (1, 2, 3, 4, 5, 6, 8, 12)
    rise = rng.uniform(0.3, 1.6 if steep else 0.5, (1, 2, len(analysed), len(grid)))
    rise[..., 0] = rng.uniform(0.0, 0.2, (1, 2, len(analysed)))
    growth = np.exp(np.cumsum(rise, axis=3))
    budgets = rng.uniform(0.1, 0.9, len(loads))
    return RideThrough(confidence_sigma=float(rng.uniform(2.0, 5.0)), gap_grid_samples=grid,
                       loads_n=tuple(analysed), rigs=("a test's",), growth=growth,
                       max_extra_delay_samples_per_load=tuple(budgets), answer_budgets_periods=tuple(budgets),
                       delay_step_samples=0.05, delay_cap_samples=1.0, elapsed_s=0.0)


def table_variant(name: str):
    """The tables the comparison runs on (built once per session)."""
    if name not in _TABLES:
        if name == "paper":                 # integral LQR, 2500 Hz, 4 states, interpolated, as shipped
            t = load_table(paper_table_path())
        elif name == "paper-switched":      # the paper's gain switching with hysteresis
            t = load_table(paper_table_path())
            t = replace(t, schedule=replace(t.schedule, mode="paper"), ride_through=_ride_through(t, 4))
        elif name == "paper-growth":        # a ride-through whose live limit moves within its grid
            t = load_table(paper_table_path())
            t = replace(t, ride_through=_ride_through(t, 1, steep=True))
        elif name == "lqg":                 # the shipped LQG: 6000 Hz, 52 states, as shipped
            t = load_table(default_table_path())
        elif name == "lqg-growth":
            t = load_table(default_table_path())
            t = replace(t, ride_through=_ride_through(t, 2, steep=True))
        elif name == "lqg-switched":
            t = load_table(default_table_path())
            t = replace(t, schedule=replace(t.schedule, mode="paper", hysteresis_n=60.0),
                        ride_through=_ride_through(t, 5))
        else:
            raise KeyError(name)
        _TABLES[name] = t
    return _TABLES[name]


VARIANTS = ("paper", "paper-switched", "paper-growth", "lqg", "lqg-growth", "lqg-switched")
# sequences per table: 170 in all (the 52-state tables cost more per step in the reference). The
# test asserts that its sequences tripped every fault decision, reached both allocations' limits,
# raised every flag and moved across grid points; with these seeds that holds from the first 11
# sequences of each table (the shipped LQG's: 32), so each table runs at least twice that many
SEQUENCES = {"paper": 30, "paper-switched": 25, "paper-growth": 25, "lqg": 40, "lqg-growth": 25,
             "lqg-switched": 25}


LOAD = 2000.0           # a grid point of the shipped table
DEFLECTED = (2e-5, -1e-5, 1e-5, 4e-6)


def _sample(strains, load, sequence=0, rate=2500.0, missed=0):
    s = Sample()
    s.strains[:] = strains
    s.axial_load = load
    s.sequence = sequence
    s.timestamp = sequence / rate
    s.missed = missed
    return s


# ---------------------------------------------------------------------------------------------
# comparison

# Tolerance. The engine computes the same quantities in another order: numba may reassociate a
# dot product's sum into vector lanes and contract a * b + c into one fused operation (its
# FASTMATH), the interpolated products are (M_i s) + offset (S_i s) where the reference forms
# M_i + offset S_i first, and the engine may split a product by bending plane. Each such sum
# differs by a few ulps of its largest term, so a continuous quantity is compared relative to
# the largest magnitude of its group (the four forces, the six voltages, the n states: a
# component that is a near-cancellation of large terms carries the error of those terms), at
# 1e-9: far above the rounding that a few hundred steps of a stable compensator accumulate
# (measured: below 1e-12), far below any difference of semantics. Copies of inputs, codes,
# flags, counts and states must be equal.
RTOL = 1e-9
C = e.COL
EXACT_COLUMNS = ["time_s", "sequence", "state", "fault", "flags", "load_N", "step_us", "input_period_us",
                 "answer_age_us", "late_answers", "bridged", "operator_command",
                 "held_samples",
                 "strain_y1", "strain_z1", "strain_y2", "strain_z2"]
GROUPS = {
    "load_filtered": ["load_filtered_N"],
    "q": ["q_1y", "q_1z", "q_2y", "q_2z"],
    "u": ["force_y_A_N", "force_z_A_N", "force_y_B_N", "force_z_B_N"],
    "voltages": [f"voltage_{s}_V" for s in ("a1", "a2", "a3", "b1", "b2", "b3")],
    "scales": ["scale_A", "scale_B"],
    "xi": ["xi_1y", "xi_1z", "xi_2y", "xi_2z"],
    "applied": ["applied_force_y_A_N", "applied_force_z_A_N", "applied_force_y_B_N", "applied_force_z_B_N"],
    "spread_deflection": ["spread_deflection"],
    "spread_voltage": ["spread_voltage_V"],
    # interpolated in the growth's logarithm: numba's log and the C library's may differ in the
    # last bits
    "gap_limit": ["gap_limit_samples"],
}
assert sorted(EXACT_COLUMNS + sum(GROUPS.values(), [])) == sorted(e.RECORD_COLUMNS), "every column compared"


_EXACT = np.array([C[n] for n in EXACT_COLUMNS])
_GROUPED = np.array([C[n] for names in GROUPS.values() for n in names])
_GROUP_STARTS = np.cumsum([0] + [len(names) for names in GROUPS.values()])[:-1]
_GROUP_SIZES = np.array([len(names) for names in GROUPS.values()])


def _deviation(a: np.ndarray, b: np.ndarray, starts=None, sizes=None) -> np.ndarray:
    """|a - b| over the largest finite magnitude of the group (groups from ``starts``; one
    group if None): 0 where equal (NaN equals NaN), inf where one is not finite and they
    differ."""
    with np.errstate(invalid="ignore", over="ignore"):
        fa = np.where(np.isfinite(a), np.abs(a), 0.0)
        fb = np.where(np.isfinite(b), np.abs(b), 0.0)
        if starts is None:
            scale = np.full(a.shape, max(fa.max(initial=0.0), fb.max(initial=0.0)))
        else:
            largest = np.maximum(np.maximum.reduceat(fa, starts), np.maximum.reduceat(fb, starts))
            scale = np.repeat(largest, sizes)
        same = (a == b) | (np.isnan(a) & np.isnan(b))
        finite = np.isfinite(a) & np.isfinite(b)
        dev = np.where(finite, np.abs(a - b) / np.where(scale > 0.0, scale, 1.0), np.inf)
        return np.where(same, 0.0, dev)


def _differs(a, b, rtol: float = RTOL) -> np.ndarray:
    """Where ``a`` and ``b`` differ beyond ``rtol`` of their largest finite magnitude."""
    return _deviation(np.asarray(a, dtype=float), np.asarray(b, dtype=float)) > rtol


class Mismatch(AssertionError):
    pass


def compare(c: Controller, r: ReferenceController, where: str) -> float:
    """Assert that the engine's controller ``c`` and the reference ``r`` agree; returns the
    largest relative difference seen among the continuous quantities."""
    problems = []
    a, b = c.record, r.record
    x, y = a[_EXACT], b[_EXACT]
    for i in np.flatnonzero(~((x == y) | ((x != x) & (y != y)))):
        problems.append(f"{EXACT_COLUMNS[i]}: engine {x[i]!r}, reference {y[i]!r}")
    dev = _deviation(a[_GROUPED], b[_GROUPED], _GROUP_STARTS, _GROUP_SIZES)
    for i in np.flatnonzero(dev > RTOL):
        k = _GROUPED[i]
        problems.append(f"{e.RECORD_COLUMNS[k]}: engine {a[k]!r}, reference {b[k]!r}")
    dev_x = _deviation(c.compensator_state, r.x)
    if (dev_x > RTOL).any():
        k = int(np.argmax(dev_x))
        problems.append(f"x_c[{k}] (of {int((dev_x > RTOL).sum())} differing): engine "
                        f"{c.compensator_state[k]!r}, reference {r.x[k]!r}")
    # the let-go (no record column): within the same tolerance, in samples
    if abs(c.let_go - r.let_go) > RTOL * max(abs(r.let_go), 1.0):
        problems.append(f"let-go: engine {c.let_go!r}, reference {r.let_go!r}")
    worst = max(dev.max(), dev_x.max(initial=0.0))
    s, iv, fv = c.safety, c.iv, c.fv
    exact = {
        "state": (int(c.state), int(r.state)),
        "fault": (int(c.supervisor.fault), int(r.fault_code)),
        "saturated samples": (s.saturated_samples, r.saturated),
        "late streak": (s.late_streak, r.late_streak),
        "late answers": (s.late_answers, r.late_total),
        "bridged samples": (s.bridged_samples, r.bridged_total),
        "longest gap": (s.longest_gap, r.longest_gap),
        "overrun streak": (s.overrun_streak, r.overrun_streak),
        "longest overrun streak": (s.max_overrun_streak, r.max_overrun_streak),
        "steps since start": (c.steps_since_start, r.steps),
        "excitation rows": (c.excitation_index, r.excitation_index),
        "grid point": (int(iv[e.V_INDEX]), r.index),
        "at bias": (c.at_bias, r.at_bias),
        # the next step's anti-windup and saturation count read whether a support saturated
        "saturated A": (c.allocator.scale_a < 1.0, r.scale_a < 1.0),
        "saturated B": (c.allocator.scale_b < 1.0, r.scale_b < 1.0),
    }
    if r.fault_code != Fault.NONE:
        exact["fault time"] = (c.supervisor.fault_time, r.fault_time)
        exact["fault channel"] = (int(iv[e.V_FAULT_CHANNEL]), r.fault_channel)
    for what, (x, y) in exact.items():
        if not (x == y or (x != x and y != y)):
            problems.append(f"{what}: engine {x!r}, reference {y!r}")
    near = {"scale A": (c.allocator.scale_a, r.scale_a, 1.0),
            "scale B": (c.allocator.scale_b, r.scale_b, 1.0),
            "filtered load": (c.filtered_load_n, r.filtered, r.last_load),
            "offset above the grid point": (float(fv[e.X_OFFSET]), r.offset, r.last_load)}
    if r.fault_code != Fault.NONE:
        near["fault value"] = (float(fv[e.X_FAULT_VALUE]), r.fault_value, abs(r.fault_value))
        near["fault limit"] = (float(fv[e.X_FAULT_LIMIT]), r.fault_limit, abs(r.fault_limit))
    for what, (x, y, scale) in near.items():
        if not (x == y or (x != x and y != y) or abs(x - y) <= RTOL * scale):
            problems.append(f"{what}: engine {x!r}, reference {y!r}")
    if problems:
        raise Mismatch(f"{where}:\n  " + "\n  ".join(problems))
    return worst


# ---------------------------------------------------------------------------------------------
# randomised sequences


def _limits(table, config) -> tuple[float, float, float]:
    """The most a configuration may set: the gap and late-answer caps (the grid's top) and the
    largest answer budget in periods (``ride_through_limits``)."""
    limits = ride_through_limits(table, config)
    return limits.gap_cap, limits.late_cap, float(limits.budgets.max())


def _random_config(rng, rate: float, gap: int, late: int, budget: float) -> dict:
    """A configuration drawn for one sequence: both allocations, anti-windup on and off, short
    fade-in, ramp and saturation times (so that they end within a sequence), limits tightened
    below the table's, other voltage ranges, orientations, force constants, strain limits."""
    cfg: dict = {
        "allocation": str(rng.choice(["scale", "clip"])),
        "anti_windup": bool(rng.random() < 0.75),
        "start_ramp_time_s": float(rng.choice([0.0, rng.integers(1, 25) / rate])),
        "safety": {
            "ramp_time_s": int(rng.integers(1, 30)) / rate,
            "saturation_time_s": float(rng.integers(1, 40) if rng.random() < 0.6
                                       else rng.integers(40, 2000)) / rate,
            "overrun_streak": int(rng.integers(1, 6)),
            "strain_limit_fraction": float(rng.choice([0.5, 0.5, 0.2, 0.05])),
        },
    }
    s = cfg["safety"]
    if rng.random() < 0.4:
        s["stale_periods"] = int(rng.integers(0, gap + 1))
    if rng.random() < 0.4:
        s["late_answer_streak"] = int(rng.integers(0, late + 1))
    if rng.random() < 0.4 and budget > 0.05:
        s["answer_budget_periods"] = float(rng.uniform(0.05, budget))
    if rng.random() < 0.3:
        s["load_range_n"] = [float(rng.uniform(-300.0, -10.0)), float(rng.uniform(4100.0, 6000.0))]
    if rng.random() < 0.4:
        low = float(rng.uniform(-30.0, 20.0))
        high = float(rng.uniform(100.0, 150.0))
        cfg["actuators"] = {"min_voltage_v": low, "max_voltage_v": high,
                            "bias_voltage_v": float(rng.uniform(low + 10.0, high - 10.0)),
                            "force_constant_n_per_v": float(rng.uniform(1.0, 6.0)),
                            "orientation_deg": [float(rng.uniform(0, 360)), float(rng.uniform(0, 360))]}
    return cfg


# strain amplitudes of a sequence: noise, a beam held near straight, deflections that
# saturate the stacks (clipped below the strain limit)
AMPLITUDES = (3e-6, 3e-5, 3e-4, 1e-3, 2e-3)


class Pair:
    """The engine's controller and the reference side by side: every call goes to both, their
    outcome (carried out, refused, the value returned) must match and so must everything after
    it; the log of calls says how to get there."""

    def __init__(self, table, config, *, excitation=None, law=True, name="") -> None:
        self.c = Controller(table, config, excitation=excitation, law=law)
        self.r = ReferenceController(table, config, excitation=excitation, law=law)
        self.config, self.law, self.name = config, law, name
        self.log: list[str] = []
        self.worst = 0.0
        self.faults: set[int] = set()
        self.at_limit = {"scale": False, "clip": False}
        self.flags_seen = 0
        self.grid_points: set[int] = set()

    def _target(self, obj, what):
        if isinstance(obj, Controller) and what in ("cycle_overran", "cycle_on_time"):
            return getattr(obj.safety, what)        # the loop reports these to the controller's safety
        return getattr(obj, what)

    def set_excitation_enabled(self, value: bool) -> None:
        self.c.excitation_enabled = self.r.excitation_enabled = value
        self.log.append(f"excitation_enabled = {value}")

    def call(self, what: str, *args):
        self.log.append(f"{what}{_describe(args)}")
        outcome = []
        for obj in (self.c, self.r):
            try:
                result = self._target(obj, what)(*args)
            except TransitionError as exc:
                outcome.append("refused: " + ("not at bias" if "bias" in str(exc) else "state"))
            else:
                outcome.append(np.array(result) if what == "step" else ("carried out", result))
        engine, reference = outcome
        where = f"{self.name}, call {len(self.log)}: {self.log[-1]}"
        try:
            if what == "step":
                if _differs(engine, reference).any():
                    raise Mismatch(f"{where}: returned voltages: engine {engine}, reference {reference}")
            elif engine != reference:
                raise Mismatch(f"{where}: engine {engine}, reference {reference}")
            self.worst = max(self.worst, compare(self.c, self.r, where))
            self._facts(where)
        except Mismatch as exc:
            raise Mismatch(f"{exc}\n  the calls before it:\n    " + "\n    ".join(self.log[-12:])) from None
        if self.r.fault_code != Fault.NONE:
            self.faults.add(int(self.r.fault_code))
        self.flags_seen |= int(self.r.record[C["flags"]])
        self.grid_points.add(self.r.index)
        return engine

    def _facts(self, where: str) -> None:
        """The clamp, on both: every voltage within [V_min, V_max]."""
        a = self.config.actuators
        for who, v in (("engine", self.c.voltages), ("reference", self.r.voltages)):
            if not np.all((v >= a.min_voltage_v) & (v <= a.max_voltage_v)):
                raise Mismatch(f"{where}: {who} voltage outside [{a.min_voltage_v}, {a.max_voltage_v}]: {v}")
        if self.r.state == State.RUNNING and self.law:
            if self.config.allocation == "clip":
                self.at_limit["clip"] |= bool(np.any((self.r.target == a.max_voltage_v)
                                                     | (self.r.target == a.min_voltage_v)))
            else:
                self.at_limit["scale"] |= min(self.r.scale_a, self.r.scale_b) < 1.0


class Sequence(Pair):
    """A random sequence of calls on a pair, from a seed."""

    def __init__(self, variant: str, seed: int) -> None:
        self.variant, self.seed = variant, seed
        table = table_variant(variant)
        self.rate = table.design.sample_rate_hz
        rng = self.rng = np.random.default_rng(seed)
        gap, late, budget = _limits(table, controller_config())
        config = controller_config(_random_config(rng, self.rate, int(gap), int(late), budget))
        law = bool(rng.random() < 0.85)
        excitation = None
        if rng.random() < 0.3:
            rows = int(rng.integers(0, 40))
            excitation = rng.choice([-1.0, 1.0], (rows, 6)) * rng.uniform(0.0, 120.0, (1, 6))
        super().__init__(table, config, excitation=excitation, law=law,
                         name=f"Sequence({variant!r}, {seed}).run()")
        self.strain_limit = self.r.strain_limit
        self.sequence = 0
        self.loads = np.asarray(table.loads_n, dtype=float)
        self.load = float(rng.uniform(self.loads[0], self.loads[-1]))
        self.target_load = self.load
        if rng.random() < 0.2:      # an excursion: from near an end of the grid to beyond it
            low, high = self.loads[0], self.loads[-1]
            end = int(rng.integers(0, 2))
            self.load = float((low + 30.0, high - 30.0)[end])
            self.target_load = float((low - 200.0, high + 200.0)[end])
        self.direction = rng.standard_normal(4)
        self.amplitude = float(rng.choice(AMPLITUDES))
        self.late_link = False
        self.slow_cycles = False
        self.events = float(rng.choice([0.01, 0.03, 0.1, 0.3]))
        self.bent = rng.random() < 0.15    # a bent beam held: saturation, and nothing else happens
        if self.bent:
            self.amplitude, self.events = 2e-3, 0.0

    # -- the inputs ----------------------------------------------------------------------------------
    def _strains(self):
        rng = self.rng
        noise = 0.05 * self.amplitude * rng.standard_normal(4)
        bound = 0.9 * self.strain_limit
        return np.clip(self.amplitude * self.direction + noise, -bound, bound)

    def _next_load(self) -> float:
        rng = self.rng
        if rng.random() < 0.02:     # a new target: the filtered load sweeps across grid points
            low, high = self.loads[0], self.loads[-1]
            self.target_load = float(rng.uniform(low - 400.0, high + 300.0) if rng.random() < 0.1
                                     else rng.uniform(low, high))
        self.load += 0.05 * (self.target_load - self.load)
        return self.load + float(rng.normal(0.0, 3.0))

    def sample(self, strains=None, load=None, missed=0):
        self.sequence += 1 + missed
        return _sample(self._strains() if strains is None else strains,
                       self._next_load() if load is None else load, self.sequence, self.rate, missed)

    def bad_sample(self):
        rng = self.rng
        strains, load = self._strains(), self._next_load()
        kind = int(rng.integers(0, 8))
        channel = int(rng.integers(0, 4))
        sign = float(rng.choice([-1.0, 1.0]))
        if kind == 0:
            strains[channel] = rng.choice([np.nan, np.inf, -np.inf])
        elif kind == 1:
            strains[channel] = sign * self.strain_limit * float(rng.uniform(1.0 + 1e-12, 2.0))
        elif kind == 2:
            strains[channel] = sign * self.strain_limit             # at the limit: allowed
        elif kind == 3:
            load = float(rng.choice([np.nan, np.inf, -np.inf]))
        elif kind == 4:
            low, high = self.config.safety.load_range_n
            load = float(rng.choice([low - rng.uniform(1e-9, 100.0), high + rng.uniform(1e-9, 100.0)]))
        elif kind == 5:
            low, high = self.config.safety.load_range_n
            load = float(rng.choice([low, high]))                   # at the range's ends: allowed
        elif kind == 6:
            strains[:] = np.nan
            load = np.nan
        else:
            strains[channel] = sign * self.strain_limit * 3.0
            load = np.inf
        return self.sample(strains, load)

    # -- one sequence ---------------------------------------------------------------------------
    def run(self, steps: int | None = None) -> Sequence:
        rng = self.rng
        first = self.sample()
        self.call("arm", first)
        if rng.random() < 0.1:
            for _ in range(int(rng.integers(1, 20))):   # armed: observed, not controlled
                self.call("step", self.sample())
        self.call("start")
        for _ in range(int(rng.integers(150, 350)) if steps is None else steps):
            self.one(rng)
        return self

    def one(self, rng) -> None:
        # one sample in order, or (at the sequence's rate of events) a gap, a silence, a bad
        # sample or an operator's command
        p = 1.0 if rng.random() > self.events else rng.random()
        if not self.bent:
            if rng.random() < 0.01:
                self.amplitude = float(rng.choice(AMPLITUDES))
                self.direction = rng.standard_normal(4)
            if rng.random() < 0.01:
                self.late_link = not self.late_link
            if rng.random() < 0.01:
                self.slow_cycles = not self.slow_cycles
        with_sample = True
        if p < 0.25:
            self.call("step", self.sample())
        elif p < 0.45:
            gap = int(self.r.let_go)
            missed = int(rng.choice([rng.integers(1, gap + 1) if gap else 1, rng.integers(gap + 1, gap + 4)]))
            self.call("step", self.sample(missed=missed))
        elif p < 0.65:
            with_sample = False
            gap = int(self.r.let_go)
            silent = None if rng.random() < 0.5 else float(
                rng.choice([rng.uniform(0.0, gap + 2.5), gap + 1.0, gap + 1.0 - 1e-9, -1.0]))
            self.call("step", None, silent)
        elif p < 0.8:
            self.call("step", self.bad_sample())
        elif p < 1.0:
            what = int(rng.integers(0, 9))
            if what == 0:
                self.call("request_stop")
            elif what == 1:
                self.call("fault", Fault(int(rng.choice([Fault.OPERATOR, Fault.HAL_ERROR]))))
            elif what == 2:
                self.call("rearm", self.sample() if rng.random() < 0.8 else None)
            elif what == 3:
                self.call("start")
            elif what == 4:
                self.call("arm", self.sample())
            elif what == 5:
                self.set_excitation_enabled(not self.r.excitation_enabled)
            elif what == 6 and rng.random() < 0.2:
                self.call("emergency_ramp_begin")
                for _ in range(int(rng.integers(1, 6))):
                    self.call("emergency_ramp_advance")
            else:
                self.call("step", self.sample())
        else:
            self.call("step", self.sample())
        # the loop's reports after the cycle: the answer's age, the cycle's timing
        if with_sample and rng.random() < 0.8:
            budget, period = self.r.answer_budget_s, self.r.period_s
            late = budget + period * float(rng.uniform(1e-6, 1.5))
            if self.late_link:
                age = late
            elif self.bent:
                age = budget
            else:
                age = float(rng.choice([budget * rng.uniform(0.0, 1.0), budget, np.nan] if rng.random() < 0.95
                                       else [late]))
            self.call("answer_sent", age)
        if self.slow_cycles or (rng.random() < 0.02 and not self.bent):
            self.call("cycle_overran")
        elif rng.random() < 0.5:
            self.call("cycle_on_time")
        # a latched fault or a stop, once at bias: an operator re-arms and starts again
        if self.r.state in (State.FAULT, State.STOPPED) and self.r.at_bias and rng.random() < 0.2:
            # on a bad sample now and then: a start on non-finite strains faults at once
            self.call("rearm", self.sample() if rng.random() < 0.9 else self.bad_sample())
            self.call("start")
            self.late_link = self.slow_cycles = False


def _describe(args) -> str:
    parts = []
    for a in args:
        if isinstance(a, Sample):
            parts.append(f"Sample(seq={a.sequence}, missed={a.missed}, strains={a.strains.tolist()}, "
                         f"load={a.axial_load!r})")
        else:
            parts.append(repr(a))
    return "(" + ", ".join(parts) + ")"


# the fault decisions every table's sequences must have exercised (the others come from outside)
DECIDED = {Fault.STRAIN_NOT_FINITE, Fault.STRAIN_OUT_OF_RANGE, Fault.LOAD_NOT_FINITE,
           Fault.LOAD_OUT_OF_SENSOR_RANGE, Fault.LOAD_OUT_OF_TABLE_RANGE, Fault.STALE_INPUT,
           Fault.PERSISTENT_SATURATION, Fault.LATE_ANSWERS, Fault.OVERRUN_STREAK}


@pytest.mark.parametrize("variant", VARIANTS)
def test_the_engine_runs_the_reference_cycle_on_random_sequences(variant):
    """Every call, the engine and the reference agree on every column of the record, the
    voltages returned, the compensator state, the counts and the latched fault (module
    ``compare``). The sequences exercise every fault decision and both allocations at their
    limits, so a decision or a clamp missing from either side is seen."""
    faults: set[int] = set()
    at_limit = {"scale": False, "clip": False}
    flags, grid_points, switches = 0, set(), 0
    worst = 0.0
    for k in range(SEQUENCES[variant]):
        seq = Sequence(variant, 1000 * VARIANTS.index(variant) + k).run()
        faults |= seq.faults
        for mode, hit in seq.at_limit.items():
            at_limit[mode] |= hit
        flags |= seq.flags_seen
        grid_points |= seq.grid_points
        switches += len(seq.grid_points) > 1
        worst = max(worst, seq.worst)
    # what the sequences went through, so that a decision or a clamp missing is seen
    missing = sorted(Fault(f).name for f in DECIDED - faults)
    assert not missing, f"the sequences never tripped {missing}: they test nothing about them"
    assert at_limit == {"scale": True, "clip": True}, f"allocations that reached the limits: {at_limit}"
    expected = dict(e.FLAG_NAMES)
    unseen = [name for bit, name in expected.items() if not flags & bit]
    assert not unseen, f"flags never raised: {unseen}"
    assert len(grid_points) > 10 and switches > 10, "the schedule moved across grid points"
    assert worst < RTOL


def test_the_reference_names_the_engine_s_codes():
    """The reference's flags and the state and fault codes it records are the engine's."""
    assert (ref.SATURATED_A, ref.SATURATED_B, ref.INTEGRATOR_HELD, ref.LOAD_OUT_OF_TABLE, ref.NO_NEW_SAMPLE,
            ref.FADING_IN, ref.RAMPING_TO_BIAS, ref.BRIDGED) == (
        e.FLAG_SATURATED_A, e.FLAG_SATURATED_B, e.FLAG_INTEGRATOR_HELD, e.FLAG_LOAD_OUT_OF_TABLE,
        e.FLAG_NO_NEW_SAMPLE, e.FLAG_FADING_IN, e.FLAG_RAMPING_TO_BIAS, e.FLAG_BRIDGED)
    assert ref.ROUNDING == e.SPAN_ROUNDING


def test_a_bridge_catches_the_compensator_up_and_holds_the_integral():
    """A gap of the sequence within the live limit: the engine flags the sample BRIDGED and
    counts it; the compensator makes one step per sample missed on the newest strains and the
    forces the stacks held (x_c <- A x_c + B y + E u_applied), the integral stays, then the
    newest sample enters the normal step: the same state and voltages as a twin fed the same
    samples without the gap whose compensator was stepped so by the test, to rounding."""
    for variant in ("paper-switched", "lqg-growth"):
        table = table_variant(variant)
        rate = table.design.sample_rate_hz
        config = controller_config({"start_ramp_time_s": 0.0})
        pair, twin = Pair(table, config, name=variant), Pair(table, config, name=variant + " twin")
        strains = np.array([1e-5, -5e-6, 4e-6, 2e-6])
        for p in (pair, twin):
            p.call("arm", _sample(strains, 1234.0, 1, rate))
            p.call("start")
            for k in range(2, 50):
                p.call("step", _sample(strains * (1 + 0.01 * k), 1234.0, k, rate))
        gap = int(pair.c.gap_limit)
        assert 0 < gap <= e.CATCH_UP_SAMPLES, "a table whose loop rides through a gap, caught up in full"
        m = twin.r.matrices()           # the load is constant: the schedule's point does not move
        x = twin.r.x.copy()
        for _ in range(gap):
            x = m.a @ x + m.b @ strains + m.e @ twin.r.applied
        twin.c.compensator_state[:] = x
        twin.r.x[:] = x
        pair.call("step", _sample(strains, 1234.0, 50 + gap, rate, missed=gap))
        twin.call("step", _sample(strains, 1234.0, 50, rate))
        c = pair.c
        assert c.state == State.RUNNING and int(c.record[e.I_BRIDGED]) == gap
        assert c.record[e.I_HELD] == gap and c.safety.longest_gap == gap
        assert int(c.record[e.I_FLAGS]) & e.FLAG_BRIDGED and c.safety.bridged_samples == gap
        np.testing.assert_allclose(c.xi, twin.c.xi, rtol=1e-12, err_msg="the integral held over the gap")
        np.testing.assert_allclose(c.compensator_state, twin.c.compensator_state, rtol=1e-9, atol=1e-18,
                                   err_msg="the compensator caught up on the gap")
        np.testing.assert_allclose(c.voltages, twin.c.voltages, rtol=1e-9)


# ---------------------------------------------------------------------------------------------
# physical facts of the engine, whatever it is fed

_any = st.floats(allow_nan=True, allow_infinity=True)
_STRAIN_LIMIT = 0.5 * 0.006398416886543535
_strain = st.one_of(_any, st.floats(-1.2 * _STRAIN_LIMIT, 1.2 * _STRAIN_LIMIT),
                    st.floats(-2e-4, 2e-4), st.sampled_from([0.0, _STRAIN_LIMIT, -_STRAIN_LIMIT]))
_load = st.one_of(_any, st.floats(-300.0, 5200.0), st.floats(0.0, 4000.0))
_sample_op = st.tuples(st.just("sample"), st.tuples(_strain, _strain, _strain, _strain), _load,
                       st.one_of(st.just(0), st.integers(0, 10)))
# a bent beam held for a while: the integral winds up until the stacks saturate
_bent = st.floats(-0.9 * _STRAIN_LIMIT, 0.9 * _STRAIN_LIMIT)
_hold_op = st.tuples(st.just("hold"), st.tuples(_bent, _bent, _bent, _bent), st.floats(0.0, 4000.0),
                     st.integers(20, 400))
_op = st.one_of(
    _sample_op, _sample_op, _sample_op, _hold_op,
    st.tuples(st.just("none"), st.one_of(st.none(), st.floats(-2.0, 12.0))),
    st.tuples(st.just("answer"), st.one_of(_any, st.floats(0.0, 4e-4))),
    st.tuples(st.just("overran")), st.tuples(st.just("on_time")),
    st.tuples(st.just("stop")),
    st.tuples(st.just("fault"), st.sampled_from([Fault.OPERATOR, Fault.HAL_ERROR])),
    st.tuples(st.just("rearm")), st.tuples(st.just("start")),
)
_config = st.fixed_dictionaries({
    "allocation": st.sampled_from(["scale", "clip"]),
    "anti_windup": st.booleans(),
    "start_ramp_time_s": st.sampled_from([0.0, 0.002]),
    "safety": st.fixed_dictionaries({"ramp_time_s": st.sampled_from([0.0004, 0.004, 0.01]),
                                     "saturation_time_s": st.sampled_from([0.002, 0.02, 1.0]),
                                     "overrun_streak": st.integers(1, 4)}),
    "actuators": st.sampled_from([{}, {"min_voltage_v": 10.0, "max_voltage_v": 140.0, "bias_voltage_v": 60.0},
                                  {"min_voltage_v": -20.0, "max_voltage_v": 120.0, "bias_voltage_v": 50.0,
                                   "force_constant_n_per_v": 1.5}]),
})


class Watch:
    """Calls on a controller of the engine, checked after each: every voltage in [V_min, V_max];
    a latched fault stays as it was latched (the first wins) until a re-arm; once it latched,
    the voltages follow the linear ramp from where they were to bias in ramp_time x rate cycles,
    then hold bias (a stop's ramp likewise)."""

    def __init__(self, c: Controller) -> None:
        self.c = c
        self.config = c.config
        self.rate = c.sample_rate_hz
        self.n = max(1, round(self.config.safety.ramp_time_s * self.rate))
        self.bias = self.config.actuators.bias_voltage_v
        self.latched = None             # (fault, time, value, limit, channel)
        self.ramp = None                # [voltages it started from, ramp steps taken]
        self.sequence = 0
        self.ramps_checked = 0

    def sample(self, strains=DEFLECTED, load=LOAD, missed=0) -> Sample:
        self.sequence = (self.sequence + 1 + missed) % 2**32     # a source's counter wraps
        return _sample(strains, load, self.sequence, self.rate, missed)

    def step(self, strains=DEFLECTED, load=LOAD, missed=0) -> np.ndarray:
        """A new sample."""
        return self.do("step", self.sample(strains, load, missed))

    def do(self, what: str, *args):
        """``what`` on the controller (the loop's reports on its safety); a refused command
        changes nothing. Returns what the call returned."""
        c = self.c
        before = c.voltages.copy()
        target = c.safety if what in ("cycle_overran", "cycle_on_time") else c
        try:
            result = getattr(target, what)(*args)
        except TransitionError:
            result = None
        self.check(before, what, int(c.record[e.I_FLAGS]) if what == "step" else 0)
        return result

    def check(self, before: np.ndarray, what: str, flags: int = 0) -> None:
        c, a = self.c, self.config.actuators
        v = c.voltages
        assert np.all((v >= a.min_voltage_v) & (v <= a.max_voltage_v)), f"{what}: voltages {v}"
        state, fault = c.state, c.supervisor.fault
        if fault != Fault.NONE:
            now = (fault, c.supervisor.fault_time, c.supervisor.detail)
            if self.latched is None:
                self.latched = now
            else:
                assert _same(now, self.latched), f"{what}: the latched fault {self.latched} became {now}"
        else:
            assert self.latched is None or state in (State.ARMED, State.RUNNING), what
            self.latched = None
        if self.ramp is None and state in (State.FAULT, State.STOPPING, State.STOPPED):
            if what == "step" and flags & e.FLAG_RAMPING_TO_BIAS:
                self.ramp = [before, 0]                 # begun in this cycle, before its step
            else:
                self.ramp = [v.copy(), 0]               # the next cycle takes its first step
                return
        if self.ramp is not None and state in (State.ARMED, State.RUNNING):
            self.ramp = None                            # re-armed
        if self.ramp is not None and what == "step":
            start, k = self.ramp
            k += 1
            self.ramp[1] = k
            if k >= self.n:
                np.testing.assert_array_equal(v, self.bias, err_msg=f"ramp step {k} of {self.n}: at bias")
                self.ramps_checked += k == self.n
            else:
                expected = self.bias + (start - self.bias) * (1.0 - k / self.n)
                np.testing.assert_allclose(v, expected, rtol=1e-12, atol=1e-12 * a.max_voltage_v,
                                           err_msg=f"ramp step {k} of {self.n}")

    def ramp_to_bias(self, with_samples: bool = True) -> None:
        """After a fault: cycles until the ramp has reached bias (checked step by step), then a
        few more that hold it."""
        assert self.ramp is not None and self.c.state == State.FAULT, self.c.supervisor.reason()
        before = self.ramps_checked
        for _ in range(self.n - self.ramp[1] + 5):
            if with_samples:
                self.step()
            else:
                self.do("step", None)
        assert self.ramps_checked == before + 1 and self.c.at_bias

    def run(self, ops) -> None:
        """A start, then ``ops`` (hypothesis' operations)."""
        self.do("arm", self.sample((0.0, 0.0, 0.0, 0.0), 1500.0))
        self.do("start")
        for op in ops:
            kind = op[0]
            if kind == "sample":
                _, strains, load, missed = op
                self.step(strains, load, missed)
            elif kind == "hold":
                _, strains, load, count = op
                for _ in range(count):
                    self.step(strains, load)
            elif kind == "none":
                self.do("step", None, op[1])
            elif kind == "answer":
                self.do("answer_sent", op[1])
            elif kind == "overran":
                self.do("cycle_overran")
            elif kind == "on_time":
                self.do("cycle_on_time")
            elif kind == "stop":
                self.do("request_stop")
            elif kind == "fault":
                self.do("fault", op[1])
            elif kind == "rearm":
                self.do("rearm", self.sample((0.0, 0.0, 0.0, 0.0), 1500.0))
            elif kind == "start":
                self.do("start")


def _same(a, b) -> bool:
    return all(x == y or (x != x and y != y) for x, y in zip(a, b, strict=True))


@settings(max_examples=150, suppress_health_check=[HealthCheck.too_slow])
@given(config=_config, ops=st.lists(_op, min_size=1, max_size=120),
       table=st.sampled_from(["paper", "paper-growth"]), law=st.booleans(),
       excitation=st.sampled_from([None, 125.0, -125.0]))
def test_no_voltage_leaves_the_range_a_fault_ramps_to_bias_and_the_first_wins(config, ops, table, law,
                                                                              excitation):
    """Whatever floats arrive (NaN, infinities, huge values, gaps, silences, late answers, stops
    and faults in any order), with the law or open loop, with excitation rows that would drive
    the stacks far beyond: the voltages never leave [V_min, V_max] (150 V at most), a latched
    fault never changes until a re-arm, and from it the voltages ramp linearly to bias in
    ramp_time x rate cycles, then hold bias."""
    rows = None if excitation is None else np.full((20, 6), excitation) * np.sign(np.arange(-10, 10))[:, None]
    Watch(Controller(table_variant(table), controller_config(config), excitation=rows, law=law)).run(ops)


@settings(max_examples=300)
@given(u=st.tuples(_any, _any, _any, _any), mode=st.sampled_from(["scale", "clip"]),
       actuators=st.sampled_from([{}, {"min_voltage_v": 10.0, "max_voltage_v": 140.0,
                                       "bias_voltage_v": 60.0}]))
def test_the_allocation_never_leaves_the_voltage_range(u, mode, actuators):
    """The engine's allocation (both supports) of any forces: voltages within [V_min, V_max]
    exactly, the delivered fractions within [0, 1]."""
    from beamctl.rt.allocation import Allocator

    config = controller_config({"allocation": mode, "actuators": actuators})
    alloc = Allocator(config.actuators, mode)
    v = np.zeros(6)
    alloc.allocate(np.array(u), v)
    a = config.actuators
    assert np.all((v >= a.min_voltage_v) & (v <= a.max_voltage_v)), (u, v)
    assert 0.0 <= alloc.scale_a <= 1.0 and 0.0 <= alloc.scale_b <= 1.0


def test_a_saturated_scale_allocation_stays_in_range_to_the_last_ulp():
    """Forces far beyond the stacks' in every direction: the scaled voltages span the range
    exactly to its ends, never an ulp beyond (the clamp holds the rounding of the centring)."""
    from beamctl.rt.allocation import Allocator

    for actuators in ({}, {"min_voltage_v": 10.0, "max_voltage_v": 140.0, "bias_voltage_v": 60.0},
                      {"min_voltage_v": -20.0, "max_voltage_v": 120.3, "bias_voltage_v": 50.0}):
        a = controller_config({"actuators": actuators}).actuators
        alloc = Allocator(a, "scale")
        v = np.zeros(6)
        for angle in np.linspace(0.0, 2.0 * np.pi, 2000):
            for magnitude in (1e3, 1e4, 3.3e5):
                f = magnitude * np.array([np.cos(angle), np.sin(angle), np.sin(3 * angle), np.cos(angle)])
                alloc.allocate(f, v)
                assert np.all((v >= a.min_voltage_v) & (v <= a.max_voltage_v)), (f, v)


# ---------------------------------------------------------------------------------------------
# the thresholds at the shipped settings

@pytest.fixture(scope="module")
def shipped():
    """The shipped table and the configuration's defaults, with the answer budget they give at
    LOAD (the table's, per grid interval the lesser of its two ends): (table, config, answer
    budget in s). The gap and late-answer limits are live: read from the controller."""
    table = load_table(default_table_path())
    config = controller_config()
    budgets = ride_through_limits(table, config).budgets
    i = bisect.bisect_right(list(table.loads_n), LOAD) - 1
    budget = min(budgets[i], budgets[min(i + 1, len(budgets) - 1)])
    return table, config, budget / table.design.sample_rate_hz


def _tolerated(shipped) -> float:
    """The latest answer (s) the loop tolerates at LOAD: the design's delay plus twice the budget's
    margin over it (the extra delay the table's delay search found the loop stable with)."""
    table, _, budget = shipped
    period = 1.0 / table.design.sample_rate_hz
    d = table.design.io.delay_samples * period
    return max(budget, d + 2.0 * (budget - d))


def _running(shipped, steps=50) -> Watch:
    """A controller of the shipped settings running at LOAD, watched (``Watch``); its live
    limits at least one sample (a beam held still at 2000 N rides through gaps)."""
    c = Controller(shipped[0], shipped[1])
    w = Watch(c)
    w.do("arm", w.sample())
    w.do("start")
    for _ in range(steps):
        w.step()
    assert c.state == State.RUNNING
    assert c.safety.gap_limit == int(c.let_go) >= int(c.gap_limit) >= 1 and c.safety.late_limit >= 1
    assert c.safety.answer_budget_s == pytest.approx(shipped[2], rel=1e-15)
    return w


def _faulted(w: Watch, fault: Fault, with_samples: bool = True) -> None:
    """``fault`` latched; the voltages then ramp to bias in ramp_time x rate cycles and hold it."""
    assert w.c.supervisor.fault == fault, w.c.supervisor.reason()
    w.ramp_to_bias(with_samples)
    assert w.c.supervisor.fault == fault, "the first fault stays"


def test_the_let_go_is_ridden_through_and_one_more_missing_sample_faults(shipped):
    w = _running(shipped)
    gap = int(w.c.let_go)
    w.step(missed=gap)
    assert w.c.state == State.RUNNING and w.c.safety.longest_gap == gap
    w.step()
    w.step(missed=int(w.c.let_go) + 1)
    _faulted(w, Fault.STALE_INPUT)


def test_a_gap_of_any_length_faults(shipped):
    w = _running(shipped, steps=5)
    w.step(missed=2**63 - 1)
    assert w.c.supervisor.fault == Fault.STALE_INPUT


@pytest.mark.parametrize("measured", [False, True])
def test_silence_faults_once_the_samples_due_exceed_the_gap_limit(shipped, measured):
    """Counted one period per call, or measured in periods: floor(silence) > gap limit."""
    w = _running(shipped)
    gap = w.c.safety.gap_limit
    if measured:
        w.do("step", None, math.nextafter(gap + 1.0, 0.0))
    else:
        for _ in range(gap):
            w.do("step", None)
    assert w.c.state == State.RUNNING
    w.do("step", None, gap + 1.0 if measured else None)
    _faulted(w, Fault.STALE_INPUT, with_samples=False)


@pytest.mark.parametrize("silent", [math.inf, 1e30, math.nan])
def test_an_endless_silence_faults(shipped, silent):
    w = _running(shipped, steps=5)
    w.do("step", None, silent)
    assert w.c.supervisor.fault == Fault.STALE_INPUT


def test_the_late_answer_limit_is_ridden_through_and_one_more_faults(shipped):
    """At a limit that holds still (configured below the live one)."""
    table, _, budget = shipped
    late = 3
    c = Controller(table, controller_config({"safety": {"late_answer_streak": late}}))
    w = Watch(c)
    w.do("arm", w.sample())
    w.do("start")
    for _ in range(50):
        w.step()
    assert c.safety.late_limit == late
    for _ in range(late):
        w.step()
        w.do("answer_sent", math.nextafter(budget, 1.0))
    w.step()
    w.do("answer_sent", budget)                 # on the budget: on time, the streak ends
    assert w.c.state == State.RUNNING and w.c.safety.late_streak == 0
    tolerated = _tolerated(shipped)
    assert tolerated > budget, "the shipped table's loop tolerates more delay than its budget at LOAD"
    for _ in range(3 * late):                   # late, within what the loop tolerates: no stall
        w.step()
        w.do("answer_sent", tolerated)
    assert w.c.state == State.RUNNING and w.c.safety.late_streak == 0, (
        "answers late within the delay the loop tolerates counted as a stall")
    late_age = tolerated + 0.25 * w.c.period_s
    for _ in range(late):
        w.step()
        w.do("answer_sent", late_age)
    assert w.c.state == State.RUNNING and w.c.safety.late_streak == late
    w.step()
    w.do("answer_sent", late_age)
    _faulted(w, Fault.LATE_ANSWERS)


def test_the_overrun_streak_faults_at_its_length(shipped):
    limit = shipped[1].safety.overrun_streak
    w = _running(shipped)
    for _ in range(limit - 1):
        w.do("cycle_overran")
        w.step()
    w.do("cycle_on_time")
    for _ in range(limit - 1):
        w.do("cycle_overran")
        w.step()
    assert w.c.state == State.RUNNING
    w.do("cycle_overran")
    _faulted(w, Fault.OVERRUN_STREAK)


def test_persistent_saturation_faults_after_saturation_time_of_saturated_samples(shipped):
    """A bent beam the stacks cannot straighten: the fault comes at the saturation_time x rate-th
    saturated sample in a row, not one before."""
    table, config = shipped[0], shipped[1]
    limit = round(config.safety.saturation_time_s * table.design.sample_rate_hz)
    w = _running(shipped)
    c = w.c
    streak = 0
    bent = (1.2e-3, -8e-4, 1.0e-3, -6e-4)
    for _ in range(3 * limit):
        w.step(bent)
        saturated = int(c.record[e.I_FLAGS]) & (e.FLAG_SATURATED_A | e.FLAG_SATURATED_B)
        streak = streak + 1 if saturated else 0
        if c.state != State.RUNNING:
            break
    assert streak == limit, f"faulted after {streak} saturated samples in a row, limit {limit}"
    _faulted(w, Fault.PERSISTENT_SATURATION)


@pytest.mark.parametrize("channel", range(4))
def test_a_strain_on_the_limit_passes_and_the_next_float_beyond_faults(shipped, channel):
    w = _running(shipped)
    beam = shipped[0].model_parameters.beam
    limit = w.c.safety.strain_limit
    assert limit == pytest.approx(shipped[1].safety.strain_limit_fraction * beam.proportional_limit
                                  / beam.youngs_modulus, rel=1e-15)
    strains = np.zeros(4)
    for sign in (1.0, -1.0):
        strains[channel] = sign * limit
        w.step(strains)
        assert w.c.state == State.RUNNING, f"strain {channel} = {sign * limit} on the limit"
    strains[channel] = math.nextafter(-limit, -1.0)
    w.step(strains)
    assert int(w.c.iv[e.V_FAULT_CHANNEL]) == channel
    _faulted(w, Fault.STRAIN_OUT_OF_RANGE)


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_a_non_finite_strain_or_load_faults(shipped, value):
    w = _running(shipped)
    w.step((0.0, 0.0, value, 0.0))
    _faulted(w, Fault.STRAIN_NOT_FINITE)
    w = _running(shipped)
    w.step(load=value)
    _faulted(w, Fault.LOAD_NOT_FINITE)


@pytest.mark.parametrize("end", [0, 1])
def test_a_load_on_the_sensor_range_s_end_passes_and_beyond_faults(shipped, end):
    low, high = shipped[1].safety.load_range_n
    edge = (low, high)[end]
    beyond = math.nextafter(edge, (-math.inf, math.inf)[end])
    w = _running(shipped)
    w.step(load=edge)
    assert w.c.state == State.RUNNING
    w.step(load=beyond)
    _faulted(w, Fault.LOAD_OUT_OF_SENSOR_RANGE)


@pytest.mark.parametrize("load", [4400.0, -150.0])
def test_the_filtered_load_leaving_the_table_faults_on_the_sample_it_leaves(shipped, load):
    """A load in the sensor's range but beyond the table's grid: the filtered load approaches it
    and the fault comes on the first sample whose filtered load is off the grid."""
    table = shipped[0]
    first, last = float(table.loads_n[0]), float(table.loads_n[-1])
    w = _running(shipped)
    filtered = []
    for _ in range(20000):
        w.step(load=load)
        filtered.append(float(w.c.record[e.I_LOAD_FILTERED]))
        if w.c.state != State.RUNNING:
            break
    assert not first <= filtered[-1] <= last and first <= filtered[-2] <= last
    _faulted(w, Fault.LOAD_OUT_OF_TABLE_RANGE)


def test_a_start_on_non_finite_strains_faults(shipped):
    """Armed, the controller observes without checking; a start on the latest sample's
    non-finite strains faults at once, before any control."""
    w = Watch(Controller(shipped[0], shipped[1]))
    w.do("arm", w.sample())
    w.step()
    w.step((0.0, np.nan, 0.0, 0.0))
    assert w.c.state == State.ARMED
    w.do("start")
    _faulted(w, Fault.STRAIN_NOT_FINITE)


def test_the_first_fault_wins(shipped):
    """Causes in one sample: the strains are checked before the load, channel by channel, and
    before the gap; later causes of any kind leave the latched fault, its time and its detail."""
    w = _running(shipped)
    gap = int(w.c.let_go)
    w.step((0.0, 1e-2, np.nan, 0.0), load=np.inf, missed=gap + 1)
    assert int(w.c.iv[e.V_FAULT_CHANNEL]) == 1
    latched = (w.c.supervisor.fault_time, w.c.supervisor.detail)
    w.do("fault", Fault.HAL_ERROR)
    w.do("cycle_overran")
    w.do("answer_sent", 1.0)
    w.do("step", None, 100.0)
    w.step(load=np.nan)
    assert (w.c.supervisor.fault_time, w.c.supervisor.detail) == latched
    _faulted(w, Fault.STRAIN_OUT_OF_RANGE)
    w = _running(shipped)
    w.step(load=-1e4, missed=gap + 1)
    _faulted(w, Fault.LOAD_OUT_OF_SENSOR_RANGE)
    w = _running(shipped)
    w.do("request_stop")
    w.step()
    w.do("fault", Fault.OPERATOR)
    assert w.c.supervisor.fault == Fault.OPERATOR, "a fault during a stop's ramp latches"
    w.ramp_to_bias()                # the stop's ramp goes on, not begun again


# ---------------------------------------------------------------------------------------------
# the decisions the loop's timing makes, on a clock of the test's own

class FakeClock:
    """Time that passes only when asked: ``tick`` per reading, and what a sleep asks for."""

    def __init__(self, tick: float = 0.0) -> None:
        self.now = 0.0
        self.tick = tick

    def __call__(self) -> float:
        self.now += self.tick
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += max(seconds, 0.0)


def test_the_loop_faults_on_the_overrun_that_completes_the_streak(shipped):
    """Timer pacing: cycles whose work overruns the period. A streak one short of the limit,
    then a cycle on time, then a full streak: the fault latches after its last overrun."""
    table, config = shipped[0], shipped[1]
    limit = config.safety.overrun_streak
    clock = FakeClock(tick=1e-7)
    c = Controller(table, replace(config, pacing="timer"))
    hal = ScriptedHal(table.design.sample_rate_hz, [], default=(DEFLECTED, LOAD), sleep=clock.sleep).open()
    loop = ControlLoop(c, hal, clock=clock, sleep=clock.sleep, max_cycles=400)
    slow = set(range(100, 100 + limit - 1)) | set(range(200, 200 + limit))
    seen = {}

    def on_cycle(lp):
        seen[lp.cycles] = (c.state, c.safety.overrun_streak)
        if lp.cycles in slow:
            clock.now += 1.5 * lp.period_s        # this cycle's work overran its deadline

    loop.on_cycle = on_cycle
    result = loop.run(require_rt=False, acquire_rt=False)
    assert result.fault == Fault.OVERRUN_STREAK.name, result.reason
    assert seen[100 + limit - 1] == (State.RUNNING, limit - 1)
    assert seen[100 + limit] == (State.RUNNING, 0), "the cycle on time ended the streak"
    assert seen[200 + limit - 1] == (State.RUNNING, limit - 1), "the last overrun's cycle ran before it"
    assert seen[200 + limit][0] == State.FAULT


def test_the_loop_faults_on_the_late_answer_beyond_the_limit(shipped):
    """Sample pacing: the HAL reports each answer's age; from sample 100 on every answer is
    later than the loop tolerates. The fault latches on the (late limit + 1)-th of them (a limit
    configured below the live one, so that it holds still)."""
    table, _, budget = shipped
    tolerated = _tolerated(shipped)
    late = 3
    config = controller_config({"safety": {"late_answer_streak": late}})
    clock = FakeClock()
    c = Controller(table, config)
    late_age = tolerated + 0.25 * c.period_s
    hal = ScriptedHal(table.design.sample_rate_hz, [], default=(DEFLECTED, LOAD), sleep=clock.sleep,
                      answer_ages_s=lambda seq: late_age if seq >= 100 else budget).open()
    states = {}

    def on_cycle(lp):
        states[hal.sequence] = (c.state, c.safety.late_streak)

    loop = ControlLoop(c, hal, clock=clock, sleep=clock.sleep, on_cycle=on_cycle, max_cycles=1000)
    result = loop.run(require_rt=False, acquire_rt=False)
    assert result.fault == Fault.LATE_ANSWERS.name, result.reason
    assert states[100 + late - 1] == (State.RUNNING, late)
    assert states[100 + late] == (State.FAULT, late + 1)


def test_the_loop_faults_once_the_silence_exceeds_the_gap_limit(shipped):
    """Sample pacing, the DAQ silent: the loop's clock moves only by its read time-outs. The
    fault comes once gap limit + 1 periods have passed without a sample (within the loop's
    shortest wait, a tenth of a period), and no cycle before it faults."""
    table, _, _ = shipped
    gap = 4                 # configured below the live limit, so that it holds still
    config = controller_config({"safety": {"stale_periods": gap}})
    rate = table.design.sample_rate_hz
    clock = FakeClock()
    c = Controller(table, config)
    hal = ScriptedHal(rate, [(DEFLECTED, LOAD)] * 100 + [None] * 100, sleep=clock.sleep).open()
    last, silences = [0.0], []

    def on_cycle(lp):
        if not int(c.record[e.I_FLAGS]) & e.FLAG_NO_NEW_SAMPLE:
            last[0] = clock.now
        else:
            silences.append(((clock.now - last[0]) * rate, c.state))

    loop = ControlLoop(c, hal, clock=clock, sleep=clock.sleep, on_cycle=on_cycle, max_cycles=1000)
    result = loop.run(require_rt=False, acquire_rt=False)
    assert result.fault == Fault.STALE_INPUT.name, result.reason
    running = [s for s, state in silences if state == State.RUNNING]
    faulted = next(s for s, state in silences if state == State.FAULT)
    assert running and max(running) < gap + 1, silences
    assert gap + 1 - 1e-9 <= faulted <= gap + 1.1 + 1e-9, silences
