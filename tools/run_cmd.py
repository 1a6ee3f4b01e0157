"""``beamctl run``: the controller service against the lab's DAQ (or any configured HAL): the
options parsed, the service (service/run.py: loop, telemetry, control socket, live view,
watchdog) built and run, its summary printed.

Loads and validates the config and the gain table (whose model hash must match the
configured model, whose content must match its own hash, and whose closed-loop check must
have passed), binds the control socket (a second service on the same socket is refused in one
line), starts telemetry, takes the real-time set-up, opens the HAL, arms, runs until
SIGINT/SIGTERM. A fault ramps the stacks to bias and holds them there, latched, until the
operator re-arms with SIGUSR1 (``systemctl kill -s USR1 beamctl``) or ``beamctl ctl rearm``,
or stops the service. Under systemd it reports readiness and feeds the watchdog from the
control loop. With ``--live`` the telemetry writer also sends decimated records to ``beamctl
monitor``, never waiting for it. Exit status: 0 when the run ended (whatever its state: the
summary says how), 2 when it could not start.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from beamctl.assembly import live as live_view
from beamctl.assembly.run import load_service_config
from beamctl.common.outputs import check_file, check_new_file
from beamctl.rt.live import check_socket_path
from beamctl.service.live import add_live_argument
from beamctl.service.run import Service, ServiceError, ServiceResult
from beamctl.tools.argtypes import seconds


def add_parser(sub) -> None:
    p = sub.add_parser(
        "run", help="the controller service (lab: against the CAN DAQ)",
        description="The controller service: loads and checks the configuration and its gain table "
                    "(`beamctl config check F` shows what it would run without starting it), binds the "
                    "control socket for `beamctl ctl`, records telemetry, arms and runs the control loop "
                    "until stopped. A fault ramps the stacks to bias and holds them there until `beamctl "
                    "ctl rearm` (or SIGUSR1). Ctrl-C or SIGTERM is how a service is stopped: the stacks "
                    "ramp to bias, telemetry is flushed, the summary printed, and the exit status is 0, "
                    "as for any run that ended (the summary says how); 2 when it could not start.")
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
    add_live_argument(p)
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
    try:
        service = Service(cfg, path, control_socket=args.control_socket, live=args.live, hold=args.hold,
                          duration_s=args.duration, require_rt=args.require_rt, log=_log)
    except ServiceError as exc:
        print(f"beamctl run: error: {exc}", file=sys.stderr)
        return 2
    table = service.table
    # the banner goes to stderr with the other messages: stdout carries the summary alone
    print(f"beamctl run: {cfg.hal.backend} backend, {table.design.sample_rate_hz:g} Hz, "
          f"{cfg.controller.pacing} pacing, gain table {cfg.table_path}, telemetry {path}"
          + (f", live view {service.live.path}" if service.live else ""), file=sys.stderr)
    _log(f"control socket {service.socket_path} (mode 0660: user and group {service.server.group} "
         f"may command)")
    try:
        outcome = service.run()
    except ServiceError as exc:
        print(f"beamctl run: error: {exc}", file=sys.stderr)
        return 2
    finally:
        service.close()
    _print_summary(args, cfg, service, outcome)
    return 0


def _log(line: str) -> None:
    """A line of the service's log (stderr, where systemd's journal takes it)."""
    print(f"beamctl run: {line}", file=sys.stderr, flush=True)


def _print_summary(args: argparse.Namespace, cfg, service: Service, outcome: ServiceResult) -> None:
    result, table = outcome.result, service.table
    if args.json:
        print(json.dumps(outcome.summary, indent=1))
    else:
        for item, report in result.realtime.items():
            print(f"  real-time {item}: {report}")
        t = result.timing
        print(f"  {result.cycles} cycles; step p50 {t['compute']['p50_us']:.1f} us, p99 "
              f"{t['compute']['p99_us']:.1f} us, max {t['compute']['max_us']:.1f} us; cycle p50 "
              f"{t['cycle']['p50_us']:.1f} us; {t['overruns']} overruns, "
              f"{t['missed_periods']} missed periods; the loop took {100 * t['loop_cpu_share']:.0f} % "
              f"of a CPU")
        age = t["answer_age"]
        if age["count"]:
            budget_us = service.loop.controller.safety.answer_budget_s * 1e6
            late = outcome.late_answers
            print(f"  answers: age p50 {age['p50_us']:.0f} us, p99 {age['p99_us']:.0f} us, max "
                  f"{age['max_us']:.0f} us; {late} later than the budget ({budget_us:.0f} us at the end); "
                  f"{result.backlog_discarded} queued samples discarded at start")
        stalls = t.get("stalls", {})
        if stalls.get("count"):
            ms = 1e3 / table.design.sample_rate_hz
            beyond = stalls.get("beyond_limit", 0)
            print(f"  stalls ridden through: {stalls['count']}"
                  f"{f' ({beyond} past the live limit, within the let-go)' if beyond else ''}, "
                  f"the longest {stalls['longest_samples'] * ms:.2f} ms "
                  f"(the live limit then {stalls['limit_at_longest_samples'] * ms:.2f} ms), the least room "
                  f"under the limit {stalls['least_room_samples'] * ms:.2f} ms (negative: past it)")
        tel = result.telemetry
        kept = "" if tel.get("mode", "full") == "full" else f" ({tel['mode']}: of {tel['received']} samples)"
        print(f"  telemetry: {tel.get('written', 0)} records{kept}, {tel.get('dropped', 0)} dropped, "
              f"{tel.get('path', '')}")
        if service.live is not None:
            print(f"  {live_view.summary(service.live, service.loop.telemetry)}")
        print(f"  ended {result.state}: {result.reason} (stopped by {result.stop_requested_by or '-'})")
    dropped = result.telemetry.get("dropped", 0)
    if dropped:
        print(f"beamctl run: warning: {dropped} of {dropped + result.telemetry.get('received', 0)} "
              f"telemetry records were dropped: the writer fell a whole ring "
              f"(controller.telemetry.buffer_time_s) behind the loop", file=sys.stderr)
