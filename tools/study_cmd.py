"""``beamctl study``: an uncertainty study (simulation/study.py) on a Dask cluster: an embedded local
one by default, or an existing one (``--scheduler tcp://host:port``). Rows are appended to
``DIR/samples.csv`` as they arrive; a study stopped part-way resumes where it stopped when run
again with the same study file and folder."""

from __future__ import annotations

import argparse
import json

from beamctl.common.outputs import check_dir, write_text
from beamctl.config.schema import ConfigError
from beamctl.reports import plots
from beamctl.simulation.study import load_study, summarise
from beamctl.simulation.study_run import ROWS, prepare, run_study
from beamctl.tools import argtypes
from beamctl.tools.progress import ProgressBar


def add_parser(sub) -> None:
    p = sub.add_parser("study", help="uncertainty study: many scattered rigs against the designs, on Dask",
                       description="Draw rigs from the study file's parameter laws, run each against each "
                                   "design (linear: the instability onset; experiment: the load ramp) on a "
                                   "Dask cluster, write one row per sample as it arrives and a report.")
    p.add_argument("--config", metavar="STUDY.yaml", required=True, help="the study file (a study: section)")
    p.add_argument("--out", metavar="DIR", required=True,
                   help="the study's folder: samples.csv, study.json, summary.json, figures; a folder "
                        "with part of the same study resumes it")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="an existing Dask scheduler, e.g. tcp://10.0.0.5:8786 (default: a local cluster "
                        "here)")
    p.add_argument("--workers", type=argtypes.number(low=1, integer=True), metavar="N",
                   help="worker processes of the local cluster (default: the cores)")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.set_defaults(run=run)


def _client(args: argparse.Namespace):
    """(client, cluster or None): the scheduler given, or a local cluster of worker processes on
    127.0.0.1 with one thread (and one BLAS thread) each."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ConfigError("beamctl study", "", "dask.distributed installed: pip install 'beamctl[study]'") \
            from None
    if args.scheduler:
        try:
            return Client(args.scheduler, timeout=10), None
        except OSError as exc:
            raise ConfigError("--scheduler", args.scheduler,
                              f"the address of a running Dask scheduler ({exc})") from None
    import logging
    import os

    workers = int(args.workers or os.cpu_count() or 1)
    # any free dashboard port: never a clash with another; the workers log errors only (Ctrl-C
    # cancels their tasks, and each said so in a warning of its own after the one-line interrupt)
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                           dashboard_address=":0", silence_logs=logging.ERROR)
    return Client(cluster), cluster


def run(args: argparse.Namespace) -> int:
    study = load_study(args.config)
    out = check_dir(args.out, "--out")
    prepare(study, out)                 # refuse a folder of another study before a cluster starts
    client, cluster = _client(args)
    try:
        with ProgressBar("study") as bar:
            rows, counts = run_study(study, out, client, progress=bar)
            bar.close()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    summary = summarise(rows, list(study.parameters), counts["wall_s"])
    summary.update(resumed=counts["resumed"], run=counts["run"], kind=study.kind)

    figures = plots.study_figures(rows, study.designs, out, study.kind)
    write_text(out / "summary.json", json.dumps(summary, indent=1))
    if args.json:
        print(json.dumps(summary, indent=1))
        return 0
    print(f"{summary['samples']} samples x {len(study.designs)} design(s), {study.kind}: "
          f"{counts['run']} run now, {counts['resumed']} from before, {counts['wall_s']:.1f} s")
    for design, d in summary["designs"].items():
        print(f"  {design}: {_design_line(d)}")
    print(f"report: {out}/ ({', '.join(p.name for p in figures)}, {ROWS}, summary.json)")
    return 0


def _design_line(d: dict) -> str:
    """A design's summary in one line: the worst failure, the Kaplan-Meier quantiles, how many
    samples were censored, the most sensitive parameters."""
    def ratio(x: float | None) -> str:
        return "undetermined" if x is None else f"{x:.4f}"

    q = d["ratio_quantiles"]
    worst = (f"worst onset / own Fx,cr {d['worst_ratio']:.4f}" if d["worst_ratio"] is not None
             else f"no failure (every ratio at least {d['worst_ratio_at_least']:.4f})" if d["censored"]
             else "no valid sample")
    censored = (f"{d['censored']} of {d['samples']} censored (never failed: ratios from "
                f"{d['censored_from_ratio']:.4f} are lower bounds)" if d["censored"] else "none censored")
    sensitive = ", ".join(f"{k} {v:+.2f}" for k, v in list(d["sensitivity"].items())[:3]) or "-"
    return (f"{worst}, 5 % {ratio(q.get('5'))}, median {ratio(q.get('50'))} (Kaplan-Meier); {censored}; "
            f"most sensitive: {sensitive}")
