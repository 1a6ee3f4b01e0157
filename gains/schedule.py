"""The gain schedule: the compensator's matrices at the filtered axial load, offered to the
control step as products that allocate nothing.

``interpolate`` (default): the matrices are linear between the two grid points around the
filtered load (the gain scheduling the paper names as future work).
``paper``: the matrices of the grid point at or above the filtered load, as the experiment's
operator switched: on to the next gain as the rising load passed each grid point (with the
gain of the point below, the loop is unstable between 3194 N and the next point; the paper
held the beam to 3223 N). The switch up from grid point i happens once the load passes
L_i + h/2 and back down once it falls below L_(i-1) - h/2, so noise on the load cell cannot
chatter between two gains.
Outside the grid the edge point is held and ``out_of_range`` is raised; nothing is ever
extrapolated. The load-cell value is low-pass filtered (first order) before the lookup.

The step asks for products at the current load over its signal vector
s = [y (4); xi (4); u_applied (4); x_c (n)] (gains/compensator.py)::

    output(s, u)                u = -(C x_c + D y + Ki xi)            the law
    update(s, x_c)              x_c = A x_c + B y + E u_applied       the compensator state
    integral_effect(dxi, du)    du = -Ki dxi                          what an integral increment does to u

Each is one matrix-vector product with the block [M_i; S_i] stacked for the grid interval i in
use (M_i the matrices of its lower grid point, S_i their slope in load), giving [M_i s; S_i s],
and one more that weighs the two halves by [1, offset]: (M_i + offset S_i) s without forming
the matrices (offset: the filtered load above grid point i; 0 in ``paper`` mode and outside the
grid). ``matrices_at(load)`` gives the matrices the same rule settles on at a load (for the
closed-loop check and plots).
"""

from __future__ import annotations

import bisect
import math
from typing import TYPE_CHECKING

import numpy as np

from beamctl.gains.compensator import MATRICES, Compensator, CompensatorPoint

if TYPE_CHECKING:
    from beamctl.gains.table import GainTable, ScheduleSettings

N_SIGNALS = 12     # y, xi and u_applied at the head of the signal vector, before the n compensator states


def _stacked(matrices: np.ndarray, loads: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """Per grid point i the block [M_i; S_i] with S_i = (M_i+1 - M_i) / (L_i+1 - L_i) (zero at
    the last point), and the slopes S [G x ...]."""
    slopes = np.zeros_like(matrices)
    if len(loads) > 1:
        slopes[:-1] = np.diff(matrices, axis=0) / np.diff(loads)[:, None, None]
    return [np.ascontiguousarray(np.vstack([m, s])) for m, s in zip(matrices, slopes, strict=True)], slopes


class GainSchedule:
    """The compensator at the filtered load. Call ``reset(load)`` before the loop, then
    ``follow(load_cell_n)`` once per sample and the products as the step needs them."""

    def __init__(self, loads_n: np.ndarray, compensator: Compensator, settings: ScheduleSettings,
                 sample_rate_hz: float | None = None) -> None:
        rate = 1.0 / compensator.period_s if sample_rate_hz is None else sample_rate_hz
        loads = np.asarray(loads_n, dtype=float)
        self.mode = settings.mode
        self._paper = self.mode == "paper"
        self._loads = [float(x) for x in loads]
        self._first, self._last = self._loads[0], self._loads[-1]
        self._last_index = len(self._loads) - 1
        self._half_band = 0.5 * settings.hysteresis_n
        self._alpha = 1.0 - math.exp(-2.0 * math.pi * settings.load_filter_hz / rate)
        self.compensator = compensator
        n = compensator.n_states
        self.n_states = n
        self._slopes = {m: _stacked(getattr(compensator, m), loads)[1] for m in MATRICES}
        if compensator.predict is not None:
            self._slopes["predict"] = _stacked(compensator.predict, loads)[1]

        g = len(self._loads)
        output = np.zeros((g, 4, N_SIGNALS + n))       # -[D Ki 0 C] over s
        output[:, :, 0:4] = -compensator.d
        output[:, :, 4:8] = -compensator.ki
        output[:, :, N_SIGNALS:] = -compensator.c
        update = np.zeros((g, n, N_SIGNALS + n))       # [B 0 E A] over s
        update[:, :, 0:4] = compensator.b
        update[:, :, 8:12] = compensator.e
        update[:, :, N_SIGNALS:] = compensator.a
        self._output_blocks, _ = _stacked(output, loads)
        self._update_blocks, _ = _stacked(update, loads)
        self._integral_blocks, _ = _stacked(-compensator.ki, loads)
        # [M_i s; S_i s] of each product, and viewed as two rows for the weighing by [1, offset]
        self._output_tmp = np.zeros(8)
        self._output_halves = self._output_tmp.reshape(2, 4)
        self._update_tmp = np.zeros(2 * n)
        self._update_halves = self._update_tmp.reshape(2, n)
        self._integral_tmp = np.zeros(8)
        self._integral_halves = self._integral_tmp.reshape(2, 4)
        self._weights = np.array([1.0, 0.0])    # [1, offset]

        self.filtered_load_n = self._first
        self.index = 0             # grid point in use (inspection; the products need no caller to read it)
        self.out_of_range = False
        self.reset(self._first)

    @property
    def alpha(self) -> float:
        """The load filter's coefficient per sample: f += alpha (load - f)."""
        return self._alpha

    @property
    def half_band_n(self) -> float:
        """Half the hysteresis band of ``paper`` mode (N)."""
        return self._half_band

    @staticmethod
    def stacked_blocks(matrices: np.ndarray, loads_n) -> list[np.ndarray]:
        """Per grid point the block [M_i; S_i] of ``matrices`` [G x ...] over ``loads_n`` (S_i
        the slope to the next point, zero at the last), as the products use them."""
        return _stacked(np.asarray(matrices, dtype=float), np.asarray(loads_n, dtype=float))[0]

    @classmethod
    def from_table(cls, table: GainTable) -> GainSchedule:
        return cls(table.loads_n, table.compensator, table.schedule, table.design.sample_rate_hz)

    # -- the load -------------------------------------------------------------------------------
    def reset(self, load_n: float) -> None:
        """Start the filter at ``load_n`` (bumpless start) and settle on its grid point."""
        if not math.isfinite(load_n):
            load_n = self._first
        self.filtered_load_n = load_n
        self.out_of_range = load_n < self._first or load_n > self._last
        self.index, self._weights[1] = self._settled(load_n)

    def _settled(self, load: float) -> tuple[int, float]:
        """(grid point, offset) at a load reached from below and settled: in ``paper`` mode the
        grid point at or above it, else the point below and the load above it."""
        if self._paper:
            return min(max(bisect.bisect_left(self._loads, load), 0), self._last_index), 0.0
        if load <= self._first:
            return 0, 0.0
        if load >= self._last:
            return self._last_index, 0.0
        i = min(max(bisect.bisect_right(self._loads, load) - 1, 0), self._last_index)
        return i, load - self._loads[i]

    def _locate(self, load: float) -> None:
        loads = self._loads
        self.out_of_range = load < self._first or load > self._last
        if self._paper:
            i = self.index
            while i < self._last_index and load > loads[i] + self._half_band:
                i += 1
            while i > 0 and load < loads[i - 1] - self._half_band:
                i -= 1
            self.index = i
        else:
            self.index, self._weights[1] = self._settled(load)

    def follow(self, load_cell_n: float) -> None:
        """Filter the new load-cell reading and move to the grid point (and offset) of the
        filtered load. A non-finite reading is not fed to the filter: the matrices in use are
        kept and ``out_of_range`` raised (the safety supervisor decides what to do about it)."""
        if load_cell_n != load_cell_n or load_cell_n in (math.inf, -math.inf):
            self.out_of_range = True
            return
        self.filtered_load_n += self._alpha * (load_cell_n - self.filtered_load_n)
        self._locate(self.filtered_load_n)

    # -- the products the step runs -------------------------------------------------------------
    def output(self, s: np.ndarray, out: np.ndarray) -> None:
        """u = -(C x_c + D y + Ki xi) at the current load into ``out`` [4]; ``s`` the signal
        vector [y; xi; u_applied; x_c]."""
        np.dot(self._output_blocks[self.index], s, out=self._output_tmp)
        np.dot(self._weights, self._output_halves, out=out)

    def update(self, s: np.ndarray, out: np.ndarray) -> None:
        """x_c = A x_c + B y + E u_applied at the current load into ``out`` [n] (which may be
        the x_c part of ``s``)."""
        np.dot(self._update_blocks[self.index], s, out=self._update_tmp)
        np.dot(self._weights, self._update_halves, out=out)

    def integral_effect(self, dxi: np.ndarray, out: np.ndarray) -> None:
        """du = -Ki dxi at the current load into ``out`` [4]: the change of u an integral
        increment ``dxi`` would make (for anti-windup)."""
        np.dot(self._integral_blocks[self.index], dxi, out=self._integral_tmp)
        np.dot(self._weights, self._integral_halves, out=out)

    # -- for the checks and plots ---------------------------------------------------------------
    def matrices_at(self, load_n: float) -> CompensatorPoint:
        """The matrices at a load reached from below and settled, by the rule the products
        follow: interpolated, or in ``paper`` mode those of the grid point at or above it (the
        strain prediction likewise, where the table has one). A new CompensatorPoint; the
        schedule's own state (filter, grid point) is untouched."""
        i, offset = self._settled(float(load_n))
        comp = self.compensator
        names = MATRICES if comp.predict is None else (*MATRICES, "predict")
        if offset == 0.0:
            return CompensatorPoint(**{m: getattr(comp, m)[i].copy() for m in names})
        return CompensatorPoint(**{m: getattr(comp, m)[i] + offset * self._slopes[m][i] for m in names})
