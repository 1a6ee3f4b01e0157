"""The rig as the stability checks see it: one bending plane of the full FE model (with the
parameters of this rig, which may differ from the design model), its I/O chain, its actual
sample rate and stack force per volt, sampled with the delayed zero-order hold.

The two planes of the circular section have the same spectrum; one plane is checked.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from beamctl.gains.closedloop import closed_loop_matrix
from beamctl.gains.compensator import PLANE_CHANNELS, CompensatorPoint
from beamctl.models.analysis import critical_load
from beamctl.models.fe import FEModel, plane_indices
from beamctl.models.iochain import IOChain, delayed_zoh, with_filters


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

    def continuous(self, axial_load_n: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A, B, C) of the plane with its I/O chain's filters at ``axial_load_n``, before
        sampling (the delay is the sampling's)."""
        a = self._a0 + axial_load_n * self._a1
        a, b, c, _ = with_filters(a, self._b, self._c, self.chain, n_control=2)
        return a, b, c

    def sampled(self, axial_load_n: float):
        """(DelayedZOH, C) of the plane with its I/O chain at ``axial_load_n``."""
        a, b, c = self.continuous(axial_load_n)
        return delayed_zoh(a, b, self.period_s, self.chain.delay_samples), c

    def loop_matrix(self, axial_load_n: float, comp: CompensatorPoint, h: np.ndarray,
                    plane_states: list[int], controller_period_s: float) -> np.ndarray:
        """The closed loop's state matrix at ``axial_load_n`` with the compensator of the whole
        beam ``comp`` (its block of this plane is taken)."""
        zoh, c = self.sampled(axial_load_n)
        io = list(PLANE_CHANNELS[self.plane])
        part = comp.plane(plane_states, self.plane)
        return closed_loop_matrix(zoh, c, part, h[np.ix_(io, io)], controller_period_s, self.force_gain)
