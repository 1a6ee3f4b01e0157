"""One recording in physical units (``RunRecord``): what the report (reports/report.py) reads a
run's telemetry into and its figures (reports/plots.py) draw."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from beamctl.rt.controller import FLAG_SATURATED_A, FLAG_SATURATED_B
from beamctl.rt.safety import State

FIGURE_POINTS = 20_000                # at most this many points a curve in a figure
DEFAULT_VOLTAGE_LIMITS_V = (0.0, 150.0)


# the per-sample series of a record (what ``RunRecord.window`` slices)
_SERIES = ("time_s", "load_n", "load_filtered_n", "deflection_m", "deflection_y_m", "deflection_z_m",
           "voltages_v", "state", "fault", "flags", "step_us", "answer_age_us", "late_answers")


@dataclass(frozen=True)
class RunRecord:
    """One recording in physical units, at full rate (rows before the first sample dropped)."""

    path: Path
    meta: dict
    model_note: str                     # which model the deflection was computed with
    sample_rate_hz: float
    time_s: np.ndarray                  # from the first sample
    load_n: np.ndarray
    load_filtered_n: np.ndarray
    deflection_m: np.ndarray            # the gauges' reconstruction, largest along the beam
    deflection_y_m: np.ndarray
    deflection_z_m: np.ndarray
    voltages_v: np.ndarray              # [n x 6]: a1 a2 a3 b1 b2 b3
    state: np.ndarray
    fault: np.ndarray
    flags: np.ndarray
    step_us: np.ndarray
    answer_age_us: np.ndarray
    late_answers: np.ndarray
    recorded_rows: int = 0              # complete rows in the file
    incomplete_row_bytes: int = 0
    critical_load_n: float | None = None
    voltage_limits_v: tuple[float, float] = DEFAULT_VOLTAGE_LIMITS_V
    bias_voltage_v: float = 75.0
    settings: dict = field(default_factory=dict)

    @property
    def label(self) -> str:
        mode = self.meta.get("mode")
        return f"{self.path.name} ({mode} run)" if mode else self.path.name

    @property
    def controlled(self) -> bool:
        return bool(np.any(self.state == State.RUNNING))

    def saturated(self, support: str) -> np.ndarray:
        """Samples whose allocation could not give support ``A``'s or ``B``'s force."""
        bit = FLAG_SATURATED_A if support == "A" else FLAG_SATURATED_B
        return (self.flags & bit) != 0

    def window(self, start_s: float, end_s: float) -> RunRecord:
        """The samples from ``start_s`` to ``end_s`` (times from the first sample, kept)."""
        part = (self.time_s >= start_s) & (self.time_s <= end_s)
        series = {name: getattr(self, name)[part] for name in _SERIES}
        return replace(self, **series)

    def stride(self) -> int:
        """Every how many samples a figure draws a point."""
        return max(1, math.ceil(len(self.time_s) / FIGURE_POINTS))


