"""``beamctl ctl start|stop|rearm|status|gains TABLE``: operator commands to a running
``beamctl run`` over its control socket (service/control.py).

Exit status: 0 done, 1 the service refused (it says why), 2 no service, no permission or no
answer (one line).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from beamctl.service.control import ControlError, default_socket_path, request
from beamctl.tools.argtypes import renamed

GAINS_TIMEOUT_S = 120.0
ACTIONS = {
    "status": "the service's state, fault, load and gain table",
    "start": "start controlling (a service started with --hold, waiting at bias)",
    "stop": "ramp the stacks to bias and end the service (as SIGTERM)",
    "rearm": "clear a latched fault once the stacks are at bias (and start again unless held)",
    "gains": "swap in another gain table at bias (checked as at the service's start)",
}


def add_parser(sub) -> None:
    p = sub.add_parser("ctl", help="operator commands to a running `beamctl run`",
                       description="Operator commands to a running `beamctl run` over its control socket. "
                                   "Exit status: 0 done, 1 refused by the service (it says why), 2 no "
                                   "service, no permission or no answer.")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--control-socket", metavar="PATH",
                        help="the service's control socket (default: $BEAMCTL_CONTROL_SOCKET, else the "
                             "first of /run/beamctl, $XDG_RUNTIME_DIR/beamctl and /tmp/beamctl-UID "
                             "holding a control.sock)")
    common.add_argument("--json", action="store_true", help="print the service's reply as JSON")
    renamed(common, "--socket", "--control-socket")
    csub = p.add_subparsers(dest="ctl_command", metavar="ACTION", required=True)
    for name, text in ACTIONS.items():
        a = csub.add_parser(name, parents=[common], help=text, description=text)
        if name == "gains":
            a.add_argument("table", metavar="TABLE",
                           help="gain table file (as `beamctl gains build` wrote it)")
        a.set_defaults(run=run)


def describe(status: dict) -> str:
    """Two lines of a status: state, fault, load, cycles; the gain table."""
    fault = "no fault" if status.get("fault") == "NONE" else status.get("reason", "")
    load = status.get("axial_load_n")
    load_text = "no sample yet" if load is None else f"load {load:.1f} N"
    bias = ", stacks at bias" if status.get("at_bias") else ""
    return (f"{status.get('state')} ({fault}){bias}; {load_text}; {status.get('cycles')} cycles\n"
            f"gain table {status.get('table')} (sha256 {status.get('table_sha256', '')[:16]}...)")


def run(args: argparse.Namespace) -> int:
    name = args.ctl_command
    payload = {"command": name}
    if name == "gains":
        payload["table"] = str(Path(args.table).absolute())   # the service runs in a directory of its own
    path = Path(args.control_socket) if args.control_socket else default_socket_path()
    try:
        # a gain table is read and checked before the answer: seconds, the first time
        reply = request(path, payload, timeout_s=GAINS_TIMEOUT_S if name == "gains" else 10.0)
    except ControlError as exc:
        print(f"beamctl ctl {name}: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(reply, indent=1))
    elif reply["ok"]:
        if reply.get("message"):
            print(f"{name}: {reply['message']}")
        print(describe(reply.get("status") or {}))
    if not reply["ok"]:
        print(f"beamctl ctl {name}: {reply.get('message', 'refused')}", file=sys.stderr)
        return 1
    return 0
