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
