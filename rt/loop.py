"""The fixed-rate loop: read -> step -> write -> telemetry, with per-stage timing.

Pacing:
- ``timer``: absolute deadlines t0 + k T on the monotonic clock; sleep until ``spin_time``
  before the deadline, then spin. After an overrun the loop skips ahead to the next deadline
  in the future and counts the missed periods (as ros2_control does), never running a burst
  of catch-up cycles. A streak of overruns is a fault (rt.safety counts it).
- ``sample``: one step per new sample from the HAL, so a DAQ streaming at its own clock (or
  a simulated plant in simulated time) sets the rate. Each sample is answered by exactly one
  write; a read time-out writes only while the voltages ramp to bias (a backend whose answers
  pair with samples, CAN, sends nothing for it). When more samples are missing, in time measured
  on the loop's clock, than the controller rides through (its let-go, ``safety.gap_limit``), a
  running controller faults.

Each answer's age (the sample's arrival to the answer having been sent, where the HAL measures
it) goes to the engine, which counts late answers against the answer budget, and is recorded
with the sample.

Start-up order: the controller's cycle warmed (every engine entry point compiled or loaded and
run through its controlled path on a copy of the controller's arrays: no first sample waits for
a compilation), real-time set-up (SCHED_FIFO, memory lock, the garbage collector collected and
frozen), then the HAL is opened (if the caller has not), then whatever the HAL queued
before the controller was ready is discarded and counted, all but the newest sample, which arms.
At the end the final state is announced to the hardware (the DAQ sees STOPPED or FAULT).

The loop installs no signal handler: a command that wants SIGINT and SIGTERM to stop the run
installs them (common/signals.py ``stop_on_signals``) and passes the ``StopRequest`` they set.
The loop looks at it every cycle: the voltages ramp to bias, telemetry is flushed, and ``run``
returns normally; ``RunResult.signal_received`` names the signal, so that the caller decides
what it means (the service: the operator's stop; a simulated experiment: cut short). Without a
request, a KeyboardInterrupt leaves the loop through the emergency ramp to bias.

Operator commands (start, stop, rearm, gains: ``OperatorCommand``) come from another thread (the
service's control socket, service/control.py) through ``post``; the loop carries out or refuses
a pending command after the cycle's read, before its step (a re-arm starts from the cycle's
sample), and records it in the sample's ``operator_command`` column (``operator_labels``). A
cycle without a pending command checks one attribute. The loop alone changes the controller:
a gain table comes prepared (loaded, checked, its arrays allocated) and the loop only swaps it in.

Offline runs only: an ``accelerator`` (simulation/simkernel.py) is offered each cycle before the
read and may run cycles of a simulated run in one compiled loop that calls the engine's cycle
itself; it returns how many, and leaves the cycles after a fault or stop, and any cycle with a
command, a re-arm or a stop request, to the loop.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from beamctl.hal.base import HalBase, HalError, HalStaleData
from beamctl.rt import realtime
from beamctl.rt.controller import (
    FLAG_RAMPING_TO_BIAS,
    I_FAULT,
    I_FLAGS,
    I_GAP_LIMIT,
    I_HELD,
    I_INPUT_PERIOD_US,
    I_LOAD,
    I_OPERATOR_COMMAND,
    I_STATE,
    I_STEP_US,
    Controller,
    PreparedTable,
)
from beamctl.rt.record import operator_code, operator_labels  # noqa: F401 (re-exported)
from beamctl.rt.safety import OPERATOR_COMMANDS, Fault, State
from beamctl.rt.stop import StopRequest
from beamctl.rt.telemetry import TelemetryWriter
from beamctl.rt.timing import LoopTiming


class OperatorCommand:
    """An operator's command for the loop: another thread posts it (``ControlLoop.post``) and
    waits for its outcome (``wait``, then ``outcome``: "carried out" or "refused", with the
    ``refusal`` saying why and ``transition`` the state before and after). ``gains`` carries the
    table prepared off the loop (``Controller.prepare_table``); a command refused before it
    reaches the loop (a table that failed its checks) is posted with its ``refusal`` so that the
    loop records it in the telemetry like any other. A waiter that gives up calls ``cancel``."""

    def __init__(self, name: str, table: PreparedTable | None = None, refusal: str = "") -> None:
        if name not in OPERATOR_COMMANDS:
            raise ValueError(f"operator command {name!r}: expected one of {OPERATOR_COMMANDS}")
        if name == "gains" and table is None and not refusal:
            raise ValueError("a gains command needs the prepared table (or the reason it was refused)")
        self.name = name
        self.table = table
        self.refusal = refusal
        self.outcome = ""               # "carried out" or "refused" once the loop has decided
        self.transition = ""            # "ARMED -> RUNNING"
        self.cycle = -1                 # the loop's cycle (telemetry row) that recorded it
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._taken = False
        self._cancelled = False

    @property
    def code(self) -> int:
        """Its ``operator_command`` code (once decided)."""
        return operator_code(self.name, self.outcome == "carried out")

    def wait(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for the outcome; True once decided."""
        return self._done.wait(timeout_s)

    def cancel(self) -> bool:
        """Withdraw the command unless the loop has taken it up; True when withdrawn (it will
        never be carried out), False when the outcome is decided or about to be."""
        with self._lock:
            if self._taken:
                return False
            self._cancelled = True
            return True

    @property
    def cancelled(self) -> bool:
        return self._cancelled

    def _take(self) -> bool:
        with self._lock:
            if self._cancelled:
                return False
            self._taken = True
            return True

    def _decide(self, refusal: str, transition: str = "", cycle: int = -1) -> None:
        self.refusal = refusal
        self.outcome = "refused" if refusal else "carried out"
        self.transition = transition
        self.cycle = cycle
        self._done.set()



@dataclass
class RunResult:
    state: str
    fault: str
    reason: str
    cycles: int
    stop_requested_by: str
    timing: dict
    telemetry: dict = field(default_factory=dict)
    realtime: dict = field(default_factory=dict)
    hal: dict = field(default_factory=dict)
    backlog_discarded: int = 0    # samples queued before the first read, dropped unanswered
    signal_received: str = ""     # SIGINT or SIGTERM during the run, even after another stop request


class ControlLoop:
    """Runs a controller against a HAL until stopped, faulted (if ``stop_on_fault``), or a
    cycle/time limit is reached (then it stops like on SIGTERM)."""

    def __init__(self, controller: Controller, hal: HalBase, *, pacing: str | None = None,
                 telemetry: TelemetryWriter | None = None, max_cycles: int | None = None,
                 stop_on_fault: bool = True, start: bool = True, spin_time: float = 2e-4,
                 clock: Callable[[], float] = time.perf_counter,
                 sleep: Callable[[float], None] = time.sleep,
                 on_cycle: Callable[[ControlLoop], None] | None = None,
                 stop: StopRequest | None = None,
                 accelerator: Callable[[ControlLoop], int] | None = None) -> None:
        self.controller = controller
        self.stop = stop
        self.hal = hal
        self.pacing = pacing or controller.config.pacing
        if self.pacing not in ("timer", "sample"):
            raise ValueError(f"pacing must be 'timer' or 'sample', got {self.pacing!r}")
        self.telemetry = telemetry
        self.max_cycles = max_cycles
        self.stop_on_fault = stop_on_fault
        self.start = start
        self._rearm_requested = False
        self._signal_command: OperatorCommand | None = None
        # told the outcome of a command a signal gave (request_rearm), once it is decided
        self.on_signal_command: Callable[[OperatorCommand], None] | None = None
        self.spin_time = spin_time
        self.clock = clock
        self.sleep = sleep
        self.on_cycle = on_cycle
        # offline runs only (simulation/simkernel.py): offered each cycle, it runs the cycles it can
        # (the engine's cycle in a compiled loop) and returns how many; 0 leaves the next to the loop
        self.accelerator = accelerator
        self.timing = LoopTiming()
        self.period_s = controller.period_s
        self.cycles = 0
        self.backlog_discarded = 0
        self._stop_signal = ""
        self._signal_received = ""
        self._command: OperatorCommand | None = None
        self._command_lock = threading.Lock()
        self.ended = False              # run() has returned: no command is carried out any more

    # -- stopping ---------------------------------------------------------------------------------
    def request_stop(self, why: str = "request") -> None:
        """Thread- and signal-safe: the loop ramps to bias and ends."""
        if not self._stop_signal:
            self._stop_signal = why

    def request_rearm(self) -> None:
        """The operator's re-arm from a signal (SIGUSR1; signal- and thread-safe): at the next
        cycle the loop posts it as the control socket's ``rearm``, decided by the same rules and
        recorded in the telemetry the same way; ``on_signal_command`` is told its outcome (the
        service logs it)."""
        self._rearm_requested = True

    # -- operator commands --------------------------------------------------------------------------
    def post(self, command: OperatorCommand) -> None:
        """Hand ``command`` to the loop (thread-safe): it is decided at the next cycle (a re-arm at
        the next cycle with a sample). Refused at once, never reaching the loop, while another
        command is pending or once the loop has ended."""
        with self._command_lock:
            pending = self._command
            if self.ended:
                command._decide(f"the control loop has ended ({self.controller.state.name})")
            elif pending is not None and not pending.cancelled:
                command._decide(f"the {pending.name} command before it is still being carried out")
            else:
                self._command = command

    def status(self) -> dict:
        """What an operator sees (safe to call from any thread; the values are a snapshot):
        state, fault and its reason, whether the stacks are at bias, the load-cell reading in N
        (None before the first sample) and the cycles run."""
        c = self.controller
        load = float(c.record[I_LOAD])
        return {"state": c.state.name, "fault": c.supervisor.fault.name, "reason": c.supervisor.reason(),
                "at_bias": c.at_bias, "axial_load_n": load if math.isfinite(load) else None,
                "cycles": self.cycles}

    def refusal(self, name: str) -> str:
        """Why the controller cannot take the operator command ``name`` now ("" if it can): the
        supervisor's rules (rt/safety.py). Safe to ask from another thread, but only the loop's
        own answer, when it carries the command out, decides."""
        return self.controller.supervisor.refusal(name, stopping=bool(self._stop_signal))

    def _carry_out(self, sample) -> float:
        """Decide the pending command at this cycle's ``sample``; return its telemetry code (0.0
        when there is none to record: withdrawn, or a re-arm waiting for a sample)."""
        command = self._command
        refusal = command.refusal or self.refusal(command.name)
        if not refusal and command.name == "rearm" and sample is None:
            return 0.0                  # a re-arm starts from a sample: the next one
        with self._command_lock:
            self._command = None
        if not command._take():
            return 0.0
        c = self.controller
        before = c.state
        if not refusal:
            name = command.name
            if name == "start":
                c.start()
            elif name == "stop":
                self.request_stop("operator")
                if c.state not in (State.STOPPING, State.STOPPED):
                    c.request_stop()
            elif name == "rearm":
                c.rearm(sample)
                if self.start:
                    c.start()
            else:
                c.use_table(command.table)
        command._decide(refusal, f"{before.name} -> {c.state.name}", self.cycles)
        return float(command.code)

    def _signal_decided(self) -> None:
        command, self._signal_command = self._signal_command, None
        self._rearm_requested = False   # signals while it was pending asked for the same re-arm
        if self.on_signal_command is not None:
            self.on_signal_command(command)

    def _end_commands(self) -> None:
        """The loop has ended: a pending command is refused, later ones too (``post``)."""
        with self._command_lock:
            self.ended = True
            command, self._command = self._command, None
        if command is not None and command._take():
            command._decide(f"the control loop ended ({self.controller.state.name}) before carrying it out")
        if self._signal_command is None and self._rearm_requested:    # signalled, not yet posted
            self._signal_command = OperatorCommand("rearm")
            self._signal_command._decide(f"the control loop ended ({self.controller.state.name}) "
                                         "before carrying it out")
        if self._signal_command is not None and self._signal_command.outcome:
            self._signal_decided()

    # -- the loop ---------------------------------------------------------------------------------
    def run(self, require_rt: bool = False, acquire_rt: bool = False) -> RunResult:
        """Open the HAL, arm (and start unless held) and cycle until done; the ramp to bias on
        any way out. ``acquire_rt``: take the controller config's real-time set-up first
        (SCHED_FIFO, affinity, locked memory, the collector frozen) and release it after; the
        service asks for it (service/run.py), offline runs and tests do not. ``require_rt``: refuse
        to run without it."""
        rt_report = {}
        # everything the cycle calls compiled, loaded and run once before it arms: a first
        # sample answered late by a compilation is a stall of the loop's own making
        self.warm_up_s = self.controller.warm()
        try:
            if acquire_rt:
                rt_report = realtime.acquire(self.controller.config.realtime, require_rt)
            self.hal.open()             # after the real-time set-up: nothing queues meanwhile
            self._arm()
            cpu0, wall0 = time.thread_time(), time.monotonic()
            try:
                self._cycle_until_done()
            except BaseException:       # a bug, or an exit from a callback: the stacks first
                self._emergency_ramp()
                raise
            finally:
                self._announce()
                wall = time.monotonic() - wall0
                if wall > 0.0:
                    self.timing.cpu_share = (time.thread_time() - cpu0) / wall
        finally:
            self._end_commands()
            if acquire_rt:
                realtime.release()
            if self.telemetry is not None:
                self.telemetry.close()
        c = self.controller
        tel = {}
        if self.telemetry is not None:
            tel = {"path": str(self.telemetry.path), "written": self.telemetry.written,
                   "received": self.telemetry.received, "dropped": self.telemetry.dropped,
                   "mode": self.telemetry.recording.mode}
        timing = {**self.timing.summary(), "max_overrun_streak": c.safety.max_overrun_streak}
        return RunResult(state=c.state.name, fault=c.supervisor.fault.name, reason=c.supervisor.reason(),
                         cycles=self.cycles, stop_requested_by=self._stop_signal,
                         timing=timing, telemetry=tel, realtime=rt_report,
                         hal=self.hal.status(), signal_received=self._signal_received,
                         backlog_discarded=self.backlog_discarded)

    def _announce(self) -> None:
        """Tell the hardware the final state now (the DAQ sees STOPPED, or the fault)."""
        c = self.controller
        try:
            self.hal.announce(c.state, c.supervisor.fault, int(c.record[I_FLAGS]))
        except HalError:
            pass            # the HAL is gone: the DAQ falls back on the silence

    def _arm(self) -> None:
        c = self.controller
        c.cap_gap_limit(getattr(self.hal, "daq_silence_timeout_s", None))
        full_scale = self.hal.strain_full_scale
        if full_scale is not None:
            c.safety.cap_strain_limit(full_scale, getattr(self.hal, "strain_lsb", 0.0))
        try:
            self.backlog_discarded = self.hal.discard_backlog()
            first = self.hal.read(timeout=max(1.0, 20 * self.period_s))
        except HalError as exc:
            c.arm(None)
            c.fault(Fault.HAL_ERROR, f"no first sample: {exc}")
            return
        c.arm(first)
        if self.start:
            c.start()
        try:        # the first sample is answered too: the stacks at bias
            self.hal.publish_status(c.state, c.supervisor.fault)
            self.hal.write(c.voltages)
        except HalError as exc:
            c.fault(Fault.HAL_ERROR, f"write: {exc}")

    def _emergency_ramp(self) -> None:
        """An unexpected error left the loop: bring the stacks from the last voltages to bias
        along the safety's ramp, writing each step directly to the HAL, before the error
        propagates."""
        c = self.controller
        c.emergency_ramp_begin()
        while not c.emergency_ramp_advance():
            try:
                self.hal.write(c.voltages)
            except Exception:   # the HAL is gone too: nothing more can be sent
                return
            time.sleep(self.period_s)

    def _finished(self) -> bool:
        c = self.controller
        state = c.state
        if state == State.STOPPED:
            return True
        if state == State.FAULT and (self.stop_on_fault or self._stop_signal) and c.at_bias:
            return True
        return False

    def _cycle_until_done(self) -> None:
        c, hal, timing, clock = self.controller, self.hal, self.timing, self.clock
        safety = c.safety
        tel = self.telemetry
        period = self.period_s
        timer = self.pacing == "timer"
        read_timeout = 0.5 * period if timer else 1.5 * period
        record = c.record
        next_deadline = clock() + period
        self._last_sample = clock()         # the arming sample
        previous_start = None
        stop = self.stop
        accelerator = self.accelerator
        while True:
            if stop is not None and stop.reason:
                if stop.signal_name:
                    self._signal_received = stop.signal_name
                self.request_stop(stop.reason)
            if self._stop_signal and c.state not in (State.STOPPING, State.STOPPED):
                c.request_stop()
            if self.max_cycles is not None and self.cycles >= self.max_cycles:
                self.request_stop("cycle limit")
            if accelerator is not None and accelerator(self):
                previous_start = None       # the accelerated cycles have no timing of their own
                continue
            t0 = clock()
            if previous_start is not None:
                timing.cycle.record(t0 - previous_start)   # start to start
            previous_start = t0
            timeout = read_timeout
            if not timer:
                state = c.state
                if state == State.RUNNING:
                    # wait no longer than the stale-input deadline (and a little, to see it pass):
                    # beyond it more samples are missing than the loop rides through at this load
                    stale_s = (safety.gap_limit + 1.0) * period
                    timeout = min(read_timeout, max(self._last_sample + stale_s - t0, 0.1 * period))
                elif state in (State.FAULT, State.STOPPING) and not c.at_bias:
                    timeout = period    # a ramp without samples still takes its time, not 1.5x
            try:
                sample = hal.read(timeout=timeout)
            except HalStaleData:
                sample = None
            except HalError as exc:
                sample = None
                c.fault(Fault.HAL_ERROR, str(exc))
            t1 = clock()
            if sample is not None:
                self._last_sample = t1
            if self._rearm_requested and self._signal_command is None:
                self._rearm_requested = False
                self._signal_command = OperatorCommand("rearm")
                self.post(self._signal_command)     # refused at once while another is pending
            operator = 0.0
            if self._command is not None:
                operator = self._carry_out(sample)
                record = c.record       # a new gain table brings its own record
            if self._signal_command is not None and self._signal_command.outcome:
                self._signal_decided()
            if sample is None and not timer:
                voltages = c.step(None, (t1 - self._last_sample) / period)
            else:
                voltages = c.step(sample)
            t2 = clock()
            record[I_OPERATOR_COMMAND] = operator
            flags = int(record[I_FLAGS])
            if timer or sample is not None or flags & FLAG_RAMPING_TO_BIAS:
                try:
                    hal.publish_status(record[I_STATE], record[I_FAULT], flags)
                    hal.write(voltages)
                except HalError as exc:
                    c.fault(Fault.HAL_ERROR, f"write: {exc}")
                else:
                    age = hal.answer_age_s
                    if sample is not None and age == age:
                        timing.answer_age.record(age)
                        c.answer_sent(age)
                if sample is not None and record[I_INPUT_PERIOD_US] > 0:
                    timing.input_period.record(record[I_INPUT_PERIOD_US] * 1e-6)
                if sample is not None and record[I_HELD] > 0.0 and record[I_FAULT] == 0:
                    timing.stalls.record(record[I_HELD], record[I_GAP_LIMIT])     # ridden through
            t3 = clock()
            record[I_STEP_US] = (t2 - t1) * 1e6
            if tel is not None:
                tel.push(record)
            timing.read.record(t1 - t0)
            timing.compute.record(t2 - t1)
            timing.write.record(t3 - t2)
            self.cycles += 1
            if self.on_cycle is not None:
                self.on_cycle(self)
            if self._finished():
                return
            if not timer:
                continue
            now = clock()
            if now > next_deadline:
                # overrun: skip to the first deadline still ahead, count what was missed
                timing.overruns += 1
                missed = int((now - next_deadline) / period) + 1
                timing.missed_periods += missed
                next_deadline += missed * period
                c.safety.cycle_overran()
            else:
                c.safety.cycle_on_time()
            remaining = next_deadline - self.spin_time - clock()
            if remaining > 0:
                self.sleep(remaining)
            while clock() < next_deadline:
                pass
            next_deadline += period
