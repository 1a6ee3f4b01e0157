"""Uncertainty studies: many rigs drawn from the scatter of their parameters, each run against
one or more gain tables, on a Dask cluster.

A study file holds one ``study:`` section::

    study:
      kind: linear                 # or experiment
      samples: 1000
      seed: 1
      sampling: random             # or latin-hypercube (uniform laws only)
      designs: [gains/default.yaml]          # gain tables (default: the shipped one)
      parameters:                  # dotted keys -> laws
        model.beam.youngs_modulus: {law: uniform, low: 72.0e9, high: 79.6e9}
        model.supports.rotational_stiffness: {law: normal, mean: 192.4, std: 10.0}
        io.delay_samples: {law: truncated-normal, mean: 0.5, std: 0.2, low: 0.0, high: 1.0}
        actuators.force_constant_n_per_v: {law: uniform, low: 2.4, high: 3.6}
      linear: {max_step_n: 50, fine_step_n: 10, fine_band: 0.04, resolution_n: 1.0}

Keys: ``model.<key>`` any numeric model parameter (a list element as ``model.damping.ratios[0]``;
a whole list, ``model.damping.ratios``, takes a factor on every element), the rig's own;
``io.delay_samples`` the rig's output delay in samples; ``actuators.force_constant_n_per_v`` the rig's
stacks (the controller keeps believing ``controller_force_constant_n_per_v``, default
3.0); ``sample_rate_hz`` the rig's true rate; for ``kind: experiment`` also ``plant.<key>`` (bow,
eccentricity, noise, load ramp of the simulated rig).

Kinds: ``linear`` finds the instability onset, the lowest load at which the discrete closed loop
of the sample's rig with the design is unstable (gains/robust.py's ``evaluate``, the full walk from
the table's first load, the first unstable step bisected to ``resolution_n``); ``experiment`` runs
the interpolated controller on the sample's simulated rig along the shipped scenario's load ramp
(simulation/experiment.py) and takes the load at which the beam was let go (its deflection passed the
limit, after a fault or not).

A sample whose rig never failed (linear: stable to the end of the table; experiment: the ramp
ended with the beam held) is **censored**: its ``onset_n`` (the table's or the ramp's end) and
``ratio`` are lower bounds, not failures. The summary and the figures treat them as right-censored
data (Kaplan-Meier): they are never counted or drawn as failures, and a quantile beyond the last
failure is undetermined, not the censoring value.

Every sample's values are drawn on the client from the seed before anything runs, so the rows do
not depend on how many workers there are or in which order they answer. Each sample is a plain
function of plain data (a ``Task``) returning a plain dict (a row).
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from beamctl.config.schema import ConfigError, dotted_get, merge, nested, read_yaml
from beamctl.gains.defaults import default_table_path
from beamctl.gains.robust import Box, Refused, evaluate
from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import load_table
from beamctl.models.params import default_dict
from beamctl.models.rig import SPECIAL_KEYS, Rig, rig_with
from beamctl.simulation.experiment import experiment_config, run_mode

KINDS = ("linear", "experiment")
LAWS = ("uniform", "normal", "truncated-normal")
SAMPLINGS = ("random", "latin-hypercube")
LINEAR_DEFAULTS = {"max_step_n": 50.0, "fine_step_n": 10.0, "fine_band": 0.04, "resolution_n": 1.0}
MAX_SAMPLES = 1_000_000


@dataclass(frozen=True)
class Law:
    law: str
    low: float = -math.inf
    high: float = math.inf
    mean: float = 0.0
    std: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        if self.law == "uniform":
            return {"law": self.law, "low": self.low, "high": self.high}
        out = {"law": self.law, "mean": self.mean, "std": self.std}
        if self.law == "truncated-normal":
            out.update(low=self.low, high=self.high)
        return out


@dataclass(frozen=True)
class Study:
    kind: str
    samples: int
    seed: int
    sampling: str
    designs: tuple[str, ...]
    parameters: dict[str, Law]
    linear: dict[str, float] = field(default_factory=lambda: dict(LINEAR_DEFAULTS))
    experiment: dict[str, Any] = field(default_factory=dict)
    controller_force_constant_n_per_v: float = 3.0
    source: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "samples": self.samples, "seed": self.seed, "sampling": self.sampling,
                "designs": list(self.designs),
                "parameters": {k: v.to_dict() for k, v in self.parameters.items()},
                "linear": self.linear, "experiment": self.experiment,
                "controller_force_constant_n_per_v": self.controller_force_constant_n_per_v}

    def digest(self) -> str:
        """Identifies the study's rows: a folder holds the rows of one study."""
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()


def _number(value: Any, key: str, source: str, expected: str = "a finite number") -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(key, value, expected, source)
    return float(value)


def _law(data: Any, key: str, source: str) -> Law:
    if not isinstance(data, dict) or data.get("law") not in LAWS:
        raise ConfigError(f"{key}.law", data.get("law") if isinstance(data, dict) else data,
                          f"one of {', '.join(LAWS)} (a mapping such as {{law: uniform, low: 1, high: 2}})",
                          source)
    law = data["law"]
    needed = {"uniform": ("low", "high"), "normal": ("mean", "std"),
              "truncated-normal": ("mean", "std", "low", "high")}[law]
    unknown = sorted(set(data) - {"law", *needed})
    if unknown:
        raise ConfigError(f"{key}.{unknown[0]}", data[unknown[0]], f"only {', '.join(needed)} with law {law}",
                          source)
    values = {}
    for name in needed:
        if name not in data:
            raise ConfigError(f"{key}.{name}", None, f"a value (law {law} needs {', '.join(needed)})", source)
        values[name] = _number(data[name], f"{key}.{name}", source)
    if "std" in values and not values["std"] > 0:
        raise ConfigError(f"{key}.std", values["std"], "a standard deviation > 0", source)
    if "low" in values and not values["low"] < values["high"]:
        raise ConfigError(f"{key}.high", values["high"], f"a value above low = {values['low']:g}", source)
    return Law(law=law, **values)


def _check_key(key: str, kind: str, source: str) -> None:

    if key in SPECIAL_KEYS:
        return
    head, _, rest = key.partition(".")
    if head == "plant" and kind == "experiment" and rest:
        return
    if head == "model" and rest:
        base, _, index = rest.partition("[")
        node: Any = default_dict()
        for part in base.split("."):
            node = node.get(part) if isinstance(node, dict) else None
        element = index[:-1]
        if isinstance(node, list) and index.endswith("]") and element.isdigit() and int(element) < len(node):
            return
        if isinstance(node, list) and not index:     # the whole list: a factor on every element
            return
        if isinstance(node, (int, float)) and not isinstance(node, bool) and not index:
            return
    extra = ", plant.<key>" if kind == "experiment" else ""
    raise ConfigError(f"study.parameters.{key}", "",
                      f"a numeric model key as model.<key> (a list element as model.damping.ratios[0]), "
                      f"{', '.join(SPECIAL_KEYS)}{extra}", source)


def study_from_dict(data: Any, source: str = "") -> Study:
    if not isinstance(data, dict) or not isinstance(data.get("study"), dict):
        raise ConfigError("study", data, "a study: section (a mapping)", source)
    s = data["study"]
    known = {"kind", "samples", "seed", "sampling", "designs", "parameters", "linear", "experiment",
             "controller_force_constant_n_per_v"}
    unknown = sorted(set(s) - known) + sorted(set(data) - {"study"})
    if unknown:
        raise ConfigError(f"study.{unknown[0]}" if unknown[0] in s else unknown[0], "",
                          f"one of the keys study.{{{', '.join(sorted(known))}}}", source)
    kind = s.get("kind", "linear")
    if kind not in KINDS:
        raise ConfigError("study.kind", kind, f"one of {', '.join(KINDS)}", source)
    samples = s.get("samples", 100)
    if isinstance(samples, bool) or not isinstance(samples, int) or not 1 <= samples <= MAX_SAMPLES:
        raise ConfigError("study.samples", samples, f"a whole number from 1 to {MAX_SAMPLES}", source)
    seed = s.get("seed", 1)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError("study.seed", seed, "a whole number >= 0", source)
    sampling = s.get("sampling", "random")
    if sampling not in SAMPLINGS:
        raise ConfigError("study.sampling", sampling, f"one of {', '.join(SAMPLINGS)}", source)
    designs = s.get("designs")
    if designs is None:

        designs = [str(default_table_path())]
    if not isinstance(designs, list) or not designs or not all(isinstance(d, str) for d in designs):
        raise ConfigError("study.designs", designs, "a list of gain table files", source)
    for d in designs:
        if not Path(d).is_file():
            raise ConfigError("study.designs", d, "an existing gain table file", source)
    parameters = s.get("parameters") or {}
    if not isinstance(parameters, dict) or not parameters:
        raise ConfigError("study.parameters", parameters, "a mapping of dotted keys to laws", source)
    laws = {}
    for key, law in parameters.items():
        _check_key(str(key), kind, source)
        laws[str(key)] = _law(law, f"study.parameters.{key}", source)
    if sampling == "latin-hypercube" and any(v.law != "uniform" for v in laws.values()):
        raise ConfigError("study.sampling", sampling, "uniform laws for every parameter (a Latin hypercube "
                          "spans a box)", source)
    linear = dict(LINEAR_DEFAULTS)
    given = s.get("linear") or {}
    if not isinstance(given, dict) or set(given) - set(LINEAR_DEFAULTS):
        raise ConfigError("study.linear", given, f"a mapping of {', '.join(LINEAR_DEFAULTS)}", source)
    for k, v in given.items():
        linear[k] = _number(v, f"study.linear.{k}", source, "a number > 0")
        if not linear[k] > 0:
            raise ConfigError(f"study.linear.{k}", v, "a number > 0", source)
    experiment = s.get("experiment") or {}
    if not isinstance(experiment, dict):
        raise ConfigError("study.experiment", experiment, "a scenario mapping (plant, controller, ...)",
                          source)
    k = _number(s.get("controller_force_constant_n_per_v", 3.0), "study.controller_force_constant_n_per_v",
                source)
    return Study(kind=kind, samples=samples, seed=seed, sampling=sampling, designs=tuple(designs),
                 parameters=laws, linear=linear, experiment=experiment,
                 controller_force_constant_n_per_v=k, source=source)


def load_study(path: str | Path) -> Study:
    return study_from_dict(read_yaml(path), str(path))


def draw(study: Study) -> np.ndarray:
    """[samples x parameters] values, in the order of ``study.parameters``, from the seed."""
    from scipy import stats
    from scipy.stats import qmc

    laws = list(study.parameters.values())
    rng = np.random.default_rng(study.seed)
    if study.sampling == "latin-hypercube":
        u = qmc.LatinHypercube(d=len(laws), seed=rng).random(study.samples)
    else:
        u = rng.random((study.samples, len(laws)))
    out = np.empty_like(u)
    for j, law in enumerate(laws):
        if law.law == "uniform":
            out[:, j] = law.low + (law.high - law.low) * u[:, j]
        elif law.law == "normal":
            out[:, j] = stats.norm.ppf(u[:, j], loc=law.mean, scale=law.std)
        else:
            a, b = (law.low - law.mean) / law.std, (law.high - law.mean) / law.std
            out[:, j] = stats.truncnorm.ppf(u[:, j], a, b, loc=law.mean, scale=law.std)
    return out


@dataclass(frozen=True)
class Task:
    """One sample against one design: everything a worker needs, plain data."""

    sample: int
    design: str
    values: dict[str, float]
    kind: str
    linear: dict[str, float]
    experiment: dict[str, Any]
    controller_force_constant_n_per_v: float


def tasks(study: Study, done: set[tuple[int, str]] = frozenset()) -> list[Task]:
    values = draw(study)
    keys = list(study.parameters)
    return [Task(sample=i, design=d, values=dict(zip(keys, map(float, values[i]), strict=True)),
                 kind=study.kind, linear=study.linear, experiment=study.experiment,
                 controller_force_constant_n_per_v=study.controller_force_constant_n_per_v)
            for i in range(study.samples) for d in study.designs if (i, d) not in done]


# -- one sample -----------------------------------------------------------------------------------
_TABLES: dict[str, Any] = {}


def _table(path: str, texts: Mapping[str, str] | None = None):
    """A worker reads each gain table once: from ``texts`` (the tables' contents, sent by the
    client: a remote worker needs no copy of the files) or else from the path."""
    import tempfile


    text = None if texts is None else texts.get(path)
    key = path if text is None else hashlib.sha256(text.encode()).hexdigest()
    if key not in _TABLES:
        if text is None:
            _TABLES[key] = load_table(path, verify=False)
        else:
            with tempfile.TemporaryDirectory() as tmp:
                copy = Path(tmp) / Path(path).name
                copy.write_text(text)
                _TABLES[key] = load_table(copy, verify=False)
    return _TABLES[key]


def design_texts(study: Study) -> dict[str, str]:
    """The designs' gain tables as text, for the workers."""
    return {d: Path(d).read_text(encoding="utf-8") for d in study.designs}


def run_task(task: Task, texts: Mapping[str, str] | None = None) -> dict[str, Any]:
    """The row of one sample: its values, the onset (or, censored, the end of the table or the
    ramp), the rig's own critical load, their ratio, whether it is censored and why it ended. An
    error of the sample itself (parameters that give no valid model) is a row too, with the
    reason. ``texts``: the designs' tables (``design_texts``)."""
    row: dict[str, Any] = {"sample": task.sample, "design": task.design, **task.values}
    table = _table(task.design, texts)          # once per worker, from the client's copy if sent
    try:
        result = _linear(task, table) if task.kind == "linear" else _experiment(task, table)
    except ConfigError as exc:
        result = {"onset_n": math.nan, "critical_load_n": math.nan, "ratio": math.nan, "censored": False,
                  "reason": f"invalid rig: {exc}"}
    row.update(result)
    return row


def drawn_rig(task: Task, table) -> Rig:
    """The rig of a sample (models/rig.py): the design's model, I/O chain, rate and stacks with
    the drawn values set as the study file states them (a model key's value replaces the
    design's, a whole list's multiplies each element; the stacks' and the rate's are absolute)."""
    model = table.model_parameters.to_dict()
    changes: dict[str, tuple[str, float]] = {}
    for key, v in task.values.items():
        if key.startswith("model."):
            changes[key[6:]] = ("factor" if isinstance(dotted_get(model, key[6:]), list) else "value", v)
        elif key == "actuators.force_constant_n_per_v":
            changes[key] = ("factor", v / task.controller_force_constant_n_per_v)
        elif key == "sample_rate_hz":
            changes[key] = ("value", v)
        elif key == "io.delay_samples":
            if not v >= 0.0:            # a rig runs a drawn delay as drawn or not at all
                raise ConfigError(key, v, "a delay of 0 samples or more (the law drew below 0)",
                                  f"sample {task.sample}")
            changes[key] = ("value", v)
    return rig_with(table.model_parameters, table.design.io, table.design.sample_rate_hz, changes,
                    source=f"sample {task.sample}")


def _linear(task: Task, table) -> dict[str, Any]:
    walk = Box(parameters={}, max_step_n=task.linear["max_step_n"], fine_step_n=task.linear["fine_step_n"],
               fine_band=task.linear["fine_band"], resolution_n=task.linear["resolution_n"])
    r = evaluate(table, GainSchedule.from_table(table), walk, task.values, mode="full",
                 rig=drawn_rig(task, table))
    if isinstance(r, Refused):                  # parameters that give no valid model: a row that says so
        return {"onset_n": math.nan, "critical_load_n": math.nan, "ratio": math.nan, "censored": False,
                "reason": f"invalid rig: {r.reason}"}
    if r.censored:                              # stable to its last load, the table's end
        end = r.stable_to_n
        return {"onset_n": end, "critical_load_n": r.critical_load_n, "ratio": r.ratio, "censored": True,
                "reason": f"stable to the end of the table ({end:.0f} N)"}
    first = "" if r.stable_to_n is not None else " (the table's first load)"
    return {"onset_n": r.onset_n, "critical_load_n": r.critical_load_n, "ratio": r.ratio, "censored": False,
            "reason": f"unstable from {r.onset_n:.0f} N{first} ({r.pole_hz:.0f} Hz)"}


def _experiment(task: Task, table) -> dict[str, Any]:

    if "sample_rate_hz" in task.values:
        raise ConfigError("sample_rate_hz", task.values["sample_rate_hz"],
                          "a linear study (the simulated rig runs at the table's rate)")
    scenario = merge(task.experiment, {"gains": {"table": task.design}, "experiment": {"paper_mode": False},
                                       "hal": {"sim": {"pace": "simulated"}}})
    rig = drawn_rig(task, table)                # the same rig a linear study takes
    for key, v in task.values.items():
        if key.startswith("plant."):            # the simulated rig's bow, noise, load programme
            scenario = merge(scenario, nested(key, v))
    if "actuators.force_constant_n_per_v" in task.values:
        own = task.controller_force_constant_n_per_v * rig.force_gain
        scenario = merge(scenario, {"hal": {"sim": {"own_actuators": True,
                                                    "actuators": {"force_constant_n_per_v": own}}}})
    if "io.delay_samples" in task.values:
        scenario = merge(scenario, {"plant": {"io": {"delay_samples": rig.chain.delay_samples}}})
    scenario = merge(scenario, {"plant": {"model": rig.params.to_dict()}})
    scenario["model"] = table.model_parameters.to_dict()
    cfg, settings = experiment_config(scenario, f"sample {task.sample}")
    trace = run_mode("interpolate", cfg, settings, table)
    critical = trace.plant_critical_load_n
    end = trace.load_n[-1] if trace.load_n else math.nan
    let_go = any(d > settings["deflection_limit"] for d in trace.deflection_m)    # the run's end (simkernel)
    return {"onset_n": float(end), "critical_load_n": float(critical), "ratio": float(end) / critical,
            "censored": not let_go, "reason": trace.fault or trace.end}


# -- the report -----------------------------------------------------------------------------------
QUANTILES = (1, 5, 50, 95)         # percent, of the onset ratio


@dataclass(frozen=True)
class Survival:
    """The Kaplan-Meier estimate of the failure probability of right-censored values (a
    censored value is a lower bound: the sample had not failed there).

    ``failure_at``: the distinct failure values, ascending; ``probability``: the estimated
    probability of failure at or below each of them (1 - the product-limit survival); the
    estimate is flat between them and ends at ``end``, the largest value observed;
    ``censored_at``: the censored values, ascending; ``failures``: the failed samples."""

    failure_at: np.ndarray
    probability: np.ndarray
    censored_at: np.ndarray
    end: float
    failures: int

    def at(self, x: Any) -> np.ndarray:
        """The estimated probability of failure at or below ``x`` (valid up to ``end``)."""
        i = np.searchsorted(self.failure_at, np.asarray(x, dtype=float), side="right")
        return np.concatenate([[0.0], self.probability])[i]

    def quantile(self, p: float) -> float | None:
        """The smallest value at which the estimated failure probability reaches ``p`` (0 < p <= 1);
        None when it never does within the data (beyond the last failure, censored samples
        left): the quantile then lies above ``end``."""
        reached = np.flatnonzero(self.probability >= p - 1e-12)
        return float(self.failure_at[reached[0]]) if reached.size else None


def kaplan_meier(values: Any, censored: Any) -> Survival:
    """The Kaplan-Meier estimate of ``values`` (finite, at least one), ``censored`` marking the
    lower bounds (scipy.stats.ecdf; a sample censored at a failure value is at risk there)."""
    from scipy.stats import CensoredData, ecdf

    values = np.asarray(values, dtype=float)
    censored = np.asarray(censored, dtype=bool)
    if not values.size or not np.isfinite(values).all():
        raise ValueError(f"Kaplan-Meier needs finite values, at least one: {values}")
    failed = values[~censored]
    failure_at = np.unique(failed)
    probability = np.zeros(0)
    if failure_at.size:
        cdf = ecdf(CensoredData(uncensored=failed, right=values[censored])).cdf
        probability = np.asarray(cdf.evaluate(failure_at), dtype=float)
    return Survival(failure_at=failure_at, probability=probability, censored_at=np.sort(values[censored]),
                    end=float(values.max()), failures=int(failed.size))


def survival(rows: list[Mapping[str, Any]], column: str = "ratio") -> Survival | None:
    """The Kaplan-Meier estimate of ``column`` (``ratio`` or ``onset_n``) over the valid ``rows``
    (of one design), their ``censored`` flags marking lower bounds; None without a valid row."""
    valid = [r for r in rows if math.isfinite(r[column])]
    if not valid:
        return None
    return kaplan_meier([r[column] for r in valid], [r["censored"] for r in valid])


def _sensitivity(rows: list[Mapping[str, Any]], keys: list[str]) -> tuple[dict[str, float], str]:
    """Spearman's rank correlation of each parameter with the onset load over the valid rows,
    strongest first, and what it was computed on. A censored sample enters at its lower bound
    (the table's or the ramp's end): its rank is right when every censored value lies above
    every onset, as when all end at the same table's end (ties among them only)."""
    from scipy.stats import spearmanr

    valid = [r for r in rows if math.isfinite(r["onset_n"])]
    onset = np.array([r["onset_n"] for r in valid], dtype=float)
    censored = np.array([r["censored"] for r in valid], dtype=bool)
    out = {}
    for k in keys:
        x = np.array([r[k] for r in valid], dtype=float)
        if len(valid) > 2 and np.ptp(x) > 0 and np.ptp(onset) > 0:
            out[k] = float(spearmanr(x, onset).statistic)
    basis = f"Spearman rank correlation with onset_n over {len(valid)} valid samples"
    if censored.any():
        exact = not (~censored).any() or onset[censored].min() > onset[~censored].max()
        basis += (f", the {int(censored.sum())} censored ones at their lower bound ("
                  + ("above every onset: ranks exact, tied among them)" if exact else
                     "some below an onset: their ranks are uncertain)"))
    return dict(sorted(out.items(), key=lambda kv: -abs(kv[1]))), basis


def summarise(rows: list[Mapping[str, Any]], keys: list[str], wall_s: float) -> dict[str, Any]:
    """``summary.json``: per design the samples, failures and censored ones, the worst ratio (of a
    failure), the ratio's Kaplan-Meier quantiles (null where the data end before them:
    ``ratio_quantiles_beyond`` then gives the ratio they lie above) and the sensitivity ranking."""
    out: dict[str, Any] = {"samples": len({r["sample"] for r in rows}), "wall_s": wall_s, "designs": {}}
    worst: list[float] = []
    bounds: list[float] = []
    for design in sorted({r["design"] for r in rows}):
        mine = sorted((r for r in rows if r["design"] == design), key=lambda r: r["sample"])
        km = survival(mine)
        valid = [r for r in mine if math.isfinite(r["ratio"])]
        failed = [r["ratio"] for r in valid if not r["censored"]]
        censored = [r["ratio"] for r in valid if r["censored"]]
        d: dict[str, Any] = {"samples": len(mine), "invalid": len(mine) - len(valid), "failures": len(failed),
                             "censored": len(censored), "worst_ratio": min(failed) if failed else None}
        if failed:
            worst.append(min(failed))
        if censored:
            d["censored_from_ratio"] = min(censored)
            bounds.append(min(censored))
            if not failed:
                d["worst_ratio_at_least"] = min(censored)
        quantiles = {f"{p:g}": km.quantile(p / 100) for p in QUANTILES} if km is not None else {}
        d["ratio_quantiles"] = quantiles
        beyond = {p: km.end for p, q in quantiles.items() if q is None}
        if beyond:
            d["ratio_quantiles_beyond"] = beyond
        d["sensitivity"], d["sensitivity_basis"] = _sensitivity(mine, keys)
        out["designs"][design] = d
    out["worst_ratio"] = min(worst) if worst else None
    if not worst and bounds:
        out["worst_ratio_at_least"] = min(bounds)
    return out
