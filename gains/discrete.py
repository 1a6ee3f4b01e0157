"""The controller as it runs each sample, and the discrete closed loop with the full FE model.

Per sample k (section 4 of the paper, as the rt loop computes it):

    q_k   = (C0 Phi)^-1 y_k                        modal displacements, eq. (30)
    h_k   = b0 q_k + s_k ;  s_k+1 = b1 q_k - a1 h_k  first-order Butterworth high-pass
    v_k   = omega_c h_k                            modal velocity estimate
    xi_k  = xi_k-1 + T q_k                         discrete integrator of eq. (21)
    u_k   = -K(Fx) [q_k, v_k, xi_k]                eq. (27)

and u_k is held on the actuators until the next sample. For frequencies well below the
cut-off f_c, omega_c s / (s + omega_c) ~ s: the scaled high-pass output tracks dq/dt with a
phase lag of atan(f / f_c).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.signal as sig

from beamctl.models.analysis import PLANE_IO, state_space
from beamctl.models.fe import FEModel, plane_indices

# columns of the 12-state vector (eq. 22) and rows of u belonging to each bending plane
PLANE_STATES = {"y": [0, 2, 4, 6, 8, 10], "z": [1, 3, 5, 7, 9, 11]}


@dataclass(frozen=True)
class VelocityFilter:
    """Coefficients of the first-order Butterworth high-pass and the scale omega_c."""

    cutoff_hz: float
    sample_rate_hz: float
    b0: float
    b1: float
    a1: float
    scale: float

    def phase_lag_deg(self, freq_hz: float) -> float:
        """Phase lag (deg) of the velocity estimate behind dq/dt at ``freq_hz``."""
        w = 2 * math.pi * freq_hz / self.sample_rate_hz
        z = complex(math.cos(w), math.sin(w))
        h = self.scale * (self.b0 + self.b1 / z) / (1 + self.a1 / z)
        derivative = 2j * math.pi * freq_hz
        return -math.degrees(math.atan2((h / derivative).imag, (h / derivative).real))


def velocity_filter(cutoff_hz: float, sample_rate_hz: float) -> VelocityFilter:
    """Design the first-order Butterworth high-pass (scipy.signal.butter, bilinear with
    pre-warping) whose output times 2 pi f_c estimates the modal velocity."""
    if not 0 < cutoff_hz < sample_rate_hz / 2:
        raise ValueError(f"velocity filter cut-off {cutoff_hz} Hz must lie between 0 and the "
                         f"Nyquist frequency {sample_rate_hz / 2} Hz")
    b, a = sig.butter(1, cutoff_hz, btype="highpass", fs=sample_rate_hz)
    return VelocityFilter(cutoff_hz=cutoff_hz, sample_rate_hz=sample_rate_hz, b0=float(b[0]),
                          b1=float(b[1]), a1=float(a[1]), scale=2 * math.pi * cutoff_hz)


@dataclass(frozen=True)
class LoopCheck:
    """Stability of the discrete closed loop at one axial load, with the gain the schedule
    settles on there, or (``gain_load_n``) the gain of that grid load."""

    load_n: float
    spectral_radius: float
    min_damping: float
    gain_load_n: float | None = None

    @property
    def stable(self) -> bool:
        return self.spectral_radius < 1.0


def discrete_fe_plane(model: FEModel, axial_load: float, sample_period: float, plane: str):
    """The full FE model of one bending plane, zero-order-hold discretised:
    (Ad, Bd, C) with inputs (Fa,A, Fa,B) and outputs (eps_1, eps_2) of that plane."""
    a, b, c = state_space(model, axial_load)
    idx = plane_indices(model.n_nodes, plane)
    states = np.concatenate([idx, model.n_dof + idx])
    io = list(PLANE_IO[plane])
    a, b, c = a[np.ix_(states, states)], b[np.ix_(states, io)], c[np.ix_(io, states)]
    n, m = a.shape[0], b.shape[1]
    aug = np.zeros((n + m, n + m))
    aug[:n, :n], aug[:n, n:] = a, b
    phi = sla.expm(aug * sample_period)
    return phi[:n, :n], phi[:n, n:], c


def closed_loop_matrix(ad: np.ndarray, bd: np.ndarray, c: np.ndarray, gain: np.ndarray,
                       c0_phi_inv: np.ndarray, filt: VelocityFilter, plane: str) -> np.ndarray:
    """State matrix of plant + controller for one plane; state [x, s (2), xi_k-1 (2)]."""
    io = list(PLANE_IO[plane])
    k = gain[np.ix_(io, PLANE_STATES[plane])]
    k_q, k_v, k_i = k[:, 0:2], k[:, 2:4], k[:, 4:6]
    t = 1.0 / filt.sample_rate_hz
    q_of_x = c0_phi_inv[np.ix_(io, io)] @ c
    # u = -(g_x x + g_s s + g_z z) with v = scale (b0 q + s) and xi = z + T q
    g_x = (k_q + filt.scale * filt.b0 * k_v + t * k_i) @ q_of_x
    g_s = filt.scale * k_v
    g_z = k_i
    n = ad.shape[0]
    a = np.zeros((n + 4, n + 4))
    a[:n, :n] = ad - bd @ g_x
    a[:n, n:n + 2] = -bd @ g_s
    a[:n, n + 2:] = -bd @ g_z
    a[n:n + 2, :n] = (filt.b1 - filt.a1 * filt.b0) * q_of_x
    a[n:n + 2, n:n + 2] = -filt.a1 * np.eye(2)
    a[n + 2:, :n] = t * q_of_x
    a[n + 2:, n + 2:] = np.eye(2)
    return a


def pole_summary(poles: np.ndarray, sample_rate_hz: float) -> tuple[float, float]:
    """Spectral radius and the damping ratio of the least damped pole (via s = ln z / T)."""
    radius = float(np.max(np.abs(poles)))
    s = np.log(poles.astype(complex)) * sample_rate_hz
    damping = -s.real / np.maximum(np.abs(s), 1e-300)
    return radius, float(np.min(damping))


def check_load(model: FEModel, axial_load: float, gain: np.ndarray, c0_phi_inv: np.ndarray,
               filt: VelocityFilter, plane: str = "y") -> LoopCheck:
    """Discrete closed loop (full FE plant of one plane at the controller's sample rate,
    (C0 Phi)^-1, velocity filter, integrator, gain) at ``axial_load``.

    The two planes of the circular section have identical matrices up to the sign of the
    rotation DOF, i.e. the same spectrum; checking one plane checks both.
    """
    ad, bd, c = discrete_fe_plane(model, axial_load, 1.0 / filt.sample_rate_hz, plane)
    a = closed_loop_matrix(ad, bd, c, gain, c0_phi_inv, filt, plane)
    radius, damping = pole_summary(np.linalg.eigvals(a), filt.sample_rate_hz)
    return LoopCheck(load_n=float(axial_load), spectral_radius=radius, min_damping=damping)
