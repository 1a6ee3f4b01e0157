"""``beamctl identify``: measure the rig's frequency responses at one axial load."""

from __future__ import annotations

import argparse
import json

from beamctl.assembly.run import load_gain_table, load_service_config
from beamctl.common.signals import stop_on_signals
from beamctl.identification.excitation import SIGNALS, SUPPORT_INPUTS
from beamctl.identification.frf_files import check_frf_out, write_frf
from beamctl.identification.identify import IdentificationError, IdentifySettings, identify
from beamctl.models.measured import resonances
from beamctl.tools import argtypes
from beamctl.tools.progress import ProgressBar

EXIT_STOPPED = 1


def add_parser(sub) -> None:
    p = sub.add_parser(
        "identify", help="measure the frequency responses strains/forces at one axial load",
        description="Excite the stacks through the configured HAL (sim or can) at a fixed axial load, "
                    "record the strains and the applied forces, and write the 4 x 4 frequency response "
                    "matrix with its coherence (.npz and .mat). Open loop below the critical load (stacks "
                    "at bias plus the excitation); --closed-loop adds the excitation to the gain table's "
                    "law. The supervisor's checks stay active; Ctrl-C ramps the stacks to bias.")
    p.add_argument("--config", metavar="RIG", help="service configuration of the rig (default: the "
                   "simulated rig of the shipped defaults)")
    p.add_argument("--load", type=argtypes.number(low=0.0), required=True, metavar="N",
                   help="axial load in N (the simulated rig holds it; on the rig, set it first: the load "
                        "cell must read it)")
    p.add_argument("--out", metavar="FILE", required=True,
                   help="result file; FILE.npz and FILE.mat are both written")
    p.add_argument("--signal", choices=SIGNALS, default="multisine",
                   help="excitation: multisine (random phases), chirp or prbs (default multisine)")
    p.add_argument("--band", metavar="LO:HI", type=argtypes.band, default=(10.0, 1200.0),
                   help="frequency band in Hz (default 10:1200)")
    p.add_argument("--amplitude", type=argtypes.positive, default=5.0, metavar="V",
                   help="peak stack swing about bias in V (default 5)")
    p.add_argument("--resolution", type=argtypes.positive, default=1.0, metavar="HZ",
                   help="frequency step in Hz; one period of the signal lasts 1/HZ s (default 1)")
    p.add_argument("--averages", type=argtypes.number(low=1, integer=True), default=8, metavar="N",
                   help="periods averaged per input, at least 3, after the transient ones (at least one, and "
                        "5 decay times of the model's slowest mode at the load) (default 8)")
    p.add_argument("--supports", choices=tuple(SUPPORT_INPUTS), default="AB",
                   help="excite the stacks of support A, B or both (default AB)")
    p.add_argument("--closed-loop", action="store_true",
                   help="run the gain table's law and add the excitation (needed at or above the "
                        "critical load)")
    p.add_argument("--max-strain", type=argtypes.positive, default=3e-4, metavar="S",
                   help="stop the excitation when a strain moves more than S from its value at the start "
                        "(default 3e-4)")
    p.add_argument("--seed", type=argtypes.number(low=0, integer=True), default=0,
                   help="random phases / sequence seed (default 0)")
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:

    cfg = load_service_config(args.config)
    settings = IdentifySettings(load_n=args.load, signal=args.signal, band_hz=args.band,
                                amplitude_v=args.amplitude, resolution_hz=args.resolution,
                                averages=int(args.averages), supports=args.supports,
                                closed_loop=args.closed_loop, max_strain=args.max_strain, seed=int(args.seed))
    check_frf_out(args.out)
    table = load_gain_table(cfg)
    try:
        with ProgressBar("identify") as bar, stop_on_signals() as stop:
            data, report = identify(cfg, table, settings, progress=bar, stop=stop)
            bar.close()
    except IdentificationError as exc:
        print(f"beamctl identify: stopped: {exc}", flush=True)
        return EXIT_STOPPED
    paths = write_frf(data, args.out)
    peaks = resonances(data)
    report.update(files=[str(p) for p in paths], frequencies=len(data.frequencies_hz),
                  resolution_hz=data.settings["resolution_hz"], resonances_hz=peaks,
                  inputs=data.settings["inputs"])
    if args.json:
        print(json.dumps(report, indent=1))
        return 0
    f = data.frequencies_hz
    print(f"identified at {data.load_n:.0f} N ({cfg.hal.backend}): {len(f)} frequencies "
          f"{f[0]:g}..{f[-1]:g} Hz every {report['resolution_hz']:.3g} Hz, "
          f"forces {', '.join(report['inputs'])}")
    for plane, freqs in peaks.items():
        print(f"resonances ({plane}): {', '.join(f'{f:.1f} Hz' for f in freqs) or 'none found'}")
    print(f"{report['rig_s']:.1f} s of rig time in {report['wall_s']:.1f} s")
    print(f"wrote {', '.join(report['files'])}")
    return 0
