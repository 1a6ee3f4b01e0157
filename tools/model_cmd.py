"""``beamctl model``: critical load, eigenfrequencies versus load, figures 5a, 5b and 6;
``beamctl model fit``: fit model parameters to measured frequency responses."""

from __future__ import annotations

import argparse
import json

import numpy as np

from beamctl.assembly.run import load_model_file
from beamctl.common.outputs import check_dir
from beamctl.config.schema import ConfigError
from beamctl.identification.fit_files import load_fitted
from beamctl.identification.frf_files import read_frf
from beamctl.models import build_model, critical_load, eigenfrequencies, reduce
from beamctl.models.fe import FEModel
from beamctl.models.modal import ModalModel
from beamctl.reports import plots
from beamctl.tools import coverage_cmd, fit_cmd

TABLE_LOADS_N = (0, 500, 1000, 1500, 2000, 2500, 3000)
FIGURE6_LOAD_N = 2000.0


def add_parser(sub) -> None:
    p = sub.add_parser("model", help="FE model: critical load, eigenfrequencies, figures 5b and 6",
                       description="Build the FE model of the beam-column and report its "
                                   "critical buckling load and eigenfrequencies versus load.")
    p.add_argument("--config", metavar="F",
                   help="model parameters (YAML) over the paper's Table 1, or a configuration "
                   "with a model: section (a rig's service config, the output of `beamctl model fit`)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of tables")
    p.add_argument("--plot", metavar="DIR", help="write figure 5b and figure 6 as PNG into DIR; with --frf "
                   "also figure 5a, and the measured resonances on figure 5b")
    p.add_argument("--frf", metavar="FILE", nargs="+",
                   help="measured frequency responses (.npz, .mat, .csv): figure 5a against the model; "
                        "several files at different loads put their resonances on figure 5b")
    p.add_argument("--fitted", metavar="MODEL",
                   help="with --frf: the fitted model (`beamctl model fit --out`), drawn after the fit "
                        "against --config's model before it")
    p.set_defaults(run=run, model_command=None)
    actions = p.add_subparsers(dest="model_command", metavar="ACTION")
    fit_cmd.add_parser(actions)
    coverage_cmd.add_parser(actions)


def summary(model: FEModel, reduced: ModalModel) -> dict:
    """The numbers ``beamctl model`` reports, as a JSON-ready dict."""
    full = {str(f): eigenfrequencies(model, f, 3).tolist() for f in TABLE_LOADS_N}
    red = {str(f): reduced.eigenfrequencies(f).tolist() for f in TABLE_LOADS_N}
    # relative error of the reduced model; none beyond the critical load (buckled: 0 Hz)
    error = {k: [r / f - 1.0 if f > 0 else None for r, f in zip(red[k], full[k][:2], strict=True)]
             for k in full}
    return {
        "critical_load_N": critical_load(model),
        "eigenfrequencies_Hz": full,
        "nodes": model.n_nodes,
        "rayleigh": {"alpha_per_s": model.rayleigh_alpha, "beta_s": model.rayleigh_beta,
                     "identification_load_N": model.params.damping.identification_load},
        "reduced_model": {
            "reference_load_N": reduced.reference_load,
            "reference_load_fraction": model.params.modal.reference_load_fraction,
            "critical_load_N": reduced.critical_load(),
            "condition_number_C0_Phi": reduced.condition_number,
            "eigenfrequencies_Hz": red,
            "relative_error": error,
        },
    }


def print_table(s: dict, source: str) -> None:
    red = s["reduced_model"]
    print(f"model: {source}, N = {s['nodes']} nodes, {4 * s['nodes']} DOF")
    print(f"critical buckling load Fx,cr = {s['critical_load_N']:.1f} N (eq. 12)")
    r = s["rayleigh"]
    print(f"Rayleigh damping: alpha = {r['alpha_per_s']:.4g} 1/s, beta = {r['beta_s']:.4g} s "
          f"(fitted at {r['identification_load_N']:g} N)")
    print(f"reduced model: modes at {red['reference_load_N']:.1f} N "
          f"({red['reference_load_fraction']:g} Fx,cr), cond(C0 Phi) = "
          f"{red['condition_number_C0_Phi']:.3g}, critical load {red['critical_load_N']:.1f} N")
    print()
    print(f"{'load N':>7} | {'f1 Hz':>8} {'f2 Hz':>8} {'f3 Hz':>8} | {'reduced f1':>10} {'f2':>8} "
          f"| {'err f1 %':>8} {'err f2 %':>8}")
    for load, f in s["eigenfrequencies_Hz"].items():
        fr, err = red["eigenfrequencies_Hz"][load], red["relative_error"][load]
        errors = " ".join(f"{'buckled':>8}" if e is None else f"{100 * e:8.3f}" for e in err)
        print(f"{load:>7} | {f[0]:8.2f} {f[1]:8.2f} {f[2]:8.2f} | {fr[0]:10.2f} {fr[1]:8.2f} "
              f"| {errors}")


def run(args: argparse.Namespace) -> int:

    if (args.frf or args.fitted) and not args.plot:
        raise ConfigError("--plot", None, "a folder for the figures: --frf and --fitted draw figure 5a")
    if args.fitted and not args.frf:
        raise ConfigError("--frf", None, "the measurement the fitted model is drawn against (--fitted)")
    params = load_model_file(args.config)
    plot_dir = check_dir(args.plot, "--plot") if args.plot else None
    measured = []
    if args.frf:

        measured = [read_frf(f) for f in args.frf]
    fitted = load_fitted(args.fitted) if args.fitted else None
    model = build_model(params)
    reduced = reduce(model)
    s = summary(model, reduced)
    if args.json:
        print(json.dumps(s, indent=2))
    else:
        print_table(s, args.config or "paper defaults (models/paper.yaml)")
    if plot_dir:

        written = [
            plots.eigenfrequencies_vs_load(model, reduced, plot_dir / "fig5b_eigenfrequencies.png",
                                           measured=measured),
            plots.frequency_response_full_vs_reduced(
                model, reduced, FIGURE6_LOAD_N, np.linspace(0.0, 1200.0, 2401),
                plot_dir / "fig6_frequency_response.png"),
        ]
        if measured:
            written.append(plots.figure_5a(measured, params, fitted, plot_dir / fit_cmd.FIG5A))
        if not args.json:
            print()
            for path in written:
                print(f"wrote {path}")
    return 0
