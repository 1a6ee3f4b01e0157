"""``beamctl monitor``: the live view of ``beamctl run --live`` (or ``beamctl experiment --live``)
in a browser, until SIGINT or SIGTERM (the operator's normal stop: exit 0)."""

from __future__ import annotations

import argparse
import sys
import time

from beamctl.common.signals import stop_on_signals
from beamctl.service.live import default_live_path
from beamctl.service.monitor import Monitor
from beamctl.tools.argtypes import number, positive, renamed


def _port(text: str) -> int:
    port = number(low=0, integer=True)(text)
    if port > 65535:
        raise argparse.ArgumentTypeError(f"{text!r}: expected a TCP port 0..65535 (0: any free one)")
    return port


def add_parser(sub) -> None:
    p = sub.add_parser("monitor", help="the live view of a running service, in a browser",
                       description="Receive the live values that `beamctl run --live` sends and serve "
                                   "a page that draws them on 127.0.0.1; print its URL (with the "
                                   "token that operator commands need).")
    p.add_argument("--port", type=_port, default=8750,
                   help="TCP port on 127.0.0.1 (default 8750; 0: any free one)")
    p.add_argument("--live", metavar="ADDRESS", default=default_live_path(),
                   help=f"the UNIX socket to listen at (default {default_live_path()}, where --live sends "
                        "without an address)")
    p.add_argument("--control-socket", metavar="PATH",
                   help="the service's control socket, for the page's buttons (default: where `beamctl "
                        "ctl` looks)")
    renamed(p, "--control", "--control-socket")
    p.add_argument("--window", type=positive, default=20.0, metavar="S",
                   help="seconds of history the page shows (default 20)")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    with (stop_on_signals() as stop,
          Monitor(args.live, args.port, args.control_socket, args.window) as monitor):
        print(f"beamctl monitor: listening for `--live` at {monitor.live_path}; operator commands go to "
              f"{monitor.control_path}", file=sys.stderr)
        print(monitor.url, flush=True)
        while not stop.reason:          # the signal handler sets it
            time.sleep(0.2)
    print(f"beamctl monitor: stopped ({stop.reason}); {monitor.store.datagrams} datagrams received, "
          f"{monitor.store.missed} missed", file=sys.stderr)
    return 0

