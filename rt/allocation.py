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
from beamctl.rt import engine
from beamctl.rt.config import ALLOCATION_MODES, Actuators
from beamctl.rt.engine import SPAN_ROUNDING


def geometry(actuators: Actuators) -> StackGeometry:
    """The stack geometry the controller believes in."""
    return StackGeometry(force_constant_n_per_v=actuators.force_constant_n_per_v,
                         bias_voltage_v=actuators.bias_voltage_v,
                         orientation_deg=tuple(actuators.orientation_deg))


class Allocator:
    """Both supports: four forces (Fay,A, Faz,A, Fay,B, Faz,B) -> six voltages.

    ``allocate(u, voltages)`` writes the voltages and returns nothing; the fraction of the
    demanded force delivered along its direction per support (1.0: reachable, < 1: saturated,
    0: invalid demand) is left in ``scale_a`` and ``scale_b``. ``mode`` is ``scale`` or
    ``clip`` (module docstring). The arithmetic is the engine's (rt/engine.py
    ``allocate_support``), the one the control cycle runs; this class holds its coefficients.
    """

    def __init__(self, actuators: Actuators, mode: str = "scale", scales: np.ndarray | None = None) -> None:
        """``scales``: where to keep (scale A, scale B), two floats (a controller passes the
        engine's, so that they are the cycle's own); by default an array of this allocator's."""
        if mode not in ALLOCATION_MODES:
            raise ValueError(f"allocation mode {mode!r}: expected one of {', '.join(ALLOCATION_MODES)}")
        self.mode = mode
        self._clip = mode == "clip"
        self.bias_voltage_v = actuators.bias_voltage_v
        self.min_voltage_v = actuators.min_voltage_v
        self.max_voltage_v = actuators.max_voltage_v
        self.mid_voltage_v = 0.5 * (self.min_voltage_v + self.max_voltage_v)
        self.voltage_span_v = self.max_voltage_v - self.min_voltage_v
        # a spread that exceeds the span only by rounding (a force that needs exactly the whole
        # range) is reachable: scaling it by 1 - eps would report saturation for nothing
        self.span_fits = self.voltage_span_v * (1.0 + SPAN_ROUNDING)
        k = actuators.force_constant_n_per_v
        # per support, per stack: volts per newton of Fy and of Fz (2/3 e_i / k), flat
        coef = []
        for t1 in actuators.orientation_deg:
            for i in range(STACKS):
                t = math.radians(t1 + 120.0 * i)
                coef += [2.0 / 3.0 * math.cos(t) / k, 2.0 / 3.0 * math.sin(t) / k]
        self.coefficients = np.array(coef)
        self.geometry = geometry(actuators)
        self.scales = np.ones(2) if scales is None else scales
        self.scales[:] = 1.0

    @property
    def scale_a(self) -> float:
        return float(self.scales[0])

    @property
    def scale_b(self) -> float:
        return float(self.scales[1])

    def allocate(self, u: np.ndarray, voltages: np.ndarray) -> None:
        """Six voltages (a1, a2, a3, b1, b2, b3) for the forces ``u`` (N)."""
        self.scales[0], self.scales[1] = engine.allocate(
            np.ascontiguousarray(u, dtype=float), self.coefficients, 0, self._clip, self.min_voltage_v,
            self.max_voltage_v, self.mid_voltage_v, self.voltage_span_v, self.span_fits, self.bias_voltage_v,
            voltages)

    def forces(self, voltages: np.ndarray) -> np.ndarray:
        """The lateral forces (Fay,A, Faz,A, Fay,B, Faz,B) that ``voltages`` produce."""
        return self.geometry.forces(voltages)
