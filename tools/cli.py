"""Entry point of the ``beamctl`` command line."""

from __future__ import annotations

import argparse
import sys

from beamctl.gains.build import tool_version
from beamctl.models.schema import ConfigError
from beamctl.tools import bench_cmd, experiment_cmd, gains_cmd, log_cmd, model_cmd, plant_cmd, run_cmd


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="beamctl",
        description="Active buckling control of a beam-column with piezo-elastic supports.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {tool_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    experiment_cmd.add_parser(sub)
    model_cmd.add_parser(sub)
    gains_cmd.add_parser(sub)
    log_cmd.add_parser(sub)
    plant_cmd.add_parser(sub)
    run_cmd.add_parser(sub)
    bench_cmd.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run ``beamctl`` with ``argv`` (default: the process arguments); return the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:          # --help, or a flag argparse refused (it printed why)
        return int(exc.code or 0)
    try:
        return int(args.run(args) or 0)
    except ConfigError as exc:
        print(f"beamctl {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
