"""``beamctl bench``: the figures the README quotes, measured in one run."""

from __future__ import annotations

import argparse
import gc
import json
import math
import time

import numpy as np

from gains.defaults import default_table_path
from gains.table import load_table
from hal.base import Sample
from rt.config import controller_config
from rt.controller import Controller


def percentiles_us(seconds: np.ndarray) -> dict:
    return {"p50": float(np.percentile(seconds, 50) * 1e6), "p99": float(np.percentile(seconds, 99) * 1e6)}


def step_timing(samples: int = 50_000) -> dict:
    """Median and 99th percentile of one control step (estimator, schedule, law, allocation,
    safety) in a running controller, over a sweep of loads and vibrating strains."""
    table = load_table(default_table_path())
    controller = Controller(table, controller_config({"start_ramp_time": 0.0}))
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


def add_parser(sub) -> None:
    p = sub.add_parser("bench", help="measure the control step and the other quoted figures")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--steps", type=int, default=50_000, help="control steps to time (default 50000)")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    result = {"step_us": step_timing(args.steps)}
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        s = result["step_us"]
        print(f"control step: p50 {s['p50']:.2f} us, p99 {s['p99']:.2f} us ({args.steps} steps)")
    return 0 if all(math.isfinite(v) for v in result["step_us"].values()) else 1
