"""``beamctl commission``: from a rig nobody has characterised to a gain table that holds it
(commission/workflow.py): identify, fit, the calibrated box, build and check, the simulated
experiment, the report; resumable."""

from __future__ import annotations

import argparse
import json
import sys

from beamctl.commission.workflow import STEPS, Commission, CommissionError, CommissionSettings, grid_of
from beamctl.common.signals import stop_on_signals
from beamctl.config.schema import ConfigError
from beamctl.models.fit import DEFAULT_PARAMETERS
from beamctl.tools import argtypes
from beamctl.tools.progress import ProgressBar


def add_parser(sub) -> None:
    p = sub.add_parser(
        "commission", help="identify a rig, fit the model, design and check a table, try it on the rig",
        description="Runs, into --out, the steps " + ", ".join(STEPS) + ": frequency responses at --loads "
                    "(as beamctl identify), the model fitted to them with 95 % intervals (as beamctl "
                    "model fit), the stacks' use up to and past the fitted critical load predicted from the "
                    "measurements' static strains (a rig whose eccentric load or bow needs more than the "
                    "stacks give is said to be so here), the uncertainty box calibrated from the fit, the "
                    "gain table designed on "
                    "the fitted model and its robust check over that box, the simulated experiment on the "
                    "rig with that table (a real rig, hal.backend can: stops before it, saying what to do "
                    "next), and report.html. Progress goes to stderr. Ctrl-C ends it with exit 130 and "
                    "nothing half-written; run again with the same --config, --out and settings to go on "
                    "where it stopped.")
    p.add_argument("--config", metavar="RIG.yaml", required=True,
                   help="the rig's service configuration (its hal backend; for the simulated rig, its "
                        "plant section is the rig)")
    p.add_argument("--out", metavar="DIR", required=True, help="the commissioning folder")
    p.add_argument("--loads", default="1000,2000", metavar="N,N,...", help="loads in N to identify at "
                   "(default 1000,2000; two or more apart predict the stacks' use at Fx,cr within about "
                   "2 %%, one only roughly)")
    p.add_argument("--averages", type=argtypes.number(low=3, integer=True), default=8, metavar="A",
                   help="averaged excitation periods per input (default 8)")
    p.add_argument("--params", default=",".join(DEFAULT_PARAMETERS), metavar="P,P,...",
                   help=f"parameters to fit (default {','.join(DEFAULT_PARAMETERS)})")
    p.add_argument("--grid", metavar="START:STOP:STEP", help="the table's load grid in N (default: every "
                   "100 N to 1.2 x the fitted model's critical load, at most 4000 N)")
    p.add_argument("--no-robust", action="store_true", help="leave out the robust check (minutes)")
    p.add_argument("--json", action="store_true", help="print the folder's summary as one JSON object")
    p.set_defaults(run=run)


class _Steps:
    """A progress bar per step, on stderr, and the steps' lines between them."""

    def __init__(self) -> None:
        self.bar: ProgressBar | None = None

    def log(self, line: str) -> None:
        self.close()
        print(f"commission: {line}", file=sys.stderr, flush=True)
        if line.endswith("..."):
            self.bar = ProgressBar(line.split(" ")[2])

    def __call__(self, done: int, total: int, label: str = "") -> None:
        if self.bar is not None:
            self.bar(done, total, label)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _loads(text: str) -> tuple[float, ...]:
    try:
        loads = tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        loads = ()
    if not loads or not all(0.0 <= x < 1e5 for x in loads) or len(set(loads)) != len(loads):
        raise ConfigError("--loads", text, "distinct axial loads in N, comma-separated, e.g. 1000,2000")
    return loads


def run(args: argparse.Namespace) -> int:
    settings = CommissionSettings(loads_n=_loads(args.loads), averages=int(args.averages),
                                  parameters=tuple(p.strip() for p in args.params.split(",") if p.strip()),
                                  robust=not args.no_robust, grid_n=grid_of(args.grid) if args.grid else None)
    steps = _Steps()
    try:
        with stop_on_signals() as stop:     # Ctrl-C: the rig's stacks ramp to bias, the step ends
            commission = Commission(args.config, args.out, settings, log=steps.log, progress=steps,
                                    stop=stop)
            summary = commission.run()
    except CommissionError as exc:
        steps.close()
        print(f"beamctl commission: {exc}", file=sys.stderr)
        return 1
    finally:
        steps.close()
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        print(f"commissioned into {summary['folder']}: {', '.join(summary['done'])}"
              + ("" if "report" in summary["done"] else " (stopped before the rest: see above)"))
    return 0
