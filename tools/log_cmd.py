"""``beamctl log export|plot``: telemetry files for MATLAB, spreadsheets and eyes."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from beamctl.rt.telemetry import TelemetryError, export, read_telemetry


def add_parser(sub) -> None:
    p = sub.add_parser("log", help="telemetry files: export to .mat/.csv, plot")
    lsub = p.add_subparsers(dest="log_command", metavar="ACTION", required=True)
    e = lsub.add_parser("export", help="convert a telemetry file to MATLAB .mat or CSV")
    e.add_argument("file", help="telemetry file (.btl)")
    e.add_argument("--to", choices=("mat", "csv"), required=True, help="output format")
    e.add_argument("--out", metavar="FILE", help="output file (default: FILE with the new suffix)")
    e.set_defaults(run=run_export)
    pl = lsub.add_parser("plot", help="figure-7 style plots of a run")
    pl.add_argument("file", help="telemetry file (.btl)")
    pl.add_argument("dir", help="directory for the PNG files")
    pl.set_defaults(run=run_plot)


def run_export(args: argparse.Namespace) -> int:
    out = Path(args.out) if args.out else Path(args.file).with_suffix("." + args.to)
    try:
        header, rows = read_telemetry(args.file)
        path = export(args.file, out, args.to)
    except TelemetryError as exc:
        print(f"beamctl log export: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {path} ({len(rows)} samples x {len(header['columns'])} columns)")
    return 0


def run_plot(args: argparse.Namespace) -> int:
    from beamctl.tools import plots

    try:
        header, rows = read_telemetry(args.file)
    except TelemetryError as exc:
        print(f"beamctl log plot: error: {exc}", file=sys.stderr)
        return 2
    for path in plots.telemetry_figures(header, rows, Path(args.dir)):
        print(f"wrote {path}")
    return 0
