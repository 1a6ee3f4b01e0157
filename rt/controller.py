"""The control step: what the dSPACE system did each sample (section 4 of the paper).

Per sample, in this order:
1. q = (C0 Phi)^-1 y (eq. 30);
2. modal velocities: first-order Butterworth high-pass of q (designed once with
   scipy.signal.butter), scaled by its cut-off angular frequency;
3. discrete integrator xi += T q (eq. 21); with anti-windup, an increment that would push
   a saturated support further along its demanded force is skipped;
4. K(Fx) from the schedule (load-cell value); u = -K [q, dq/dt, xi] (eq. 27);
5. allocation to the six stack voltages (rt.allocation);
6. safety: input checks before 1, saturation after 5, and the voltage ramps of the lifecycle.

Every quantity lives in one preallocated record (``RECORD_COLUMNS``); the step only runs
numpy calls with ``out=`` and scalar arithmetic on precomputed data, and the record is also
what telemetry stores.
"""

from __future__ import annotations

import numpy as np

from beamctl.gains.discrete import velocity_filter
from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import GainTable
from beamctl.hal.base import Sample
from beamctl.rt.allocation import Allocator
from beamctl.rt.config import ControllerConfig
from beamctl.rt.safety import Fault, Safety, State, TransitionError

RECORD_COLUMNS = (
    ["time_s", "sequence", "state", "fault", "flags"]
    + [f"strain_{c}" for c in ("y1", "z1", "y2", "z2")]
    + ["load_N", "load_filtered_N"]
    + [f"q_{m}" for m in ("1y", "1z", "2y", "2z")]
    + [f"qdot_{m}" for m in ("1y", "1z", "2y", "2z")]
    + [f"xi_{m}" for m in ("1y", "1z", "2y", "2z")]
    + ["force_y_A_N", "force_z_A_N", "force_y_B_N", "force_z_B_N"]
    + [f"voltage_{s}_V" for s in ("a1", "a2", "a3", "b1", "b2", "b3")]
    + ["scale_A", "scale_B", "step_us"]
)
COL = {name: i for i, name in enumerate(RECORD_COLUMNS)}
N_COLUMNS = len(RECORD_COLUMNS)
# indices used in the step (integers decided here, not looked up by name in the loop)
I_TIME, I_SEQUENCE, I_STATE, I_FAULT, I_FLAGS = (COL[n] for n in ("time_s", "sequence", "state",
                                                                  "fault", "flags"))
I_LOAD, I_LOAD_FILTERED = COL["load_N"], COL["load_filtered_N"]
I_SCALE_A, I_SCALE_B, I_STEP_US = COL["scale_A"], COL["scale_B"], COL["step_us"]

# flag bits
FLAG_SATURATED_A = 1
FLAG_SATURATED_B = 2
FLAG_INTEGRATOR_HELD = 4
FLAG_LOAD_OUT_OF_TABLE = 8
FLAG_NO_NEW_SAMPLE = 16
FLAG_FADING_IN = 32
FLAG_RAMPING_TO_BIAS = 64


class Controller:
    """The integral LQR of a gain table with its estimator, allocation and supervisor.

    In every state but RUNNING the stacks are not controlled, yet q is still estimated from
    each sample (telemetry, monitoring an uncontrolled beam).

    Lifecycle: ``arm(sample)`` (stacks at bias), ``start()`` (bumpless: integrator zero,
    voltages faded in from bias), ``step(sample)`` once per sample (``step(None)`` when the
    sample is missing: the voltages hold until the stale-input fault), ``fault(...)``,
    ``request_stop()``, ``rearm()``.
    """

    def __init__(self, table: GainTable, config: ControllerConfig) -> None:
        self.table = table
        self.config = config
        self.sample_rate_hz = table.design.sample_rate_hz
        self.period = 1.0 / self.sample_rate_hz
        filt = velocity_filter(table.design.velocity_cutoff_hz, self.sample_rate_hz)
        self.filter = filt
        self.schedule = GainSchedule(table)
        self.allocator = Allocator(config.actuators)

        r = np.zeros(N_COLUMNS)
        self.record = r
        self.strains = r[COL["strain_y1"]:COL["strain_y1"] + 4]
        self.q = r[COL["q_1y"]:COL["q_1y"] + 4]
        self.qdot = r[COL["qdot_1y"]:COL["qdot_1y"] + 4]
        self.xi = r[COL["xi_1y"]:COL["xi_1y"] + 4]
        self.x = r[COL["q_1y"]:COL["q_1y"] + 12]           # [q, qdot, xi], eq. (22)
        self.q_qdot = r[COL["q_1y"]:COL["q_1y"] + 8]
        self.u = r[COL["force_y_A_N"]:COL["force_y_A_N"] + 4]
        self.voltages = r[COL["voltage_a1_V"]:COL["voltage_a1_V"] + 6]

        self._c0_phi_inv = np.ascontiguousarray(table.c0_phi_inv)
        self._hp_b0 = filt.scale * filt.b0
        # [q; omega_c b0 q] = [Ti; omega_c b0 Ti] y in one product
        self._estimate = np.vstack([self._c0_phi_inv, self._hp_b0 * self._c0_phi_inv])
        # filter state scaled by omega_c: s' <- omega_c b1 q - a1 qdot
        self._hp_update = np.hstack([filt.scale * filt.b1 * np.eye(4), -filt.a1 * np.eye(4)])
        self._hp_state = np.zeros(4)
        self._dxi = np.zeros(4)
        # -[K_i; dK/dFx_i] per grid interval: u = a[:4] + offset a[4:] with a = block x
        blocks = -np.concatenate([table.gains, self.schedule.slopes], axis=1)
        self._blocks = [np.ascontiguousarray(b) for b in blocks]
        self._blocks_integral = [np.ascontiguousarray(b[:, 8:12]) for b in blocks]
        self._a = np.zeros(8)
        self._a_gain, self._a_slope = self._a[:4], self._a[4:]
        self._du = np.zeros(4)
        self._target = np.zeros(6)                            # voltages from the allocation
        self._bias = np.full(6, config.actuators.bias_voltage)

        beam = table.model_parameters.beam
        self.safety = Safety(config.safety, beam.proportional_limit / beam.youngs_modulus,
                             config.actuators.bias_voltage, self.sample_rate_hz, self.voltages)
        self.supervisor = self.safety.supervisor
        self._anti_windup = config.anti_windup
        self._start_samples = max(1, round(config.start_ramp_time * self.sample_rate_hz))
        self._steps_since_start = 0
        self.voltages[:] = self._bias

    # -- lifecycle -----------------------------------------------------------------------------
    @property
    def state(self) -> State:
        return self.supervisor.state

    def arm(self, sample: Sample | None = None) -> None:
        """Stacks at bias, integrator cleared; the first sample primes the load filter."""
        self.supervisor.arm()
        self._clear(sample)

    def rearm(self, sample: Sample | None = None) -> None:
        """Operator acknowledgement after a fault or stop; only once the ramp has reached bias
        (the voltages never jump)."""
        if not self.at_bias:
            raise TransitionError("cannot re-arm before the voltages have ramped to bias")
        self.supervisor.rearm()
        self._clear(sample)

    def _clear(self, sample: Sample | None) -> None:
        self.xi[:] = 0.0
        self.qdot[:] = 0.0
        self.voltages[:] = self._bias
        self.safety.clear()
        self.allocator.scale_a = self.allocator.scale_b = 1.0
        if sample is not None:
            self.schedule.reset(sample.axial_load)
            np.dot(self._c0_phi_inv, sample.strains, out=self.q)

    def start(self) -> None:
        """Start controlling from the latest sample: integrator at zero, the velocity filter
        at rest on the current q (no kick however long the controller sat armed), voltages
        faded in from bias. A start on a non-finite strain faults at once."""
        self.supervisor.start()
        self._steps_since_start = 0
        self.xi[:] = 0.0
        if not np.all(np.isfinite(self.q)):
            self.q[:] = 0.0
            self._hp_state[:] = 0.0
            self.fault(Fault.STRAIN_NOT_FINITE, "non-finite strain when starting")
            return
        np.multiply(self.q, -self._hp_b0, out=self._hp_state)

    def request_stop(self) -> None:
        """Ramp to bias and stop (SIGINT/SIGTERM, end of run)."""
        self.safety.request_stop()

    def fault(self, fault: Fault, detail: str = "") -> None:
        """Latch ``fault`` (first one wins) and ramp the voltages to bias."""
        self.safety.trip(fault, detail)

    # -- the step ---------------------------------------------------------------------------------
    def step(self, sample: Sample | None) -> np.ndarray:
        """One control period. ``sample`` None means no new sample arrived. Returns the six
        voltages to write (the controller's own array)."""
        r = self.record
        r[I_FLAGS] = 0.0
        safety = self.safety
        if sample is None:
            r[I_FLAGS] = FLAG_NO_NEW_SAMPLE
            safety.sample_missing()
        else:
            safety.sample_arrived(sample.timestamp)
            r[I_TIME] = sample.timestamp
            r[I_SEQUENCE] = sample.sequence
            self.strains[:] = sample.strains
            r[I_LOAD] = sample.axial_load
            if self.supervisor.state == State.RUNNING:
                safety.check_inputs(self.strains, sample.axial_load)
        state = self.supervisor.state
        if state == State.RUNNING:
            if sample is not None:      # no new sample: the voltages hold, the law waits
                self._control()
        else:
            if sample is not None:      # keep observing: q for telemetry and the operator
                np.dot(self._c0_phi_inv, self.strains, out=self.q)
            if state in (State.FAULT, State.STOPPING):
                self._ramp()
        r[I_STATE] = self.supervisor.state
        r[I_FAULT] = self.supervisor.fault
        return self.voltages

    def _control(self) -> None:
        r = self.record
        schedule = self.schedule
        schedule.locate(r[I_LOAD])
        r[I_LOAD_FILTERED] = schedule.filtered_load_n
        if schedule.out_of_range:
            r[I_FLAGS] += FLAG_LOAD_OUT_OF_TABLE
            self.fault(Fault.LOAD_OUT_OF_TABLE_RANGE,
                       f"filtered load {schedule.filtered_load_n:.1f} N outside the table's "
                       f"[{self.table.loads_n[0]:g}, {self.table.loads_n[-1]:g}] N")
            self._ramp()
            return
        index, offset = schedule.index, schedule.offset_n
        # 1. q = (C0 Phi)^-1 y (eq. 30) and 2. qdot = omega_c (b0 q + s)
        np.dot(self._estimate, self.strains, out=self.q_qdot)
        self.qdot += self._hp_state
        np.dot(self._hp_update, self.q_qdot, out=self._hp_state)
        # 3. integrator with anti-windup
        np.multiply(self.q, self.period, out=self._dxi)
        alloc = self.allocator
        if self._anti_windup and (alloc.scale_a < 1.0 or alloc.scale_b < 1.0):
            # change of u the increment would cause: -K_int dxi
            np.dot(self._blocks_integral[index], self._dxi, out=self._a)
            np.multiply(self._a_slope, offset, out=self._a_slope)
            np.add(self._a_gain, self._a_slope, out=self._du)
            u, du = self.u, self._du
            winds = ((alloc.scale_a < 1.0 and du[0] * u[0] + du[1] * u[1] > 0.0)
                     or (alloc.scale_b < 1.0 and du[2] * u[2] + du[3] * u[3] > 0.0))
            if winds:
                r[I_FLAGS] += FLAG_INTEGRATOR_HELD
            else:
                self.xi += self._dxi
        else:
            self.xi += self._dxi
        # 4. u = -K(Fx) x (eq. 27), K interpolated without forming it
        np.dot(self._blocks[index], self.x, out=self._a)
        if offset == 0.0:
            self.u[:] = self._a_gain
        else:
            np.multiply(self._a_slope, offset, out=self._a_slope)
            np.add(self._a_gain, self._a_slope, out=self.u)
        # 5. allocation
        alloc.allocate(self.u, self._target)
        r[I_SCALE_A] = alloc.scale_a
        r[I_SCALE_B] = alloc.scale_b
        if alloc.scale_a < 1.0:
            r[I_FLAGS] += FLAG_SATURATED_A
        if alloc.scale_b < 1.0:
            r[I_FLAGS] += FLAG_SATURATED_B
        # 6. bumpless start: fade the voltages in from bias
        self._steps_since_start += 1
        if self._steps_since_start < self._start_samples:
            r[I_FLAGS] += FLAG_FADING_IN
            fade = self._steps_since_start / self._start_samples
            np.subtract(self._target, self._bias, out=self.voltages)
            self.voltages *= fade
            self.voltages += self._bias
        else:
            self.voltages[:] = self._target
        self.safety.saturation(alloc.scale_a < 1.0 or alloc.scale_b < 1.0)

    def _ramp(self) -> None:
        self.record[I_FLAGS] += FLAG_RAMPING_TO_BIAS
        self.safety.ramp_step()

    @property
    def at_bias(self) -> bool:
        return self.safety.at_bias
