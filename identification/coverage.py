"""How well identification and the model fit recover a rig that the model only approximates,
over many seeded simulated rigs: the check of the fit's errors and of its confidence intervals.

Each rig is drawn from its seed (``draw_rig``): its beam scattered about Table 1 (E x[0.95, 1.05],
kr x[0.8, 1.2], the damping ratios together x[0.5, 2]), stacks of 2.7 to 3.3 N/V where the
controller believes 3.0, a finer FE mesh than the model's (``nodes``), strain and load-cell noise,
an eccentric load and an initial bow in directions of its own. The rig is identified on the
simulated backend at each of ``loads_n`` (identification/identify.py, the same run as ``beamctl
identify``), the measurements are fitted together from Table 1 (models/fit.py, ``parameters``),
and each fitted value is compared with the rig's own: its relative error and its z-score (error /
the fit's standard error). A 95 % interval (1.96 standard errors) covers the truth where
|z| <= 1.96; ``summarise`` counts how often, per parameter.

``SUPPORT_SCATTER`` adds the supports' lateral and stack stiffness (kl, kp x[0.8, 1.2]). The
strains see the support mostly as one effective rotational stiffness, kr + kp le^2 kl / (kl + kp)
(le the 7.5 mm extension): the fit (kl and kp free by default) names the product of their powers
the data determine and says which of them it leaves undetermined; held at Table 1 on such a rig,
kr takes up their difference (tens of percent). ``summarise`` counts, per parameter, the values
within ``TOLERANCE`` of the rig's and those the fit said were undetermined.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from typing import Any

import numpy as np

from beamctl.assembly.run import load_gain_table, service_config
from beamctl.common.workers import WorkerDied
from beamctl.identification.identify import IdentifySettings, identify
from beamctl.models.fit import ALIASES, DEFAULT_PARAMETERS, FitError, FitSettings, fit, resolve_keys
from beamctl.models.params import ModelParameters, load_parameters, parameters_from_dict

Z_95 = 1.959964                 # the two-sided 95 % point of the normal distribution
BEAM_SCATTER = {"beam.youngs_modulus": (0.95, 1.05), "supports.rotational_stiffness": (0.8, 1.2),
                "damping.ratios": (0.5, 2.0)}
# what a fit must reach on such a rig (relative error): E, the supports (or say they are
# undetermined), the damping
TOLERANCE = {"beam.youngs_modulus": 0.01, "supports.rotational_stiffness": 0.05,
             "supports.lateral_stiffness": 0.05, "supports.actuator_stiffness": 0.05, "damping.ratios": 0.10}
SUPPORT_SCATTER = {"supports.lateral_stiffness": (0.8, 1.2), "supports.actuator_stiffness": (0.8, 1.2)}


@dataclass(frozen=True)
class CoverageSettings:
    """The rigs of a coverage check and how each is identified and fitted."""

    rigs: int = 20
    seed: int = 1                   # rig i has the seed ``seed + i``
    loads_n: tuple[float, ...] = (1000.0, 2000.0)      # as `beamctl commission` measures
    averages: int = 8
    amplitude_v: float = IdentifySettings.amplitude_v
    parameters: tuple[str, ...] = DEFAULT_PARAMETERS
    nodes: int = 71                 # the rig's FE nodes (Table 1's model: 35)
    model_nodes: int = 0            # the fitted model's FE nodes (0: Table 1's)
    strain_noise: float = 3e-7
    load_noise_n: float = 2.0
    eccentricity_m: float = 2e-4
    bow_m: float = 1e-4
    # factor ranges about Table 1 (uniform); the damping ratios move together
    scatter: dict[str, tuple[float, float]] = field(default_factory=lambda: dict(BEAM_SCATTER))
    force_constant_n_per_v: tuple[float, float] = (2.7, 3.3)

    def __post_init__(self) -> None:
        if self.rigs < 1 or self.averages < 3 or self.nodes < 3 or not self.loads_n:
            raise ValueError(f"coverage settings: at least 1 rig, 3 averages, 3 nodes and one load "
                             f"(rigs {self.rigs}, averages {self.averages}, nodes {self.nodes}, "
                             f"loads {self.loads_n})")


def draw_rig(settings: CoverageSettings, index: int) -> tuple[dict[str, Any], dict[str, Any]]:
    """(the rig's true values by fit key, the service configuration of its simulated rig)."""
    rng = np.random.default_rng(settings.seed + index)
    table1 = load_parameters().to_dict()
    # a key not scattered is the rig's as in Table 1 (the truth of a fit that frees it anyway)
    truth: dict[str, Any] = {key: table1[key.split(".")[0]][key.split(".")[1]]
                             for key in {**BEAM_SCATTER, **SUPPORT_SCATTER}}
    model: dict[str, Any] = {"fe": {"nodes": settings.nodes}}
    for key, (low, high) in settings.scatter.items():
        factor = float(rng.uniform(low, high))
        section, name = key.split(".")
        value = table1[section][name]
        value = [v * factor for v in value] if isinstance(value, list) else value * factor
        truth[key] = value
        model.setdefault(section, {})[name] = value
    k = float(rng.uniform(*settings.force_constant_n_per_v))
    truth["actuators.force_constant_n_per_v"] = k
    rig = {"hal": {"sim": {"pace": "simulated", "own_actuators": True,
                           "actuators": {"force_constant_n_per_v": k}}},
           "plant": {"noise": {"strain": settings.strain_noise, "load": settings.load_noise_n,
                               "seed": settings.seed + index},
                     "eccentricity": {"amplitude": settings.eccentricity_m,
                                      "angle_deg": float(rng.uniform(0.0, 360.0))},
                     "bow": {"amplitude": settings.bow_m, "angle_deg": float(rng.uniform(0.0, 360.0))},
                     "model": model}}
    return truth, rig


def start_model(settings: CoverageSettings) -> ModelParameters:
    """Table 1, on ``model_nodes`` FE nodes where given: the model the fit starts from."""
    start = load_parameters()
    if not settings.model_nodes:
        return start
    d = start.to_dict()
    d["fe"]["nodes"] = settings.model_nodes
    return parameters_from_dict(d, source="coverage start model")


def run_rig(settings: CoverageSettings, index: int) -> dict[str, Any]:
    """One rig identified and fitted: per fitted key its value, standard error, relative error
    and z-score against the rig's own value (lists element by element); ``error`` when the fit
    refused (then no values)."""
    truth, rig = draw_rig(settings, index)
    cfg = service_config(rig, f"coverage rig {index} (seed {settings.seed + index})")
    table = load_gain_table(cfg)
    data = [identify(cfg, table, IdentifySettings(load_n=load, averages=settings.averages,
                                             amplitude_v=settings.amplitude_v))[0]
            for load in settings.loads_n]
    row: dict[str, Any] = {"rig": index, "seed": settings.seed + index}
    try:
        result = fit(start_model(settings), data, FitSettings(parameters=settings.parameters))
    except FitError as exc:
        row["error"] = str(exc)
        return row
    for key, value in result.values.items():
        if key not in truth:
            continue
        values = value if isinstance(value, list) else [value]
        true = truth[key] if isinstance(truth[key], list) else [truth[key]]
        std = result.std_errors[key] if isinstance(value, list) else [result.std_errors[key]]
        for i, (v, t, s) in enumerate(zip(values, true, std, strict=True)):
            name = f"{key}[{i}]" if isinstance(value, list) else key
            row[name] = {"value": v, "true": t, "std_error": s, "relative_error": v / t - 1.0,
                         "z": (v - t) / s if s > 0 else None, "undetermined": name in result.undetermined}
    row["correlations"] = result.correlations
    row["undetermined"] = result.undetermined
    row["combinations"] = [c["text"] for c in result.combinations]
    row["misfit"] = result.misfit
    row["warnings"] = result.warnings
    return row


def _run_one(args: tuple[CoverageSettings, int]) -> dict[str, Any]:
    # a worker process of this check: one BLAS thread, Ctrl-C is the caller's to handle
    import signal

    from threadpoolctl import threadpool_limits

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with threadpool_limits(1):
        return _row(*args)


def _row(settings: CoverageSettings, index: int) -> dict[str, Any]:
    try:
        return run_rig(settings, index)
    except Exception as exc:        # this rig's, in its row: the others still run
        return {"rig": index, "seed": settings.seed + index, "error": f"{type(exc).__name__}: {exc}"}


def run(settings: CoverageSettings, workers: int = 1,
        progress: Callable[[int, int], None] | None = None) -> Iterator[dict[str, Any]]:
    """The rows of every rig as they finish (in the rigs' order), in ``workers`` processes. The
    fitted parameters are checked first (ConfigError naming the unknown one)."""
    resolve_keys(settings.parameters, start_model(settings))
    jobs = [(settings, i) for i in range(settings.rigs)]
    if workers <= 1:
        for done, job in enumerate(jobs, 1):
            row = _row(*job)
            if progress:
                progress(done, len(jobs))
            yield row
        return
    pool = ProcessPoolExecutor(workers, mp_context=get_context("spawn"))
    done = 0
    try:
        for done, row in enumerate(pool.map(_run_one, jobs), 1):
            if progress:
                progress(done, len(jobs))
            yield row
    except BrokenProcessPool:
        pool.shutdown(wait=False, cancel_futures=True)
        flight = ", ".join(f"{i} (seed {settings.seed + i})"
                           for i in range(done, min(done + workers, len(jobs))))
        raise WorkerDied(f"a worker process of the coverage study died (killed, out of memory, or a crash) "
                         f"while it fitted one of the rigs in flight: {flight}; the rows before are "
                         "complete") from None
    except BaseException:           # Ctrl-C, a closed generator: the rigs not begun are not run
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown()


def summarise(rows: Sequence[dict[str, Any]], settings: CoverageSettings) -> dict[str, Any]:
    """Per fitted quantity (a list key's elements together): rigs, the largest relative error
    and how many of the 95 % intervals cover the truth; the settings and the refused fits."""
    keys = resolve_keys(settings.parameters, load_parameters())
    per: dict[str, dict[str, Any]] = {}
    for key in keys:
        cells = [c for r in rows for name, c in r.items()
                 if isinstance(c, dict) and (name == key or name.startswith(key + "["))]
        if not cells:
            continue
        covered = sum(c["z"] is not None and abs(c["z"]) <= Z_95 for c in cells)
        loose = [name for r in rows for name in r.get("undetermined", [])
                 if name == key or name.startswith(key + "[")]
        tolerance = TOLERANCE.get(key)
        within = (None if tolerance is None else
                  sum(abs(c["relative_error"]) <= tolerance for c in cells))
        per[key] = {"values": len(cells), "max_relative_error": max(abs(c["relative_error"]) for c in cells),
                    "covered_95": covered, "coverage_95": covered / len(cells),
                    "max_abs_z": max((abs(c["z"]) for c in cells if c["z"] is not None), default=None),
                    "tolerance": tolerance, "within_tolerance": within, "undetermined": len(loose),
                    "within_or_undetermined": None if tolerance is None else sum(
                        abs(c["relative_error"]) <= tolerance or c.get("undetermined", False) for c in cells)}
    aliases = {v: k for k, v in ALIASES.items()}
    return {"settings": {**asdict(settings), "loads_n": list(settings.loads_n),
                         "parameters": list(settings.parameters)},
            "rigs": len(rows),
            "refused": [{"rig": r["rig"], "error": r["error"]} for r in rows if "error" in r],
            "warned": sum(bool(r.get("warnings")) for r in rows),
            "max_misfit": max((r["misfit"] for r in rows if r.get("misfit") is not None), default=None),
            "parameters": {aliases.get(k, k): v for k, v in per.items()}}
