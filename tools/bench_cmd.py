"""``beamctl bench``: the figures the README quotes, measured in one run."""

from __future__ import annotations

import argparse
import gc
import json
import math
import time

import numpy as np

from beamctl.gains.defaults import default_table_path
from beamctl.gains.table import load_table
from beamctl.hal.base import Sample
from beamctl.rt.config import controller_config
from beamctl.rt.controller import Controller
from beamctl.tools.argtypes import steps
from beamctl.tools.signals import Interrupted


def percentiles_us(seconds: np.ndarray) -> dict:
    return {"p50": float(np.percentile(seconds, 50) * 1e6), "p99": float(np.percentile(seconds, 99) * 1e6)}


def step_timing(samples: int = 50_000) -> dict:
    """Median and 99th percentile of one control step (estimator, schedule, law, allocation,
    safety) in a running controller, over a sweep of loads and vibrating strains."""
    table = load_table(default_table_path())
    controller = Controller(table, controller_config({"start_ramp_time_s": 0.0}))
    rng = np.random.default_rng(0)
    inputs = []
    for k in range(1000):
        s = Sample()
        s.strains[:] = 3e-6 * np.sin(2 * np.pi * 20 * k / 2500.0) + 1e-7 * rng.standard_normal(4)
        s.axial_load = 300.0 + 3.4 * k
        inputs.append(s)
    controller.arm(inputs[0])
    controller.start()
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
    if controller.state.name != "RUNNING":
        raise RuntimeError(f"benchmark controller left RUNNING: {controller.supervisor.reason()}")
    return percentiles_us(times)


def timer_pacing(cycles: int = 5000) -> dict:
    """Start-to-start time of the loop's cycles with ``timer`` pacing (absolute deadlines at the
    table's rate) against the sim backend: median, 99th percentile, overruns."""
    from beamctl.hal.sim import SimBackend
    from beamctl.models import build_model
    from beamctl.models.plant import Plant, plant_config
    from beamctl.rt.allocation import geometry
    from beamctl.rt.loop import ControlLoop

    table = load_table(default_table_path())
    config = controller_config({"pacing": "timer"})
    plant = Plant(build_model(table.model_parameters),
                  plant_config({"sample_rate_hz": table.design.sample_rate_hz,
                                "io": table.design.io.to_dict(),
                                "load": {"start": 2000.0, "end": 2000.0}}))
    hal = SimBackend(plant, geometry(config.actuators)).open()
    try:
        result = ControlLoop(Controller(table, config), hal, max_cycles=cycles).run(acquire_rt=False)
    finally:
        hal.close()
    if result.signal_received:
        raise Interrupted(result.signal_received, "the timer pacing measurement")
    cycle = result.timing["cycle"]
    return {"period_us": 1e6 / table.design.sample_rate_hz, "p50": cycle["p50_us"],
            "p99": cycle["p99_us"], "max": cycle["max_us"], "overruns": result.timing["overruns"],
            "cycles": cycle["count"]}


def can_latency(samples: int = 5000) -> dict:
    """Sensor frame sent by the plant emulator -> voltage frame back from the controller,
    over python-can's virtual bus (both in this process, emulator in lockstep)."""
    import can

    from beamctl.hal.budget import LIMIT as BUS_LIMIT
    from beamctl.hal.budget import bus_budget
    from beamctl.hal.can_backend import CanBackend
    from beamctl.hal.dbc import Contract
    from beamctl.hal.emulator import CanPlantEmulator
    from beamctl.models import build_model
    from beamctl.models.plant import Plant, plant_config
    from beamctl.rt.allocation import geometry
    from beamctl.rt.loop import ControlLoop

    table = load_table(default_table_path())
    config = controller_config({"pacing": "sample"})
    plant = Plant(build_model(table.model_parameters),
                  plant_config({"sample_rate_hz": table.design.sample_rate_hz,
                                "io": table.design.io.to_dict(),
                                "load": {"start": 2000.0, "end": 2000.0},
                                "bow": {"amplitude": 5e-5, "angle_deg": 234.0}}))
    channel = f"bench-{time.monotonic_ns()}"
    emulator_bus = can.Bus(interface="virtual", channel=channel)
    emulator = CanPlantEmulator(emulator_bus, plant, geometry(config.actuators), pace="lockstep",
                                latency_samples=samples + 100)
    # CAN FD (1 + 4 Mbit/s) where classic CAN does not carry the table's rate
    classic = bus_budget(Contract(), table.design.sample_rate_hz, 1e6)
    use_fd = classic.load > BUS_LIMIT
    backend = CanBackend(table.design.sample_rate_hz, "virtual", channel, rate_tolerance=0.0, fd=use_fd,
                         data_bitrate_bit_s=4e6 if use_fd else None).open()
    loop = ControlLoop(Controller(table, config), backend, max_cycles=samples + 50)
    emulator.start(samples + 100)
    try:
        result = loop.run(acquire_rt=False)
    finally:
        emulator.stop()
        backend.close()
        emulator_bus.shutdown()
    if result.signal_received:
        raise Interrupted(result.signal_received, "the CAN latency measurement")
    latencies = emulator.latencies_s[100:samples + 50]
    latencies = latencies[np.isfinite(latencies)]
    budget = bus_budget(backend.contract, table.design.sample_rate_hz, 1e6)
    fd = bus_budget(backend.contract, table.design.sample_rate_hz, 1e6, True, 4e6)
    return {**percentiles_us(latencies), "samples": int(latencies.size), "sample_rate_hz":
            table.design.sample_rate_hz, "bus": backend.budget.description,
            "bus_load_percent": 100 * backend.budget.load,
            "max_rate_classic_1M_Hz": budget.max_sample_rate_hz,
            "max_rate_fd_1M_4M_Hz": fd.max_sample_rate_hz}


def sim_realtime_factor() -> dict:
    """Plant seconds per wall second of the experiment's controlled run (default scenario,
    the sim backend through the rt loop, telemetry written)."""
    import tempfile
    from pathlib import Path

    from beamctl.tools.experiment import experiment_config, run_mode
    from beamctl.tools.service import load_gain_table

    cfg, settings = experiment_config()
    with tempfile.TemporaryDirectory() as tmp:
        trace = run_mode("interpolate", cfg, settings, load_gain_table(cfg), Path(tmp))
    return {"factor": trace.plant_s / trace.wall_s, "plant_s": trace.plant_s, "wall_s": trace.wall_s}


def gains_build_time() -> float:
    """Seconds to build the default table: 81 LQR designs and 161 closed-loop checks."""
    from beamctl.gains.build import build_table
    from beamctl.models import build_model

    model = build_model(load_table(default_table_path()).model_parameters)
    start = time.perf_counter()
    table = build_table(model)
    elapsed = time.perf_counter() - start
    if not table.all_stable:
        raise RuntimeError("the default table is no longer stable")
    return elapsed


def add_parser(sub) -> None:
    p = sub.add_parser("bench", help="measure the control step and the other quoted figures")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--steps", type=steps, default=50_000, help="control steps to time (default 50000)")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    result = {"step_us": step_timing(args.steps)}
    lat = can_latency()
    result["can_latency_us"] = {"p50": lat["p50"], "p99": lat["p99"]}
    sim = sim_realtime_factor()
    result["sim_realtime_factor"] = sim["factor"]
    result["gains_build_s"] = gains_build_time()
    result["timer_cycle_us"] = timer_pacing()
    result["can"] = lat
    result["sim"] = sim
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        s = result["step_us"]
        print(f"control step: p50 {s['p50']:.2f} us, p99 {s['p99']:.2f} us ({args.steps} steps)")
        print(f"CAN sensor frame in -> voltage frame out (virtual bus): p50 {lat['p50']:.1f} us, "
              f"p99 {lat['p99']:.1f} us ({lat['samples']} samples)")
        print(f"bus load at {lat['sample_rate_hz']:g} Hz: {lat['bus_load_percent']:.1f} % of {lat['bus']}; "
              f"highest rate on classic CAN 1 Mbit/s {lat['max_rate_classic_1M_Hz']:.0f} Hz "
              f"(CAN FD 1/4 Mbit/s: {lat['max_rate_fd_1M_4M_Hz']:.0f} Hz)")
        print(f"experiment simulation: {sim['factor']:.1f} x real time ({sim['plant_s']:.1f} s of plant "
              f"time in {sim['wall_s']:.1f} s, controlled run)")
        print(f"gain table build (81 points, 161 closed-loop checks): {result['gains_build_s']:.2f} s")
        tc = result["timer_cycle_us"]
        print(f"timer pacing, start to start ({tc['period_us']:.0f} us period, {tc['cycles']} cycles): "
              f"p50 {tc['p50']:.1f} us, p99 {tc['p99']:.1f} us, max {tc['max']:.1f} us, "
              f"{tc['overruns']} overruns")
    finite = [*result["step_us"].values(), *result["can_latency_us"].values()]
    return 0 if all(math.isfinite(v) for v in finite) else 1
