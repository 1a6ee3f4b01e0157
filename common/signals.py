"""What a signal means to a command: ``Interrupted`` ends it with 128 + the signal's number,
as a shell reports a command a signal ended (130 for Ctrl-C, 143 for SIGTERM)."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

from beamctl.rt.stop import StopRequest  # numpy-free: the command line imports this module early


class Interrupted(Exception):
    """A signal stopped the command (a simulated run: after the loop ramped the stacks to bias)."""

    def __init__(self, signal_name: str, during: str) -> None:
        self.signal_name = signal_name
        super().__init__(f"{signal_name} during {during}")

    @property
    def exit_status(self) -> int:
        """128 + the signal's number."""
        return 128 + signal.Signals[self.signal_name].value


@contextlib.contextmanager
def stop_on_signals(*signals: signal.Signals) -> Iterator[StopRequest]:
    """Within the block, ``signals`` (default SIGINT and SIGTERM) set the request a control loop
    reads (the stacks ramp to bias, the run ends normally and names the signal); the previous
    handlers come back after it. A command's choice: library code installs no handler. Off the
    main thread (where Python allows no handler) the request is only set by its holder."""
    request = StopRequest()

    def handler(signum, _frame) -> None:
        name = signal.Signals(signum).name
        request.set(name, name)

    installed = {}
    if threading.current_thread() is threading.main_thread():
        for sig in signals or (signal.SIGINT, signal.SIGTERM):
            installed[sig] = signal.signal(sig, handler)
    try:
        yield request
    finally:
        for sig, previous in installed.items():
            signal.signal(sig, previous)
