"""Per-stage timing as data, as LinuxCNC's HAL exports ``runtime`` and ``maxtime`` for every
function: last, max, count and a histogram on fixed log-spaced bins from which percentiles
are read. Recording is a bisect and two list updates: nothing is allocated per sample."""

from __future__ import annotations

import bisect
import math

# bin edges: 0.5 us to 1 s, 100 bins per decade (2.3 % wide; a percentile is reported as the
# geometric centre of its bin, within 1.2 %)
_PER_DECADE = 100
_EDGES = [0.5e-6 * 10 ** (k / _PER_DECADE) for k in range(6 * _PER_DECADE + 31)]
_HALF_BIN = 10 ** (-0.5 / _PER_DECADE)


class StageTimer:
    """Durations (s) of one stage of the cycle."""

    __slots__ = ("name", "last_s", "max_s", "count", "total_s", "counts")

    def __init__(self, name: str) -> None:
        self.name = name
        self.last_s = 0.0
        self.max_s = 0.0
        self.count = 0
        self.total_s = 0.0
        self.counts = [0] * (len(_EDGES) + 1)

    def record(self, seconds: float) -> None:
        self.last_s = seconds
        if seconds > self.max_s:
            self.max_s = seconds
        self.count += 1
        self.total_s += seconds
        self.counts[bisect.bisect_right(_EDGES, seconds)] += 1

    def percentile(self, p: float) -> float:
        """The p-th percentile (s): centre of the histogram bin holding it (within 1.2 %)."""
        if not self.count:
            return math.nan
        target = p / 100.0 * self.count
        running = 0
        for i, c in enumerate(self.counts):
            running += c
            if running >= target and c:
                return _EDGES[i] * _HALF_BIN if i < len(_EDGES) else self.max_s
        return self.max_s

    def summary(self) -> dict:
        us = 1e6
        return {"count": self.count, "last_us": self.last_s * us, "max_us": self.max_s * us,
                "mean_us": (self.total_s / self.count * us) if self.count else math.nan,
                "p50_us": self.percentile(50) * us, "p99_us": self.percentile(99) * us,
                "p99.9_us": self.percentile(99.9) * us}


class StallLog:
    """The stalls ridden through (samples the stacks held the last answer before a sample, as
    the engine counts them): how many, how many of them longer than the live limit then (ridden
    through up to the let-go: survived, but not with the limit's confidence), the longest and the
    live limit then, and the least room any stall left under its limit."""

    __slots__ = ("count", "beyond_limit", "longest", "limit_at_longest", "least_room", "limit_at_least_room")

    def __init__(self) -> None:
        self.count = 0
        self.beyond_limit = 0
        self.longest = 0.0
        self.limit_at_longest = math.nan
        self.least_room = math.inf
        self.limit_at_least_room = math.nan

    def record(self, held: float, limit: float) -> None:
        self.count += 1
        if held > limit:
            self.beyond_limit += 1
        if held > self.longest:
            self.longest, self.limit_at_longest = held, limit
        if limit - held < self.least_room:
            self.least_room, self.limit_at_least_room = limit - held, limit

    def summary(self) -> dict:
        return {"count": self.count, "beyond_limit": self.beyond_limit, "longest_samples": self.longest,
                "limit_at_longest_samples": self.limit_at_longest,
                "least_room_samples": None if self.count == 0 else self.least_room,
                "limit_at_least_room_samples": self.limit_at_least_room}


class LoopTiming:
    """The stages of one cycle, the link's timing (each answer's age, the period of the incoming
    samples, where the HAL measures them), plus the count of overruns and the periods they
    skipped (the streaks that fault are counted by rt.safety)."""

    STAGES = ("read", "compute", "write", "cycle", "answer_age", "input_period")

    def __init__(self) -> None:
        self.read = StageTimer("read")
        self.compute = StageTimer("compute")
        self.write = StageTimer("write")
        self.cycle = StageTimer("cycle")
        self.answer_age = StageTimer("answer_age")
        self.input_period = StageTimer("input_period")
        self.overruns = 0          # cycles that ended after their deadline
        self.missed_periods = 0    # periods skipped after overruns
        self.stalls = StallLog()
        # the loop thread's CPU time over the wall time it cycled: Linux holds a real-time thread
        # whose share passes kernel.sched_rt_runtime_us / sched_rt_period_us (95 %) for the rest of
        # the second
        self.cpu_share = math.nan

    def summary(self) -> dict:
        out = {name: getattr(self, name).summary() for name in self.STAGES}
        out.update(overruns=self.overruns, missed_periods=self.missed_periods, stalls=self.stalls.summary(),
                   loop_cpu_share=self.cpu_share)
        return out
