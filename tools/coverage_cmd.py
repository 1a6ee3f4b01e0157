"""``beamctl model coverage``: identification and the fit on seeded simulated rigs that the model
only approximates (identification/coverage.py): per fitted parameter the largest error and how
often its 95 % interval covers the rig's own value."""

from __future__ import annotations

import argparse
import json
import os

from beamctl.common.outputs import check_file, write_text
from beamctl.config.schema import ConfigError
from beamctl.identification.coverage import BEAM_SCATTER, SUPPORT_SCATTER, CoverageSettings, summarise
from beamctl.identification.coverage import run as run_rigs
from beamctl.models.fit import ALIASES, DEFAULT_PARAMETERS
from beamctl.tools import argtypes
from beamctl.tools.progress import ProgressBar


def add_parser(sub) -> None:
    p = sub.add_parser(
        "coverage", help="how well identification and the fit recover simulated rigs, and whether "
                         "the fit's 95 %% intervals cover them",
        description="Draws --rigs simulated rigs from seeds (E, kr, the damping and the stacks' force "
                    "per volt scattered about Table 1 (E +-5 %, kr +-20 %, the damping x0.5..2), a finer "
                    "FE mesh than the model's, strain and load-cell noise, an eccentric load, a bow), "
                    "identifies each on the simulated backend "
                    "at --loads and fits the measurements together from Table 1. Prints per parameter the "
                    "largest relative error and how many 95 % intervals (1.96 standard errors) hold the "
                    "rig's own value. --scatter-supports also scatters kl and kp: the strains see only "
                    "the support's effective rotational stiffness, so fit them too (--params "
                    "E,kr,kl,kp,damping,force_constant) and read kr's wider interval.")
    p.add_argument("--rigs", type=argtypes.number(low=1, integer=True), default=20, metavar="N",
                   help="rigs (default 20)")
    p.add_argument("--seed", type=argtypes.number(low=0, integer=True), default=1, metavar="S",
                   help="rig i has the seed S + i (default 1)")
    p.add_argument("--loads", default="1000,2000", metavar="N,N,...",
                   help="axial loads in N to identify each rig at (default 1000,2000, as commissioning)")
    p.add_argument("--averages", type=argtypes.number(low=3, integer=True), default=8, metavar="A",
                   help="averaged excitation periods per input (default 8)")
    p.add_argument("--params", default=",".join(DEFAULT_PARAMETERS), metavar="P,P,...",
                   help=f"parameters to fit (aliases {', '.join(ALIASES)} or dotted keys; "
                        f"default {','.join(DEFAULT_PARAMETERS)}, as `beamctl model fit`)")
    p.add_argument("--scatter-supports", action="store_true",
                   help="also scatter the supports' kl and kp x0.8..1.2 about Table 1")
    p.add_argument("--workers", type=argtypes.number(low=1, integer=True), metavar="N",
                   help="worker processes (default: the cores, at most 2)")
    p.add_argument("--out", metavar="FILE.json", help="also write every rig's row and the summary")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.set_defaults(run=run)


def _loads(text: str) -> tuple[float, ...]:
    try:
        loads = tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        loads = ()
    if not loads or not all(0.0 <= x < 1e5 for x in loads):
        raise ConfigError("--loads", text, "axial loads in N, comma-separated, e.g. 1000,2000")
    return loads


def run(args: argparse.Namespace) -> int:
    settings = CoverageSettings(rigs=int(args.rigs), seed=int(args.seed), loads_n=_loads(args.loads),
                                averages=int(args.averages),
                                scatter={**BEAM_SCATTER,
                                         **(SUPPORT_SCATTER if args.scatter_supports else {})},
                                parameters=tuple(p.strip() for p in args.params.split(",") if p.strip()))
    out = check_file(args.out, "--out") if args.out else None
    workers = int(args.workers) if args.workers else min(2, os.cpu_count() or 1)
    with ProgressBar("coverage") as bar:
        rows = list(run_rigs(settings, workers,
                             lambda done, total: bar(done, total, f"rig {done} of {total}")))
        bar.close()
    summary = summarise(rows, settings)
    if out is not None:
        write_text(out, json.dumps({"summary": summary, "rigs": rows}, indent=1) + "\n")
    if args.json:
        print(json.dumps(summary, indent=1))
        return 0
    print(f"{summary['rigs']} rigs at {', '.join(f'{x:g}' for x in settings.loads_n)} N, "
          f"{settings.averages} averages; fitted {', '.join(settings.parameters)}"
          f"{'; kl and kp scattered too' if args.scatter_supports else ''}")
    print(f"  {'parameter':<16}{'values':>7}{'largest error':>15}{'95 % covers':>14}{'largest |z|':>13}"
          f"   within tolerance (or undetermined)")
    for name, p in summary["parameters"].items():
        z = "-" if p["max_abs_z"] is None else f"{p['max_abs_z']:.2f}"
        tol = ("" if p.get("tolerance") is None else
               f"   {p['within_tolerance']} of {p['values']} within {100 * p['tolerance']:g} %"
               + (f" ({p['within_or_undetermined']} with the {p['undetermined']} undetermined)"
                  if p["undetermined"] else ""))
        print(f"  {name:<16}{p['values']:>7}{p['max_relative_error'] * 100:>14.2f}%"
              f"{p['covered_95']:>8} of {p['values']:<3}{z:>11}{tol}")
    if summary["max_misfit"] is not None:
        print(f"  misfit at most {summary['max_misfit']:.3g} (1: down to the data's noise); the fit warned "
              f"on {summary['warned']} of {summary['rigs']} rigs"
              + (" (the rows in --out say why)" if out else ""))
    for refused in summary["refused"]:
        print(f"  rig {refused['rig']}: fit refused: {refused['error']}")
    if out is not None:
        print(f"wrote {out}")
    return 0
