"""Reduced modal model (section 3.1): the first two bending modes in y and z, eq. (13)-(20),
and the strain-to-modal-displacement map (C0 Phi)^-1 of eq. (30)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from beamctl.config.schema import ConfigError
from beamctl.models.analysis import PLANE_IO, critical_load, frequency_response, lateral_displacements
from beamctl.models.fe import PLANE_DOFS, FEModel, dof, plane_eigen

MODES_PER_PLANE = 2
# column order of Phi (eq. 15) and of q_m (eq. 13): (1y, 1z, 2y, 2z)
MODE_ORDER = (("y", 0), ("z", 0), ("y", 1), ("z", 1))


def orient_modes(model: FEModel, vectors: np.ndarray, plane: str) -> np.ndarray:
    """Fix the arbitrary sign of each mode: the lateral displacement weighted towards
    support A (weight lb - x) is positive, i.e. the first half-wave bows to +y (+z)."""
    lat = PLANE_DOFS[plane][0]
    nodes = model.beam_nodes
    weight = model.params.beam.length - model.node_x[nodes]
    rows = [dof(k, lat) for k in nodes]
    signs = np.sign(weight @ vectors[rows])
    signs[signs == 0] = 1.0
    return vectors * signs


@dataclass(frozen=True)
class ModalModel:
    """The reduced modal model of eq. (16)-(19).

    Attributes
    ----------
    reference_load : axial load (N) at which the mode shapes were computed.
    phi : [4N x 4] mass-normalised mode shapes (1y, 1z, 2y, 2z), eq. (15).
    stiffness_elastic, stiffness_geometric, damping : [4 x 4] modal matrices of eq. (16).
    input_matrix : [8 x 4] Bm; output_matrix : [4 x 8] Cm (eq. 18).
    c0_phi, c0_phi_inv : [4 x 4] (C0 Phi) and its inverse (eq. 30).
    condition_number : 2-norm condition number of C0 Phi.
    """

    reference_load: float
    phi: np.ndarray
    stiffness_elastic: np.ndarray
    stiffness_geometric: np.ndarray
    damping: np.ndarray
    input_matrix: np.ndarray
    output_matrix: np.ndarray
    c0_phi: np.ndarray
    c0_phi_inv: np.ndarray
    condition_number: float

    def system_matrix(self, axial_load: float) -> np.ndarray:
        """Am(Fx) of eq. (18), [8 x 8], for the state x_m = [q_m, q_m_dot]."""
        a = np.zeros((8, 8))
        a[:4, 4:] = np.eye(4)
        a[4:, :4] = -self.stiffness_elastic + axial_load * self.stiffness_geometric
        a[4:, 4:] = -self.damping
        return a

    def eigenfrequencies(self, axial_load: float) -> np.ndarray:
        """Undamped eigenfrequencies (Hz) of the reduced model in the y plane, ascending;
        0 Hz for a mode that has buckled."""
        k = self.stiffness_elastic - axial_load * self.stiffness_geometric
        y = [i for i, (plane, _) in enumerate(MODE_ORDER) if plane == "y"]
        lam = np.linalg.eigvalsh(k[np.ix_(y, y)])
        return np.sqrt(np.clip(lam, 0.0, None)) / (2 * np.pi)

    def critical_load(self) -> float:
        """Buckling load of the reduced model, det(Ke~ - Fx Kg~) = 0."""
        mu = np.linalg.eigvals(np.linalg.solve(self.stiffness_elastic, self.stiffness_geometric))
        return float(1.0 / np.max(mu.real))

    def frequency_response(self, axial_load: float, freqs_hz) -> np.ndarray:
        """Gm(Fx, s) of eq. (20), [nf x 4 x 4]."""
        blocks = []
        for plane in ("y", "z"):
            modes = [i for i, (p, _) in enumerate(MODE_ORDER) if p == plane]
            io = list(PLANE_IO[plane])
            blocks.append((np.array(modes + [m + 4 for m in modes]), io, io))
        return frequency_response(self.system_matrix(axial_load), self.input_matrix,
                                  self.output_matrix, freqs_hz, blocks)


def reduce(model: FEModel, reference_load: float | None = None) -> ModalModel:
    """Modal truncation of ``model`` to two bending modes per plane (eq. 14-19).

    The mode shapes are those of the beam loaded with ``reference_load`` in N (default: the
    parameters' ``modal.reference_load_fraction`` of the model's own critical load, so that
    the reference load lies below it for every model). A gauge placement for which C0 Phi is
    ill-conditioned (condition number above ``sensors.max_condition_number``) is refused.
    """
    if reference_load is None:
        fraction = model.params.modal.reference_load_fraction
        key, value, load = "modal.reference_load_fraction", fraction, fraction * critical_load(model)
    else:
        key, value, load = "reference_load", reference_load, reference_load
    k_ref = model.load_stiffness(load)
    per_plane = {}
    for plane in ("y", "z"):
        lam, vec = plane_eigen(k_ref, model.mass, plane, MODES_PER_PLANE)
        if lam[0] <= 0:
            raise ConfigError(key, value,
                              f"a load below the critical buckling load (at {load:.1f} N the "
                              f"first mode has buckled and has no mode shape to reduce onto)")
        per_plane[plane] = orient_modes(model, vec, plane)
    phi = np.column_stack([per_plane[plane][:, i] for plane, i in MODE_ORDER])

    k_e = phi.T @ model.elastic_stiffness @ phi
    k_g = phi.T @ model.geometric_stiffness @ phi
    d = phi.T @ model.damping @ phi
    b_m = np.vstack([np.zeros((4, 4)), phi.T @ model.input_matrix])
    c0_phi = model.output_matrix @ phi
    c_m = np.hstack([c0_phi, np.zeros((4, 4))])
    cond = float(np.linalg.cond(c0_phi))
    limit = model.params.sensors.max_condition_number
    if not np.isfinite(cond) or cond > limit:
        raise ConfigError(
            "sensors.strain_gauge_positions", list(model.params.sensors.strain_gauge_positions),
            f"gauge positions that observe both modes: cond(C0 Phi) = {cond:.4g} exceeds "
            f"sensors.max_condition_number = {limit:g} (a gauge at a node of a mode, or two "
            f"gauges seeing the same mode combination)")
    return ModalModel(reference_load=load, phi=phi, stiffness_elastic=k_e, stiffness_geometric=k_g,
                      damping=d, input_matrix=b_m, output_matrix=c_m, c0_phi=c0_phi,
                      c0_phi_inv=np.linalg.inv(c0_phi), condition_number=cond)


class Deflection:
    """Largest lateral deflection along the beam from modal displacements (Phi q)."""

    def __init__(self, model) -> None:
        phi = reduce(model).phi
        lat = np.stack([lateral_displacements(model, phi[:, j]) for j in range(4)], axis=-1)
        self._vy, self._vz = lat[:, 0, :], lat[:, 1, :]       # [n_beam x 4]
        self._y = np.zeros(len(self._vy))
        self._z = np.zeros(len(self._vz))

    def __call__(self, q: np.ndarray) -> tuple[float, float, float]:
        """(|w|, w_y, w_z) in m at the point of largest magnitude, of one q."""
        np.dot(self._vy, q, out=self._y)
        np.dot(self._vz, q, out=self._z)
        mag = np.hypot(self._y, self._z)
        k = int(np.argmax(mag))
        return float(mag[k]), float(self._y[k]), float(self._z[k])

    def many(self, q: np.ndarray) -> np.ndarray:
        """[m x 3] for q [m x 4]: the largest magnitude (m) and its y and z components."""
        return np.column_stack(self.series(q))

    def series(self, q: np.ndarray, chunk: int = 20_000) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(|w|, w_y, w_z) in m of every row of ``q`` [n x 4], as ``__call__`` gives them one by
        one (``chunk`` rows at a time: a long recording never builds its whole [n x nodes] field)."""
        q = np.asarray(q, dtype=float)
        out = np.empty((3, len(q)))
        for start in range(0, len(q), chunk):
            block = q[start:start + chunk]
            y, z = block @ self._vy.T, block @ self._vz.T
            mag = np.hypot(y, z)
            k = np.argmax(mag, axis=1)
            rows = np.arange(len(block))
            out[:, start:start + len(block)] = mag[rows, k], y[rows, k], z[rows, k]
        return out[0], out[1], out[2]
