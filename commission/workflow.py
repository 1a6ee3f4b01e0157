"""Commissioning a rig: from a rig nobody has characterised to a gain table that holds it, in
one folder, step by step:

1. ``identify``: frequency responses at each load (``frf_<load>N.npz``; the same run as
   ``beamctl identify``);
2. ``fit``: the model fitted to them (``fitted.yaml`` as ``beamctl model fit`` writes it, and
   ``fit.json`` with each parameter's 95 % interval);
3. ``stacks``: how much of the stacks' voltage swing holding the beam straight takes up to and
   past the fitted critical load, predicted from the static strains of the measurements
   (``stacks.json``, models/authority.py): a rig whose imperfection needs more than the stacks
   give at Fx,cr is said to be so here, before any gain table is built;
4. ``box``: the uncertainty box the design must hold (``box.yaml``, see ``calibrated_box``);
5. ``gains``: the gain table designed on the fitted model (``gains.yaml``) and, unless left out,
   the robust check over the box (``robust.json``);
6. ``experiment``: the simulated experiment on the rig with that table (``experiment/``); against
   real hardware the workflow stops before it and says what to do next;
7. ``report``: ``report.html`` with the figures and numbers of every step.

Each step writes its files whole (under a temporary name, moved into place when complete) and
is then recorded in ``commission.json``; run again on the same folder with the same
configuration and settings, the workflow goes on where it stopped (an interrupted step is run
again, the ones recorded are kept; a recorded step whose files are gone is run again, with every
step after it). A folder of another rig or other settings is refused.
"""

from __future__ import annotations

import hashlib
import html
import json
import math
import shutil
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import yaml

from beamctl.assembly.run import ServiceConfig, load_gain_table, plant_parameters, service_config
from beamctl.common.outputs import check_dir, replacing, write_text
from beamctl.common.signals import Interrupted
from beamctl.config.schema import ConfigError, read_yaml
from beamctl.gains.build import build_lqg_table
from beamctl.gains.defaults import LQG_GRID_N
from beamctl.gains.robust import box_from_dict, robust_check, table_record
from beamctl.gains.table import write_table
from beamctl.identification.fit_files import fitted_document, load_fitted
from beamctl.identification.frf_files import read_frf, write_frf
from beamctl.identification.identify import IdentifySettings, identify
from beamctl.models import authority, build_model, critical_load
from beamctl.models.authority import finite_point
from beamctl.models.fit import DEFAULT_PARAMETERS, FitError, FitSettings, fit, resolve_keys
from beamctl.models.measured import FrfData
from beamctl.models.params import ModelParameters
from beamctl.reports import plots
from beamctl.rt.allocation import geometry as controller_geometry
from beamctl.rt.stop import StopRequest
from beamctl.simulation.experiment import experiment_config, experiment_tables, run_experiment

STEPS = ("identify", "fit", "stacks", "box", "gains", "experiment", "report")
# steps whose files only the report reads as they are (the experiment quotes the stacks' limit,
# the report the current one): missing, they are run again alone, and the report after them
ADVISORY = ("stacks",)
STATE = "commission.json"
STACKS_FIGURE = "stacks_vs_load.png"
Z_95 = 1.959964
# The calibrated box: each fitted parameter within INFLATION x its 95 % interval of the fitted
# value, and never narrower than FLOOR (the fit's intervals count the measurement's noise and the
# FE mesh, not what a real rig has that no simulated one does); a parameter not fitted and what
# identification cannot see, as box B has it.
INFLATION = 3.0
# a fit whose residual is beyond this many times the data's noise is not calibrated on: the
# model misses something the rig has (a good fit of the simulated rigs: 1.1 to 1.3)
MISFIT_STOP = 3.0
FULL_PARAMETERS = ("E", "kr", "kl", "kp", "damping", "force_constant", "gauges")
# the shipped LQG's grid (gains/defaults.py) is the default's step and its highest top
GRID_STEP_N = float(LQG_GRID_N[1] - LQG_GRID_N[0])
GRID_TOP_N = float(LQG_GRID_N[-1])
GRID_TOP_FRACTION = 1.2
FLOOR = {"beam.youngs_modulus": 0.01, "supports.rotational_stiffness": 0.10,
         "supports.lateral_stiffness": 0.10, "supports.actuator_stiffness": 0.10, "damping.ratios": 0.30}
UNSEEN = {"beam.youngs_modulus": {"factor": [0.97, 1.03]},
          "supports.rotational_stiffness": {"factor": [0.8, 1.2]},
          "supports.lateral_stiffness": {"factor": [0.8, 1.2]},
          "supports.actuator_stiffness": {"factor": [0.8, 1.2]},
          "damping.ratios": {"factor": [0.5, 2.0]},
          "actuators.force_constant_n_per_v": {"factor": [0.9, 1.1]},     # the stacks' drift
          "io.delay_samples": {"value": [0.0, 1.0]},
          "sensors.strain_gauge_positions[0]": {"offset": [-1e-3, 1e-3]},
          "sensors.strain_gauge_positions[1]": {"offset": [-1e-3, 1e-3]},
          "sample_rate_hz": {"factor": [0.99, 1.01]}}


def default_grid(critical_n: float) -> list[float]:
    """The table's loads when --grid is not given: every GRID_STEP_N from 0 to GRID_TOP_FRACTION
    of the fitted model's critical load (at most 4000 N, the shipped design's top). An LQG design
    holds a model to about 1.25 x its critical load (Table 1's: 4000 N of 3194 N, a knife-edge),
    so a softer rig's table ends lower instead of ending unstable."""
    top = min(GRID_TOP_N, GRID_STEP_N * math.floor(GRID_TOP_FRACTION * critical_n / GRID_STEP_N))
    return [GRID_STEP_N * i for i in range(int(round(top / GRID_STEP_N)) + 1)]


class CommissionError(Exception):
    """A step found that the rig cannot be commissioned this way (one line, what to do)."""


@dataclass(frozen=True)
class CommissionSettings:
    # two loads: the frequency responses at both decorrelate E and kr, and the static strains at
    # both predict the stacks' use at Fx,cr within about 2 % (one load: rough and mostly low)
    loads_n: tuple[float, ...] = (1000.0, 2000.0)
    averages: int = 8
    parameters: tuple[str, ...] = DEFAULT_PARAMETERS
    robust: bool = True
    grid_n: tuple[float, float, float] | None = None     # the table's load grid (default: default_grid)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["loads_n"] = list(self.loads_n)
        d["parameters"] = list(self.parameters)
        d["grid_n"] = list(self.grid_n) if self.grid_n else None
        return d


def calibrated_box(fitted: dict[str, Any], std_errors: dict[str, Any],
                   undetermined: Sequence[str] = ()) -> dict[str, Any]:
    """The box (a ``box:`` mapping) around the fitted model: a fitted parameter within
    INFLATION x 1.96 of its relative standard error of the fitted value, at least FLOOR; the
    others, what identification cannot see, and a fitted parameter the data leave undetermined
    (``undetermined``: scalar unknowns as the fit names them, ``supports.lateral_stiffness``,
    ``damping.ratios[1]``) as in UNSEEN, the prior's range, never narrower than its own interval
    would give."""
    parameters: dict[str, Any] = dict(UNSEEN)
    for key in fitted:
        if key not in FLOOR:
            continue
        values = fitted[key] if isinstance(fitted[key], list) else [fitted[key]]
        errors = std_errors[key] if isinstance(std_errors[key], list) else [std_errors[key]]
        rel = max((abs(s / v) for s, v in zip(errors, values, strict=True) if v), default=0.0)
        half = max(INFLATION * Z_95 * rel, FLOOR[key])
        low, high = 1.0 - half, 1.0 + half
        if any(n == key or n.startswith(key + "[") for n in undetermined):
            prior_low, prior_high = UNSEEN[key]["factor"]
            low, high = min(low, prior_low), max(high, prior_high)
        parameters[key] = {"factor": [round(max(low, 0.05), 6), round(high, 6)]}
    return {"parameters": parameters}


def calibration(fitted: dict[str, Any], undetermined: Sequence[str]) -> dict[str, str]:
    """Per parameter of the box: how its range came about (calibrated from the fit, or kept at
    the prior's and why)."""
    out = {}
    for key in UNSEEN:
        if key in fitted and key in FLOOR:
            loose = [n for n in undetermined if n == key or n.startswith(key + "[")]
            out[key] = (f"kept at the prior's range or wider: the data leave {', '.join(loose)} undetermined"
                        if loose
                        else "calibrated from the fit")
        elif key in fitted:
            out[key] = "fitted; its range is the drift a rig has after identification"
        else:
            out[key] = "not fitted, or not seen by identification: the prior's range"
    return out


class Commission:
    """One commissioning folder (see the module docstring). ``log`` takes a line per step;
    ``progress(done, total, label)`` the progress within a step."""

    def __init__(self, config_path: str | Path, out: str | Path, settings: CommissionSettings,
                 log: Callable[[str], None] = print, progress: Callable[..., None] | None = None,
                 stop: StopRequest | None = None) -> None:
        self.config_path = Path(config_path)
        self.cfg = service_config(read_yaml(self.config_path), str(self.config_path))     # refused first
        text = self.config_path.read_bytes()
        self.settings = settings
        resolve_keys(settings.parameters, self.cfg.model)          # refused before the rig moves
        self.out = check_dir(out, "--out")
        self.out.mkdir(parents=True, exist_ok=True)
        self.log = log
        self._report_progress = progress
        self.stop = stop
        # what the configuration reads from other files counts too: the model it names and the
        # gain table the identification runs with
        table_path = Path(self.cfg.table_path)
        self.identity = {"config": str(self.config_path.resolve()),
                         "config_sha256": hashlib.sha256(text).hexdigest(),
                         "model_sha256": self.cfg.model.digest(),
                         "table_sha256": (hashlib.sha256(table_path.read_bytes()).hexdigest()
                                          if table_path.is_file() else None),
                         "settings": settings.to_dict()}
        state = self.out / STATE
        self.done: list[str] = []
        if state.exists():
            try:
                recorded = json.loads(state.read_text())
                # a folder of an earlier beamctl lacks keys: another commissioning, not a damaged one
                same = {k: recorded.get(k) for k in self.identity} == self.identity
                done = list(recorded["done"]) if same else []
            except (ValueError, KeyError, TypeError, AttributeError):
                raise ConfigError("--out", str(self.out), f"a commissioning folder ({STATE} there is "
                                  "damaged: move it away to start again)") from None
            if not same:
                raise ConfigError("--out", str(self.out), "a new folder, or the folder of this "
                                  "configuration and these settings (it holds another commissioning"
                                  f"{_differences(recorded, self.identity)})")
            # a step whose files are gone (moved, deleted) is run again, and every step after it
            kept: list[str] = []
            for step in STEPS:
                if step not in done or not all((self.out / name).exists() for name in self._files(step)):
                    if step in ADVISORY:        # nothing later is built on it: only the report again
                        continue
                    break
                kept.append(step)
            # an advisory step run again changes the report
            if any(step not in kept and any(STEPS.index(k) > STEPS.index(step) for k in kept)
                   for step in ADVISORY):
                kept = [step for step in kept if step != "report"]
            self.done = kept
        elif any(self.out.iterdir()):
            raise ConfigError("--out", str(self.out), "an empty folder or one this workflow began")

    # -- running -----------------------------------------------------------------------------------
    def progress(self, done: int, total: int, label: str = "") -> None:
        """A step's progress; where a stop was asked for (Ctrl-C: ``stop``), the step ends here
        (Interrupted) with nothing of it written. The steps that drive the rig (identify,
        experiment) read the request themselves and ramp the stacks to bias first."""
        self._check_stop()
        if self._report_progress is not None:
            self._report_progress(done, total, label)

    def _check_stop(self) -> None:
        if self.stop is not None and self.stop.reason:
            raise Interrupted(self.stop.signal_name or self.stop.reason, "the commissioning")

    def run(self) -> dict[str, Any]:
        """Every step not done yet, in order; the summary of the folder."""
        for number, step in enumerate(STEPS, 1):
            self._check_stop()
            if step in self.done:
                self.log(f"step {number}/{len(STEPS)} {step}: done before, kept")
                continue
            self.log(f"step {number}/{len(STEPS)} {step} ...")
            note = getattr(self, f"_{step}")()
            if step == "experiment" and self.cfg.hal.backend != "sim":
                self.log(f"step {number}/{len(STEPS)} {step}: {note}")    # not done: asked again next time
                break
            self.done = [s for s in STEPS if s in self.done or s == step]
            write_text(self.out / STATE, json.dumps({**self.identity, "done": self.done}, indent=1) + "\n")
            self.log(f"step {number}/{len(STEPS)} {step}: {note}")
        return self.summary()

    def _files(self, step: str) -> list[str]:
        """The files a step leaves in the folder (what a resumed run needs of it)."""
        if step == "identify":
            return [p.name for p in self._frf_paths()]
        sim = self.cfg.hal.backend == "sim"
        gains = ["gains.yaml", "robust.json"] if self.settings.robust else ["gains.yaml"]
        return {"fit": ["fit.json", "fitted.yaml"], "stacks": ["stacks.json"], "box": ["box.yaml"],
                "gains": gains, "experiment": ["experiment/summary.json"] if sim else [],
                "report": ["report.html"]}[step]

    def _frf_paths(self) -> list[Path]:
        return [self.out / f"frf_{load:g}N.npz" for load in self.settings.loads_n]

    def _identify(self) -> str:
        table = load_gain_table(self.cfg)
        for path, load in zip(self._frf_paths(), self.settings.loads_n, strict=True):
            settings = IdentifySettings(load_n=load, averages=self.settings.averages)
            data, _ = identify(self.cfg, table, settings, self._report_progress, self.stop)
            write_frf(data, path)
        return f"{len(self.settings.loads_n)} measurement(s): {', '.join(p.name for p in self._frf_paths())}"

    def _fit(self) -> str:
        data = [read_frf(p) for p in self._frf_paths()]
        start = self.cfg.model
        resolve_keys(self.settings.parameters, start)
        try:
            result = fit(start, data, FitSettings(parameters=self.settings.parameters),
                         progress=lambda n, cost: self.progress(n, n + 1, f"evaluation {n}, cost {cost:.4g}"))
        except FitError as exc:
            raise CommissionError(f"the fit cannot be trusted: {exc}") from None
        if result.misfit is not None and result.misfit > MISFIT_STOP:
            for warning in result.warnings:
                self.log(f"warning: {warning}")
            free = ",".join(self.settings.parameters)
            raise CommissionError(
                f"the model does not explain the measurements: the fit's residual is {result.misfit:.3g} x "
                f"the data's noise (at most {MISFIT_STOP:g} is taken; fitted {free}); a box calibrated on it "
                f"need not hold the rig, so nothing is calibrated. Free what the rig may differ in (--params "
                f"{','.join(FULL_PARAMETERS)}), check the configuration's gauge positions and stack "
                f"orientation against the rig, or measure at more loads (--loads), then run again")
        intervals = {}
        for key, value in result.values.items():
            se = result.std_errors[key]
            if isinstance(value, list):
                intervals[key] = [[v - Z_95 * s, v + Z_95 * s] for v, s in zip(value, se, strict=True)]
            else:
                intervals[key] = [value - Z_95 * se, value + Z_95 * se]
        write_text(self.out / "fit.json", json.dumps({**result.to_json(), "intervals_95": intervals},
                                                     indent=1) + "\n")
        write_text(self.out / "fitted.yaml", fitted_document(result, data))
        worst = max(result.correlations.items(), key=lambda kv: abs(kv[1]), default=None)
        warn = f"; {worst[0].replace('|', ' and ')} correlated {worst[1]:+.3f}" if worst else ""
        misfit = ("" if result.misfit is None
                  else f", misfit {result.misfit:.3g} (1: down to the data's noise)")
        for warning in result.warnings:
            self.log(f"warning: {warning}")
        return (f"{len(result.keys)} parameters, cost {result.start_cost:.4g} -> {result.cost:.4g}"
                f"{misfit}{warn}")

    def _stacks(self) -> str:
        data = [read_frf(p) for p in self._frf_paths()]
        params, k = load_fitted(str(self.out / "fitted.yaml"))
        result = stack_authority(self.cfg, params, k, data)
        write_text(self.out / "stacks.json", json.dumps(result, indent=1) + "\n")
        for warning in result.get("warnings", []):
            self.log(f"warning: {warning}")
        if result.get("not_enough"):
            self.log(f"warning: the stacks cannot hold this rig straight to its critical load (a stack "
                     f"at its limit from about {result['limit_n']:.0f} N): see below")
        return result["text"]

    def _box(self) -> str:
        fitted = json.loads((self.out / "fit.json").read_text())
        undetermined = fitted.get("undetermined", [])
        box = {"box": calibrated_box(fitted["parameters"], fitted["std_errors"], undetermined)}
        how = calibration(fitted["parameters"], undetermined)
        params, _ = load_fitted(str(self.out / "fitted.yaml"))
        box_from_dict(box["box"], params, "calibrated box")          # the rules of every box file
        header = ("# The uncertainty box the design must hold, calibrated from the fit (fit.json):\n"
                  f"# each fitted parameter within {INFLATION:g} x its 95 % interval, at least its floor;\n"
                  "# the rest as box B has it (stacks' drift +-10 %, delay 0..1 sample, gauges +-1 mm,\n"
                  "# rate +-1 %).\n"
                  + "".join(f"#   {key}: {text}\n" for key, text in how.items()))
        write_text(self.out / "box.yaml", header + yaml.safe_dump(box, sort_keys=False))
        kept = [k for k, text in how.items() if text.startswith("kept")]
        for key in kept:
            self.log(f"warning: {key} {how[key]}")
        calibrated = sum(text == "calibrated from the fit" for text in how.values())
        return (f"{len(box['box']['parameters'])} parameters, {calibrated} calibrated from the fit"
                + (f", {len(kept)} kept at the prior's range (undetermined)" if kept else ""))

    def _gains(self) -> str:
        params, _ = load_fitted(str(self.out / "fitted.yaml"))
        model = build_model(params)
        if self.settings.grid_n:
            start, stop, step = self.settings.grid_n
            grid = [start + i * step for i in range(int(round((stop - start) / step)) + 1)]
        else:
            grid = default_grid(critical_load(model))
        table = build_lqg_table(model, grid, progress=self.progress)
        if not table.all_stable:
            unstable = [c.load_n for c in table.checks if not c.stable]
            raise CommissionError(f"the table designed on the fitted model is unstable at {len(unstable)} "
                                  f"check point(s) ({', '.join(f'{x:g}' for x in unstable[:5])} N): not "
                                  f"written; a grid that ends lower "
                                  f"(--grid 0:{max(grid[-1] - 300, 100):g}:100) may hold")
        note = f"{len(table.loads_n)} loads, fitted model's Fx,cr {critical_load(model):.0f} N"
        if self.settings.robust:
            params_box = box_from_dict(read_yaml(self.out / "box.yaml")["box"], params, "box.yaml")
            result = robust_check(table, params_box, progress=self.progress)
            table = replace(table, robust=table_record(result, "the calibrated box (box.yaml)"))
            write_text(self.out / "robust.json", json.dumps(result.to_dict(table), indent=1) + "\n")
            note += f"; robust check: worst onset / own Fx,cr {result.worst_ratio:.4f}"
            if result.refused:
                note += f" ({result.refused_text()})"
            if result.worst_ratio < 1.0:
                with replacing(self.out / "gains-not-held.yaml") as temp:
                    write_table(table, temp)
                refused = f"; {result.refused_text()}" if result.refused else ""
                raise CommissionError(f"NOT HELD: a rig of the calibrated box goes unstable below its own "
                                      f"critical load ({result.worst_ratio:.4f}); the table is in "
                                      f"gains-not-held.yaml, robust.json names the rig{refused}")
        with replacing(self.out / "gains.yaml") as temp:
            write_table(table, temp)
        (self.out / "gains-not-held.yaml").unlink(missing_ok=True)      # an earlier run's, not this table
        return note

    def _stacks_limit(self) -> float | None:
        """The load at which the stacks step predicts a stack reaches its limit at or below the
        fitted Fx,cr (None: the stacks hold the beam straight to Fx,cr, or not predicted)."""
        stacks = json.loads((self.out / "stacks.json").read_text())
        return stacks.get("limit_n") if stacks.get("not_enough") else None

    def _experiment(self) -> str:
        if self.cfg.hal.backend != "sim":
            limit = self._stacks_limit()
            raise_to = ("raise the load" if limit is None else
                        f"raise the load no further than about {0.95 * limit:.0f} N (the stacks step: "
                        f"a stack reaches its limit at about {limit:.0f} N, below Fx,cr)")
            return ("a real rig: stopped here, before the beam is loaded past its critical load. Next: "
                    f"set gains.table: {self.out / 'gains.yaml'} and the fitted force constant "
                    f"({self.out / 'fitted.yaml'}) in the rig's configuration, `beamctl config check`, then "
                    f"`beamctl run --hold` and {raise_to}")
        raw = read_yaml(self.config_path)
        _, k = load_fitted(str(self.out / "fitted.yaml"))
        # the rig stays the configured one, whole: the controller's model becomes the fitted one,
        # and what the rig's plant section leaves out (kl and kp, say) must not follow it
        plant = {**(raw.get("plant") or {}), "model": plant_parameters(self.cfg).to_dict()}
        scenario = {**raw, "gains": {"table": str(self.out / "gains.yaml")},
                    "model": str(self.out / "fitted.yaml"), "plant": plant}
        if k is not None:
            controller = dict(raw.get("controller") or {})
            controller["actuators"] = {**(controller.get("actuators") or {}), "force_constant_n_per_v": k}
            scenario["controller"] = controller
        experiment = dict(scenario.get("experiment") or {})
        experiment["paper_mode"] = False
        scenario["experiment"] = experiment
        cfg, settings = experiment_config(scenario, f"{self.config_path} with the commissioned table")
        tables = experiment_tables(cfg, settings)
        summary, traces = run_experiment(cfg, settings, tables, progress=self._report_progress,
                                         stop=self.stop)
        loads = traces["interpolate"].arrays()["load_n"]
        own = summary["plant_critical_load_N"]
        let_go = summary["controlled"]["load_at_1.0mm_N"]
        a = cfg.controller.actuators
        # the stacks' use during the controlled run, against the load (the stacks step's prediction
        # drawn over it in the report)
        limits = (a.min_voltage_v, a.max_voltage_v, a.bias_voltage_v, cfg.controller.allocation)
        use = [[round(float(row[0]), 1), round(authority.voltage_fraction(row[1:], *limits), 4)]
               for row in traces["interpolate"].voltages]
        summary["commission"] = {"own_critical_load_N": own, "let_go_at_N": let_go, "stack_use": use,
                                 "stacks_limit_N": self._stacks_limit(),
                                 "fault": summary["controlled"].get("fault", ""),
                                 "max_load_N": float(loads.max()) if loads.size else None,
                                 "held_past_own_critical_load": bool(
                                     loads.size and loads.max() > own and (let_go is None or let_go > own))}
        folder = self.out / "experiment"
        partial = self.out / "experiment.partial"
        if partial.exists():
            shutil.rmtree(partial)
        partial.mkdir()
        plots.experiment_figures(summary, traces, partial)
        write_text(partial / "summary.json", json.dumps(summary, indent=1) + "\n")
        if folder.exists():
            shutil.rmtree(folder)
        partial.rename(folder)
        return held_text(summary["commission"])

    def _report(self) -> str:
        data = [read_frf(p) for p in self._frf_paths()]
        params, k = load_fitted(str(self.out / "fitted.yaml"))
        plots.figure_5a(data, self.cfg.model, (params, k), self.out / "fig5a_frequency_response.png")
        stacks = json.loads((self.out / "stacks.json").read_text())
        if "fraction" in stacks:
            experiment = self.out / "experiment" / "summary.json"
            run = json.loads(experiment.read_text()) if experiment.exists() else None
            plots.stack_use_figure(stacks, run["commission"].get("stack_use") if run else None,
                                   self.out / STACKS_FIGURE, run["plant_critical_load_N"] if run else None)
        else:                                   # not predicted: an earlier figure is not this one's
            (self.out / STACKS_FIGURE).unlink(missing_ok=True)
        write_text(self.out / "report.html", report_html(self.out))
        return "report.html"

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {"folder": str(self.out), "done": list(self.done)}
        for name in ("fit.json", "stacks.json", "robust.json", "experiment/summary.json"):
            path = self.out / name
            if path.exists():
                out[name.split("/")[0].removesuffix(".json")] = json.loads(path.read_text())
        return out


def _differences(recorded: dict[str, Any], identity: dict[str, Any]) -> str:
    """What makes a folder another commissioning, for the refusal: ': its loads_n [2000.0], here
    [1000.0, 2000.0]' (settings by name; the configuration and the files it names by what)."""
    found = []
    theirs = recorded.get("settings") if isinstance(recorded.get("settings"), dict) else {}
    ours = identity["settings"]
    for key in [*ours, *(k for k in theirs if k not in ours)]:
        if theirs.get(key) != ours.get(key):
            found.append(f"its {key} {theirs.get(key)}, here {ours.get(key)}"
                         + (" (the default loads are 1000,2000)" if key == "loads_n" else ""))
    for key, what in (("config", "another configuration file"), ("config_sha256", "the configuration edited"),
                      ("model_sha256", "another model"), ("table_sha256", "another gain table")):
        if recorded.get(key) != identity[key]:
            found.append(what)
    return ": " + "; ".join(found) if found else ""


def stack_authority(cfg: ServiceConfig, params: ModelParameters, force_constant: float | None,
                    data: list[FrfData]) -> dict[str, Any]:
    """The stacks' use over the load range (models/authority.py) from the measurements' static
    strains, with the fitted model and force constant (where it was not fitted, the measurements'
    own, as the fit takes it, else the configuration's); JSON-ready, with ``text`` the one line the
    workflow says. A measurement records the forces its controller believed it applied (its own
    force constant): they are rescaled to the fitted one, as the fit rescales its frequency
    responses. A measurement that cannot be used is left out with a warning naming it."""
    a = cfg.controller.actuators
    recorded = [d.force_constant_n_per_v for d in data if d.force_constant_n_per_v]
    k = force_constant or (recorded[0] if recorded else a.force_constant_n_per_v)
    geometry = controller_geometry(replace(a, force_constant_n_per_v=k))
    warnings: list[str] = []
    points = []
    for d in data:
        name = Path(d.source).name if d.source else "a measurement"
        static = d.settings.get("static")
        if static is None:
            warnings.append(f"{name} carries no static strains (measured by hand or by an earlier beamctl): "
                            "left out")
            continue
        try:
            if not isinstance(static, dict):
                raise ValueError(f"{name}: its static strains are not a mapping of strain and force_n")
            point = finite_point(d.load_n, static, name)
        except ValueError as exc:
            warnings.append(f"{exc}: left out")
            continue
        if d.force_constant_n_per_v:
            scale = k / d.force_constant_n_per_v
            point = replace(point, force_n=tuple(scale * f for f in point.force_n))
        points.append(point)
    if not points:
        return {"text": "not predicted: no measurement carries usable static strains (identify again to "
                        "have them)", "warnings": warnings}
    try:
        result = authority.predict(build_model(params), points, geometry, a.min_voltage_v, a.max_voltage_v,
                                   cfg.controller.allocation)
    except ValueError as exc:
        return {"text": f"not predicted: {exc}", "warnings": warnings}
    return {**result.to_json(), "warnings": warnings + result.warnings, "force_constant_n_per_v": k,
            "text": result.text()}


def held_text(c: dict[str, Any]) -> str:
    """What the commissioned table held in the simulated experiment, in words."""
    own = f"the rig's own Fx,cr {c['own_critical_load_N']:.0f} N"
    if c["let_go_at_N"] is not None:
        text = f"{own}; the beam passed 1 mm at {c['let_go_at_N']:.0f} N"
        if str(c.get("fault", "")).startswith("PERSISTENT_SATURATION"):
            text += (" after the stacks stayed at their limits (PERSISTENT_SATURATION): near its critical "
                     "load the beam's own stiffness is nearly gone and the stacks carry the moment of the "
                     "rig's eccentric load and bow, so their force, not the gains, is the limit; a "
                     "straighter load line holds longer")
            if c.get("stacks_limit_N") is not None:
                text += (" (the stacks step predicted a stack at its limit from about "
                         f"{c['stacks_limit_N']:.0f} N)")
        elif c.get("fault"):
            text += f" ({c['fault']})"
        return text
    top = c["max_load_N"]
    return f"{own}; held below 1 mm to the ramp's end, {top:.0f} N" if top is not None else own


def report_html(out: Path) -> str:
    """The commissioning report: every step's numbers and figures, in one page."""
    def table(rows: list[tuple[str, str]]) -> str:
        return "<table>" + "".join(f"<tr><th>{html.escape(a)}</th><td>{html.escape(b)}</td></tr>"
                                   for a, b in rows) + "</table>"

    fit_data = json.loads((out / "fit.json").read_text())
    parts = ["<!doctype html><meta charset='utf-8'><title>beamctl commissioning</title>",
             "<style>body{font-family:sans-serif;max-width:60em;margin:auto}th{text-align:left;"
             "padding-right:1em}img{max-width:100%}</style>",
             f"<h1>Commissioning: {html.escape(str(out))}</h1>", "<h2>Fit (95 % intervals)</h2>"]
    rows = []
    for key, value in fit_data["parameters"].items():
        interval = fit_data["intervals_95"][key]
        rows.append((key, f"{value} ({interval})"))
    parts.append(table(rows))
    if fit_data.get("misfit") is not None:
        rows = [("misfit", f"{fit_data['misfit']:.3g} (the residual over what the measured coherence "
                           "predicts; 1: the model explains the data down to their noise)")]
        parts.append(table(rows))
    if fit_data.get("correlations"):
        parts.append(table([(k.replace("|", " and "), f"correlated {v:+.3f}")
                            for k, v in fit_data["correlations"].items()]))
    if fit_data.get("warnings"):
        parts.append("<ul>" + "".join(f"<li><strong>warning</strong>: {html.escape(w)}</li>"
                                      for w in fit_data["warnings"]) + "</ul>")
    parts.append("<img src='fig5a_frequency_response.png' alt='measured and fitted frequency responses'>")
    stacks = json.loads((out / "stacks.json").read_text()) if (out / "stacks.json").exists() else None
    if stacks is not None:
        parts.append("<h2>Stack authority</h2><p>" + html.escape(stacks["text"]) + "</p>")
        if (out / STACKS_FIGURE).exists():
            parts.append(f"<img src='{STACKS_FIGURE}' alt='the stacks swing used against the load'>")
    parts.append("<h2>Calibrated box</h2><pre>" + html.escape((out / "box.yaml").read_text()) + "</pre>")
    robust = out / "robust.json"
    if robust.exists():
        r = json.loads(robust.read_text()).get("robust", {})
        parts.append("<h2>Robust check</h2>" + table([
            ("worst onset / own Fx,cr", f"{r.get('worst_ratio')}"),
            ("worst rig", json.dumps(r.get("worst_rig_si", r.get("worst_rig")))),
            ("rigs evaluated", f"{r.get('evaluated')}")]))
    else:
        parts.append("<h2>Robust check</h2><p>left out (--no-robust): how far the table holds a rig of the "
                     "box is not known.</p>")
    experiment = out / "experiment" / "summary.json"
    if experiment.exists():
        s = json.loads(experiment.read_text())
        # the stacks step's limit as it is now (it may have been run again after the experiment)
        limit = stacks.get("limit_n") if stacks and stacks.get("not_enough") else None
        parts.append("<h2>Simulated experiment on the rig</h2>" + table([
            ("the rig's own Fx,cr", f"{s['plant_critical_load_N']:.0f} N"),
            ("controlled run", held_text({**s["commission"], "stacks_limit_N": limit}))]))
        parts += [f"<img src='experiment/{p.name}' alt='{html.escape(p.stem)}'>"
                  for p in sorted((out / "experiment").glob("*.png"))]
    return "\n".join(parts) + "\n"


def grid_of(text: str) -> tuple[float, float, float]:
    """``START:STOP:STEP`` in N."""
    try:
        start, stop, step = (float(x) for x in text.split(":"))
    except ValueError:
        raise ConfigError("--grid", text, "START:STOP:STEP in N, e.g. 0:4000:100") from None
    if not (0 <= start < stop and step > 0 and math.isfinite(stop)):
        raise ConfigError("--grid", text, "0 <= START < STOP and STEP > 0")
    return start, stop, step

