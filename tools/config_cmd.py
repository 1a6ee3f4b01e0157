"""``beamctl config check F``: what a service configuration would run and whether ``beamctl run``
would start with it, without starting it (service/check.py)."""

from __future__ import annotations

import argparse
import json

from beamctl.service.check import check_config

EXIT_WOULD_REFUSE = 1


def add_parser(sub) -> None:
    p = sub.add_parser("config", help="service configurations: check one before running it")
    actions = p.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    c = actions.add_parser(
        "check", help="what `beamctl run --config F` would run, and whether it would start",
        description="Reads the configuration as `beamctl run` does and reports, without starting the "
                    "service: the gain table it would run (path, SHA-256, design, closed-loop check, "
                    "ride-through limits, the robust check recorded in it), the backend and the bus "
                    "budget, the voltages, the control socket and the telemetry file. The HAL is built "
                    "but not opened, the socket looked at but not bound, nothing is written.")
    c.add_argument("file", metavar="F", help="service configuration, e.g. deploy/lab.yaml")
    c.add_argument("--json", action="store_true", help="print the report as one JSON object")
    c.epilog = ("exit status 0: the service would start; 1: it would refuse, the reasons printed one a line; "
                "2: the command itself was used wrongly")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    result = check_config(args.file)
    if args.json:
        print(json.dumps(result.to_dict(), indent=1))
    else:
        width = max((len(k) for k, _ in result.items), default=0)
        for key, value in result.items:
            print(f"{key:<{width}}  {value}")
        if result.would_start:
            print(f"`beamctl run --config {args.file}` would start")
        else:
            print(f"`beamctl run --config {args.file}` would refuse to start:")
            for reason in result.refusals:
                print(f"  - {reason}")
    return 0 if result.would_start else EXIT_WOULD_REFUSE
