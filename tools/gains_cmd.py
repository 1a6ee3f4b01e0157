"""``beamctl gains build|check|show``: offline gain generation and inspection."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from beamctl.assembly.run import load_model_file
from beamctl.common.outputs import check_dir, check_file, replacing, write_text
from beamctl.config.schema import ConfigError
from beamctl.gains.build import build_lqg_table, build_table, closed_loop_checks, with_robust
from beamctl.gains.defaults import DESIGNS, default_table_path, paper_table_path
from beamctl.gains.ridethrough import REFERENCE
from beamctl.gains.robust import (
    DEFAULT_BOX,
    box_from_dict,
    describe,
    load_box,
    rig_of,
    robust_check,
    robust_text,
    table_record,
)
from beamctl.gains.table import GainTable, changed_file_message, load_table, write_table
from beamctl.models import build_model
from beamctl.reports import plots
from beamctl.simulation import stall
from beamctl.simulation.experiment import UNLIMITED_STACKS, rig_scenario
from beamctl.tools import argtypes
from beamctl.tools.progress import ProgressBar


def parse_grid(text: str) -> np.ndarray:
    """``start:stop:step`` in N, stop included."""
    parts = text.split(":")
    try:
        start, stop, step = (float(p) for p in parts)
    except ValueError:
        raise ConfigError("--grid", text, "START:STOP:STEP in N, e.g. 0:4000:50") from None
    if not (np.isfinite([start, stop, step]).all() and step > 0 and stop >= start >= 0):
        raise ConfigError("--grid", text, "0 <= START <= STOP and STEP > 0")
    count = int(np.floor((stop - start) / step + 1e-9)) + 1
    if count > 10_000:
        raise ConfigError("--grid", text, f"at most 10000 grid points (this is {count})")
    return start + step * np.arange(count)


def add_parser(sub) -> None:
    p = sub.add_parser("gains", help="gain tables (scheduled compensators): build, check, show")
    gsub = p.add_subparsers(dest="gains_command", metavar="ACTION", required=True)

    b = gsub.add_parser("build", help="design the controller over a load grid, check the closed loop "
                        "on the nominal model and over the uncertainty box")
    b.add_argument("--config", metavar="F",
                   help="model parameters (YAML) over the paper's Table 1, or a configuration "
                   "with a model: section (a rig's service config, the output of `beamctl model fit`)")
    b.add_argument("--design", choices=DESIGNS, default="lqg",
                   help="lqg: the delay-aware LQG at 6000 Hz (the shipped default); integral-lqr: the "
                        "paper's design at 2500 Hz")
    b.add_argument("--grid", metavar="START:STOP:STEP",
                   help="load grid in N (default lqg 0:4000:100, integral-lqr 0:4000:50, paper mode "
                        "0:3500:500)")
    b.add_argument("--mode", choices=("interpolate", "paper"), default="interpolate",
                   help="schedule: linear interpolation, or the paper's stepwise switching (integral-lqr)")
    b.add_argument("--json", action="store_true",
                   help="print what was built (grid, check, file, the robust check) as one JSON object; the "
                        "build's lines go to stderr")
    b.add_argument("--no-robust", action="store_true",
                   help="skip the robust check of the built table (minutes) and its worst case")
    b.add_argument("--box", metavar="FILE", help="the uncertainty box of the robust check (YAML, a box: "
                   "section; default: the README's box B)")
    b.add_argument("--out", metavar="FILE", default="gain-table.yaml",
                   help="where to write the table (default: gain-table.yaml here)")
    b.add_argument("--force", action="store_true",
                   help="write the table even if the closed loop is unstable somewhere (marked forced)")
    b.set_defaults(run=run_build)

    c = gsub.add_parser("check", help="the discrete closed loop at every grid point and midpoint; with "
                        "--robust, the worst rig of the uncertainty box, searched for")
    c.add_argument("file", nargs="*", help="gain table(s) (default: the shipped default and the paper's "
                   "design, side by side; with --robust the shipped default)")
    c.add_argument("--robust", action="store_true",
                   help="search the uncertainty box for the rig whose loop goes unstable at the lowest "
                        "fraction of its own critical load (minutes, both cores)")
    c.add_argument("--record", action="store_true",
                   help="with --robust: write the result into the table file (`gains show` and `beamctl "
                        "config check` report it; the file's content hash is renewed)")
    c.add_argument("--box", metavar="FILE", help="the uncertainty box (YAML, a box: section; default: "
                   "box B, docs/pages/robustness.md)")
    c.add_argument("--seed", type=argtypes.integer(low=0, high=2**32 - 1), metavar="N",
                   help="the search's seed (default: the box's, 1): the same seed finds the same rigs")
    c.add_argument("--workers", type=argtypes.number(low=1, integer=True), metavar="N",
                   help="processes for --robust here (default: 2, or 1 on a single core)")
    c.add_argument("--scheduler", metavar="ADDRESS",
                   help="spread --robust over an existing Dask cluster, e.g. tcp://10.0.0.5:8786 "
                        "(pip install 'beamctl[study]' there and here)")
    c.add_argument("--worst-rig", metavar="FILE", dest="worst_rig",
                   help="write the worst rig found as a `beamctl experiment --config` scenario (with one "
                        "table: its stacks scaled so that their force does not limit)")
    c.add_argument("--json", action="store_true", help="print one JSON object (progress stays on stderr)")
    c.epilog = ("exit status 0: every table stable at every check point, as built, and with --robust its "
                "worst rig held to its own critical load; 1: not so; 2: bad input; 130: Ctrl-C")
    c.set_defaults(run=run_check)

    t = gsub.add_parser("stalls", help="stalls in the time domain: at each load, the live ride-through "
                        "limit and the shortest stall the simulated rig loses (nominal and the robust "
                        "check's worst rig; about 10 s a load)")
    t.add_argument("file", nargs="?", help="gain table (default: the shipped gains/default.yaml)")
    t.add_argument("--loads", metavar="N,N,...", type=argtypes.number_list(low=0.0),
                   help="loads in N (default: 2000 N to 100 N below the table's top, every 200 N, "
                        "and 3300 N)")
    t.add_argument("--rig", choices=("nominal", "worst", "both"), default="both",
                   help="the rig(s): nominal, the robust check's worst (recorded in the table), or both")
    t.add_argument("--plot", metavar="FILE", help="write the limit and the edge versus load as PNG")
    t.add_argument("--json", action="store_true", help="print one JSON object (progress stays on stderr)")
    t.epilog = ("exit status 0: at every load where the rig is held, a stall of the live limit survived, "
                "and the limit below the edge; "
                "1: not so; 2: bad input")
    t.set_defaults(run=run_stalls)

    s = gsub.add_parser("show", help="gains versus load")
    s.add_argument("file", nargs="?", help="gain table (default: the shipped gains/default.yaml)")
    s.add_argument("--plot", metavar="DIR", help="write gains versus load as PNG into DIR")
    s.add_argument("--json", action="store_true",
                   help="print the table's description (design, check, hashes, robust check, gains by load) "
                        "as one JSON object")
    s.set_defaults(run=run_show)


def _load(file: str | None, action: str) -> GainTable:
    """The table as it is (changed, unchecked or forced), for inspection; a changed one is
    reported on stderr."""
    path = file or default_table_path()
    table = load_table(path, verify=False)
    if not table.intact:
        print(f"beamctl gains {action}: warning: {path}: the content does not match its SHA-256: "
              f"{changed_file_message(path, table.design.kind, table.schedule.mode)}; `beamctl run` refuses "
              "it", file=sys.stderr)
    return table


def run_build(args: argparse.Namespace) -> int:
    status = _build(args)
    if args.json:
        print(json.dumps(args.build_report, indent=1))
    return status


def _build(args: argparse.Namespace) -> int:
    """The build; its lines go to stdout, or with --json to stderr (and ``args.build_report``
    holds what the JSON says)."""
    out_stream = sys.stderr if args.json else sys.stdout

    def say(text: str) -> None:
        print(text, file=out_stream, flush=True)

    report: dict = {}
    args.build_report = report
    grid = parse_grid(args.grid) if args.grid else None
    params = load_model_file(args.config)
    out = check_file(args.out, "--out")
    if args.box and args.no_robust:
        raise ConfigError("--box", args.box, "no --no-robust (the box is what the robust check covers)")

    box = load_box(args.box, params) if args.box else DEFAULT_BOX      # refused before minutes of work
    model = build_model(params)
    if args.design == "lqg" and args.mode != "interpolate":
        raise ConfigError("--mode", args.mode, "'interpolate' with --design lqg (the paper's stepwise "
                          "switching belongs to --design integral-lqr)")
    with ProgressBar("gains build") as bar:
        if args.design == "lqg":
            table = build_lqg_table(model, grid, force=args.force, progress=bar)
        else:
            table = build_table(model, grid, mode=args.mode, force=args.force, progress=bar)
        elapsed = bar.close()
    worst = max(table.checks, key=lambda c: c.spectral_radius)
    report.update(file=str(out), design=table.design.kind,
                  loads_N=[float(table.loads_n[0]), float(table.loads_n[-1])], grid_points=len(table.loads_n),
                  checks=len(table.checks), all_stable=table.all_stable,
                  largest_spectral_radius=worst.spectral_radius, at_N=worst.load_n, written=False,
                  robust=None)
    say(f"{len(table.loads_n)} grid points {table.loads_n[0]:g}..{table.loads_n[-1]:g} N, "
          f"mode {table.schedule.mode}, {len(table.checks)} closed-loop checks in {elapsed:.1f} s")
    say(f"largest spectral radius {worst.spectral_radius:.6f} at {worst.load_n:g} N; "
          f"least damping {min(c.min_damping for c in table.checks):.4g}")
    if not table.all_stable:
        unstable = [c.load_n for c in table.checks if not c.stable]
        more = " ..." if len(unstable) > 8 else ""
        say(f"UNSTABLE at {len(unstable)} check points: {unstable[:8]}{more}")
        if not args.force:
            say("table not written (use --force to write it, marked as forced)")
            return 1
    with replacing(out) as temp:      # the service never reads half a table
        write_table(table, temp)
    report["written"] = True
    say(f"wrote {out}{' (forced: unstable points)' if table.forced and not table.all_stable else ''}")
    if args.no_robust:
        say("robust check skipped (--no-robust): how far the table holds a rig that differs from the "
              f"model is unknown; run `beamctl gains check --robust --record {out}`")
    elif table.all_stable:
        print(f"robust check: searching {args.box or 'box B'} for its worst rig ({box.budget} rigs at "
              "most: minutes, 2 to 4 on 2 idle cores, the time left shown below; --no-robust skips it)",
              file=sys.stderr, flush=True)
        result = _robust(table, box, None)
        say(_robust_line(result))
        with ProgressBar("ride-through over the worst rig") as bar:
            table = with_robust(model, table, table_record(result, args.box or "box B"), bar)
            bar.close()
        report["robust"] = table.robust
        with replacing(out) as temp:      # the table keeps its robust check (`gains show`, `config check`)
            write_table(table, temp)
        say(f"recorded the robust check in {out}")
        if result.worst_ratio < 1.0:
            say("NOT HELD: a rig of the box goes unstable below its own critical load (exit status 1)")
            return 1
    return 0


def _robust(table: GainTable, box, workers: int | None, client=None):
    """The robust check with its progress on stderr, here or on the Dask cluster of ``client``."""

    with ProgressBar("robust check") as bar:
        result = robust_check(table, box, workers=workers, progress=bar, client=client)
        bar.close()
    if result.refused:
        print(f"robust check: {result.refused_text()}", file=sys.stderr)
    return result


def _dask_client(address: str):
    try:
        from distributed import Client
    except ImportError:
        raise ConfigError("--scheduler", address, "dask.distributed installed: pip install "
                          "'beamctl[study]'") from None
    try:
        return Client(address, timeout=10)
    except Exception as exc:        # noqa: BLE001 - whatever answers there, it is no scheduler of ours
        raise ConfigError("--scheduler", address, "the address of a running Dask scheduler, e.g. "
                          f"tcp://10.0.0.5:8786 ({type(exc).__name__}: {str(exc)[:120]})") from None


def _robust_line(result) -> str:
    w = result.worst
    onset = "stable to the end of the table" if w.censored else f"unstable from {w.onset_n:.0f} N"
    bound = " (censored: a lower bound)" if w.censored else ""
    return (f"robust check over the box ({result.count} rigs searched in {result.elapsed_s:.0f} s): worst "
            f"onset / own Fx,cr = {result.worst_ratio:.4f}{bound} ({onset} of its {w.critical_load_n:.0f} N)")


def run_check(args: argparse.Namespace) -> int:
    # no file: the shipped default and the paper's design side by side; with --robust the shipped
    # default alone (the paper's design is known to lose rigs of box B: README)
    files = args.file or ([str(default_table_path())] if args.robust
                          else [str(default_table_path()), str(paper_table_path())])
    for flag, value in (("--box", args.box), ("--seed", args.seed), ("--scheduler", args.scheduler),
                        ("--worst-rig", args.worst_rig), ("--workers", args.workers)):
        if value is not None and not args.robust:
            raise ConfigError(flag, value, "--robust as well (it sets how the robust check runs)")
    if args.record and not args.robust:
        raise ConfigError("--record", True, "--robust as well (it records the robust check's result)")
    shipped = {default_table_path().resolve(), paper_table_path().resolve()}
    if args.record and (not args.file or any(Path(f).resolve() in shipped for f in args.file)):
        raise ConfigError("--record", True, "a table file of your own (the shipped tables are not changed)")
    if args.worst_rig and len(files) > 1:
        raise ConfigError("--worst-rig", args.worst_rig, "one gain table (the scenario runs that table)")
    if args.scheduler and args.workers:
        raise ConfigError("--workers", args.workers, "no --scheduler (the cluster has its own workers)")
    worst_rig = check_file(args.worst_rig, "--worst-rig") if args.worst_rig is not None else None
    tables = [(path, _load(path, "check")) for path in files]
    changed = [path for path, table in tables if not table.intact]
    if args.record and changed:
        raise ConfigError("--record", changed[0], "a table whose content matches its SHA-256 (this one was "
                          "changed after it was built: rebuild it)")
    box = None
    if args.robust:

        box = load_box(args.box, tables[0][1].model_parameters) if args.box else DEFAULT_BOX
        if args.seed is not None:
            box = replace(box, seed=args.seed)
    client = _dask_client(args.scheduler) if args.scheduler else None      # before minutes of work
    try:
        reports = [_check_one(path, table, box, args, client) for path, table in tables]
    finally:
        if client is not None:
            client.close()
    if worst_rig is not None:
        _write_worst_rig(worst_rig, *tables[0], reports[0]["robust"])
    if args.json:
        print(json.dumps(reports[0] if len(reports) == 1 else {"tables": reports}, indent=1))
    elif len(reports) > 1:
        _side_by_side(reports)
    ok = all(r["all_stable"] and r["sha256_matches"] for r in reports)
    held = all(r["robust"]["worst_ratio"] >= 1.0 for r in reports if "robust" in r)
    return 0 if ok and held else 1


def _write_worst_rig(out, path: str, table: GainTable, robust: dict) -> None:
    """The worst rig as a scenario of ``beamctl experiment`` (simulation/experiment.rig_scenario)."""
    import yaml


    rig = rig_of(table, box_from_dict(robust["box"], table.model_parameters), robust["worst_rig"])
    scenario = rig_scenario(table, str(Path(path).resolve()), rig)
    onset = ("stable to the end of the table" if robust["censored"]
             else f"unstable from {robust['onset_N']:.0f} N")
    header = (f"# The worst rig the robust check of {path} found (seed {robust['box']['seed']}): onset / "
              f"own Fx,cr = {robust['worst_ratio']:.4f},\n# {onset} of its own Fx,cr "
              f"{robust['critical_load_N']:.0f} N (pole at {robust['pole_hz']:.0f} Hz). Its stacks give "
              f"{UNLIMITED_STACKS:g} times the shipped force per volt,\n# believed and actual alike (the "
              "rig's stack gain kept), so that force does not limit the run.\n"
              "# Run: beamctl experiment --config THIS_FILE --no-paper\n")
    write_text(out, header + yaml.safe_dump(scenario, sort_keys=False))


def _check_one(path: str, table: GainTable, box, args: argparse.Namespace, client=None) -> dict:
    """Nominal check (and robust check with a box) of one table; printed unless --json."""
    model = build_model(table.model_parameters)
    with ProgressBar(f"gains check {path}") as bar:
        checks = closed_loop_checks(model, table, progress=bar)
        bar.close()
    all_stable = all(c.stable for c in checks)
    report = {
        "file": path, "design": design_summary(table),
        "points": [{"load_N": c.load_n, "spectral_radius": c.spectral_radius, "stable": c.stable,
                    "min_damping": c.min_damping, "gain_load_N": c.gain_load_n} for c in checks],
        "all_stable": all_stable, "sha256_matches": table.intact}
    result = _robust(table, box, args.workers, client) if box is not None else None
    if result is not None:
        report.update(result.to_dict(table))
        if args.record:
            with ProgressBar("ride-through over the worst rig") as bar:
                recorded = with_robust(model, table, table_record(result, args.box or "box B"), bar)
                bar.close()
            with replacing(Path(path)) as temp:
                write_table(recorded, temp)
            report["recorded"] = path
            print(f"recorded the robust check in {path}", file=sys.stderr)
    if args.json:
        return report
    print(f"gain table {path}: {report['design']}")
    if len(args.file) == 1:           # one table asked for: every load
        print(f"{'load N':>8} {'spectral radius':>16} {'min damping':>12}  stable")
        for c in checks:
            gain = "" if c.gain_load_n is None else f"  (gain of {c.gain_load_n:g} N)"
            print(f"{c.load_n:8.1f} {c.spectral_radius:16.6f} {c.min_damping:12.5f}  "
                  f"{'yes' if c.stable else 'NO'}{gain}")
    worst = max(checks, key=lambda c: c.spectral_radius)
    print(f"nominal: all stable: {'yes' if all_stable else 'NO'} ({len(checks)} loads, largest spectral "
          f"radius {worst.spectral_radius:.6f} at {worst.load_n:g} N)")
    if result is not None:
        _print_robust(result)
    if table.intact:
        print("content SHA-256: matches (the table is as it was built)")
    else:
        print("content SHA-256: DOES NOT MATCH (the file was changed after it was built; "
              "`beamctl run` refuses it)")
    print()
    return report


def design_summary(table: GainTable) -> str:
    d = table.design
    return f"{d.kind}, {d.sample_rate_hz:g} Hz, assumes {d.io.describe()}"


def _print_robust(result) -> None:

    w = result.worst
    print(_robust_line(result).replace("robust check over the box", "robust"))
    phases = result.phases
    print(f"  search: seed {result.box.seed}, {phases.get('global', 0)} rigs of differential evolution, "
          f"{phases.get('refine', 0)} of local refinement, {phases.get('verify', 0)} walked again from the "
          "table's first load at the fine steps")
    print(f"  worst rig: {describe(w.values, result.box)}")
    if w.censored:
        print(f"  stable to the end of the table; the least stable pole there |z| = "
              f"{w.spectral_radius:.5f} at {w.pole_hz:.0f} Hz")
    else:
        print(f"  stable to {w.stable_to_n:.1f} N, unstable at {w.onset_n:.1f} N (|z| = "
              f"{w.spectral_radius:.5f}, {w.pole_hz:.0f} Hz); its own Fx,cr {w.critical_load_n:.1f} N")
    if result.worst_ratio < 1.0:
        print("  NOT HELD: this rig of the box goes unstable below its own critical load (exit status 1)")
    print(f"  {'ratio':>7} {'onset N':>8} {'own Fx,cr N':>11} {'pole Hz':>8}  rig")
    for r in sorted(result.verified, key=lambda r: r.ratio):
        onset = "-" if r.censored else f"{r.onset_n:.0f}"
        print(f"  {r.ratio:7.4f} {onset:>8} {r.critical_load_n:11.0f} {r.pole_hz:8.0f}  "
              f"{describe(r.values, result.box)}")


def _side_by_side(reports: list[dict]) -> None:
    print("side by side:")
    print(f"  {'table':<40} {'nominal':>8} {'worst ratio over box':>21}")
    for r in reports:
        robust = f"{r['robust']['worst_ratio']:.4f}" if "robust" in r else "(--robust)"
        print(f"  {r['design'][:40]:<40} {'stable' if r['all_stable'] else 'UNSTABLE':>8} {robust:>21}")


def _ride_through_json(table: GainTable) -> dict | None:
    """The ride-through per grid load at the reference operating point (gains/ridethrough.py)."""
    rt = table.ride_through
    if rt is None:
        return None
    rate = table.design.sample_rate_hz
    rows = rt.reference_limits(table.loads_n)
    return {"criterion": rt.criterion, "confidence_sigma": rt.confidence_sigma, "rigs": list(rt.rigs),
            "reference": dict(REFERENCE), "cap_ms": 1e3 * rt.gap_cap_samples / rate,
            "per_load_ms": {f"{load:g}": 1e3 * n / rate
                            for load, (n, _) in zip(table.loads_n, rows, strict=True)}}


def run_show(args: argparse.Namespace) -> int:
    plot_dir = check_dir(args.plot, "--plot") if args.plot else None
    table = _load(args.file, "show")
    d, s = table.design, table.schedule
    comp = table.compensator
    if args.json:
        written = str(plots.gains_vs_load(table, plot_dir / "gains_vs_load.png")) if plot_dir else None
        print(json.dumps({
            "file": str(args.file or default_table_path()), "created": table.created,
            "tool_version": table.tool_version, "model_sha256": table.model_sha256, "sha256": table.sha256,
            "content_matches": table.intact, "design": d.kind, "sample_rate_hz": d.sample_rate_hz,
            "io": d.io.to_dict(), "schedule": s.mode, "loads_N": [float(x) for x in table.loads_n],
            "compensator_states": comp.n_states, "all_stable": table.all_stable, "forced": table.forced,
            "robust": table.robust, "plot": written, "ride_through": _ride_through_json(table),
            "gains_A_y": {"unit": "D in N per unit strain, Ki in N per unit of xi (the summed T H y)",
                          "D": comp.d[:, 0, :].tolist(), "Ki": comp.ki[:, 0, :].tolist()}}, indent=1))
        return 0
    print(f"gain table: {args.file or default_table_path()}")
    print(f"created {table.created} by beamctl {table.tool_version}; "
          f"model sha256 {table.model_sha256[:16]}...")
    print(f"design {d.kind} for {d.sample_rate_hz:g} Hz, assuming the I/O chain: {d.io.describe()}")
    print(f"compensator: {comp.n_states} states over {comp.n_points} grid points; schedule {s.mode}, "
          f"load filter {s.load_filter_hz:g} Hz, hysteresis {s.hysteresis_n:g} N")
    if d.kind == "integral-lqr":
        print(f"velocity filter cut-off {d.velocity_cutoff_hz:g} Hz")
        print(f"Q diagonal {', '.join(f'{x:.3g}' for x in d.weights.q)}")
        print(f"R diagonal {', '.join(f'{x:.3g}' for x in d.weights.r)}")
    else:
        print(f"design parameters: {json.dumps(d.parameters, sort_keys=True)}")
    check = "all stable" if table.all_stable else "UNSTABLE points" if table.checked else "none"
    recorded = " (as recorded before the change)" if not table.intact else ""
    print(f"check{recorded}: {check}{' (forced)' if table.forced else ''}")
    print(f"content sha256: {'matches' if table.intact else 'DOES NOT MATCH (changed after it was built)'}")
    print(f"robust check: {robust_text(table.robust)}")
    rt = table.ride_through
    if rt is not None:
        print(f"ride-through: {rt.describe(table.loads_n, d.sample_rate_hz)}")
        print(f"  {rt.reference_text(table.loads_n, d.sample_rate_hz)}")
    else:
        print("ride-through: not analysed by this version (fixed limits: 5 samples, half a period); rebuild "
              "the table (`beamctl gains build`)")
    print()
    step = max(1, len(table.loads_n) // 16)
    if table.gains is not None:
        print("gains of support A, y direction (row Fay,A), signed, by state: N per modal unit (q), N s per "
              "modal unit (dq), N per modal unit s (iq):")
        names = ["q1y", "q2y", "dq1y", "dq2y", "iq1y", "iq2y"]
        cols = [0, 2, 4, 6, 8, 10]
        rows = table.gains[:, 0, :]
    else:
        print("compensator gains of support A, y direction (row Fay,A), signed: D in N per unit strain, "
              "by gauge; Ki in N per unit of xi (the summed T H y), by channel:")
        names = ["D y1", "D y2", "Ki y1", "Ki y2"]
        cols = [0, 2, 4, 6]
        rows = np.concatenate([comp.d[:, 0, :], comp.ki[:, 0, :]], axis=1)
    print(f"{'load N':>8} " + " ".join(f"{n:>11}" for n in names))
    for i in range(0, len(table.loads_n), step):
        print(f"{table.loads_n[i]:8.0f} " + " ".join(f"{rows[i, c]:11.4g}" for c in cols))
    if plot_dir:

        path = plots.gains_vs_load(table, plot_dir / "gains_vs_load.png")
        print(f"\nwrote {path}")
    return 0


def run_stalls(args: argparse.Namespace) -> int:
    """The time-domain survival edge against the live limit (simulation/stall.py)."""
    plot = check_file(args.plot, "--plot") if args.plot else None
    table = load_table(args.file or default_table_path())
    if table.ride_through is None:
        raise ConfigError("file", args.file or default_table_path(),
                          "a table with a ride-through analysis (rebuild it: `beamctl gains build`)")
    top = float(table.loads_n[-1]) - 100.0
    beyond = [x for x in args.loads or () if x > top]
    if beyond:
        raise ConfigError("--loads", ",".join(f"{x:g}" for x in beyond),
                          f"loads up to {top:g} N (100 N below the table's top: the load's noise and filter "
                          "stay in its range)")
    loads = sorted(set(args.loads)) if args.loads else sorted(
        {*np.arange(2000.0, top + 1e-9, 200.0).tolist(), 3300.0, top})
    rigs = {}
    if args.rig in ("nominal", "both"):
        rigs["nominal"] = stall.StallRig(table)
    if args.rig in ("worst", "both"):
        worst = stall.worst_rig(table)
        if worst is None:
            raise ConfigError("--rig", args.rig, "a table that records its robust check's worst rig "
                              "(`beamctl gains check --robust --record`)")
        rigs["worst rig"] = stall.StallRig(table, rig=worst)
    curves = {}
    for name, rig in rigs.items():
        with ProgressBar(f"stalls, {name}") as bar:
            curves[name] = stall.edges(rig, loads, bar)
    ok = all(r.limit_samples >= 1 and (r.edge_samples > r.limit_samples or r.edge_samples > r.cap_samples)
             for rows in curves.values() for r in rows if r.held)
    if plot:
        stall.edge_figure(curves, plot)
    if args.json:
        print(json.dumps({name: [{"load_N": r.load_n, "limit_ms": 1e3 * r.limit_samples / r.rate_hz,
                                  "let_go_ms": 1e3 * r.let_go_samples / r.rate_hz,
                                  "edge_ms": 1e3 * r.edge_samples / r.rate_hz,
                                  "edge_beyond_cap": r.edge_samples > r.cap_samples,
                                  "limit_samples": r.limit_samples, "edge_samples": r.edge_samples,
                                  "rate_hz": r.rate_hz, "held_without_stall": r.held} for r in rows]
                          for name, rows in curves.items()}, indent=1))
        return 0 if ok else 1
    for name, rows in curves.items():
        print(f"{name}: load N, live limit ms, let-go ms (a longer stall faults), survival edge ms "
              "(the shortest stall lost), edge / limit")
        for r in rows:
            if not r.held:
                print(f"  {r.load_n:7.0f}  not held without a stall (beyond the loop's stability onset)")
                continue
            limit, edge = 1e3 * r.limit_samples / r.rate_hz, 1e3 * r.edge_samples / r.rate_hz
            beyond = r.edge_samples > r.cap_samples
            ratio = "-" if beyond or r.limit_samples <= 0 else f"{r.edge_samples / r.limit_samples:.2f}"
            let_go = 1e3 * r.let_go_samples / r.rate_hz
            mark = ">" if beyond else " "
            print(f"  {r.load_n:7.0f} {limit:8.1f} {let_go:8.1f} {mark}{edge:8.1f} {ratio:>6}")
    if plot:
        print(f"wrote {plot}")
    return 0 if ok else 1
