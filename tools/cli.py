"""Entry point of the ``beamctl`` command line.

A refusal of bad input (a flag, a configuration value, an unreadable input file, an output
path that cannot be written) is one line on stderr and exit status 2, before the work starts.
"""

from __future__ import annotations

import argparse
import sys

from beamctl.gains.build import tool_version
from beamctl.models.schema import ConfigError
from beamctl.rt.telemetry import TelemetryError
from beamctl.tools import bench_cmd, experiment_cmd, gains_cmd, log_cmd, model_cmd, plant_cmd, run_cmd
from beamctl.tools.outputs import OutputPathError


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


def _command_name(args: argparse.Namespace) -> str:
    """``beamctl gains build``: the command and its action, as the user typed them."""
    words = [getattr(args, key, None) for key in ("command", "gains_command", "log_command")]
    return " ".join(["beamctl", *(w for w in words if w)])


def main(argv: list[str] | None = None) -> int:
    """Run ``beamctl`` with ``argv`` (default: the process arguments); return the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:          # --help, or a flag argparse refused (it printed why)
        return int(exc.code or 0)
    try:
        return int(args.run(args) or 0)
    except (ConfigError, OutputPathError, TelemetryError) as exc:
        print(f"{_command_name(args)}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
