"""What work spread over processes reports when a process of it dies."""

from __future__ import annotations


class WorkerDied(RuntimeError):
    """A worker process died (killed, out of memory, a crash) while it evaluated the work in
    flight; the message names that work (the rigs of a robust check, a study's samples)."""
