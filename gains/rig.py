"""The rig as the stability checks see it: one bending plane of the full FE model (with the
parameters of this rig, which may differ from the design model), its I/O chain, its actual
sample rate and stack force per volt, sampled with the delayed zero-order hold.

The two planes of the circular section have the same spectrum; one plane is checked.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from beamctl.gains.closedloop import closed_loop_matrix
from beamctl.gains.compensator import PLANE_CHANNELS, CompensatorPoint
from beamctl.models.analysis import critical_load
from beamctl.models.fe import FEModel, plane_indices
from beamctl.models.iochain import IOChain, delayed_zoh, with_filters


@dataclass(frozen=True)
class LoopPoles:
    """Poles of the loop at one load: spectral radius and the damping ratio of the least
    damped pole (via s = ln z / T)."""

    load_n: float
    spectral_radius: float
    min_damping: float

    @property
    def stable(self) -> bool:
        return self.spectral_radius < 1.0


def pole_summary(poles: np.ndarray, sample_rate_hz: float) -> tuple[float, float]:
    """Spectral radius and the damping ratio of the least damped pole (via s = ln z / T)."""
    radius = float(np.max(np.abs(poles)))
    s = np.log(poles.astype(complex)) * sample_rate_hz
    damping = -s.real / np.maximum(np.abs(s), 1e-300)
    return radius, float(np.min(damping))


class RigPlane:
    """One bending plane of ``model`` with the rig's I/O chain, sampled at ``sample_rate_hz``
    (the DAQ's actual rate); ``force_gain`` = actual / believed stack force per volt."""

    def __init__(self, model: FEModel, chain: IOChain, sample_rate_hz: float, force_gain: float = 1.0,
                 plane: str = "y") -> None:
        self.model = model
        self.chain = chain
        self.sample_rate_hz = float(sample_rate_hz)
        self.period_s = 1.0 / self.sample_rate_hz
        self.force_gain = float(force_gain)
        self.plane = plane
        idx = plane_indices(model.n_nodes, plane)
        io = list(PLANE_CHANNELS[plane])
        m = model.mass[np.ix_(idx, idx)]
        factor = sla.cho_factor(m)
        ke = model.elastic_stiffness[np.ix_(idx, idx)]
        kg = model.geometric_stiffness[np.ix_(idx, idx)]
        d = model.damping[np.ix_(idx, idx)]
        b0 = model.input_matrix[np.ix_(idx, io)]
        n = len(idx)
        solved = sla.cho_solve(factor, np.hstack([ke, kg, d, b0]))
        self._a0 = np.zeros((2 * n, 2 * n))
        self._a0[:n, n:] = np.eye(n)
        self._a0[n:, :n] = -solved[:, :n]
        self._a0[n:, n:] = -solved[:, 2 * n:3 * n]
        self._a1 = np.zeros((2 * n, 2 * n))          # d A / d Fx
        self._a1[n:, :n] = solved[:, n:2 * n]
        self._b = np.vstack([np.zeros((n, 2)), solved[:, 3 * n:]])
        self._c = np.hstack([model.output_matrix[np.ix_(io, idx)], np.zeros((2, n))])
        self._critical = None

    @property
    def critical_load_n(self) -> float:
        if self._critical is None:
            self._critical = critical_load(self.model, self.plane)
        return self._critical

    def sampled(self, axial_load_n: float):
        """(DelayedZOH, C) of the plane with its I/O chain at ``axial_load_n``."""
        a = self._a0 + axial_load_n * self._a1
        a, b, c, _ = with_filters(a, self._b, self._c, self.chain, n_control=2)
        return delayed_zoh(a, b, self.period_s, self.chain.delay_samples), c

    def loop_matrix(self, axial_load_n: float, comp: CompensatorPoint, h: np.ndarray,
                    plane_states: list[int], controller_period_s: float) -> np.ndarray:
        """The closed loop's state matrix at ``axial_load_n`` with the compensator of the whole
        beam ``comp`` (its block of this plane is taken)."""
        zoh, c = self.sampled(axial_load_n)
        io = list(PLANE_CHANNELS[self.plane])
        part = comp.plane(plane_states, self.plane)
        return closed_loop_matrix(zoh, c, part, h[np.ix_(io, io)], controller_period_s, self.force_gain)

    def poles(self, axial_load_n: float, comp: CompensatorPoint, h: np.ndarray, plane_states: list[int],
              controller_period_s: float) -> LoopPoles:
        m = self.loop_matrix(axial_load_n, comp, h, plane_states, controller_period_s)
        radius, damping = pole_summary(np.linalg.eigvals(m), self.sample_rate_hz)
        return LoopPoles(load_n=float(axial_load_n), spectral_radius=radius, min_damping=damping)
