"""A delay-aware model-based design: discrete LQG with integral action, per bending plane.

Design model (one plane): the first ``n_modes`` bending modes of the FE model at a fixed
reference load (mass-normalised, so the modal state matrix is affine in the axial load), the
static residual of the modes left out (the strain the stack forces cause through the modes
not modelled, a feedthrough of the force acting at the sampling instant), the I/O chain's
delay as buffer states, sampled with the exact delayed zero-order hold of models.iochain.

    s = [q (n_modes), dq/dt (n_modes), u_k-1 ... u_k-whole-1 (2 each)]
    s_k+1 = Phi s_k + Gamma u_k ;  y_k = Cs s_k  (Cs includes the residual on u_k-whole-1)
    xi_k = xi_k-1 + T H y_k   (H = (C0 Phi)^-1 of modes 1-2: the gauge-based modal displacement)

State feedback u = -Kx s - Kxi xi from a discrete LQR on [s; xi] with the weights of the
paper's design on modes 1-2 and their integrals (none on the higher modes); a steady-state
Kalman filter in current-estimator form with force noise at the stacks, process noise on the
higher modes and strain-gauge noise; the estimator is fed the force actually applied. As a
compensator (gains.compensator): with p the predicted state,

    s_hat = p + M (y - Cs p);  u = -Kx s_hat - Kxi xi;  p <- Phi s_hat + Gamma u_applied

so A = Phi (I - M Cs), B = Phi M, E = Gamma, C = Kx (I - M Cs), D = Kx M, Ki = Kxi, H.

Scaling: scipy's discrete Riccati solvers fail on this model in SI modal units; the design is
solved with displacements scaled to 1e-6 modal units, velocities to 1e-6 times each mode's
angular frequency, integrals to 1e-9 and forces in N, then transformed back.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np
import scipy.linalg as sla

from beamctl.gains.compensator import PLANE_CHANNELS, Compensator
from beamctl.models.analysis import critical_load
from beamctl.models.fe import FEModel, build_model, plane_eigen, plane_indices
from beamctl.models.iochain import IOChain, delayed_zoh, with_filters
from beamctl.models.modal import orient_modes

DISPLACEMENT_SCALE = 1e-6
INTEGRAL_SCALE = 1e-9
FILTER_SCALE = 1e-6        # anti-alias filter states, in strain


@dataclass(frozen=True)
class LqgSettings:
    """What an LQG design is made of (all stored in the gain table).

    n_modes: bending modes per plane in the design model.
    reference_load_fraction: load of the mode shapes, as a fraction of the design model's
        critical load.
    q_displacement, q_velocity, q_integral: LQR weights on modes 1 and 2 (as the paper's Q).
    r_force: LQR weight on each force (1/N^2).
    force_noise_n: standard deviation of the force disturbance at each stack per sample (N).
    high_mode_noise: process noise on the velocities of modes 3.. (modal units / s per sample,
        relative to force_noise_n through the mode's input gain: 0 means none).
    strain_noise: standard deviation of the strain measurement (strain).
    youngs_modulus_factor: the design model's beam Young's modulus relative to the model's
        (a softer design model moves the schedule towards the weakest rig).
    estimator_mode1_load_offset_n: the Kalman filter's (and the compensator's prediction) model
        of mode 1 alone sees the grid load plus this offset, a softer mode 1 than the LQR's; the
        higher modes keep the grid load (softening them instead destabilises mode 5 on stiff rigs).
    """

    n_modes: int = 7
    reference_load_fraction: float = 0.78
    q_displacement: tuple[float, float] = (2e10, 3e5)
    q_velocity: tuple[float, float] = (5e3, 0.5)
    q_integral: tuple[float, float] = (5e14, 5e14)
    r_force: float = 1.0
    force_noise_n: float = 1.0
    high_mode_noise: float = 0.0
    strain_noise: float = 0.2e-6
    youngs_modulus_factor: float = 1.0
    estimator_mode1_load_offset_n: float = 0.0

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


@dataclass(frozen=True)
class PlaneModel:
    """The design model of one plane, affine in the axial load."""

    k_elastic: np.ndarray      # [m x m]
    k_geometric: np.ndarray
    damping: np.ndarray
    b: np.ndarray              # [m x 2] modal force input
    c: np.ndarray              # [2 x m] strains per modal displacement
    residual: np.ndarray       # [2 x 2] strain per force of the modes left out
    omega: np.ndarray          # [m] angular frequencies at the reference load (scaling)

    def continuous(self, axial_load_n: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        m = self.k_elastic.shape[0]
        a = np.zeros((2 * m, 2 * m))
        a[:m, m:] = np.eye(m)
        a[m:, :m] = -(self.k_elastic - axial_load_n * self.k_geometric)
        a[m:, m:] = -self.damping
        b = np.vstack([np.zeros((m, 2)), self.b])
        c = np.hstack([self.c, np.zeros((2, m))])
        return a, b, c


def plane_model(model: FEModel, plane: str, n_modes: int, reference_load_n: float) -> PlaneModel:
    """Modal design model of one plane (see the module docstring)."""
    io = list(PLANE_CHANNELS[plane])
    k_ref = model.load_stiffness(reference_load_n)
    lam, phi = plane_eigen(k_ref, model.mass, plane, n_modes)
    if lam[0] <= 0:
        raise ValueError(f"reference load {reference_load_n:.1f} N is beyond the design model's "
                         f"critical load: no mode shapes to design on")
    phi = orient_modes(model, phi, plane)
    b0 = model.input_matrix[:, io]
    c0 = model.output_matrix[io]
    idx = plane_indices(model.n_nodes, plane)
    static = np.zeros((model.n_dof, 2))
    static[idx] = sla.solve(k_ref[np.ix_(idx, idx)], b0[idx], assume_a="sym")
    residual = c0 @ static - (c0 @ phi) @ np.diag(1.0 / lam) @ (phi.T @ b0)
    return PlaneModel(k_elastic=phi.T @ model.elastic_stiffness @ phi,
                      k_geometric=phi.T @ model.geometric_stiffness @ phi,
                      damping=phi.T @ model.damping @ phi, b=phi.T @ b0, c=c0 @ phi,
                      residual=residual, omega=np.sqrt(lam))


@dataclass(frozen=True)
class SampledDesignModel:
    """s_k+1 = phi s_k + gamma u_k, y_k = cs s_k, with s = [x, buffer]."""

    phi: np.ndarray
    gamma: np.ndarray
    cs: np.ndarray
    noise_in: np.ndarray       # [n x 2] a force disturbance at the stacks held over one sample
    n_modal: int


def sampled_model(pm: PlaneModel, axial_load_n: float, period_s: float, chain: IOChain) -> SampledDesignModel:
    """The design model with the delay as buffer states and the anti-alias filter's states after
    the modal states (the static residual reaches the strains unfiltered: a small error, the
    residual being nearly static). A reconstruction filter is not modelled: refused."""
    if chain.reconstruction is not None:
        raise ValueError("the LQG design does not model a reconstruction filter; declare only the "
                         "delay and the anti-alias filter")
    a, b, c = pm.continuous(axial_load_n)
    a, b, c, _ = with_filters(a, b, c, chain, n_control=2)
    zoh = delayed_zoh(a, b, period_s, chain.delay_samples)
    n = a.shape[0]
    whole = zoh.whole
    nb = 2 * (whole + 1)
    phi = np.zeros((n + nb, n + nb))
    gamma = np.zeros((n + nb, 2))
    phi[:n, :n] = zoh.ad

    def force(k_back: int, matrix: np.ndarray) -> None:
        if k_back == 0:
            gamma[:n] += matrix
        else:
            phi[:n, n + 2 * (k_back - 1):n + 2 * k_back] += matrix

    force(whole, zoh.b_now)
    if zoh.fraction > 0.0:
        force(whole + 1, zoh.b_before)
    gamma[n:n + 2] = np.eye(2)
    for j in range(1, whole + 1):
        phi[n + 2 * j:n + 2 * j + 2, n + 2 * (j - 1):n + 2 * j] = np.eye(2)
    cs = np.zeros((2, n + nb))
    cs[:, :n] = c
    # the residual strain of the force acting at the sampling instant: u_k-whole-1
    if chain.reconstruction is None:
        cs[:, n + 2 * whole:n + 2 * whole + 2] = pm.residual
    noise_in = np.zeros((n + nb, 2))
    noise_in[:n] = zoh.b_now + zoh.b_before
    return SampledDesignModel(phi=phi, gamma=gamma, cs=cs, noise_in=noise_in, n_modal=n)


def _scales(pm: PlaneModel, n_states: int, n_modal: int) -> np.ndarray:
    """Riccati scaling of the state [q, dq/dt, anti-alias filter (strain), buffer (N)]."""
    m = len(pm.omega)
    s = np.ones(n_states)
    s[:m] = DISPLACEMENT_SCALE
    s[m:2 * m] = DISPLACEMENT_SCALE * pm.omega
    s[2 * m:n_modal] = FILTER_SCALE
    return s


def plane_design(pm: PlaneModel, axial_load_n: float, period_s: float, chain: IOChain, h: np.ndarray,
                 settings: LqgSettings):
    """Compensator matrices (A, B, E, C, D, Ki) of one plane at one load."""
    sm = sampled_model(pm, axial_load_n, period_s, chain)
    phi, gamma, cs = sm.phi, sm.gamma, sm.cs
    n = phi.shape[0]
    m = len(pm.omega)
    # LQR on z = [s; xi]; xi_k+1 = xi_k + T H cs s_k+1
    t = period_s
    big_phi = np.zeros((n + 2, n + 2))
    big_phi[:n, :n] = phi
    big_phi[n:, :n] = t * h @ cs @ phi
    big_phi[n:, n:] = np.eye(2)
    big_gamma = np.vstack([gamma, t * h @ cs @ gamma])
    q = np.zeros(n + 2)
    q[0:2] = settings.q_displacement
    q[m:m + 2] = settings.q_velocity
    q[n:n + 2] = settings.q_integral
    # cost per sample = T x (continuous cost), the same for Q and R: their ratio is the paper's
    scale = np.concatenate([_scales(pm, n, sm.n_modal), np.full(2, INTEGRAL_SCALE)])
    sp = big_phi / scale[:, None] * scale[None, :]
    sg = big_gamma / scale[:, None]
    sq = np.diag(q * scale**2)
    r = settings.r_force * np.eye(2)
    p = sla.solve_discrete_are(sp, sg, sq, r)
    k_scaled = np.linalg.solve(r + sg.T @ p @ sg, sg.T @ p @ sp)
    k = k_scaled / scale[None, :]
    kx, kxi = k[:, :n], k[:, n:]
    # Kalman filter on s (the buffer is known exactly: no noise there)
    if settings.estimator_mode1_load_offset_n != 0.0:
        k_el = pm.k_elastic.copy()
        k_el[0, 0] -= settings.estimator_mode1_load_offset_n * pm.k_geometric[0, 0]
        sm = sampled_model(replace(pm, k_elastic=k_el), axial_load_n, period_s, chain)
        phi, gamma, cs = sm.phi, sm.gamma, sm.cs
    sc = _scales(pm, n, sm.n_modal)
    w = settings.force_noise_n**2 * sm.noise_in @ sm.noise_in.T
    if settings.high_mode_noise > 0 and m > 2:
        for i in range(2, m):
            w[m + i, m + i] += (settings.high_mode_noise * period_s) ** 2
    v = settings.strain_noise**2 * np.eye(2)
    sphi = phi / sc[:, None] * sc[None, :]
    scs = cs * sc[None, :]
    sw = w / sc[:, None] / sc[None, :]
    sw = 0.5 * (sw + sw.T) + 1e-30 * np.eye(n)
    pk = sla.solve_discrete_are(sphi.T, scs.T, sw, v)
    mk_scaled = pk @ scs.T @ np.linalg.inv(scs @ pk @ scs.T + v)
    mk = mk_scaled * sc[:, None]
    i_mc = np.eye(n) - mk @ cs
    return (phi @ i_mc, phi @ mk, gamma, kx @ i_mc, kx @ mk, kxi)


def design(model: FEModel, loads_n, sample_rate_hz: float, chain: IOChain, h: np.ndarray,
           settings: LqgSettings, progress=None) -> Compensator:
    """The LQG compensator of both planes at every grid load (states: plane y, then z)."""
    design_model = model
    if settings.youngs_modulus_factor != 1.0:
        params = model.params
        beam = replace(params.beam,
                       youngs_modulus=params.beam.youngs_modulus * settings.youngs_modulus_factor)
        design_model = build_model(replace(params, beam=beam))
    ref = settings.reference_load_fraction * critical_load(design_model)
    period = 1.0 / sample_rate_hz
    planes = {p: plane_model(design_model, p, settings.n_modes, ref) for p in ("y", "z")}
    loads = [float(x) for x in loads_n]
    per_plane = {}
    for p in ("y", "z"):
        io = list(PLANE_CHANNELS[p])
        per_plane[p] = [plane_design(planes[p], load, period, chain, h[np.ix_(io, io)], settings)
                        for load in loads]
        if progress:
            progress(p)
    ny = per_plane["y"][0][0].shape[0]
    nz = per_plane["z"][0][0].shape[0]
    nc = ny + nz
    g = len(loads)
    mats = {k: np.zeros(s) for k, s in (("a", (g, nc, nc)), ("b", (g, nc, 4)), ("e", (g, nc, 4)),
                                         ("c", (g, 4, nc)), ("d", (g, 4, 4)), ("ki", (g, 4, 4)))}
    states = {"y": list(range(ny)), "z": list(range(ny, nc))}
    for p in ("y", "z"):
        s = np.asarray(states[p])
        io = list(PLANE_CHANNELS[p])
        for i, (a, b, e, c, d, ki) in enumerate(per_plane[p]):
            mats["a"][i][np.ix_(s, s)] = a
            mats["b"][i][np.ix_(s, io)] = b
            mats["e"][i][np.ix_(s, io)] = e
            mats["c"][i][np.ix_(io, s)] = c
            mats["d"][i][np.ix_(io, io)] = d
            mats["ki"][i][np.ix_(io, io)] = ki
    # bumpless start: the predicted modal displacement of modes 1-2 from the gauges
    start = np.zeros((nc, 4))
    for p in ("y", "z"):
        io = list(PLANE_CHANNELS[p])
        s0 = states[p][0]
        start[np.ix_([s0, s0 + 1], io)] = h[np.ix_(io, io)]
    return Compensator(h=np.array(h, dtype=float), start=start, period_s=period, plane_states=states,
                       **mats)
