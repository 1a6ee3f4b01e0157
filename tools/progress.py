"""Progress display for long commands: a bar redrawn in place on a terminal, a line every
10 % otherwise (logs, CI); both with an estimate of the time left once there is one."""

from __future__ import annotations

import sys
import time
from typing import TextIO


class ProgressBar:
    """Call with (done, total, label); ``close()`` ends the line. As a context manager, an
    error or interruption inside the block ends the line too (without "done")."""

    def __init__(self, title: str, stream: TextIO | None = None, width: int = 30) -> None:
        self.title = title
        self.stream = stream or sys.stderr
        self.width = width
        self.tty = self.stream.isatty()
        self._last_draw = 0.0
        self._last_decile = -1
        self._start = time.monotonic()
        self._open = False

    def left_s(self, fraction: float) -> float | None:
        """The time left at ``fraction`` done, from the rate so far (None: too early to say)."""
        elapsed = time.monotonic() - self._start
        if fraction < 0.02 or elapsed < 2.0 or fraction >= 1.0:
            return None
        return elapsed * (1.0 - fraction) / fraction

    def __call__(self, done: int, total: int, label: str = "") -> None:
        fraction = done / total if total else 1.0
        left = self.left_s(fraction)
        if left is not None:
            label = f"{label}, {_duration(left)} left" if label else f"{_duration(left)} left"
        if self.tty:
            now = time.monotonic()
            if now - self._last_draw < 0.1 and done < total:
                return
            self._last_draw = now
            filled = int(round(self.width * fraction))
            bar = "#" * filled + "-" * (self.width - filled)
            self.stream.write(f"\r{self.title} [{bar}] {done}/{total} {label:<36}")
            self._open = True
        else:
            decile = int(fraction * 10)
            if decile == self._last_decile:
                return
            self._last_decile = decile
            self.stream.write(f"{self.title}: {100 * fraction:3.0f} % {label}\n")
        self.stream.flush()

    def close(self) -> float:
        """End the display; return the elapsed time in s."""
        elapsed = time.monotonic() - self._start
        if self.tty and self._open:
            self.stream.write(f"\r{self.title}: done in {elapsed:.1f} s{' ' * (self.width + 60)}\n")
            self.stream.flush()
        self._open = False
        return elapsed

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, exc_type, *_) -> None:
        """Left by an error or Ctrl-C: end the bar's line, so that the message has its own."""
        if exc_type is not None and self.tty and self._open:
            self.stream.write("\n")
            self.stream.flush()
        self._open = False


def _duration(seconds: float) -> str:
    """``about 40 s``, ``about 3 min``, ``about 1.5 h``."""
    if seconds < 90:
        return f"about {max(1, round(seconds))} s"
    if seconds < 5400:
        return f"about {round(seconds / 60)} min"
    return f"about {seconds / 3600:.1f} h"
