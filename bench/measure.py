"""Measurements behind ``beamctl bench``: the control step's cost, the answer latency over CAN
with the DAQ emulator in its own process, timer pacing, the live view's cost, the offline
simulation and the gain build. Each returns plain numbers (medians, percentiles, ratios) for
the command line to print or write as JSON."""

from __future__ import annotations

import gc
import json
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
from dataclasses import replace
from pathlib import Path

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from beamctl.assembly import live as live_view
from beamctl.assembly.run import load_gain_table
from beamctl.common.signals import Interrupted, stop_on_signals
from beamctl.gains.build import build_table
from beamctl.gains.defaults import default_table_path
from beamctl.gains.table import load_table
from beamctl.hal import create as create_backend
from beamctl.hal.base import Sample
from beamctl.hal.budget import LIMIT as BUS_LIMIT
from beamctl.hal.budget import bus_budget
from beamctl.hal.config import hal_config
from beamctl.hal.dbc import Contract
from beamctl.models import build_model
from beamctl.models.plant import Plant, clear_discretisations, plant_config
from beamctl.rt import engine, realtime
from beamctl.rt.allocation import geometry
from beamctl.rt.config import controller_config
from beamctl.rt.controller import Controller
from beamctl.rt.loop import ControlLoop
from beamctl.rt.telemetry import TelemetryWriter
from beamctl.simulation import simkernel
from beamctl.simulation.experiment import experiment_config, run_mode, summarise

EMULATOR_PRIORITY = 70         # SCHED_FIFO of the emulator's process (the controller's is 80)


def percentiles_us(seconds: np.ndarray) -> dict:
    return {"p50": float(np.percentile(seconds, 50) * 1e6), "p99": float(np.percentile(seconds, 99) * 1e6)}


_compiled: dict = {}


def _cycle_counter():
    """A numba intrinsic reading the CPU's cycle counter (LLVM ``readcyclecounter``)."""
    if "counter" not in _compiled:

        @intrinsic
        def read_counter(typingctx):
            def codegen(context, builder, signature, args):
                fnty = ir.FunctionType(ir.IntType(64), [])
                return builder.call(cgutils.get_or_insert_function(builder.module, fnty,
                                                                   "llvm.readcyclecounter"), [])
            return types.uint64(), codegen

        _compiled["counter"] = read_counter
    return _compiled["counter"]


def _timed_cycles():
    """A compiled loop running the engine's ``sample_cycle`` on each row of its inputs and
    recording each call's duration in CPU cycles (compiled once per process)."""
    if "timed" not in _compiled:


        counter = _cycle_counter()
        cycle = engine.sample_cycle

        def timed(core, nb, inputs, ticks):
            for i in range(inputs.shape[0]):
                row = inputs[i]
                t0 = counter()
                cycle(core, nb, row[0], row[1], row[2], 0, row[3:7])
                ticks[i] = counter() - t0

        _compiled["timed"] = numba.njit(nogil=True)(timed)
    return _compiled["timed"]


def _counter_hz() -> float:
    """The cycle counter's rate, against ``time.perf_counter`` over 0.2 s."""

    counter = _cycle_counter()
    now = numba.njit(lambda: counter())
    now()
    t0, c0 = time.perf_counter(), now()
    while time.perf_counter() - t0 < 0.2:
        pass
    t1, c1 = time.perf_counter(), now()
    return (c1 - c0) / (t1 - t0)


def step_timing(samples: int = 50_000) -> dict:
    """The control step (estimator, schedule, law, allocation, safety: the engine's cycle) in a
    running controller over a sweep of loads and vibrating strains, two ways: the compiled cycle
    alone, each call timed inside compiled code by the CPU's cycle counter ("compiled"), and the
    controller's ``step`` as the loop calls it from Python, timed with ``perf_counter`` ("call").
    Median and 99th percentile of each, in microseconds."""
    table = load_table(default_table_path())
    rng = np.random.default_rng(0)
    k = np.arange(1000)
    strains = 3e-6 * np.sin(2 * np.pi * 20 * k / 2500.0)[:, None] + 1e-7 * rng.standard_normal((1000, 4))
    loads = 300.0 + 3.4 * k
    inputs = []
    for i in range(1000):
        s = Sample()
        s.strains[:] = strains[i]
        s.axial_load = loads[i]
        s.timestamp, s.sequence = i / table.design.sample_rate_hz, i
        inputs.append(s)

    def running() -> Controller:
        controller = Controller(table, controller_config({"start_ramp_time_s": 0.0}))
        controller.arm(inputs[0])
        controller.start()
        return controller

    def check(controller: Controller) -> None:
        if controller.state.name != "RUNNING":
            raise RuntimeError(f"benchmark controller left RUNNING: {controller.supervisor.reason()}")

    # the compiled cycle alone
    controller = running()
    rows = np.empty((samples, 7))
    for i in range(samples):
        s = inputs[i % 1000]
        rows[i, :3] = (i / table.design.sample_rate_hz, i, s.axial_load)
        rows[i, 3:7] = s.strains
    ticks = np.zeros(samples, dtype=np.uint64)
    timed = _timed_cycles()
    timed(controller._core, controller._nb, rows[:100], ticks[:100])        # compiled or loaded
    hz = _counter_hz()
    controller = running()
    gc.collect()
    gc.disable()
    try:
        timed(controller._core, controller._nb, rows, ticks)
    finally:
        gc.enable()
    check(controller)
    compiled = percentiles_us(ticks.astype(float) / hz)
    # the call from Python
    controller = running()
    times = np.empty(samples)
    clock = time.perf_counter
    gc.collect()
    gc.disable()
    try:
        for i in range(samples):
            s = inputs[i % 1000]
            t0 = clock()
            controller.step(s)
            times[i] = clock() - t0
    finally:
        gc.enable()
    check(controller)
    call = percentiles_us(times)
    return {"compiled": compiled, "call": call, "counter_hz": hz, "p50": compiled["p50"],
            "p99": compiled["p99"], "call_over_compiled_p50": call["p50"] / compiled["p50"]}


def _timer_run(cycles: int, what: str, telemetry: Path | None = None, live: str | None = None,
               acquire_rt: bool = False):
    """The loop with ``timer`` pacing at the default table's rate against the sim backend, for
    ``cycles`` cycles; with a telemetry file and a live view at the socket ``live`` if given, and
    the real-time set-up (SCHED_FIFO, affinity, locked memory, where granted) if asked."""

    table = load_table(default_table_path())
    config = controller_config({"pacing": "timer"})
    plant = Plant(build_model(table.model_parameters),
                  plant_config({"sample_rate_hz": table.design.sample_rate_hz,
                                "io": table.design.io.to_dict(),
                                "load": {"start": 2000.0, "end": 2000.0}}))
    controller = Controller(table, config)
    publisher = writer = None
    if live is not None:
        publisher = live_view.live_publisher(live, controller, f"beamctl bench: {what}")
    if telemetry is not None:
        writer = TelemetryWriter.for_controller(telemetry, controller, live=publisher)
    hal = create_backend("sim", plant=plant, geometry=geometry(config.actuators)).open()
    try:
        if writer is not None:
            writer.start()
        with stop_on_signals() as stop:
            loop = ControlLoop(controller, hal, telemetry=writer, max_cycles=cycles, stop=stop)
            if publisher is not None:
                live_view.watch_loop(publisher, loop, writer)
            result = loop.run(acquire_rt=acquire_rt)
    finally:
        hal.close()
        if writer is not None:
            writer.close()
        if publisher is not None:
            publisher.close()
    if result.signal_received:
        raise Interrupted(result.signal_received, what)
    return result, publisher


def timer_pacing(cycles: int = 5000) -> dict:
    """Start-to-start time of the loop's cycles with ``timer`` pacing (absolute deadlines at the
    table's rate) against the sim backend: median, 99th percentile, overruns."""
    table = load_table(default_table_path())
    result, _ = _timer_run(cycles, "the timer pacing measurement")
    cycle = result.timing["cycle"]
    return {"period_us": 1e6 / table.design.sample_rate_hz, "p50": cycle["p50_us"],
            "p99": cycle["p99_us"], "max": cycle["max_us"], "overruns": result.timing["overruns"],
            "cycles": cycle["count"]}


LIVE_CASES = ("without --live", "nobody listening", "viewer attached", "viewer stalled")


def live_view_timing(cycles: int = 12_000, rounds: int = 5) -> dict:
    """The loop's timing (``timer`` pacing, the sim backend, telemetry written, the real-time
    set-up as ``beamctl run`` takes it) with the live view four ways, in rounds that take each in
    turn: without ``--live``; ``--live`` with nobody listening; a viewer attached (``beamctl
    monitor`` in its own process, its page's event stream read by another); a viewer stalled (a
    socket bound and never read). Per case the medians over the rounds of the cycle's p50 and p99
    and the step's p50 (us), the datagrams sent and dropped, and the ratios to the case without
    ``--live``."""

    runs: dict[str, list[dict]] = {case: [] for case in LIVE_CASES}
    datagrams = {case: [0, 0] for case in LIVE_CASES}
    with tempfile.TemporaryDirectory(prefix="bb", dir="/tmp") as tmp:
        attached, stalled = os.path.join(tmp, "attached.sock"), os.path.join(tmp, "stalled.sock")
        monitor = subprocess.Popen([sys.executable, "-c", CLI, "monitor", "--port", "0", "--live", attached],
                                   stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        page = None
        never_read = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        try:
            url = urllib.parse.urlsplit(monitor.stdout.readline().decode().strip())
            if not url.port:
                raise RuntimeError("beamctl monitor did not start")
            events = f"http://127.0.0.1:{url.port}/events?{url.query}"
            page = subprocess.Popen([sys.executable, "-c", "import sys, urllib.request\n"
                                     "for line in urllib.request.urlopen(sys.argv[1]): pass", events],
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            never_read.bind(stalled)
            live = {"without --live": None, "nobody listening": os.path.join(tmp, "nobody.sock"),
                    "viewer attached": attached, "viewer stalled": stalled}
            for k in range(rounds):
                for case in LIVE_CASES:
                    result, publisher = _timer_run(cycles, f"the live view measurement ({case})",
                                                   Path(tmp) / f"{k}.btl", live[case], acquire_rt=True)
                    (Path(tmp) / f"{k}.btl").unlink()
                    realtime = result.realtime.get("scheduler", "not asked")
                    t = result.timing
                    runs[case].append({"cycle_p50": t["cycle"]["p50_us"], "cycle_p99": t["cycle"]["p99_us"],
                                       "step_p50": t["compute"]["p50_us"], "overruns": t["overruns"]})
                    if publisher is not None:
                        datagrams[case][0] += publisher.sent
                        datagrams[case][1] += publisher.dropped
        finally:
            never_read.close()
            for process in (page, monitor):
                if process is not None:
                    process.terminate()
                    process.wait()
    out: dict = {"cycles": cycles, "rounds": rounds, "realtime": realtime,
                 "period_us": 1e6 / load_table(default_table_path()).design.sample_rate_hz}
    for case in LIVE_CASES:
        med = {key: float(np.median([r[key] for r in runs[case]])) for key in runs[case][0]}
        med["sent"], med["dropped"] = datagrams[case]
        out[case] = med
    base = out["without --live"]
    for case in LIVE_CASES[1:]:
        out[case]["ratio"] = {key: out[case][key] / base[key]
                              for key in ("cycle_p50", "cycle_p99", "step_p50")}
    return out


def _emulator_priority() -> None:
    """In the emulator's process before it starts: SCHED_FIFO below the controller's, if allowed
    (a DAQ is hardware with its own clock; a busy machine should not delay its samples)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(EMULATOR_PRIORITY))
    except (OSError, AttributeError):
        pass


def can_transport() -> tuple[str, str]:
    """The bus between two processes: socketcan on vcan0 where the kernel has it, else the
    loopback-only local bus (hal/localbus.py) on a channel of its own."""
    if Path("/sys/class/net/vcan0").exists():
        return "socketcan", "vcan0"
    return "beamctl_local", f"bench-{os.getpid()}-{time.monotonic_ns()}"


def can_latency(samples: int = 10_000, load_n: float = 2000.0) -> dict:
    """The controller's latency over CAN with the DAQ emulator in its own process: for each
    sample, the time from the strain frame's send (its bus time stamp) to the send call of the
    voltage frame answering that sequence, measured by the controller's HAL (``answer_age_s``).
    The emulator streams at the table's rate on the wall clock (real-time priority where
    granted); the controller runs ``beamctl run``'s loop (real-time set-up where granted)."""

    table = load_table(default_table_path())
    rate = table.design.sample_rate_hz
    # the shipped safety settings (the table's ride-through limits); a fault does not end the
    # measurement (the controller goes on answering, at bias) but is reported
    config = controller_config({"pacing": "sample"})
    interface, channel = can_transport()
    use_fd = bus_budget(Contract(), rate, 1e6).load > BUS_LIMIT

    spin_s = hal_config({}).can["spin_s"]           # the service's default
    backend = create_backend("can", sample_rate_hz=rate, interface=interface, channel=channel,
                             rate_tolerance=0.0, fd=use_fd, spin_s=spin_s,
                             data_bitrate_bit_s=4e6 if use_fd else None)
    controller = Controller(table, config)
    ages = np.full(samples, np.nan)
    answered = 0

    warm_up = int(0.5 * rate)            # the first half second is not measured

    def on_cycle(loop: ControlLoop) -> None:
        nonlocal answered
        age = backend.answer_age_s
        if loop.cycles > warm_up and age == age and answered < samples:
            ages[answered] = age
            answered += 1

    with tempfile.TemporaryDirectory() as tmp, stop_on_signals() as stop:
        loop = ControlLoop(controller, backend, max_cycles=samples + 2 * warm_up, on_cycle=on_cycle,
                           stop=stop, stop_on_fault=False)
        stats_path = Path(tmp) / "daq.json"
        cfg = Path(tmp) / "plant.yaml"
        cfg.write_text(json.dumps({"plant": {"load": {"start": load_n, "end": load_n},
                                             "bow": {"amplitude": 5e-5, "angle_deg": 234.0}}}))
        # as `beamctl run` does: real-time set-up, then the bus (listening before the emulator sends)
        rt_report = realtime.acquire(config.realtime)
        backend.open()
        duration = (samples + 4 * warm_up) / rate + 5.0
        emulator = subprocess.Popen(
            [sys.executable, "-c", "import sys; from beamctl.tools.cli import main; sys.exit(main())",
             "plant", "--can", f"{interface}:{channel}", "--config", str(cfg),
             "--duration", f"{duration:.3f}", "--stats", str(stats_path)],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=_emulator_priority)
        try:
            first = emulator.stdout.readline()          # the banner: the emulator is on the bus
            if not first:
                raise RuntimeError(f"the plant emulator did not start: {emulator.stderr.read().decode()}")
            result = loop.run(acquire_rt=False)
        finally:
            realtime.release()
            emulator.send_signal(signal.SIGINT)
            try:
                emulator.communicate(timeout=10.0)
            except subprocess.TimeoutExpired:
                emulator.kill()
                emulator.communicate()
            backend.close()
        daq = json.loads(stats_path.read_text()) if stats_path.exists() else None
    if result.signal_received:
        raise Interrupted(result.signal_received, "the CAN latency measurement")
    ages = ages[:answered]
    budget_s = controller.safety.answer_budget_s
    budget = bus_budget(backend.contract, rate, 1e6)
    fd = bus_budget(backend.contract, rate, 1e6, True, 4e6)
    return {"p50": float(np.percentile(ages, 50) * 1e6), "p99": float(np.percentile(ages, 99) * 1e6),
            "p99.9": float(np.percentile(ages, 99.9) * 1e6), "max": float(ages.max() * 1e6),
            "late": int(np.sum(ages > budget_s)), "budget_us": budget_s * 1e6,
            "half_period_us": 0.5e6 / rate, "over_half_period": int(np.sum(ages > 0.5 / rate)),
            "samples": int(ages.size), "sample_rate_hz": rate, "transport": f"{interface}:{channel}",
            "ended": f"{result.state} {result.reason}", "realtime": rt_report,
            "late_limit": controller.safety.late_limit, "gap_limit": controller.safety.gap_limit,
            "bridged_samples": controller.safety.bridged_samples,
            "longest_gap": controller.safety.longest_gap,
            "bus": backend.budget.description, "bus_load_percent": 100 * backend.budget.load,
            "max_rate_classic_1M_Hz": budget.max_sample_rate_hz,
            "max_rate_fd_1M_4M_Hz": fd.max_sample_rate_hz,
            "daq_stalls": daq_stalls(daq, table),
            "hal": {k: v for k, v in result.hal.items() if isinstance(v, int | float)},
            "loop_timing": {k: result.timing[k] for k in ("read", "compute", "write", "answer_age")}}


def daq_stalls(daq: dict | None, table) -> dict | None:
    """The stalls the DAQ saw (``beamctl plant --stats``: the plant steps in a row the stacks
    held one voltage, the longest per minute) against the table's ride-through at the reference
    operating point (gains/ridethrough.py ``REFERENCE``, the simulated rig at 3300 N): the highest
    analysed load up to which every load's limit is at least the longest stall measured."""
    if daq is None or table.ride_through is None:
        return None
    rt = table.ride_through
    longest = int(daq["held_longest_samples"])
    loads = sorted(set(float(x) for x in rt.loads_n))
    limits = [n for n, _ in rt.reference_limits(loads)]
    up_to = None
    for load, limit in zip(loads, limits, strict=True):
        if limit < longest:
            break
        up_to = load
    return {"longest_samples": longest, "longest_ms": float(daq["held_longest_ms"]),
            "per_minute_ms": daq["held_longest_per_minute_ms"], "missed_answers": daq["missed_answers"],
            "not_sent_late": daq["not_sent_late"], "rides_through_up_to_N": up_to,
            "table_top_N": float(table.loads_n[-1])}


def sim_realtime_factor() -> dict:
    """Plant seconds per wall second of the experiment's controlled run (default scenario,
    the sim backend through the rt loop, telemetry written)."""


    cfg, settings = experiment_config()
    with tempfile.TemporaryDirectory() as tmp:
        trace = run_mode("interpolate", cfg, settings, load_gain_table(cfg), Path(tmp))
    return {"factor": trace.plant_s / trace.wall_s, "plant_s": trace.plant_s, "wall_s": trace.wall_s}


def offline_timing(repeats: int = 3) -> dict:
    """The default experiment's controlled run (70 s ramp, shipped LQG at 6000 Hz, no
    telemetry) through the loop and through the compiled kernel, alternately in one process:
    microseconds per simulated sample of each, the kernel with the plant's discretisations
    computed afresh (cold) and shared from the run before (warm), their ratios per round, and
    how far the two runs' results differ."""

    import numpy as np


    cfg, settings = experiment_config()
    table = load_gain_table(cfg)

    def per_sample(engine: str, cold: bool, config=cfg):
        if cold:
            clear_discretisations()
        trace = run_mode("interpolate", config, settings, table, engine=engine)
        return trace.wall_s / trace.cycles * 1e6, trace

    # numba compiles the kernel (or loads its disk cache) at its first call in a process: a run
    # of 0.1 s of plant time takes that before the rounds
    short = replace(cfg, plant={**cfg.plant, "load": {**cfg.plant["load"], "end": cfg.plant["load"]["start"],
                                                      "hold": 0.1}})
    start = time.perf_counter()
    simkernel.kernel()
    per_sample("kernel", False, short)
    compile_s = time.perf_counter() - start

    rounds = []
    for _ in range(repeats):
        loop_us, loop_trace = per_sample("loop", cold=True)
        cold_us, kernel_trace = per_sample("kernel", cold=True)
        warm_us, _ = per_sample("kernel", cold=False)
        a, b = loop_trace.arrays(), kernel_trace.arrays()
        same = a["load_n"].shape == b["load_n"].shape
        rounds.append({
            "loop_us": loop_us, "kernel_cold_us": cold_us, "kernel_warm_us": warm_us,
            "ratio_cold": loop_us / cold_us, "ratio_warm": loop_us / warm_us,
            "kernel_share": kernel_trace.kernel_cycles / kernel_trace.cycles,
            "same_samples": bool(same),
            "max_deflection_difference_m": float(np.max(np.abs(a["deflection_m"] - b["deflection_m"])))
            if same else math.inf,
            "held_load_n": (summarise(loop_trace, "", "scale")["load_at_1.0mm_N"],
                            summarise(kernel_trace, "", "scale")["load_at_1.0mm_N"]),
            "cycles": kernel_trace.cycles})
    med = {key: float(np.median([r[key] for r in rounds]))
           for key in ("loop_us", "kernel_cold_us", "kernel_warm_us", "ratio_cold", "ratio_warm")}
    return {"rounds": rounds, "median": med, "compile_or_cache_load_s": compile_s}


# the command line as a process of its own, as a user starts it
CLI = "import sys; from beamctl.tools.cli import main; sys.exit(main())"
# the commands ``command_times`` times: (name, arguments; {out}: a file in a folder of the run's)
COMMANDS = (("gains build --no-robust", ("gains", "build", "--no-robust", "--out", "{out}/table.yaml")),
            ("experiment", ("experiment", "--out", "{out}/experiment")))


def command_times(rounds: int = 3, progress=None) -> dict:
    """Wall seconds of whole commands (``COMMANDS``), each started as a user starts it (a fresh
    process: imports, compiled code from its cache, the work, the files written), the commands
    taken in turn ``rounds`` times after one warm-up round (which fills the caches a first
    start compiles), so that a slow stretch of the machine falls on all alike: per command the
    runs, median, least and most."""
    names = [name for name, _ in COMMANDS]
    runs: dict[str, list[float]] = {name: [] for name in names}
    total = (rounds + 1) * len(COMMANDS)
    with tempfile.TemporaryDirectory(prefix="bench-commands-") as tmp:
        for r in range(rounds + 1):
            for k, (name, args) in enumerate(COMMANDS):
                if progress:
                    progress(r * len(COMMANDS) + k, total,
                             f"{'warm-up' if r == 0 else f'round {r}/{rounds}'}: {name}")
                argv = [a.format(out=tmp) for a in args]
                start = time.perf_counter()
                done = subprocess.run([sys.executable, "-c", CLI, *argv], stdout=subprocess.DEVNULL,
                                      stderr=subprocess.PIPE, text=True, check=False)
                elapsed = time.perf_counter() - start
                if done.returncode != 0:
                    last = (done.stderr.strip().splitlines() or ["no message"])[-1]
                    raise RuntimeError(f"`beamctl {' '.join(argv)}` ended with exit status "
                                       f"{done.returncode}: {last}")
                if r > 0:
                    runs[name].append(elapsed)
    return {name: {"runs_s": [round(t, 3) for t in ts], "median_s": float(np.median(ts)),
                   "min_s": min(ts), "max_s": max(ts)} for name, ts in runs.items()}


def gains_build_time() -> float:
    """Seconds to build the default table: 81 LQR designs and 161 closed-loop checks."""

    model = build_model(load_table(default_table_path()).model_parameters)
    start = time.perf_counter()
    table = build_table(model)
    elapsed = time.perf_counter() - start
    if not table.all_stable:
        raise RuntimeError("the default table is no longer stable")
    return elapsed
