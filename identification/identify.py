"""Identification of the rig: excite the stacks through the HAL at a fixed axial load, record
the four strains and the forces the applied voltages give, and estimate the 4 x 4 frequency
response matrix strains / forces with its coherence.

The excitation runs inside the control loop (rt/loop.py) as the controller's own output, so
everything that guards a control run guards it too: the supervisor's input checks (strain
limit, load range, stale input, late answers), the voltage limits, the ramp to bias on a stop,
a fault or Ctrl-C. Open loop (below the critical load) the stacks sit at bias plus the
excitation; in closed loop (``closed_loop``) the gain table's law runs and the excitation is
added to its voltages. The excitation starts once the load cell has read the requested load for
``SETTLE_S`` (the simulated rig brings the load there itself; in closed loop from below the
critical load, under control); after it, in closed loop, the law keeps holding the beam until the
load is back below ``OPEN_LOOP_LOAD_FRACTION`` of the critical load (the operator lowers it; the
simulated rig does so itself), and only then do the stacks ramp to bias.
A strain that moves more than ``max_strain`` from where it was when the
excitation started ends the run (ramp to bias); nothing is written then.

The inputs are excited one after the other (``supports``: A, B or both: the y and z force of
each), each for one transient period and ``averages`` periods of a periodic signal
(identification/excitation.py). Per input j and output i, over the averaged periods (rectangular window,
one period a segment: a periodic signal has no leakage):

- open loop, the H1 estimator: H_ij = S_(u_j y_i) / S_(u_j u_j), u_j the force the applied
  voltages give (the controller's own stack geometry and force constant);
- closed loop, the same cross-spectra taken against the excitation r_j (the reference), so that
  the feedback of the measurement noise does not bias the estimate: H = S_yr S_ur^-1 over the
  four inputs (which must all be excited);
- coherence gamma^2_ij = |S_(r_j y_i)|^2 / (S_(r_j r_j) S_(y_i y_i)) (in open loop r_j is u_j).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace

import numpy as np
import scipy.signal as sig

from beamctl.assembly.run import (
    ServiceConfig,
    build_hal,
    build_plant,
    check_voltage_range,
    plant_settings,
)
from beamctl.common.signals import Interrupted
from beamctl.config.schema import ConfigError
from beamctl.gains.table import GainTable
from beamctl.hal.base import HalError
from beamctl.identification.excitation import (
    SIGNALS,
    SUPPORT_INPUTS,
    excited_lines,
    force_gains,
    input_names,
    periodic_signal,
    voltage_directions,
)
from beamctl.models import build_model, critical_load, state_space
from beamctl.models.measured import FrfData, nan_matrix
from beamctl.models.plant import LoadRamp
from beamctl.rt.allocation import geometry as controller_geometry
from beamctl.rt.controller import I_LOAD, Controller
from beamctl.rt.loop import ControlLoop, StopRequest
from beamctl.rt.safety import Fault

# open loop only below this fraction of the controller model's critical load: the beam at bias
# is then stiff enough that a small excitation stays small
OPEN_LOOP_LOAD_FRACTION = 0.95
# the rig's load cell must read the requested load within this (N, or fraction of the load) for
# SETTLE_S before the excitation starts, and does so within LOAD_WAIT_S or the run ends
LOAD_TOLERANCE_N = 25.0
LOAD_TOLERANCE_FRACTION = 0.02
SETTLE_S = 0.5
LOAD_WAIT_S = 120.0
MIN_AVERAGES = 3
MAX_RUN_S = 3600.0                  # rig time of one identification
TRANSIENT_TIME_CONSTANTS = 5.0
# the simulated rig, closed loop: the load rises under control from this fraction of the model's
# critical load to the requested one at this rate (as an operator would bring it there)
CLOSED_LOOP_START_FRACTION = 0.8
SIM_LOAD_RATE_N_PER_S = 200.0


class IdentificationError(Exception):
    """The identification could not give a measurement (a fault, the strain limit, a load
    that is not the requested one); the stacks were ramped to bias."""


@dataclass(frozen=True)
class IdentifySettings:
    load_n: float
    signal: str = "multisine"
    band_hz: tuple[float, float] = (10.0, 1200.0)
    amplitude_v: float = 5.0
    resolution_hz: float = 1.0
    averages: int = 8
    supports: str = "AB"
    closed_loop: bool = False
    max_strain: float = 3e-4
    seed: int = 0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["band_hz"] = list(self.band_hz)
        return d


@dataclass
class Recording:
    """What one identification run recorded, per excited input: the strains, the applied
    forces and the excitation's force along that input, one row per excitation sample."""

    inputs: tuple[int, ...]
    period_samples: int
    periods: int                        # per input, the transient ones included
    transient: int                      # periods dropped at the start of each input
    strains: np.ndarray                 # [n x 4]
    forces: np.ndarray                  # [n x 4]
    reference: np.ndarray               # [n] the excitation's force along its input
    loads_n: np.ndarray                 # [n]


def check_settings(s: IdentifySettings, cfg: ServiceConfig, sample_rate_hz: float) -> None:
    """Refuse what cannot be run safely or cannot give a measurement, naming the flag."""
    if s.signal not in SIGNALS:
        raise ConfigError("--signal", s.signal, f"one of {', '.join(SIGNALS)}")
    if s.supports not in SUPPORT_INPUTS:
        raise ConfigError("--supports", s.supports, "A, B or AB")
    if not (math.isfinite(s.load_n) and s.load_n >= 0):
        raise ConfigError("--load", s.load_n, "a load in N, >= 0")
    if not s.averages >= MIN_AVERAGES:
        raise ConfigError("--averages", s.averages,
                          f"at least {MIN_AVERAGES} periods to average (with fewer, the coherence of pure "
                          f"noise is 1 / averages >= 0.5, and tells measured from noise no more)")
    a = cfg.controller.actuators
    room = min(a.bias_voltage_v - a.min_voltage_v, a.max_voltage_v - a.bias_voltage_v)
    if not 0 < s.amplitude_v <= room:
        raise ConfigError("--amplitude", s.amplitude_v,
                          f"a stack swing in V, > 0 and at most {room:g} V (bias {a.bias_voltage_v:g} V "
                          f"within the limits {a.min_voltage_v:g}..{a.max_voltage_v:g} V)")
    if not 0 < s.max_strain:
        raise ConfigError("--max-strain", s.max_strain, "a strain amplitude > 0")
    if s.closed_loop and s.supports != "AB":
        raise ConfigError("--supports", s.supports,
                          "AB with --closed-loop: under feedback every force moves, so all four "
                          "must be excited to separate them")
    if not s.closed_loop:
        critical = critical_load(build_model(cfg.model))
        if s.load_n >= OPEN_LOOP_LOAD_FRACTION * critical:
            raise ConfigError("--load", s.load_n,
                              f"a load below {OPEN_LOOP_LOAD_FRACTION:g} x the model's critical load "
                              f"{critical:.0f} N for an open-loop identification (the stacks at bias "
                              f"do not hold the beam there); use --closed-loop above it")
    periodic_signal(s.signal, sample_rate_hz, s.band_hz, s.resolution_hz, s.seed)   # its own checks
    inputs = len(SUPPORT_INPUTS[s.supports])
    duration = inputs * (s.averages + transient_periods(cfg, s, 1.0 / s.resolution_hz)) / s.resolution_hz
    if duration > MAX_RUN_S:
        raise ConfigError("--averages", s.averages,
                          f"fewer periods or a coarser --resolution: {inputs} inputs x the periods of "
                          f"1 / {s.resolution_hz:g} Hz take {duration:.0f} s of rig time, more than "
                          f"{MAX_RUN_S:g} s")


def transient_periods(cfg: ServiceConfig, s: IdentifySettings, period_s: float) -> int:
    """Periods to drop before averaging: at least one, and at least ``TRANSIENT_TIME_CONSTANTS``
    decay times of the model's slowest stable mode at the load (a lightly damped beam near its
    critical load rings for seconds)."""
    poles = np.linalg.eigvals(state_space(build_model(cfg.model), s.load_n)[0])
    decay = -poles.real[poles.real < 0]
    slowest_s = 1.0 / decay.min() if len(decay) else 0.0
    return max(1, math.ceil(TRANSIENT_TIME_CONSTANTS * slowest_s / period_s))


def excitation_plan(s: IdentifySettings, cfg: ServiceConfig, sample_rate_hz: float):
    """(the [n x 6] voltage rows, the reference force [n], inputs, period, periods per input)."""
    g = controller_geometry(cfg.controller.actuators)     # the controller's belief of the stacks
    directions = voltage_directions(g)
    gains = force_gains(g)
    inputs = SUPPORT_INPUTS[s.supports]
    transient = transient_periods(cfg, s, 1.0 / s.resolution_hz)
    periods = s.averages + transient
    rows, reference = [], []
    for k, j in enumerate(inputs):
        e = periodic_signal(s.signal, sample_rate_hz, s.band_hz, s.resolution_hz, s.seed + 7919 * k)
        values = np.tile(e.values, periods) * s.amplitude_v
        rows.append(np.outer(values, directions[j]))
        reference.append(values * gains[j])
    period = len(e.values)
    return np.vstack(rows), np.concatenate(reference), inputs, period, periods, transient


def record(cfg: ServiceConfig, table: GainTable, s: IdentifySettings, progress=None,
           stop: StopRequest | None = None) -> Recording:
    """Run the excitation through the configured HAL and record it (see the module docstring).
    Raises IdentificationError (the stacks at bias) or Interrupted (Ctrl-C, SIGTERM)."""
    rate = table.design.sample_rate_hz
    check_settings(s, cfg, rate)
    excitation, reference, inputs, period, periods, transient = excitation_plan(s, cfg, rate)
    n = len(excitation)
    if cfg.hal.backend == "sim":
        start = s.load_n
        if s.closed_loop:
            start = min(s.load_n, CLOSED_LOOP_START_FRACTION * critical_load(build_model(cfg.model)))
        load = {"start": start, "end": s.load_n, "rate": SIM_LOAD_RATE_N_PER_S, "hold": 0.0}
        sim_plant = build_plant(cfg, table, {"load": load})
        hal = build_hal(cfg, table, sim_plant)
    else:
        sim_plant = None
        try:
            hal = build_hal(cfg, table)
        except HalError as exc:             # the hal section describes a bus or DBC it cannot have
            raise ConfigError(f"hal.{cfg.hal.backend}", cfg.hal.can["channel"], f"a bus that can be opened "
                              f"({exc})", cfg.source) from None
        check_voltage_range(cfg, hal)
    controller = Controller(table, replace(cfg.controller, pacing="sample"), excitation=excitation,
                            law=s.closed_loop)
    controller.excitation_enabled = False           # until the load has settled at s.load_n
    strains = np.zeros((n, 4))
    forces = np.zeros((n, 4))
    loads = np.zeros(n)
    state = {"stop": "", "start": None, "cycles": 0, "settled": 0, "recorded": 0, "holding": False,
             "missed_before": 0}
    tolerance = max(LOAD_TOLERANCE_N, LOAD_TOLERANCE_FRACTION * s.load_n)
    settle, wait = round(SETTLE_S * rate), round(LOAD_WAIT_S * rate)
    every = max(1, n // 200)

    # closed loop above the critical load, the stacks hold the beam until the load is back below
    # where the beam stands without them
    safe_load = OPEN_LOOP_LOAD_FRACTION * critical_load(build_model(cfg.model))

    def on_cycle(loop: ControlLoop) -> None:
        c = loop.controller
        k = c.excitation_index
        if state["holding"]:
            hold_until_safe(loop, c)
            return
        if state["stop"]:
            return
        if not c.excitation_enabled:
            wait_for_load(loop, c)
            return
        if k <= state["recorded"]:
            return
        state["recorded"] = k
        i = k - 1
        strains[i] = c.strains
        forces[i] = c.applied_forces
        loads[i] = c.record[I_LOAD]
        deviation = float(np.max(np.abs(strains[i] - state["start"])))
        if deviation > s.max_strain:
            end(loop, c, f"a strain moved {deviation:.3g} from its value at the start, beyond "
                         f"--max-strain {s.max_strain:g}: the excitation was stopped (lower --amplitude, "
                         f"or check the rig)")
            return
        if progress is not None and (k % every == 0 or k >= n):
            j = inputs[min(i // (periods * period), len(inputs) - 1)]
            progress(k, n, f"force {input_names((j,))[0]}")
        if k >= n:
            lost = _samples_missed(loop) - state["missed_before"]
            end(loop, c, f"{lost} samples the DAQ sent never reached the controller during the excitation: "
                         f"the record has gaps; repeat the identification" if lost else "")

    def end(loop: ControlLoop, c: Controller, reason: str) -> None:
        """The excitation is over (``reason``: why, if it is no measurement). Open loop the stacks
        ramp to bias now; closed loop the law holds the beam until the load is back below the
        critical load (the simulated rig lowers it; on the rig the operator does)."""
        state["stop"] = reason
        c.excitation_enabled = False
        if not s.closed_loop:
            loop.request_stop(reason or "excitation done")
            return
        state["holding"] = True
        if sim_plant is not None and sim_plant.axial_load > safe_load:
            sim_plant.follow_load(LoadRamp(sim_plant.axial_load, CLOSED_LOOP_START_FRACTION * safe_load,
                                           SIM_LOAD_RATE_N_PER_S, hold=sim_plant.time))
        hold_until_safe(loop, c)

    def hold_until_safe(loop: ControlLoop, c: Controller) -> None:
        load = c.record[I_LOAD]
        if load < safe_load:
            state["holding"] = False
            loop.request_stop(state["stop"] or "excitation done")
        elif progress is not None and state["cycles"] % every == 0:
            progress(state["recorded"], n, f"lower the load below {safe_load:.0f} N")
        state["cycles"] += 1

    def wait_for_load(loop: ControlLoop, c: Controller) -> None:
        """The excitation starts once the load cell has read the requested load for SETTLE_S."""
        state["cycles"] += 1
        load = c.record[I_LOAD]
        state["settled"] = state["settled"] + 1 if abs(load - s.load_n) <= tolerance else 0
        if state["settled"] >= settle:
            state["start"] = c.strains.copy()
            state["missed_before"] = _samples_missed(loop)
            c.excitation_enabled = True
        elif state["cycles"] > wait:
            end(loop, c, f"the load cell reads {load:.0f} N, not the requested {s.load_n:g} N (within "
                         f"{tolerance:.0f} N), after {LOAD_WAIT_S:g} s: set the rig's load first")
        elif progress is not None and state["cycles"] % every == 0:
            progress(0, n, f"load {load:.0f} N")

    loop = ControlLoop(controller, hal, stop_on_fault=True, on_cycle=on_cycle, stop=stop)
    try:
        result = loop.run(acquire_rt=False)
    except HalError as exc:                 # the HAL would not open: nothing was excited
        raise IdentificationError(f"the {cfg.hal.backend} backend failed: {exc}") from None
    finally:
        hal.close()
    if result.signal_received:
        raise Interrupted(result.signal_received, "the identification (the stacks ramped to bias)")
    if controller.supervisor.fault != Fault.NONE:
        raise IdentificationError(f"the controller faulted: {controller.supervisor.reason()} "
                                  f"(the stacks ramped to bias; nothing written)")
    if state["stop"]:
        raise IdentificationError(f"{state['stop']}; the stacks ramped to bias, nothing written")
    if controller.excitation_index < n:
        raise IdentificationError(f"the run ended after {controller.excitation_index} of {n} excitation "
                                  f"samples ({result.reason or result.state})")
    return Recording(inputs=inputs, period_samples=period, periods=periods, transient=transient,
                     strains=strains, forces=forces, reference=reference, loads_n=loads)


def _samples_missed(loop: ControlLoop) -> int:
    """Samples the hardware sent that never reached the controller so far (backends that count
    them: CAN's sequence numbers)."""
    return int(loop.hal.status().get("samples_missed", 0))


def estimate(rec: Recording, sample_rate_hz: float, band_hz: tuple[float, float],
             closed_loop: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frequencies [nf], H [nf x 4 x 4], coherence [nf x 4 x 4]) from a recording, at the
    lines of the period within the band (see the module docstring)."""
    p = rec.period_samples
    freqs = np.fft.rfftfreq(p, 1.0 / sample_rate_hz)
    keep = excited_lines(p, sample_rate_hz, band_hz)
    nf = len(keep)
    s_yr = np.zeros((nf, 4, 4), dtype=complex)   # [f, output, input j]
    s_ur = np.zeros((nf, 4, 4), dtype=complex)   # [f, force, input j]
    coherence = nan_matrix(nf)[1]
    kwargs = {"fs": sample_rate_hz, "window": "boxcar", "nperseg": p, "noverlap": 0, "detrend": False}
    for k, j in enumerate(rec.inputs):
        rows = averaged(rec, k)
        r = rec.forces[rows, j] if not closed_loop else rec.reference[rows]
        _, s_rr = sig.welch(r, **kwargs)
        for i in range(4):
            _, c_ry = sig.csd(r, rec.strains[rows, i], **kwargs)
            _, c_ru = sig.csd(r, rec.forces[rows, i], **kwargs)
            _, s_yy = sig.welch(rec.strains[rows, i], **kwargs)
            s_yr[:, i, j] = c_ry[keep]
            s_ur[:, i, j] = c_ru[keep]
            with np.errstate(invalid="ignore", divide="ignore"):
                coherence[:, i, j] = np.abs(c_ry[keep]) ** 2 / (s_rr[keep] * s_yy[keep])
    frf = nan_matrix(nf)[0]
    cols = list(rec.inputs)
    if closed_loop:
        # H S_ur = S_yr  <=>  S_ur^T H^T = S_yr^T
        frf[:] = np.linalg.solve(s_ur.transpose(0, 2, 1), s_yr.transpose(0, 2, 1)).transpose(0, 2, 1)
    else:
        for j in cols:
            frf[:, :, j] = s_yr[:, :, j] / s_ur[:, j, j][:, None]
    return freqs[keep], frf, np.clip(coherence, 0.0, 1.0, where=np.isfinite(coherence), out=coherence)


def averaged(rec: Recording, k: int) -> slice:
    """The samples of the k-th excited input's averaged periods (its transient dropped)."""
    per_input = rec.periods * rec.period_samples
    return slice(k * per_input + rec.transient * rec.period_samples, (k + 1) * per_input)


def static_means(rec: Recording) -> dict[str, list[float]]:
    """The mean strains and stack forces over the averaged periods (the excitation has no mean:
    what is left is the beam at rest at the measurement's load; models/authority.py uses it)."""
    parts = [averaged(rec, k) for k in range(len(rec.inputs))]
    return {"strain": [float(x) for x in np.concatenate([rec.strains[r] for r in parts]).mean(axis=0)],
            "force_n": [float(x) for x in np.concatenate([rec.forces[r] for r in parts]).mean(axis=0)]}


def identify(cfg: ServiceConfig, table: GainTable, s: IdentifySettings, progress=None,
             stop: StopRequest | None = None) -> tuple[FrfData, dict]:
    """Record and estimate; returns the measurement and a report (timing, counts)."""
    start = time.perf_counter()
    rate = table.design.sample_rate_hz
    rec = record(cfg, table, s, progress, stop)
    freqs, frf, coherence = estimate(rec, rate, s.band_hz, s.closed_loop)
    a = cfg.controller.actuators
    io = plant_settings(cfg, table).io if cfg.hal.backend == "sim" else table.design.io
    settings = {"identify": s.to_dict(), "backend": cfg.hal.backend, "config": cfg.source,
                "gain_table": str(cfg.table_path), "inputs": input_names(rec.inputs),
                "period_samples": rec.period_samples, "resolution_hz": rate / rec.period_samples,
                "bias_voltage_v": a.bias_voltage_v, "orientation_deg": list(a.orientation_deg),
                "transient_periods": rec.transient, "static": static_means(rec)}
    data = FrfData(frequencies_hz=freqs, frf=frf, coherence=coherence, load_n=float(np.mean(rec.loads_n)),
                   sample_rate_hz=rate, force_constant_n_per_v=a.force_constant_n_per_v, io=io.to_dict(),
                   settings=settings)
    report = {"wall_s": time.perf_counter() - start, "rig_s": len(rec.loads_n) / rate,
              "samples": len(rec.loads_n), "transient_periods": rec.transient,
              "mean_load_n": data.load_n}
    return data, report
