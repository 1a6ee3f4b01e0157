"""``beamctl model fit``: fit model parameters to measured frequency responses (and measured
eigenfrequencies), write the fitted model as a configuration file, draw figure 5a."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from beamctl.assembly.run import load_model_file, service_config
from beamctl.commission.workflow import stack_authority
from beamctl.common.outputs import check_dir, check_file, write_text
from beamctl.config.schema import ConfigError, read_yaml
from beamctl.identification.fit_files import fitted_document, read_eigenfrequencies
from beamctl.identification.frf_files import read_frf
from beamctl.models.fit import (
    ALIASES,
    DEFAULT_PARAMETERS,
    FORCE_CONSTANT_KEY,
    FitError,
    FitSettings,
    fit,
)
from beamctl.reports import plots
from beamctl.tools import argtypes
from beamctl.tools.progress import ProgressBar

EXIT_NOT_CONVERGED = 1
FIG5A = "fig5a_frequency_response.png"


def add_parser(sub) -> None:
    p = sub.add_parser(
        "fit", help="fit model parameters to measured frequency responses",
        description="Nonlinear least squares of the log-magnitude and phase errors, weighted by coherence, "
                    "from the --config model as start, within bounds (a factor 3 of the start; gauges "
                    "+-10 mm). Reports each value, its standard error and the correlated pairs; a fit that "
                    "did not converge is refused and nothing is written. Where the measurements carry "
                    "static strains (beamctl identify records them), also the stacks' use at the fitted "
                    "critical load, as beamctl commission's stacks step.")
    p.add_argument("frf", nargs="+", metavar="FRF", help="measured frequency responses (.npz, .mat, .csv)")
    p.add_argument("--config", metavar="F", help="the start model (model parameters, or a configuration "
                   "with a model: section; default: the paper's Table 1)")
    p.add_argument("--params", default=",".join(DEFAULT_PARAMETERS), metavar="P,P,...",
                   help=f"parameters to fit: dotted model keys or the aliases {', '.join(ALIASES)} "
                        f"(default {','.join(DEFAULT_PARAMETERS)})")
    p.add_argument("--band", metavar="LO:HI", type=argtypes.band, default=(0.0, math.inf),
                   help="fit only this band in Hz (default: all measured)")
    p.add_argument("--min-coherence", type=argtypes.number(low=0.0), default=0.5, metavar="G",
                   help="leave out points of lower coherence (default 0.5)")
    p.add_argument("--eigenfrequencies", metavar="CSV",
                   help="measured eigenfrequencies: columns load_n, mode, frequency_hz, and optionally "
                        "plane (y/z) and sigma (relative uncertainty, default 0.005)")
    p.add_argument("--max-evaluations", type=argtypes.number(low=1, integer=True), default=400, metavar="N",
                   help="model evaluations before the fit is given up as not converged (default 400)")
    p.add_argument("--out", metavar="MODEL.yaml", required=True, help="the fitted model, as a configuration")
    p.add_argument("--plot", metavar="DIR", help="also write figure 5a (before and after the fit) into DIR")
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    p.set_defaults(run=run)


def _fmt(v) -> str:
    return "[" + ", ".join(f"{e:.6g}" for e in v) + "]" if isinstance(v, list) else f"{v:.6g}"


def _stacks(config: str | None, result, data) -> dict | None:
    """The stacks' use over the load range (commission's stacks step) where the measurements carry
    static strains (``beamctl identify`` records them); the voltage range and allocation of the
    --config's controller section where it has one, else the defaults."""
    if not any(isinstance(d.settings.get("static"), dict) for d in data):
        return None
    try:
        raw = read_yaml(config) if config else {}
        controller = raw.get("controller") if isinstance(raw, dict) else None
        cfg = service_config({"controller": controller} if controller else {}, config or "defaults")
    except ConfigError as exc:          # the fit is written: the stacks' line says why it is missing
        return {"text": f"not predicted: {exc}", "warnings": []}
    return stack_authority(cfg, result.parameters, result.force_constant_n_per_v, data)


def run(args: argparse.Namespace) -> int:

    start = load_model_file(args.config)
    settings = FitSettings(parameters=tuple(p.strip() for p in args.params.split(",") if p.strip()),
                           band_hz=args.band, min_coherence=args.min_coherence,
                           max_evaluations=int(args.max_evaluations))
    if settings.min_coherence >= 1:
        raise ConfigError("--min-coherence", settings.min_coherence, "a coherence below 1")
    out = check_file(args.out, "--out")
    if args.plot and Path(args.plot).resolve() == out.resolve():
        raise ConfigError("--plot", args.plot, "a folder for the figure, not the --out file")
    plot_dir = check_dir(args.plot, "--plot") if args.plot else None
    data = [read_frf(f) for f in args.frf]
    eigen = read_eigenfrequencies(args.eigenfrequencies) if args.eigenfrequencies else []
    try:
        with ProgressBar("fit") as bar:
            result = fit(start, data, settings, eigen,
                         progress=lambda n, cost: bar(n, n + 1, f"evaluation {n}, cost {cost:.4g}"))
            bar.close()
    except FitError as exc:
        print(f"beamctl model fit: not converged: {exc}", flush=True)
        return EXIT_NOT_CONVERGED
    write_text(out, fitted_document(result, data))
    written = [out]
    if plot_dir is not None:
        written.append(plots.figure_5a(data, start, (result.parameters, result.force_constant_n_per_v),
                                 plot_dir / FIG5A))
    stacks = _stacks(args.config, result, data)
    if args.json:
        print(json.dumps({**result.to_json(), **({"stacks": stacks} if stacks else {})}, indent=1))
        return 0
    print(f"fitted {len(result.keys)} parameters to {len(data)} measurement(s){' and ' if eigen else ''}"
          f"{f'{len(eigen)} eigenfrequencies' if eigen else ''}: cost {result.cost:.6g} "
          f"(start {result.start_cost:.6g}), {result.evaluations} evaluations"
          + ("" if result.misfit is None else f"; misfit {result.misfit:.3g} (1: down to the data's noise)"))
    width = max(len(k) for k in result.keys)
    for k in result.keys:
        v, sd = result.values[k], result.std_errors[k]
        rel = (np.asarray(sd) / np.abs(np.asarray(v)) * 100).tolist()
        rel_text = _fmt(rel) if isinstance(rel, list) else f"{rel:.2g}"
        print(f"  {k:<{width}}  {_fmt(result.start[k])} -> {_fmt(v)} +- {_fmt(sd)} ({rel_text} %)")
    for pair, r in result.correlations.items():
        print(f"  correlated (poorly separable): {pair.replace('|', ' and ')}: {r:+.3f}")
    for warning in result.warnings:
        print(f"  warning: {warning}")
    if stacks:
        print(f"  stacks: {stacks['text']}")
        for warning in stacks.get("warnings", []):
            print(f"  stacks warning: {warning}")
    if FORCE_CONSTANT_KEY in result.values:
        print(f"set controller.actuators.force_constant_n_per_v: {result.values[FORCE_CONSTANT_KEY]:.6g} "
              f"in the rig's configuration")
    print(f"wrote {', '.join(str(p) for p in written)}")
    return 0
