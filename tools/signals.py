"""What a signal means to a command: ``Interrupted`` ends it with 128 + the signal's number,
as a shell reports a command a signal ended (130 for Ctrl-C, 143 for SIGTERM)."""

from __future__ import annotations

import signal


class Interrupted(Exception):
    """A signal stopped the command (a simulated run: after the loop ramped the stacks to bias)."""

    def __init__(self, signal_name: str, during: str) -> None:
        self.signal_name = signal_name
        super().__init__(f"{signal_name} during {during}")

    @property
    def exit_status(self) -> int:
        """128 + the signal's number."""
        return 128 + signal.Signals[self.signal_name].value
