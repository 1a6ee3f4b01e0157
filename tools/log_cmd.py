"""``beamctl log export|plot``: telemetry files for MATLAB, spreadsheets and eyes."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from beamctl.rt.telemetry import export, read_telemetry
from beamctl.tools.outputs import OutputPathError, check_dir, check_file, replacing


def add_parser(sub) -> None:
    p = sub.add_parser("log", help="telemetry files: export to .mat/.csv, plot")
    lsub = p.add_subparsers(dest="log_command", metavar="ACTION", required=True)
    e = lsub.add_parser("export", help="convert a telemetry file to MATLAB .mat or CSV")
    e.add_argument("file", help="telemetry file (.btl)")
    e.add_argument("--to", choices=("mat", "csv"), required=True, help="output format")
    e.add_argument("--out", metavar="FILE", help="output file (default: FILE with the new suffix)")
    e.set_defaults(run=run_export)
    pl = lsub.add_parser("plot", help="a run over time (deflection in mm, load, the six voltages, state) "
                         "and its figure 7")
    pl.add_argument("file", help="telemetry file (.btl)")
    pl.add_argument("dir", help="directory for the PNG files")
    pl.set_defaults(run=run_plot)


def _read(file: str, command: str) -> tuple[dict, np.ndarray]:
    """The recording; a warning when it ends in an incomplete row (its complete rows are used)."""
    header, rows = read_telemetry(file)
    ignored = header["incomplete_row_bytes"]
    if ignored:
        print(f"beamctl log {command}: warning: {file} holds {len(rows)} complete rows and ends in an "
              f"incomplete row ({ignored} bytes ignored: the recording was cut off mid-write)",
              file=sys.stderr)
    return header, rows


def run_export(args: argparse.Namespace) -> int:
    what = "--out" if args.out else "--out (default)"
    out = check_file(args.out or Path(args.file).with_suffix("." + args.to), what)
    if out.resolve() == Path(args.file).resolve():
        raise OutputPathError(what, out, "it is the telemetry file being exported")
    header, rows = _read(args.file, "export")
    with replacing(out) as temp:
        export(header, rows, temp, args.to)
    print(f"wrote {out} ({len(rows)} samples x {len(header['columns'])} columns)")
    return 0


def run_plot(args: argparse.Namespace) -> int:
    from beamctl.tools import report
    from beamctl.tools.plots import save

    out_dir = check_dir(args.dir, "DIR")
    run = report.load_run(args.file)
    for warning in report.warnings(run):
        print(f"beamctl log plot: warning: {warning}", file=sys.stderr)
    for name, fig in report.run_figures(run).items():
        print(f"wrote {save(fig, out_dir / name)}")
    return 0
