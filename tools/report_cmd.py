"""``beamctl report RUN``: one self-contained HTML page for a recorded run."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from beamctl.common.outputs import OutputPathError, check_file
from beamctl.reports import report


def add_parser(sub) -> None:
    p = sub.add_parser("report", help="one HTML page for a recorded run: figures, settings, faults, "
                                      "figures of merit",
                       description="Read a telemetry file (.btl, from `beamctl run` or `beamctl experiment "
                                   "--telemetry`) and write one self-contained HTML page: the run over time "
                                   "and its figure 7 (embedded PNG), the settings it was recorded with, its "
                                   "state changes and faults, and its figures of merit.")
    p.add_argument("recording", metavar="RUN", help="telemetry file (.btl)")
    p.add_argument("--out", metavar="FILE.html", help="the page (default: RUN with the suffix .html)")
    p.add_argument("--json", action="store_true", help="print the page's path and the figures of merit as "
                                                       "one JSON object")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:

    what = "--out" if args.out else "--out (default)"
    out = check_file(args.out or Path(args.recording).with_suffix(".html"), what)
    if out.resolve() == Path(args.recording).resolve():
        raise OutputPathError(what, out, "it is the recording being reported")
    page, merit = report.write_report(args.recording, out, warn=lambda text: print(
        f"beamctl report: warning: {text}", file=sys.stderr))
    if args.json:
        print(json.dumps({"page": str(page), "merit": merit}, indent=1))
        return 0
    faults = ", ".join(merit["faults"]) or "none"
    print(f"wrote {page} ({merit['samples']} samples, {merit['duration_s']:.2f} s, "
          f"ended {merit['end_state']}, faults: {faults})")
    return 0
