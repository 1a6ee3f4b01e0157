"""Offline runs in a compiled kernel: a simulated run's cycles without Python per sample.

A simulated load ramp (``beamctl experiment``, a study's experiment sample) runs the same cycle
as the rig: per sample the sim backend's measurement of the plant, the engine's control cycle
(rt/engine.py ``cycle``, the one compiled implementation the service runs too: checks, schedule,
law, allocation and clamp, every fault decision), the stacks' forces on the rig and the plant's
step, and the experiment's monitor. ``run_cycles`` runs these cycles in one compiled loop that
calls the engine's ``cycle`` and the plant's compiled ``measure`` and ``step``
(models/plantstep.py, the ones models/plant.py calls: the end stops included) itself; only the
monitor's arithmetic is written here (tests/simulation/test_simkernel.py compares the two runs).

It hands over to the loop after any cycle that leaves the controller neither RUNNING nor ARMED
(a fault or a stop: the loop then runs the ramp to bias), and before any cycle the loop must run
itself: a stop, a re-arm or an operator command, a DAQ gone silent, telemetry (a run with
telemetry runs in the loop). It returns for what needs Python: a new discretisation of the plant
(a new load cell), a new block of measurement noise, the monitor's progress and end check.

Not kept in kernel cycles: the loop's per-stage timing (a simulated sample has none worth
measuring).
``Accelerator`` is the ``ControlLoop`` hook: offered each cycle, it runs as many
kernel cycles as it can and returns how many. Numba keys a disk cache on this file alone; the
kernel's cache is dropped when the engine it calls has changed (``kernel``).
"""

from __future__ import annotations

import math

import numpy as np

from beamctl.hal.sim import SimBackend
from beamctl.models import plantstep
from beamctl.rt import engine as e
from beamctl.rt.safety import Fault, State

# what a call of run_cycles ends on
DONE = 0            # the cycle budget is spent
EVENT = 1           # the controller left RUNNING and ARMED: the loop runs the next cycles
NEED_NOISE = 2      # the next cycle needs a new block of measurement noise
NEED_CELL = 3       # the plant crossed into another load cell: a discretisation to fetch
MONITOR = 4         # a monitor entry needs Python (progress, voltages, the end check)
MONITOR_FULL = 5    # the monitor's arrays are full

# float scalars (in and out)
F_TIME, F_LOAD = range(2)
# float constants
(F_PERIOD, F_RAMP_START, F_RAMP_END, F_RAMP_RATE, F_RAMP_HOLD, F_CELL, F_LIMIT, F_END_TIME) = range(2, 10)
F_ON_STOPS = 10     # the time the beam first came to rest on its end stops (NaN: not yet; in and out)
N_F = 11
# integer scalars (in and out)
(K_NOISE, K_SEQUENCE, K_BIN, K_COUNTER, K_ENTRIES, K_CYCLES) = range(6)
# integer constants
(K_MONITOR, K_DECIMATE, K_CALLBACK_EVERY) = range(6, 9)
N_K = 9


def _run_cycles(f, k, budget, state, work, ad, bd, c_meas, meas_lo, inputs, history, noise, stop_rows,
                stop_out, ik, pf, buf, iv, fv, mats, rig_force, rig_bias, vy, vz, lateral, q_lo, mon,
                scratch):
    """Run up to ``budget`` cycles; return (why it stopped, cycles run). ``f`` and ``k`` carry
    the plant's and the monitor's scalars in and out; ``buf``, ``iv``, ``fv``, ``mats`` are the
    controller's engine arrays; the other arrays the plant's and the monitor's own, changed in
    place."""
    rig_f = scratch[0:4]
    strains = scratch[4:8]
    cycles = 0
    while cycles < budget:
        # -- the sample the sim backend reads (measure: C x behind the filter, noise) ------------
        i_noise = k[K_NOISE]
        if i_noise >= noise.shape[0]:
            return NEED_NOISE, cycles
        plantstep.measure(state, c_meas, meas_lo, noise, i_noise, strains)
        for j in range(4):
            fv[e.IN_Y + j] = strains[j]
        k[K_SEQUENCE] += 1
        fv[e.IN_TIME] = f[F_TIME]
        fv[e.IN_SEQUENCE] = k[K_SEQUENCE]
        fv[e.IN_LOAD] = f[F_LOAD] + noise[i_noise, 4]
        fv[e.IN_MISSED] = 0.0
        k[K_NOISE] = i_noise + 1
        # -- the engine's cycle ----------------------------------------------------------------------
        controller_state = e.cycle(buf, iv, fv, mats, 1)
        buf[e.I_OPERATOR_COMMAND] = 0.0             # no operator's command in a kernel cycle
        # -- the write: the rig's stacks' forces, the plant's step --------------------------------
        for j in range(4):
            acc = 0.0
            for m in range(6):
                acc += rig_force[j, m] * (buf[e.I_V + m] - rig_bias[m])
            rig_f[j] = acc
        pf[plantstep.P_LOAD] = f[F_LOAD]
        plantstep.step(state, work, ad, bd, inputs, history, stop_rows, stop_out, rig_f, ik, pf)
        if ik[plantstep.K_RESTED] == 1 and not f[F_ON_STOPS] == f[F_ON_STOPS]:
            f[F_ON_STOPS] = f[F_TIME]
        t_new = f[F_TIME] + f[F_PERIOD]
        f[F_TIME] = t_new
        if t_new <= f[F_RAMP_HOLD]:
            new_load = f[F_RAMP_START]
        else:
            travel = f[F_RAMP_RATE] * (t_new - f[F_RAMP_HOLD])
            if f[F_RAMP_END] >= f[F_RAMP_START]:
                new_load = min(f[F_RAMP_START] + travel, f[F_RAMP_END])
            else:
                new_load = max(f[F_RAMP_START] - travel, f[F_RAMP_END])
        f[F_LOAD] = new_load
        cycles += 1
        k[K_CYCLES] += 1
        # -- the experiment's monitor -----------------------------------------------------------------
        if k[K_MONITOR] == 1:
            k[K_COUNTER] += 1
            if k[K_COUNTER] % k[K_DECIMATE] == 0:
                best, by, bz = -1.0, 0.0, 0.0
                for b in range(vy.shape[0]):
                    a1 = 0.0
                    a2 = 0.0
                    for m in range(4):
                        a1 += vy[b, m] * buf[e.I_Q + m]
                        a2 += vz[b, m] * buf[e.I_Q + m]
                    mag = math.hypot(a1, a2)
                    if mag > best:
                        best, by, bz = mag, a1, a2
                true = -1.0
                for b in range(lateral.shape[1]):
                    a1 = 0.0
                    a2 = 0.0
                    for m in range(lateral.shape[2]):
                        a1 += lateral[0, b, m] * state[q_lo + m]
                        a2 += lateral[1, b, m] * state[q_lo + m]
                    mag = math.hypot(a1, a2)
                    if mag > true:
                        true = mag
                n_e = k[K_ENTRIES]
                vmin, vmax = buf[e.I_V], buf[e.I_V]
                for j in range(1, 6):
                    vmin = min(vmin, buf[e.I_V + j])
                    vmax = max(vmax, buf[e.I_V + j])
                mon[0, n_e] = new_load
                mon[1, n_e] = best
                mon[2, n_e] = by
                mon[3, n_e] = bz
                mon[4, n_e] = true
                mon[5, n_e] = vmin
                mon[6, n_e] = vmax
                mon[7, n_e] = controller_state
                mon[8, n_e] = 1.0 if (fv[e.X_SCALE_A] < 1.0 or fv[e.X_SCALE_B] < 1.0) else 0.0
                k[K_ENTRIES] = n_e + 1
                if (k[K_COUNTER] % k[K_CALLBACK_EVERY] == 0 or best > f[F_LIMIT]
                        or t_new >= f[F_END_TIME]):
                    return MONITOR, cycles
                if n_e + 1 >= mon.shape[1]:
                    return MONITOR_FULL, cycles
        # -- a fault or a stop: the loop runs the ramp ------------------------------------------------
        if controller_state != e.S_RUNNING and controller_state != e.S_ARMED:
            return EVENT, cycles
        # -- a new load cell needs a discretisation --------------------------------------------------
        ratio = new_load / f[F_CELL]
        cell = math.floor(ratio + 0.5)
        if cell != k[K_BIN] or abs(ratio - math.floor(ratio) - 0.5) < 1e-9:
            return NEED_CELL, cycles
    return DONE, cycles


_kernel = None


def kernel():
    """The compiled ``run_cycles`` (numba; compiled once per process, cached on disk where the
    package's folder is writable, and recompiled when the engine or the plant's step it calls has changed:
    ``engine.compile_caller``)."""
    global _kernel
    if _kernel is None:
        _kernel = e.compile_caller(_run_cycles, callees=(plantstep,))
    return _kernel


class Accelerator:
    """The ``ControlLoop`` hook that runs a simulated run's cycles in the kernel.

    ``monitor``: the run's ``RunMonitor`` (the loop's ``on_cycle``), or None. Built once per run
    before the loop starts; every array the kernel uses is the plant's, the controller's and the
    monitor's own."""

    def __init__(self, controller, hal, monitor=None) -> None:

        if type(hal) is not SimBackend:
            raise TypeError("the simulation kernel runs the sim backend only")
        self.run_cycles = kernel()
        self.controller = controller
        self.hal = hal
        self.plant = hal.plant
        self.monitor = monitor
        self.kernel_cycles = 0
        self._f = np.zeros(N_F)
        self._k = np.zeros(N_K, dtype=np.int64)
        self._rig_force = np.ascontiguousarray(hal._force_matrix)
        self._rig_bias = np.ascontiguousarray(hal._bias)
        plant = self.plant
        self._c_meas = np.ascontiguousarray(plant._c)
        if monitor is not None:
            self._vy, self._vz = monitor.deflection._vy, monitor.deflection._vz
        else:
            self._vy = self._vz = np.zeros((1, 4))
        self._lateral = np.ascontiguousarray(plant._lateral)
        self._scratch = np.zeros(8)
        f, k = self._f, self._k
        f[F_PERIOD] = plant.period_s
        f[F_CELL] = 2.0 * plant.config.load_tolerance
        k[K_MONITOR] = 1 if monitor is not None else 0
        if monitor is not None:
            k[K_DECIMATE] = monitor.decimate
            k[K_CALLBACK_EVERY] = monitor.decimate * monitor.callback_every
            f[F_LIMIT], f[F_END_TIME] = monitor.limit, monitor.end_time
        else:
            k[K_DECIMATE] = k[K_CALLBACK_EVERY] = 1
            f[F_LIMIT] = f[F_END_TIME] = math.inf

    def eligible(self, loop) -> bool:
        """Whether the next cycles are the kernel's kind: sample pacing on the simulated sim
        backend, no telemetry, the controller RUNNING or ARMED without a fault, nothing asked of
        the loop."""
        c, hal, plant = self.controller, self.hal, self.plant
        if loop.pacing != "sample" or loop.telemetry is not None or hal._silent or hal.pace != "simulated":
            return False
        if loop._stop_signal or loop._rearm_requested or (loop.stop is not None and loop.stop.reason):
            return False
        if getattr(loop, "_command", None) is not None:
            return False
        if loop.on_cycle is not self.monitor:
            return False
        if c.state not in (State.RUNNING, State.ARMED) or c.supervisor.fault != Fault.NONE:
            return False
        return plant._feedthrough is None and hal.is_open

    def __call__(self, loop) -> int:
        """Run as many cycles as the kernel can; return how many (0: the loop runs the next)."""
        if not self.eligible(loop):
            return 0
        c, hal, plant, monitor = self.controller, self.hal, self.plant, self.monitor
        f, k = self._f, self._k
        ramp = plant.config.load
        f[F_RAMP_START], f[F_RAMP_END], f[F_RAMP_RATE], f[F_RAMP_HOLD] = (ramp.start, ramp.end, ramp.rate,
                                                                          ramp.hold)
        f[F_TIME], f[F_LOAD] = plant.time, plant.axial_load
        k[K_NOISE], k[K_SEQUENCE] = plant._noise_index, hal._sequence
        f[F_ON_STOPS] = math.nan if plant.on_stops_since is None else plant.on_stops_since
        k[K_BIN], k[K_CYCLES] = plant._bin, 0
        budget = (loop.max_cycles - loop.cycles) if loop.max_cycles is not None else 1 << 62
        if monitor is not None:
            k[K_COUNTER] = monitor.counter
            if monitor.ended:
                k[K_MONITOR] = 0
        total = 0
        while budget - total > 0:
            if monitor is not None and k[K_MONITOR] == 1:
                mon = monitor.reserve()
                k[K_ENTRIES] = 0
            else:
                mon = _NO_MONITOR
            why, n = self.run_cycles(
                f, k, budget - total, plant._state, plant._work, plant._ad, plant._bd,
                self._c_meas, plant._measured.start, plant._inputs, plant._history, plant._noise_block,
                plant._stop_rows, plant._stop_out, plant._ik, plant._pf, c._buffer, c.iv, c.fv, c._mats,
                self._rig_force, self._rig_bias, self._vy, self._vz,
                self._lateral, plant._q.start, mon, self._scratch)
            total += n
            # the scalars back where the objects keep them
            plant.time, plant.axial_load = f[F_TIME], f[F_LOAD]
            plant._noise_index = int(k[K_NOISE])
            if f[F_ON_STOPS] == f[F_ON_STOPS]:
                plant.on_stops_since = float(f[F_ON_STOPS])
            hal._sequence = int(k[K_SEQUENCE])
            if monitor is not None and k[K_MONITOR] == 1:
                monitor.counter = int(k[K_COUNTER])
                monitor.commit(int(k[K_ENTRIES]))
            if why == NEED_NOISE:
                plant._refill_noise()
                k[K_NOISE] = plant._noise_index
                continue
            if why == NEED_CELL:
                plant._use_load(plant.axial_load)
                k[K_BIN] = plant._bin
                continue
            if why == MONITOR:
                self._sync(loop)
                monitor.after_entry(loop)
                if monitor.ended:
                    break
                continue
            if why == MONITOR_FULL:
                continue
            break
        self._sync(loop)
        return total

    def _sync(self, loop) -> None:
        """The loop's and the backend's counts after the kernel's cycles, as the loop would have
        left them (the controller's state is the engine's arrays themselves)."""
        c, hal, k = self.controller, self.hal, self._k
        done = int(k[K_CYCLES])
        k[K_CYCLES] = 0
        hal.reads += done
        hal.writes += done
        loop.cycles += done
        self.kernel_cycles += done
        if done:
            hal.publish_status(c.record[e.I_STATE], c.record[e.I_FAULT], int(c.record[e.I_FLAGS]))
            loop._last_sample = loop.clock()


_NO_MONITOR = np.zeros((9, 1))


class RunMonitor:
    """A simulated run's decimated trace (every ``decimate``-th cycle: load, deflection from the
    gauges and its components, the plant's true deflection, voltage range, state, whether the
    allocation was saturated), its end (the
    deflection limit or the ramp's end: the loop is asked to stop) and its progress. The loop's
    ``on_cycle`` in loop cycles; the kernel fills the same arrays in its own."""

    FIELDS = ("load_n", "deflection_m", "deflection_y_m", "deflection_z_m", "true_deflection_m",
              "v_min", "v_max", "state", "saturated")

    def __init__(self, controller, plant, deflection, limit: float, end_time: float, decimate: int = 10,
                 callback_every: int = 50, progress=None, label: str = "") -> None:
        self.controller = controller
        self.plant = plant
        self.deflection = deflection
        self.limit = float(limit)
        self.end_time = float(end_time)
        self.decimate = int(decimate)
        self.callback_every = int(callback_every)
        self.progress = progress
        self.label = label
        self.counter = 0
        self.entries = 0
        self._data = np.zeros((len(self.FIELDS), 4096))
        self.voltages: list[tuple] = []
        self.end = ""
        self.fault = ""

    @property
    def ended(self) -> bool:
        return bool(self.end)

    def reserve(self) -> np.ndarray:
        """A view of the free columns for the kernel (grown when full)."""
        if self.entries + 1 >= self._data.shape[1]:
            self._data = np.concatenate([self._data, np.zeros_like(self._data)], axis=1)
        return self._data[:, self.entries:]

    def commit(self, n: int) -> None:
        self.entries += n

    def __call__(self, loop) -> None:
        self.counter += 1
        if self.end or self.counter % self.decimate:     # after its end the run is over: not recorded
            return
        c, plant = self.controller, self.plant
        d, dy, dz = self.deflection(c.q)
        v = c.voltages
        col = self.reserve()[:, 0]
        alloc = c.allocator
        col[:] = (plant.axial_load, d, dy, dz, plant.deflection()[0], float(v.min()), float(v.max()),
                  int(c.state), alloc.scale_a < 1.0 or alloc.scale_b < 1.0)
        self.commit(1)
        self.after_entry(loop)

    def after_entry(self, loop) -> None:
        """What follows an entry: progress and voltages every ``callback_every`` entries, the
        end check."""
        c, plant = self.controller, self.plant
        if self.counter % (self.callback_every * self.decimate) == 0:
            self.voltages.append((plant.axial_load, *c.voltages.tolist()))
            if self.progress:
                self.progress(min(plant.time / self.end_time, 1.0), f"{self.label} {plant.axial_load:4.0f} N")
        d = self._data[1, self.entries - 1]
        if d > self.limit:
            self.end = f"deflection passed {self.limit * 1e3:g} mm at {plant.axial_load:.0f} N"
        elif plant.time >= self.end_time:
            self.end = f"ramp ended at {plant.axial_load:.0f} N"
        if self.end:
            supervisor = c.supervisor
            self.fault = supervisor.reason() if supervisor.fault != Fault.NONE else ""
            loop.request_stop(self.end)

    def arrays(self) -> dict[str, np.ndarray]:
        data = self._data[:, :self.entries]
        out = {name: data[i].copy() for i, name in enumerate(self.FIELDS)}
        out["state"] = out["state"].astype(int)
        out["saturated"] = out["saturated"].astype(bool)
        return out

