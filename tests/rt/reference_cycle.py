"""The control cycle in plain Python: the readable specification of the compiled engine
(rt/engine.py), for tests only.

``ReferenceController`` has the Python face of ``beamctl.rt.controller.Controller`` (``arm``,
``start``, ``rearm``, ``request_stop``, ``fault``, ``step``, ``answer_sent``, the loop's overrun
reports) and fills the same telemetry record (``RECORD_COLUMNS``), written for a reader rather
than for speed: every quantity has a name, every matrix is formed at the load it is used at,
and each decision is one ``if`` that says what it decides. tests/rt/test_engine.py runs it beside
the engine on randomised sequences and compares every column of the record after every call.

The cycle, per call of ``step``
-------------------------------
A new sample:
1. (RUNNING only) input checks, the first failing one faults: a strain non-finite
   (STRAIN_NOT_FINITE) or beyond the strain limit (STRAIN_OUT_OF_RANGE), channels in order; then
   the load-cell value non-finite (LOAD_NOT_FINITE) or outside the sensor's range
   (LOAD_OUT_OF_SENSOR_RANGE).
2. (RUNNING only) the stall ridden through: the stacks held the last answer for the samples the
   source skipped before this one (``sample.missed``) or for the silence before it, whichever is
   longer (floor(time since the previous sample / period - 0.5)); a stall longer than the live
   let-go (below) faults STALE_INPUT; otherwise it is bridged by catching up: before the normal step the
   compensator's state makes one step per sample missed (at most ``CATCH_UP_SAMPLES``) on the
   newest strains and the forces the stacks held, x_c <- A x_c + B y + E u_applied; the integral
   stays as it was.
3. Then, RUNNING: the controlled step (``_control``): the load filter and the schedule (the
   filtered load leaving the grid faults LOAD_OUT_OF_TABLE_RANGE), q, the integral with
   anti-windup, the law, allocation with the clamp to [V_min, V_max], excitation, the fade-in,
   the applied forces, the compensator's update, the moving statistics and the live limit (below),
   and the saturation count (saturation_time x rate saturated samples in a row fault
   PERSISTENT_SATURATION).
   Any other state: q is still estimated from the sample; FAULT and STOPPING advance the ramp to
   bias (a stop ends in STOPPED the call after the ramp has reached bias); the applied forces.

No sample (``step(None, silent_periods)``): the voltages hold. ``silent_periods`` is the time
since the last sample in periods (None: one period per call since the last sample); a RUNNING
controller faults STALE_INPUT once floor(silent_periods) exceeds the let-go's whole samples
(or the silence is not a number). FAULT and
STOPPING advance the ramp.

Between cycles: ``answer_sent(age_s)``: an answer later than the budget is late (counted); one
later than the delay the loop tolerates (the design's delay plus twice the budget's margin over
it) held the stacks stale, and more than the late limit of those in a row fault a RUNNING
controller (LATE_ANSWERS); any other answer ends the streak; NaN (not measured) counts nothing.
``cycle_overran()``: the overrun streak grows and faults OVERRUN_STREAK (in any state) when it
reaches the configured streak; ``cycle_on_time()`` ends it.

The ride-through (gains/ridethrough.py, ``rt.controller.ride_through_limits``). The live limit is
the longest gap of the table's grid (and on, interpolated linearly in the growth's logarithm up to
the next grid gap) whose growth (of the interval between the analysed loads that
holds the filtered load) k x g x spread keeps within the headroom, for the deflection and the
voltages both, capped by the configuration: spread_q = the larger over the planes of sqrt(var q_1)
times mode 1's strain at the gauges, headroom_q = strain limit - the largest |mean strain|;
spread_v = the largest sqrt(var V_i), headroom_v = the least of V_max - mean V_i, mean V_i - V_min.
The means and variances are exponential (coefficient 1 - exp(-T / 0.1 s)) over the controlled
samples; a start sets the means where the signals are and the variances so that a growth of 10 is
allowed. The let-go is the same at LET_GO_SIGMA for k (never below the live limit, capped
alike) with the spreads at LET_GO_SIGMA instead of k, or the excursion beyond k spreads whole
where that is larger: a stall of more samples than it faults STALE_INPUT, and the late-answer limit is the
let-go capped by the configuration; the answer budget
the table's per grid point (the lesser of a grid interval's ends), tightened by the configuration.

Faults latch: the first wins until an operator re-arms, the state becomes FAULT and the
voltages ramp linearly from where they were to bias in ramp_time x rate samples, then hold it
(a fault during a stop's ramp lets that ramp go on).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

from beamctl.rt.config import ControllerConfig
from beamctl.rt.controller import (
    EXCURSION_TIME_S,
    LET_GO_SIGMA,
    SPREAD_CLIP_FLOOR,
    SPREAD_TIME_S,
    START_GROWTH,
    ride_through_limits,
)
from beamctl.rt.engine import CATCH_UP_SAMPLES, GROWTH_CAP, RECORD_COLUMNS
from beamctl.rt.safety import Fault, State, TransitionError

# the record's layout is the telemetry's format (rt/engine.py defines it); the values in it are
# what this file specifies
COL = {name: i for i, name in enumerate(RECORD_COLUMNS)}

# flag bits of the record's ``flags`` column
SATURATED_A = 1
SATURATED_B = 2
INTEGRATOR_HELD = 4
LOAD_OUT_OF_TABLE = 8
NO_NEW_SAMPLE = 16
FADING_IN = 32
RAMPING_TO_BIAS = 64
BRIDGED = 128

# A spread of voltages or a delivered fraction that misses the range only by rounding (relative
# 1e-12, far above the few ulps of the coefficients and far below any real excess) counts as
# fitting: a force that needs exactly the whole range is not a saturation.
ROUNDING = 1e-12
CAP = 4.0e18                # the engine's cap on a count of samples (int64)

MATRIX_NAMES = ("a", "b", "e", "c", "d", "ki")


@dataclass
class Point:
    """The compensator's matrices at one point of the schedule."""

    a: np.ndarray
    b: np.ndarray
    e: np.ndarray
    c: np.ndarray
    d: np.ndarray
    ki: np.ndarray
    predict: np.ndarray | None


def _slopes(matrices: np.ndarray, loads: np.ndarray) -> np.ndarray:
    """Per grid point the slope in load to the next point; zero at the last one."""
    slopes = np.zeros_like(matrices)
    for i in range(len(loads) - 1):
        slopes[i] = (matrices[i + 1] - matrices[i]) / (loads[i + 1] - loads[i])
    return slopes


def clamp(v: float, low: float, high: float) -> float:
    """``v`` within [low, high] (NaN passes)."""
    return low if v < low else (high if v > high else v)


class ReferenceController:
    """The engine's control cycle in plain Python, with the lifecycle of ``Controller``."""

    def __init__(self, table, config: ControllerConfig, *, excitation: np.ndarray | None = None,
                 law: bool = True) -> None:
        rate = table.design.sample_rate_hz
        self.period_s = 1.0 / rate
        self.law = law
        self.anti_windup = config.anti_windup
        self.clip_allocation = config.allocation == "clip"
        s = config.safety
        a = config.actuators
        beam = table.model_parameters.beam

        # -- settings -----------------------------------------------------------------------------
        self.start_samples = max(1, round(config.start_ramp_time_s * rate))      # fade-in
        self.saturation_limit = max(1, round(s.saturation_time_s * rate))
        self.ramp_samples = max(1, int(round(s.ramp_time_s * rate)))
        self.overrun_limit = s.overrun_streak
        self.strain_limit = s.strain_limit_fraction * beam.proportional_limit / beam.youngs_modulus
        self.load_low, self.load_high = s.load_range_n
        self.bias = a.bias_voltage_v
        self.v_min, self.v_max = a.min_voltage_v, a.max_voltage_v
        self.v_mid = 0.5 * (self.v_min + self.v_max)
        self.v_span = self.v_max - self.v_min
        # stack i of a support pushes along e_i = (cos t_i, sin t_i), t_i = t_1 + (i - 1) 120 deg,
        # with k (V_i - V_bias); the lateral force F needs stack shares 2/3 e_i . F / k volts
        k = a.force_constant_n_per_v
        angles = [[math.radians(t1 + 120.0 * i) for i in range(3)] for t1 in a.orientation_deg]
        self.axes = [np.array([[math.cos(t), math.sin(t)] for t in support]) for support in angles]
        self.volts_per_newton = [2.0 / 3.0 * ax / k for ax in self.axes]       # [3 x 2] per support
        self.force_per_volt = [k * ax.T for ax in self.axes]                   # [2 x 3] per support
        self.excitation = None if excitation is None else np.array(excitation, dtype=float)
        self.excitation_enabled = True

        # -- the table ------------------------------------------------------------------------------
        comp = table.compensator
        self.loads = np.asarray(table.loads_n, dtype=float)
        self.first_load, self.last_load = float(self.loads[0]), float(self.loads[-1])
        self.paper_mode = table.schedule.mode == "paper"
        self.half_band = 0.5 * table.schedule.hysteresis_n
        self.alpha = 1.0 - math.exp(-2.0 * math.pi * table.schedule.load_filter_hz / rate)
        self.c0_phi_inv = np.asarray(table.c0_phi_inv, dtype=float)
        self.integral_map = self.period_s * np.asarray(comp.h, dtype=float)      # T H
        self.start_map = np.asarray(comp.start, dtype=float)
        self.grid = {m: np.asarray(getattr(comp, m), dtype=float) for m in MATRIX_NAMES}
        predict = getattr(comp, "predict", None)
        if predict is not None:
            self.grid["predict"] = np.asarray(predict, dtype=float)
        self.slope = {m: _slopes(v, self.loads) for m, v in self.grid.items()}
        n = comp.n_states
        # the ride-through (the table's analysis, tightened by the configuration)
        limits = ride_through_limits(table, config)
        budgets = np.asarray(limits.budgets, dtype=float)
        self.interval_budgets = np.minimum(budgets, np.concatenate([budgets[1:], budgets[-1:]]))
        # the latest answer the loop tolerates: the design's delay plus twice the budget's margin
        # over it (the extra delay the table's delay search found stable), never below the budget
        design = table.design.io.delay_samples
        self.interval_tolerated = [max(b, design + 2.0 * (b - design)) for b in self.interval_budgets]
        self.growth_loads = [float(v) for v in limits.growth_loads]
        self.growth = np.asarray(limits.growth, dtype=float)      # [interval, bridge, output, gap]
        self.gap_grid = [float(v) for v in limits.grid]
        self.sigma = limits.confidence_sigma
        self.gap_cap, self.late_cap = limits.gap_cap, limits.late_cap
        self.stat_alpha = 1.0 - math.exp(-self.period_s / SPREAD_TIME_S)
        self.excursion_decay = math.exp(-self.period_s / EXCURSION_TIME_S)
        c0_phi = np.linalg.inv(self.c0_phi_inv)
        self.mode1_strain = [float(np.abs(c0_phi[[0, 2], 0]).max()), float(np.abs(c0_phi[[1, 3], 1]).max())]

        # -- state ------------------------------------------------------------------------------------
        self.record = np.zeros(len(RECORD_COLUMNS))
        r = self.record
        self.q = r[COL["q_1y"]:COL["q_1y"] + 4]
        self.u = r[COL["force_y_A_N"]:COL["force_y_A_N"] + 4]
        self.voltages = r[COL["voltage_a1_V"]:COL["voltage_a1_V"] + 6]
        self.strains = r[COL["strain_y1"]:COL["strain_y1"] + 4]
        self.xi = r[COL["xi_1y"]:COL["xi_1y"] + 4]
        self.applied = r[COL["applied_force_y_A_N"]:COL["applied_force_y_A_N"] + 4]
        self.x = np.zeros(n)                    # the compensator's state x_c
        self.catch_up = CATCH_UP_SAMPLES       # the samples of a gap caught up on
        self.voltages[:] = self.bias
        r[COL["load_N"]] = math.nan             # no load seen yet
        r[COL["time_s"]] = math.nan
        self.state = State.INIT
        self.fault_code = Fault.NONE
        self.fault_time = math.nan
        self.fault_value = math.nan
        self.fault_limit = math.nan
        self.fault_channel = -1
        self.time = 0.0                         # the latest sample's time stamp
        # the schedule: filtered load, grid point and the load above it (0 in paper mode)
        self.filtered = 0.0
        self.index = 0
        self.offset = 0.0
        self.out_of_range = False
        self.scale_a = self.scale_b = 1.0       # the latest allocation's delivered fractions
        self.target = np.zeros(6)               # the voltages the allocation asks for
        self.ramp_from = np.zeros(6)
        self.ramp_step = 0
        self.steps = 0                          # controlled samples since the start
        self.excitation_index = 0
        self.saturated = 0                      # saturated samples in a row
        self.silent_calls = 0                   # calls without a sample in a row
        self.late_streak = 0
        self.late_total = 0
        self.overrun_streak = 0
        self.max_overrun_streak = 0
        self.bridged_total = 0
        self.longest_gap = 0
        # the moving statistics of the ride-through and the live limit (samples)
        self.q_mean, self.q_var = [0.0, 0.0], [0.0, 0.0]
        self.y_mean = [0.0] * 4
        self.v_mean, self.v_var = [0.0] * 6, [0.0] * 6
        self.excursion_q = self.excursion_v = 0.0
        self.live_limit = 0.0
        self.let_go = 0.0

    # the ride-through limits now
    @property
    def gap_limit(self) -> float:
        """The live limit: a stall up to it is survived with k sigma to spare."""
        return self.live_limit

    @property
    def late_limit(self) -> int:
        """Late answers in a row that are ridden through; more fault LATE_ANSWERS."""
        return int(min(self.let_go, self.late_cap))

    @property
    def answer_budget_s(self) -> float:
        """An answer sent later than this after its sample arrived is late."""
        return self.interval_budgets[self.index] * self.period_s

    def _stats_start(self) -> None:
        """At a start: the means where the signals are, the variances that allow a growth of
        START_GROWTH at the headroom that leaves."""
        k = self.sigma * START_GROWTH
        self.y_mean = [float(y) if math.isfinite(y) else 0.0 for y in self.strains]
        headroom_q = self.strain_limit - max(abs(y) for y in self.y_mean)
        for p in range(2):
            q = float(self.q[p])
            self.q_mean[p] = q if math.isfinite(q) else 0.0
            ok = headroom_q > 0.0 and self.mode1_strain[p] > 0.0
            self.q_var[p] = (headroom_q / (k * self.mode1_strain[p])) ** 2 if ok else 0.0
        for j, v in enumerate(self.voltages):
            self.v_mean[j] = float(v)
            h = min(self.v_max - v, v - self.v_min)
            self.v_var[j] = (h / k) ** 2 if h > 0.0 else 0.0
        self.excursion_q = self.excursion_v = 0.0
        self._update_limit()

    def _stats_update(self) -> None:
        """One controlled sample into the exponential means and variances (a deviation beyond
        k spreads enters as k spreads) and into the excursion (the largest deviation from the
        means now, or the last excursion decayed), then the limit."""
        a = self.stat_alpha

        def clipped(d: float, var: float, floor: float) -> float:
            c = max(self.sigma * math.sqrt(var), floor)
            return max(-c, min(c, d))

        self.excursion_q *= self.excursion_decay
        self.excursion_v *= self.excursion_decay
        for p in range(2):
            d = float(self.q[p]) - self.q_mean[p]
            self.excursion_q = max(self.excursion_q, abs(d) * self.mode1_strain[p])
            d = clipped(d, self.q_var[p], SPREAD_CLIP_FLOOR[0] / self.mode1_strain[p]
                        if self.mode1_strain[p] > 0.0 else math.inf)
            self.q_mean[p] += a * d
            self.q_var[p] = (1.0 - a) * (self.q_var[p] + a * d * d)
        for j in range(4):
            self.y_mean[j] += a * (float(self.strains[j]) - self.y_mean[j])
        for j in range(6):
            d = float(self.voltages[j]) - self.v_mean[j]
            self.excursion_v = max(self.excursion_v, abs(d))
            d = clipped(d, self.v_var[j], SPREAD_CLIP_FLOOR[1])
            self.v_mean[j] += a * d
            self.v_var[j] = (1.0 - a) * (self.v_var[j] + a * d * d)
        self._update_limit()

    def _update_limit(self) -> None:
        """The live limit from the growth the headroom allows, at the filtered load."""
        r = self.record
        spread_q = max(math.sqrt(self.q_var[p]) * self.mode1_strain[p] for p in range(2))
        spread_v = max(math.sqrt(v) for v in self.v_var)
        headroom_q = self.strain_limit - max(abs(y) for y in self.y_mean)
        headroom_v = min(min(self.v_max - m, m - self.v_min) for m in self.v_mean)
        r[COL["spread_deflection"]] = spread_q
        r[COL["spread_voltage_V"]] = spread_v
        interval = max(bisect.bisect_right(self.growth_loads, self.filtered) - 1, 0)
        curves = self.growth[interval, 0]          # the one bridge: hold

        def allowed(bound_q: float, bound_v: float) -> tuple[float, float]:
            aq = headroom_q / bound_q if bound_q > 0.0 else math.inf
            av = headroom_v / bound_v if bound_v > 0.0 else math.inf
            return (aq if headroom_q > 0.0 else 0.0), (av if headroom_v > 0.0 else 0.0)

        def longest(aq: float, av: float) -> float:
            """The last grid gap allowed, then log-linearly on to where a growth reaches it; a
            growth at the cap is never allowed, nor interpolated towards."""
            limit = 0.0
            before = None
            for n, g_q, g_v in zip(self.gap_grid, curves[0], curves[1], strict=True):
                capped = not (g_q < GROWTH_CAP and g_v < GROWTH_CAP)
                if capped or g_q > aq or g_v > av:
                    if before is None:
                        return 0.0
                    fractions = [0.0 if capped else 1.0]
                    for g, p, a in ((g_q, before[0], aq), (g_v, before[1], av)):
                        if g > a:
                            ok = 0.0 < p < g and a > 0.0
                            fractions.append(math.log(a / p) / math.log(g / p) if ok else 0.0)
                    return limit + max(min(fractions), 0.0) * (n - limit)
                limit = n
                before = (g_q, g_v)
            return limit

        k = self.sigma
        limit = longest(*allowed(max(k * spread_q, self.excursion_q), max(k * spread_v, self.excursion_v)))
        # the let-go: the spreads at its sigma, or the excursion beyond k spreads, whole
        g = min(LET_GO_SIGMA, k)
        go = longest(*allowed(max(g * spread_q, self.excursion_q - (k - g) * spread_q),
                              max(g * spread_v, self.excursion_v - (k - g) * spread_v)))
        self.live_limit = min(limit, self.gap_cap)
        self.let_go = min(max(go, limit), self.gap_cap)
        r[COL["gap_limit_samples"]] = self.live_limit

    # == lifecycle (every command carried out records the state and the fault) ====================
    @property
    def at_bias(self) -> bool:
        return bool(np.all(self.voltages == self.bias))

    def arm(self, sample=None) -> None:
        """INIT -> ARMED: stacks at bias, integral and compensator at rest."""
        if self.state != State.INIT:
            raise TransitionError(f"cannot arm in state {self.state.name}")
        self.state = State.ARMED
        self._clear(sample)
        self._record_state()

    def rearm(self, sample=None) -> None:
        """FAULT or STOPPED -> ARMED, only once the voltages are at bias (checked first); the
        latched fault is cleared."""
        if not self.at_bias:
            raise TransitionError("cannot re-arm before the voltages have ramped to bias")
        if self.state not in (State.FAULT, State.STOPPED):
            raise TransitionError(f"cannot re-arm in state {self.state.name}")
        self.state = State.ARMED
        self.fault_code = Fault.NONE
        self.fault_channel = -1
        self._clear(sample)
        self._record_state()

    def _clear(self, sample) -> None:
        """Arming: integral, compensator and applied forces at zero, the stacks at bias, the
        ramp, saturation, silence and late-answer counts start again (the overrun streak is the
        loop's and goes on), the allocation delivered everything. With a sample: its time, load
        (the load filter starts there), strains and q."""
        self.xi[:] = 0.0
        self.applied[:] = 0.0
        self.x[:] = 0.0
        self.voltages[:] = self.bias
        self.ramp_step = 0
        self.saturated = 0
        self.silent_calls = 0
        self.late_streak = 0
        self.scale_a = self.scale_b = 1.0
        r = self.record
        if sample is None:
            r[COL["time_s"]] = math.nan
            return
        r[COL["time_s"]] = sample.timestamp
        self.time = sample.timestamp
        r[COL["sequence"]] = sample.sequence
        r[COL["load_N"]] = sample.axial_load
        self._reset_schedule(sample.axial_load)
        self.strains[:] = sample.strains
        self._estimate_q()

    def start(self) -> None:
        """ARMED -> RUNNING from the latest sample: the schedule settled at its load, the
        integral at zero, the compensator at rest on its strains (x_c = start y), the fade-in and
        the excitation from their beginning. Non-finite strains fault at once."""
        if self.state != State.ARMED:
            raise TransitionError(f"cannot start in state {self.state.name}")
        self.state = State.RUNNING
        self._reset_schedule(self.record[COL["load_N"]])
        self.steps = 0
        self.excitation_index = 0
        self.xi[:] = 0.0
        if not np.all(np.isfinite(self.strains)):
            self.q[:] = 0.0
            self.x[:] = 0.0
            self._trip(Fault.STRAIN_NOT_FINITE, math.nan, self.strain_limit)
        else:
            self.x = self.start_map @ self.strains
            self._stats_start()
        self._record_state()

    def request_stop(self) -> None:
        """RUNNING, ARMED or INIT -> STOPPING: ramp to bias from the voltages now."""
        if self.state in (State.RUNNING, State.ARMED, State.INIT):
            self._ramp_begin()
            self.state = State.STOPPING
        self._record_state()

    def fault(self, fault: Fault, detail: str = "") -> None:
        """A fault from outside the cycle (the loop: a HAL error; an operator)."""
        self._trip(fault, math.nan, math.nan)
        self._record_state()

    def _trip(self, fault: Fault, value: float, limit: float, channel: int = -1) -> bool:
        """Latch ``fault`` unless one is latched (the first wins) or the controller has stopped;
        the ramp to bias begins from the voltages now, unless a stop's ramp is under way."""
        if self.state in (State.FAULT, State.STOPPED) or self.fault_code != Fault.NONE:
            return False
        stopping = self.state == State.STOPPING
        self.state = State.FAULT
        self.fault_code = fault
        self.fault_time = self.time
        self.fault_value, self.fault_limit, self.fault_channel = value, limit, channel
        if not stopping:
            self._ramp_begin()
        return True

    def _ramp_begin(self) -> None:
        self.ramp_from = self.voltages.copy()
        self.ramp_step = 0

    def _ramp_advance(self) -> bool:
        """The ramp's next voltages: bias + (from - bias)(1 - k / N) at its k-th step, k = 1..N
        (the N-th writes bias); False while ramping, True from the call after the last step on,
        with bias held."""
        if self.ramp_step < self.ramp_samples:
            self.ramp_step += 1
            remaining = 1.0 - self.ramp_step / self.ramp_samples
            self.voltages[:] = (self.ramp_from - self.bias) * remaining + self.bias
            return False
        self.voltages[:] = self.bias
        return True

    # the loop's emergency exit
    def emergency_ramp_begin(self) -> None:
        self._ramp_begin()
        self._record_state()

    def emergency_ramp_advance(self) -> bool:
        return self._ramp_advance()

    # == the loop's reports between cycles ==========================================================
    def cycle_overran(self) -> None:
        self.overrun_streak += 1
        self.max_overrun_streak = max(self.max_overrun_streak, self.overrun_streak)
        if self.overrun_streak >= self.overrun_limit:
            self._trip(Fault.OVERRUN_STREAK, self.overrun_streak, self.overrun_limit)
        self._record_state()

    def cycle_on_time(self) -> None:
        self.overrun_streak = 0
        self._record_state()

    def answer_sent(self, age_s: float) -> None:
        """The latest sample's answer had been sent ``age_s`` after the sample arrived."""
        if age_s != age_s:                      # not measured
            return
        r = self.record
        r[COL["answer_age_us"]] = age_s * 1e6
        if age_s <= self.answer_budget_s:
            self.late_streak = 0
        else:
            self.late_total += 1
            tolerated = self.interval_tolerated[self.index] * self.period_s
            if age_s <= tolerated:
                self.late_streak = 0
            else:
                self.late_streak += 1
                if self.late_streak > self.late_limit and self.state == State.RUNNING:
                    self._trip(Fault.LATE_ANSWERS, age_s, tolerated, self.late_streak)
        r[COL["late_answers"]] = self.late_total
        self._record_state()

    # == the cycle ===================================================================================
    def step(self, sample, silent_periods: float | None = None) -> np.ndarray:
        """One control period (module docstring); returns the six voltages."""
        r = self.record
        flags = 0
        r[COL["answer_age_us"]] = math.nan
        r[COL["bridged"]] = 0.0
        running = self.state == State.RUNNING
        if sample is None:
            flags |= NO_NEW_SAMPLE
            r[COL["input_period_us"]] = math.nan
            self.silent_calls += 1
            silent = self.silent_calls if silent_periods is None or silent_periods < 0 else silent_periods
            # the samples due in that time are missing: floor(silent) of them; a silence of the
            # limit's whole samples + 1 periods or more faults, and so does an endless or unknown one
            if running and not silent < int(self.let_go) + 1:
                self._trip(Fault.STALE_INPUT, silent, int(self.let_go))
        else:
            self.silent_calls = 0
            self.time = sample.timestamp
            since = sample.timestamp - r[COL["time_s"]]
            r[COL["input_period_us"]] = since * 1e6
            r[COL["time_s"]] = sample.timestamp
            r[COL["sequence"]] = sample.sequence
            r[COL["held_samples"]] = 0.0
            gap = float(sample.missed)
            if running:
                self._check_inputs(sample.strains, sample.axial_load)
                missed = 0 if gap < 0.0 else int(gap) if gap < CAP else int(CAP)     # NaN: the cap
                # the stall: the samples missing, or the silence before this one, the longer
                held = max(gap, 0.0)
                silent = math.floor(since / self.period_s - 0.5) if since > 0.0 else 0.0
                held = max(held, silent)
                if not gap <= CAP:              # beyond the count's cap, or NaN
                    held = gap
                r[COL["held_samples"]] = held
                if held > self.longest_gap:
                    self.longest_gap = int(min(held, CAP))
                if held > 0.0 or held != held:
                    if not held <= self.let_go:
                        self._trip(Fault.STALE_INPUT, held, self.let_go)
                    elif self.state == State.RUNNING and self.law and missed > 0:
                        # bridged by catching up (``_control``): x_c steps once per sample missed
                        flags |= BRIDGED
                        r[COL["bridged"]] = missed
                        self.bridged_total += missed
            self.strains[:] = sample.strains
            r[COL["load_N"]] = sample.axial_load
        if self.state == State.RUNNING:
            if sample is not None:              # no sample: the voltages hold, the law waits
                flags |= self._control()
        else:
            if sample is not None:              # still observed: q for telemetry and the operator
                self._estimate_q()
            if self.state in (State.FAULT, State.STOPPING):
                flags |= RAMPING_TO_BIAS
                if self._ramp_advance() and self.state == State.STOPPING:
                    self.state = State.STOPPED
            self._apply_forces()
        r[COL["flags"]] = flags
        self._record_state()
        return self.voltages

    def _record_state(self) -> None:
        self.record[COL["state"]] = self.state
        self.record[COL["fault"]] = self.fault_code

    def _check_inputs(self, strains: np.ndarray, load: float) -> None:
        """The first failing check faults: strains (channels in order), then the load cell."""
        for channel, e in enumerate(strains):
            if not math.isfinite(e):
                self._trip(Fault.STRAIN_NOT_FINITE, e, self.strain_limit, channel)
                return
            if abs(e) > self.strain_limit:
                self._trip(Fault.STRAIN_OUT_OF_RANGE, e, self.strain_limit, channel)
                return
        if not math.isfinite(load):
            self._trip(Fault.LOAD_NOT_FINITE, load, 0.0)
        elif not self.load_low <= load <= self.load_high:
            self._trip(Fault.LOAD_OUT_OF_SENSOR_RANGE, load, 0.0)

    def _estimate_q(self) -> None:
        """q = (C0 Phi)^-1 y (eq. 30), for telemetry and the operator (non-finite strains give a
        non-finite q)."""
        with np.errstate(invalid="ignore", over="ignore"):
            self.q[:] = self.c0_phi_inv @ self.strains

    def _control(self) -> int:
        """One controlled sample: returns its flags."""
        flags = 0
        r = self.record
        if self.law:
            self._follow(r[COL["load_N"]])
            r[COL["load_filtered_N"]] = self.filtered
            if self.out_of_range:
                flags |= LOAD_OUT_OF_TABLE
                self._trip(Fault.LOAD_OUT_OF_TABLE_RANGE, self.filtered, self.last_load)
                self._ramp_advance()            # the ramp's first step, this sample
                flags |= RAMPING_TO_BIAS
                self._apply_forces()
                return flags
            m = self.matrices()
            for _ in range(min(int(r[COL["bridged"]]), int(self.catch_up))):
                self.x = m.a @ self.x + m.b @ self.strains + m.e @ self.applied
            self._estimate_q()
            # integral action: an increment that would push a saturated support further along
            # the force it was asked for (with the previous u) is held back (anti-windup)
            dxi = self.integral_map @ self.strains
            held = False
            if self.anti_windup and (self.scale_a < 1.0 or self.scale_b < 1.0):
                du = -m.ki @ dxi
                held = ((self.scale_a < 1.0 and du[0] * self.u[0] + du[1] * self.u[1] > 0.0)
                        or (self.scale_b < 1.0 and du[2] * self.u[2] + du[3] * self.u[3] > 0.0))
            if held:
                flags |= INTEGRATOR_HELD
            else:
                self.xi += dxi
            # the law
            self.u[:] = -(m.c @ self.x + m.d @ self.strains + m.ki @ self.xi)
            # allocation to the stacks, within [V_min, V_max]
            self.scale_a = self._allocate(self.u[0], self.u[1], 0)
            self.scale_b = self._allocate(self.u[2], self.u[3], 1)
            r[COL["scale_A"]] = self.scale_a
            r[COL["scale_B"]] = self.scale_b
            if self.scale_a < 1.0:
                flags |= SATURATED_A
            if self.scale_b < 1.0:
                flags |= SATURATED_B
        else:                                   # open loop: bias (plus the excitation)
            self._estimate_q()
            self.target[:] = self.bias
        # the excitation's next row, within the voltage limits
        if self.excitation is not None and self.excitation_enabled:
            if self.excitation_index < len(self.excitation):
                row = self.excitation[self.excitation_index]
                self.target[:] = [clamp(v, self.v_min, self.v_max) for v in self.target + row]
                self.excitation_index += 1
        # the bumpless start: the voltages faded in from bias over the first start_samples
        self.steps += 1
        if self.steps < self.start_samples:
            flags |= FADING_IN
            fade = self.steps / self.start_samples
            self.voltages[:] = (self.target - self.bias) * fade + self.bias
        else:
            self.voltages[:] = self.target
        self._apply_forces()
        if self.law:
            # the compensator's next state sees the forces the stacks give
            m = self.matrices()
            self.x = m.a @ self.x + m.b @ self.strains + m.e @ self.applied
            # the fade-in's ramp is not a spread: the statistics start over until it ends
            if self.steps <= self.start_samples:
                self._stats_start()
            else:
                self._stats_update()
            # saturation_limit saturated samples in a row fault
            if self.scale_a < 1.0 or self.scale_b < 1.0:
                self.saturated += 1
                if self.saturated >= self.saturation_limit:
                    self._trip(Fault.PERSISTENT_SATURATION, self.saturated, self.saturation_limit)
            else:
                self.saturated = 0
        return flags

    def _apply_forces(self) -> None:
        """u_applied: the lateral forces the voltages about to be written give."""
        dv = self.voltages - self.bias
        self.applied[0:2] = self.force_per_volt[0] @ dv[0:3]
        self.applied[2:4] = self.force_per_volt[1] @ dv[3:6]

    # == allocation =============================================================================
    def _allocate(self, fy: float, fz: float, support: int) -> float:
        """The three voltages of ``support`` for the lateral force (fy, fz) into ``target``;
        returns the fraction of the force delivered along its direction."""
        first = 3 * support
        coef = self.volts_per_newton[support]
        if self.clip_allocation:
            # the paper's: each stack its share about the bias, clipped at its own limit
            g = [coef[i, 0] * fy + coef[i, 1] * fz for i in range(3)]
            wanted = g[0] * g[0] + g[1] * g[1] + g[2] * g[2]
            if not wanted < math.inf:           # NaN or infinite demand, or overflow: no force
                self.target[first:first + 3] = self.bias
                return 0.0
            v = [self.bias + gi for gi in g]
            clipped = any(vi < self.v_min or vi > self.v_max for vi in v)
            v = [clamp(vi, self.v_min, self.v_max) for vi in v]
            self.target[first:first + 3] = v
            if not clipped:
                return 1.0
            # F_applied . F / |F|^2
            delivered = sum((vi - self.bias) * gi for vi, gi in zip(v, g, strict=True)) / wanted
            return 1.0 if delivered > 1.0 - ROUNDING else delivered
        # scale: the shares centred in [V_min, V_max]; a spread that does not fit scales the
        # force down as a whole (its direction kept)
        if not (math.isfinite(fy) and math.isfinite(fz)):
            fy = fz = math.nan
        g = [coef[i, 0] * fy + coef[i, 1] * fz for i in range(3)]
        hi, lo = max(g), min(g)
        if any(gi != gi for gi in g):
            hi = lo = math.nan
        spread = hi - lo
        if spread <= self.v_span * (1.0 + ROUNDING):
            scale = 1.0
        elif spread < math.inf:
            scale = self.v_span / spread
        else:                                   # NaN (invalid demand) or overflow: no force
            scale = 0.0
            g = [0.0, 0.0, 0.0]
            hi = lo = 0.0
        centre = self.v_mid - scale * 0.5 * (hi + lo)
        self.target[first:first + 3] = [clamp(centre + scale * gi, self.v_min, self.v_max) for gi in g]
        return scale

    # == the schedule ==========================================================================
    def matrices(self) -> Point:
        """The compensator's matrices at the schedule's point: those of grid point ``index``
        plus ``offset`` times the slope to the next point (interpolated between the two)."""
        at = {m: self.grid[m][self.index] + self.offset * self.slope[m][self.index] for m in self.grid}
        return Point(predict=at.pop("predict", None), **at)

    def _reset_schedule(self, load: float) -> None:
        """The filter starts at ``load`` (non-finite: the first grid point), settled."""
        if not math.isfinite(load):
            load = self.first_load
        self.filtered = load
        self.out_of_range = load < self.first_load or load > self.last_load
        self._settle(load)

    def _settle(self, load: float) -> None:
        """Grid point and offset at a load reached from below and settled. interpolate: the
        point at or below the load and the load above it (the edge point beyond the grid);
        paper: the point at or above the load."""
        last = len(self.loads) - 1
        if self.paper_mode:
            self.index = min(bisect.bisect_left(list(self.loads), load), last)
            self.offset = 0.0
        elif load <= self.first_load:
            self.index, self.offset = 0, 0.0
        elif load >= self.last_load:
            self.index, self.offset = last, 0.0
        else:
            self.index = bisect.bisect_right(list(self.loads), load) - 1
            self.offset = load - self.loads[self.index]

    def _follow(self, load: float) -> None:
        """The load filter (first order) and the grid point of the filtered load. A non-finite
        reading is not filtered and counts as out of range. paper: the grid point moves up once
        the filtered load passes the point above the current one's load + half the band, down
        once it falls below the point below's load - half the band."""
        if not math.isfinite(load):
            self.out_of_range = True
            return
        self.filtered = self.filtered + self.alpha * (load - self.filtered)
        f = self.filtered
        self.out_of_range = f < self.first_load or f > self.last_load
        if self.paper_mode:
            i, last = self.index, len(self.loads) - 1
            while i < last and f > self.loads[i] + self.half_band:
                i += 1
            while i > 0 and f < self.loads[i - 1] - self.half_band:
                i -= 1
            self.index = i
        else:
            self._settle(f)
