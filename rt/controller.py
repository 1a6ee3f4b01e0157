"""The controller: one controller form for every design, a scheduled discrete state-space
compensator with integral action (gains/compensator.py), run each sample as the dSPACE system
ran the paper's controller (section 4), by the compiled engine (rt/engine.py).

Per sample, in this order (the engine's ``cycle``):
1. input checks (strain and load-cell ranges), and the stall the stacks held a stale voltage
   through, against the live ride-through limit (a gap is bridged by catching the compensator up on it);
2. q = (C0 Phi)^-1 y (eq. 30), for telemetry and the operator (the law reads y itself);
3. integral action xi += T H y; with anti-windup, an increment whose effect -Ki dxi would push
   a saturated support further along its demanded force is skipped;
4. the law u = -(C x_c + D y) - Ki xi at the filtered load (the schedule's product);
5. allocation to the six stack voltages, clamped to the voltage range, faded in from bias after
   a start;
6. the lateral forces those voltages produce, u_applied = M (V - V_bias), and the compensator's
   next state x_c = A x_c + B y + E u_applied (so an estimator sees the force the stacks give,
   saturated or not); the saturation count.

This class is the engine's Python face: it allocates the engine's arrays, prepares gain tables
(their matrices flattened once), and turns the lifecycle into engine commands. The compensator
starts at rest on the sample it starts on, x_c = start y (bumpless: for the paper's design the
velocity estimate starts at zero). Every quantity the telemetry stores lives in one preallocated
record (``RECORD_COLUMNS``, rt/engine.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from beamctl.config.schema import ConfigError
from beamctl.gains.ridethrough import CONFIDENCE_SIGMA, DELAY_MARGIN, GROWTH_CAP, LET_GO_SIGMA
from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import GainTable
from beamctl.hal.base import Sample
from beamctl.rt import engine as e
from beamctl.rt.allocation import Allocator
from beamctl.rt.config import ControllerConfig
from beamctl.rt.engine import (  # noqa: F401 (the record's layout, re-exported for its readers)
    COL,
    FLAG_BRIDGED,
    FLAG_FADING_IN,
    FLAG_INTEGRATOR_HELD,
    FLAG_LOAD_OUT_OF_TABLE,
    FLAG_NAMES,
    FLAG_NO_NEW_SAMPLE,
    FLAG_RAMPING_TO_BIAS,
    FLAG_SATURATED_A,
    FLAG_SATURATED_B,
    I_ANSWER_AGE_US,
    I_BRIDGED,
    I_FAULT,
    I_FLAGS,
    I_GAP_LIMIT,
    I_HELD,
    I_INPUT_PERIOD_US,
    I_LATE_ANSWERS,
    I_LOAD,
    I_LOAD_FILTERED,
    I_OPERATOR_COMMAND,
    I_SCALE_A,
    I_SCALE_B,
    I_SEQUENCE,
    I_SIGNALS,
    I_STATE,
    I_STEP_US,
    I_TIME,
    N_COLUMNS,
    RECORD_COLUMNS,
    SIGNAL_COLUMNS,
)
from beamctl.rt.record import TRIGGER_FLAGS, code_labels, column_unit, flag_labels  # noqa: F401 (re-exported)
from beamctl.rt.safety import Fault, Safety, State, TransitionError

# Without a ride-through analysis in the table (a file written before tables carried one, or one
# analysed by the relative criterion of earlier versions), the limits the controller had before:
# 5 samples missing or late in a row, half a period, whatever the spreads (as a growth of 1 up to
# them and none beyond).
LEGACY_GAP_LIMIT, LEGACY_BUDGET_PERIODS = 5, 0.5
# the moving spreads of the ride-through follow the signals with this time constant
SPREAD_TIME_S = 0.1
# the excursion the loop shows beyond its means is held at its peak and decays with this time
# constant: a stall's recovery at 3300 N rings at about 7 ms and is over within 20 ms
# (simulation/stall.py), so that the envelope holds over its swings
EXCURSION_TIME_S = 0.01
# a sample enters the moving statistics within k spreads of the mean (a recovery's transient does
# not inflate them for long after), and within at least these (strain, V): a quarter of the
# gauges' 0.2 ue noise, a tenth of the stacks' stationary 0.2 V spread at 3300 N
SPREAD_CLIP_FLOOR = (5e-8, 0.02)
# a start allows the growth of this (the moving variances begin at the headroom over k times it)
START_GROWTH = 10.0


def tolerated_periods(budgets: np.ndarray, design_delay_samples: float) -> np.ndarray:
    """The latest answer (periods after its sample) the loop tolerates, per grid point: the design's
    delay plus the extra delay of the table's delay search, whose half the answer budget allows
    (gains/ridethrough.py ``answer_budget``); from a budget the configuration tightened, as much
    less. Never less than the budget."""
    b = np.asarray(budgets, dtype=float)
    return np.maximum(b, design_delay_samples + DELAY_MARGIN * (b - design_delay_samples))


@dataclass(frozen=True)
class RideThroughLimits:
    """What the engine takes of a table's ride-through (``ride_through_limits``): per grid point
    the answer budget in periods, the loads the growth was analysed at and per interval between
    them the growth curves [interval, bridge (catch_up), output (deflection, voltage), gap], the gap
    grid, k of the k-sigma bound, and the caps on the gap and late-answer limits (samples)."""

    budgets: np.ndarray
    growth_loads: np.ndarray
    growth: np.ndarray
    grid: np.ndarray
    confidence_sigma: float
    gap_cap: float
    late_cap: float
    source: str

@dataclass(frozen=True)
class PreparedTable:
    """A gain table made ready for a controller (``Controller.prepare_table``), so that a swap
    in the loop (``use_table``) only rebinds arrays."""

    table: GainTable
    schedule: GainSchedule
    core: np.ndarray            # the engine's one array (rt/engine.py ``core_array``): the record, the
                                # compensator's state and scratch, fv, iv, then every matrix of the table
    nb: int                     # the length of its first part (the record, x_c, scratch)
    table_iv: np.ndarray        # the engine's per-table integer settings (``engine.TABLE_IV``)
    alpha: float                # the load filter's coefficient
    half_band_n: float
    first_n: float
    last_n: float
    limits: RideThroughLimits   # the ride-through as the engine takes it (ride_through_limits)
    c0_phi_inv: np.ndarray
    mode1_strain: np.ndarray    # mode 1's strain per unit q_1 at the gauges, the larger of each plane's


def _stacked(blocks: list[np.ndarray]) -> np.ndarray:
    return np.concatenate([np.ascontiguousarray(b).ravel() for b in blocks])


# the signal vector's entries of each bending plane: its two strains, integrals, applied forces
PLANE_SIGNALS = {"y": [0, 2, 4, 6, 8, 10], "z": [1, 3, 5, 7, 9, 11]}
PLANE_OUTPUTS = {"y": [0, 2], "z": [1, 3]}


def plane_split(compensator, blocks: dict[str, list[np.ndarray]]) -> int | None:
    """The number of plane-y states when the compensator's planes do not couple and plane y's
    states come first (the engine then runs each product per plane, ``engine.V_SPLIT``), else
    None. ``blocks``: the schedule's [M_i; S_i] blocks of each product ("out", "upd"),
    checked to vanish outside the planes' own rows and columns at every grid point."""
    n = compensator.n_states
    ys, zs = list(compensator.plane_states["y"]), list(compensator.plane_states["z"])
    ny = len(ys)
    if ys != list(range(ny)) or zs != list(range(ny, n)) or ny == 0 or ny == n:
        return None
    rows = {"out": PLANE_OUTPUTS, "upd": {"y": list(range(ny)), "z": list(range(ny, n))}}
    for key, stacked in blocks.items():
        for block in stacked:
            half = block.shape[0] // 2
            for m in (block[:half], block[half:]):
                mask = np.ones_like(m, dtype=bool)
                for p in ("y", "z"):
                    states = ys if p == "y" else zs
                    cols = PLANE_SIGNALS[p] + [12 + i for i in states]
                    mask[np.ix_(rows[key][p], cols)] = False
                if np.any(m[mask] != 0.0):
                    return None
    return ny


def plane_blocks(stacked: list[np.ndarray], key: str, ny: int, n: int) -> np.ndarray:
    """The blocks of ``plane_split`` per plane: plane y's [M_i; S_i] of its rows and columns for
    every grid point, then plane z's, flat (the engine's order)."""
    out = []
    for p, states in (("y", list(range(ny))), ("z", list(range(ny, n)))):
        rows = states if key == "upd" else PLANE_OUTPUTS[p]
        cols = PLANE_SIGNALS[p] + [12 + i for i in states]
        for block in stacked:
            half = block.shape[0] // 2
            sub = np.ix_(rows, cols)
            out.append(np.vstack([block[:half][sub], block[half:][sub]]).ravel())
    return np.concatenate(out)


def ride_through_limits(table: GainTable, config: ControllerConfig) -> RideThroughLimits:
    """The ride-through of ``table`` as the engine uses it (``RideThroughLimits``): from the
    table's analysis (stored with the table when it was built), the configuration's settings
    tightening it where they are smaller; a configured value beyond what the analysis allows at
    any load is refused (ConfigError)."""
    s = config.safety
    g = len(table.loads_n)
    rt = getattr(table, "ride_through", None)
    if rt is None:
        grid = np.array([float(LEGACY_GAP_LIMIT), LEGACY_GAP_LIMIT + 1.0])
        one = np.array([[[1.0, GROWTH_CAP], [1.0, GROWTH_CAP]]])     # [bridge, output, gap]
        growth = np.broadcast_to(one, (g, 1, 2, 2)).copy()
        growth_loads = np.asarray(table.loads_n, dtype=float)
        budgets = np.full(g, LEGACY_BUDGET_PERIODS)
        k = CONFIDENCE_SIGMA
        source = "the limits used without a ride-through analysis in the table"
    else:
        grid = np.asarray(rt.gap_grid_samples, dtype=float)
        growth_loads = np.unique(np.asarray(rt.loads_n, dtype=float))
        growth = rt.interval_growth(growth_loads)
        budgets = np.asarray(rt.answer_budgets_periods, dtype=float)
        k = rt.confidence_sigma
        source = "the gain table's ride-through analysis"
    gap_cap = late_cap = float(grid[-1])
    for key, value in (("stale_periods", s.stale_periods), ("late_answer_streak", s.late_answer_streak),
                       ("answer_budget_periods", s.answer_budget_periods)):
        if value is None:
            continue
        most = float(budgets.max()) if key == "answer_budget_periods" else float(grid[-1])
        if value > most:
            raise ConfigError(f"controller.safety.{key}", value,
                              f"at most {most:g}, what {source} allows (a smaller value tightens it)")
        if key == "stale_periods":
            gap_cap = float(value)
        elif key == "late_answer_streak":
            late_cap = float(value)
        else:
            budgets = np.minimum(budgets, value)
    return RideThroughLimits(budgets=budgets, growth_loads=growth_loads, growth=growth, grid=grid,
                             confidence_sigma=float(k), gap_cap=gap_cap, late_cap=late_cap, source=source)


class Controller:
    """The compensator of a gain table with its allocation and safety, run by the engine.

    In every state but RUNNING the stacks are not controlled, yet q is still estimated from
    each sample (telemetry, monitoring an uncontrolled beam).

    Lifecycle: ``arm(sample)`` (stacks at bias), ``start()`` (bumpless: integrator zero,
    compensator at rest on the current sample, voltages faded in from bias), ``step(sample)``
    once per sample (``step(None, silent_periods)`` when the sample is missing: the voltages hold
    and the silence counts towards STALE_INPUT), ``fault(...)``, ``request_stop()``, ``rearm()``.
    """

    def __init__(self, table: GainTable, config: ControllerConfig, *, excitation: np.ndarray | None = None,
                 law: bool = True) -> None:
        """``excitation`` [n x 6], volts added to the law's voltages at the first n control steps
        after a start (identification: then bias, or the law alone), clamped to the voltage
        limits; ``law`` False leaves the stacks at bias plus the excitation (open loop)."""
        self.config = config
        self.sample_rate_hz = table.design.sample_rate_hz
        self.period_s = 1.0 / self.sample_rate_hz
        self.model_sha256 = table.model_sha256
        self.iv = iv = np.zeros(e.N_IV, dtype=np.int64)
        self.fv = fv = np.zeros(e.N_FV)
        self.allocator = Allocator(config.actuators, config.allocation, fv[e.X_SCALE_A:e.X_SCALE_B + 1])
        self._force_matrix = np.ascontiguousarray(self.allocator.geometry.force_matrix())
        self._excitation = None if excitation is None else np.ascontiguousarray(excitation, dtype=float)
        if self._excitation is not None and (self._excitation.ndim != 2 or self._excitation.shape[1] != 6):
            raise ValueError(f"excitation must be [n x 6] volts, got shape {self._excitation.shape}")
        act = config.actuators
        self._v_min, self._v_max = act.min_voltage_v, act.max_voltage_v
        self._law = law
        beam = table.model_parameters.beam
        s = config.safety
        iv[e.V_ANTI_WINDUP] = 1 if config.anti_windup else 0
        iv[e.V_LAW] = 1 if law else 0
        iv[e.V_CLIP] = 1 if config.allocation == "clip" else 0
        iv[e.V_START_SAMPLES] = max(1, round(config.start_ramp_time_s * self.sample_rate_hz))
        iv[e.V_SAT_LIMIT] = max(1, round(s.saturation_time_s * self.sample_rate_hz))
        iv[e.V_OVERRUN_LIMIT] = s.overrun_streak
        iv[e.V_RAMP_SAMPLES] = max(1, int(round(s.ramp_time_s * self.sample_rate_hz)))
        iv[e.V_EXC_ROWS] = 0 if self._excitation is None else len(self._excitation)
        iv[e.V_EXC_ENABLED] = 1
        iv[e.V_FAULT_CHANNEL] = -1
        alloc = self.allocator
        fv[e.P_STRAIN_LIMIT] = s.strain_limit_fraction * beam.proportional_limit / beam.youngs_modulus
        fv[e.P_LOAD_LOW], fv[e.P_LOAD_HIGH] = s.load_range_n
        fv[e.P_V_MIN], fv[e.P_V_MAX] = alloc.min_voltage_v, alloc.max_voltage_v
        fv[e.P_V_MID] = alloc.mid_voltage_v
        fv[e.P_SPAN], fv[e.P_SPAN_FITS] = alloc.voltage_span_v, alloc.span_fits
        fv[e.P_BIAS] = act.bias_voltage_v
        fv[e.X_SCALE_A] = fv[e.X_SCALE_B] = 1.0
        fv[e.P_PERIOD] = self.period_s
        fv[e.P_STAT_ALPHA] = 1.0 - np.exp(-self.period_s / SPREAD_TIME_S)
        fv[e.P_START_GROWTH] = START_GROWTH
        fv[e.P_EXCURSION_DECAY] = np.exp(-self.period_s / EXCURSION_TIME_S)
        fv[e.P_CLIP_FLOOR:e.P_CLIP_FLOOR + 2] = SPREAD_CLIP_FLOOR
        fv[e.P_CATCH_UP] = e.CATCH_UP_SAMPLES
        self._gap_cap = np.inf          # the DAQ's own silence (``cap_gap_limit``)
        self._bias = np.full(6, act.bias_voltage_v)
        self.safety = Safety(self, iv, fv, tuple(s.load_range_n), s.ramp_time_s)
        self.supervisor = self.safety.supervisor
        self._bind(self.prepare_table(table))
        self._command(e.C_RESET_SCHEDULE)       # the limits at the first grid point until a load is seen
        self.voltages[:] = self._bias
        self.record[I_LOAD] = np.nan        # no load seen yet (a start then keeps the schedule's)
        self.record[I_TIME] = np.nan

    # -- the gain table ----------------------------------------------------------------------------
    def prepare_table(self, table: GainTable) -> PreparedTable:
        """Everything the engine needs of ``table`` (its matrices flat, a record buffer sized for
        its compensator, its settings), made ready off the loop for ``use_table``. A table for
        another sample rate or another model than this controller's is refused (ValueError); a
        configured safety limit beyond the table's ride-through analysis too (ConfigError)."""
        rate = table.design.sample_rate_hz
        if rate != self.sample_rate_hz:
            raise ValueError(f"the table runs at {rate:g} Hz, the controller at {self.sample_rate_hz:g} Hz")
        if table.model_sha256 != self.model_sha256:
            raise ValueError(f"the table was designed for the model with SHA-256 {table.model_sha256}, "
                             f"the controller runs the model with SHA-256 {self.model_sha256}")
        limits = ride_through_limits(table, self.config)
        # the answer budget per grid interval (the engine's index): the lesser of its two ends
        budgets = np.minimum(limits.budgets, np.concatenate([limits.budgets[1:], limits.budgets[-1:]]))
        tolerated = tolerated_periods(budgets, table.design.io.delay_samples)
        budgets = np.concatenate([budgets, tolerated]) * self.period_s
        comp = table.compensator
        schedule = GainSchedule.from_table(table)
        n = comp.n_states
        blocks = {"out": schedule._output_blocks, "upd": schedule._update_blocks}
        ny = plane_split(comp, blocks)
        if ny is None:
            flat = {key: _stacked(b) for key, b in blocks.items()}
        else:
            flat = {key: plane_blocks(b, key, ny, n) for key, b in blocks.items()}
        parts = {
            "c0": np.asarray(table.c0_phi_inv, dtype=float),
            "th": self.period_s * np.asarray(comp.h, dtype=float),            # T H
            "force": self._force_matrix,
            "coef": self.allocator.coefficients,
            "loads": np.asarray(table.loads_n, dtype=float),
            "out": flat["out"],
            "upd": flat["upd"],
            "int": _stacked(schedule._integral_blocks),
            "start": np.asarray(comp.start, dtype=float),
            "exc": self._excitation if self._excitation is not None else np.zeros(0),
            "lim": budgets,
            "grid": limits.grid,
            "growth": np.ascontiguousarray(limits.growth),
            "gloads": limits.growth_loads,
        }
        offsets, at = {}, 0
        for key, part in parts.items():
            offsets[key] = at
            at += np.asarray(part).size
        mats = np.concatenate([np.ascontiguousarray(p, dtype=float).ravel() for p in parts.values()])
        table_iv = np.zeros(e.TABLE_IV.stop - e.TABLE_IV.start, dtype=np.int64)

        def put(slot: int, value: int) -> None:
            table_iv[slot - e.V_PAPER] = value

        put(e.V_PAPER, 1 if schedule.mode == "paper" else 0)
        put(e.V_N_LOADS, len(table.loads_n))
        put(e.V_N_X, n)
        put(e.V_SPLIT, 0 if ny is None else 1)
        put(e.V_NY, 0 if ny is None else ny)
        for slot, key in ((e.O_C0, "c0"), (e.O_TH, "th"), (e.O_FORCE, "force"), (e.O_COEF, "coef"),
                          (e.O_LOADS, "loads"), (e.O_OUT, "out"), (e.O_UPD, "upd"), (e.O_INT, "int"),
                          (e.O_START, "start"), (e.O_EXC, "exc"), (e.O_LIM, "lim"),
                          (e.O_GRID, "grid"), (e.O_GROWTH, "growth"), (e.O_GLOADS, "gloads")):
            put(slot, offsets[key])
        put(e.V_N_GRID, len(limits.grid))
        put(e.V_N_GLOADS, len(limits.growth_loads))
        # mode 1's strain at the gauges per unit q_1 (q = (C0 Phi)^-1 y): the column of C0 Phi
        c0_phi = np.linalg.inv(np.asarray(table.c0_phi_inv, dtype=float))
        mode1 = np.array([np.abs(c0_phi[[0, 2], 0]).max(), np.abs(c0_phi[[1, 3], 1]).max()])
        return PreparedTable(table=table, schedule=schedule,
                             core=e.core_array(N_COLUMNS + n + e.scratch_size(n), mats),
                             nb=N_COLUMNS + n + e.scratch_size(n),
                             table_iv=table_iv, alpha=schedule.alpha, half_band_n=schedule.half_band_n,
                             first_n=float(table.loads_n[0]), last_n=float(table.loads_n[-1]),
                             limits=limits, c0_phi_inv=np.ascontiguousarray(table.c0_phi_inv),
                             mode1_strain=mode1)

    def use_table(self, prepared: PreparedTable) -> None:
        """Run the table of ``prepared`` (``prepare_table``) from the next step on. Only at bias
        and not controlling: ARMED, or FAULT once the ramp has reached bias. The record moves
        into the new buffer (``record`` is then another array), the compensator rests and the
        schedule starts at the latest load; nothing is allocated."""
        refusal = self.supervisor.refusal("gains")
        if refusal:
            raise TransitionError(f"cannot change the gain table: {refusal}")
        buffer, _, _, _ = e.core_views(prepared.core, prepared.nb)
        np.copyto(buffer[:N_COLUMNS], self.record)
        buffer[N_COLUMNS:] = 0.0
        self._bind(prepared)
        self._command(e.C_RESET_SCHEDULE)       # the schedule and the limits at the latest load

    def _bind(self, p: PreparedTable) -> None:
        """The table's arrays and settings into the engine, and the views of its buffer: the
        record, and the compensator's state after it."""
        self.table = p.table
        self.schedule = p.schedule
        self._prepared = p
        buffer, fv, iv, mats = e.core_views(p.core, p.nb)
        np.copyto(fv, self.fv)          # the controller's state and settings move with it
        np.copyto(iv, self.iv)
        self.iv, self.fv = iv, fv
        self.safety.iv, self.safety.fv = iv, fv
        self.allocator.scales = fv[e.X_SCALE_A:e.X_SCALE_B + 1]
        self._core = p.core
        self._nb = p.nb
        iv[e.TABLE_IV] = p.table_iv
        fv[e.P_ALPHA], fv[e.P_HALF_BAND] = p.alpha, p.half_band_n
        fv[e.P_FIRST], fv[e.P_LAST] = p.first_n, p.last_n
        fv[e.P_K_SIGMA] = p.limits.confidence_sigma
        fv[e.P_LET_GO_SIGMA] = min(LET_GO_SIGMA, p.limits.confidence_sigma)
        fv[e.P_C1:e.P_C1 + 2] = p.mode1_strain
        fv[e.P_GAP_CAP] = min(p.limits.gap_cap, self._gap_cap)
        fv[e.P_LET_GO_CAP] = p.limits.gap_cap
        fv[e.P_LATE_CAP] = p.limits.late_cap
        self._mats = mats
        self._buffer = buffer
        r = buffer[:N_COLUMNS]
        self.record = r
        self.q = r[e.I_Q:e.I_Q + 4]
        self.u = r[e.I_U:e.I_U + 4]
        self.voltages = r[e.I_V:e.I_V + 6]
        self.strains = r[e.I_Y:e.I_Y + 4]
        self.xi = r[e.I_XI:e.I_XI + 4]
        self.applied_forces = r[e.I_APPLIED:e.I_APPLIED + 4]
        n = p.table.compensator.n_states
        self.compensator_state = buffer[N_COLUMNS:N_COLUMNS + n]
        self._c0_phi_inv = p.c0_phi_inv

    # -- the engine ---------------------------------------------------------------------------------
    def _command(self, what: int, arg: int = 0) -> int:
        return int(e.command(self._buffer, self.iv, self.fv, self._mats, what, arg))

    def _inputs(self, sample: Sample | None) -> int:
        if sample is None:
            return 0
        fv = self.fv
        fv[e.IN_TIME] = sample.timestamp
        fv[e.IN_SEQUENCE] = sample.sequence
        fv[e.IN_LOAD] = sample.axial_load
        fv[e.IN_MISSED] = sample.missed
        fv[e.IN_Y:e.IN_Y + 4] = sample.strains
        return 1

    def _refused(self, code: int, action: str, allowed: str) -> None:
        if code == e.R_NOT_AT_BIAS:
            raise TransitionError(f"cannot {action} before the voltages have ramped to bias")
        if code == e.R_STATE:
            raise TransitionError(f"cannot {action} in state {self.state.name} (allowed from {allowed})")

    # -- lifecycle -----------------------------------------------------------------------------
    @property
    def state(self) -> State:
        return State(int(self.iv[e.V_STATE]))

    def arm(self, sample: Sample | None = None) -> None:
        """Stacks at bias, integrator cleared; the first sample primes the load filter."""
        self._refused(self._command(e.C_ARM, self._inputs(sample)), "arm", "INIT")

    def rearm(self, sample: Sample | None = None) -> None:
        """Operator acknowledgement after a fault or stop; only once the ramp has reached bias
        (the voltages never jump)."""
        self._refused(self._command(e.C_REARM, self._inputs(sample)), "re-arm", "FAULT, STOPPED")
        self.supervisor.python_detail = ""

    def start(self) -> None:
        """Start controlling from the latest sample: integrator at zero, the compensator at
        rest on that sample and the schedule settled at its load (no kick however long the
        controller sat armed), voltages faded in from bias. A start on a non-finite strain
        faults at once."""
        self._refused(self._command(e.C_START), "start", "ARMED")

    def request_stop(self) -> None:
        """Ramp to bias and stop (SIGINT/SIGTERM, end of run)."""
        self._command(e.C_STOP)

    def fault(self, fault: Fault, detail: str = "") -> None:
        """Latch ``fault`` (first one wins) and ramp the voltages to bias."""
        latched = self.supervisor.fault != Fault.NONE
        self._command(e.C_TRIP, int(fault))
        if not latched and self.supervisor.fault == fault:
            self.supervisor.python_detail = detail

    # -- the step ---------------------------------------------------------------------------------
    def step(self, sample: Sample | None, silent_periods: float | None = None) -> np.ndarray:
        """One control period. ``sample`` None means no new sample arrived; ``silent_periods`` is
        then the time since the last one in periods (None: one more period). Returns the six
        voltages to write (the controller's own array)."""
        if sample is None:
            self.fv[e.IN_SILENT] = -1.0 if silent_periods is None else silent_periods
            e.cycle(self._buffer, self.iv, self.fv, self._mats, 0)
        else:
            # the gap as a float: any count a backend reports (beyond int64 too) reaches the engine
            e.sample_cycle(self._core, self._nb, sample.timestamp, sample.sequence, sample.axial_load,
                           float(sample.missed), sample.strains)
        return self.voltages

    def cap_gap_limit(self, seconds: float | None) -> None:
        """The DAQ falls back to bias by itself after ``seconds`` without an answer (its silence
        time-out; None: it does not): the live ride-through limit stays two samples short of it
        (past it the stacks ramp toward bias: no longer held with the limit's confidence). The
        let-go does not: a DAQ that fell back takes the controller's frames again when they come
        (hal/beamctl.dbc), and its ramp is slow against a stall's time (75 V over 500 ms: 0.15 V a
        ms, against spreads of 0.2 V and tens of volts of headroom), so the catch-up's assumption
        that the stacks held is off by little; where the silence was the DAQ's or the bus's own the
        controller could not have pre-empted the fallback anyway (it sends only answers). Below the
        critical load, where the let-go is the table's cap, a stall past the DAQ's time-out (a host
        holding the process 25 ms at 2048 N) is ridden through instead of faulted; what the beam
        did meanwhile the supervisor sees when the samples return."""
        if seconds is None or not seconds > 0:
            return
        self._gap_cap = max(float(np.floor(seconds / self.period_s)) - 2.0, 0.0)
        self.fv[e.P_GAP_CAP] = min(self._prepared.limits.gap_cap, self._gap_cap)

    @property
    def gap_limit(self) -> float:
        """The live ride-through limit in samples (gains/ridethrough.py, rt/engine.py): a stall
        up to it is survived with k sigma to spare."""
        return float(self.fv[e.X_LIMIT])

    @property
    def let_go(self) -> float:
        """The live let-go in samples (gains/ridethrough.py ``LET_GO_SIGMA``): a longer stall
        faults STALE_INPUT."""
        return float(self.fv[e.X_LET_GO])

    def warm(self) -> float:
        """Make everything the loop's cycle calls ready before it arms: every entry point of
        the engine compiled (or loaded from numba's cache) and run through its controlled path
        on a copy of this controller's arrays, with the argument types the step passes. Returns
        the seconds it took."""
        import time

        started = time.perf_counter()
        core = self._core.copy()
        nb = self._nb
        buf, fv, iv, mats = e.core_views(core, nb)
        strains = np.zeros(4)
        load = float(self._prepared.first_n)
        e.sample_cycle(core, nb, 0.0, 0, load, 0.0, strains)
        e.command(buf, iv, fv, mats, e.C_START, 0)
        iv[e.V_STATE] = e.S_RUNNING
        for k in range(1, 4):
            e.sample_cycle(core, nb, k * self.period_s, k, load, float(k > 2), strains)
            e.answered(buf, iv, fv, 0.0)
        e.cycle(buf, iv, fv, mats, 0)
        e.command(buf, iv, fv, mats, e.C_OVERRAN, 0)
        e.command(buf, iv, fv, mats, e.C_ON_TIME, 0)
        return time.perf_counter() - started

    def answer_sent(self, age_s: float) -> None:
        """The answer to the latest sample had been sent ``age_s`` after the sample arrived (NaN:
        not measured): late answers are counted and a streak beyond the limit faults."""
        e.answered(self._buffer, self.iv, self.fv, age_s)

    # -- the loop's emergency exit -------------------------------------------------------------------
    def emergency_ramp_begin(self) -> None:
        """Begin the one ramp to bias from the voltages now (the loop's exit on an error)."""
        self._command(e.C_RAMP_BEGIN)

    def emergency_ramp_advance(self) -> bool:
        """The ramp's next voltages into ``voltages``; True once at bias (nothing to write)."""
        return self._command(e.C_RAMP_ADVANCE) == 1

    # -- identification's excitation -------------------------------------------------------------------
    @property
    def excitation_index(self) -> int:
        """Excitation rows applied since the start."""
        return int(self.iv[e.V_EXC_INDEX])

    @property
    def excitation_enabled(self) -> bool:
        """The rows advance only while enabled (set between steps)."""
        return bool(self.iv[e.V_EXC_ENABLED])

    @excitation_enabled.setter
    def excitation_enabled(self, value: bool) -> None:
        self.iv[e.V_EXC_ENABLED] = 1 if value else 0

    @property
    def at_bias(self) -> bool:
        return self.safety.at_bias

    @property
    def filtered_load_n(self) -> float:
        return float(self.fv[e.X_FILTERED])

    @property
    def steps_since_start(self) -> int:
        return int(self.iv[e.V_STEPS])

