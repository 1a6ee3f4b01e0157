"""``beamctl experiment``: the paper's figure 7 on the simulated rig."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from beamctl.common.outputs import check_dir, write_text
from beamctl.common.signals import stop_on_signals
from beamctl.reports import plots
from beamctl.rt.live import check_socket_path
from beamctl.service.live import add_live_argument
from beamctl.simulation.experiment import (
    check_engine,
    experiment_tables,
    load_experiment_config,
    run_experiment,
)
from beamctl.tools.progress import ProgressBar

REPORT_FILES = (*plots.EXPERIMENT_FIGURES, "summary.txt", "summary.json")

PAPER = {"uncontrolled": {"load_at_0.5mm_N": 2438.0, "load_at_1.0mm_N": 2723.0, "buckling_angle_deg": 234.0},
         "controlled": {"load_at_1.0mm_N": 3223.0, "buckling_angle_deg": 128.0}}


def add_parser(sub) -> None:
    p = sub.add_parser("experiment", help="the paper's experiment (figure 7) on the simulated rig",
                       description="Ramp the axial load on the simulated beam: uncontrolled, then "
                                   "controlled with the interpolated schedule, then with the paper's "
                                   "500 N switching; write a report folder.")
    p.add_argument("--config", metavar="F", help="scenario file (plant, controller, model, experiment)")
    p.add_argument("--out", metavar="DIR", default="experiment-report",
                   help="report folder (default: experiment-report here)")
    p.add_argument("--telemetry", nargs="?", const="", default=None, metavar="DIR",
                   help="also record each run's full-rate telemetry, as `beamctl run --telemetry FILE` "
                        "records one run, into DIR (default: the report folder): telemetry_<mode>.btl, "
                        "about 40 MB a run with the default scenario")
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    p.add_argument("--engine", choices=("auto", "loop", "kernel"), default="auto",
                   help="how the runs are simulated: the compiled kernel for the uneventful cycles "
                        "(needs numba, no --telemetry), every cycle through the control loop, or auto "
                        "(the kernel where it can run; default); the results are the same")
    p.add_argument("--no-paper", action="store_true", help="skip the run with the paper's 500 N switching")
    add_live_argument(p)
    p.set_defaults(run=run)


def _fmt(value, unit="", digits=0) -> str:
    return "-" if value is None else f"{value:.{digits}f}{unit}"


def summary_table(summary: dict) -> str:
    rows = [("", "uncontrolled", "interpolated", "paper 500 N", "paper (experiment)")]
    runs = [summary.get(k, {}) for k in ("uncontrolled", "controlled", "paper_switching")]
    def line(label, key, unit, digits, paper):
        rows.append((label, *[_fmt(r.get(key), unit, digits) for r in runs], paper))
    line("load at 0.5 mm", "load_at_0.5mm_N", " N", 0, "2438 N")
    line("load at 1.0 mm", "load_at_1.0mm_N", " N", 0, "2723 N / 3223 N")
    line("direction at failure", "buckling_angle_deg", " deg", 0, "234 deg / 128 deg")
    line("max deflection < 3000 N (gauges)", "max_deflection_below_3000N_mm", " mm", 3, "0 (controlled)")
    line("max deflection < 3000 N (beam)", "true_max_deflection_below_3000N_mm", " mm", 3, "-")
    line("voltage range min", "min_voltage_V", " V", 1, "")
    line("voltage range max", "max_voltage_V", " V", 1, "150 V at failure")
    # a fault before the run's end (the controller ramped the stacks to bias): its reason's name
    rows.append(("controller fault", *[(r.get("fault") or "-").split(":")[0] if r else "-" for r in runs],
                 ""))
    widths = [max(len(r[i]) for r in rows) for i in range(5)]
    text = "\n".join("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)) for r in rows)
    head = [f"critical load Fx,cr = {summary['critical_load_N']:.0f} N"]
    own = summary.get("plant_critical_load_N")
    if own is not None and abs(own - summary["critical_load_N"]) > 0.5:
        head[0] += f" (the controller's model); the simulated rig's own: {own:.0f} N"
    if "io_chain" in summary:
        head.append(f"rig I/O chain: {summary['io_chain']['description']}")
    for label, key in (("interpolated", "controlled"), ("paper 500 N", "paper_switching")):
        if "design" in summary.get(key, {}):
            allocation = summary[key].get("allocation")
            head.append(f"design ({label}): {summary[key]['design']}"
                        + (f"; allocation {allocation}" if allocation else ""))
    return "\n".join(head) + "\n" + text


def remove_report(out: Path) -> None:
    """Remove the figures and summaries of a report (never telemetry: a recording is kept)."""
    for name in REPORT_FILES:
        (out / name).unlink(missing_ok=True)


def run(args: argparse.Namespace) -> int:
    cfg, settings = load_experiment_config(args.config)
    if args.no_paper:
        settings = {**settings, "paper_mode": False}
    if args.live is not None:
        check_socket_path(args.live, "--live")
    out = check_dir(args.out, "--out")
    recording = None
    if args.telemetry is not None:          # --telemetry alone: into the report folder
        recording = check_dir(args.telemetry, "--telemetry") if args.telemetry else out
    check_engine(args.engine, recording is not None or args.live is not None)
    tables = experiment_tables(cfg, settings)
    # The folder holds one experiment's report: a previous one's figures and summaries go
    # now, so that a run cut short leaves nothing that could be taken for its result.
    remove_report(out)
    start = time.monotonic()
    with ProgressBar("experiment") as bar, stop_on_signals() as stop:
        summary, traces = run_experiment(cfg, settings, tables, recording,
                                         progress=bar, stop=stop, engine=args.engine, live=args.live)
        bar.close()
    summary["wall_time_s"] = time.monotonic() - start
    table = summary_table(summary)
    try:
        figures = plots.experiment_figures(summary, traces, out)
        write_text(out / "summary.txt", table + "\n")
        write_text(out / "summary.json", json.dumps(summary, indent=1))
    except BaseException:       # a report is whole or absent
        remove_report(out)
        raise
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        print(table)
        print(f"\n{sum(t.plant_s for t in traces.values()):.0f} s of plant time in "
              f"{summary['wall_time_s']:.1f} s ({summary['sim_realtime_factor']:.1f} x real time)")
        recorded = "" if recording is None else (", telemetry_<mode>.btl" if recording == out
                                                 else f"; telemetry_<mode>.btl in {recording}/")
        print(f"report: {out}/ ({', '.join(p.name for p in figures)}, summary.txt, summary.json{recorded})")
    return 0
