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
      linear: {max_step_n: 50, fine_step_n: 10, fine_band: 0.04}

Keys: ``model.<key>`` any numeric model parameter (a list element as ``model.damping.ratios[0]``;
a whole list, ``model.damping.ratios``, takes a factor on every element), the rig's own;
``io.delay_samples`` the rig's output delay in samples; ``actuators.force_constant_n_per_v`` the rig's
stacks (the controller keeps believing ``controller_force_constant_n_per_v``, default
3.0); ``sample_rate_hz`` the rig's true rate; for ``kind: experiment`` also ``plant.<key>`` (bow,
eccentricity, noise, load ramp of the simulated rig).

Kinds: ``linear`` finds the largest load up to which the discrete closed loop of the sample's rig
with the design is stable (gains/robust.py's check, one scenario); ``experiment`` runs the
interpolated controller on the sample's simulated rig along the shipped scenario's load ramp
(tools/experiment.py) and takes the load at which the beam was let go (the deflection limit, a
fault, or the ramp's end).

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

from beamctl.config.schema import ConfigError, read_yaml

KINDS = ("linear", "experiment")
LAWS = ("uniform", "normal", "truncated-normal")
SAMPLINGS = ("random", "latin-hypercube")
SPECIAL_KEYS = ("io.delay_samples", "actuators.force_constant_n_per_v", "sample_rate_hz")
LINEAR_DEFAULTS = {"max_step_n": 50.0, "fine_step_n": 10.0, "fine_band": 0.04}
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
    from beamctl.models.params import default_dict

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
        from beamctl.gains.defaults import default_table_path

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

    from beamctl.gains.table import load_table

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
    """The row of one sample: its values, the held load, the rig's own critical load, their
    ratio and why it ended. An error of the sample itself (parameters that give no valid model)
    is a row too, with the reason. ``texts``: the designs' tables (``design_texts``)."""
    row: dict[str, Any] = {"sample": task.sample, "design": task.design, **task.values}
    table = _table(task.design, texts)          # once per worker, from the client's copy if sent
    try:
        result = _linear(task, table) if task.kind == "linear" else _experiment(task, table)
    except ConfigError as exc:
        result = {"held_load_n": math.nan, "critical_load_n": math.nan, "ratio": math.nan,
                  "reason": f"invalid rig: {exc}"}
    row.update(result)
    return row


def _linear(task: Task, table) -> dict[str, Any]:
    from beamctl.gains.robust import Box, Range, evaluate
    from beamctl.gains.schedule import GainSchedule

    params: dict[str, Range] = {}
    values: dict[str, float] = {}
    model = table.model_parameters.to_dict()
    for key, v in task.values.items():
        if key.startswith("model."):
            kind = "factor" if isinstance(_lookup(model, key[6:]), list) else "value"
            params[key[6:]] = Range(kind, v, v)
            values[key[6:]] = v
        elif key == "actuators.force_constant_n_per_v":
            params[key] = Range("factor", 0.0, 10.0)
            values[key] = v / task.controller_force_constant_n_per_v
        elif key == "sample_rate_hz":
            params[key] = Range("factor", 0.0, 10.0)
            values[key] = v / table.design.sample_rate_hz
        else:                                   # io.delay_samples
            params[key] = Range("value", v, v)
            values[key] = v
    box = Box(parameters=params, max_step_n=task.linear["max_step_n"], fine_step_n=task.linear["fine_step_n"],
              fine_band=task.linear["fine_band"])
    r = evaluate(table, GainSchedule.from_table(table), box, f"sample {task.sample}", values)
    held = math.nan if r.held_load_n is None else r.held_load_n
    return {"held_load_n": held, "critical_load_n": r.critical_load_n, "ratio": r.ratio,
            "reason": f"unstable at {r.limit.load_n:.0f} N ({r.limit.frequency_hz:.0f} Hz)"
            if r.limit.spectral_radius >= 1 else "stable to the end of the table"}


def _lookup(node: Any, key: str) -> Any:
    """The value at a dotted key (``[i]`` an element) of a nested mapping."""
    base, _, index = key.partition("[")
    for part in base.split("."):
        node = node[part]
    return node[int(index[:-1])] if index else node


def _set_model_value(model: dict, key: str, value: float) -> None:
    """Set a drawn value in a model dict: a scalar key or a list element replaced, a whole list
    multiplied (the key conventions of the study file)."""
    base, _, index = key.partition("[")
    parts = base.split(".")
    node = model
    for part in parts[:-1]:
        node = node[part]
    leaf = parts[-1]
    if index:
        node[leaf][int(index[:-1])] = value
    elif isinstance(node[leaf], list):
        node[leaf] = [x * value for x in node[leaf]]
    else:
        node[leaf] = value


def _experiment(task: Task, table) -> dict[str, Any]:
    from beamctl.config.schema import merge, nested
    from beamctl.tools.experiment import experiment_config, run_mode

    scenario = merge(task.experiment, {"gains": {"table": task.design}, "experiment": {"paper_mode": False},
                                       "hal": {"sim": {"pace": "simulated"}}})
    rig_model = table.model_parameters.to_dict()       # the design's model, the drawn values set
    for key, v in task.values.items():
        if key.startswith("model."):
            _set_model_value(rig_model, key[6:], v)
        elif key == "actuators.force_constant_n_per_v":
            scenario = merge(scenario, {"hal": {"sim": {"own_actuators": True,
                                                        "actuators": {"force_constant_n_per_v": v}}}})
        elif key == "io.delay_samples":
            scenario = merge(scenario, {"plant": {"io": {"delay_samples": v}}})
        elif key == "sample_rate_hz":
            raise ConfigError(key, v, "a linear study (the simulated rig runs at the table's rate)")
        else:                                   # plant.<key>
            scenario = merge(scenario, nested(key, v))
    scenario = merge(scenario, {"plant": {"model": rig_model}})
    scenario["model"] = table.model_parameters.to_dict()
    cfg, settings = experiment_config(scenario, f"sample {task.sample}")
    trace = run_mode("interpolate", cfg, settings, table)
    critical = trace.plant_critical_load_n
    held = trace.load_n[-1] if trace.load_n else math.nan
    return {"held_load_n": float(held), "critical_load_n": float(critical), "ratio": float(held) / critical,
            "reason": trace.fault or trace.end}


# -- the report -----------------------------------------------------------------------------------
def summarise(rows: list[Mapping[str, Any]], keys: list[str], wall_s: float) -> dict[str, Any]:
    """``summary.json``: per design the samples, the worst ratio and its quantiles, and the
    sensitivity ranking (Spearman rank correlation of each parameter with the held load)."""
    from scipy.stats import spearmanr

    out: dict[str, Any] = {"samples": len({r["sample"] for r in rows}), "wall_s": wall_s, "designs": {}}
    worst = math.inf
    for design in sorted({r["design"] for r in rows}):
        mine = sorted((r for r in rows if r["design"] == design), key=lambda r: r["sample"])
        ratio = np.array([r["ratio"] for r in mine], dtype=float)
        good = np.isfinite(ratio)
        held = np.array([r["held_load_n"] for r in mine], dtype=float)
        sensitivity = {}
        for k in keys:
            x = np.array([r[k] for r in mine], dtype=float)
            ok = good & np.isfinite(held)
            if ok.sum() > 2 and np.ptp(x[ok]) > 0 and np.ptp(held[ok]) > 0:
                sensitivity[k] = float(spearmanr(x[ok], held[ok]).statistic)
        ranked = dict(sorted(sensitivity.items(), key=lambda kv: -abs(kv[1])))
        q = {f"{p:g}": float(np.quantile(ratio[good], p / 100)) for p in (1, 5, 50, 95)} if good.any() else {}
        w = float(ratio[good].min()) if good.any() else math.nan
        worst = min(worst, w)
        out["designs"][design] = {"samples": len(mine), "invalid": int((~good).sum()), "worst_ratio": w,
                                  "ratio_quantiles": q, "sensitivity": ranked}
    out["worst_ratio"] = worst if math.isfinite(worst) else None
    return out
