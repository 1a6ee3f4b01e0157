"""A stop asked of a control loop from outside it (a signal handler, another thread): kept in a
module of its own, free of numpy, so that the command line's signal handling can make one
before anything heavy is imported."""

from __future__ import annotations


class StopRequest:
    """A stop asked from outside the loop: a signal handler or another thread sets it once
    (the first reason wins), the loop reads it each cycle."""

    __slots__ = ("reason", "signal_name")

    def __init__(self) -> None:
        self.reason = ""
        self.signal_name = ""

    def set(self, reason: str, signal_name: str = "") -> None:
        if signal_name and not self.signal_name:
            self.signal_name = signal_name
        if not self.reason:
            self.reason = reason
