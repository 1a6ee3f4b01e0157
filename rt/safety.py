"""Safety, in one place: the lifecycle and its latched fault (as in ros2_control's lifecycle),
the input checks, the counts of saturated samples, missing samples, late answers and overrun
cycles that end in a fault, and the one ramp to bias that faults, stops and the loop's emergency exit use.

    INIT --arm--> ARMED --start--> RUNNING --fault--> FAULT --rearm--> ARMED
                                     |  \\--stop--> STOPPING --(ramp done)--> STOPPED
                                     \\-- a fault while stopping also ends in FAULT

In ARMED the stacks sit at the bias voltage. Entering FAULT or STOPPING freezes the
integrator and ramps the voltages linearly from where they were to the bias within the
configured ramp time; the first fault's reason is latched until an operator re-arms.
"""

from __future__ import annotations

import enum
import math

import numpy as np

from beamctl.rt.config import Safety as SafetySettings


class State(enum.IntEnum):
    INIT = 0
    ARMED = 1
    RUNNING = 2
    FAULT = 3
    STOPPING = 4
    STOPPED = 5


class Fault(enum.IntEnum):
    NONE = 0
    STRAIN_NOT_FINITE = 1
    STRAIN_OUT_OF_RANGE = 2
    LOAD_NOT_FINITE = 3
    LOAD_OUT_OF_SENSOR_RANGE = 4
    LOAD_OUT_OF_TABLE_RANGE = 5
    STALE_INPUT = 6
    OVERRUN_STREAK = 7
    PERSISTENT_SATURATION = 8
    HAL_ERROR = 9
    OPERATOR = 10
    LATE_ANSWERS = 11


DESCRIPTIONS = {
    Fault.NONE: "no fault",
    Fault.STRAIN_NOT_FINITE: "a strain reading is not a finite number",
    Fault.STRAIN_OUT_OF_RANGE: "a strain reading exceeds the limit derived from the proportional limit",
    Fault.LOAD_NOT_FINITE: "the load-cell reading is not a finite number",
    Fault.LOAD_OUT_OF_SENSOR_RANGE: "the load-cell reading is outside the sensor range",
    Fault.LOAD_OUT_OF_TABLE_RANGE: "the axial load is outside the gain table's load range",
    Fault.STALE_INPUT: "no valid sample for too many periods of time",
    Fault.OVERRUN_STREAK: "too many consecutive overruns of the control period",
    Fault.PERSISTENT_SATURATION: "the stack voltages stayed saturated for too long",
    Fault.HAL_ERROR: "the hardware abstraction reported an error",
    Fault.OPERATOR: "stopped by the operator",
    Fault.LATE_ANSWERS: "a streak of samples was answered later than the latency budget",
}


class TransitionError(RuntimeError):
    """A lifecycle transition that is not allowed from the current state."""


class Supervisor:
    """Holds the state and the latched fault; the controller asks it what to do."""

    def __init__(self) -> None:
        self.state = State.INIT
        self.fault = Fault.NONE
        self.detail = ""
        self.fault_time = None

    def _require(self, *allowed: State, action: str) -> None:
        if self.state not in allowed:
            raise TransitionError(f"cannot {action} in state {self.state.name} "
                                  f"(allowed from {', '.join(s.name for s in allowed)})")

    def arm(self) -> None:
        self._require(State.INIT, action="arm")
        self.state = State.ARMED

    def start(self) -> None:
        self._require(State.ARMED, action="start")
        self.state = State.RUNNING

    def rearm(self) -> None:
        """Operator acknowledgement of a latched fault (or a new start after a stop)."""
        self._require(State.FAULT, State.STOPPED, action="re-arm")
        self.state = State.ARMED
        self.fault = Fault.NONE
        self.detail = ""
        self.fault_time = None

    def trip(self, fault: Fault, detail: str = "", time_s: float | None = None) -> bool:
        """Enter FAULT with ``fault`` unless a fault is already latched. Returns True if this
        call latched it."""
        if self.state in (State.FAULT, State.STOPPED) or self.fault != Fault.NONE:
            return False
        self.state = State.FAULT
        self.fault = fault
        self.detail = detail
        self.fault_time = time_s
        return True

    def request_stop(self) -> None:
        if self.state in (State.RUNNING, State.ARMED, State.INIT):
            self.state = State.STOPPING

    def stopped(self) -> None:
        if self.state == State.STOPPING:
            self.state = State.STOPPED

    def reason(self) -> str:
        text = DESCRIPTIONS[self.fault]
        return f"{self.fault.name}: {text}" + (f" ({self.detail})" if self.detail else "")


class BiasRamp:
    """The ramp to bias: linear from the voltages it begins at to the bias voltage in ``samples``
    steps, then bias held. The one way the stacks are brought to rest (faults, stops and the
    loop's emergency exit)."""

    def __init__(self, bias_voltage: float, samples: int) -> None:
        self.bias = np.full(6, float(bias_voltage))
        self.samples = max(1, int(samples))
        self._from = self.bias.copy()
        self._step = 0

    def begin(self, voltages: np.ndarray) -> None:
        """Start a ramp from ``voltages`` (copied)."""
        np.copyto(self._from, voltages)
        self._step = 0

    def reset(self) -> None:
        self._step = 0

    def advance(self, out: np.ndarray) -> bool:
        """Write the ramp's next six voltages into ``out``. False while ramping (the last ramp
        step writes bias); True from the call after it on, with bias in ``out``."""
        if self._step < self.samples:
            self._step += 1
            remaining = 1.0 - self._step / self.samples
            np.subtract(self._from, self.bias, out=out)
            out *= remaining
            out += self.bias
            return False
        out[:] = self.bias
        return True


class Safety:
    """The controller's safety: the supervisor (state and latched fault), the checks of every
    sample, the counts that end in a fault (saturated samples, missing samples, overrun cycles)
    and the ramp of ``voltages``, the controller's output array, to bias.

    The controller reports each sample (``sample_arrived`` / ``sample_missing``, ``check_inputs``,
    ``saturation``) and the loop each cycle's timing (``cycle_overran`` / ``cycle_on_time``); a
    fault latches in the supervisor and starts the ramp, which ``ramp_step`` advances once per
    sample. Nothing here allocates unless it trips.
    """

    def __init__(self, settings: SafetySettings, proportional_limit_strain: float, bias_voltage: float,
                 sample_rate_hz: float, voltages: np.ndarray) -> None:
        self.supervisor = Supervisor()
        self.voltages = voltages
        self.ramp = BiasRamp(bias_voltage, round(settings.ramp_time * sample_rate_hz))
        self.strain_limit = settings.strain_limit_fraction * proportional_limit_strain
        self._load_low, self._load_high = settings.load_range
        self._saturation_limit = max(1, round(settings.saturation_time * sample_rate_hz))
        self._stale_limit = settings.stale_periods
        self._overrun_limit = settings.overrun_streak
        self.answer_budget_s = settings.answer_budget_periods / sample_rate_hz
        self._late_limit = settings.late_answer_streak
        self.late_answers = 0
        self.late_streak = 0
        self.time_s = 0.0                 # time stamp of the latest sample, recorded with a fault
        self.saturated_samples = 0
        self.missing_samples = 0
        self.overrun_streak = 0
        self.max_overrun_streak = 0

    def clear(self) -> None:
        """Arming: the sample counts start again and the ramp is reset (overruns are the loop's
        and keep counting)."""
        self.ramp.reset()
        self.saturated_samples = 0
        self.missing_samples = 0
        self.late_streak = 0

    # -- faults and stops -------------------------------------------------------------------------
    def trip(self, fault: Fault, detail: str = "") -> None:
        """Latch ``fault`` (the first one wins) and ramp the voltages to bias from where they are
        (a stop's ramp already under way goes on)."""
        was = self.supervisor.state
        if self.supervisor.trip(fault, detail, self.time_s) and was != State.STOPPING:
            self.ramp.begin(self.voltages)

    def request_stop(self) -> None:
        """Ramp to bias and stop."""
        if self.supervisor.state in (State.RUNNING, State.ARMED, State.INIT):
            self.ramp.begin(self.voltages)
        self.supervisor.request_stop()

    def ramp_step(self) -> None:
        """One sample of the ramp to bias; a stop ends (STOPPED) once bias is reached."""
        if self.ramp.advance(self.voltages) and self.supervisor.state == State.STOPPING:
            self.supervisor.stopped()

    @property
    def at_bias(self) -> bool:
        return bool(np.all(self.voltages == self.ramp.bias))

    # -- what the controller reports each sample --------------------------------------------------
    def sample_arrived(self, time_s: float) -> None:
        self.missing_samples = 0
        self.time_s = time_s

    def sample_missing(self, silent_periods: float | None = None) -> None:
        """No new sample this cycle. ``silent_periods``: the time since the last valid sample, in
        periods, as the caller measured it; None counts one period per call (a timer-paced loop
        ticks once a period). ``stale_periods`` of silence fault a running controller."""
        self.missing_samples += 1
        silent = self.missing_samples if silent_periods is None else silent_periods
        if silent >= self._stale_limit and self.supervisor.state == State.RUNNING:
            self.trip(Fault.STALE_INPUT, f"{silent:.1f} periods without a valid sample")

    def answer_sent(self, age_s: float) -> None:
        """The answer to the latest sample was sent ``age_s`` after the sample arrived (NaN: not
        measured). Beyond the budget it is late; ``late_answer_streak`` late answers in a row
        fault a running controller."""
        if not age_s <= self.answer_budget_s:
            if age_s != age_s:
                return
            self.late_answers += 1
            self.late_streak += 1
            if self.late_streak >= self._late_limit and self.supervisor.state == State.RUNNING:
                self.trip(Fault.LATE_ANSWERS, f"{self.late_streak} answers in a row later than "
                                              f"{self.answer_budget_s * 1e6:.0f} us, the last "
                                              f"{age_s * 1e6:.0f} us")
        else:
            self.late_streak = 0

    def cap_strain_limit(self, full_scale: float, resolution: float) -> None:
        """The sensor cannot report strains beyond ``full_scale`` (it clips there): a reading
        within one ``resolution`` step of full scale is out of range too."""
        self.strain_limit = min(self.strain_limit, full_scale - 0.5 * resolution)

    def check_inputs(self, strains: np.ndarray, load_n: float) -> None:
        """Fault on a non-finite strain or one beyond the strain limit, then on a load-cell value
        that is non-finite or outside the sensor's range."""
        limit = self.strain_limit
        for i in range(4):
            e = strains[i]
            if not abs(e) <= limit:
                if e != e or abs(e) == math.inf:
                    self.trip(Fault.STRAIN_NOT_FINITE, f"strain {i} = {e}")
                else:
                    self.trip(Fault.STRAIN_OUT_OF_RANGE, f"strain {i} = {e:.3g}, limit {limit:.3g}")
                return
        if not self._load_low <= load_n <= self._load_high:
            if load_n != load_n or abs(load_n) == math.inf:
                self.trip(Fault.LOAD_NOT_FINITE, f"load = {load_n}")
            else:
                self.trip(Fault.LOAD_OUT_OF_SENSOR_RANGE,
                          f"load = {load_n:.1f} N, range [{self._load_low:g}, {self._load_high:g}] N")

    def saturation(self, saturated: bool) -> None:
        """A saturated allocation this sample; ``saturation_time`` of them in a row faults."""
        if saturated:
            self.saturated_samples += 1
            if self.saturated_samples >= self._saturation_limit:
                self.trip(Fault.PERSISTENT_SATURATION, f"saturated for {self.saturated_samples} samples")
        else:
            self.saturated_samples = 0

    # -- what the loop reports each cycle -----------------------------------------------------------
    def cycle_overran(self) -> None:
        """A cycle ended after its deadline; ``overrun_streak`` of them in a row fault."""
        self.overrun_streak += 1
        self.max_overrun_streak = max(self.max_overrun_streak, self.overrun_streak)
        if self.overrun_streak >= self._overrun_limit:
            self.trip(Fault.OVERRUN_STREAK, f"{self.overrun_streak} overruns in a row")

    def cycle_on_time(self) -> None:
        self.overrun_streak = 0
