"""``beamctl plant``: the simulated beam behind the DBC, as the DAQ on a CAN bus, and
``beamctl bus-budget``: what the frames cost on the bus."""

from __future__ import annotations

import argparse
import signal
import sys
import threading

from beamctl.config.schema import ConfigError
from beamctl.hal.base import HalConfigurationError
from beamctl.hal.budget import LIMIT, bus_budget
from beamctl.hal.config import check_bitrates
from beamctl.hal.dbc import Contract
from beamctl.hal.emulator import CanPlantEmulator
from beamctl.rt import realtime
from beamctl.rt.config import Realtime
from beamctl.service.setup import build_plant, load_gain_table, load_service_config, plant_geometry
from beamctl.tools.argtypes import positive, seconds


def parse_can(text: str) -> tuple[str, str]:
    interface, sep, channel = text.partition(":")
    if not sep or not interface or not channel:
        raise ConfigError("--can", text, "INTERFACE:CHANNEL, e.g. socketcan:vcan0 or virtual:bench")
    return interface, channel


def add_parser(sub) -> None:
    p = sub.add_parser("plant", help="run the simulated beam as the DAQ on a CAN bus")
    p.add_argument("--can", required=True, metavar="INTERFACE:CHANNEL",
                   help="python-can interface and channel, e.g. socketcan:vcan0")
    p.add_argument("--config", metavar="F", help="service config (model, plant and controller sections)")
    p.add_argument("--pace", choices=("wallclock", "lockstep"), default="wallclock",
                   help="send at the sample rate (default) or wait for each answer")
    p.add_argument("--duration", type=seconds, default=0.0, metavar="S", help="stop after S plant seconds")
    p.add_argument("--silence-timeout", type=positive, metavar="S",
                   help="fall back to bias after S seconds without a valid voltage frame "
                        "(default: the DBC's SilenceTimeoutMs)")
    p.add_argument("--fallback-ramp", type=seconds, metavar="S",
                   help="ramp to bias within S seconds when falling back (default: the DBC's FallbackRampMs)")
    p.set_defaults(run=run_plant)

    b = sub.add_parser("bus-budget", help="bus load of the DBC's frames at a sample rate")
    b.add_argument("--rate", type=positive, default=2500.0, help="sample rate in Hz (default 2500)")
    b.add_argument("--bitrate", type=positive, default=1e6, help="(nominal) bit rate (default 1e6)")
    b.add_argument("--fd", action="store_true", help="CAN FD with bit-rate switch")
    b.add_argument("--data-bitrate", type=positive, default=4e6, help="CAN FD data bit rate (default 4e6)")
    b.add_argument("--dbc", help="DBC file (default: the shipped hal/beamctl.dbc)")
    b.set_defaults(run=run_budget)


def run_plant(args: argparse.Namespace) -> int:
    import can


    interface, channel = parse_can(args.can)
    cfg = load_service_config(args.config)
    table = load_gain_table(cfg)
    plant = build_plant(cfg, table)
    try:
        bus = can.Bus(interface=interface, channel=channel)
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        print(f"beamctl plant: error: cannot open {interface}:{channel}: {exc}", file=sys.stderr)
        return 2
    emulator = CanPlantEmulator(bus, plant, plant_geometry(cfg), pace=args.pace,
                                silence_timeout_s=args.silence_timeout, fallback_ramp_s=args.fallback_ramp,
                                skip_late=True)
    previous = {}
    if threading.current_thread() is threading.main_thread():   # the operator's stop
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: emulator.stop_event.set())
    samples = int(args.duration * plant.config.sample_rate_hz) if args.duration else None
    print(f"plant on {interface}:{channel}: {plant.config.sample_rate_hz:g} Hz, {args.pace}, load "
          f"{plant.config.load.start:g} -> {plant.config.load.end:g} N at {plant.config.load.rate:g} N/s; "
          f"falls back to bias {1e3 * emulator.silence_timeout_s:g} ms after the last valid voltage frame",
          flush=True)
    # a DAQ is hardware with a clock of its own: the emulator takes the real-time set-up the
    # service takes (SCHED_FIFO below the controller's, locked memory, the garbage collector
    # frozen: a collection stalls the plant for milliseconds), where granted

    granted = realtime.acquire(Realtime(priority=EMULATOR_PRIORITY, cpu=-1, lock_memory=True))
    print(f"plant real-time set-up: {granted.get('scheduler', '-')}; garbage collector "
          f"{granted.get('gc', '-')}", flush=True)
    try:
        emulator.run(samples)
    finally:
        realtime.release()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        bus.shutdown()
    d, angle = plant.deflection()
    print(f"stopped after {emulator.samples} samples ({plant.time:.2f} s plant time), "
          f"{emulator.voltage_frames} voltage frames, {emulator.missed_answers} missed answers, "
          f"{emulator.skipped} not sent (this process late), "
          f"{sum(emulator.rejected.values())} rejected, {emulator.fallbacks} fallbacks to bias, "
          f"load {plant.axial_load:.0f} N, deflection {1e3 * d:.3f} mm at {angle:.0f} deg")
    return 0


EMULATOR_PRIORITY = 70     # SCHED_FIFO of the emulator: below the controller's 80


def run_budget(args: argparse.Namespace) -> int:
    # the data phase's rate is checked even without --fd: the CAN FD comparison uses it
    check_bitrates(args.bitrate, args.data_bitrate, True, ("--bitrate", "--data-bitrate"))
    try:
        contract = Contract(args.dbc)
    except HalConfigurationError as exc:
        print(f"beamctl bus-budget: error: {exc}", file=sys.stderr)
        return 2
    b = bus_budget(contract, args.rate, args.bitrate, args.fd, args.data_bitrate)
    # near the limit one decimal would show "80.0 % (exceeds the 80 % limit)": show enough
    digits = 1 if abs(b.load - LIMIT) >= 5e-4 else 3
    print(f"{b.description}, {args.rate:g} Hz: bus load {100 * b.load:.{digits}f} % "
          f"({'fits' if b.load <= LIMIT else 'exceeds'} the {100 * LIMIT:.0f} % limit)")
    for name, share in b.per_message.items():
        codec = next(c for c in contract.codecs.values() if c.name == name)
        print(f"  {name:<14} {codec.length} bytes every {codec.divisor:>2} samples: {100 * share:5.1f} %")
    print(f"highest sample rate within {100 * LIMIT:.0f} %: {b.max_sample_rate_hz:.0f} Hz")
    if not args.fd:
        fd = bus_budget(contract, args.rate, args.bitrate, True, args.data_bitrate)
        print(f"with CAN FD ({args.data_bitrate / 1e6:g} Mbit/s data phase): {100 * fd.load:.1f} %, "
              f"up to {fd.max_sample_rate_hz:.0f} Hz")
    return 0 if b.load <= LIMIT else 1
