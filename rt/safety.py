"""Safety: the lifecycle and its latched fault (as in ros2_control's lifecycle), the names of
the states and faults, and the Python face of the counts and the ramp that the compiled engine
(rt/engine.py) keeps. The decisions themselves (input checks, saturation, missing samples,
late answers, overruns, the one ramp to bias) are made in the engine, every sample, and nowhere
else.

    INIT --arm--> ARMED --start--> RUNNING --fault--> FAULT --rearm--> ARMED
                                     |  \\--stop--> STOPPING --(ramp done)--> STOPPED
                                     \\-- a fault while stopping also ends in FAULT

In ARMED the stacks sit at the bias voltage. Entering FAULT or STOPPING freezes the
integrator and ramps the voltages linearly from where they were to the bias within the
configured ramp time; the first fault's reason is latched until an operator re-arms.
"""

from __future__ import annotations

import enum

import numpy as np

from beamctl.rt import engine as e


class State(enum.IntEnum):
    INIT = e.S_INIT
    ARMED = e.S_ARMED
    RUNNING = e.S_RUNNING
    FAULT = e.S_FAULT
    STOPPING = e.S_STOPPING
    STOPPED = e.S_STOPPED


class Fault(enum.IntEnum):
    NONE = e.F_NONE
    STRAIN_NOT_FINITE = e.F_STRAIN_NOT_FINITE
    STRAIN_OUT_OF_RANGE = e.F_STRAIN_OUT_OF_RANGE
    LOAD_NOT_FINITE = e.F_LOAD_NOT_FINITE
    LOAD_OUT_OF_SENSOR_RANGE = e.F_LOAD_OUT_OF_SENSOR_RANGE
    LOAD_OUT_OF_TABLE_RANGE = e.F_LOAD_OUT_OF_TABLE_RANGE
    STALE_INPUT = e.F_STALE_INPUT
    OVERRUN_STREAK = e.F_OVERRUN_STREAK
    PERSISTENT_SATURATION = e.F_PERSISTENT_SATURATION
    HAL_ERROR = e.F_HAL_ERROR
    OPERATOR = e.F_OPERATOR
    LATE_ANSWERS = e.F_LATE_ANSWERS


DESCRIPTIONS = {
    Fault.NONE: "no fault",
    Fault.STRAIN_NOT_FINITE: "a strain reading is not a finite number",
    Fault.STRAIN_OUT_OF_RANGE: "a strain reading exceeds the limit derived from the proportional limit",
    Fault.LOAD_NOT_FINITE: "the load-cell reading is not a finite number",
    Fault.LOAD_OUT_OF_SENSOR_RANGE: "the load-cell reading is outside the sensor range",
    Fault.LOAD_OUT_OF_TABLE_RANGE: "the axial load is outside the gain table's load range",
    Fault.STALE_INPUT: ("the stacks held a stale voltage longer than the beam rides through "
                        "(samples missing, or a silence)"),
    Fault.OVERRUN_STREAK: "too many consecutive overruns of the control period",
    Fault.PERSISTENT_SATURATION: "the stack voltages stayed saturated for too long",
    Fault.HAL_ERROR: "the hardware abstraction reported an error",
    Fault.OPERATOR: "stopped by the operator",
    Fault.LATE_ANSWERS: "a streak of samples was answered later than the delay the loop tolerates",
}


# the commands an operator gives the controller (``beamctl ctl``, the control socket; SIGUSR1 is a
# rearm); which is carried out in which state is ``Supervisor.refusal``'s to say, and nobody else's
OPERATOR_COMMANDS = ("start", "stop", "rearm", "gains")


class TransitionError(RuntimeError):
    """A lifecycle transition that is not allowed from the current state."""


class Supervisor:
    """The lifecycle state and the latched fault, as the engine holds them (``iv``), with the
    reason in words. The controller changes them through the engine's commands."""

    def __init__(self, safety: Safety) -> None:
        self._safety = safety
        self.python_detail = ""         # the detail of a fault latched from Python (a HAL error)

    @property
    def state(self) -> State:
        return State(int(self._safety.iv[e.V_STATE]))

    @property
    def fault(self) -> Fault:
        return Fault(int(self._safety.iv[e.V_FAULT]))

    @property
    def fault_time(self) -> float | None:
        return None if self.fault == Fault.NONE else float(self._safety.fv[e.X_FAULT_TIME])

    @property
    def detail(self) -> str:
        """The latched fault's detail: the values the engine recorded when it tripped, or the
        text of a fault latched from Python."""
        fault = self.fault
        if fault == Fault.NONE:
            return ""
        if self.python_detail:
            return self.python_detail
        iv, fv = self._safety.iv, self._safety.fv
        value, limit = float(fv[e.X_FAULT_VALUE]), float(fv[e.X_FAULT_LIMIT])
        channel = int(iv[e.V_FAULT_CHANNEL])
        if fault == Fault.STRAIN_NOT_FINITE:
            return f"strain {channel} = {value}" if channel >= 0 else "non-finite strain when starting"
        if fault == Fault.STRAIN_OUT_OF_RANGE:
            return f"strain {channel} = {value:.3g}, limit {limit:.3g}"
        if fault == Fault.LOAD_NOT_FINITE:
            return f"load = {value}"
        if fault == Fault.LOAD_OUT_OF_SENSOR_RANGE:
            low, high = self._safety.load_range_n
            return f"load = {value:.1f} N, range [{low:g}, {high:g}] N"
        if fault == Fault.LOAD_OUT_OF_TABLE_RANGE:
            return (f"filtered load {value:.1f} N outside the table's [{self._safety.table_first_n:g}, "
                    f"{limit:g}] N")
        if fault == Fault.STALE_INPUT:
            return (f"the stacks held a stale voltage for {value:.0f} samples; the live let-go was "
                    f"{limit:.0f} (the ride-through limit {float(fv[e.X_LIMIT]):.0f})")
        if fault == Fault.OVERRUN_STREAK:
            return f"{value:.0f} overruns in a row"
        if fault == Fault.PERSISTENT_SATURATION:
            return f"saturated for {value:.0f} samples"
        if fault == Fault.LATE_ANSWERS:
            return (f"{channel} answers in a row later than {limit * 1e6:.0f} us, the last "
                    f"{value * 1e6:.0f} us")
        return ""

    def refusal(self, command: str, stopping: bool = False) -> str:
        """Why the operator's ``command`` (one of OPERATOR_COMMANDS) cannot be carried out now,
        "" if it can: the lifecycle's rules, in one place. ``stopping``: the service is ending (a
        stop was asked for). The engine's own transitions (rt/engine.py, ``command``) accept
        every command this allows (tests/rt/test_safety.py)::

            stop    always (ramp to bias and end)
            start   from ARMED
            rearm   from FAULT once the ramp has reached bias (then a start, unless held)
            gains   at bias and not controlling: ARMED, or FAULT once the ramp has reached bias
        """
        if command not in OPERATOR_COMMANDS:
            raise ValueError(f"operator command {command!r}: expected one of {OPERATOR_COMMANDS}")
        state = self.state
        if command == "stop":
            return ""
        if state == State.STOPPING or stopping:
            return "the service is stopping"
        if state == State.INIT:
            return "the controller is not armed yet (no first sample from the HAL)"
        if command == "start":
            if state == State.RUNNING:
                return "the controller is already running"
            if state == State.FAULT:
                return f"a fault is latched ({self.reason()}): re-arm first"
            return "" if state == State.ARMED else f"the controller has {state.name.lower()}"
        if state == State.RUNNING:
            return ("the controller is running: no fault to re-arm" if command == "rearm" else
                    "the controller is running: the gain table changes only at bias (ARMED, or "
                    "FAULT once the ramp has reached bias)")
        if command == "rearm" and state != State.FAULT:
            return f"no fault is latched ({state.name}): nothing to re-arm"
        if command == "gains" and state not in (State.ARMED, State.FAULT):
            return f"the controller has {state.name.lower()}: the gain table changes only at bias"
        if not self._safety.at_bias:
            return f"the stacks are still ramping to bias after the fault: {command} once they are at bias"
        return ""

    def reason(self) -> str:
        fault = self.fault
        detail = self.detail
        return f"{fault.name}: {DESCRIPTIONS[fault]}" + (f" ({detail})" if detail else "")


class Safety:
    """The settings and counts of the controller's safety, read from the engine's arrays; the
    loop reports each cycle's timing here (``cycle_overran`` / ``cycle_on_time``) and the answer's
    age (``answer_sent``)."""

    def __init__(self, controller, iv: np.ndarray, fv: np.ndarray, load_range: tuple[float, float],
                 ramp_time_s: float) -> None:
        self._controller = controller
        self.iv, self.fv = iv, fv
        self.load_range_n = load_range
        self.ramp_time_s = ramp_time_s
        self.supervisor = Supervisor(self)

    @property
    def table_first_n(self) -> float:
        return float(self.fv[e.P_FIRST])

    @property
    def strain_limit(self) -> float:
        return float(self.fv[e.P_STRAIN_LIMIT])

    def cap_strain_limit(self, full_scale: float, resolution: float) -> None:
        """The sensor cannot report strains beyond ``full_scale`` (it clips there): a reading
        within one ``resolution`` step of full scale is out of range too."""
        self.fv[e.P_STRAIN_LIMIT] = min(self.strain_limit, full_scale - 0.5 * resolution)

    @property
    def answer_budget_s(self) -> float:
        return float(self.fv[e.P_BUDGET_S])

    @property
    def gap_limit(self) -> int:
        """Samples missing in a row that the loop rides through (more: STALE_INPUT): the live
        let-go (gains/ridethrough.py ``LET_GO_SIGMA``), never below the live ride-through limit."""
        return int(self.iv[e.V_GAP_LIMIT])

    @property
    def late_limit(self) -> int:
        """Late answers in a row that the loop rides through (more: LATE_ANSWERS)."""
        return int(self.iv[e.V_LATE_LIMIT])

    @property
    def late_answers(self) -> int:
        return int(self.iv[e.V_LATE_TOTAL])

    @property
    def late_streak(self) -> int:
        return int(self.iv[e.V_LATE_STREAK])

    @property
    def saturated_samples(self) -> int:
        return int(self.iv[e.V_SATURATED])

    @property
    def bridged_samples(self) -> int:
        """Samples bridged (the compensator caught up on them) since the controller was built."""
        return int(self.iv[e.V_BRIDGED])

    @property
    def longest_gap(self) -> int:
        return int(self.iv[e.V_MAX_GAP])

    @property
    def max_overrun_streak(self) -> int:
        return int(self.iv[e.V_OVERRUN_MAX])

    @property
    def overrun_streak(self) -> int:
        return int(self.iv[e.V_OVERRUN_STREAK])

    @property
    def at_bias(self) -> bool:
        return bool(np.all(self._controller.voltages == self.fv[e.P_BIAS]))

    def answer_sent(self, age_s: float) -> None:
        self._controller.answer_sent(age_s)

    def cycle_overran(self) -> None:
        """A cycle ended after its deadline; ``overrun_streak`` of them in a row fault."""
        self._controller._command(e.C_OVERRAN)

    def cycle_on_time(self) -> None:
        self._controller._command(e.C_ON_TIME)
