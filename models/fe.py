"""3D finite element model of the beam-column with piezo-elastic supports (section 2.1).

N nodes, N-1 Euler-Bernoulli elements with cubic Hermitian shape functions; node 1 and N
are the tips of the axial extensions (one element each), nodes 2 and N-1 the spring
elements of supports A and B, and the beam-column spans nodes 2..N-1 in N-3 equal
elements. Every node carries 4 DOF in the order (v, w, phi_y, phi_z) (eq. 3), with
phi_z = v' and phi_y = -w' so that eq. (1) holds as printed.

The bending planes decouple: x-y holds (v, phi_z), x-z holds (w, phi_y). Eigenproblems
are solved per plane, which keeps the y and z modes of the circular section apart instead
of returning an arbitrary mix of a repeated eigenvalue.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.linalg as sla

from beamctl.config.schema import ConfigError
from beamctl.models.params import ModelParameters

DOF_PER_NODE = 4
V, W, PHI_Y, PHI_Z = range(DOF_PER_NODE)
Plane = Literal["y", "z"]
# (lateral, rotation) DOF of each bending plane within a node
PLANE_DOFS: dict[str, tuple[int, int]] = {"y": (V, PHI_Z), "z": (W, PHI_Y)}
# rotation sign: phi_z = +v', phi_y = -w'
PLANE_ROTATION_SIGN = {"y": 1.0, "z": -1.0}


def planar_element(length: float, bending_stiffness: float, mass_per_length: float):
    """Mass, elastic and geometric stiffness of one Euler-Bernoulli element in one plane,
    DOF (u1, u1', u2, u2') (consistent mass; geometric stiffness for unit axial load)."""
    l = length
    ke = bending_stiffness / l**3 * np.array(
        [[12, 6 * l, -12, 6 * l], [6 * l, 4 * l * l, -6 * l, 2 * l * l],
         [-12, -6 * l, 12, -6 * l], [6 * l, 2 * l * l, -6 * l, 4 * l * l]])
    me = mass_per_length * l / 420.0 * np.array(
        [[156, 22 * l, 54, -13 * l], [22 * l, 4 * l * l, 13 * l, -3 * l * l],
         [54, 13 * l, 156, -22 * l], [-13 * l, -3 * l * l, -22 * l, 4 * l * l]])
    kg = 1.0 / l * np.array(
        [[6 / 5, l / 10, -6 / 5, l / 10], [l / 10, 2 * l * l / 15, -l / 10, -l * l / 30],
         [-6 / 5, -l / 10, 6 / 5, -l / 10], [l / 10, -l * l / 30, -l / 10, 2 * l * l / 15]])
    return me, ke, kg


def element_matrices(length: float, bending_stiffness: float, mass_per_length: float):
    """The [8 x 8] element mass, elastic and geometric stiffness matrices (eq. 1) in the DOF
    order (v1, w1, phi_y1, phi_z1, v2, w2, phi_y2, phi_z2)."""
    planar = planar_element(length, bending_stiffness, mass_per_length)
    out = []
    for m4 in planar:
        m8 = np.zeros((8, 8))
        for plane, (lat, rot) in PLANE_DOFS.items():
            sign = np.array([1.0, PLANE_ROTATION_SIGN[plane], 1.0, PLANE_ROTATION_SIGN[plane]])
            idx = [lat, rot, DOF_PER_NODE + lat, DOF_PER_NODE + rot]
            m8[np.ix_(idx, idx)] = sign[:, None] * m4 * sign[None, :]
        out.append(m8)
    return tuple(out)


def assemble(node_x: np.ndarray, bending_stiffness: np.ndarray, mass_per_length: np.ndarray):
    """Global M, Ke, Kg [4N x 4N] of a chain of elements between consecutive nodes.

    The geometric stiffness is assembled over every element: the axial load passes through
    the axial extensions as well (this reproduces the paper's 3194 N and 123.6/466.2 Hz).
    """
    n = DOF_PER_NODE * len(node_x)
    mass, elastic, geometric = np.zeros((n, n)), np.zeros((n, n)), np.zeros((n, n))
    for e in range(len(node_x) - 1):
        me, ke, kg = element_matrices(node_x[e + 1] - node_x[e], bending_stiffness[e],
                                      mass_per_length[e])
        s = slice(DOF_PER_NODE * e, DOF_PER_NODE * (e + 2))
        mass[s, s] += me
        elastic[s, s] += ke
        geometric[s, s] += kg
    return mass, elastic, geometric


def dof(node: int, which: int) -> int:
    """Global index of DOF ``which`` (V, W, PHI_Y, PHI_Z) at 0-based ``node``."""
    return DOF_PER_NODE * node + which


def plane_indices(n_nodes: int, plane: Plane) -> np.ndarray:
    """Global DOF indices of one bending plane, (lateral, rotation) node by node."""
    lat, rot = PLANE_DOFS[plane]
    return np.array([dof(k, d) for k in range(n_nodes) for d in (lat, rot)])


def curvature_row(node_x: np.ndarray, x: float, plane: Plane) -> np.ndarray:
    """Row vector mapping the DOF vector to the curvature u''(x) of one plane (Hermitian shape
    functions of the element holding ``x``; at a node, the mean of its two elements)."""
    n = DOF_PER_NODE * len(node_x)
    lat, rot = PLANE_DOFS[plane]
    sign = PLANE_ROTATION_SIGN[plane]
    tol = 1e-9 * (node_x[-1] - node_x[0])
    at_node = np.flatnonzero(np.abs(node_x - x) <= tol)
    if at_node.size and 0 < at_node[0] < len(node_x) - 1:
        elements = [at_node[0] - 1, at_node[0]]
    else:
        elements = [int(np.clip(np.searchsorted(node_x, x, side="right") - 1, 0, len(node_x) - 2))]
    row = np.zeros(n)
    for e in elements:
        l = node_x[e + 1] - node_x[e]
        xi = (x - node_x[e]) / l
        # second derivatives of the cubic Hermitian shape functions with respect to x
        g2 = np.array([(-6 + 12 * xi) / l**2, (-4 + 6 * xi) / l,
                       (6 - 12 * xi) / l**2, (-2 + 6 * xi) / l])
        idx = [dof(e, lat), dof(e, rot), dof(e + 1, lat), dof(e + 1, rot)]
        row[idx] += g2 * np.array([1.0, sign, 1.0, sign]) / len(elements)
    return row


def plane_eigen(stiffness: np.ndarray, mass: np.ndarray, plane: Plane, count: int):
    """Lowest ``count`` eigenpairs of (stiffness - lambda mass) restricted to one plane.

    Returns (lambda [count], vectors [4N x count]) with vectors mass-normalised and embedded
    in the full DOF vector (zero in the other plane).
    """
    n = stiffness.shape[0]
    idx = plane_indices(n // DOF_PER_NODE, plane)
    lam, vec = sla.eigh(stiffness[np.ix_(idx, idx)], mass[np.ix_(idx, idx)],
                        subset_by_index=[0, count - 1])
    full = np.zeros((n, count))
    full[idx] = vec
    return lam, full


def buckling_eigen(elastic: np.ndarray, geometric: np.ndarray,
                   plane: Plane = "y") -> tuple[float, np.ndarray]:
    """Lowest buckling load det(Ke - Fx Kg) = 0 of one plane (eq. 12) and its mode.

    Solved as Kg phi = mu Ke phi (Ke is positive definite thanks to the supports) with
    Fx,cr = 1/mu_max. Returns (Fx,cr in N, the mode as a full DOF vector, unscaled).
    """
    n = elastic.shape[0]
    idx = plane_indices(n // DOF_PER_NODE, plane)
    mu, vec = sla.eigh(geometric[np.ix_(idx, idx)], elastic[np.ix_(idx, idx)],
                       subset_by_index=[len(idx) - 1, len(idx) - 1])
    mode = np.zeros(n)
    mode[idx] = vec[:, 0]
    return float(1.0 / mu[0]), mode


@dataclass(frozen=True)
class FEModel:
    """Matrices of eq. (2) and (5) for one set of parameters.

    Attributes
    ----------
    node_x : [N] node positions in m (support A spring at 0, support B spring at beam length)
    mass, elastic_stiffness, geometric_stiffness, damping : [4N x 4N]
        M, Ke (beam and supports), Kg (for unit axial load) and D = alpha M + beta Ke.
    input_matrix : [4N x 4] B0, actuator forces (Fay,A, Faz,A, Fay,B, Faz,B) at nodes 1, N.
    output_matrix : [4 x 4N] C0, surface strains (eps_y1, eps_z1, eps_y2, eps_z2).
    rayleigh_alpha, rayleigh_beta : the damping coefficients (1/s and s).
    """

    params: ModelParameters
    node_x: np.ndarray
    mass: np.ndarray
    elastic_stiffness: np.ndarray
    geometric_stiffness: np.ndarray
    damping: np.ndarray
    input_matrix: np.ndarray
    output_matrix: np.ndarray
    rayleigh_alpha: float
    rayleigh_beta: float

    @property
    def n_nodes(self) -> int:
        return len(self.node_x)

    @property
    def n_dof(self) -> int:
        return DOF_PER_NODE * len(self.node_x)

    @property
    def beam_nodes(self) -> np.ndarray:
        """0-based indices of the nodes on the beam-column itself (nodes 2..N-1)."""
        return np.arange(1, self.n_nodes - 1)

    def load_stiffness(self, axial_load: float) -> np.ndarray:
        """Ke - Fx Kg, the stiffness of the loaded beam-column (eq. 2)."""
        return self.elastic_stiffness - axial_load * self.geometric_stiffness


def node_positions(params: ModelParameters) -> np.ndarray:
    """Node positions: extension tip, N-2 nodes spanning the beam, extension tip."""
    lb, le = params.beam.length, params.extension.length
    return np.concatenate([[-le], np.linspace(0.0, lb, params.fe.nodes - 2), [lb + le]])


def structure(params: ModelParameters):
    """Undamped M, Ke, Kg, B0, C0 of the paper's beam-column (eq. 1-5)."""
    x = node_positions(params)
    n_el = len(x) - 1
    b, e = params.beam, params.extension
    inertia_b, inertia_e = np.pi * b.radius**4 / 4, np.pi * e.radius**4 / 4
    bending = np.full(n_el, b.youngs_modulus * inertia_b)
    mu = np.full(n_el, b.density * np.pi * b.radius**2)
    for end in (0, n_el - 1):
        bending[end] = e.youngs_modulus * inertia_e
        mu[end] = e.density * np.pi * e.radius**2
    mass, elastic, geometric = assemble(x, bending, mu)

    s = params.supports
    last = len(x) - 1
    for node in (0, last):  # piezo stacks: lateral stiffness kp at nodes 1 and N
        for d in (V, W):
            elastic[dof(node, d), dof(node, d)] += s.actuator_stiffness
    for node in (1, last - 1):  # spring elements: kl and kr at nodes 2 and N-1
        for d in (V, W):
            elastic[dof(node, d), dof(node, d)] += s.lateral_stiffness
        for d in (PHI_Y, PHI_Z):
            elastic[dof(node, d), dof(node, d)] += s.rotational_stiffness

    n = DOF_PER_NODE * len(x)
    b0 = np.zeros((n, 4))  # eq. (2)/(4): u = (Fay,A, Faz,A, Fay,B, Faz,B)
    b0[dof(0, V), 0] = b0[dof(0, W), 1] = b0[dof(last, V), 2] = b0[dof(last, W), 3] = 1.0
    c0 = np.array([  # eq. (5): eps = -rb g''(xs)
        -b.radius * curvature_row(x, xs, plane)
        for xs in params.sensors.strain_gauge_positions for plane in ("y", "z")
    ])
    return x, mass, elastic, geometric, b0, c0


def rayleigh_coefficients(mass, elastic, geometric, ratios, load) -> tuple[float, float]:
    """alpha, beta of D = alpha M + beta Ke giving the two modal damping ratios to the first
    two bending modes of the beam loaded with ``load``.

    With mass-normalised loaded modes phi_i (eigenvalue w_i^2), the modal damping is
    phi_i^T D phi_i = alpha + beta phi_i^T Ke phi_i = 2 zeta_i w_i: two linear equations.
    """
    lam, modes = plane_eigen(elastic - load * geometric, mass, "y", 2)
    if lam[0] <= 0:
        return float("nan"), float("nan")
    omega = np.sqrt(lam)
    ke_modal = np.einsum("ij,ik,kj->j", modes, elastic, modes)
    alpha, beta = np.linalg.solve(np.column_stack([np.ones(2), ke_modal]),
                                  2.0 * np.asarray(ratios) * omega)
    return float(alpha), float(beta)


def build_model(params: ModelParameters) -> FEModel:
    """Assemble the FE model of eq. (2) and (5), with Rayleigh damping fitted at the
    identification load. Parameters that give negative damping are refused."""
    x, mass, elastic, geometric, b0, c0 = structure(params)
    d = params.damping
    alpha, beta = rayleigh_coefficients(mass, elastic, geometric, d.ratios, d.identification_load)
    if not np.isfinite(alpha):
        critical, _ = buckling_eigen(elastic, geometric)
        raise ConfigError("damping.identification_load", d.identification_load,
                          f"a load below this model's critical buckling load Fx,cr = "
                          f"{critical:.1f} N (the first mode has no frequency beyond it): the "
                          f"load at which damping.ratios were identified on this beam")
    if alpha < 0 or beta < 0:
        raise ConfigError(
            "damping.ratios", list(d.ratios),
            f"ratios that give non-negative Rayleigh coefficients at "
            f"damping.identification_load = {d.identification_load:g} N; they give "
            f"alpha = {alpha:.4g} 1/s, beta = {beta:.4g} s, i.e. negative damping")
    return FEModel(params=params, node_x=x, mass=mass, elastic_stiffness=elastic,
                   geometric_stiffness=geometric, damping=alpha * mass + beta * elastic,
                   input_matrix=b0, output_matrix=c0, rayleigh_alpha=alpha, rayleigh_beta=beta)
