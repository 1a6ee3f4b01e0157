"""Entry point of the ``beamctl`` command line.

Exit status:

- 0: done;
- 1: a check failed (an unstable gain table, a bus over budget);
- 2: bad input (a flag, a configuration value, an unreadable input file, an output path that
  cannot be written), refused in one line on stderr before the work starts;
- 128 + the signal's number when a signal stopped the command: 130 for Ctrl-C (SIGINT), 143
  for SIGTERM. ``beamctl run`` and ``beamctl plant`` are the exceptions: for a service (the
  controller, the emulated DAQ) SIGINT and SIGTERM are the operator's normal stop, and it
  exits 0;
- 141 (128 + SIGPIPE, what a shell reports for a tool killed by a closed pipe) when the
  reader of stdout went away early (``beamctl gains check | head -3``): the output is cut
  short, quietly.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from typing import NoReturn

from beamctl.common.outputs import OutputPathError
from beamctl.common.signals import Interrupted

# Only the standard library and the two modules above are imported before main() runs: the
# rest (numpy, scipy, python-can: about a second) is imported inside it, so that a Ctrl-C
# even then ends in one line, not a traceback.

EXIT_BAD_INPUT = 2
EXIT_SIGINT = 130
EXIT_BROKEN_PIPE = 141


class _Parser(argparse.ArgumentParser):
    """argparse refusing a flag in one line, ``beamctl bus-budget: error: ...``, like every
    other refusal (``--help`` shows the usage)."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message}\n")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command, or with ``command`` "ctl" of that one alone: the operator's
    commands to a running service need only the standard library, and answer without waiting
    seconds for numpy and scipy to load."""
    from beamctl.tools import ctl_cmd

    if command == "ctl":
        parser = _Parser(prog="beamctl")
        ctl_cmd.add_parser(parser.add_subparsers(dest="command", metavar="COMMAND", required=True))
        return parser
    from beamctl.gains.build import tool_version
    from beamctl.tools import (
        bench_cmd,
        commission_cmd,
        config_cmd,
        experiment_cmd,
        gains_cmd,
        identify_cmd,
        log_cmd,
        model_cmd,
        monitor_cmd,
        plant_cmd,
        report_cmd,
        run_cmd,
        study_cmd,
    )

    parser = _Parser(
        prog="beamctl",
        description="Active buckling control of a beam-column with piezo-elastic supports.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {tool_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    experiment_cmd.add_parser(sub)
    model_cmd.add_parser(sub)
    identify_cmd.add_parser(sub)
    gains_cmd.add_parser(sub)
    log_cmd.add_parser(sub)
    report_cmd.add_parser(sub)
    plant_cmd.add_parser(sub)
    run_cmd.add_parser(sub)
    ctl_cmd.add_parser(sub)
    monitor_cmd.add_parser(sub)
    bench_cmd.add_parser(sub)
    study_cmd.add_parser(sub)
    commission_cmd.add_parser(sub)
    config_cmd.add_parser(sub)
    return parser


def _command_name(args: argparse.Namespace) -> str:
    """``beamctl gains build``: the command and its action, as the user typed them."""
    words = [getattr(args, key, None)
             for key in ("command", "gains_command", "log_command", "ctl_command", "config_command",
                         "model_command")]
    return " ".join(["beamctl", *(w for w in words if w)])


def _discard_stdout() -> None:
    """Point stdout at /dev/null so that the interpreter's last flush at exit does not fail
    again on the closed pipe (the recipe of the ``signal`` module's note on SIGPIPE)."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, ValueError, OSError):    # replaced by a caller (tests): nothing to do
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, fd)
    os.close(devnull)


def _run(argv: list[str] | None) -> int:
    """Parse ``argv`` and run the command; every refusal and interruption in one line."""
    from beamctl.common.extras import MissingExtraError
    from beamctl.common.workers import WorkerDied
    from beamctl.config.schema import ConfigError
    from beamctl.rt.live import LiveError
    from beamctl.rt.telemetry import TelemetryError

    name = "beamctl"
    try:
        words = sys.argv[1:] if argv is None else argv
        try:
            args = (build_parser("ctl") if words[:1] == ["ctl"] else build_parser()).parse_args(words)
        except SystemExit as exc:      # --help, or a flag argparse refused (it printed why)
            return int(exc.code or 0)
        name = _command_name(args)
        status = int(args.run(args) or 0)
        sys.stdout.flush()
        return status
    except (ConfigError, OutputPathError, TelemetryError, MissingExtraError, LiveError) as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except WorkerDied as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        return 1
    except Interrupted as exc:
        print(f"{name}: interrupted ({exc})", file=sys.stderr)
        return exc.exit_status
    except KeyboardInterrupt:
        print(f"{name}: interrupted (SIGINT)", file=sys.stderr)
        return EXIT_SIGINT
    except BrokenPipeError:
        _discard_stdout()
        return EXIT_BROKEN_PIPE


def _terminated(signum, _frame) -> NoReturn:
    """SIGTERM ends a command as Ctrl-C does: through its clean-up (no half-written file)."""
    raise Interrupted(signal.Signals(signum).name, "the command")


def main(argv: list[str] | None = None) -> int:
    """Run ``beamctl`` with ``argv`` (default: the process arguments); return the exit code."""
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _terminated)
    try:
        return _run(argv)
    except KeyboardInterrupt:           # while the libraries were still being imported
        print("beamctl: interrupted (SIGINT)", file=sys.stderr)
        return EXIT_SIGINT
    except Interrupted as exc:
        print(f"beamctl: interrupted ({exc})", file=sys.stderr)
        return exc.exit_status
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    raise SystemExit(main())
