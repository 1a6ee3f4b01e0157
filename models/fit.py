"""Fitting model parameters to measured frequency responses and eigenfrequencies.

The model of a measurement is the sampled plant (models/plant.py) of the parameters at the
measurement's load, sampled like the rig (its rate, the zero-order hold, its I/O chain), from
the four commanded forces to the four measured strains; where the forces were computed from
voltages with a force constant k_m, the model is scaled by k / k_m, k the stack force per volt
being fitted. A measurement without a sample rate is compared with the continuous FE response.

The error, per measured entry of each bending plane's 2 x 2 block and per frequency in the band
whose coherence reaches ``min_coherence``:

    r = w log(H_measured / H_model),   w = sqrt(gamma^2 / (1 - gamma^2)) (gamma^2 <= 0.999)

split into its real part (the log-magnitude error) and its imaginary part (the phase error in
rad). For the H1 estimate both parts have the variance (1 - gamma^2) / (2 n gamma^2) (n averages),
so w weighs each frequency by how well it was measured: the resonances, where the response
stands far above the noise, count most; antiresonances and the noise floor hardly at all. The
gamma^2 of the weight is the running median of the measured coherence over WEIGHT_LINES lines:
a line's own coherence estimate moves with that line's noise, and weights that follow the error
they weigh bias the fit (measured with ``beamctl model coverage``: at 2800 N, kr 9 % off and its
interval covering 3 of 6 rigs with each line's own coherence, 5.8 % and 5 of 6 with the median;
across 1000, 2000 and 2800 N the force constant's interval went from 0 to 6 of 6). Which points
enter the fit is still decided by each line's own coherence.
Measured eigenfrequencies add (ln f_model - ln f_measured) / sigma.

Free parameters: any numeric key of the model configuration (``beam.youngs_modulus``,
``damping.ratios``, ...), a list key with all its elements, and ``actuators.force_constant_n_per_v``.
Each is fitted as ln(p / p_start) within ``BOUND_FACTOR`` of the start (damping ratios below
0.9); gauge positions as an offset within +- ``GAUGE_BOUND_M``. Nonlinear least squares
(scipy.optimize.least_squares, trust region reflective) from the start model; the standard
errors come from the Jacobian at the solution, cov = s^2 (J^T J)^-1 with s^2 the residual
variance. A fit that did not converge, that ends on a bound, or whose data do not determine a
parameter is refused (FitError).

The mesh: the model's strains at the gauges come from the curvature of cubic elements, linear
within an element, so the mesh moves them by up to 0.1 %; with correlated parameters (kr, kl, kp)
that moves the fit by percent. The fit is therefore polished on the mesh with twice the beam
elements, from the solution on the model's own (the values, cost and Jacobian are then the finer
mesh's; the fitted model keeps the start's mesh). The change is reported (``mesh_correction``)
and, times MESH_UNCERTAINTY, added in quadrature to each standard error as the finer mesh's own
uncertainty, since the error does not shrink steadily with the mesh (it depends on where in its
element a gauge lies).

Tied parameters: per group of parameters correlated beyond COMBINED_CORRELATION the product of
their powers the data determine best is reported (``combinations``). The supports' stiffnesses
(kr, kl, kp) are such a group: the strains see mostly one effective rotational stiffness. Each of
them in a tie gets a standard error of at least TIED_RELATIVE_ERROR and is ``undetermined``: along
the tie, the part of the residual that is not noise moves them further than the noise says.

How sure it is: ``misfit`` is the residual over what the measured coherence and averages predict
(1: the model explains the data down to their noise); ``warnings`` name a misfit above
``MISFIT_WARNING`` and parameters whose standard error passes ``WEAK_RELATIVE_ERROR`` of the
value, with what the data tie them to.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.ndimage import median_filter
from scipy.optimize import least_squares

from beamctl.config.schema import ConfigError, merge, nested
from beamctl.models.analysis import eigenfrequencies, fe_frequency_response
from beamctl.models.fe import build_model
from beamctl.models.measured import PLANE_PAIRS, FrfData, resonances
from beamctl.models.params import ModelParameters, parameters_from_dict
from beamctl.models.plant import Plant, plant_config

FORCE_CONSTANT_KEY = "actuators.force_constant_n_per_v"
GAUGES_KEY = "sensors.strain_gauge_positions"
ALIASES = {
    "E": "beam.youngs_modulus",
    "kr": "supports.rotational_stiffness",
    "kl": "supports.lateral_stiffness",
    "kp": "supports.actuator_stiffness",
    "damping": "damping.ratios",
    "gauges": GAUGES_KEY,
    "force_constant": FORCE_CONSTANT_KEY,
}
# the supports' three stiffnesses are free by default: the data tie them together (the fit says
# how: ``combinations``) but a rig's kl and kp differ from Table 1's by up to 20 % (measured
# statically), and held at Table 1's, kr takes up their difference (+51 % on a rig 15 to 18 %
# stiffer) with the misfit near 1
DEFAULT_PARAMETERS = ("E", "kr", "kl", "kp", "damping", "force_constant")
# keys that describe the model's numerics or a measured condition, not the beam: never fitted
NOT_FITTED = ("fe.nodes", "modal.reference_load_fraction", "damping.identification_load",
              "sensors.max_condition_number")
BOUND_FACTOR = 3.0
MAX_NODES = 401                 # the largest mesh a model may have (models/params.py)
GAUGE_BOUND_M = 0.01
MAX_DAMPING_RATIO = 0.9
MAX_COHERENCE = 0.999
WEIGHT_LINES = 9                # the coherence of a weight: the running median over this many lines
CORRELATION_REPORTED = 0.9      # pairs correlated beyond this are reported as poorly separable
MISFIT_WARNING = 2.0            # a residual variance beyond this many times the predicted is warned of
WEAK_RELATIVE_ERROR = 0.01      # a standard error beyond this fraction (95 %: +-2 %) is warned of
UNDETERMINED_RELATIVE_ERROR = 0.025   # beyond this (95 %: +-5 %) a parameter is undetermined: the data do
                                      # not place it; a calibrated box keeps the prior's range for it
COMBINED_CORRELATION = 0.95     # parameters correlated beyond this (chained) form a group whose best
                                # determined product of powers is reported (``combinations``)
SUPPORT_KEYS = ("supports.rotational_stiffness", "supports.lateral_stiffness", "supports.actuator_stiffness")
TIED_RELATIVE_ERROR = 0.05      # the least standard error of a support stiffness tied to another: each
                                # is undetermined, their combination is what the data give
_FAILED_RESIDUAL = 1e3          # per residual, where the parameters give no valid model
MESH_UNCERTAINTY = 2.5          # the finer mesh's change times this is its own uncertainty (the mesh
                                # error is erratic, set by where in its element a gauge lies; with kl and
                                # kp free it moves the supports along what the data tie together:
                                # `beamctl model coverage --scatter-supports`, 20 rigs on 71 nodes, at 1 x
                                # the change kr's interval held the rig 14 times, kp's 14, kl's 16)
# the resonance stage (``resonance_start``): the stiffness parameters, matched to the measured
# resonances first (each peak to the nearest of the plane's lowest RESONANCE_MODES eigenfrequencies,
# its log error over RESONANCE_SIGMA), RESONANCE_PEAKS per plane and measurement
STIFFNESS_KEYS = ("beam.youngs_modulus", "supports.rotational_stiffness", "supports.lateral_stiffness",
                  "supports.actuator_stiffness")
RESONANCE_MODES = 4
RESONANCE_PEAKS = 3
RESONANCE_SIGMA = 0.005
# then the damping ratios, together, scaled by the factor of this grid whose residual is least
DAMPING_SCAN = tuple(float(v) for v in np.exp(np.linspace(np.log(0.25), np.log(4.0), 9)))


class FitError(Exception):
    """The fit cannot be trusted (not converged, on a bound, a parameter not determined)."""


@dataclass(frozen=True)
class Eigenfrequency:
    """A measured eigenfrequency: ``mode`` (1, 2, 3) in ``plane`` at ``load_n``; ``sigma`` its
    relative uncertainty."""

    load_n: float
    mode: int
    frequency_hz: float
    plane: str = "y"
    sigma: float = 0.005


@dataclass(frozen=True)
class FitSettings:
    parameters: tuple[str, ...] = DEFAULT_PARAMETERS
    band_hz: tuple[float, float] = (0.0, math.inf)
    min_coherence: float = 0.5
    max_evaluations: int = 400
    mesh_correction: bool = True
    resonance_start: bool = True


@dataclass
class FitResult:
    keys: list[str]                          # the dotted keys, in order
    start: dict[str, Any]                    # start values (a list for a list key)
    values: dict[str, Any]
    std_errors: dict[str, Any]
    correlations: dict[str, float]           # "key_a|key_b" of the pairs beyond CORRELATION_REPORTED
    cost: float                              # 0.5 sum r^2 at the solution
    start_cost: float
    residuals: int
    evaluations: int
    message: str
    parameters: ModelParameters              # the fitted model
    force_constant_n_per_v: float | None     # fitted, or None
    correlation_matrix: list[list[float]] = field(default_factory=list)
    names: list[str] = field(default_factory=list)   # one per scalar unknown ("damping.ratios[0]")
    # per scalar unknown, the change the finer mesh made (relative; gauges in m); {} when not applied
    mesh_correction: dict[str, float] = field(default_factory=dict)
    # the residual's variance over what the measured coherence and averages predict (1: the model
    # explains the data down to their noise); None when a file does not record its averages
    misfit: float | None = None
    warnings: list[str] = field(default_factory=list)
    # the scalar unknowns whose standard error passes UNDETERMINED_RELATIVE_ERROR of the value
    undetermined: list[str] = field(default_factory=list)
    # per group of parameters the data tie together: the product of their powers the data
    # determine best ({"names", "exponents", "relative_std_error", "text"})
    combinations: list[dict[str, Any]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"parameters": self.values, "std_errors": self.std_errors, "cost": self.cost,
                "mesh_correction": self.mesh_correction, "misfit": self.misfit, "warnings": self.warnings,
                "undetermined": self.undetermined, "combinations": self.combinations,
                "start": self.start, "start_cost": self.start_cost, "correlations": self.correlations,
                "residuals": self.residuals, "evaluations": self.evaluations, "message": self.message}


def resolve_keys(names: Sequence[str], start: ModelParameters) -> list[str]:
    """Dotted keys of the parameters to fit (aliases E, kr, kl, kp, damping, gauges,
    force_constant allowed); an unknown or non-numeric key is refused naming it."""
    flat = _flatten(start.to_dict())
    keys: list[str] = []
    for name in names:
        key = ALIASES.get(name, name)
        if key != FORCE_CONSTANT_KEY and (key not in flat or key in NOT_FITTED):
            numeric = sorted(k for k in flat if k not in NOT_FITTED)
            raise ConfigError("--params", name, f"a model key or an alias: {', '.join(ALIASES)}; "
                                                f"or one of {', '.join(numeric)}")
        if key in keys:
            raise ConfigError("--params", name, "each parameter once")
        keys.append(key)
    if not keys:
        raise ConfigError("--params", "", "at least one parameter to fit")
    return keys


def _flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def model_response(params: ModelParameters, d: FrfData, freqs_hz: np.ndarray,
                   force_constant_n_per_v: float | None = None) -> np.ndarray:
    """The model's [nf x 4 x 4] response as measurement ``d`` would see it at ``freqs_hz``: the
    sampled plant at d's rate and I/O chain (the continuous FE response when d has no rate), at
    d's load, scaled by k / k_d when the stacks' true force per volt k differs from the k_d d's
    forces were computed with (``None``: k = k_d)."""
    model = build_model(params)
    if d.sample_rate_hz:
        plant = Plant(model, plant_config({"sample_rate_hz": d.sample_rate_hz, "io": d.io or {}}))
        g = plant.frequency_response(d.load_n, freqs_hz)
    else:
        g = fe_frequency_response(model, d.load_n, freqs_hz)
    if force_constant_n_per_v is not None and d.force_constant_n_per_v:
        g = g * (force_constant_n_per_v / d.force_constant_n_per_v)
    return g


class Problem:
    """The residual function of one fit: unknowns x -> weighted residuals."""

    def __init__(self, start: ModelParameters, keys: list[str], data: Sequence[FrfData],
                 eigen: Sequence[Eigenfrequency], settings: FitSettings) -> None:
        self.start = start
        self.keys = keys
        self.data = list(data)
        self.eigen = list(eigen)
        flat = _flatten(start.to_dict())
        known = [d.force_constant_n_per_v for d in self.data if d.force_constant_n_per_v]
        if FORCE_CONSTANT_KEY in keys and not known:
            raise ConfigError("--params", FORCE_CONSTANT_KEY,
                              "measurements whose forces were computed from voltages (none of the files "
                              "records force_constant_n_per_v, so the stack force per volt cannot be fitted)")
        self.force_constant_start = known[0] if known else None
        self.start_values: dict[str, Any] = {
            k: (self.force_constant_start if k == FORCE_CONSTANT_KEY else flat[k]) for k in keys}
        # one scalar unknown per value (a list key: one per element)
        self.names: list[str] = []
        self.slots: list[tuple[str, int | None]] = []
        low, high = [], []
        for k in keys:
            v = self.start_values[k]
            for i, x0 in enumerate(v if isinstance(v, list) else [v]):
                self.names.append(f"{k}[{i}]" if isinstance(v, list) else k)
                self.slots.append((k, i if isinstance(v, list) else None))
                if k == GAUGES_KEY:
                    low.append(-GAUGE_BOUND_M)
                    high.append(GAUGE_BOUND_M)
                else:
                    top = BOUND_FACTOR if k != "damping.ratios" else min(BOUND_FACTOR, MAX_DAMPING_RATIO / x0)
                    low.append(-math.log(BOUND_FACTOR))
                    high.append(max(math.log(top), 1e-3))   # a start at the cap may still rise a little
        self.bounds = (np.array(low), np.array(high))
        self.selection = [self._select(d, settings) for d in self.data]
        if sum(len(f) for f, _ in self.selection) == 0 and not self.eigen:
            raise ConfigError("--band", f"{settings.band_hz[0]:g}:{settings.band_hz[1]:g}",
                              f"a band with measured points of coherence >= {settings.min_coherence:g} "
                              "(none of the files has any)")

    @staticmethod
    def _select(d: FrfData, s: FitSettings):
        """(frequency indices, [(out, in, weights)]) of the points that enter the fit."""
        lo, hi = s.band_hz
        in_band = (d.frequencies_hz >= lo) & (d.frequencies_hz <= hi)
        if d.sample_rate_hz:
            in_band &= d.frequencies_hz < 0.5 * d.sample_rate_hz
        entries = []
        for pairs in PLANE_PAIRS.values():
            for i, j in pairs:
                if not np.isfinite(d.frf[0, i, j]):
                    continue
                g2 = d.coherence[:, i, j]
                ok = in_band & (g2 >= s.min_coherence) & (np.abs(d.frf[:, i, j]) > 0)
                g2 = np.minimum(median_filter(g2, size=WEIGHT_LINES, mode="nearest"), MAX_COHERENCE)
                entries.append((i, j, ok, np.sqrt(g2 / (1.0 - g2))))
        used = np.flatnonzero(np.any([e[2] for e in entries], axis=0)) if entries else np.zeros(0, int)
        return used, [(i, j, ok[used], w[used]) for i, j, ok, w in entries]

    def values(self, x: np.ndarray) -> dict[str, Any]:
        out = {k: (list(v) if isinstance(v, list) else v) for k, v in self.start_values.items()}
        for xi, (k, i) in zip(x, self.slots, strict=True):
            base = self.start_values[k] if i is None else self.start_values[k][i]
            value = base + xi if k == GAUGES_KEY else base * math.exp(xi)
            if i is None:
                out[k] = value
            else:
                out[k][i] = value
        return out

    def model(self, values: dict[str, Any]) -> ModelParameters:
        overrides: dict = {}
        for k, v in values.items():
            if k != FORCE_CONSTANT_KEY:
                overrides = merge(overrides, nested(k, v))
        return parameters_from_dict(merge(self.start.to_dict(), overrides), "fit")

    def residuals(self, x: np.ndarray) -> np.ndarray:
        values = self.values(x)
        try:
            params = self.model(values)
            parts = []
            for d, (used, entries) in zip(self.data, self.selection, strict=True):
                if not len(used):
                    continue
                g = model_response(params, d, d.frequencies_hz[used], values.get(FORCE_CONSTANT_KEY))
                for i, j, ok, w in entries:
                    with np.errstate(divide="ignore", invalid="ignore"):
                        e = np.log(d.frf[used, i, j] / g[:, i, j])
                    e = np.where(ok, w * e, 0.0)
                    parts += [e.real, e.imag]
            if self.eigen:
                model = build_model(params)
                for m in self.eigen:
                    f = eigenfrequencies(model, m.load_n, max(3, m.mode), m.plane)[m.mode - 1]
                    parts.append(np.array([(math.log(max(f, 1e-9)) - math.log(m.frequency_hz)) / m.sigma]))
            r = np.concatenate(parts)
        except (ConfigError, np.linalg.LinAlgError):
            return np.full(self.size, _FAILED_RESIDUAL)
        if not np.all(np.isfinite(r)):
            return np.where(np.isfinite(r), r, _FAILED_RESIDUAL)
        return r

    @property
    def size(self) -> int:
        """Length of the residual vector (points left out enter as zeros)."""
        n = sum(2 * len(used) * len(entries) for used, entries in self.selection if len(used))
        return n + len(self.eigen)

    @property
    def points(self) -> int:
        """The residuals that carry data: the degrees of freedom before the parameters."""
        n = sum(2 * int(ok.sum()) for _, entries in self.selection for _, _, ok, _ in entries)
        return n + len(self.eigen)


def refined_nodes(nodes: int) -> int | None:
    """FE nodes of the mesh with twice the beam elements (N - 3 of them between the supports);
    None when that is more than a model may have (models/params.py)."""
    twice = 2 * (nodes - 3) + 3
    return twice if twice <= MAX_NODES else None


def refined(problem: Problem) -> Problem | None:
    """The same problem on the mesh with twice the beam elements (None: no finer mesh allowed)."""
    nodes = refined_nodes(problem.start.fe.nodes)
    if nodes is None:
        return None
    d = problem.start.to_dict()
    d["fe"]["nodes"] = nodes
    fine = Problem.__new__(Problem)
    fine.__dict__.update(problem.__dict__)
    fine.start = parameters_from_dict(d, "fit, refined mesh")
    return fine


def fit(start: ModelParameters, data: Sequence[FrfData], settings: FitSettings = FitSettings(),
        eigen: Sequence[Eigenfrequency] = (),
        progress: Callable[[int, float], None] | None = None) -> FitResult:
    """Fit ``settings.parameters`` of ``start`` to the measurements (see the module docstring)."""
    keys = resolve_keys(settings.parameters, start)
    problem = Problem(start, keys, data, eigen, settings)
    x0 = np.zeros(len(problem.names))
    calls = {"n": 0}

    def solve(on: Problem, x_start: np.ndarray, budget: int):
        def fun(x: np.ndarray) -> np.ndarray:
            r = on.residuals(x)
            calls["n"] += 1
            if progress is not None:
                progress(calls["n"], 0.5 * float(r @ r))
            return r

        result = least_squares(fun, x_start, bounds=problem.bounds, method="trf", x_scale=1.0,
                               diff_step=1e-4, max_nfev=budget)
        if result.status <= 0:
            raise FitError(f"the fit did not converge within {settings.max_evaluations} evaluations "
                           f"({result.message}); nothing written. Fit fewer parameters, narrow --band, or "
                           f"start from a model closer to the rig")
        return result

    def on_bound(result) -> None:
        at_bound = [n for n, active in zip(problem.names, result.active_mask, strict=True) if active]
        if at_bound:
            raise FitError(f"{', '.join(at_bound)} ended on the bound of the fit (a factor {BOUND_FACTOR:g} "
                           f"from the start, gauges +-{GAUGE_BOUND_M * 1e3:g} mm): the data do not place it "
                           f"within the bounds; nothing written. Start from a closer model or leave it out "
                           f"of --params")

    r0 = problem.residuals(x0)
    x1 = resonance_start(problem, x0, settings) if settings.resonance_start else x0
    result = solve(problem, x1, settings.max_evaluations)
    on_bound(result)                    # before the finer mesh: its solve would not change that
    coarse, coarse_result = result.x, result
    fine = refined(problem) if settings.mesh_correction else None
    notes: list[str] = []
    if fine is not None:
        # the strains at the gauges come from the curvature of cubic elements, linear within an
        # element: the mesh moves them by up to 0.1 % (Table 1's 35 nodes against 401), and with
        # correlated parameters (kr, kl, kp) that moves the fit by percent. Polished on the mesh
        # with twice the elements, from the coarse solution. The error does not shrink steadily
        # with the mesh (it depends on where in its element a gauge lies: 36 nodes are closer to
        # 401 than 71 are), so the change itself is taken as the finer mesh's own uncertainty.
        try:
            result = solve(fine, np.clip(coarse, *problem.bounds), settings.max_evaluations)
            on_bound(result)
        except FitError as exc:         # the model's own mesh converged: keep it, and say so
            notes.append(f"the fit on the finer mesh ({fine.start.fe.nodes} nodes) was not taken ({exc}); "
                         "the values are the model mesh's, without the mesh's account")
            fine, result = None, coarse_result
    shift = result.x - coarse
    jac = result.jac
    m, p = problem.points, jac.shape[1]
    jtj = jac.T @ jac
    column = np.sqrt(np.diag(jtj))
    weak = [n for n, c in zip(problem.names, column, strict=True) if not c > 1e-9 * max(column.max(), 1e-300)]
    if weak:
        raise FitError(f"the data do not depend on {', '.join(weak)}: it cannot be fitted from these "
                       f"measurements; leave it out of --params")
    s2 = 2.0 * result.cost / max(m - p, 1)
    misfit = _misfit(problem, result.fun, m - p)
    scaled = jtj / np.outer(column, column)
    cov_x = s2 * np.linalg.pinv(scaled) / np.outer(column, column)
    sd_data = np.sqrt(np.clip(np.diag(cov_x), 0.0, None))
    corr = cov_x / np.outer(sd_data, sd_data)          # how the data tie the parameters together
    sd_x = np.sqrt(sd_data ** 2 + (MESH_UNCERTAINTY * shift) ** 2)
    combinations = _combinations(problem, cov_x, corr, MESH_UNCERTAINTY * shift)
    # the supports' stiffnesses tied together: the data determine their combination, not each
    # (along the tie, what of the residual is not noise moves them beyond their intervals:
    # `beamctl model coverage --scatter-supports`, 20 rigs, kr 5 % off at 2.2 standard errors,
    # kp 0.75 % at 3.8, the misfit 1.18, the same on the rig's own mesh)
    tied = {i for c in combinations for i, n in enumerate(problem.names)
            if n in c["names"] and problem.slots[i][0] in SUPPORT_KEYS
            and sum(problem.slots[problem.names.index(m)][0] in SUPPORT_KEYS for m in c["names"]) >= 2}
    for i in tied:
        sd_x[i] = max(sd_x[i], TIED_RELATIVE_ERROR)
    values = problem.values(result.x)
    std: dict[str, Any] = {}
    for n_i, (k, i) in enumerate(problem.slots):
        v = values[k] if i is None else values[k][i]
        sd = sd_x[n_i] if k == GAUGES_KEY else abs(v) * sd_x[n_i]
        if i is None:
            std[k] = float(sd)
        else:
            std.setdefault(k, []).append(float(sd))
    correlations = {f"{problem.names[a]}|{problem.names[b]}": float(corr[a, b])
                    for a in range(p) for b in range(a + 1, p) if abs(corr[a, b]) > CORRELATION_REPORTED}
    clean = {k: (float(v) if not isinstance(v, list) else [float(e) for e in v]) for k, v in values.items()}
    undetermined = [n for n_i, (n, (k, _)) in enumerate(zip(problem.names, problem.slots, strict=True))
                    if k != GAUGES_KEY and (sd_x[n_i] > UNDETERMINED_RELATIVE_ERROR or n_i in tied)]
    warnings = notes + _warnings(problem, clean, std, corr, misfit, combinations)
    mesh = {name: float(math.expm1(d) if problem.slots[i][0] != GAUGES_KEY else d)
            for i, (name, d) in enumerate(zip(problem.names, shift, strict=True))}
    return FitResult(keys=keys, start=problem.start_values, values=clean, std_errors=std,
                     correlations=correlations, cost=float(result.cost), start_cost=0.5 * float(r0 @ r0),
                     mesh_correction=mesh if fine is not None else {}, misfit=misfit,
                     warnings=warnings,
                     residuals=m, evaluations=calls["n"], message=str(result.message),
                     parameters=problem.model(values),
                     force_constant_n_per_v=clean.get(FORCE_CONSTANT_KEY),
                     correlation_matrix=corr.tolist(), names=problem.names,
                     undetermined=undetermined, combinations=combinations)


def resonance_start(problem: Problem, x0: np.ndarray, settings: FitSettings) -> np.ndarray:
    """Where the frequency responses' fit starts. First the stiffness unknowns (E, kr, kl, kp,
    where free) are moved so that the model's eigenfrequencies meet the resonances the
    measurements show (``resonances``: the most prominent peaks of each plane, within the band),
    the other unknowns at their start; then, where the damping is free, its ratios are scaled
    together by the factor of DAMPING_SCAN that leaves the least residual (a common factor keeps
    the Rayleigh coefficients' signs: every ratio of the scan is one the model takes). A start
    whose resonances miss the measured ones by more than their half-power width, or whose damping
    is far from the rig's, is in the basin of a wrong minimum: the residual falls by broadening
    the model's peaks (raising one ratio, lowering the other, up to where the model refuses them)
    faster than by moving them; on a rig with supports 15 to 18 % stiffer and damping 0.57 x
    Table 1's, the fit from Table 1 ended there with the damping 3 x the rig's and a misfit of
    140. The stiffness unknowns stay where none is free or too few peaks are found; the damping's
    scan runs wherever the damping is free."""
    stiff = [n for n, (k, _) in enumerate(problem.slots) if k in STIFFNESS_KEYS]
    lo, hi = settings.band_hz
    peaks = []
    for d in problem.data:
        for plane, found in resonances(d, RESONANCE_PEAKS, settings.min_coherence).items():
            peaks += [(d.load_n, plane, f) for f in found if lo <= f <= hi]
    x = x0.copy()
    if stiff and len(peaks) >= len(stiff):
        x = _match_resonances(problem, x0, stiff, peaks, settings)
    damping = [n for n, (k, _) in enumerate(problem.slots) if k == "damping.ratios"]
    if damping:
        low, high = problem.bounds[0][damping], problem.bounds[1][damping]
        best, cost = x, math.inf
        for factor in DAMPING_SCAN:
            trial = x.copy()
            trial[damping] = x[damping] + math.log(factor)
            if np.any(trial[damping] < low) or np.any(trial[damping] > high):
                continue
            r = problem.residuals(trial)
            if 0.5 * float(r @ r) < cost:
                best, cost = trial, 0.5 * float(r @ r)
        x = best
    return x


def _match_resonances(problem: Problem, x0: np.ndarray, stiff: list[int], peaks: list, settings: FitSettings):
    """x0 with the ``stiff`` unknowns fitted to the measured resonances ``peaks`` ((load, plane,
    Hz) each matched to the nearest of the plane's lowest RESONANCE_MODES eigenfrequencies)."""
    cases = sorted({(load, plane) for load, plane, _ in peaks})
    measured = np.log([f for _, _, f in peaks])

    def fun(z: np.ndarray) -> np.ndarray:
        x = x0.copy()
        x[stiff] = z
        try:
            model = build_model(problem.model(problem.values(x)))
            modes = {c: eigenfrequencies(model, c[0], RESONANCE_MODES, c[1]) for c in cases}
        except (ConfigError, np.linalg.LinAlgError):
            return np.full(len(peaks), _FAILED_RESIDUAL)
        out = np.empty(len(peaks))
        for i, (load, plane, _) in enumerate(peaks):
            f = np.log(np.maximum(modes[(load, plane)], 1e-9))
            out[i] = np.min(np.abs(f - measured[i])) / RESONANCE_SIGMA
        return out

    low, high = problem.bounds[0][stiff], problem.bounds[1][stiff]
    result = least_squares(fun, x0[stiff], bounds=(low, high), method="trf", diff_step=1e-4,
                           max_nfev=settings.max_evaluations)
    x = x0.copy()
    x[stiff] = np.clip(result.x, low, high)
    # a move of nothing is none: least_squares starts its trust region at |x|, and a start a hair
    # from zero would end it at once
    x[np.abs(x - x0) < 1e-6] = x0[np.abs(x - x0) < 1e-6]
    return x


def _averages(d: FrfData) -> int | None:
    """The averages a measurement was estimated from (its ``settings.identify.averages``)."""
    identify = d.settings.get("identify") if isinstance(d.settings, dict) else None
    a = identify.get("averages") if isinstance(identify, dict) else None
    if isinstance(a, bool) or not isinstance(a, (int, float)) or not a >= 1 or a != int(a):
        return None
    return int(a)


def _misfit(problem: Problem, residuals: np.ndarray, dof: int) -> float | None:
    """The frequency responses' residual over what their coherence and averages predict: per
    file, a weighted point's real and imaginary parts each have the variance 1 / (2 n) (n its
    averages), so sum(2 n_k |r_k|^2) / dof is 1 for a model right down to the noise. None when a
    file does not say its averages."""
    averages = [_averages(d) for d in problem.data]
    if not problem.data or any(a is None for a in averages):
        return None
    total, start = 0.0, 0
    for (used, entries), n in zip(problem.selection, averages, strict=True):
        size = 2 * len(used) * len(entries) if len(used) else 0
        part = residuals[start:start + size]
        total += 2.0 * n * float(part @ part)
        start += size
    points = problem.points - len(problem.eigen)
    return total / max(dof - len(problem.eigen), 1) if points else None


def _short(name: str) -> str:
    """A scalar unknown's name with the alias of its key (``kr``, ``damping[0]``)."""
    aliases = {v: k for k, v in ALIASES.items()}
    key, _, rest = name.partition("[")
    return aliases.get(key, key) + (f"[{rest}" if rest else "")


def _combinations(problem: Problem, cov_x: np.ndarray, corr: np.ndarray,
                  mesh: np.ndarray) -> list[dict[str, Any]]:
    """Groups of log-parameters the data tie together (chained |correlation| beyond
    COMBINED_CORRELATION; gauge offsets left out) and, per group, the product of powers of them
    the data determine best: the eigenvector of the group's covariance with the least variance
    (exponents scaled so that the largest is 1; its standard error relative, the mesh's
    uncertainty ``mesh`` of the log-parameters projected on it added)."""
    p = len(problem.names)
    logs = [i for i in range(p) if problem.slots[i][0] != GAUGES_KEY]
    group_of = {i: i for i in logs}

    def root(i):
        while group_of[i] != i:
            i = group_of[i]
        return i

    for a in logs:
        for b in logs:
            if a < b and abs(corr[a, b]) > COMBINED_CORRELATION:
                group_of[root(b)] = root(a)
    groups: dict[int, list[int]] = {}
    for i in logs:
        groups.setdefault(root(i), []).append(i)
    out = []
    for members in groups.values():
        if len(members) < 2:
            continue
        sub = cov_x[np.ix_(members, members)]
        lam, vec = np.linalg.eigh(sub)
        v = vec[:, 0] / np.abs(vec[:, 0]).max()
        sd = math.hypot(math.sqrt(max(lam[0], 0.0)) / np.abs(vec[:, 0]).max(), float(v @ mesh[members]))
        names = [problem.names[i] for i in members]
        text = " x ".join(f"{_short(n)}^{e:.2f}" for n, e in zip(names, v, strict=True) if abs(e) >= 0.005)
        out.append({"names": names, "exponents": [float(e) for e in v], "relative_std_error": float(sd),
                    "text": f"{text} is determined to +-{100 * sd:.2g} % (a standard error)"})
    return out


def _warnings(problem: Problem, values: dict[str, Any], std: dict[str, Any], corr: np.ndarray,
              misfit: float | None, combinations: Sequence[dict[str, Any]] = ()) -> list[str]:
    """What a person should know before trusting the fit: a residual beyond the noise the data
    predict, parameters the data leave loose (with what they are tied to), and what a group of
    tied parameters determines together."""
    out = []
    if misfit is not None and misfit > MISFIT_WARNING:
        out.append(f"the residual is {misfit:.1f} x what the measured coherence predicts: the model misses "
                   f"something the data show (a parameter held at its start value, such as kl, kp or the "
                   f"gauge positions, may differ on the rig); the intervals assume the model is right")
    for n_i, (key, i) in enumerate(problem.slots):
        if key == GAUGES_KEY:
            continue
        v = values[key] if i is None else values[key][i]
        sd = std[key] if i is None else std[key][i]
        if abs(sd) > WEAK_RELATIVE_ERROR * abs(v):
            partners = [problem.names[j] for j in np.argsort(-np.abs(corr[n_i]))
                        if j != n_i and abs(corr[n_i, j]) > CORRELATION_REPORTED]
            tied = f" (tied to {', '.join(partners[:2])})" if partners else ""
            state = ("undetermined" if abs(sd) > UNDETERMINED_RELATIVE_ERROR * abs(v)
                     else "not determined closely")
            out.append(f"{problem.names[n_i]} is {state}: +-{100 * sd / abs(v):.1f} % a "
                       f"standard error{tied}; fix what it is tied to from another measurement, or read "
                       f"the interval before designing on it")
    loose = {problem.names[n_i] for n_i, (key, i) in enumerate(problem.slots) if key != GAUGES_KEY
             and abs(std[key] if i is None else std[key][i])
             > WEAK_RELATIVE_ERROR * abs(values[key] if i is None else values[key][i])}
    for c in combinations:
        if loose & set(c["names"]):
            out.append(f"the data tie {', '.join(_short(n) for n in c['names'])} together: {c['text']}")
    return out
