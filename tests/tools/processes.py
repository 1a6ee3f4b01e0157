"""``beamctl`` in a process of its own, for what only a real process shows: signals, pipes."""

import signal
import subprocess
import sys
import threading
from pathlib import Path

# Ctrl-C as at a terminal. A process started from a background job of a non-interactive shell
# (a CI runner may run the suite so) inherits SIGINT ignored, and Python then leaves it so.
_AT_A_TERMINAL = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
                  "from beamctl.tools.cli import main; sys.exit(main())")


def beamctl(*argv: str, cwd: Path, **kwargs) -> subprocess.Popen:
    """``beamctl`` in its own process (stdout and stderr piped unless ``kwargs`` say where),
    SIGINT handled as at a terminal."""
    kwargs.setdefault("stdout", subprocess.PIPE)
    kwargs.setdefault("stderr", subprocess.PIPE)
    return subprocess.Popen([sys.executable, "-c", _AT_A_TERMINAL, *argv], cwd=cwd, **kwargs)


def interrupt_when(process: subprocess.Popen, marker: bytes, timeout_s: float = 300.0,
                   signum: int = signal.SIGINT) -> tuple[int, str]:
    """Send ``signum`` (SIGINT: Ctrl-C) once ``marker`` appears on the process's stderr (it is
    working); return the exit status and all of stderr. A process that never shows the marker
    is killed."""
    watchdog = threading.Timer(timeout_s, process.kill)
    watchdog.start()
    try:
        err = b""
        for line in process.stderr:
            err += line
            if marker in line:
                process.send_signal(signum)
                break
        rest = process.communicate(timeout=timeout_s)[1]
    finally:
        watchdog.cancel()
    return process.returncode, (err + rest).decode()
