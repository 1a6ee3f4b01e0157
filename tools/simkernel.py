"""Offline runs in a compiled kernel: the cycles of a simulated run in which nothing happens.

A simulated load ramp (``beamctl experiment``, a study's experiment sample) spends almost all
of its cycles in one state: the controller RUNNING (or ARMED, for the uncontrolled run), a new
sample every cycle, no fault, no operator. ``run_cycles`` runs such cycles, with the arithmetic
of one pass of ``ControlLoop._cycle_until_done`` over the sim backend (the plant's measurement,
the control step of rt/controller.py with its schedule, allocation and saturation count, the
stacks' forces on the rig, the plant's step) and the experiment's monitor, compiled with numba.

It hands over to the loop, without touching anything, whenever the next cycle would do more
than that: a sample that trips a check (strain, load cell, table range), the saturation count
reaching its limit, a stop, a re-arm or an operator command, a DAQ gone silent. The loop then
runs that cycle itself, with the same code as on the rig, and offers the next one to the
kernel again. The kernel also returns for what needs Python: a new discretisation of the plant
(a new load cell), a new block of measurement noise, the monitor's progress and end check.

Not kept in kernel cycles: the loop's per-stage timing (a simulated sample has none worth
measuring) and telemetry (a run with telemetry runs in the loop).

``Accelerator`` is the ``ControlLoop`` hook: offered each cycle, it runs as many kernel cycles
as it can and returns how many. The record layout, flag bits and states are passed to the
kernel as data, so that a change in rt/controller.py can never meet a stale compiled copy.
Requires numba (``pip install 'beamctl[fast]'``).
"""

from __future__ import annotations

import math

import numpy as np

from beamctl.rt import controller as ctl
from beamctl.rt.safety import Fault, State

# what a call of run_cycles ends on
DONE = 0            # the cycle budget is spent
EVENT = 1           # the next cycle does more than the kernel does: the loop runs it
NEED_NOISE = 2      # the next cycle needs a new block of measurement noise
NEED_CELL = 3       # the plant crossed into another load cell: a discretisation to fetch
MONITOR = 4         # a monitor entry needs Python (progress, voltages, the end check)
MONITOR_FULL = 5    # the monitor's arrays are full

# float scalars (in and out)
F_TIME, F_LOAD, F_FILTERED, F_SCALE_A, F_SCALE_B, F_SAFETY_TIME = range(6)
# float constants
(F_PERIOD, F_ALPHA, F_HALF_BAND, F_FIRST, F_LAST, F_STRAIN_LIMIT, F_LOAD_LOW, F_LOAD_HIGH,
 F_RAMP_START, F_RAMP_END, F_RAMP_RATE, F_RAMP_HOLD, F_CELL, F_V_MIN, F_V_MAX, F_V_MID, F_SPAN,
 F_SPAN_FITS, F_LIMIT, F_END_TIME) = range(6, 26)
N_F = 26
# integer scalars (in and out)
(K_NOISE, K_HEAD, K_SEQUENCE, K_INDEX, K_SATURATED, K_STEPS, K_BIN, K_COUNTER, K_ENTRIES, K_CYCLES,
 K_MISSING) = range(11)
# integer constants
(K_RUNNING, K_START_SAMPLES, K_SAT_LIMIT, K_PAPER, K_ANTI_WINDUP, K_FRACTIONAL, K_DELAYED, K_MONITOR,
 K_DECIMATE, K_CALLBACK_EVERY, K_STATE) = range(11, 22)
N_K = 22

# the record's layout, as data
(L_TIME, L_SEQUENCE, L_FLAGS, L_LOAD, L_LOAD_FILTERED, L_Q, L_U, L_V, L_SCALE_A, L_SCALE_B,
 L_INPUT_PERIOD, L_ANSWER_AGE, L_STRAINS, L_XI, L_APPLIED, L_FLAG_SAT_A, L_FLAG_SAT_B, L_FLAG_HELD,
 L_FLAG_FADING, L_OPERATOR) = range(20)


def layout() -> np.ndarray:
    """Column indices and flag bits of rt/controller.py's record, for the kernel."""
    c = ctl.COL
    return np.array([ctl.I_TIME, ctl.I_SEQUENCE, ctl.I_FLAGS, ctl.I_LOAD, ctl.I_LOAD_FILTERED,
                     c["q_1y"], c["force_y_A_N"], c["voltage_a1_V"], ctl.I_SCALE_A, ctl.I_SCALE_B,
                     ctl.I_INPUT_PERIOD_US, ctl.I_ANSWER_AGE_US, c["strain_y1"], c["xi_1y"],
                     c["applied_force_y_A_N"], ctl.FLAG_SATURATED_A, ctl.FLAG_SATURATED_B,
                     ctl.FLAG_INTEGRATOR_HELD, ctl.FLAG_FADING_IN, ctl.I_OPERATOR_COMMAND], dtype=np.int64)


def _run_cycles(f, k, lay, budget, state, nxt, ad, bd, c_meas, meas_lo, inputs, history, noise,
                buffer, n_record, c0phiinv, t_h, ctl_force, bias, out_blocks, upd_blocks, int_blocks,
                weights, loads, coef, rig_force, rig_bias, vy, vz, lateral, q_lo, mon, scratch):
    """Run up to ``budget`` cycles; return (why it stopped, cycles run). ``f`` and ``k`` carry
    the scalars in and out; the arrays are the plant's, the controller's and the monitor's own,
    changed in place. A cycle that would do more than the kernel does is left untouched."""
    n_states = state.shape[0]
    n_x = buffer.shape[0] - n_record                # compensator states
    sig = n_record - 12                             # the record's signal vector [y; xi; u_applied]
    i_strain, i_xi, i_applied = lay[L_STRAINS], lay[L_XI], lay[L_APPLIED]
    i_q, i_u, i_v = lay[L_Q], lay[L_U], lay[L_V]
    m_sig = 12 + n_x
    s = scratch[0:m_sig]
    tmp = scratch[m_sig:m_sig + 2 * n_x]
    y = scratch[m_sig + 2 * n_x + 8:m_sig + 2 * n_x + 12]
    u = scratch[m_sig + 2 * n_x + 12:m_sig + 2 * n_x + 16]
    dxi = scratch[m_sig + 2 * n_x + 16:m_sig + 2 * n_x + 20]
    target = scratch[m_sig + 2 * n_x + 20:m_sig + 2 * n_x + 26]
    rig_f = scratch[m_sig + 2 * n_x + 26:m_sig + 2 * n_x + 30]
    tmp_out = scratch[m_sig + 2 * n_x + 30:m_sig + 2 * n_x + 38]
    forced = scratch[m_sig + 2 * n_x + 38:m_sig + 2 * n_x + 38 + n_states]
    running = k[K_RUNNING] == 1
    paper = k[K_PAPER] == 1
    n_loads = loads.shape[0]
    last_index = n_loads - 1
    n_inputs = inputs.shape[0]
    hist_len = history.shape[0]
    cycles = 0
    while cycles < budget:
        # -- the sample the sim backend would read (measure: C x behind the filter, noise) --------
        i_noise = k[K_NOISE]
        if i_noise >= noise.shape[0]:
            return NEED_NOISE, cycles
        for j in range(4):
            acc = 0.0
            for m in range(c_meas.shape[1]):
                acc += c_meas[j, m] * state[meas_lo + m]
            y[j] = acc + noise[i_noise, j]
        load = f[F_LOAD] + noise[i_noise, 4]
        flags = 0
        index = k[K_INDEX]
        filtered = f[F_FILTERED]
        w1 = weights[1]
        scale_a, scale_b = f[F_SCALE_A], f[F_SCALE_B]
        if running:
            # -- safety.check_inputs: a reading that trips is the loop's ---------------------------
            limit = f[F_STRAIN_LIMIT]
            for j in range(4):
                if not abs(y[j]) <= limit:
                    return EVENT, cycles
            if not (f[F_LOAD_LOW] <= load <= f[F_LOAD_HIGH]):
                return EVENT, cycles
            # -- schedule.follow -----------------------------------------------------------------
            filtered = filtered + f[F_ALPHA] * (load - filtered)
            if filtered < f[F_FIRST] or filtered > f[F_LAST]:
                return EVENT, cycles
            if paper:
                while index < last_index and filtered > loads[index] + f[F_HALF_BAND]:
                    index += 1
                while index > 0 and filtered < loads[index - 1] - f[F_HALF_BAND]:
                    index -= 1
            else:
                if filtered <= f[F_FIRST]:
                    index, w1 = 0, 0.0
                elif filtered >= f[F_LAST]:
                    index, w1 = last_index, 0.0
                else:
                    index = np.searchsorted(loads, filtered, side="right") - 1
                    if index < 0:
                        index = 0
                    if index > last_index:
                        index = last_index
                    w1 = filtered - loads[index]
            w0 = weights[0]
            # -- integral action with anti-windup --------------------------------------------------
            for j in range(4):
                acc = 0.0
                for m in range(4):
                    acc += t_h[j, m] * y[m]
                dxi[j] = acc
            for m in range(4):
                s[m] = y[m]
                s[8 + m] = buffer[i_applied + m]
            for m in range(n_x):
                s[12 + m] = buffer[n_record + m]
            held = False
            if k[K_ANTI_WINDUP] == 1 and (scale_a < 1.0 or scale_b < 1.0):
                for j in range(8):
                    acc = 0.0
                    for m in range(4):
                        acc += int_blocks[index, j, m] * dxi[m]
                    tmp_out[j] = acc
                du0 = w0 * tmp_out[0] + w1 * tmp_out[4]
                du1 = w0 * tmp_out[1] + w1 * tmp_out[5]
                du2 = w0 * tmp_out[2] + w1 * tmp_out[6]
                du3 = w0 * tmp_out[3] + w1 * tmp_out[7]
                u0, u1, u2, u3 = buffer[i_u], buffer[i_u + 1], buffer[i_u + 2], buffer[i_u + 3]
                held = ((scale_a < 1.0 and du0 * u0 + du1 * u1 > 0.0)
                        or (scale_b < 1.0 and du2 * u2 + du3 * u3 > 0.0))
            if held:
                flags += lay[L_FLAG_HELD]
                for m in range(4):
                    s[4 + m] = buffer[i_xi + m]
            else:
                for m in range(4):
                    s[4 + m] = buffer[i_xi + m] + dxi[m]
            # -- u = -(C x_c + D y) - Ki xi ---------------------------------------------------------
            np.dot(out_blocks[index], s, tmp_out)
            for j in range(4):
                u[j] = w0 * tmp_out[j] + w1 * tmp_out[4 + j]
            # -- allocation (rt/allocation.py, scale mode) ---------------------------------------------
            for support in range(2):
                fy, fz = u[2 * support], u[2 * support + 1]
                if not (fy - fy == 0.0 and fz - fz == 0.0):
                    fy = math.nan
                    fz = math.nan
                g1 = coef[support, 0, 0] * fy + coef[support, 0, 1] * fz
                g2 = coef[support, 1, 0] * fy + coef[support, 1, 1] * fz
                g3 = coef[support, 2, 0] * fy + coef[support, 2, 1] * fz
                hi = g1 if g1 > g2 else g2
                hi = hi if hi > g3 else g3
                lo = g1 if g1 < g2 else g2
                lo = lo if lo < g3 else g3
                spread = hi - lo
                if spread <= f[F_SPAN_FITS]:
                    scale = 1.0
                elif spread < math.inf:
                    scale = f[F_SPAN] / spread
                else:
                    scale = 0.0
                    g1 = g2 = g3 = hi = lo = 0.0
                centre = f[F_V_MID] - scale * 0.5 * (hi + lo)
                for st in range(3):
                    g = g1 if st == 0 else (g2 if st == 1 else g3)
                    v = centre + scale * g
                    target[3 * support + st] = f[F_V_MIN] if v < f[F_V_MIN] else (
                        f[F_V_MAX] if v > f[F_V_MAX] else v)
                if support == 0:
                    scale_a = scale
                else:
                    scale_b = scale
            saturated = scale_a < 1.0 or scale_b < 1.0
            if saturated and k[K_SATURATED] + 1 >= k[K_SAT_LIMIT]:
                return EVENT, cycles        # persistent saturation: the loop latches the fault
            if scale_a < 1.0:
                flags += lay[L_FLAG_SAT_A]
            if scale_b < 1.0:
                flags += lay[L_FLAG_SAT_B]
            # -- commit: the step as the controller makes it ---------------------------------------
            buffer[lay[L_LOAD_FILTERED]] = filtered
            for j in range(4):
                acc = 0.0
                for m in range(4):
                    acc += c0phiinv[j, m] * y[m]
                buffer[i_q + j] = acc
                buffer[i_strain + j] = y[j]
                buffer[i_xi + j] = s[4 + j]
                buffer[i_u + j] = u[j]
            buffer[lay[L_SCALE_A]] = scale_a
            buffer[lay[L_SCALE_B]] = scale_b
            steps = k[K_STEPS] + 1
            k[K_STEPS] = steps
            if steps < k[K_START_SAMPLES]:
                flags += lay[L_FLAG_FADING]
                fade = steps / k[K_START_SAMPLES]
                for j in range(6):
                    buffer[i_v + j] = (target[j] - bias[j]) * fade + bias[j]
            else:
                for j in range(6):
                    buffer[i_v + j] = target[j]
            for j in range(4):
                acc = 0.0
                for m in range(6):
                    acc += ctl_force[j, m] * (buffer[i_v + m] - bias[m])
                buffer[i_applied + j] = acc
            # x_c = A x_c + B y + E u_applied over the committed signals
            np.dot(upd_blocks[index], buffer[sig:sig + m_sig], tmp)
            for j in range(n_x):
                buffer[n_record + j] = w0 * tmp[j] + w1 * tmp[n_x + j]
            k[K_SATURATED] = k[K_SATURATED] + 1 if saturated else 0
            k[K_INDEX] = index
            weights[1] = w1
            f[F_FILTERED] = filtered
            f[F_SCALE_A] = scale_a
            f[F_SCALE_B] = scale_b
        else:
            # ARMED: observe (q for the monitor), the stacks at bias
            for j in range(4):
                buffer[i_strain + j] = y[j]
            for j in range(4):
                acc = 0.0
                for m in range(4):
                    acc += c0phiinv[j, m] * y[m]
                buffer[i_q + j] = acc
            for j in range(4):
                acc = 0.0
                for m in range(6):
                    acc += ctl_force[j, m] * (buffer[i_v + m] - bias[m])
                buffer[i_applied + j] = acc
        # the record's sample fields, as step() writes them
        t_s = f[F_TIME]
        k[K_SEQUENCE] += 1
        buffer[lay[L_INPUT_PERIOD]] = (t_s - buffer[lay[L_TIME]]) * 1e6
        buffer[lay[L_TIME]] = t_s
        buffer[lay[L_SEQUENCE]] = k[K_SEQUENCE]
        buffer[lay[L_LOAD]] = load
        buffer[lay[L_FLAGS]] = flags
        buffer[lay[L_ANSWER_AGE]] = math.nan
        buffer[lay[L_OPERATOR]] = 0.0               # no operator's command in a kernel cycle
        f[F_SAFETY_TIME] = t_s
        k[K_MISSING] = 0
        k[K_NOISE] = i_noise + 1
        # -- the write: the rig's stacks' forces, the plant's step --------------------------------
        for j in range(4):
            acc = 0.0
            for m in range(6):
                acc += rig_force[j, m] * (buffer[i_v + m] - rig_bias[m])
            rig_f[j] = acc
        if k[K_DELAYED] == 1:
            head = k[K_HEAD]
            if hist_len > 1:
                nxt_head = (head + 1) % hist_len
                for j in range(4):
                    inputs[j] = history[nxt_head, j]
            else:
                for j in range(4):
                    inputs[j] = rig_f[j]
            if k[K_FRACTIONAL] == 1:
                for j in range(4):
                    inputs[4 + j] = history[head, j]
            for j in range(4):
                history[head, j] = rig_f[j]
            k[K_HEAD] = (head + 1) % hist_len
        else:
            for j in range(4):
                inputs[j] = rig_f[j]
        inputs[n_inputs - 1] = f[F_LOAD]
        np.dot(ad, state, nxt)
        np.dot(bd, inputs, forced)
        for j in range(n_states):
            state[j] = nxt[j] + forced[j]
        t_new = t_s + f[F_PERIOD]
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
                        a1 += vy[b, m] * buffer[i_q + m]
                        a2 += vz[b, m] * buffer[i_q + m]
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
                e = k[K_ENTRIES]
                vmin, vmax = buffer[i_v], buffer[i_v]
                for j in range(1, 6):
                    vmin = min(vmin, buffer[i_v + j])
                    vmax = max(vmax, buffer[i_v + j])
                mon[0, e] = new_load
                mon[1, e] = best
                mon[2, e] = by
                mon[3, e] = bz
                mon[4, e] = true
                mon[5, e] = vmin
                mon[6, e] = vmax
                mon[7, e] = k[K_STATE]
                mon[8, e] = 1.0 if (scale_a < 1.0 or scale_b < 1.0) else 0.0
                k[K_ENTRIES] = e + 1
                if (k[K_COUNTER] % k[K_CALLBACK_EVERY] == 0 or best > f[F_LIMIT]
                        or t_new >= f[F_END_TIME]):
                    return MONITOR, cycles
                if e + 1 >= mon.shape[1]:
                    return MONITOR_FULL, cycles
        # -- a new load cell needs a discretisation --------------------------------------------------
        ratio = new_load / f[F_CELL]
        cell = math.floor(ratio + 0.5)
        if cell != k[K_BIN] or abs(ratio - math.floor(ratio) - 0.5) < 1e-9:
            return NEED_CELL, cycles
    return DONE, cycles


_kernel = None


def kernel():
    """The compiled ``run_cycles`` (numba; compiled once per process, cached on disk where the
    package's folder is writable)."""
    global _kernel
    if _kernel is None:
        try:
            import numba
        except ImportError as exc:
            raise ImportError("the compiled simulation kernel needs numba: "
                              "pip install 'beamctl[fast]'") from exc
        # reassociation lets the compiler split each dot product's sum into vector lanes (the
        # strict left-to-right sum is a chain of dependent adds, several times slower); NaN and
        # infinity keep their IEEE meaning (the checks of a sample rely on it)
        flags = {"reassoc", "contract"}
        try:
            _kernel = numba.njit(cache=True, nogil=True, fastmath=flags)(_run_cycles)
        except Exception:           # a read-only install: compile per process
            _kernel = numba.njit(cache=False, nogil=True, fastmath=flags)(_run_cycles)
    return _kernel


def available() -> bool:
    """Whether numba can be imported (the kernel's one requirement)."""
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


class Accelerator:
    """The ``ControlLoop`` hook that runs a simulated run's uneventful cycles in the kernel.

    ``monitor``: the run's ``RunMonitor`` (the loop's ``on_cycle``), or None. Built once per run
    before the loop starts; every array the kernel uses is the plant's, the controller's and the
    monitor's own."""

    def __init__(self, controller, hal, monitor=None) -> None:
        from beamctl.hal.sim import SimBackend

        if type(hal) is not SimBackend:
            raise TypeError("the simulation kernel runs the sim backend only")
        self.run_cycles = kernel()
        self.controller = controller
        self.hal = hal
        self.plant = hal.plant
        self.monitor = monitor
        self.kernel_cycles = 0
        c = controller
        alloc = c.allocator
        self._layout = layout()
        self._f = np.zeros(N_F)
        self._k = np.zeros(N_K, dtype=np.int64)
        self._coef = np.asarray(alloc._coef, dtype=float)
        self._n_record = ctl.N_COLUMNS
        self._schedule = None
        self._bind_table()
        self._rig_force = np.ascontiguousarray(hal._force_matrix)
        self._rig_bias = np.ascontiguousarray(hal._bias)
        plant = self.plant
        self._c_meas = np.ascontiguousarray(plant._c)
        if monitor is not None:
            self._vy, self._vz = monitor.deflection._vy, monitor.deflection._vz
        else:
            self._vy = self._vz = np.zeros((1, 4))
        self._lateral = np.ascontiguousarray(plant._lateral)
        settings = c.safety
        f, k = self._f, self._k
        f[F_PERIOD] = plant.sample_period
        f[F_LOAD_LOW], f[F_LOAD_HIGH] = settings._load_low, settings._load_high
        f[F_CELL] = 2.0 * plant.config.load_tolerance
        f[F_V_MIN], f[F_V_MAX], f[F_V_MID] = alloc.min_voltage_v, alloc.max_voltage_v, alloc.mid_voltage_v
        f[F_SPAN], f[F_SPAN_FITS] = alloc.voltage_span_v, alloc._span_fits
        k[K_START_SAMPLES] = c._start_samples
        k[K_SAT_LIMIT] = settings._saturation_limit
        k[K_ANTI_WINDUP] = 1 if c._anti_windup else 0
        k[K_FRACTIONAL] = 1 if plant._fractional else 0
        k[K_DELAYED] = 1 if plant._delayed else 0
        k[K_MONITOR] = 1 if monitor is not None else 0
        if monitor is not None:
            k[K_DECIMATE] = monitor.decimate
            k[K_CALLBACK_EVERY] = monitor.decimate * monitor.callback_every
            f[F_LIMIT], f[F_END_TIME] = monitor.limit, monitor.end_time
        else:
            k[K_DECIMATE] = k[K_CALLBACK_EVERY] = 1
            f[F_LIMIT] = f[F_END_TIME] = math.inf

    def _bind_table(self) -> None:
        """The arrays of the controller's gain table (again after an operator's swap)."""
        c = self.controller
        sched = c.schedule
        self._schedule = sched
        self._out_blocks = np.ascontiguousarray(np.stack(sched._output_blocks))
        self._upd_blocks = np.ascontiguousarray(np.stack(sched._update_blocks))
        self._int_blocks = np.ascontiguousarray(np.stack(sched._integral_blocks))
        self._loads = np.asarray(sched._loads, dtype=float)
        self._buffer = c.record.base if c.record.base is not None else c.record
        n_x = c.compensator_state.shape[0]
        self._scratch = np.zeros(12 + n_x + 2 * n_x + 8 + 38 + self.plant.n_states)
        f = self._f
        f[F_ALPHA], f[F_HALF_BAND] = sched._alpha, sched._half_band
        f[F_FIRST], f[F_LAST] = sched._first, sched._last
        self._k[K_PAPER] = 1 if sched._paper else 0

    def eligible(self, loop) -> bool:
        """Whether the next cycles are the kernel's kind: sample pacing on the simulated sim
        backend, no telemetry, the controller RUNNING its law (scale allocation, no excitation)
        or ARMED, nothing asked of the loop."""
        c, hal, plant = self.controller, self.hal, self.plant
        if loop.pacing != "sample" or loop.telemetry is not None or hal._silent or hal.pace != "simulated":
            return False
        if loop._stop_signal or loop._rearm_requested or (loop.stop is not None and loop.stop.reason):
            return False
        if getattr(loop, "_command", None) is not None:
            return False
        if loop.on_cycle is not self.monitor:
            return False
        state = c.supervisor.state
        if state == State.RUNNING:
            if not c._law or c._excitation is not None or getattr(c.allocator, "mode", "scale") != "scale":
                return False
        elif state != State.ARMED:
            return False
        if c.supervisor.fault != Fault.NONE or plant._feedthrough is not None or not hal.is_open:
            return False
        return True

    def __call__(self, loop) -> int:
        """Run as many cycles as the kernel can; return how many (0: the loop runs the next)."""
        if not self.eligible(loop):
            return 0
        c, hal, plant, monitor = self.controller, self.hal, self.plant, self.monitor
        if c.schedule is not self._schedule:
            self._bind_table()
        sched, alloc, safety = c.schedule, c.allocator, c.safety
        f, k = self._f, self._k
        state = c.supervisor.state
        ramp = plant.config.load
        f[F_RAMP_START], f[F_RAMP_END], f[F_RAMP_RATE], f[F_RAMP_HOLD] = (ramp.start, ramp.end, ramp.rate,
                                                                          ramp.hold)
        f[F_TIME], f[F_LOAD], f[F_FILTERED] = plant.time, plant.axial_load, sched.filtered_load_n
        f[F_SCALE_A], f[F_SCALE_B], f[F_SAFETY_TIME] = alloc.scale_a, alloc.scale_b, safety.time_s
        f[F_STRAIN_LIMIT] = safety.strain_limit
        k[K_NOISE], k[K_HEAD], k[K_SEQUENCE] = plant._noise_index, plant._head, hal._sequence
        k[K_INDEX], k[K_SATURATED], k[K_STEPS] = sched.index, safety.saturated_samples, c._steps_since_start
        k[K_BIN], k[K_CYCLES], k[K_MISSING] = plant._bin, 0, safety.missing_samples
        k[K_RUNNING] = 1 if state == State.RUNNING else 0
        k[K_STATE] = int(state)
        budget = (loop.max_cycles - loop.cycles) if loop.max_cycles is not None else 1 << 62
        if monitor is not None:
            k[K_COUNTER] = monitor.counter
            if monitor.ended:
                k[K_MONITOR] = 0
        total = 0
        why = EVENT
        while budget - total > 0:
            if monitor is not None and k[K_MONITOR] == 1:
                mon = monitor.reserve()
                k[K_ENTRIES] = 0
            else:
                mon = _NO_MONITOR
            why, n = self.run_cycles(
                f, k, self._layout, budget - total, plant._state, plant._next, plant._ad, plant._bd,
                self._c_meas, plant._measured.start, plant._inputs, plant._history, plant._noise_block,
                self._buffer, self._n_record, c._c0_phi_inv, c._integral_map, c._force_matrix, c._bias,
                self._out_blocks, self._upd_blocks, self._int_blocks, sched._weights, self._loads,
                self._coef, self._rig_force, self._rig_bias, self._vy, self._vz, self._lateral,
                plant._q.start, mon, self._scratch)
            total += n
            # the scalars back where the objects keep them
            plant.time, plant.axial_load = f[F_TIME], f[F_LOAD]
            plant._noise_index, plant._head = int(k[K_NOISE]), int(k[K_HEAD])
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
        """The objects' own state after the kernel's cycles, as the loop would have left it."""
        c, hal, f, k = self.controller, self.hal, self._f, self._k
        sched, alloc, safety = c.schedule, c.allocator, c.safety
        sched.filtered_load_n, sched.index, sched.out_of_range = f[F_FILTERED], int(k[K_INDEX]), False
        alloc.scale_a, alloc.scale_b = f[F_SCALE_A], f[F_SCALE_B]
        safety.saturated_samples, safety.missing_samples = int(k[K_SATURATED]), int(k[K_MISSING])
        safety.time_s = f[F_SAFETY_TIME]
        c._steps_since_start = int(k[K_STEPS])
        done = int(k[K_CYCLES])
        k[K_CYCLES] = 0
        hal.reads += done
        hal.writes += done
        loop.cycles += done
        self.kernel_cycles += done
        if done:
            hal.publish_status(c.record[ctl.I_STATE], c.record[ctl.I_FAULT], int(c.record[ctl.I_FLAGS]))
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

