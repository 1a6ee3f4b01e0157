"""Force allocation: the lateral force (Fy, Fz) wanted at a support, produced by its three
piezo stacks at 120 deg.

Stack i of a support pushes along e_i = (cos t_i, sin t_i), t_i = t_1 + (i - 1) 120 deg,
with force f_i = k (V_i - V_bias) (k: force constant in N/V). Because e_1 + e_2 + e_3 = 0
and sum e_i e_i^T = 3/2 I, the stack forces f_i = 2/3 e_i . F + c give the lateral force F
for any common part c. Two modes (``controller.allocation``), chosen when the allocator is
built:

- ``scale`` (the default): the common part centres the three voltages in [V_min, V_max], i.e.
  keeps every voltage as far from its limits as possible. When the spread of the voltages does
  not fit, the force is scaled down as a whole (direction kept) until it does. A non-finite
  demand produces no force: the voltages go to the middle of the range.
- ``clip``: the paper's setup (section 4: the control forces transformed into the directions of
  the stacks): no common part, V_i = V_bias + 2/3 e_i . F / k, and each stack clipped at its
  own limit. A stack that clips gives less than its share and the force turns towards the
  stacks that still have room (the paper's beam failed in another direction when its first
  stacks reached 150 V). A non-finite demand produces no force: the voltages go to the bias.

Either way the allocator reports per support the fraction of the demanded force delivered
along its direction (1.0: reachable, < 1: saturated, 0: invalid demand).
"""

from __future__ import annotations

import math

import numpy as np

from beamctl.models.actuators import STACKS, StackGeometry
from beamctl.rt.config import ALLOCATION_MODES, Actuators

SPAN_ROUNDING = 1e-12   # relative: far above the few ulps of the coefficients, far below any real excess


def geometry(actuators: Actuators) -> StackGeometry:
    """The stack geometry the controller believes in."""
    return StackGeometry(force_constant_n_per_v=actuators.force_constant, bias_voltage=actuators.bias_voltage,
                         orientation_deg=tuple(actuators.orientation_deg))


class Allocator:
    """Both supports: four forces (Fay,A, Faz,A, Fay,B, Faz,B) -> six voltages.

    ``allocate(u, voltages)`` writes the voltages and returns nothing; the fraction of the
    demanded force delivered along its direction per support (1.0: reachable, < 1: saturated,
    0: invalid demand) is left in ``scale_a`` and ``scale_b``. ``mode`` is ``scale`` or
    ``clip`` (module docstring); the step runs the chosen one, decided here.
    """

    def __init__(self, actuators: Actuators, mode: str = "scale") -> None:
        if mode not in ALLOCATION_MODES:
            raise ValueError(f"allocation mode {mode!r}: expected one of {', '.join(ALLOCATION_MODES)}")
        self.mode = mode
        self._support = self._scaled if mode == "scale" else self._clipped
        self.bias_voltage_v = actuators.bias_voltage
        self.min_voltage_v = actuators.min_voltage_v
        self.max_voltage_v = actuators.max_voltage_v
        self.mid_voltage_v = 0.5 * (self.min_voltage_v + self.max_voltage_v)
        self.voltage_span_v = self.max_voltage_v - self.min_voltage_v
        # a spread that exceeds the span only by rounding (a force that needs exactly the whole
        # range) is reachable: scaling it by 1 - eps would report saturation for nothing
        self._span_fits = self.voltage_span_v * (1.0 + SPAN_ROUNDING)
        k = actuators.force_constant
        # per support, per stack: volts per newton of Fy and of Fz (2/3 e_i / k)
        self._coef = []
        for t1 in actuators.orientation_deg:
            row = []
            for i in range(STACKS):
                t = math.radians(t1 + 120.0 * i)
                row.append((2.0 / 3.0 * math.cos(t) / k, 2.0 / 3.0 * math.sin(t) / k))
            self._coef.append(tuple(row))
        self.geometry = geometry(actuators)
        self.scale_a = 1.0
        self.scale_b = 1.0

    def _scaled(self, fy: float, fz: float, coef, voltages: np.ndarray, first: int) -> float:
        """Centred voltages; the force scaled down as a whole when their spread does not fit."""
        (ay1, az1), (ay2, az2), (ay3, az3) = coef
        if not (fy - fy == 0.0 and fz - fz == 0.0):  # NaN or infinite demand: no force
            fy = fz = math.nan
        g1 = ay1 * fy + az1 * fz
        g2 = ay2 * fy + az2 * fz
        g3 = ay3 * fy + az3 * fz
        hi = g1 if g1 > g2 else g2
        hi = hi if hi > g3 else g3
        lo = g1 if g1 < g2 else g2
        lo = lo if lo < g3 else g3
        spread = hi - lo
        if spread <= self._span_fits:
            scale = 1.0
        elif spread < math.inf:
            scale = self.voltage_span_v / spread
        else:                                   # NaN (invalid demand) or overflow
            scale = 0.0
            g1 = g2 = g3 = hi = lo = 0.0
        centre = self.mid_voltage_v - scale * 0.5 * (hi + lo)
        v_min, v_max = self.min_voltage_v, self.max_voltage_v
        for k, g in ((0, g1), (1, g2), (2, g3)):
            v = centre + scale * g
            voltages[first + k] = v_min if v < v_min else (v_max if v > v_max else v)
        return scale

    def _clipped(self, fy: float, fz: float, coef, voltages: np.ndarray, first: int) -> float:
        """The paper's transform around the bias, each stack clipped at its own limit."""
        (ay1, az1), (ay2, az2), (ay3, az3) = coef
        g1 = ay1 * fy + az1 * fz
        g2 = ay2 * fy + az2 * fz
        g3 = ay3 * fy + az3 * fz
        wanted = g1 * g1 + g2 * g2 + g3 * g3
        bias, v_min, v_max = self.bias_voltage_v, self.min_voltage_v, self.max_voltage_v
        if not wanted < math.inf:               # NaN or infinite demand, or overflow: no force
            voltages[first] = voltages[first + 1] = voltages[first + 2] = bias
            return 0.0
        v1, v2, v3 = bias + g1, bias + g2, bias + g3
        clipped = False
        if v1 < v_min or v1 > v_max:
            v1 = v_min if v1 < v_min else v_max
            clipped = True
        if v2 < v_min or v2 > v_max:
            v2 = v_min if v2 < v_min else v_max
            clipped = True
        if v3 < v_min or v3 > v_max:
            v3 = v_min if v3 < v_min else v_max
            clipped = True
        voltages[first] = v1
        voltages[first + 1] = v2
        voltages[first + 2] = v3
        if not clipped:
            return 1.0
        # F_applied . F / |F|^2 = sum (V_i - V_bias) g_i / sum g_i^2 (sum e_i e_i^T = 3/2 I); a
        # stack over its limit by rounding only (a force that needs exactly the limit) gives it all
        delivered = ((v1 - bias) * g1 + (v2 - bias) * g2 + (v3 - bias) * g3) / wanted
        return 1.0 if delivered > 1.0 - SPAN_ROUNDING else delivered

    def allocate(self, u: np.ndarray, voltages: np.ndarray) -> None:
        """Six voltages (a1, a2, a3, b1, b2, b3) for the forces ``u`` (N)."""
        fya, fza, fyb, fzb = u.tolist()
        self.scale_a = self._support(fya, fza, self._coef[0], voltages, 0)
        self.scale_b = self._support(fyb, fzb, self._coef[1], voltages, 3)

    def forces(self, voltages: np.ndarray) -> np.ndarray:
        """The lateral forces (Fay,A, Faz,A, Fay,B, Faz,B) that ``voltages`` produce."""
        return self.geometry.forces(voltages)
