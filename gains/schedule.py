"""The gain schedule: the compensator's matrices over the load grid, as the blocks the control
step's products run on and as the matrices the checks analyse.

The rule, which the compiled engine runs each sample (rt/engine.py ``_follow``, ``_settle``,
``_product``) and which ``matrices_at`` states for a settled load:

``interpolate`` (default): the matrices are linear between the two grid points around the
filtered load (the gain scheduling the paper names as future work).
``paper``: the matrices of the grid point at or above the filtered load, as the experiment's
operator switched: on to the next gain as the rising load passed each grid point (with the
gain of the point below, the loop is unstable between 3194 N and the next point; the paper
held the beam to 3223 N). The switch up from grid point i happens once the load passes
L_i + h/2 and back down once it falls below L_(i-1) - h/2, so noise on the load cell cannot
chatter between two gains.
Outside the grid the edge point is held (the engine then faults LOAD_OUT_OF_TABLE_RANGE while
running); nothing is ever extrapolated. The load-cell value is low-pass filtered (first order,
coefficient ``alpha`` per sample) before the lookup.

The engine runs three products over the signal vector s = [y (4); xi (4); u_applied (4); x_c (n)]
(gains/compensator.py)::

    output      u = -(C x_c + D y + Ki xi)            the law
    update      x_c = A x_c + B y + E u_applied       the compensator state
    integral    du = -Ki dxi                          what an integral increment does to u (anti-windup)

Each is one matrix-vector product with the block [M_i; S_i] of the grid interval i in use (M_i
the matrices of its lower grid point, S_i their slope in load; ``_output_blocks``,
``_update_blocks``, ``_integral_blocks``, ``stacked_blocks``), giving [M_i s; S_i s], weighed by
[1, offset]: (M_i + offset S_i) s without forming the matrices (offset: the filtered load above
grid point i; 0 in ``paper`` mode and outside the grid). This module builds those blocks and
``matrices_at(load)``, the matrices the same rule settles on at a load (for the closed-loop
checks and plots); it keeps no running state and runs no products itself.
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
    """The compensator of a gain table over its load grid: the blocks [M_i; S_i] the engine's
    products run on, the load filter's and the hysteresis' settings, and the matrices at a
    settled load (``matrices_at``)."""

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

    def _settled(self, load: float) -> tuple[int, float]:
        """(grid point, offset) at a load reached from below and settled: in ``paper`` mode the
        grid point at or above it, else the point below and the load above it (the engine's
        ``_settle``)."""
        if self._paper:
            return min(max(bisect.bisect_left(self._loads, load), 0), self._last_index), 0.0
        if load <= self._first:
            return 0, 0.0
        if load >= self._last:
            return self._last_index, 0.0
        i = min(max(bisect.bisect_right(self._loads, load) - 1, 0), self._last_index)
        return i, load - self._loads[i]

    # -- for the checks and plots ---------------------------------------------------------------
    def matrices_at(self, load_n: float) -> CompensatorPoint:
        """The matrices at a load reached from below and settled, by the rule the engine's
        products follow: interpolated, or in ``paper`` mode those of the grid point at or above
        it (the strain prediction likewise, where the table has one). A new CompensatorPoint
        (its arrays the caller's own)."""
        i, offset = self._settled(float(load_n))
        comp = self.compensator
        names = MATRICES if comp.predict is None else (*MATRICES, "predict")
        if offset == 0.0:
            return CompensatorPoint(**{m: getattr(comp, m)[i].copy() for m in names})
        return CompensatorPoint(**{m: getattr(comp, m)[i] + offset * self._slopes[m][i] for m in names})
