"""``beamctl run``: the controller service against the lab's DAQ (or any configured HAL).

Loads and validates the config and the gain table (whose model hash must match the
configured model, whose content must match its own hash, and whose closed-loop check must
have passed), checks the bus budget (CAN), starts telemetry, takes the real-time set-up, opens
the HAL, discards what queued before it was ready, arms, runs until SIGINT/SIGTERM. A fault
ramps the stacks to bias and holds them there, latched, until the operator
re-arms with SIGUSR1 (``systemctl kill -s USR1 beamctl``) or stops the service. Under systemd
it reports readiness and feeds the watchdog from the control loop. With ``--live`` the telemetry
writer also sends decimated records to ``beamctl monitor`` (rt/live.py), never waiting for it.

The operator commands the running service over its control socket (service/control.py, ``beamctl
ctl``): start (after ``--hold``, which arms and waits at bias), stop, rearm, gains TABLE, status.
The socket is bound before anything else starts, so a second service on the same socket is
refused in one line.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from pathlib import Path

from beamctl.common.outputs import check_file, check_new_file
from beamctl.common.signals import stop_on_signals
from beamctl.gains.table import GainTable
from beamctl.hal.base import HalBase, HalError
from beamctl.rt import realtime
from beamctl.rt.controller import Controller
from beamctl.rt.live import check_socket_path
from beamctl.rt.loop import ControlLoop
from beamctl.rt.telemetry import TelemetryWriter
from beamctl.service import live as live_view
from beamctl.service.control import ControlError, ControlServer, default_socket_path
from beamctl.service.sdnotify import Notifier
from beamctl.service.setup import (
    ServiceConfig,
    TableSwaps,
    build_hal,
    check_voltage_range,
    load_gain_table,
    load_service_config,
)
from beamctl.tools.argtypes import seconds


def add_parser(sub) -> None:
    p = sub.add_parser("run", help="the controller service (lab: against the CAN DAQ)")
    p.add_argument("--config", metavar="F", required=True, help="service config, e.g. deploy/lab.yaml")
    p.add_argument("--telemetry", metavar="FILE", help="telemetry file (default: run.telemetry or "
                                                        "beamctl-<time>.btl)")
    p.add_argument("--duration", type=seconds, metavar="S",
                   help="stop after S seconds (default: run.duration_s; 0 until stopped)")
    p.add_argument("--require-rt", action="store_true",
                   help="refuse to run without SCHED_FIFO, affinity and locked memory")
    p.add_argument("--hold", action="store_true",
                   help="arm and hold the stacks at bias until `beamctl ctl start`")
    p.add_argument("--control-socket", metavar="PATH",
                   help="the control socket for `beamctl ctl` (default: control.socket, else "
                        "$BEAMCTL_CONTROL_SOCKET, /run/beamctl/control.sock, $XDG_RUNTIME_DIR/beamctl/"
                        "control.sock or /tmp/beamctl-UID/control.sock)")
    p.add_argument("--json", action="store_true", help="print the run summary as JSON")
    live_view.add_live_argument(p)
    p.set_defaults(run=run)


def _output_paths(args: argparse.Namespace, cfg) -> Path:
    """The telemetry file, and the CAN recording if one is configured, checked; return the
    telemetry file."""
    if cfg.hal.backend == "can" and cfg.hal.can["record"]:
        check_file(cfg.hal.can["record"], f"{cfg.source}: hal.can.record")
    if args.telemetry:
        return check_new_file(args.telemetry, "--telemetry")
    if cfg.telemetry:
        return check_new_file(cfg.telemetry, f"{cfg.source}: run.telemetry")
    return check_new_file("beamctl-%Y%m%d-%H%M%S.btl", "telemetry")


def run(args: argparse.Namespace) -> int:
    cfg = load_service_config(args.config)
    if args.live is not None:
        check_socket_path(args.live, "--live")
    path = _output_paths(args, cfg)
    table = load_gain_table(cfg)
    notifier = Notifier()
    try:
        hal = build_hal(cfg, table)
    except HalError as exc:             # the hal section describes a bus or DBC it cannot have
        print(f"beamctl run: error: {cfg.source}: hal.{cfg.hal.backend}: {exc}", file=sys.stderr)
        return 2
    check_voltage_range(cfg, hal)
    controller = Controller(table, cfg.controller)
    try:
        server = ControlServer(args.control_socket or cfg.control_socket or default_socket_path())
    except ControlError as exc:
        print(f"beamctl run: error: {exc}", file=sys.stderr)
        return 2
    try:
        return _serve(args, cfg, path, table, hal, controller, notifier, server)
    finally:
        server.close()


def _log(line: str) -> None:
    """A line of the service's log (stderr, where systemd's journal takes it)."""
    print(f"beamctl run: {line}", file=sys.stderr, flush=True)


def _serve(args: argparse.Namespace, cfg: ServiceConfig, path: Path, table: GainTable, hal: HalBase,
           controller: Controller, notifier: Notifier, server: ControlServer) -> int:
    """The service with its control socket bound: telemetry, the loop, the summary."""
    live = None
    if args.live is not None:
        live = live_view.live_publisher(args.live, controller, f"beamctl run, {cfg.hal.backend} backend",
                                        table_path=str(cfg.table_path))
    duration_s = cfg.duration_s if args.duration is None else args.duration
    max_cycles = int(duration_s * table.design.sample_rate_hz) if duration_s else None
    # the banner goes to stderr with the other messages: stdout carries the summary alone
    print(f"beamctl run: {cfg.hal.backend} backend, {table.design.sample_rate_hz:g} Hz, "
          f"{cfg.controller.pacing} pacing, gain table {cfg.table_path}, telemetry {path}"
          + (f", live view {live.path}" if live else ""), file=sys.stderr)
    _log(f"control socket {server.path} (mode 0660: user and group {server.group} may command)")
    # Telemetry starts before the loop asks for SCHED_FIFO (the writer thread must not inherit
    # it); the loop then takes its real-time set-up and only after it opens the HAL, so that no
    # sample queues up while memory is locked and the collector runs.
    created = [d for d in (path.parent, *path.parent.parents) if not d.exists()]   # deepest first
    meta = {"config": cfg.source, "gain_table": str(cfg.table_path), "model_sha256": table.model_sha256,
            "backend": cfg.hal.backend}
    telemetry = TelemetryWriter.for_controller(path, controller, meta=meta, live=live).start()

    def on_cycle(loop: ControlLoop) -> None:
        notifier.feed()

    with stop_on_signals(signal.SIGINT, signal.SIGTERM) as stop:     # the operator's stop
        loop = ControlLoop(controller, hal, telemetry=telemetry, stop_on_fault=False,
                           max_cycles=max_cycles, on_cycle=on_cycle if notifier.watchdog_interval_s else None,
                           stop=stop, start=not args.hold)
        swaps = TableSwaps(cfg, hal, controller)
        server.serve(loop, table=str(Path(cfg.table_path).absolute()), table_sha256=table.sha256,
                     prepare_table=swaps.prepare, log=_log)
        if live is not None:
            live_view.watch_loop(live, loop, telemetry, table_path=lambda: server.table)
        rearm = None
        if threading.current_thread() is threading.main_thread():
            rearm = signal.signal(signal.SIGUSR1, lambda *_: loop.request_rearm())
        notifier.ready(f"running at {table.design.sample_rate_hz:g} Hz")
        try:
            result = loop.run(require_rt=args.require_rt)
        except (realtime.RealtimeError, HalError) as exc:
            if telemetry.written == 0:      # refused before the first sample: no recording to keep
                path.unlink(missing_ok=True)
                for directory in created:
                    try:
                        directory.rmdir()
                    except OSError:
                        break
            print(f"beamctl run: error: {exc}", file=sys.stderr)
            return 2
        finally:
            if rearm is not None:
                signal.signal(signal.SIGUSR1, rearm)
            notifier.stopping()
            server.close()          # no command after the loop: the reader process can end
            swaps.close()
            hal.close()
            if live is not None:
                live.close()
    summary = {"state": result.state, "fault": result.fault, "reason": result.reason, "cycles": result.cycles,
               "late_answers": controller.safety.late_answers, "backlog_discarded": result.backlog_discarded,
               "stopped_by": result.stop_requested_by, "realtime": result.realtime,
               "timing": result.timing, "telemetry": result.telemetry, "hal": result.hal}
    if live is not None:
        summary["live"] = {"path": live.path, "sent": live.sent, "dropped": live.dropped,
                           "error": telemetry.live_error}
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        for item, report in result.realtime.items():
            print(f"  real-time {item}: {report}")
        t = result.timing
        print(f"  {result.cycles} cycles; step p50 {t['compute']['p50_us']:.1f} us, p99 "
              f"{t['compute']['p99_us']:.1f} us, max {t['compute']['max_us']:.1f} us; cycle p50 "
              f"{t['cycle']['p50_us']:.1f} us; {t['overruns']} overruns, "
              f"{t['missed_periods']} missed periods")
        age = t["answer_age"]
        if age["count"]:
            budget_us = cfg.controller.safety.answer_budget_periods * 1e6 / table.design.sample_rate_hz
            late = controller.safety.late_answers
            print(f"  answers: age p50 {age['p50_us']:.0f} us, p99 {age['p99_us']:.0f} us, max "
                  f"{age['max_us']:.0f} us; {late} later than the {budget_us:.0f} us budget; "
                  f"{result.backlog_discarded} queued samples discarded at start")
        tel = result.telemetry
        kept = "" if tel.get("mode", "full") == "full" else f" ({tel['mode']}: of {tel['received']} samples)"
        print(f"  telemetry: {tel.get('written', 0)} records{kept}, {tel.get('dropped', 0)} dropped, "
              f"{tel.get('path', '')}")
        if live is not None:
            print(f"  {live_view.summary(live, telemetry)}")
        print(f"  ended {result.state}: {result.reason} (stopped by {result.stop_requested_by or '-'})")
    dropped = result.telemetry.get("dropped", 0)
    if dropped:
        print(f"beamctl run: warning: {dropped} of {dropped + result.telemetry.get('received', 0)} "
              f"telemetry records were dropped: the writer fell a whole ring "
              f"(controller.telemetry.buffer_time_s) behind the loop", file=sys.stderr)
    return 0
