"""The discrete closed loop of one bending plane: the rig (FE plant with its I/O chain, sampled
with a delayed zero-order hold) and the compensator the control step runs. Every stability
check, nominal or robust, builds its loop here.

State: [plant x (n), applied forces of the last whole+1 samples (2 each), compensator x_c,
integral xi_k-1 (2)]. Per sample::

    y_k     = C x_k                                      (strains after the anti-alias filter)
    xi_k    = xi_k-1 + T H y_k
    u_k     = -(Cc x_c + D y_k + Ki xi_k)
    x_k+1   = Ad x_k + g (B_now u_k-whole + B_before u_k-whole-1)
    x_c,k+1 = Ac x_c + Bc y_k + E u_k

g is the ratio of the stacks' actual to believed force per volt (1 for the nominal rig); the
compensator is told the force it believes it applied.
"""

from __future__ import annotations

import numpy as np

from beamctl.gains.compensator import CompensatorPoint
from beamctl.models.iochain import DelayedZOH


def closed_loop_matrix(plant: DelayedZOH, c: np.ndarray, comp: CompensatorPoint, h: np.ndarray,
                       period_s: float, force_gain: float = 1.0) -> np.ndarray:
    """State matrix of the loop (see the module docstring); ``comp`` and ``h`` for this plane
    (2 inputs, 2 outputs), ``c`` [2 x n] the plant's strain output."""
    n = plant.ad.shape[0]
    whole = plant.whole
    nb = 2 * (whole + 1)
    nc = comp.a.shape[0]
    total = n + nb + nc + 2
    ib, ic, ii = n, n + nb, n + nb + nc
    # u_k = L z with z the loop state: -(Cc x_c + (D + T Ki H) C x + Ki xi_k-1)
    direct = comp.d + period_s * comp.ki @ h
    law = np.zeros((2, total))
    law[:, :n] = -direct @ c
    law[:, ic:ii] = -comp.c
    law[:, ii:] = -comp.ki
    m = np.zeros((total, total))
    m[:n, :n] = plant.ad

    def force(k_back: int, matrix: np.ndarray) -> None:
        """x_k+1 += g matrix u_k-k_back."""
        if k_back == 0:
            m[:n] += force_gain * matrix @ law
        else:
            col = ib + 2 * (k_back - 1)
            m[:n, col:col + 2] += force_gain * matrix

    force(whole, plant.b_now)
    if plant.fraction > 0.0:
        force(whole + 1, plant.b_before)
    # buffer: [u_k-1, ..., u_k-whole-1] <- [u_k, u_k-1, ..., u_k-whole]
    m[ib:ib + 2] = law
    for j in range(1, whole + 1):
        m[ib + 2 * j:ib + 2 * j + 2, ib + 2 * (j - 1):ib + 2 * j] = np.eye(2)
    # compensator and integral
    m[ic:ii, :n] = comp.b @ c
    m[ic:ii, ic:ii] += comp.a
    m[ic:ii] += comp.e @ law
    m[ii:, :n] = period_s * h @ c
    m[ii:, ii:] = np.eye(2)
    return m


def spectral_radius(matrix: np.ndarray) -> tuple[float, np.ndarray]:
    """Largest pole magnitude and the poles."""
    poles = np.linalg.eigvals(matrix)
    return float(np.max(np.abs(poles))), poles

