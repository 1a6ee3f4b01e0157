"""Measured frequency responses of the rig: the strains per lateral actuator force, as
``beamctl identify`` records them or as another tool exported them.

A measurement holds, at ``nf`` frequencies, the 4 x 4 matrix of frequency responses
H[f, output, input] in strain per N, outputs (eps_y1, eps_z1, eps_y2, eps_z2) at the two gauge
positions, inputs (Fay,A, Faz,A, Fay,B, Faz,B), and the coherence of each entry. An entry that
was not measured (its input was not excited) is NaN in both.

What the model needs to compare itself with it: the axial load during the measurement, and
where known the sample rate of the data (the model is then sampled like the rig: zero-order
hold and the I/O chain's delay and filters) and the stack force per volt the forces were
computed with (the forces are then k (V - V_bias) along the stacks' axes, and the fit can
identify the true k).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

OUTPUTS = ("y1", "z1", "y2", "z2")          # eps_y1, eps_z1, eps_y2, eps_z2
INPUTS = ("yA", "zA", "yB", "zB")           # Fay,A, Faz,A, Fay,B, Faz,B
# the entries a bending plane couples (y outputs to y inputs, z to z); the others are zero
PLANE_PAIRS = {"y": ((0, 0), (0, 2), (2, 0), (2, 2)), "z": ((1, 1), (1, 3), (3, 1), (3, 3))}


@dataclass(frozen=True)
class FrfData:
    """A measured 4 x 4 frequency response matrix (see the module docstring).

    Attributes
    ----------
    frequencies_hz : [nf] strictly increasing, > 0.
    frf : [nf x 4 x 4] complex, strain per N; NaN where not measured.
    coherence : [nf x 4 x 4] in [0, 1]; NaN where not measured.
    load_n : the axial load during the measurement (N).
    sample_rate_hz : the rate the data was sampled at (None: unknown; the model is then taken
        in continuous time).
    force_constant_n_per_v : the stack force per volt the forces were computed with (None: the
        forces were measured, not computed from voltages).
    io : the rig's I/O chain the model should include (models/iochain.py mapping; None: none).
    settings : how it was measured (signal, band, averages, rig), JSON-ready.
    source : file name, for messages.
    """

    frequencies_hz: np.ndarray
    frf: np.ndarray
    coherence: np.ndarray
    load_n: float
    sample_rate_hz: float | None = None
    force_constant_n_per_v: float | None = None
    io: dict | None = None
    settings: dict[str, Any] = field(default_factory=dict)
    source: str = ""

    @property
    def measured(self) -> np.ndarray:
        """[4 x 4] bool: which entries were measured (finite somewhere)."""
        return np.any(np.isfinite(self.frf), axis=0)

    def label(self) -> str:
        name = self.source or "measurement"
        return f"{name} at {self.load_n:.0f} N"


def nan_matrix(nf: int) -> tuple[np.ndarray, np.ndarray]:
    """An all-unmeasured (frf, coherence) pair of ``nf`` frequencies."""
    return (np.full((nf, 4, 4), complex(math.nan, math.nan)), np.full((nf, 4, 4), math.nan))


def resonances(data: FrfData, count: int = 3, min_coherence: float = 0.5) -> dict[str, list[float]]:
    """The ``count`` most prominent resonance frequencies (Hz, ascending) of each bending plane:
    peaks of the plane's measured responses (each normalised to its largest magnitude, summed
    over the plane's entries, points below ``min_coherence`` left out), refined by a parabola
    through the peak's neighbours on the log magnitude."""
    from scipy.signal import find_peaks

    f = data.frequencies_hz
    out: dict[str, list[float]] = {}
    for plane, pairs in PLANE_PAIRS.items():
        total = np.zeros(len(f))
        for i, j in pairs:
            h = np.abs(data.frf[:, i, j])
            if not np.all(np.isfinite(h)) or not h.max() > 0:
                continue
            good = np.nan_to_num(data.coherence[:, i, j], nan=0.0) >= min_coherence
            total += np.where(good, h / h.max(), 0.0)
        if not total.max() > 0:
            out[plane] = []
            continue
        peaks, props = find_peaks(total, prominence=0.05 * total.max())
        best = peaks[np.argsort(props["prominences"])[::-1][:count]]
        found = []
        for k in sorted(best):
            if 0 < k < len(f) - 1 and np.all(total[k - 1:k + 2] > 0):
                a, b, c = np.log(total[k - 1:k + 2])
                shift = 0.5 * (a - c) / (a - 2 * b + c) if a - 2 * b + c != 0 else 0.0
                found.append(float(f[k] + shift * (f[k + 1] - f[k - 1]) / 2))
            else:
                found.append(float(f[k]))
        out[plane] = found
    return out
