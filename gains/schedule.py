"""Gain schedule K(Fx) for the loop: a precomputed lookup that allocates nothing per call.

``interpolate`` (default): K is linear between the two grid points around the filtered
load (the gain scheduling the paper names as future work).
``paper``: K is the gain of the grid point at or above the filtered load, as the
experiment's operator switched: on to the next gain as the rising load passed each grid point
(with the gain of the point below, the loop is unstable between 3194 N and the next point;
the paper held the beam to 3223 N). The switch up from grid point i happens once the load
passes L_i + h/2 and back down once it falls below L_(i-1) - h/2, so noise on the load cell
cannot chatter between two gains.
Outside the grid the edge gain is held and ``out_of_range`` is raised; nothing is ever
extrapolated. The load-cell value is low-pass filtered (first order) before the lookup.
"""

from __future__ import annotations

import bisect
import math

import numpy as np

from beamctl.gains.table import GainTable


class GainSchedule:
    """K(Fx) lookup. Call ``reset(load)`` before the loop, then ``update(load_cell_n)`` once
    per sample; it returns a [4 x 12] array that is overwritten by the next call."""

    def __init__(self, table: GainTable, sample_rate_hz: float | None = None) -> None:
        rate = table.design.sample_rate_hz if sample_rate_hz is None else sample_rate_hz
        self.mode = table.schedule.mode
        self._paper = self.mode == "paper"
        self._loads = [float(x) for x in table.loads_n]
        self._gains = np.ascontiguousarray(table.gains, dtype=float)
        self._slopes = np.zeros_like(self._gains)
        if len(self._loads) > 1:
            self._slopes[:-1] = np.diff(self._gains, axis=0) / np.diff(table.loads_n)[:, None, None]
        self._first, self._last = self._loads[0], self._loads[-1]
        self._last_index = len(self._loads) - 1
        self._half_band = 0.5 * table.schedule.hysteresis_n
        self._alpha = 1.0 - math.exp(-2.0 * math.pi * table.schedule.load_filter_hz / rate)
        self._out = np.zeros(self._gains.shape[1:])
        self.filtered_load_n = self._first
        self.index = 0
        self.offset_n = 0.0
        self.out_of_range = False
        self.reset(self._first)

    def reset(self, load_n: float) -> None:
        """Start the filter at ``load_n`` (bumpless start) and select its gain."""
        if not math.isfinite(load_n):
            load_n = self._first
        self.filtered_load_n = load_n
        self.index = self._ceil_index(load_n) if self._paper else self._floor_index(load_n)
        self._select(load_n)

    def _floor_index(self, load: float) -> int:
        return min(max(bisect.bisect_right(self._loads, load) - 1, 0), self._last_index)

    def _ceil_index(self, load: float) -> int:
        return min(max(bisect.bisect_left(self._loads, load), 0), self._last_index)

    def _select(self, load: float) -> None:
        """Set ``index`` and ``offset_n`` (load above grid point ``index`` used for
        interpolation; 0 in paper mode and outside the grid) and form K in the out array."""
        self._locate(load)
        if self.offset_n == 0.0:
            self._out[...] = self._gains[self.index]
        else:
            np.multiply(self._slopes[self.index], self.offset_n, out=self._out)
            self._out += self._gains[self.index]

    def _locate(self, load: float) -> None:
        loads = self._loads
        self.out_of_range = load < self._first or load > self._last
        self.offset_n = 0.0
        if self._paper:
            i = self.index
            while i < self._last_index and load > loads[i] + self._half_band:
                i += 1
            while i > 0 and load < loads[i - 1] - self._half_band:
                i -= 1
            self.index = i
        elif load <= self._first:
            self.index = 0
        elif load >= self._last:
            self.index = self._last_index
        else:
            i = self._floor_index(load)
            self.index = i
            self.offset_n = load - loads[i]

    @property
    def slopes(self) -> np.ndarray:
        """dK/dFx per grid interval [G x 4 x 12] (zero for the last point): K(Fx) =
        gains[index] + offset_n slopes[index]."""
        return self._slopes

    def _filter(self, load_cell_n: float) -> bool:
        """Feed a reading to the load filter; a non-finite one is refused (False) and flagged."""
        if load_cell_n != load_cell_n or load_cell_n in (math.inf, -math.inf):
            self.out_of_range = True
            return False
        self.filtered_load_n += self._alpha * (load_cell_n - self.filtered_load_n)
        return True

    def locate(self, load_cell_n: float) -> None:
        """Filter the reading and find ``index`` and ``offset_n`` without forming K (for a
        loop that applies the gains itself); same rules as ``update``."""
        if self._filter(load_cell_n):
            self._locate(self.filtered_load_n)

    def update(self, load_cell_n: float) -> np.ndarray:
        """Filter the new load-cell reading and return K(Fx) [4 x 12] (a reused array).

        A non-finite reading is not fed to the filter: the previous gain is kept and
        ``out_of_range`` raised (the safety supervisor decides what to do about it)."""
        if self._filter(load_cell_n):
            self._select(self.filtered_load_n)
        return self._out

    def gain_at(self, load_n: float) -> np.ndarray:
        """K at a load reached from below and settled (a copy): the interpolated gain, or in
        ``paper`` mode the gain of the grid point at or above it. For the closed-loop check
        and plots, not for the loop (it resets the filter)."""
        self.reset(load_n)
        return self._out.copy()
