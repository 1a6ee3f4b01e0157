"""``beamctl experiment``: the paper's experiment (section 4, figure 7) on the software plant,
through the same rt loop and HAL as on the rig.

Each mode runs the load ramp on a fresh plant with the same scenario and the same rig:
- ``uncontrolled``: the controller is armed but never started (stacks at bias); it still
  estimates q from the strains, which is what the deflection is measured with;
- ``interpolate``: the shipped gain table, linear interpolation, anti-windup on;
- ``paper``: the experiment's setup, gains for 0..3500 N every 500 N switched stepwise and
  an integrator without anti-windup; its allocation is ``experiment.paper_allocation``:
  ``scale`` (the default, as the other runs: a force the stacks cannot give is scaled down,
  its direction kept) or ``clip`` (the paper's: each stack clipped at its own limit).
The rig may differ from the controller's belief: the plant's own beam (``plant.model``), its
own stacks (``hal.sim.own_actuators``) and its I/O chain (``plant.io``: transport delay,
anti-aliasing and reconstruction filters, models/iochain.py); the report states the chain and
the controller design of each run.
A run ends when the measured deflection passes ``experiment.deflection_limit`` or the ramp
reaches its end. A controller fault does not end a run: the beam is watched until it fails.
SIGINT or SIGTERM during a run ramps the stacks to bias (the loop's stop) and raises
``Interrupted``: a run cut short is no result.

Deflection, as the paper measures it (figure 7): the lateral deflection along the beam
reconstructed from the strain gauges, Phi (C0 Phi)^-1 y, its largest magnitude. The report
also gives the simulated beam's true elastic deflection: under control the two differ, since
the integral action zeroes the strain at the gauges and leaves a small deflection shaped to
have no curvature there (0.05 mm at 2000 N with the default bow), which gauges cannot see.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np

from beamctl.assembly import live as live_view
from beamctl.assembly.run import (
    ServiceConfig,
    build_plant,
    load_gain_table,
    plant_geometry,
    plant_parameters,
    plant_settings,
    service_config,
)
from beamctl.common.signals import Interrupted
from beamctl.config.schema import (
    ConfigError,
    boolean,
    choice,
    merge,
    positive,
    read_yaml,
    validate,
)
from beamctl.gains.build import build_table
from beamctl.gains.table import GainTable, require_checked
from beamctl.hal import create as create_backend
from beamctl.models import build_model, critical_load
from beamctl.models.modal import Deflection
from beamctl.models.plant import plant_config
from beamctl.models.rig import Rig
from beamctl.rt.config import ALLOCATION_MODES
from beamctl.rt.controller import Controller
from beamctl.rt.loop import ControlLoop, StopRequest
from beamctl.rt.telemetry import TelemetryWriter
from beamctl.simulation.simkernel import Accelerator, RunMonitor

MODES = ("uncontrolled", "interpolate", "paper")
DECIMATE = 10
PAPER_TARGETS_N = {"0.5mm": 2438.0, "1.0mm": 2723.0}

# The shipped scenario. The bow amplitude is fitted (Southwell, w = a Fx / (Fcr - Fx)) so that
# the uncontrolled beam reaches 0.5 mm and 1.0 mm as close as one amplitude allows to the
# paper's 2438 N and 2723 N (equal relative error on both); the direction is the paper's
# passive buckling direction. Noise: 0.2 ue RMS on the strains, 2 N on the load cell.
BOW_AMPLITUDE_M = 1.61e-4
SCENARIO: dict = {
    "plant": {"bow": {"amplitude": BOW_AMPLITUDE_M, "angle_deg": 234.0},
              "load": {"start": 260.0, "end": 4000.0, "rate": 50.0, "hold": 0.5},
              "noise": {"strain": 2e-7, "load": 2.0, "seed": 1}},
    "experiment": {"deflection_limit": 1.5e-3, "paper_mode": True, "paper_allocation": "scale"},
}
_EXPERIMENT_SCHEMA = {"deflection_limit": positive("m"), "paper_mode": boolean(),
                      "paper_allocation": choice(*ALLOCATION_MODES)}


@dataclass
class RunTrace:
    """Decimated record of one run."""

    mode: str
    load_n: list = field(default_factory=list)
    deflection_m: list = field(default_factory=list)       # measured (gauges)
    deflection_y_m: list = field(default_factory=list)     # components at the largest magnitude
    deflection_z_m: list = field(default_factory=list)
    true_deflection_m: list = field(default_factory=list)  # the plant's elastic deflection
    v_min: list = field(default_factory=list)
    v_max: list = field(default_factory=list)
    saturated: list = field(default_factory=list)          # the allocation could not give the force
    voltages: list = field(default_factory=list)
    state: list = field(default_factory=list)
    wall_s: float = 0.0
    plant_s: float = 0.0
    end: str = ""
    fault: str = ""
    telemetry: str = ""
    engine: str = "loop"
    cycles: int = 0
    kernel_cycles: int = 0        # of ``cycles``, those the compiled kernel ran
    plant_critical_load_n: float = math.nan     # the simulated rig's own Fx,cr

    def arrays(self) -> dict:
        return {k: np.asarray(v) for k, v in self.__dict__.items() if isinstance(v, list)}


def experiment_config(data: dict | None = None, source: str = "") -> tuple[ServiceConfig, dict]:
    """The scenario over the shipped defaults: (service config, experiment settings). The
    simulated rig (``plant``, its own ``plant.model`` and ``plant.io``) is checked now, before
    any table is built or run (its sample rate against the table's when the plant is built)."""
    merged = merge(SCENARIO, data or {})
    experiment = validate(merged.pop("experiment"), _EXPERIMENT_SCHEMA, source, "experiment.")
    cfg = service_config(merged, source)
    if cfg.hal.backend != "sim":
        raise ConfigError("hal.backend", cfg.hal.backend,
                          "'sim': beamctl experiment runs the simulated rig (`beamctl run` drives "
                          "the rig over CAN)", source)
    plant_config(cfg.plant, source, "plant.")
    plant_parameters(cfg)
    return cfg, experiment


def load_experiment_config(path: str | Path | None) -> tuple[ServiceConfig, dict]:
    return experiment_config(read_yaml(path) if path else {}, str(path) if path else "defaults")


# stacks that do not limit: the controller's belief and the rig's own force per volt both scaled
# by this (their ratio, the rig's stack gain, kept), so that 150 V gives 4 times the force
UNLIMITED_STACKS = 4.0


def rig_scenario(table: GainTable, table_path: str, rig: Rig,
                 force_constant_n_per_v: float = 3.0, stack_scale: float = UNLIMITED_STACKS,
                 ramp: dict | None = None) -> dict:
    """A scenario of ``beamctl experiment`` for a rig (models/rig.py: the robust check's worst,
    say) run by the table at ``table_path``: the rig's own beam, I/O delay and DAQ rate, and
    stacks whose force per volt the controller believes ``force_constant_n_per_v`` x
    ``stack_scale`` while the rig's are that times its ``force_gain`` (force does not limit)."""
    plant: dict = {"load": dict(ramp or {}), "io": {"delay_samples": float(rig.chain.delay_samples)},
                   "sample_rate_hz": float(rig.sample_rate_hz), "model": rig.params.to_dict()}
    gain = float(rig.force_gain)
    believed = force_constant_n_per_v * stack_scale
    return {"model": table.model_parameters.to_dict(), "gains": {"table": str(table_path)}, "plant": plant,
            "controller": {"actuators": {"force_constant_n_per_v": believed}},
            "hal": {"sim": {"own_actuators": True, "actuators": {"force_constant_n_per_v": believed * gain}}},
            "experiment": {"paper_mode": False}}


def paper_table(cfg: ServiceConfig) -> GainTable:
    """The experiment's gains: 0..3500 N every 500 N, switched stepwise (built for this run),
    under the rule of every table that runs: refused unless its closed-loop check passed."""
    # a simulated run has no missing samples or late answers: no ride-through analysis (the
    # controller then rides through what a table without one does, which this run never needs)
    table = build_table(build_model(cfg.model), mode="paper", analyse_ride_through=False)
    require_checked(table, "the paper's switching table for this model",
                    "leave its run out with --no-paper (experiment.paper_mode: false); "
                    "`beamctl gains build --mode paper --config F --out paper.yaml` shows the check")
    return table


def design_label(table: GainTable | None) -> str:
    """The controller design a run used, in words, for the report (``None``: the uncontrolled
    run): the table's design kind, rate, grid and schedule, and the I/O chain it assumes."""
    if table is None:
        return "none (controller armed, stacks at bias)"
    d, s = table.design, table.schedule
    schedule = "interpolated" if s.mode == "interpolate" else "switched (paper)"
    kind = (f"integral LQR, {d.sample_rate_hz:g} Hz, velocity filter {d.velocity_cutoff_hz:g} Hz"
            if d.kind == "integral-lqr" else f"{d.kind}, {d.sample_rate_hz:g} Hz")
    chain = "a direct I/O chain" if d.io.is_direct else f"the I/O chain: {d.io.describe()}"
    return (f"{kind}, gains at {len(table.loads_n)} loads {table.loads_n[0]:g}..{table.loads_n[-1]:g} N "
            f"{schedule}; assumes {chain}")


def experiment_tables(cfg: ServiceConfig, settings: dict) -> dict[str, GainTable]:
    """The gain table of every run, in the order of the runs, each loaded and checked before
    the first run starts (a table that may not run is refused now, not after two runs)."""
    modes = MODES if settings["paper_mode"] else MODES[:2]
    shipped = load_gain_table(cfg)
    return {mode: paper_table(cfg) if mode == "paper" else shipped for mode in modes}


ENGINES = ("auto", "loop", "kernel")


def check_engine(engine: str, telemetry: bool = False) -> str:
    """The engine a run will use: ``loop`` (every cycle through ``ControlLoop``) or ``kernel``
    (simulation/simkernel.py runs the cycles in one compiled loop, the loop a fault's ramp and what
    needs Python). ``auto`` takes the kernel unless telemetry is asked for. Both run the
    engine's compiled cycle."""
    if engine not in ENGINES:
        raise ConfigError("engine", engine, f"one of {', '.join(ENGINES)}")
    if engine == "auto":
        return "loop" if telemetry else "kernel"
    if engine == "kernel" and telemetry:
        raise ConfigError("engine", engine, "'loop' or 'auto' with telemetry: the kernel records none")
    return engine


def run_allocation(mode: str, cfg: ServiceConfig, settings: dict) -> str:
    """The allocation a run uses: ``experiment.paper_allocation`` for the paper's run, the
    controller's own for the others."""
    return settings["paper_allocation"] if mode == "paper" else cfg.controller.allocation


def run_mode(mode: str, cfg: ServiceConfig, settings: dict, table: GainTable,
             telemetry_dir: Path | None = None, progress=None, stop: StopRequest | None = None,
             engine: str = "auto", live: str | None = None) -> RunTrace:
    """One load ramp with ``table``; full-rate telemetry into ``telemetry_dir/telemetry_<mode>.btl``
    if given, live values to ``beamctl monitor`` at the socket ``live`` if given. ``engine``:
    see ``check_engine`` (a run with telemetry or a live view runs in the loop); both give the
    same run."""

    engine = check_engine(engine, telemetry_dir is not None or live is not None)
    controller_cfg = replace(cfg.controller, pacing="sample",
                             anti_windup=cfg.controller.anti_windup if mode == "interpolate" else False,
                             allocation=run_allocation(mode, cfg, settings))
    plant = build_plant(cfg, table)
    hal = create_backend("sim", plant=plant, geometry=plant_geometry(cfg), pace="simulated")
    controller = Controller(table, controller_cfg)
    monitor = RunMonitor(controller, plant, Deflection(build_model(cfg.model)), settings["deflection_limit"],
                         plant.config.load.duration(), decimate=DECIMATE, progress=progress, label=mode)
    trace = RunTrace(mode)
    accelerator = Accelerator(controller, hal, monitor) if engine == "kernel" else None

    hal.open()
    telemetry = publisher = None
    start = time.perf_counter()
    try:
        if live is not None:
            source = f" ({cfg.source})" if cfg.source else ""
            publisher = live_view.live_publisher(live, controller, f"beamctl experiment, {mode} run{source}")
        if telemetry_dir is not None or publisher is not None:
            path = None if telemetry_dir is None else telemetry_dir / f"telemetry_{mode}.btl"
            telemetry = TelemetryWriter.for_controller(
                path, controller, meta={"mode": mode, "scenario": cfg.source}, live=publisher).start()
            trace.telemetry = "" if path is None else str(path)
        loop = ControlLoop(controller, hal, telemetry=telemetry, stop_on_fault=False, stop=stop,
                           start=(mode != "uncontrolled"), on_cycle=monitor, accelerator=accelerator)
        if publisher is not None:
            live_view.watch_loop(publisher, loop, telemetry)
        result = loop.run(acquire_rt=False)
    finally:
        hal.close()
        if telemetry is not None:
            telemetry.close()
        if publisher is not None:
            publisher.close()
    if result.signal_received:
        raise Interrupted(result.signal_received, f"the {mode} run")
    trace.wall_s = time.perf_counter() - start
    trace.plant_s = plant.time
    for name, values in monitor.arrays().items():
        setattr(trace, name, values.tolist())
    trace.voltages = monitor.voltages
    trace.end, trace.fault = monitor.end, monitor.fault
    trace.engine = engine
    trace.cycles = result.cycles
    trace.kernel_cycles = accelerator.kernel_cycles if accelerator is not None else 0
    trace.plant_critical_load_n = plant.critical_load
    return trace


def first_crossing(load: np.ndarray, values: np.ndarray, threshold: float) -> float | None:
    """The load at which ``values`` first exceeds ``threshold`` (linear between samples)."""
    above = np.flatnonzero(values > threshold)
    if not above.size:
        return None
    i = int(above[0])
    if i == 0:
        return float(load[0])
    frac = (threshold - values[i - 1]) / (values[i] - values[i - 1])
    return float(load[i - 1] + frac * (load[i] - load[i - 1]))


def direction_at(deflection_m: np.ndarray, y_m: np.ndarray, z_m: np.ndarray,
                 threshold: float) -> float | None:
    """The direction of the deflection (deg from +y towards +z, 0..360) where its magnitude
    first exceeds ``threshold``, else at the last sample (None without samples)."""
    above = np.flatnonzero(deflection_m > threshold)
    i = int(above[0]) if above.size else len(deflection_m) - 1
    if i < 0:
        return None
    return math.degrees(math.atan2(z_m[i], y_m[i])) % 360.0


def angle_at(trace: RunTrace, threshold: float) -> float | None:
    a = trace.arrays()
    return direction_at(a["deflection_m"], a["deflection_y_m"], a["deflection_z_m"], threshold)


def summarise(trace: RunTrace, design: str, allocation: str) -> dict:
    a = trace.arrays()
    load, d = a["load_n"], a["deflection_m"]
    below_3000 = load <= 3000.0
    out = {
        "load_at_0.5mm_N": first_crossing(load, d, 0.5e-3),
        "load_at_1.0mm_N": first_crossing(load, d, 1.0e-3),
        "buckling_angle_deg": angle_at(trace, 1.0e-3),
        "max_voltage_V": float(a["v_max"].max()) if a["v_max"].size else None,
        "min_voltage_V": float(a["v_min"].min()) if a["v_min"].size else None,
        "max_deflection_below_3000N_mm": float(d[below_3000].max() * 1e3) if below_3000.any() else None,
        "true_max_deflection_below_3000N_mm": (float(a["true_deflection_m"][below_3000].max() * 1e3)
                                               if below_3000.any() else None),
        "design": design,
        "allocation": allocation,
        "end": trace.end,
        "fault": trace.fault,
        "plant_time_s": trace.plant_s,
        "wall_time_s": trace.wall_s,
        "telemetry": trace.telemetry,
    }
    return out


def run_experiment(cfg: ServiceConfig, settings: dict, tables: dict[str, GainTable],
                   telemetry_dir: Path | None = None, progress=None,
                   stop: StopRequest | None = None, engine: str = "auto",
                   live: str | None = None) -> tuple[dict, dict[str, RunTrace]]:
    """Run every mode of ``tables`` (``experiment_tables``) in turn; return the summary and the
    runs' traces. Full-rate telemetry of each run goes into ``telemetry_dir`` if given, live
    values to ``beamctl monitor`` at the socket ``live`` if given."""
    modes = tuple(tables)
    engine = check_engine(engine, telemetry_dir is not None or live is not None)
    done = dict.fromkeys(modes, 0.0)
    lock = threading.Lock()

    def step(mode: str, fraction: float, label: str) -> None:
        if progress:
            with lock:
                done[mode] = fraction
                progress(round(1000 * sum(done.values()) / len(modes)), 1000, label)

    def run(mode: str) -> RunTrace:
        return run_mode(mode, cfg, settings, tables[mode], telemetry_dir, partial(step, mode), stop, engine,
                        live)

    started = time.perf_counter()
    traces = {mode: run(mode) for mode in modes}
    wall_s = time.perf_counter() - started
    if progress:
        progress(1000, 1000, "done")
    io = plant_settings(cfg, tables[modes[0]]).io
    summary: dict = {"critical_load_N": critical_load(build_model(cfg.model)),
                     "plant_critical_load_N": critical_load(build_model(plant_parameters(cfg))),
                     "io_chain": {"description": io.describe(), **io.to_dict()}}
    names = {"uncontrolled": "uncontrolled", "interpolate": "controlled", "paper": "paper_switching"}
    for mode, trace in traces.items():
        design = design_label(None if mode == "uncontrolled" else tables[mode])
        summary[names[mode]] = summarise(trace, design, run_allocation(mode, cfg, settings))
    plant_s = sum(t.plant_s for t in traces.values())
    summary["scenario"] = {"source": cfg.source, "bow_amplitude_mm": 1e3 * cfg.plant["bow"]["amplitude"],
                           "bow_angle_deg": cfg.plant["bow"]["angle_deg"],
                           "force_constant_N_per_V": cfg.controller.actuators.force_constant_n_per_v,
                           "rig_force_constant_N_per_V": plant_geometry(cfg).force_constant_n_per_v,
                           "plant_model": cfg.plant_model,
                           "load_rate_N_per_s": cfg.plant["load"]["rate"],
                           "deflection_limit_mm": 1e3 * settings["deflection_limit"]}
    summary["sim_realtime_factor"] = plant_s / wall_s if wall_s else None
    summary["engine"] = {mode: trace.engine for mode, trace in traces.items()}
    return summary, traces
