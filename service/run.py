"""The lab service as an object: the control loop, its telemetry, the control socket, the live
view and systemd's watchdog, owned together. ``beamctl run`` builds one and prints its summary;
a test or a script can start one in-process (``start`` in a thread of its own, commanded over
its control socket like the real one, ``request_stop``).

Building it checks everything a start needs (the gain table, the backend's settings, the voltage
range against the DBC) and binds the control socket, so that a second service on the same
socket is refused before anything moves; ``run`` starts telemetry, takes the real-time set-up
(the service acquires it, not the loop by default), opens the HAL, arms and runs until stopped:
by SIGINT/SIGTERM when run on the main thread, by ``request_stop``, by the control socket's
``stop``, or after ``duration_s``. A fault ramps the stacks to bias and holds them there,
latched, until ``rearm`` (the control socket, or SIGUSR1 on the main thread).
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from beamctl.assembly import live as live_view
from beamctl.assembly.run import ServiceConfig, build_hal, check_voltage_range, load_gain_table
from beamctl.common.signals import stop_on_signals
from beamctl.gains.table import GainTable
from beamctl.hal.base import HalBase, HalError
from beamctl.rt import realtime
from beamctl.rt.controller import Controller
from beamctl.rt.loop import ControlLoop, OperatorCommand, RunResult, StopRequest
from beamctl.rt.telemetry import TelemetryWriter
from beamctl.service.control import ControlError, default_socket_path
from beamctl.service.control_server import ControlServer
from beamctl.service.sdnotify import Notifier
from beamctl.service.swaps import TableSwaps


class ServiceError(Exception):
    """The service cannot start (or its loop could not begin): one line for the operator."""


@dataclass
class ServiceResult:
    """How a run ended: the loop's result, the late answers, the live view's figures (or None)."""

    result: RunResult
    late_answers: int
    live: dict[str, Any] | None = None
    summary: dict[str, Any] = field(default_factory=dict)


class Service:
    """One run of the controller service (see the module docstring)."""

    def __init__(self, cfg: ServiceConfig, telemetry_path: str | Path, *,
                 control_socket: str | Path | None = None, live: str | None = None, hold: bool = False,
                 duration_s: float | None = None, require_rt: bool = False, acquire_rt: bool = True,
                 notifier: Notifier | None = None, log: Callable[[str], None] = lambda line: None,
                 table: GainTable | None = None, hal: HalBase | None = None) -> None:
        self.cfg = cfg
        self.telemetry_path = Path(telemetry_path)
        self.hold = hold
        self.require_rt = require_rt
        self.acquire_rt = acquire_rt
        self.log = log
        self.notifier = notifier or Notifier()
        self.table = table if table is not None else load_gain_table(cfg)
        rate = self.table.design.sample_rate_hz
        duration_s = cfg.duration_s if duration_s is None else duration_s
        self.max_cycles = int(duration_s * rate) if duration_s else None
        try:
            self.hal = hal if hal is not None else build_hal(cfg, self.table)
        except HalError as exc:         # the hal section describes a bus or DBC it cannot have
            raise ServiceError(f"{cfg.source}: hal.{cfg.hal.backend}: {exc}") from None
        check_voltage_range(cfg, self.hal)
        self.controller = Controller(self.table, cfg.controller)
        try:
            self.server = ControlServer(control_socket or cfg.control_socket or default_socket_path())
        except ControlError as exc:
            raise ServiceError(str(exc)) from None
        self.live = None
        if live is not None:
            title = f"beamctl run, {cfg.hal.backend} backend"
            self.live = live_view.live_publisher(live, self.controller, title, table_path=str(cfg.table_path))
        self.loop: ControlLoop | None = None
        self.outcome: ServiceResult | None = None
        self.error: BaseException | None = None
        self._stop = StopRequest()
        self._started = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def socket_path(self) -> Path:
        return Path(self.server.path)

    # -- running ---------------------------------------------------------------------------------
    def run(self) -> ServiceResult:
        """Run until stopped; the summary of the run. Raises ServiceError if the loop could not
        begin (real-time set-up refused with ``require_rt``, the HAL could not open): a
        telemetry file with nothing in it is then removed."""
        created = [d for d in (self.telemetry_path.parent, *self.telemetry_path.parent.parents)
                   if not d.exists()]   # deepest first
        cfg, table = self.cfg, self.table
        meta = {"config": cfg.source, "gain_table": str(cfg.table_path), "model_sha256": table.model_sha256,
                "backend": cfg.hal.backend}
        # Telemetry starts before the loop asks for SCHED_FIFO (the writer thread must not inherit
        # it); the loop then takes its real-time set-up and only after it opens the HAL, so that no
        # sample queues up while memory is locked and the collector runs.
        telemetry = TelemetryWriter.for_controller(self.telemetry_path, self.controller, meta=meta,
                                                   live=self.live).start()
        notifier = self.notifier

        def on_cycle(loop: ControlLoop) -> None:
            notifier.feed()

        main = threading.current_thread() is threading.main_thread()
        with stop_on_signals(signal.SIGINT, signal.SIGTERM) as signals:     # the operator's stop
            stop = signals if main else self._stop
            self._stop = stop
            loop = ControlLoop(self.controller, self.hal, telemetry=telemetry, stop_on_fault=False,
                               max_cycles=self.max_cycles,
                               on_cycle=on_cycle if notifier.watchdog_interval_s else None,
                               stop=stop, start=not self.hold)
            self.loop = loop
            swaps = TableSwaps(cfg, self.hal, self.controller)
            self.server.serve(loop, table=str(Path(cfg.table_path).absolute()), table_sha256=table.sha256,
                              prepare_table=swaps.prepare, log=self.log)
            if self.live is not None:
                live_view.watch_loop(self.live, loop, telemetry, table_path=lambda: self.server.table)
            rearm = signal.signal(signal.SIGUSR1, lambda *_: loop.request_rearm()) if main else None
            loop.on_signal_command = self._log_signal_command
            notifier.ready(f"running at {table.design.sample_rate_hz:g} Hz")
            self._started.set()
            try:
                result = loop.run(require_rt=self.require_rt, acquire_rt=self.acquire_rt)
            except (realtime.RealtimeError, HalError) as exc:
                if telemetry.written == 0:      # refused before the first sample: no recording to keep
                    self.telemetry_path.unlink(missing_ok=True)
                    for directory in created:
                        try:
                            directory.rmdir()
                        except OSError:
                            break
                raise ServiceError(str(exc)) from None
            finally:
                if rearm is not None:
                    signal.signal(signal.SIGUSR1, rearm)
                notifier.stopping()
                self.server.close()          # no command after the loop: the reader process can end
                swaps.close()
                self.hal.close()
                if self.live is not None:
                    self.live.close()
        live = None
        if self.live is not None:
            live = {"path": self.live.path, "sent": self.live.sent, "dropped": self.live.dropped,
                    "error": telemetry.live_error}
        self.outcome = ServiceResult(result=result, late_answers=self.controller.safety.late_answers,
                                     live=live)
        self.outcome.summary = self._summary()
        return self.outcome

    def _log_signal_command(self, command: OperatorCommand) -> None:
        """The outcome of SIGUSR1's re-arm, as the control socket logs its commands (called in the
        control loop: the line is written by the control socket's thread)."""
        outcome = (f"carried out ({command.transition})" if command.outcome == "carried out"
                   else f"refused: {command.refusal}")
        self.server.log_later(f"operator {command.name} (SIGUSR1): {outcome}")

    def _summary(self) -> dict[str, Any]:
        o = self.outcome
        r = o.result
        summary = {"state": r.state, "fault": r.fault, "reason": r.reason, "cycles": r.cycles,
                   "late_answers": o.late_answers, "backlog_discarded": r.backlog_discarded,
                   "stopped_by": r.stop_requested_by, "realtime": r.realtime,
                   "timing": r.timing, "telemetry": r.telemetry, "hal": r.hal}
        if o.live is not None:
            summary["live"] = o.live
        return summary

    def start(self, timeout_s: float = 30.0) -> Service:
        """Run in a thread of this process (no signal handlers: stop with ``request_stop`` or
        the control socket); return once the loop is about to start (its socket answers)."""
        def target() -> None:
            try:
                self.run()
            except BaseException as exc:    # kept for ``join``
                self.error = exc
            finally:
                self._started.set()
        self._thread = threading.Thread(target=target, name="beamctl-service", daemon=True)
        self._thread.start()
        if not self._started.wait(timeout_s):
            raise ServiceError(f"the service did not start within {timeout_s:g} s")
        if self.error is not None:
            raise self.error
        return self

    def request_stop(self, reason: str = "request") -> None:
        """Stop the run as the operator's stop does: the stacks ramp to bias, the run ends."""
        self._stop.set(reason, reason)

    def join(self, timeout_s: float | None = None) -> ServiceResult:
        """Wait for a started service to end; its summary (re-raises what ended it otherwise)."""
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                raise ServiceError(f"the service did not stop within {timeout_s:g} s")
        if self.error is not None:
            raise self.error
        assert self.outcome is not None
        return self.outcome

    def close(self) -> None:
        """Release what a service that never ran holds (its control socket, the live view)."""
        self.server.close()
        if self.live is not None:
            self.live.close()
