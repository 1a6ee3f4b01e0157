"""``beamctl log export|plot``: telemetry files for MATLAB, spreadsheets and eyes."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
from pathlib import Path

import numpy as np

from beamctl.common.outputs import OutputPathError, check_dir, check_file, replacing
from beamctl.config.schema import ConfigError
from beamctl.reports import recordings, report
from beamctl.reports.plots import save
from beamctl.reports.recordings import FORMATS
from beamctl.rt.telemetry import TelemetryReader, read_telemetry


def add_parser(sub) -> None:

    p = sub.add_parser("log", help="telemetry files: export to MDF4/HDF5/.mat/.csv, plot")
    lsub = p.add_subparsers(dest="log_command", metavar="ACTION", required=True)
    e = lsub.add_parser("export", help="convert a telemetry file to MDF4, HDF5, MATLAB .mat or CSV")
    e.add_argument("file", help="telemetry file (.btl)")
    e.add_argument("--to", choices=tuple(FORMATS), required=True,
                   help="mdf (MDF4, .mf4), h5 (HDF5), mat73 (MATLAB v7.3), mat (MATLAB v5), csv")
    e.add_argument("--out", metavar="FILE", help="output file (default: FILE with the format's suffix)")
    e.add_argument("--force", action="store_true", help="replace an existing output file")
    e.add_argument("--json", action="store_true", help="print what was written as one JSON object")
    e.set_defaults(run=run_export)
    pl = lsub.add_parser("plot", help="a run over time (deflection in mm, load, the six voltages, state) "
                         "and its figure 7")
    pl.add_argument("file", help="telemetry file (.btl)")
    pl.add_argument("--out", metavar="DIR", help="folder for the PNG files (default: FILE's name with "
                                                 "-figures, beside it)")
    pl.add_argument("--json", action="store_true", help="print the files written as one JSON object")
    pl.add_argument("dir", nargs="?", help=argparse.SUPPRESS)
    pl.set_defaults(run=run_plot)


def _warn_incomplete(file: str, command: str, header: dict, rows: int) -> None:
    """A warning when the recording ends in an incomplete row (its complete rows are used)."""
    ignored = header["incomplete_row_bytes"]
    if ignored:
        print(f"beamctl log {command}: warning: {file} holds {rows} complete rows and ends in an "
              f"incomplete row ({ignored} bytes ignored: the recording was cut off mid-write)",
              file=sys.stderr)


def _read(file: str, command: str) -> tuple[dict, np.ndarray]:
    """The recording, with the warning of ``_warn_incomplete``."""
    header, rows = read_telemetry(file)
    _warn_incomplete(file, command, header, len(rows))
    return header, rows


def run_export(args: argparse.Namespace) -> int:

    what = "--out" if args.out else "--out (default)"
    out = check_file(args.out or Path(args.file).with_suffix(recordings.FORMATS[args.to]), what)
    if out.resolve() == Path(args.file).resolve():
        raise OutputPathError(what, out, "it is the telemetry file being exported")
    if out.exists() and not args.force:
        raise ConfigError(what, str(out), "a file that is not there yet: one is there already, maybe an "
                                          "earlier export (give another --out, or --force to replace it)")
    recordings.check_format(args.to)                  # refused before any output exists
    with TelemetryReader(args.file) as reader:
        header = reader.header
    try:
        # asammdf prints its read rate to stdout when a block takes over 10 s to load: stdout
        # carries this command's result alone
        with replacing(out) as temp, contextlib.redirect_stdout(io.StringIO()):
            rows = recordings.export(args.file, temp, args.to)
    except OSError as exc:
        raise OutputPathError(what, out, (exc.strerror or str(exc)).lower()) from None
    _warn_incomplete(args.file, "export", header, rows)
    if args.json:
        print(json.dumps({"file": str(out), "format": args.to, "samples": rows,
                          "columns": len(header["columns"])}, indent=1))
    else:
        print(f"wrote {out} ({rows} samples x {len(header['columns'])} columns, {args.to})")
    return 0


def run_plot(args: argparse.Namespace) -> int:

    if args.dir is not None:
        raise ConfigError("DIR", args.dir, "--out DIR (the folder is a flag, as on every command)")
    default = Path(args.file).with_name(Path(args.file).stem + "-figures")
    out_dir = check_dir(args.out or default, "--out" if args.out else "--out (default)")
    run = report.load_run(args.file)
    for warning in report.warnings(run):
        print(f"beamctl log plot: warning: {warning}", file=sys.stderr)
    written = [str(save(fig, out_dir / name)) for name, fig in report.run_figures(run).items()]
    if args.json:
        print(json.dumps({"figures": written}, indent=1))
    else:
        for path in written:
            print(f"wrote {path}")
    return 0
