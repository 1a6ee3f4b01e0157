"""``beamctl plant``: the simulated beam behind the DBC, as the DAQ on a CAN bus, and
``beamctl bus-budget``: what the frames cost on the bus."""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

from beamctl.assembly.run import build_plant, load_gain_table, load_service_config, plant_geometry
from beamctl.common.outputs import check_file, write_text
from beamctl.config.schema import ConfigError
from beamctl.gains.defaults import default_table_path
from beamctl.gains.table import load_table
from beamctl.hal.base import HalConfigurationError
from beamctl.hal.budget import LIMIT, bus_budget
from beamctl.hal.can_backend import open_hint
from beamctl.hal.config import HAL_DEFAULTS, check_bitrates
from beamctl.hal.dbc import Contract
from beamctl.hal.emulator import CanPlantEmulator
from beamctl.rt import realtime
from beamctl.rt.config import Realtime
from beamctl.tools.argtypes import positive, seconds


def parse_can(text: str) -> tuple[str, str]:
    interface, sep, channel = text.partition(":")
    if not sep or not interface or not channel:
        raise ConfigError("--can", text, "INTERFACE:CHANNEL, e.g. socketcan:vcan0 or virtual:bench")
    return interface, channel


def add_parser(sub) -> None:
    p = sub.add_parser(
        "plant", help="run the simulated beam as the DAQ on a CAN bus",
        description="The simulated rig playing the lab's DAQ: it sends the strain and load frames of "
                    "hal/beamctl.dbc on a CAN bus at the gain table's rate and applies the voltage "
                    "frames `beamctl run` answers with, falling back to bias when they stop. On this "
                    "machine use python-can's virtual or the local bus (--can beamctl_local:CH); on the "
                    "lab PC a SocketCAN interface (--can socketcan:vcan0 after `modprobe vcan`). Runs "
                    "until Ctrl-C or --duration; exit 0 then.")
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
    p.add_argument("--cpu", type=int, default=None, metavar="N",
                   help="the CPU the simulated DAQ runs on (default: the first it may run on, where it may "
                        "run on more than one: CPU 0, the lab configuration's loop runs on 1; -1: any)")
    p.add_argument("--stats", metavar="FILE",
                   help="write what the DAQ saw as JSON when it stops: samples, answers, and the stalls the "
                        "stacks held one voltage through (the longest, per minute of plant time), in samples "
                        "and ms")
    p.set_defaults(run=run_plant)

    b = sub.add_parser(
        "bus-budget", help="bus load of the DBC's frames at a sample rate",
        description="What the frames of the DBC cost on the bus at a sample rate, per message, and the "
                    "highest rate within the 80 % the service allows. Without flags: the shipped gain "
                    "table's rate on the HAL's default bus (CAN FD 1 Mbit/s with a 4 Mbit/s data phase); "
                    "--config takes the rate from a service configuration's gain table and the bus from "
                    "its hal.can section; the flags override either.")
    b.add_argument("--config", metavar="F", help="service configuration: its table's rate, its hal.can bus")
    b.add_argument("--rate", type=positive, help="sample rate in Hz (default: the gain table's)")
    b.add_argument("--bitrate", type=positive, help="(nominal) bit rate in bit/s (default 1e6)")
    b.add_argument("--fd", action=argparse.BooleanOptionalAction, default=None,
                   help="CAN FD with bit-rate switch, or (--no-fd) classic CAN (default: CAN FD)")
    b.add_argument("--data-bitrate", type=positive, help="CAN FD data bit rate in bit/s (default 4e6)")
    b.add_argument("--dbc", help="DBC file (default: the shipped hal/beamctl.dbc)")
    b.add_argument("--json", action="store_true", help="print the budget as one JSON object")
    b.set_defaults(run=run_budget)


def run_plant(args: argparse.Namespace) -> int:
    import can


    interface, channel = parse_can(args.can)
    cpus = sorted(os.sched_getaffinity(0))
    if args.cpu is not None and args.cpu != -1 and args.cpu not in cpus:
        print(f"beamctl plant: error: --cpu {args.cpu}: expected one of the CPUs this process may run on "
              f"({', '.join(map(str, cpus))}), or -1 for any", file=sys.stderr)
        return 2
    stats = check_file(args.stats, "--stats") if args.stats else None
    cfg = load_service_config(args.config)
    table = load_gain_table(cfg)
    plant = build_plant(cfg, table)
    try:
        bus = can.Bus(interface=interface, channel=channel)
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        print(f"beamctl plant: error: cannot open {interface}:{channel}: {exc}"
              f"{open_hint(interface, channel)}", file=sys.stderr)
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

    if args.pace == "wallclock":     # a DAQ keeps its clock: no discretisation made on the way
        t0 = time.monotonic()
        try:
            cells = plant.prepare()
        except ValueError as exc:
            print(f"beamctl plant: error: {exc}", file=sys.stderr)
            return 2
        print(f"plant: {cells} discretisations of the load programme made in {time.monotonic() - t0:.1f} s",
              flush=True)
    cpu = args.cpu if args.cpu is not None else (cpus[0] if len(cpus) > 1 else -1)
    granted = realtime.acquire(Realtime(priority=EMULATOR_PRIORITY, helper_priority=EMULATOR_PRIORITY - 1,
                                              cpu=cpu, lock_memory=True))
    print(f"plant real-time set-up: {granted.get('scheduler', '-')}; {granted.get('affinity', 'any CPU')}; "
          f"garbage collector {granted.get('gc', '-')}", flush=True)
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
          f"load {plant.axial_load:.0f} N, deflection {1e3 * d:.3f} mm at {angle:.0f} deg; "
          "the stacks held one "
          f"voltage through at most {emulator.held_longest} samples "
          f"({1e3 * emulator.held_longest * plant.config.period_s:.2f} ms)")
    if stats is not None:
        ms = 1e3 * plant.config.period_s
        write_text(stats, json.dumps({
            "samples": emulator.samples, "sample_rate_hz": plant.config.sample_rate_hz,
            "voltage_frames": emulator.voltage_frames, "missed_answers": emulator.missed_answers,
            "not_sent_late": emulator.skipped, "fallbacks": emulator.fallbacks,
            "held_longest_samples": emulator.held_longest, "held_longest_ms": emulator.held_longest * ms,
            "held_longest_per_minute_samples": emulator.held_longest_per_minute,
            "held_longest_per_minute_ms": [n * ms for n in emulator.held_longest_per_minute],
            "long_holds": [{"time_s": t, "load_N": f, "samples": n, "ms": n * ms, "not_sent_by_daq": u}
                           for t, f, n, u in emulator.long_holds],
            "load_N": plant.axial_load, "deflection_mm": 1e3 * d}, indent=1) + "\n")
    return 0


# SCHED_FIFO of the emulator: below the controller's loop (80), above its other threads (60)
EMULATOR_PRIORITY = 70


def _budget_settings(args: argparse.Namespace) -> tuple[float, float, bool, float, str | None, str]:
    """(rate, bit rate, CAN FD, data bit rate, DBC, where the rate came from): the flags over the
    configuration's (or the shipped table's and the HAL's defaults)."""
    if args.config:
        cfg = load_service_config(args.config)
        can, table_path = cfg.hal.can, cfg.table_path
    else:
        can, table_path = HAL_DEFAULTS["can"], default_table_path()
    rate, source = args.rate, "--rate"
    if rate is None:
        if not Path(table_path).is_file():
            raise ConfigError("gains.table", str(table_path), "an existing gain table file: its rate is the "
                              "budget's (or give --rate)", cfg.source if args.config else "")
        rate, source = load_table(table_path, verify=False).design.sample_rate_hz, f"the rate of {table_path}"
    return (rate, args.bitrate or can["bitrate_bit_s"], can["fd"] if args.fd is None else args.fd,
            args.data_bitrate or can["data_bitrate_bit_s"], args.dbc or can["dbc"] or None, source)


def run_budget(args: argparse.Namespace) -> int:
    rate, bitrate, fd, data_bitrate, dbc, source = _budget_settings(args)
    # the data phase's rate is checked even without --fd: the CAN FD comparison uses it
    check_bitrates(bitrate, data_bitrate, True, ("--bitrate", "--data-bitrate"))
    try:
        contract = Contract(dbc)
    except HalConfigurationError as exc:
        print(f"beamctl bus-budget: error: {exc}", file=sys.stderr)
        return 2
    b = bus_budget(contract, rate, bitrate, fd, data_bitrate)
    fd_alternative = None if fd else bus_budget(contract, rate, bitrate, True, data_bitrate)
    if args.json:
        print(json.dumps({"bus": b.description, "sample_rate_hz": rate, "rate_from": source, "load": b.load,
                          "limit": LIMIT, "fits": b.load <= LIMIT, "per_message": b.per_message,
                          "max_sample_rate_hz": b.max_sample_rate_hz,
                          "can_fd_load": None if fd_alternative is None else fd_alternative.load}, indent=1))
        return 0 if b.load <= LIMIT else 1
    args = argparse.Namespace(rate=rate, fd=fd, data_bitrate=data_bitrate)
    print(f"at {rate:g} Hz ({source})")
    # near the limit one decimal would show "80.0 % (exceeds the 80 % limit)": show enough
    digits = 1 if abs(b.load - LIMIT) >= 5e-4 else 3
    print(f"{b.description}, {args.rate:g} Hz: bus load {100 * b.load:.{digits}f} % "
          f"({'fits' if b.load <= LIMIT else 'exceeds'} the {100 * LIMIT:.0f} % limit)")
    for name, share in b.per_message.items():
        codec = next(c for c in contract.codecs.values() if c.name == name)
        print(f"  {name:<14} {codec.length} bytes every {codec.divisor:>2} samples: {100 * share:5.1f} %")
    print(f"highest sample rate within {100 * LIMIT:.0f} %: {b.max_sample_rate_hz:.0f} Hz")
    if fd_alternative is not None:
        print(f"with CAN FD ({args.data_bitrate / 1e6:g} Mbit/s data phase): "
              f"{100 * fd_alternative.load:.1f} %, up to {fd_alternative.max_sample_rate_hz:.0f} Hz")
    return 0 if b.load <= LIMIT else 1
