"""The paper's discrete controller pieces and what a closed-loop check reports.

The paper's controller per sample k (section 4; run by rt as the compensator of
``gains.compensator.from_integral_lqr``):

    q_k   = (C0 Phi)^-1 y_k                        modal displacements, eq. (30)
    h_k   = b0 q_k + s_k ;  s_k+1 = b1 q_k - a1 h_k  first-order Butterworth high-pass
    v_k   = omega_c h_k                            modal velocity estimate
    xi_k  = xi_k-1 + T q_k                         discrete integrator of eq. (21)
    u_k   = -K(Fx) [q_k, v_k, xi_k]                eq. (27)

and u_k is held on the actuators until the next sample. For frequencies well below the
cut-off f_c, omega_c s / (s + omega_c) ~ s: the scaled high-pass output tracks dq/dt with a
phase lag of atan(f / f_c). The closed loop every check analyses is built in
gains/closedloop.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.signal as sig


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


def pole_summary(poles: np.ndarray, sample_rate_hz: float) -> tuple[float, float]:
    """Spectral radius and the damping ratio of the least damped pole (via s = ln z / T; a pole
    at z = 0, e.g. of a hold's buffer, dies within a sample: damping 1)."""
    radius = float(np.max(np.abs(poles)))
    poles = poles[poles != 0]
    if poles.size == 0:
        return radius, 1.0
    s = np.log(poles.astype(complex)) * sample_rate_hz
    damping = -s.real / np.maximum(np.abs(s), 1e-300)
    return radius, float(np.min(damping))
