"""Analyses of the FE model: state space (eq. 6/7), eigenfrequencies versus axial load
(eq. 11), critical buckling load (eq. 12) and frequency responses (eq. 9)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.linalg as sla

from beamctl.models.fe import (
    DOF_PER_NODE,
    PLANE_DOFS,
    FEModel,
    Plane,
    buckling_eigen,
    dof,
    plane_eigen,
    plane_indices,
)

# (states, inputs, outputs) of the y and z bending planes in the 4-input, 4-output systems
PLANE_IO = {"y": (0, 2), "z": (1, 3)}


def state_space(model: FEModel, axial_load: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A_FE(Fx), B_FE, C_FE of eq. (6)/(7) for the state x_FE = [r, r_dot]."""
    n = model.n_dof
    factor = sla.cho_factor(model.mass)
    rhs = np.hstack([model.load_stiffness(axial_load), model.damping, model.input_matrix])
    solved = sla.cho_solve(factor, rhs)
    a = np.zeros((2 * n, 2 * n))
    a[:n, n:] = np.eye(n)
    a[n:, :n] = -solved[:, :n]
    a[n:, n:] = -solved[:, n:2 * n]
    b = np.vstack([np.zeros((n, 4)), solved[:, 2 * n:]])
    c = np.hstack([model.output_matrix, np.zeros((4, n))])
    return a, b, c


def fe_plane_blocks(model: FEModel):
    """Independent (state, input, output) index blocks of the FE state space, one per plane."""
    n = model.n_dof
    blocks = []
    for plane in ("y", "z"):
        idx = plane_indices(model.n_nodes, plane)
        blocks.append((np.concatenate([idx, n + idx]), list(PLANE_IO[plane]), list(PLANE_IO[plane])))
    return blocks


def eigenvalues(model: FEModel, axial_load: float, count: int = 3, plane: Plane = "y") -> np.ndarray:
    """Lowest ``count`` eigenvalues (2 pi f)^2 of eq. (11) in one plane; negative once buckled."""
    lam, _ = plane_eigen(model.load_stiffness(axial_load), model.mass, plane, count)
    return lam


def eigenfrequencies(model: FEModel, axial_load: float, count: int = 3, plane: Plane = "y") -> np.ndarray:
    """Lowest ``count`` undamped eigenfrequencies in Hz of eq. (11) in one bending plane.

    A mode whose eigenvalue is not positive (the beam has buckled in it) is reported as 0 Hz.
    """
    lam = eigenvalues(model, axial_load, count, plane)
    return np.sqrt(np.clip(lam, 0.0, None)) / (2 * np.pi)


def critical_load(model: FEModel, plane: Plane = "y") -> float:
    """Lowest buckling load Fx,cr of eq. (12), det(Ke - Fx Kg) = 0, in N."""
    load, _ = buckling_mode(model, plane)
    return load


def buckling_mode(model: FEModel, plane: Plane = "y") -> tuple[float, np.ndarray]:
    """Critical load and first buckling mode of one plane.

    The mode (``fe.buckling_eigen``) is scaled to a largest lateral displacement on the beam
    of +1 (its sign chosen so that the beam bows towards the positive axis).
    """
    load, mode = buckling_eigen(model.elastic_stiffness, model.geometric_stiffness, plane)
    lateral = mode[[dof(k_, PLANE_DOFS[plane][0]) for k_ in model.beam_nodes]]
    mode /= lateral[np.argmax(np.abs(lateral))]
    return load, mode


def lateral_displacements(model: FEModel, r: np.ndarray) -> np.ndarray:
    """[n_beam_nodes x 2] lateral displacements (v, w) at the beam-column's nodes."""
    nodes = model.beam_nodes
    return np.column_stack([r[DOF_PER_NODE * nodes + PLANE_DOFS["y"][0]],
                            r[DOF_PER_NODE * nodes + PLANE_DOFS["z"][0]]])


def frequency_response(a: np.ndarray, b: np.ndarray, c: np.ndarray, freqs_hz: Sequence[float],
                       blocks: Sequence[tuple] | None = None) -> np.ndarray:
    """G(s) = C (sI - A)^-1 B at s = j 2 pi f for each frequency, shape [nf, ny, nu].

    The system is diagonalised once, A = V diag(lambda) V^-1, so each frequency costs a
    scaling of precomputed C V and V^-1 B instead of a matrix inverse. ``blocks`` lists
    independent (states, inputs, outputs) subsystems (the two bending planes); a block is
    diagonalised on its own, which keeps the repeated y/z eigenvalues of the circular
    section apart. Entries coupling different blocks are zero.
    """
    s = 2j * np.pi * np.asarray(freqs_hz, dtype=float)
    if blocks is None:
        blocks = [(np.arange(a.shape[0]), np.arange(b.shape[1]), np.arange(c.shape[0]))]
    g = np.zeros((len(s), c.shape[0], b.shape[1]), dtype=complex)
    for states, inputs, outputs in blocks:
        ab = a[np.ix_(states, states)]
        bb = b[np.ix_(states, inputs)]
        cb = c[np.ix_(outputs, states)]
        lam, vec = np.linalg.eig(ab)
        left = cb @ vec
        right = np.linalg.solve(vec, bb)
        g[np.ix_(np.arange(len(s)), outputs, inputs)] = np.einsum(
            "in,fn,nj->fij", left, 1.0 / (s[:, None] - lam[None, :]), right)
    return g


def fe_frequency_response(model: FEModel, axial_load: float, freqs_hz: Sequence[float]) -> np.ndarray:
    """The [nf x 4 x 4] matrix of frequency responses G_FE(Fx, s) of eq. (9)."""
    a, b, c = state_space(model, axial_load)
    return frequency_response(a, b, c, freqs_hz, fe_plane_blocks(model))
