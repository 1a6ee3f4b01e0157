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


# every command and the module that parses and runs it, in the order ``beamctl --help`` lists them
COMMANDS = {"experiment": "experiment_cmd", "model": "model_cmd", "identify": "identify_cmd",
            "gains": "gains_cmd", "log": "log_cmd", "report": "report_cmd", "plant": "plant_cmd",
            "bus-budget": "plant_cmd", "run": "run_cmd", "ctl": "ctl_cmd", "monitor": "monitor_cmd",
            "bench": "bench_cmd", "study": "study_cmd", "commission": "commission_cmd",
            "config": "config_cmd"}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command, or with ``command`` (one of ``COMMANDS``) of that one alone:
    a command imports what it runs and nothing of the others' (about 1.3 s of numba, scipy and
    matplotlib modules here), and the operator's commands to a running service (``ctl``) need
    only the standard library, so that they answer without waiting for numpy and scipy."""
    import importlib

    if command in COMMANDS:
        parser = _Parser(prog="beamctl")
        module = importlib.import_module(f"beamctl.tools.{COMMANDS[command]}")
        module.add_parser(parser.add_subparsers(dest="command", metavar="COMMAND", required=True))
        return parser
    from beamctl.gains.build import tool_version

    parser = _Parser(
        prog="beamctl",
        description="Active buckling control of a beam-column with piezo-elastic supports.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {tool_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in dict.fromkeys(COMMANDS.values()):      # a module may add more than one command
        importlib.import_module(f"beamctl.tools.{name}").add_parser(sub)
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
            args = build_parser(words[0] if words[:1] and words[0] in COMMANDS else None).parse_args(words)
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
