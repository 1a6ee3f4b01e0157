"""``beamctl model fit``: fit model parameters to measured frequency responses (and measured
eigenfrequencies), write the fitted model as a configuration file, draw figure 5a."""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path

import numpy as np
import yaml

from beamctl.common.outputs import check_dir, check_file, write_text
from beamctl.config.schema import ConfigError, read_yaml
from beamctl.identification.frf_files import read_frf
from beamctl.models.fit import (
    ALIASES,
    DEFAULT_PARAMETERS,
    FORCE_CONSTANT_KEY,
    Eigenfrequency,
    FitError,
    FitResult,
    FitSettings,
    fit,
    model_response,
)
from beamctl.models.measured import FrfData
from beamctl.models.params import ModelParameters
from beamctl.reports import plots
from beamctl.service.setup import load_model_file
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
                    "did not converge is refused and nothing is written.")
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


def read_eigenfrequencies(path: str) -> list[Eigenfrequency]:
    """The measured eigenfrequencies of a CSV file (see ``--eigenfrequencies``)."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = [r for r in csv.reader(f) if r and not r[0].lstrip().startswith("#")]
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError("--eigenfrequencies", path, f"a readable CSV file ({exc})") from None
    if not rows:
        raise ConfigError("--eigenfrequencies", path, "a header row and at least one row")
    header = [h.strip() for h in rows[0]]
    known = ("load_n", "mode", "frequency_hz", "plane", "sigma")
    for h in header:
        if h not in known:
            raise ConfigError("column", h, f"one of {', '.join(known)}", path)
    for h in known[:3]:
        if h not in header:
            raise ConfigError("column", h, "present (load_n, mode, frequency_hz are required)", path)
    out = []
    for n, row in enumerate(rows[1:], start=2):
        cells = dict(zip(header, (c.strip() for c in row), strict=False))
        try:
            load, mode, freq = float(cells["load_n"]), int(cells["mode"]), float(cells["frequency_hz"])
            sigma = float(cells.get("sigma") or 0.005)
        except (KeyError, ValueError):
            raise ConfigError(f"row {n}", ",".join(row), "numbers: load_n, mode (1, 2 or 3), frequency_hz",
                              path) from None
        plane = cells.get("plane") or "y"
        if not (math.isfinite(load) and load >= 0 and mode in (1, 2, 3) and math.isfinite(freq) and freq > 0
                and plane in ("y", "z") and math.isfinite(sigma) and sigma > 0):
            raise ConfigError(f"row {n}", ",".join(row),
                              "load_n >= 0, mode 1..3, frequency_hz > 0, plane y or z, sigma > 0", path)
        out.append(Eigenfrequency(load, mode, freq, plane, sigma))
    return out


def fitted_document(result: FitResult, files: list[FrfData]) -> str:
    """The fitted model as a configuration file: a header of comments with the fit, the model
    section (every model parameter), and the stack force per volt when it was fitted."""
    lines = ["# Model fitted by `beamctl model fit` to:"]
    lines += [f"#   {d.source} ({d.load_n:.0f} N, {len(d.frequencies_hz)} frequencies)" for d in files]
    lines.append(f"# cost {result.cost:.6g} (start {result.start_cost:.6g}), "
                 f"{result.evaluations} evaluations")
    lines.append("# parameter: start -> fitted +- standard error")
    for k in result.keys:
        lines.append(f"#   {k}: {_fmt(result.start[k])} -> {_fmt(result.values[k])} +- "
                     f"{_fmt(result.std_errors[k])}")
    for pair, r in result.correlations.items():
        lines.append(f"# correlated (poorly separable): {pair.replace('|', ' and ')}: {r:+.3f}")
    lines += ["# `beamctl model --config F` and `beamctl gains build --config F` read the model section;",
              "# a rig's configuration takes it with `model: F`."]
    doc: dict = {"model": result.parameters.to_dict()}
    if result.force_constant_n_per_v is not None:
        lines.append("# Set the rig's controller.actuators.force_constant_n_per_v to the fitted value below.")
        doc["controller"] = {"actuators": {"force_constant_n_per_v": result.force_constant_n_per_v}}
    return "\n".join(lines) + "\n" + yaml.safe_dump(doc, sort_keys=False)


def _fmt(v) -> str:
    return "[" + ", ".join(f"{e:.6g}" for e in v) + "]" if isinstance(v, list) else f"{v:.6g}"


def load_fitted(path: str) -> tuple[ModelParameters, float | None]:
    """A fitted model file: its parameters and the fitted force constant (None if absent)."""
    params = load_model_file(path, "--fitted")
    data = read_yaml(path)
    k = ((data.get("controller") or {}).get("actuators") or {}).get("force_constant_n_per_v")
    return params, (float(k) if k is not None else None)


def figure_5a(measured: list[FrfData], before: ModelParameters,
              fitted: tuple[ModelParameters, float | None] | None, path: Path) -> Path:
    """Figure 5a for the first measurement: Gy and Gz measured, the model before and after."""

    d = measured[0]
    freqs = d.frequencies_hz
    curves = [("model before the fit", model_response(before, d, freqs))]
    if fitted is not None:
        curves.append(("model after the fit", model_response(fitted[0], d, freqs, fitted[1])))
    return plots.frequency_response_measured(d, curves, path)


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
        written.append(figure_5a(data, start, (result.parameters, result.force_constant_n_per_v),
                                 plot_dir / FIG5A))
    if args.json:
        print(json.dumps(result.to_json(), indent=1))
        return 0
    print(f"fitted {len(result.keys)} parameters to {len(data)} measurement(s){' and ' if eigen else ''}"
          f"{f'{len(eigen)} eigenfrequencies' if eigen else ''}: cost {result.cost:.6g} "
          f"(start {result.start_cost:.6g}), {result.evaluations} evaluations")
    width = max(len(k) for k in result.keys)
    for k in result.keys:
        v, sd = result.values[k], result.std_errors[k]
        rel = (np.asarray(sd) / np.abs(np.asarray(v)) * 100).tolist()
        rel_text = _fmt(rel) if isinstance(rel, list) else f"{rel:.2g}"
        print(f"  {k:<{width}}  {_fmt(result.start[k])} -> {_fmt(v)} +- {_fmt(sd)} ({rel_text} %)")
    for pair, r in result.correlations.items():
        print(f"  correlated (poorly separable): {pair.replace('|', ' and ')}: {r:+.3f}")
    if FORCE_CONSTANT_KEY in result.values:
        print(f"set controller.actuators.force_constant_n_per_v: {result.values[FORCE_CONSTANT_KEY]:.6g} "
              f"in the rig's configuration")
    print(f"wrote {', '.join(str(p) for p in written)}")
    return 0
