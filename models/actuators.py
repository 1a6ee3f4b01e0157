"""The piezo stacks of a support as a physical fact: three stacks at 120 deg in the y-z
plane, stack i pushing along e_i = (cos t_i, sin t_i), t_i = t_1 + (i - 1) 120 deg, with
force k (V_i - V_bias). Used forwards by the simulated plant (voltages -> forces) and
backwards by the controller's allocation (forces -> voltages)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

STACKS = 3


@dataclass(frozen=True)
class StackGeometry:
    force_constant_n_per_v: float
    bias_voltage_v: float
    orientation_deg: tuple[float, float]  # stack 1 at supports A and B, from +y towards +z

    def axes(self) -> np.ndarray:
        """[2 supports x 3 stacks x (y, z)] unit vectors."""
        return np.array([[[math.cos(math.radians(t1 + 120.0 * i)), math.sin(math.radians(t1 + 120.0 * i))]
                          for i in range(STACKS)] for t1 in self.orientation_deg])

    def forces(self, voltages: np.ndarray) -> np.ndarray:
        """Lateral forces (Fay,A, Faz,A, Fay,B, Faz,B) in N of six stack voltages."""
        volts = np.asarray(voltages, dtype=float).reshape(2, STACKS) - self.bias_voltage_v
        f = self.force_constant_n_per_v * volts
        return np.einsum("si,sid->sd", f, self.axes()).reshape(4)

    def force_matrix(self) -> np.ndarray:
        """[4 x 6] matrix F = M (V - V_bias): the same map, for a loop that precomputes it."""
        m = np.zeros((4, 6))
        ax = self.axes()
        for s in range(2):
            m[2 * s:2 * s + 2, 3 * s:3 * s + 3] = self.force_constant_n_per_v * ax[s].T
        return m
