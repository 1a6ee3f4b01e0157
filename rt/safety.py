"""Lifecycle and fault states of the controller, as in ros2_control's lifecycle.

    INIT --arm--> ARMED --start--> RUNNING --fault--> FAULT --rearm--> ARMED
                                     |  \\--stop--> STOPPING --(ramp done)--> STOPPED
                                     \\-- a fault while stopping also ends in FAULT

In ARMED the stacks sit at the bias voltage. Entering FAULT or STOPPING freezes the
integrator and ramps the voltages linearly from where they were to the bias within the
configured ramp time; the first fault's reason is latched until an operator re-arms.
"""

from __future__ import annotations

import enum


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


DESCRIPTIONS = {
    Fault.NONE: "no fault",
    Fault.STRAIN_NOT_FINITE: "a strain reading is not a finite number",
    Fault.STRAIN_OUT_OF_RANGE: "a strain reading exceeds the limit derived from the proportional limit",
    Fault.LOAD_NOT_FINITE: "the load-cell reading is not a finite number",
    Fault.LOAD_OUT_OF_SENSOR_RANGE: "the load-cell reading is outside the sensor range",
    Fault.LOAD_OUT_OF_TABLE_RANGE: "the axial load is outside the gain table's load range",
    Fault.STALE_INPUT: "no new sample for too many periods",
    Fault.OVERRUN_STREAK: "too many consecutive overruns of the control period",
    Fault.PERSISTENT_SATURATION: "the stack voltages stayed saturated for too long",
    Fault.HAL_ERROR: "the hardware abstraction reported an error",
    Fault.OPERATOR: "stopped by the operator",
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

    @property
    def controlling(self) -> bool:
        return self.state == State.RUNNING

    def reason(self) -> str:
        text = DESCRIPTIONS[self.fault]
        return f"{self.fault.name}: {text}" + (f" ({self.detail})" if self.detail else "")
