"""Integral LQR of section 3.2: the 12-state augmented modal model (eq. 21-25) and the gain
K_LQR(Fx) = R^-1 B^T P(Fx) from the continuous-time algebraic Riccati equation (eq. 26-29).

State order (eq. 22): x = [q_m, q_m_dot, x_i] with q_m = (q1y, q1z, q2y, q2z) and
x_i = integral of q_m. Inputs (eq. 4): u = (Fay,A, Faz,A, Fay,B, Faz,B) in N.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from beamctl.models.modal import ModalModel

N_STATES = 12
N_INPUTS = 4


@dataclass(frozen=True)
class Weights:
    """Diagonals of Q [12] and R [4] of eq. (26), in the state order of eq. (22).

    Units: R in 1/N^2; Q in 1/(modal unit)^2, 1/(modal unit/s)^2 and 1/(modal unit s)^2 for
    displacements, velocities and integrals. A modal unit of a mass-normalised mode of this
    beam is about 6.6 m of largest lateral deflection (mode 1; 6.2 m for mode 2), so
    q = 1e-5 is a deflection of 66 um. A weight w on a state means: a deviation of
    1/sqrt(w) in that state costs as much as 1 N of actuator force (R = I).
    """

    q: tuple[float, ...]
    r: tuple[float, ...]

    @classmethod
    def from_modes(cls, displacement: tuple[float, float], velocity: tuple[float, float],
                   integral: tuple[float, float], force: float = 1.0) -> Weights:
        """Weights from per-mode values (mode 1, mode 2), the same in y and z."""
        def per_plane(pair):
            return (pair[0], pair[0], pair[1], pair[1])

        return cls(q=per_plane(displacement) + per_plane(velocity) + per_plane(integral),
                   r=(force,) * N_INPUTS)

    def matrices(self) -> tuple[np.ndarray, np.ndarray]:
        return np.diag(np.asarray(self.q, dtype=float)), np.diag(np.asarray(self.r, dtype=float))


def augmented_system(reduced: ModalModel, axial_load: float) -> tuple[np.ndarray, np.ndarray]:
    """A(Fx) [12 x 12] and B [12 x 4] of eq. (24)."""
    a = np.zeros((N_STATES, N_STATES))
    a[:8, :8] = reduced.system_matrix(axial_load)
    a[8:, :4] = np.eye(4)  # eq. (23): x_i_dot = q_m
    b = np.zeros((N_STATES, N_INPUTS))
    b[:8] = reduced.input_matrix
    return a, b


def lqr_gain(reduced: ModalModel, axial_load: float, weights: Weights) -> np.ndarray:
    """K_LQR(Fx) [4 x 12] of eq. (28), u = -K x (eq. 27)."""
    a, b = augmented_system(reduced, axial_load)
    q, r = weights.matrices()
    p = sla.solve_continuous_are(a, b, q, r)
    return np.linalg.solve(r, b.T @ p)
