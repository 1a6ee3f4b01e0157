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

With a strain FIR pre-filter (``strain_fir`` = (b0 .. b_nf), nf >= 1) the estimator sees
yf_k = b0 y_k + b1 y_k-1 + ... instead of y_k: the design model gets the past strains
w = [y_k-1 .. y_k-nf] as states (yf = Cf [s; w]) and the compensator keeps the raw past strains
r = [y_k-1 .. y_k-nf] (x = [p; r], p the prediction of [s; w]), so with F = [b1 I .. b_nf I]:

    yf = b0 y + F r;  s_hat = p + M (yf - Cf p);  p <- Phi s_hat + Gamma u_applied;  r <- [y, r..]

The LQR ignores w (it does not act on the plant); the integral action keeps the raw y.

The strain prediction (``Compensator.predict``, for a sample that does not arrive) is the
strain the estimator expects: without the FIR (x = p, Cf = b0 Cs) y_hat = Cf p, so that
x <- A x + B y_hat + E u = Phi p + Gamma u, the time update without a measurement; with the FIR
the raw strain whose filtered value is the expected one, y_hat = (Cf p - F r) / b0, so that
yf = Cf p, s_hat = p and again p <- Phi p + Gamma u (and r <- [y_hat, r..]).

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
    estimator_mode1_offset_schedule: the estimator's mode-1 load offset as a function of the
        grid load, (load, offset) points, linear between them and held beyond the ends; ()
        means the constant estimator_mode1_load_offset_n at every load.
    q_velocity_high: LQR weights on the velocities of modes 3, 4, ... (() none): active damping
        of mode 3 keeps it stable across the box's output delays when the loop gain is high.
    strain_fir: coefficients (b0, b1, ...) of a digital FIR pre-filter on the strains the
        estimator sees, yf_k = b0 y_k + b1 y_k-1 + ... ((1.0,): none). (1, 2, 1)/4 has a double
        zero at the Nyquist frequency: it gain-stabilises mode 5 (2.5-2.7 kHz) for one sample
        of lag at low frequencies. The past strains are compensator states and states of the
        estimator's design model (the Kalman filter sees the filtered strains); the integral
        action keeps the raw strains.
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
    estimator_mode1_offset_schedule: tuple[tuple[float, float], ...] = ()
    q_velocity_high: tuple[float, ...] = ()
    strain_fir: tuple[float, ...] = (1.0,)

    def at_load(self, axial_load_n: float) -> LqgSettings:
        """The settings of the design at one grid load (the scheduled estimator offset)."""
        if not self.estimator_mode1_offset_schedule:
            return self
        points = np.asarray(self.estimator_mode1_offset_schedule, dtype=float)
        offset = float(np.interp(axial_load_n, points[:, 0], points[:, 1]))
        return replace(self, estimator_mode1_load_offset_n=offset)

    def to_dict(self) -> dict:
        def plain(v):
            return [plain(x) for x in v] if isinstance(v, (tuple, list)) else v
        return {k: plain(v) for k, v in asdict(self).items()}


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


def _with_fir(sm: SampledDesignModel, fir) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The sampled model with the strain FIR's past strains w_j = y_k-j (j = 1..len(fir)-1)
    after its states: (phi, gamma, cf, noise_in) with yf_k = cf [s_k; w_k]."""
    n = sm.phi.shape[0]
    nf = len(fir) - 1
    na = n + 2 * nf
    phi = np.zeros((na, na))
    phi[:n, :n] = sm.phi
    gamma = np.zeros((na, 2))
    gamma[:n] = sm.gamma
    cf = np.zeros((2, na))
    cf[:, :n] = fir[0] * sm.cs
    if nf:
        phi[n:n + 2, :n] = sm.cs
        for j in range(1, nf):
            phi[n + 2 * j:n + 2 * j + 2, n + 2 * (j - 1):n + 2 * j] = np.eye(2)
        for j in range(1, nf + 1):
            cf[:, n + 2 * (j - 1):n + 2 * j] = fir[j] * np.eye(2)
    noise_in = np.zeros((na, 2))
    noise_in[:n] = sm.noise_in
    return phi, gamma, cf, noise_in


def plane_design(pm: PlaneModel, axial_load_n: float, period_s: float, chain: IOChain, h: np.ndarray,
                 settings: LqgSettings):
    """Compensator matrices (A, B, E, C, D, Ki) and the strain prediction P of one plane at one
    load.

    With the strain FIR (nf = len(strain_fir) - 1 > 0) the compensator state is
    [p (the prediction of [s; w]), r (the raw past strains y_k-1 .. y_k-nf)]:
    yf = b0 y + F r, s_hat = p + M (yf - Cf p), u = -Kx s_hat - Kxi xi,
    p <- Phi s_hat + Gamma u_applied, r <- [y, r_1 .. r_nf-1]; P = [Cf, -F] / b0.
    Without it the state is p and P = Cf."""
    fir = tuple(float(b) for b in settings.strain_fir)
    nf = len(fir) - 1
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
    for i, weight in enumerate(settings.q_velocity_high[:max(m - 2, 0)]):
        q[m + 2 + i] = weight
    # cost per sample = T x (continuous cost), the same for Q and R: their ratio is the paper's
    scale = np.concatenate([_scales(pm, n, sm.n_modal), np.full(2, INTEGRAL_SCALE)])
    sp = big_phi / scale[:, None] * scale[None, :]
    sg = big_gamma / scale[:, None]
    sq = np.diag(q * scale**2)
    r = settings.r_force * np.eye(2)
    p = sla.solve_discrete_are(sp, sg, sq, r)
    k_scaled = np.linalg.solve(r + sg.T @ p @ sg, sg.T @ p @ sp)
    k = k_scaled / scale[None, :]
    kxi = k[:, n:]
    # the past strains of the FIR do not act on the plant: no feedback from them
    kx = np.zeros((2, n + 2 * nf))
    kx[:, :n] = k[:, :n]
    # Kalman filter on [s; w] (the buffer is known exactly: no noise there)
    if settings.estimator_mode1_load_offset_n != 0.0:
        k_el = pm.k_elastic.copy()
        k_el[0, 0] -= settings.estimator_mode1_load_offset_n * pm.k_geometric[0, 0]
        sm = sampled_model(replace(pm, k_elastic=k_el), axial_load_n, period_s, chain)
    phi, gamma, cf, noise_in = _with_fir(sm, fir)
    sc = np.concatenate([_scales(pm, n, sm.n_modal), np.full(2 * nf, FILTER_SCALE)])
    na = phi.shape[0]
    w = settings.force_noise_n**2 * noise_in @ noise_in.T
    if settings.high_mode_noise > 0 and m > 2:
        for i in range(2, m):
            w[m + i, m + i] += (settings.high_mode_noise * period_s) ** 2
    v = settings.strain_noise**2 * np.eye(2)
    sphi = phi / sc[:, None] * sc[None, :]
    scs = cf * sc[None, :]
    sw = w / sc[:, None] / sc[None, :]
    sw = 0.5 * (sw + sw.T) + 1e-30 * np.eye(na)
    pk = sla.solve_discrete_are(sphi.T, scs.T, sw, v)
    mk_scaled = pk @ scs.T @ np.linalg.inv(scs @ pk @ scs.T + v)
    mk = mk_scaled * sc[:, None]
    i_mc = np.eye(na) - mk @ cf
    if nf == 0:
        return (phi @ i_mc, phi @ mk, gamma, kx @ i_mc, kx @ mk, kxi, cf.copy())
    b0 = fir[0]
    f = np.hstack([fir[j] * np.eye(2) for j in range(1, nf + 1)])      # [2 x 2 nf]
    nr = 2 * nf
    a = np.zeros((na + nr, na + nr))
    a[:na, :na] = phi @ i_mc
    a[:na, na:] = phi @ mk @ f
    for j in range(1, nf):
        a[na + 2 * j:na + 2 * j + 2, na + 2 * (j - 1):na + 2 * j] = np.eye(2)
    b = np.zeros((na + nr, 2))
    b[:na] = b0 * phi @ mk
    b[na:na + 2] = np.eye(2)
    e = np.zeros((na + nr, 2))
    e[:na] = gamma
    c = np.hstack([kx @ i_mc, kx @ mk @ f])
    d = b0 * kx @ mk
    predict = np.hstack([cf, -f]) / b0
    return (a, b, e, c, d, kxi, predict)


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
        per_plane[p] = [plane_design(planes[p], load, period, chain, h[np.ix_(io, io)],
                                     settings.at_load(load)) for load in loads]
        if progress:
            progress(p)
    ny = per_plane["y"][0][0].shape[0]
    nz = per_plane["z"][0][0].shape[0]
    nc = ny + nz
    g = len(loads)
    mats = {k: np.zeros(s) for k, s in (("a", (g, nc, nc)), ("b", (g, nc, 4)), ("e", (g, nc, 4)),
                                         ("c", (g, 4, nc)), ("d", (g, 4, 4)), ("ki", (g, 4, 4)),
                                         ("predict", (g, 4, nc)))}
    states = {"y": list(range(ny)), "z": list(range(ny, nc))}
    for p in ("y", "z"):
        s = np.asarray(states[p])
        io = list(PLANE_CHANNELS[p])
        for i, (a, b, e, c, d, ki, predict) in enumerate(per_plane[p]):
            mats["predict"][i][np.ix_(io, s)] = predict
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
        # the FIR's past strains (the plane's last 2 nf states) and their predictions (the 2 nf
        # states before them) start at the strains
        for j in range(2 * (len(settings.strain_fir) - 1)):
            first = states[p][len(states[p]) - 2 * (j + 1)]
            start[np.ix_([first, first + 1], io)] = np.eye(2)
    return Compensator(h=np.array(h, dtype=float), start=start, period_s=period, plane_states=states,
                       **mats)
