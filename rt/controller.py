"""The control step: one controller form for every design, a scheduled discrete state-space
compensator with integral action (gains/compensator.py), run each sample as the dSPACE system
ran the paper's controller (section 4).

Per sample, in this order:
1. q = (C0 Phi)^-1 y (eq. 30), for telemetry and the operator (the law reads y itself);
2. integral action xi += T H y; with anti-windup, an increment whose effect -Ki dxi would push
   a saturated support further along its demanded force is skipped;
3. the law u = -(C x_c + D y) - Ki xi at the filtered load (the schedule's product);
4. allocation to the six stack voltages (rt.allocation), faded in from bias after a start;
5. the lateral forces those voltages produce, u_applied = M (V - V_bias), and the compensator's
   next state x_c = A x_c + B y + E u_applied (so an estimator sees the force the stacks give,
   saturated or not);
6. safety (rt.safety): input checks before 1, saturation after 4, and the ramps of the lifecycle.

The compensator starts at rest on the sample it starts on, x_c = start y (bumpless: for the
paper's design the velocity estimate starts at zero). Every quantity the telemetry stores lives
in one preallocated record (``RECORD_COLUMNS``); the step only runs numpy calls with ``out=``
and scalar arithmetic on precomputed data.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import GainTable
from beamctl.hal.base import Sample
from beamctl.rt.allocation import Allocator
from beamctl.rt.config import ControllerConfig
from beamctl.rt.safety import Fault, Safety, State, TransitionError

# The compensator's signals y, xi and u_applied (gains/schedule.py) are the record's last twelve
# columns, and its state x_c follows them in the same buffer, past the record: the schedule's
# products read the signal vector [y; xi; u_applied; x_c] where the telemetry stores it.
SIGNAL_COLUMNS = ([f"strain_{c}" for c in ("y1", "z1", "y2", "z2")]
                  + [f"xi_{m}" for m in ("1y", "1z", "2y", "2z")]
                  + ["applied_force_y_A_N", "applied_force_z_A_N", "applied_force_y_B_N",
                     "applied_force_z_B_N"])
RECORD_COLUMNS = (
    ["time_s", "sequence", "state", "fault", "flags"]
    + ["load_N", "load_filtered_N"]
    + [f"q_{m}" for m in ("1y", "1z", "2y", "2z")]
    + ["force_y_A_N", "force_z_A_N", "force_y_B_N", "force_z_B_N"]
    + [f"voltage_{s}_V" for s in ("a1", "a2", "a3", "b1", "b2", "b3")]
    + ["scale_A", "scale_B", "step_us"]
    # timing of the link: time between this sample's arrival and the previous one's, the age of
    # this sample when its answer was sent (NaN where the HAL does not measure it), and the
    # count of late answers so far (rt/safety.py)
    + ["input_period_us", "answer_age_us", "late_answers"]
    # an operator's command carried out or refused at this sample (rt/loop.py operator_labels)
    + ["operator_command"]
    + SIGNAL_COLUMNS
)
COL = {name: i for i, name in enumerate(RECORD_COLUMNS)}
N_COLUMNS = len(RECORD_COLUMNS)
I_SIGNALS = N_COLUMNS - len(SIGNAL_COLUMNS)
# indices used in the step (integers decided here, not looked up by name in the loop)
I_TIME, I_SEQUENCE, I_STATE, I_FAULT, I_FLAGS = (COL[n] for n in ("time_s", "sequence", "state",
                                                                  "fault", "flags"))
I_LOAD, I_LOAD_FILTERED = COL["load_N"], COL["load_filtered_N"]
I_SCALE_A, I_SCALE_B, I_STEP_US = COL["scale_A"], COL["scale_B"], COL["step_us"]
I_INPUT_PERIOD_US, I_ANSWER_AGE_US, I_LATE_ANSWERS = (COL[n] for n in ("input_period_us", "answer_age_us",
                                                                       "late_answers"))
I_OPERATOR_COMMAND = COL["operator_command"]

# flag bits
FLAG_SATURATED_A = 1
FLAG_SATURATED_B = 2
FLAG_INTEGRATOR_HELD = 4
FLAG_LOAD_OUT_OF_TABLE = 8
FLAG_NO_NEW_SAMPLE = 16
FLAG_FADING_IN = 32
FLAG_RAMPING_TO_BIAS = 64
FLAG_NAMES = {FLAG_SATURATED_A: "SATURATED_A", FLAG_SATURATED_B: "SATURATED_B",
              FLAG_INTEGRATOR_HELD: "INTEGRATOR_HELD", FLAG_LOAD_OUT_OF_TABLE: "LOAD_OUT_OF_TABLE",
              FLAG_NO_NEW_SAMPLE: "NO_NEW_SAMPLE", FLAG_FADING_IN: "FADING_IN",
              FLAG_RAMPING_TO_BIAS: "RAMPING_TO_BIAS"}
# the flags that start a triggered recording's window (with any change of a coded column)
TRIGGER_FLAGS = FLAG_SATURATED_A | FLAG_SATURATED_B

# Units of the columns whose names do not end in one (``load_N``, ``voltage_a1_V``, ``step_us``,
# ``time_s`` do): strains are m/m, the modal coordinates of the mass-normalised modes (eq. 15)
# m sqrt(kg), their integrals m sqrt(kg) s. Codes, counts and fractions have none.
_UNIT_SUFFIXES = {"_N": "N", "_V": "V", "_us": "us", "_s": "s"}
_UNIT_PREFIXES = {"strain_": "m/m", "q_": "m*sqrt(kg)", "xi_": "m*sqrt(kg)*s"}


def code_labels() -> dict[str, dict[int, str]]:
    """The record's coded columns and the label of each code: {column: {code: label}}."""
    from beamctl.rt.loop import operator_labels  # the loop defines the operator's commands

    return {"state": {int(s): s.name for s in State}, "fault": {int(f): f.name for f in Fault},
            "operator_command": operator_labels()}


def flag_labels() -> dict[str, dict[int, str]]:
    """The record's bit-field columns and the label of each bit: {column: {bit: label}}."""
    return {"flags": dict(FLAG_NAMES)}


def column_unit(column: str) -> str:
    """The unit of a record column ("" for codes, counts and fractions)."""
    for prefix, unit in _UNIT_PREFIXES.items():
        if column.startswith(prefix):
            return unit
    for suffix, unit in _UNIT_SUFFIXES.items():
        if column.endswith(suffix):
            return unit
    return ""


@dataclass(frozen=True)
class PreparedTable:
    """A gain table made ready for a controller (``Controller.prepare_table``), so that a swap
    in the loop (``use_table``) only rebinds arrays."""

    table: GainTable
    schedule: GainSchedule
    buffer: np.ndarray          # [N_COLUMNS + n]: the record, then the compensator's state
    c0_phi_inv: np.ndarray
    integral_map: np.ndarray    # T H
    start_map: np.ndarray


class Controller:
    """The compensator of a gain table with its allocation and safety.

    In every state but RUNNING the stacks are not controlled, yet q is still estimated from
    each sample (telemetry, monitoring an uncontrolled beam).

    Lifecycle: ``arm(sample)`` (stacks at bias), ``start()`` (bumpless: integrator zero,
    compensator at rest on the current sample, voltages faded in from bias), ``step(sample)``
    once per sample (``step(None, silent_periods)`` when the sample is missing: the voltages hold
    until the stale-input fault), ``fault(...)``, ``request_stop()``, ``rearm()``.
    """

    def __init__(self, table: GainTable, config: ControllerConfig, *, excitation: np.ndarray | None = None,
                 law: bool = True) -> None:
        """``excitation`` [n x 6], volts added to the law's voltages at the first n control steps
        after a start (identification: then bias, or the law alone), clamped to the voltage
        limits; ``law`` False leaves the stacks at bias plus the excitation (open loop)."""
        self.config = config
        self.sample_rate_hz = table.design.sample_rate_hz
        self.period = 1.0 / self.sample_rate_hz
        self.model_sha256 = table.model_sha256
        self.allocator = Allocator(config.actuators, config.allocation)
        self._bind(self.prepare_table(table))
        self._force_matrix = np.ascontiguousarray(self.allocator.geometry.force_matrix())
        self._dxi = np.zeros(4)
        self._du = np.zeros(4)
        self._dv = np.zeros(6)
        self._target = np.zeros(6)                            # voltages from the allocation
        self._bias = np.full(6, config.actuators.bias_voltage)
        self._law = law
        self._excitation = None if excitation is None else np.ascontiguousarray(excitation, dtype=float)
        if self._excitation is not None and (self._excitation.ndim != 2 or self._excitation.shape[1] != 6):
            raise ValueError(f"excitation must be [n x 6] volts, got shape {self._excitation.shape}")
        self.excitation_index = 0       # excitation rows applied since the start
        self.excitation_enabled = True  # the rows advance only while enabled (set between steps)
        self._v_min, self._v_max = config.actuators.min_voltage_v, config.actuators.max_voltage_v

        beam = table.model_parameters.beam
        self.safety = Safety(config.safety, beam.proportional_limit / beam.youngs_modulus,
                             config.actuators.bias_voltage, self.sample_rate_hz, self.voltages)
        self.supervisor = self.safety.supervisor
        self._anti_windup = config.anti_windup
        self._start_samples = max(1, round(config.start_ramp_time * self.sample_rate_hz))
        self._steps_since_start = 0
        self.voltages[:] = self._bias
        self.record[I_LOAD] = np.nan        # no load seen yet (a start then keeps the schedule's)

    # -- the gain table ----------------------------------------------------------------------------
    def prepare_table(self, table: GainTable) -> PreparedTable:
        """Everything the step needs of ``table`` (its schedule, its maps, a record buffer sized
        for its compensator), made ready off the loop for ``use_table``. A table for another
        sample rate or another model than this controller's is refused (ValueError)."""
        rate = table.design.sample_rate_hz
        if rate != self.sample_rate_hz:
            raise ValueError(f"the table runs at {rate:g} Hz, the controller at {self.sample_rate_hz:g} Hz")
        if table.model_sha256 != self.model_sha256:
            raise ValueError(f"the table was designed for the model with SHA-256 {table.model_sha256}, "
                             f"the controller runs the model with SHA-256 {self.model_sha256}")
        comp = table.compensator
        return PreparedTable(table=table, schedule=GainSchedule.from_table(table),
                             buffer=np.zeros(N_COLUMNS + comp.n_states),
                             c0_phi_inv=np.ascontiguousarray(table.c0_phi_inv),
                             integral_map=np.ascontiguousarray(self.period * comp.h),      # T H
                             start_map=np.ascontiguousarray(comp.start))

    def use_table(self, prepared: PreparedTable) -> None:
        """Run the table of ``prepared`` (``prepare_table``) from the next step on. Only at bias
        and not controlling: ARMED, or FAULT once the ramp has reached bias. The record moves
        into the new buffer (``record`` is then another array), the compensator rests and the
        schedule starts at the latest load; nothing is allocated."""
        state = self.supervisor.state
        if state not in (State.ARMED, State.FAULT) or not self.at_bias:
            raise TransitionError(f"cannot change the gain table in state {state.name}"
                                  + ("" if self.at_bias else " before the voltages have ramped to bias"))
        buffer = prepared.buffer
        np.copyto(buffer[:N_COLUMNS], self.record)
        buffer[N_COLUMNS:] = 0.0
        self._bind(prepared)
        self.safety.voltages = self.voltages
        self.schedule.reset(self.record[I_LOAD])

    def _bind(self, p: PreparedTable) -> None:
        """The table's schedule and maps, and the views of its buffer: the record, and the
        compensator's state after it."""
        self.table = p.table
        self.schedule = p.schedule
        buffer = p.buffer
        r = buffer[:N_COLUMNS]
        self.record = r
        self.q = r[COL["q_1y"]:COL["q_1y"] + 4]
        self.u = r[COL["force_y_A_N"]:COL["force_y_A_N"] + 4]
        self.voltages = r[COL["voltage_a1_V"]:COL["voltage_a1_V"] + 6]
        # the compensator's signal vector s = [y; xi; u_applied; x_c]: the record's last columns
        # and the state after them
        self._signals = buffer[I_SIGNALS:]
        self.strains = r[COL["strain_y1"]:COL["strain_y1"] + 4]
        self.xi = r[COL["xi_1y"]:COL["xi_1y"] + 4]
        self.applied_forces = r[COL["applied_force_y_A_N"]:COL["applied_force_y_A_N"] + 4]
        self.compensator_state = buffer[N_COLUMNS:]
        self._c0_phi_inv = p.c0_phi_inv
        self._integral_map = p.integral_map
        self._start_map = p.start_map

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
        self.compensator_state[:] = 0.0
        self.voltages[:] = self._bias
        self.applied_forces[:] = 0.0
        self.safety.clear()
        self.allocator.scale_a = self.allocator.scale_b = 1.0
        self.record[I_TIME] = np.nan if sample is None else sample.timestamp
        if sample is not None:
            self.record[I_LOAD] = sample.axial_load
            self.schedule.reset(sample.axial_load)
            self.strains[:] = sample.strains
            np.dot(self._c0_phi_inv, self.strains, out=self.q)

    def start(self) -> None:
        """Start controlling from the latest sample: integrator at zero, the compensator at
        rest on that sample and the schedule settled at its load (no kick however long the
        controller sat armed), voltages faded in from bias. A start on a non-finite strain
        faults at once."""
        self.supervisor.start()
        self.schedule.reset(self.record[I_LOAD])
        self._steps_since_start = 0
        self.excitation_index = 0
        self.xi[:] = 0.0
        if not np.all(np.isfinite(self.strains)):
            self.q[:] = 0.0
            self.compensator_state[:] = 0.0
            self.fault(Fault.STRAIN_NOT_FINITE, "non-finite strain when starting")
            return
        np.dot(self._start_map, self.strains, out=self.compensator_state)

    def request_stop(self) -> None:
        """Ramp to bias and stop (SIGINT/SIGTERM, end of run)."""
        self.safety.request_stop()

    def fault(self, fault: Fault, detail: str = "") -> None:
        """Latch ``fault`` (first one wins) and ramp the voltages to bias."""
        self.safety.trip(fault, detail)

    # -- the step ---------------------------------------------------------------------------------
    def step(self, sample: Sample | None, silent_periods: float | None = None) -> np.ndarray:
        """One control period. ``sample`` None means no new sample arrived; ``silent_periods`` is
        then the time since the last one in periods (None: one more period). Returns the six
        voltages to write (the controller's own array)."""
        r = self.record
        r[I_FLAGS] = 0.0
        r[I_ANSWER_AGE_US] = np.nan
        safety = self.safety
        if sample is None:
            r[I_FLAGS] = FLAG_NO_NEW_SAMPLE
            r[I_INPUT_PERIOD_US] = np.nan
            safety.sample_missing(silent_periods)
        else:
            safety.sample_arrived(sample.timestamp)
            r[I_INPUT_PERIOD_US] = (sample.timestamp - r[I_TIME]) * 1e6
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
            self._take_applied_forces()
        r[I_STATE] = self.supervisor.state
        r[I_FAULT] = self.supervisor.fault
        return self.voltages

    def _control(self) -> None:
        r = self.record
        if self._law:
            schedule = self.schedule
            schedule.follow(r[I_LOAD])
            r[I_LOAD_FILTERED] = schedule.filtered_load_n
            if schedule.out_of_range:
                r[I_FLAGS] += FLAG_LOAD_OUT_OF_TABLE
                self.fault(Fault.LOAD_OUT_OF_TABLE_RANGE,
                           f"filtered load {schedule.filtered_load_n:.1f} N outside the table's "
                           f"[{self.table.loads_n[0]:g}, {self.table.loads_n[-1]:g}] N")
                self._ramp()
                self._take_applied_forces()
                return
            # 1. q = (C0 Phi)^-1 y (eq. 30), for telemetry
            np.dot(self._c0_phi_inv, self.strains, out=self.q)
            # 2. integral action with anti-windup
            np.dot(self._integral_map, self.strains, out=self._dxi)
            alloc = self.allocator
            if self._anti_windup and (alloc.scale_a < 1.0 or alloc.scale_b < 1.0):
                schedule.integral_effect(self._dxi, self._du)       # -Ki dxi: what the increment does
                u, du = self.u, self._du
                winds = ((alloc.scale_a < 1.0 and du[0] * u[0] + du[1] * u[1] > 0.0)
                         or (alloc.scale_b < 1.0 and du[2] * u[2] + du[3] * u[3] > 0.0))
                if winds:
                    r[I_FLAGS] += FLAG_INTEGRATOR_HELD
                else:
                    self.xi += self._dxi
            else:
                self.xi += self._dxi
            # 3. u = -(C x_c + D y) - Ki xi at the filtered load
            schedule.output(self._signals, self.u)
            # 4. allocation
            alloc.allocate(self.u, self._target)
            r[I_SCALE_A] = alloc.scale_a
            r[I_SCALE_B] = alloc.scale_b
            if alloc.scale_a < 1.0:
                r[I_FLAGS] += FLAG_SATURATED_A
            if alloc.scale_b < 1.0:
                r[I_FLAGS] += FLAG_SATURATED_B
        else:                           # open loop (identification): bias plus the excitation
            np.dot(self._c0_phi_inv, self.strains, out=self.q)
            self._target[:] = self._bias
        if self._excitation is not None and self.excitation_enabled:
            self._excite()
        # the bumpless start: voltages faded in from bias
        self._steps_since_start += 1
        if self._steps_since_start < self._start_samples:
            r[I_FLAGS] += FLAG_FADING_IN
            fade = self._steps_since_start / self._start_samples
            np.subtract(self._target, self._bias, out=self.voltages)
            self.voltages *= fade
            self.voltages += self._bias
        else:
            self.voltages[:] = self._target
        # 5. the forces these voltages produce, and the compensator's next state
        self._take_applied_forces()
        if self._law:
            self.schedule.update(self._signals, self.compensator_state)
            self.safety.saturation(self.allocator.scale_a < 1.0 or self.allocator.scale_b < 1.0)

    def _excite(self) -> None:
        """The next excitation row onto the target voltages, within the voltage limits."""
        k = self.excitation_index
        if k < len(self._excitation):
            self._target += self._excitation[k]
            np.clip(self._target, self._v_min, self._v_max, out=self._target)
            self.excitation_index = k + 1

    def _take_applied_forces(self) -> None:
        """u_applied = M (V - V_bias): the lateral forces the voltages about to be written give,
        with the controller's own stack geometry."""
        np.subtract(self.voltages, self._bias, out=self._dv)
        np.dot(self._force_matrix, self._dv, out=self.applied_forces)

    def _ramp(self) -> None:
        self.record[I_FLAGS] += FLAG_RAMPING_TO_BIAS
        self.safety.ramp_step()

    @property
    def at_bias(self) -> bool:
        return self.safety.at_bias
