"""``beamctl`` in a process of its own, for what only a real process shows: signals, pipes."""

import json
import os
import signal
import subprocess
import sys
import threading
import time
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


class DaskCluster:
    """A Dask scheduler and two workers, each a process of its own on 127.0.0.1 (`dask scheduler`,
    `dask worker --no-nanny`: a killed worker stays dead)."""

    def __init__(self, folder: Path) -> None:
        dask = str(Path(sys.executable).parent / "dask")
        self.file = folder / "scheduler.json"
        common = ["--no-dashboard"]
        self.scheduler = subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0",
                                           "--scheduler-file", str(self.file), *common],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 60
        while not self.file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        self.address = json.loads(self.file.read_text())["address"]
        self._worker = [dask, "worker", "--scheduler-file", str(self.file), "--nthreads", "1", "--no-nanny",
                        "--host", "127.0.0.1", *common]
        self.workers = [self._start_worker() for _ in range(2)]
        self._wait_for_workers()

    def _start_worker(self) -> subprocess.Popen:
        return subprocess.Popen(self._worker, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})

    def _wait_for_workers(self) -> None:
        import distributed

        with distributed.Client(self.address, timeout=30) as client:
            client.wait_for_workers(len(self.workers), timeout=60)

    def revive(self) -> None:
        """A new worker in place of each one that has ended (a test killed it), registered with
        the scheduler before this returns."""
        dead = [i for i, p in enumerate(self.workers) if p.poll() is not None]
        for i in dead:
            self.workers[i] = self._start_worker()
        if dead:
            self._wait_for_workers()

    def close(self) -> None:
        for p in self.workers:
            p.kill()
        self.scheduler.send_signal(signal.SIGINT)
        for p in (*self.workers, self.scheduler):
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
