"""``beamctl bench``: the figures the documentation quotes, measured in one run
(bench/measure.py)."""

from __future__ import annotations

import argparse
import json
import math
import sys

from beamctl.bench.measure import (
    LIVE_CASES,
    can_latency,
    command_times,
    gains_build_time,
    live_view_timing,
    offline_timing,
    sim_realtime_factor,
    step_timing,
    timer_pacing,
)
from beamctl.gains.defaults import default_table_path
from beamctl.gains.table import load_table
from beamctl.tools.argtypes import number, steps
from beamctl.tools.progress import ProgressBar


def print_offline(result: dict) -> None:
    for k, r in enumerate(result["rounds"], 1):
        print(f"round {k}: loop {r['loop_us']:.2f} us/sample, kernel {r['kernel_cold_us']:.2f} (cold) / "
              f"{r['kernel_warm_us']:.2f} (warm) us/sample: x{r['ratio_cold']:.1f} / x{r['ratio_warm']:.1f}; "
              f"{r['cycles']} samples, {100 * r['kernel_share']:.1f} % in the kernel; held to 1 mm at "
              f"{r['held_load_n'][0]:.1f} / {r['held_load_n'][1]:.1f} N, largest deflection difference "
              f"{r['max_deflection_difference_m']:.1e} m")
    m = result["median"]
    print(f"median over {len(result['rounds'])} rounds: loop {m['loop_us']:.2f} us/sample, kernel "
          f"{m['kernel_cold_us']:.2f} (cold) / {m['kernel_warm_us']:.2f} (warm); "
          f"ratio x{m['ratio_cold']:.1f} / x{m['ratio_warm']:.1f} "
          f"(numba compile or cache load {result['compile_or_cache_load_s']:.1f} s)")


def add_parser(sub) -> None:
    p = sub.add_parser(
        "bench", help="measure the control step and the other quoted figures",
        description="Measures, in one run, the figures the documentation quotes: the compiled control "
                    "step, the controller's answer latency with the DAQ emulator in its own process over "
                    "the local CAN transport, the simulation's real-time factor, a gain table build, the "
                    "timer pacing and the live view's cost. About 2.5 minutes (--quick: about 30 s, "
                    "fewer samples, coarser percentiles); progress on stderr. Medians and percentiles, "
                    "never a pass/fail: the machine is shared.")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--quick", action="store_true",
                   help="a short run: 10000 steps, 5 s of answers, shorter timer and live-view runs")
    p.add_argument("--steps", type=steps, default=None, help="control steps to time (default 50000)")
    p.add_argument("--latency-s", type=number(low=1.0), default=None,
                   help="seconds of answers to measure the CAN latency over (default 60)")
    p.add_argument("--offline", action="store_true",
                   help="only the offline simulation: the experiment's run through the loop and the "
                        "compiled kernel, per-sample cost and ratio")
    p.add_argument("--repeat", type=number(low=1, integer=True), default=3,
                   help="rounds of --offline and --commands (default 3)")
    p.add_argument("--live", action="store_true",
                   help="only the loop's timing with and without a live view (beamctl monitor)")
    p.add_argument("--commands", action="store_true",
                   help="only whole commands, each a process of its own as a user starts it: `beamctl "
                        "gains build --no-robust` and `beamctl experiment`, in turn, --repeat rounds after "
                        "a warm-up (default 3; about 3 minutes here), median, least and most")
    p.set_defaults(run=run)


def print_live_view_timing(lv: dict) -> None:
    print(f"live view, timer pacing ({lv['period_us']:.0f} us period, {lv['cycles']} cycles, median of "
          f"{lv['rounds']} rounds), telemetry written, real-time set-up {lv['realtime']}:")
    for case in LIVE_CASES:
        r = lv[case]
        line = (f"  {case:17s} cycle p50 {r['cycle_p50']:.1f} us, p99 {r['cycle_p99']:.1f} us; "
                f"step p50 {r['step_p50']:.2f} us; {r['overruns']:.0f} overruns")
        if "ratio" in r:
            q = r["ratio"]
            line += (f"; / without: {q['cycle_p50']:.3f}, {q['cycle_p99']:.3f}, {q['step_p50']:.3f}; "
                     f"datagrams {r['sent']} sent, {r['dropped']} dropped")
        print(line)


def run(args: argparse.Namespace) -> int:
    if args.offline:
        result = offline_timing(args.repeat)
        if args.json:
            print(json.dumps(result, indent=1))
        else:
            print_offline(result)
        return 0
    if args.commands:
        with ProgressBar("bench") as bar:
            try:
                times = command_times(args.repeat, progress=bar)
            except RuntimeError as exc:     # a command timed ended in an error: which, and why
                bar.close()
                print(f"beamctl bench: {exc}", file=sys.stderr)
                return 1
            bar.close()
        if args.json:
            print(json.dumps({"commands": times}, indent=1))
        else:
            print(f"whole commands, wall time, median of {args.repeat} after a warm-up (least, most):")
            for name, t in times.items():
                print(f"  beamctl {name:24s} {t['median_s']:6.2f} s  ({t['min_s']:.2f}, {t['max_s']:.2f})")
        return 0
    if args.live:
        lv = live_view_timing()
        if args.json:
            print(json.dumps({"live_view": lv}, indent=1))
        else:
            print_live_view_timing(lv)
        return 0
    quick = args.quick
    args.steps = args.steps or (10_000 if quick else 50_000)
    args.latency_s = args.latency_s or (5.0 if quick else 60.0)
    rate = load_table(default_table_path()).design.sample_rate_hz
    # (what, rough seconds on this 2-core machine: the weights of the progress and its time left)
    stages = [("control step", 2 + args.steps / 10_000), ("CAN latency", 8 + args.latency_s),
              ("simulation", 10), ("gain table build", 10), ("timer pacing", 2 if quick else 5),
              ("live view", 6 if quick else 30)]
    total = sum(w for _, w in stages)
    done = 0.0
    result: dict = {}
    with ProgressBar("bench") as bar:
        for k, (name, weight) in enumerate(stages):
            bar(int(done), int(total), f"{k + 1}/{len(stages)} {name}")
            if name == "control step":
                result["step_us"] = step_timing(args.steps)
            elif name == "CAN latency":
                lat = can_latency(round(args.latency_s * rate))
                result["can_latency_us"] = {key: lat[key] for key in ("p50", "p99", "p99.9", "max")}
            elif name == "simulation":
                sim = sim_realtime_factor()
                result["sim_realtime_factor"] = sim["factor"]
            elif name == "gain table build":
                result["gains_build_s"] = gains_build_time()
            elif name == "timer pacing":
                result["timer_cycle_us"] = timer_pacing(2000 if quick else 5000)
            else:
                result["live_view"] = (live_view_timing(cycles=3000, rounds=2) if quick
                                       else live_view_timing())
            done += weight
        bar(int(total), int(total), "done")
        bar.close()
    result["can"] = lat
    result["sim"] = sim
    result["quick"] = quick
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        s = result["step_us"]
        c, p = s["compiled"], s["call"]
        print(f"control step ({args.steps} steps): the compiled cycle p50 {c['p50']:.2f} us, p99 "
              f"{c['p99']:.2f} us (CPU cycle counter); called from Python as the loop does p50 "
              f"{p['p50']:.2f} us, p99 {p['p99']:.2f} us (x{s['call_over_compiled_p50']:.2f})")
        print(f"CAN latency, strain frame sent -> voltage frame sent, emulator in its own process "
              f"({lat['transport'].split(':')[0]}): p50 {lat['p50']:.1f} us, p99 {lat['p99']:.1f} us, "
              f"p99.9 {lat['p99.9']:.1f} us, max {lat['max']:.0f} us over {lat['samples']} samples "
              f"({lat['samples'] / lat['sample_rate_hz']:.0f} s); {lat['over_half_period']} later than "
              f"half a period ({lat['half_period_us']:.0f} us), {lat['late']} later than the answer budget; "
              f"{lat['ended']}")
        st = lat.get("daq_stalls")
        if st:
            per = ", ".join(f"{x:.2f}" for x in st["per_minute_ms"]) or "none"
            up = (f"up to {st['rides_through_up_to_N']:g} N" if st["rides_through_up_to_N"] is not None
                  else "at no load")
            print(f"stalls seen by the DAQ (the stacks held one voltage): "
                  f"longest {st['longest_samples']} samples "
                  f"({st['longest_ms']:.2f} ms), per minute of plant time {per} ms; the shipped table rides "
                  f"through that {up} of its {st['table_top_N']:g} N at the reference operating point "
                  f"(`beamctl gains show`)")
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
        print_live_view_timing(result["live_view"])
    finite = [result["step_us"]["p50"], result["step_us"]["p99"], *result["can_latency_us"].values()]
    return 0 if all(math.isfinite(v) for v in finite) else 1
