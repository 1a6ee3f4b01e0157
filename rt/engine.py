"""The real-time engine: the control cycle, compiled once (numba), over preallocated arrays.

Everything that happens per sample is here, in one implementation that the service loop, the
offline simulations (simulation/simkernel.py runs it inside its compiled loop) and the checks all run:
input checks, the load filter and the schedule, the bridge over missing samples (the
compensator caught up), integral action with anti-windup, the law, allocation to the six
stacks with the clamp to the voltage range, excitation, the bumpless fade-in, the applied
forces and the compensator's update, the saturation and late-answer counts, every fault
decision and the one ramp to bias. Python (rt/controller.py, rt/loop.py) is the supervisor
above it: configuration, the lifecycle commands an operator gives, telemetry, sockets.

State lives in four arrays, allocated when a controller is built or a table is prepared:

- ``buf`` (per gain table): the telemetry record (``RECORD_COLUMNS``), then the compensator's
  state x_c (n), then scratch. The compensator's signal vector s = [y; xi; u_applied; x_c] is
  the record's last twelve columns and x_c after them.
- ``iv`` (int64): the lifecycle state, the latched fault, the counters, and integer settings.
- ``fv`` (float64): the load filter, the ramp, fault details, float settings, and the inputs
  of the next cycle (``IN_*``: the sample, or the silence since the last one).
- ``mats`` (per gain table): every matrix of the table, flat, at offsets held in ``iv``
  (``O_*``); the schedule's blocks [M_i; S_i] per grid point (gains/schedule.py), so the
  matrices at a load are M_i + offset S_i without forming them.

Each function returns plain integers; nothing allocates. The record's layout, the state and
fault codes and the flag bits are defined here, beside the code that writes them (a compiled
function keeps module constants as they were when it was compiled; numba's cache is keyed on
this file).

Missing samples (a sequence jump of ``missed`` samples, or a silence): the stacks held the last
answer's voltages meanwhile (no sample, no answer). The stall is measured as what the beam saw,
the samples the stacks held that voltage before the new sample (the jump, or the silence since
the sample before, whichever is longer: ``held_samples``), and compared with the live limit
(``_live_limit``: the table's ride-through growth against the headroom over k times the spreads
the engine measures, gains/ridethrough.py); past it the controller faults STALE_INPUT. Within it
the gap is bridged by catching up (``_catch_up``): the compensator's state makes one step per
sample missed on the newest strains and the forces the stacks held, the integral stays, and the
newest sample enters the normal step. The compensator so keeps the beam's time: held still
instead (the estimate held), a loss of every other sample runs it at half its rate, and the loop
went unstable from 2500 N within 300 ms on the simulated rig (nominal and the worst rig of the
box); caught up, it holds them to 3700 N (``StallRig.loss``). A single stall moves the stacks
less too (100 samples at 3300 N: 44 V against 71 V held), and far less than running the
compensator's prediction through the gap, which drifts from the operating point the beam is held
at. An answer sent later than the answer budget counts as late; more late
answers in a row than the live limit fault LATE_ANSWERS.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# -- the record (one row of telemetry per sample) ---------------------------------------------------
# The compensator's signals y, xi and u_applied are the record's last twelve columns, and its
# state x_c follows them in the same buffer: the schedule's products read the signal vector
# [y; xi; u_applied; x_c] where the telemetry stores it.
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
    # this sample when its answer had been sent (NaN where the HAL does not measure it), and the
    # count of late answers so far
    + ["input_period_us", "answer_age_us", "late_answers"]
    # samples missing before this one (a gap of the sequence), bridged by catching up
    + ["bridged"]
    # an operator's command carried out or refused at this sample (rt/loop.py operator_labels)
    + ["operator_command"]
    # the ride-through: the live limit (samples the stacks may hold a stale voltage), the stall
    # ridden through at this sample (samples the stacks held the last answer before it), and the
    # measured spreads it follows from (mode 1 at the gauges, strain; the stacks, V)
    + ["gap_limit_samples", "held_samples", "spread_deflection", "spread_voltage_V"]
    + SIGNAL_COLUMNS
)
COL = {name: i for i, name in enumerate(RECORD_COLUMNS)}
N_COLUMNS = len(RECORD_COLUMNS)
I_SIGNALS = N_COLUMNS - len(SIGNAL_COLUMNS)
I_TIME, I_SEQUENCE, I_STATE, I_FAULT, I_FLAGS = 0, 1, 2, 3, 4
I_LOAD, I_LOAD_FILTERED = 5, 6
I_Q, I_U, I_V = 7, 11, 15
I_SCALE_A, I_SCALE_B, I_STEP_US = 21, 22, 23
I_INPUT_PERIOD_US, I_ANSWER_AGE_US, I_LATE_ANSWERS, I_BRIDGED, I_OPERATOR_COMMAND = 24, 25, 26, 27, 28
I_GAP_LIMIT, I_HELD, I_SPREAD_Q, I_SPREAD_V = 29, 30, 31, 32
I_Y, I_XI, I_APPLIED = 33, 37, 41
assert (COL["q_1y"], COL["force_y_A_N"], COL["voltage_a1_V"], COL["scale_A"], COL["input_period_us"],
        COL["bridged"], COL["operator_command"], COL["gap_limit_samples"], COL["spread_voltage_V"],
        COL["strain_y1"], COL["xi_1y"], COL["applied_force_y_A_N"], N_COLUMNS) == (
    I_Q, I_U, I_V, I_SCALE_A, I_INPUT_PERIOD_US, I_BRIDGED, I_OPERATOR_COMMAND, I_GAP_LIMIT, I_SPREAD_V, I_Y,
    I_XI, I_APPLIED, 45), "the record's column indices"

# flag bits of the record's ``flags`` column
FLAG_SATURATED_A = 1
FLAG_SATURATED_B = 2
FLAG_INTEGRATOR_HELD = 4
FLAG_LOAD_OUT_OF_TABLE = 8
FLAG_NO_NEW_SAMPLE = 16
FLAG_FADING_IN = 32
FLAG_RAMPING_TO_BIAS = 64
FLAG_BRIDGED = 128
FLAG_NAMES = {FLAG_SATURATED_A: "SATURATED_A", FLAG_SATURATED_B: "SATURATED_B",
              FLAG_INTEGRATOR_HELD: "INTEGRATOR_HELD", FLAG_LOAD_OUT_OF_TABLE: "LOAD_OUT_OF_TABLE",
              FLAG_NO_NEW_SAMPLE: "NO_NEW_SAMPLE", FLAG_FADING_IN: "FADING_IN",
              FLAG_RAMPING_TO_BIAS: "RAMPING_TO_BIAS", FLAG_BRIDGED: "BRIDGED"}

# -- lifecycle states and faults (rt/safety.py names them) -----------------------------------------
S_INIT, S_ARMED, S_RUNNING, S_FAULT, S_STOPPING, S_STOPPED = 0, 1, 2, 3, 4, 5
(F_NONE, F_STRAIN_NOT_FINITE, F_STRAIN_OUT_OF_RANGE, F_LOAD_NOT_FINITE, F_LOAD_OUT_OF_SENSOR_RANGE,
 F_LOAD_OUT_OF_TABLE_RANGE, F_STALE_INPUT, F_OVERRUN_STREAK, F_PERSISTENT_SATURATION, F_HAL_ERROR,
 F_OPERATOR, F_LATE_ANSWERS) = range(12)

# -- iv: integer state, then integer settings ----------------------------------------------------------
(V_STATE, V_FAULT, V_INDEX, V_SATURATED, V_STEPS, V_EXC_INDEX, V_EXC_ENABLED, V_RAMP_STEP, V_SILENT,
 V_LATE_STREAK, V_LATE_TOTAL, V_OVERRUN_STREAK, V_OVERRUN_MAX, V_BRIDGED, V_MAX_GAP, V_FAULT_CHANNEL,
 V_OUT_OF_RANGE) = range(17)
# settings of the controller
(V_ANTI_WINDUP, V_LAW, V_CLIP, V_START_SAMPLES, V_SAT_LIMIT, V_GAP_LIMIT, V_LATE_LIMIT, V_OVERRUN_LIMIT,
 V_RAMP_SAMPLES, V_EXC_ROWS) = range(17, 27)
# settings of the gain table in use (copied from its ``table_iv`` by ``use_table``)
(V_PAPER, V_N_LOADS, V_N_X, O_C0, O_TH, O_FORCE, O_COEF, O_LOADS, O_OUT, O_UPD, O_INT, O_START, O_EXC,
 V_SPLIT, V_NY, O_LIM, O_GRID, O_GROWTH, V_N_GRID, O_GLOADS, V_N_GLOADS, V_GINDEX) = range(27, 49)
N_IV = 49
TABLE_IV = slice(V_PAPER, N_IV)

# -- fv: float state, settings, inputs -------------------------------------------------------------------
(X_FILTERED, X_OFFSET, X_SCALE_A, X_SCALE_B, X_TIME, X_FAULT_TIME, X_FAULT_VALUE, X_FAULT_LIMIT) = range(8)
X_RAMP_FROM = 8                                 # 6 voltages
X_TARGET = 14                                   # 6 voltages from the allocation
X_DXI = 20                                      # 4: the integral increment
X_DU = 24                                       # 4: what it does to u
(P_STRAIN_LIMIT, P_LOAD_LOW, P_LOAD_HIGH, P_ALPHA, P_HALF_BAND, P_FIRST, P_LAST, P_V_MIN, P_V_MAX, P_V_MID,
 P_SPAN, P_SPAN_FITS, P_BIAS, P_BUDGET_S) = range(28, 42)
(IN_TIME, IN_SEQUENCE, IN_LOAD, IN_MISSED, IN_SILENT) = range(42, 47)
IN_Y = 47                                       # 4 strains
# the ride-through's measurements: moving means and variances of q_1 (planes y, z), the strains'
# means, the stacks' means and variances; the live limit (samples) and the growth the headroom
# allows (deflection, voltage)
X_QM, X_QV, X_YM, X_VM, X_VV, X_LIMIT, X_ALLOWED = 51, 53, 55, 59, 65, 71, 73
# its settings: the moving statistics' coefficient, k of the k-sigma bound, mode 1's strain per
# unit q_1 at the gauges (the larger of a plane's two), the caps on the gap and late-answer limits
# (the DAQ's silence, the configuration's), the period, the growth allowed at a start
P_STAT_ALPHA, P_K_SIGMA, P_C1, P_GAP_CAP, P_LATE_CAP, P_PERIOD, P_START_GROWTH = 75, 76, 77, 79, 80, 81, 82
# the samples of a gap caught up on (``_catch_up``; the older ones of a longer gap are held)
P_CATCH_UP = 83
# the excursion the loop shows now beyond its means (deflection as strain, voltage), held at its
# peak and decaying by P_EXCURSION_DECAY per sample (``_stats_update``), and that decay
X_EXCURSION, P_EXCURSION_DECAY = 84, 86
# the least deviation a sample's entry into the moving statistics is clipped at (deflection as
# strain, voltage): a spread that collapsed (a stack held at a limit) still learns
P_CLIP_FLOOR = 87
# the latest answer the loop tolerates at the grid point in use (s): the design's delay and the
# extra delay its loop stays stable with (the table's delay search); an answer later than the
# budget is late, and only one later than this holds the stacks stale
P_TOLERATED_S = 89
# the let-go: the growth allowed (deflection, voltage) over the spreads at P_LET_GO_SIGMA, or the
# excursion beyond k spreads where that is larger, the gap it allows (samples; past it a stall or
# a streak of stale answers faults), and that sigma
X_ALLOWED_LET_GO, X_LET_GO, P_LET_GO_SIGMA = 90, 92, 93
# a growth the ride-through analysis stores as this diverged (gains/ridethrough.py): never allowed
GROWTH_CAP = 2.0e3
# the let-go's cap (samples): the configuration's and the grid's, not the DAQ's silence (a DAQ that
# fell back to bias by itself takes the controller's frames again when they come)
P_LET_GO_CAP = 94
N_FV = 95

# Scratch after x_c in ``buf``: a plane's gathered signals (6 + n), a product's result (n + 4).
# ``V_SPLIT`` 1: the compensator's two bending planes do not couple and their
# states are contiguous (plane y the first ``V_NY``): each product runs per plane on the plane's
# six signals and its own states, on blocks stored per plane ([M_i; S_i] of the plane's rows and
# columns), half the arithmetic of the whole matrices; 0: the whole matrices.
def scratch_size(n_states: int) -> int:
    return 2 * n_states + 10


def _scratch(n):
    """Offsets of the scratch areas for a compensator of ``n`` states: a plane's gathered
    signals, a product's result."""
    t = N_COLUMNS + n
    return t, t + 6 + n


# commands (``command``): the lifecycle and what the loop reports between cycles
(C_ARM, C_START, C_REARM, C_STOP, C_TRIP, C_RESET_SCHEDULE, C_RAMP_BEGIN, C_RAMP_ADVANCE, C_OVERRAN,
 C_ON_TIME, C_CLEAR) = range(11)
# refusals of a command (negative return values)
R_STATE = -1        # not allowed in this state
R_NOT_AT_BIAS = -2  # the voltages have not ramped to bias yet

# the samples of a gap the compensator catches up on (``_catch_up``, 0.55 us each on this 2-core
# machine: 330 us at most); the older ones of a longer gap are held
CATCH_UP_SAMPLES = 600
GAP_COUNT_CAP = 4.0e18  # the longest gap counted (a count beyond int64 would overflow)
SPAN_ROUNDING = 1e-12   # relative: far above the few ulps of the coefficients, far below any real excess


# ---------------------------------------------------------------------------------------------------
# The compiled functions. Written as plain functions of arrays; ``_jit`` compiles them below.

def _at_bias(buf, fv):
    b = fv[P_BIAS]
    for j in range(6):
        if buf[I_V + j] != b:
            return False
    return True


def _ramp_begin(buf, iv, fv):
    for j in range(6):
        fv[X_RAMP_FROM + j] = buf[I_V + j]
    iv[V_RAMP_STEP] = 0


def _ramp_advance(buf, iv, fv):
    """The ramp's next voltages into the record; False while ramping (the last ramp step writes
    bias), True from the call after it on, with bias held."""
    samples = iv[V_RAMP_SAMPLES]
    b = fv[P_BIAS]
    if iv[V_RAMP_STEP] < samples:
        iv[V_RAMP_STEP] += 1
        remaining = 1.0 - iv[V_RAMP_STEP] / samples
        for j in range(6):
            buf[I_V + j] = (fv[X_RAMP_FROM + j] - b) * remaining + b
        return False
    for j in range(6):
        buf[I_V + j] = b
    return True


def _trip(buf, iv, fv, fault, value, limit, channel):
    """Latch ``fault`` unless one is latched (the first wins) and ramp to bias from the voltages
    now (a stop's ramp already under way goes on). True when this call latched it."""
    state = iv[V_STATE]
    if state == S_FAULT or state == S_STOPPED or iv[V_FAULT] != F_NONE:
        return False
    iv[V_STATE] = S_FAULT
    iv[V_FAULT] = fault
    iv[V_FAULT_CHANNEL] = channel
    fv[X_FAULT_TIME] = fv[X_TIME]
    fv[X_FAULT_VALUE] = value
    fv[X_FAULT_LIMIT] = limit
    if state != S_STOPPING:
        _ramp_begin(buf, iv, fv)
    return True


def gap_allowed(growth, o, grid, g0, n, allowed_q, allowed_v):
    """The longest gap (samples) of the grid (``grid[g0:g0 + n]``) whose growth (deflection at
    ``growth[o:o + n]``, voltage after it) is within what the headroom allows, and between the
    last grid gap allowed and the first not, the gap where each output's growth, interpolated
    linearly in its logarithm (a gap's growth is close to exponential in its length), reaches what
    is allowed: 0 when not even the first is allowed, the grid's end when all are. A growth at
    GROWTH_CAP (what the table stores for one past it: a loop that diverged) is never allowed, and
    nothing is interpolated towards it."""
    best = 0.0
    for i in range(n):
        gq = growth[o + i]
        gv = growth[o + n + i]
        capped = not (gq < GROWTH_CAP and gv < GROWTH_CAP)
        if capped or gq > allowed_q or gv > allowed_v:
            if i == 0:
                return 0.0
            f = 1.0
            pq = growth[o + i - 1]
            pv = growth[o + n + i - 1]
            if capped:
                f = 0.0
            if gq > allowed_q:
                fq = 0.0
                if 0.0 < pq < gq and allowed_q > 0.0:
                    fq = math.log(allowed_q / pq) / math.log(gq / pq)
                if fq < f:
                    f = fq
            if gv > allowed_v:
                fv_ = 0.0
                if 0.0 < pv < gv and allowed_v > 0.0:
                    fv_ = math.log(allowed_v / pv) / math.log(gv / pv)
                if fv_ < f:
                    f = fv_
            if not f > 0.0:
                f = 0.0
            return best + f * (grid[g0 + i] - best)
        best = grid[g0 + i]
    return best


def _allowed_over(fv, slot, a, b, sq, sv, hq, hv):
    """Into ``fv[slot:slot + 2]``: the growth the headrooms ``hq`` (strain) and ``hv`` (V) allow
    over the bound max(a spreads, the excursion less b spreads), deflection and voltage; 0 where
    there is no headroom."""
    bq = a * sq
    if fv[X_EXCURSION] - b * sq > bq:
        bq = fv[X_EXCURSION] - b * sq
    bv = a * sv
    if fv[X_EXCURSION + 1] - b * sv > bv:
        bv = fv[X_EXCURSION + 1] - b * sv
    fv[slot] = (hq / bq if bq > 0.0 else math.inf) if hq > 0.0 else 0.0
    fv[slot + 1] = (hv / bv if bv > 0.0 else math.inf) if hv > 0.0 else 0.0


def _allowed(buf, fv):
    """The growth the headroom allows, deflection and voltage (gains/ridethrough.py): the
    headroom over k times the spread, from the moving means and variances, or over the excursion
    the loop shows now where that is larger (a recovery under way: a gap that starts there grows
    from it); at the let-go, the same over the spreads at its sigma or the excursion beyond the k
    spreads, whichever is larger."""
    k = fv[P_K_SIGMA]
    sq = 0.0
    for p in range(2):
        s = math.sqrt(fv[X_QV + p]) * fv[P_C1 + p]
        if s > sq:
            sq = s
    ym = 0.0
    for j in range(4):
        a = abs(fv[X_YM + j])
        if a > ym:
            ym = a
    sv = 0.0
    hv = math.inf
    for j in range(6):
        s = math.sqrt(fv[X_VV + j])
        if s > sv:
            sv = s
        m = fv[X_VM + j]
        h = fv[P_V_MAX] - m if fv[P_V_MAX] - m < m - fv[P_V_MIN] else m - fv[P_V_MIN]
        if h < hv:
            hv = h
    hq = fv[P_STRAIN_LIMIT] - ym
    _allowed_over(fv, X_ALLOWED, k, 0.0, sq, sv, hq, hv)
    # at the let-go the spreads count at its sigma, and the excursion beyond the k spreads the
    # stationary loop's noise peaks reach whole (a recovery under way is a deviation that is there,
    # not a bound on one): continuous where the excursion is k spreads
    g = fv[P_LET_GO_SIGMA]
    _allowed_over(fv, X_ALLOWED_LET_GO, g, k - g, sq, sv, hq, hv)
    buf[I_SPREAD_Q] = sq
    buf[I_SPREAD_V] = sv


def _live_limit(buf, iv, fv, mats):
    """The live ride-through limit (samples) of the grid interval in use, from the growth the
    headroom allows now at k sigma, and the let-go, from the growth it allows at the let-go's
    sigma (never below the limit); the limit capped by the DAQ's silence and the configuration,
    the let-go by the configuration. A stall within the limit is survived with k sigma to spare;
    one past the let-go faults; one between is ridden through (the beam is more likely held than
    lost: letting go of it sooner could only lose it, and the supervisor watches what it does once
    the samples come back)."""
    _allowed(buf, fv)
    # the growth's interval: between the analysed loads around the filtered load
    i = iv[V_GINDEX]
    og = iv[O_GLOADS]
    last = iv[V_N_GLOADS] - 1
    load = fv[X_FILTERED]
    while i < last and mats[og + i + 1] <= load:
        i += 1
    while i > 0 and mats[og + i] > load:
        i -= 1
    iv[V_GINDEX] = i
    n = iv[V_N_GRID]
    o = iv[O_GROWTH] + 2 * n * i
    best = gap_allowed(mats, o, mats, iv[O_GRID], n, fv[X_ALLOWED], fv[X_ALLOWED + 1])
    go = gap_allowed(mats, o, mats, iv[O_GRID], n, fv[X_ALLOWED_LET_GO], fv[X_ALLOWED_LET_GO + 1])
    if go < best:
        go = best
    if best > fv[P_GAP_CAP]:
        best = fv[P_GAP_CAP]
    if go > fv[P_LET_GO_CAP]:
        go = fv[P_LET_GO_CAP]
    fv[X_LIMIT] = best
    fv[X_LET_GO] = go
    iv[V_GAP_LIMIT] = int(go)
    late = fv[P_LATE_CAP]
    iv[V_LATE_LIMIT] = int(go if go < late else late)
    buf[I_GAP_LIMIT] = best


def _stats_start(buf, iv, fv, mats):
    """The moving statistics at a start: the means where the signals are, the variances as
    large as lets the headroom allow a growth of P_START_GROWTH (they settle to the measured
    within a few of their time constants)."""
    k = fv[P_K_SIGMA] * fv[P_START_GROWTH]
    ym = 0.0
    for j in range(4):
        y = buf[I_Y + j]
        fv[X_YM + j] = y if y - y == 0.0 else 0.0
        if abs(fv[X_YM + j]) > ym:
            ym = abs(fv[X_YM + j])
    hq = fv[P_STRAIN_LIMIT] - ym
    for p in range(2):
        q = buf[I_Q + p]
        fv[X_QM + p] = q if q - q == 0.0 else 0.0
        s = hq / (k * fv[P_C1 + p]) if hq > 0.0 and fv[P_C1 + p] > 0.0 else 0.0
        fv[X_QV + p] = s * s
    for j in range(6):
        fv[X_VM + j] = buf[I_V + j]
        h = fv[P_V_MAX] - buf[I_V + j]
        if buf[I_V + j] - fv[P_V_MIN] < h:
            h = buf[I_V + j] - fv[P_V_MIN]
        s = h / k if h > 0.0 else 0.0
        fv[X_VV + j] = s * s
    fv[X_EXCURSION] = 0.0
    fv[X_EXCURSION + 1] = 0.0
    _live_limit(buf, iv, fv, mats)


def _stats_update(buf, iv, fv, mats):
    """One controlled sample into the moving statistics (exponential, coefficient
    P_STAT_ALPHA; a deviation beyond k spreads, or beyond the floor where that is larger, enters
    as that: a recovery's transient, which the excursion covers while it lasts, does not inflate
    the spreads for long after it) and into the excursion; then the live limits."""
    a = fv[P_STAT_ALPHA]
    k = fv[P_K_SIGMA]
    decay = fv[P_EXCURSION_DECAY]
    eq = fv[X_EXCURSION] * decay
    ev = fv[X_EXCURSION + 1] * decay
    for p in range(2):
        d = buf[I_Q + p] - fv[X_QM + p]
        x = abs(d) * fv[P_C1 + p]
        if x > eq:
            eq = x
        c = k * math.sqrt(fv[X_QV + p])
        f = fv[P_CLIP_FLOOR] / fv[P_C1 + p] if fv[P_C1 + p] > 0.0 else math.inf
        if c < f:
            c = f
        if abs(d) > c:
            d = c if d > 0.0 else -c
        fv[X_QM + p] += a * d
        fv[X_QV + p] = (1.0 - a) * (fv[X_QV + p] + a * d * d)
    for j in range(4):
        fv[X_YM + j] += a * (buf[I_Y + j] - fv[X_YM + j])
    for j in range(6):
        d = buf[I_V + j] - fv[X_VM + j]
        if abs(d) > ev:
            ev = abs(d)
        c = k * math.sqrt(fv[X_VV + j])
        if c < fv[P_CLIP_FLOOR + 1]:
            c = fv[P_CLIP_FLOOR + 1]
        if abs(d) > c:
            d = c if d > 0.0 else -c
        fv[X_VM + j] += a * d
        fv[X_VV + j] = (1.0 - a) * (fv[X_VV + j] + a * d * d)
    fv[X_EXCURSION] = eq
    fv[X_EXCURSION + 1] = ev
    _live_limit(buf, iv, fv, mats)


def _limits(iv, fv, mats):
    """The answer budget at the grid point in use (the table's, per grid interval: the lesser of
    its two ends); the gap and late-answer limits are live (``_live_limit``)."""
    fv[P_BUDGET_S] = mats[iv[O_LIM] + iv[V_INDEX]]
    fv[P_TOLERATED_S] = mats[iv[O_LIM] + iv[V_N_LOADS] + iv[V_INDEX]]


def _settle(iv, fv, mats, load):
    """Grid point and offset at a load reached from below and settled (gains/schedule.py)."""
    n = iv[V_N_LOADS]
    o = iv[O_LOADS]
    last = n - 1
    if iv[V_PAPER] == 1:
        i = 0                                   # bisect_left
        while i < n and mats[o + i] < load:
            i += 1
        iv[V_INDEX] = min(max(i, 0), last)
        fv[X_OFFSET] = 0.0
        _limits(iv, fv, mats)
        return
    if load <= mats[o]:
        iv[V_INDEX] = 0
        fv[X_OFFSET] = 0.0
    elif load >= mats[o + last]:
        iv[V_INDEX] = last
        fv[X_OFFSET] = 0.0
    else:
        i = 0                                   # bisect_right - 1
        while i + 1 < n and mats[o + i + 1] <= load:
            i += 1
        iv[V_INDEX] = i
        fv[X_OFFSET] = load - mats[o + i]
    _limits(iv, fv, mats)


def _reset_schedule(iv, fv, mats, load):
    if not (load - load == 0.0):                # NaN or infinite: the first grid point
        load = fv[P_FIRST]
    fv[X_FILTERED] = load
    iv[V_OUT_OF_RANGE] = 1 if (load < fv[P_FIRST] or load > fv[P_LAST]) else 0
    _settle(iv, fv, mats, load)


def _follow(iv, fv, mats, load):
    """Filter a load-cell reading and move to the grid point of the filtered load; a non-finite
    reading is not filtered (the matrices are kept) and counts as out of range."""
    if not (load - load == 0.0):
        iv[V_OUT_OF_RANGE] = 1
        return
    filtered = fv[X_FILTERED] + fv[P_ALPHA] * (load - fv[X_FILTERED])
    fv[X_FILTERED] = filtered
    iv[V_OUT_OF_RANGE] = 1 if (filtered < fv[P_FIRST] or filtered > fv[P_LAST]) else 0
    if iv[V_PAPER] == 1:
        o = iv[O_LOADS]
        i = iv[V_INDEX]
        last = iv[V_N_LOADS] - 1
        half = fv[P_HALF_BAND]
        while i < last and filtered > mats[o + i] + half:
            i += 1
        while i > 0 and filtered < mats[o + i - 1] - half:
            i -= 1
        if i != iv[V_INDEX]:
            iv[V_INDEX] = i
            _limits(iv, fv, mats)
    else:
        _settle(iv, fv, mats, filtered)


def _product(mats, o, rows, cols, index, offset, s, s0, out, out0):
    """out[out0 + j] = ((M_i + offset S_i) s[s0:s0 + cols])_j for the block [M_i; S_i] of grid
    point ``index`` stored at ``o`` (rows x cols each). Written as loops over a 2-D view: the
    compiler vectorises them, and for the per-plane blocks they are several times faster than a
    BLAS call's overhead."""
    size = 2 * rows * cols
    base = o + index * size
    block = mats[base:base + size].reshape((2 * rows, cols))
    x = s[s0:s0 + cols]
    for j in range(rows):
        a = 0.0
        b = 0.0
        for m in range(cols):
            a += block[j, m] * x[m]
            b += block[rows + j, m] * x[m]
        out[out0 + j] = a + offset * b


def _small_product(mats, o, rows, cols, index, offset, s, s0, out, out0):
    """``_product`` for a small block (the integral's 4 x 4), written out."""
    base = o + index * 2 * rows * cols
    for j in range(rows):
        r0 = base + j * cols
        r1 = base + (rows + j) * cols
        a = 0.0
        b = 0.0
        for m in range(cols):
            a += mats[r0 + m] * s[s0 + m]
            b += mats[r1 + m] * s[s0 + m]
        out[out0 + j] = a + offset * b


def _matvec(mats, o, rows, cols, x, x0, out, out0):
    for j in range(rows):
        a = 0.0
        for m in range(cols):
            a += mats[o + j * cols + m] * x[x0 + m]
        out[out0 + j] = a


def _applied_forces(buf, iv, fv, mats):
    """u_applied = M (V - V_bias): the lateral forces of the voltages about to be written."""
    o = iv[O_FORCE]
    b = fv[P_BIAS]
    for j in range(4):
        a = 0.0
        for m in range(6):
            a += mats[o + j * 6 + m] * (buf[I_V + m] - b)
        buf[I_APPLIED + j] = a


def _gather(buf, p, start, count, at):
    """Plane ``p``'s six signals (its two strains, integrals and applied forces) and its
    ``count`` states from ``start`` into buf[at:at + 6 + count]."""
    for k in range(3):
        buf[at + 2 * k] = buf[I_SIGNALS + 4 * k + p]
        buf[at + 2 * k + 1] = buf[I_SIGNALS + 4 * k + p + 2]
    for j in range(count):
        buf[at + 6 + j] = buf[N_COLUMNS + start + j]


def _update(buf, iv, fv, mats):
    """x_c <- A x_c + B y + E u_applied at the current load, over the signal vector in ``buf``."""
    n = iv[V_N_X]
    sp, res = _scratch(n)
    index, offset = iv[V_INDEX], fv[X_OFFSET]
    if iv[V_SPLIT] == 1:
        o = iv[O_UPD]
        start = 0
        for p in range(2):
            count = iv[V_NY] if p == 0 else n - iv[V_NY]
            cols = 6 + count
            _gather(buf, p, start, count, sp)
            _product(mats, o, count, cols, index, offset, buf, sp, buf, N_COLUMNS + start)
            o += iv[V_N_LOADS] * 2 * count * cols
            start += count
        return
    _product(mats, iv[O_UPD], n, 12 + n, index, offset, buf, I_SIGNALS, buf, res)
    for j in range(n):
        buf[N_COLUMNS + j] = buf[res + j]


def _output(buf, iv, fv, mats):
    """u = -(C x_c + D y) - Ki xi at the current load into the record."""
    n = iv[V_N_X]
    sp, res = _scratch(n)
    index, offset = iv[V_INDEX], fv[X_OFFSET]
    if iv[V_SPLIT] == 1:
        o = iv[O_OUT]
        start = 0
        for p in range(2):
            count = iv[V_NY] if p == 0 else n - iv[V_NY]
            cols = 6 + count
            _gather(buf, p, start, count, sp)
            _product(mats, o, 2, cols, index, offset, buf, sp, buf, res)
            buf[I_U + p] = buf[res]
            buf[I_U + p + 2] = buf[res + 1]
            o += iv[V_N_LOADS] * 4 * cols
            start += count
        return
    _product(mats, iv[O_OUT], 4, 12 + n, index, offset, buf, I_SIGNALS, buf, I_U)


def allocate_support(fy, fz, mats, oc, clip, v_min, v_max, v_mid, span, span_fits, bias, out, first):
    """The three voltages of one support for the lateral force (fy, fz) into out[first:first + 3];
    returns the fraction of the force delivered along its direction (rt/allocation.py explains
    the two modes; ``oc`` the support's coefficients: per stack, volts per N of Fy and of Fz)."""
    ay1, az1 = mats[oc], mats[oc + 1]
    ay2, az2 = mats[oc + 2], mats[oc + 3]
    ay3, az3 = mats[oc + 4], mats[oc + 5]
    if clip:
        g1 = ay1 * fy + az1 * fz
        g2 = ay2 * fy + az2 * fz
        g3 = ay3 * fy + az3 * fz
        wanted = g1 * g1 + g2 * g2 + g3 * g3
        if not wanted < math.inf:               # NaN or infinite demand, or overflow: no force
            out[first] = bias
            out[first + 1] = bias
            out[first + 2] = bias
            return 0.0
        v1, v2, v3 = bias + g1, bias + g2, bias + g3
        clipped = False
        if v1 < v_min or v1 > v_max:
            v1 = v_min if v1 < v_min else v_max
            clipped = True
        if v2 < v_min or v2 > v_max:
            v2 = v_min if v2 < v_min else v_max
            clipped = True
        if v3 < v_min or v3 > v_max:
            v3 = v_min if v3 < v_min else v_max
            clipped = True
        out[first] = v1
        out[first + 1] = v2
        out[first + 2] = v3
        if not clipped:
            return 1.0
        delivered = ((v1 - bias) * g1 + (v2 - bias) * g2 + (v3 - bias) * g3) / wanted
        return 1.0 if delivered > 1.0 - SPAN_ROUNDING else delivered
    if not (fy - fy == 0.0 and fz - fz == 0.0):  # NaN or infinite demand: no force
        fy = math.nan
        fz = math.nan
    g1 = ay1 * fy + az1 * fz
    g2 = ay2 * fy + az2 * fz
    g3 = ay3 * fy + az3 * fz
    hi = g1 if g1 > g2 else g2
    hi = hi if hi > g3 else g3
    lo = g1 if g1 < g2 else g2
    lo = lo if lo < g3 else g3
    spread = hi - lo
    if spread <= span_fits:
        scale = 1.0
    elif spread < math.inf:
        scale = span / spread
    else:                                       # NaN (invalid demand) or overflow
        scale = 0.0
        g1 = g2 = g3 = hi = lo = 0.0
    centre = v_mid - scale * 0.5 * (hi + lo)
    v = centre + scale * g1
    out[first] = v_min if v < v_min else (v_max if v > v_max else v)
    v = centre + scale * g2
    out[first + 1] = v_min if v < v_min else (v_max if v > v_max else v)
    v = centre + scale * g3
    out[first + 2] = v_min if v < v_min else (v_max if v > v_max else v)
    return scale


def _check_inputs(buf, iv, fv):
    """Fault on a non-finite strain or one beyond the strain limit, then on a load-cell value
    that is non-finite or outside the sensor's range (the new sample, in the inputs)."""
    limit = fv[P_STRAIN_LIMIT]
    for j in range(4):
        e = fv[IN_Y + j]
        if not abs(e) <= limit:
            if e != e or abs(e) == math.inf:
                _trip(buf, iv, fv, F_STRAIN_NOT_FINITE, e, limit, j)
            else:
                _trip(buf, iv, fv, F_STRAIN_OUT_OF_RANGE, e, limit, j)
            return
    load = fv[IN_LOAD]
    if not (fv[P_LOAD_LOW] <= load <= fv[P_LOAD_HIGH]):
        if load != load or abs(load) == math.inf:
            _trip(buf, iv, fv, F_LOAD_NOT_FINITE, load, 0.0, -1)
        else:
            _trip(buf, iv, fv, F_LOAD_OUT_OF_SENSOR_RANGE, load, 0.0, -1)


def _integrate(buf, iv, fv, mats):
    """xi += Theta y, unless anti-windup holds it (a saturated support whose force the
    increment would push further): True when held."""
    _matvec(mats, iv[O_TH], 4, 4, buf, I_Y, fv, X_DXI)
    scale_a, scale_b = fv[X_SCALE_A], fv[X_SCALE_B]
    if iv[V_ANTI_WINDUP] == 1 and (scale_a < 1.0 or scale_b < 1.0):
        _small_product(mats, iv[O_INT], 4, 4, iv[V_INDEX], fv[X_OFFSET], fv, X_DXI, fv, X_DU)
        du0, du1, du2, du3 = fv[X_DU], fv[X_DU + 1], fv[X_DU + 2], fv[X_DU + 3]
        if ((scale_a < 1.0 and du0 * buf[I_U] + du1 * buf[I_U + 1] > 0.0)
                or (scale_b < 1.0 and du2 * buf[I_U + 2] + du3 * buf[I_U + 3] > 0.0)):
            return True
    for j in range(4):
        buf[I_XI + j] += fv[X_DXI + j]
    return False


def _catch_up(buf, iv, fv, mats, missed):
    """The ``missed`` samples of a gap, each as a step the stacks did not see: the compensator's
    state advances on the newest strains (the nearest measurement of the samples missed) and the
    forces the stacks held (u_applied, unchanged), so that it keeps the beam's time, one step per
    sample whether it came or not. The integral stays (its increments would be the newest
    strains' N times over: a kick to the loop's slowest state for a small static correction
    missed)."""
    for _ in range(missed):
        _update(buf, iv, fv, mats)


def _control(buf, iv, fv, mats):
    """One controlled sample (RUNNING, a new sample in the record)."""
    flags = 0
    if iv[V_LAW] == 1:
        _follow(iv, fv, mats, buf[I_LOAD])
        buf[I_LOAD_FILTERED] = fv[X_FILTERED]
        if iv[V_OUT_OF_RANGE] == 1:
            flags += FLAG_LOAD_OUT_OF_TABLE
            o = iv[O_LOADS]
            _trip(buf, iv, fv, F_LOAD_OUT_OF_TABLE_RANGE, fv[X_FILTERED], mats[o + iv[V_N_LOADS] - 1], -1)
            _ramp_advance(buf, iv, fv)
            flags += FLAG_RAMPING_TO_BIAS
            _applied_forces(buf, iv, fv, mats)
            return flags
        # q = (C0 Phi)^-1 y (eq. 30), for telemetry
        _matvec(mats, iv[O_C0], 4, 4, buf, I_Y, buf, I_Q)
        # a gap: the compensator catches up on the samples it missed (the integral stays)
        missed = buf[I_BRIDGED]
        if missed > 0.0:
            _catch_up(buf, iv, fv, mats, int(missed if missed < fv[P_CATCH_UP] else fv[P_CATCH_UP]))
        # integral action with anti-windup
        if _integrate(buf, iv, fv, mats):
            flags += FLAG_INTEGRATOR_HELD
        # u = -(C x_c + D y) - Ki xi at the filtered load
        _output(buf, iv, fv, mats)
        # allocation and the clamp to the voltage range
        clip = iv[V_CLIP] == 1
        oc = iv[O_COEF]
        v_min, v_max, v_mid = fv[P_V_MIN], fv[P_V_MAX], fv[P_V_MID]
        span, fits, bias = fv[P_SPAN], fv[P_SPAN_FITS], fv[P_BIAS]
        scale_a = allocate_support(buf[I_U], buf[I_U + 1], mats, oc, clip, v_min, v_max, v_mid, span, fits,
                                   bias, fv, X_TARGET)
        scale_b = allocate_support(buf[I_U + 2], buf[I_U + 3], mats, oc + 6, clip, v_min, v_max, v_mid, span,
                                   fits, bias, fv, X_TARGET + 3)
        fv[X_SCALE_A] = scale_a
        fv[X_SCALE_B] = scale_b
        buf[I_SCALE_A] = scale_a
        buf[I_SCALE_B] = scale_b
        if scale_a < 1.0:
            flags += FLAG_SATURATED_A
        if scale_b < 1.0:
            flags += FLAG_SATURATED_B
    else:                                       # open loop (identification): bias plus the excitation
        _matvec(mats, iv[O_C0], 4, 4, buf, I_Y, buf, I_Q)
        for j in range(6):
            fv[X_TARGET + j] = fv[P_BIAS]
    # excitation rows (identification), within the voltage limits
    if iv[V_EXC_ROWS] > 0 and iv[V_EXC_ENABLED] == 1:
        k = iv[V_EXC_INDEX]
        if k < iv[V_EXC_ROWS]:
            o = iv[O_EXC] + 6 * k
            for j in range(6):
                v = fv[X_TARGET + j] + mats[o + j]
                fv[X_TARGET + j] = fv[P_V_MIN] if v < fv[P_V_MIN] else (fv[P_V_MAX] if v > fv[P_V_MAX] else v)
            iv[V_EXC_INDEX] = k + 1
    # the bumpless start: voltages faded in from bias
    iv[V_STEPS] += 1
    steps = iv[V_STEPS]
    start = iv[V_START_SAMPLES]
    b = fv[P_BIAS]
    if steps < start:
        flags += FLAG_FADING_IN
        fade = steps / start
        for j in range(6):
            buf[I_V + j] = (fv[X_TARGET + j] - b) * fade + b
    else:
        for j in range(6):
            buf[I_V + j] = fv[X_TARGET + j]
    # the forces these voltages produce, and the compensator's next state
    _applied_forces(buf, iv, fv, mats)
    if iv[V_LAW] == 1:
        _update(buf, iv, fv, mats)
        # the fade-in moves the stacks from bias on purpose: the moving statistics start over
        # where the voltages are until it ends, so that the ramp is not taken for a spread
        if steps <= start:
            _stats_start(buf, iv, fv, mats)
        else:
            _stats_update(buf, iv, fv, mats)
        if fv[X_SCALE_A] < 1.0 or fv[X_SCALE_B] < 1.0:
            iv[V_SATURATED] += 1
            if iv[V_SATURATED] >= iv[V_SAT_LIMIT]:
                _trip(buf, iv, fv, F_PERSISTENT_SATURATION, iv[V_SATURATED], iv[V_SAT_LIMIT], -1)
        else:
            iv[V_SATURATED] = 0
    return flags


def cycle(buf, iv, fv, mats, sample):
    """One control period. ``sample`` 1: a new sample in the inputs (IN_TIME, IN_SEQUENCE, IN_Y,
    IN_LOAD, IN_MISSED: samples of the source skipped before it); 0: none arrived (IN_SILENT:
    periods since the last one, negative to count one period per call). Returns the state."""
    flags = 0
    buf[I_ANSWER_AGE_US] = math.nan
    buf[I_BRIDGED] = 0.0
    running = iv[V_STATE] == S_RUNNING
    missed = 0
    if sample == 0:
        flags = FLAG_NO_NEW_SAMPLE
        buf[I_INPUT_PERIOD_US] = math.nan
        iv[V_SILENT] += 1
        silent = fv[IN_SILENT]
        if silent < 0.0:
            silent = float(iv[V_SILENT])
        # the samples due in that time are missing: more than gap_limit of them fault (compared
        # as floats: an endless or unknown silence, inf or NaN, faults too)
        if running and not silent < iv[V_GAP_LIMIT] + 1.0:
            _trip(buf, iv, fv, F_STALE_INPUT, silent, iv[V_GAP_LIMIT], -1)
    else:
        iv[V_SILENT] = 0
        t = fv[IN_TIME]
        fv[X_TIME] = t
        since = t - buf[I_TIME]
        buf[I_INPUT_PERIOD_US] = since * 1e6
        buf[I_TIME] = t
        buf[I_SEQUENCE] = fv[IN_SEQUENCE]
        buf[I_HELD] = 0.0
        # compared as a float before it is a count: a gap of any length (beyond int64 too) faults
        gap = fv[IN_MISSED]
        if running:
            _check_inputs(buf, iv, fv)
            if gap < 0.0:
                missed = 0
            elif gap < GAP_COUNT_CAP:
                missed = int(gap)
            else:                                   # beyond int64, or NaN: the cap
                missed = int(GAP_COUNT_CAP)
            # the stacks held the last answer for as long as the samples missing, or the silence
            # before this one, whichever is longer: that time is what the limit is compared with
            held = gap if gap > 0.0 else 0.0
            silent = math.floor(since / fv[P_PERIOD] - 0.5) if since > 0.0 else 0.0
            if silent > held:
                held = silent
            if not gap <= GAP_COUNT_CAP:
                held = gap
            buf[I_HELD] = held
            if held > iv[V_MAX_GAP]:
                iv[V_MAX_GAP] = int(held) if held < GAP_COUNT_CAP else int(GAP_COUNT_CAP)
            if held > 0.0 or not held == held:
                # the gap is bridged by catching up (``_control``, ``_catch_up``): the
                # compensator steps once per sample missed, the integral stays
                if not held <= fv[X_LET_GO]:
                    _trip(buf, iv, fv, F_STALE_INPUT, held, fv[X_LET_GO], -1)
                elif iv[V_STATE] == S_RUNNING and iv[V_LAW] == 1 and missed > 0:
                    flags += FLAG_BRIDGED
                    buf[I_BRIDGED] = missed
                    iv[V_BRIDGED] += missed
        for j in range(4):
            buf[I_Y + j] = fv[IN_Y + j]
        buf[I_LOAD] = fv[IN_LOAD]
    state = iv[V_STATE]
    if state == S_RUNNING:
        if sample == 1:                         # no new sample: the voltages hold, the law waits
            flags += _control(buf, iv, fv, mats)
    else:
        if sample == 1:                         # keep observing: q for telemetry and the operator
            _matvec(mats, iv[O_C0], 4, 4, buf, I_Y, buf, I_Q)
        if state == S_FAULT or state == S_STOPPING:
            flags += FLAG_RAMPING_TO_BIAS
            if _ramp_advance(buf, iv, fv) and iv[V_STATE] == S_STOPPING:
                iv[V_STATE] = S_STOPPED
        _applied_forces(buf, iv, fv, mats)
    buf[I_FLAGS] = flags
    buf[I_STATE] = iv[V_STATE]
    buf[I_FAULT] = iv[V_FAULT]
    return iv[V_STATE]


def core_array(buffer_size, mats):
    """The engine's one array for a gain table: ``buf`` (``buffer_size``), ``fv``, ``iv`` (its
    int64 values in float64 slots, read through a view), then ``mats``. One array is one
    argument to unbox per call (numba's dispatch costs per argument)."""
    core = np.zeros(buffer_size + N_FV + N_IV + mats.size)
    core[buffer_size + N_FV + N_IV:] = mats
    return core


def core_views(core, buffer_size):
    """(buf, fv, iv, mats) of a ``core_array`` whose buffer is ``buffer_size`` long: views,
    sharing its memory."""
    b = buffer_size
    return core[:b], core[b:b + N_FV], core[b + N_FV:b + N_FV + N_IV].view(np.int64), core[b + N_FV + N_IV:]


def sample_cycle(core, nb, time_s, sequence, load_n, missed, strains):
    """``cycle`` on a new sample given as arguments, over a ``core_array`` whose buffer is ``nb``
    long (the loop's call: one array to unbox, no Python writes into the inputs first). Returns
    the state."""
    buf = core[:nb]
    fv = core[nb:nb + N_FV]
    iv = core[nb + N_FV:nb + N_FV + N_IV].view(np.int64)
    mats = core[nb + N_FV + N_IV:]
    fv[IN_TIME] = time_s
    fv[IN_SEQUENCE] = sequence
    fv[IN_LOAD] = load_n
    fv[IN_MISSED] = missed
    for j in range(4):
        fv[IN_Y + j] = strains[j]
    return cycle(buf, iv, fv, mats, 1)


def answered(buf, iv, fv, age_s):
    """The answer to the latest sample had been sent ``age_s`` after the sample arrived (NaN: not
    measured). Later than the budget it is late (counted). An answer later than the delay the loop
    tolerates held the stacks at a stale voltage; more than ``late_limit`` such answers in a row
    fault a running controller (a streak of answers late within that delay is a loop running with
    more delay than its design, stable: the stacks never hold one voltage much longer than a
    period). Returns the state."""
    if age_s != age_s:
        return iv[V_STATE]
    buf[I_ANSWER_AGE_US] = age_s * 1e6
    if age_s <= fv[P_BUDGET_S]:
        iv[V_LATE_STREAK] = 0
    else:
        iv[V_LATE_TOTAL] += 1
        if age_s <= fv[P_TOLERATED_S]:
            iv[V_LATE_STREAK] = 0
        else:
            iv[V_LATE_STREAK] += 1
            if iv[V_LATE_STREAK] > iv[V_LATE_LIMIT] and iv[V_STATE] == S_RUNNING:
                _trip(buf, iv, fv, F_LATE_ANSWERS, age_s, fv[P_TOLERATED_S], iv[V_LATE_STREAK])
    buf[I_LATE_ANSWERS] = iv[V_LATE_TOTAL]
    buf[I_STATE] = iv[V_STATE]
    buf[I_FAULT] = iv[V_FAULT]
    return iv[V_STATE]


def _clear(buf, iv, fv, mats, with_sample):
    """Arming: integrator and compensator at rest, stacks at bias, the counts start again (the
    overrun streak is the loop's and keeps counting); with a sample (in the inputs) the load
    filter, the strains and q start from it."""
    n = iv[V_N_X]
    for j in range(4):
        buf[I_XI + j] = 0.0
        buf[I_APPLIED + j] = 0.0
    for j in range(n):
        buf[N_COLUMNS + j] = 0.0
    for j in range(6):
        buf[I_V + j] = fv[P_BIAS]
    iv[V_RAMP_STEP] = 0
    iv[V_SATURATED] = 0
    iv[V_SILENT] = 0
    iv[V_LATE_STREAK] = 0
    fv[X_SCALE_A] = 1.0
    fv[X_SCALE_B] = 1.0
    if with_sample == 1:
        buf[I_TIME] = fv[IN_TIME]
        fv[X_TIME] = fv[IN_TIME]
        buf[I_SEQUENCE] = fv[IN_SEQUENCE]
        buf[I_LOAD] = fv[IN_LOAD]
        _reset_schedule(iv, fv, mats, fv[IN_LOAD])
        for j in range(4):
            buf[I_Y + j] = fv[IN_Y + j]
        _matvec(mats, iv[O_C0], 4, 4, buf, I_Y, buf, I_Q)
    else:
        buf[I_TIME] = math.nan


def command(buf, iv, fv, mats, what, arg):
    """A lifecycle command or a report of the loop (``C_*``); 0 when carried out, a refusal
    (``R_*``) when not allowed now. ``arg``: C_ARM/C_REARM 1 with a sample in the inputs;
    C_TRIP the fault; C_OVERRAN/C_ON_TIME unused. C_RAMP_ADVANCE returns 1 once at bias."""
    state = iv[V_STATE]
    if what == C_ARM:
        if state != S_INIT:
            return R_STATE
        iv[V_STATE] = S_ARMED
        _clear(buf, iv, fv, mats, arg)
    elif what == C_REARM:
        if not _at_bias(buf, fv):
            return R_NOT_AT_BIAS
        if state != S_FAULT and state != S_STOPPED:
            return R_STATE
        iv[V_STATE] = S_ARMED
        iv[V_FAULT] = F_NONE
        iv[V_FAULT_CHANNEL] = -1
        _clear(buf, iv, fv, mats, arg)
    elif what == C_START:
        if state != S_ARMED:
            return R_STATE
        iv[V_STATE] = S_RUNNING
        _reset_schedule(iv, fv, mats, buf[I_LOAD])
        iv[V_STEPS] = 0
        iv[V_EXC_INDEX] = 0
        for j in range(4):
            buf[I_XI + j] = 0.0
        finite = True
        for j in range(4):
            if not (buf[I_Y + j] - buf[I_Y + j] == 0.0):
                finite = False
        n = iv[V_N_X]
        if not finite:
            for j in range(4):
                buf[I_Q + j] = 0.0
            for j in range(n):
                buf[N_COLUMNS + j] = 0.0
            _trip(buf, iv, fv, F_STRAIN_NOT_FINITE, math.nan, fv[P_STRAIN_LIMIT], -1)
        else:
            _matvec(mats, iv[O_START], n, 4, buf, I_Y, buf, N_COLUMNS)
            _stats_start(buf, iv, fv, mats)
    elif what == C_STOP:
        if state == S_RUNNING or state == S_ARMED or state == S_INIT:
            _ramp_begin(buf, iv, fv)
            iv[V_STATE] = S_STOPPING
    elif what == C_TRIP:
        _trip(buf, iv, fv, arg, math.nan, math.nan, -1)
    elif what == C_RESET_SCHEDULE:
        _reset_schedule(iv, fv, mats, buf[I_LOAD])
    elif what == C_RAMP_BEGIN:
        _ramp_begin(buf, iv, fv)
    elif what == C_RAMP_ADVANCE:
        return 1 if _ramp_advance(buf, iv, fv) else 0
    elif what == C_OVERRAN:
        iv[V_OVERRUN_STREAK] += 1
        if iv[V_OVERRUN_STREAK] > iv[V_OVERRUN_MAX]:
            iv[V_OVERRUN_MAX] = iv[V_OVERRUN_STREAK]
        if iv[V_OVERRUN_STREAK] >= iv[V_OVERRUN_LIMIT]:
            _trip(buf, iv, fv, F_OVERRUN_STREAK, iv[V_OVERRUN_STREAK], iv[V_OVERRUN_LIMIT], -1)
    elif what == C_ON_TIME:
        iv[V_OVERRUN_STREAK] = 0
    elif what == C_CLEAR:
        _clear(buf, iv, fv, mats, arg)
    buf[I_STATE] = iv[V_STATE]
    buf[I_FAULT] = iv[V_FAULT]
    return 0


def allocate(u, mats, oc, clip, v_min, v_max, v_mid, span, span_fits, bias, out):
    """Both supports: four forces -> six voltages into ``out``; returns (scale A, scale B)."""
    a = allocate_support(u[0], u[1], mats, oc, clip, v_min, v_max, v_mid, span, span_fits, bias, out, 0)
    b = allocate_support(u[2], u[3], mats, oc + 6, clip, v_min, v_max, v_mid, span, span_fits, bias, out, 3)
    return a, b


# reassociation lets the compiler split a dot product's sum into vector lanes; NaN and infinity
# keep their IEEE meaning (the checks of a sample rely on them)
FASTMATH = {"reassoc", "contract"}


def _jit(fn):
    return numba.njit(cache=True, nogil=True, fastmath=FASTMATH)(fn)


# compiled in dependency order (callees first), so that each compiled caller binds the compiled
# callee: the module's names are rebound to the compiled functions
_scratch = _jit(_scratch)
_at_bias = _jit(_at_bias)
_ramp_begin = _jit(_ramp_begin)
_ramp_advance = _jit(_ramp_advance)
_trip = _jit(_trip)
gap_allowed = _jit(gap_allowed)
_allowed_over = _jit(_allowed_over)
_allowed = _jit(_allowed)
_live_limit = _jit(_live_limit)
_stats_start = _jit(_stats_start)
_stats_update = _jit(_stats_update)
_limits = _jit(_limits)
_settle = _jit(_settle)
_reset_schedule = _jit(_reset_schedule)
_follow = _jit(_follow)
_product = _jit(_product)
_small_product = _jit(_small_product)
_matvec = _jit(_matvec)
_applied_forces = _jit(_applied_forces)
_gather = _jit(_gather)
_update = _jit(_update)
_output = _jit(_output)
allocate_support = _jit(allocate_support)
_check_inputs = _jit(_check_inputs)
_integrate = _jit(_integrate)
_catch_up = _jit(_catch_up)
_control = _jit(_control)
cycle = _jit(cycle)
sample_cycle = _jit(sample_cycle)
answered = _jit(answered)
_clear = _jit(_clear)
command = _jit(command)
allocate = _jit(allocate)


def source_digest(*others) -> str:
    """SHA-256 of this file and of the modules ``others``: a compiled caller in another module
    (numba keys its disk cache on the caller's file only) drops its cache when the engine, or
    another module it compiled in, has changed."""
    import hashlib

    h = hashlib.sha256()
    for path in (__file__, *(m.__file__ for m in others)):
        with open(path, "rb") as f:
            h.update(f.read())
    return h.hexdigest()


def compile_caller(fn, callees=(), **options):
    """``fn`` compiled like the engine (numba ``njit``, cached on disk, ``options`` added) for a
    caller in another module that calls the engine's functions (and those of the modules
    ``callees``): numba keys a disk cache on the caller's own file, and the code it compiled in
    would go stale unseen; the caller's cache is dropped when these files' content differs from
    the one it was compiled with."""
    from pathlib import Path

    options = {"nogil": True, "fastmath": FASTMATH, **options}
    dispatcher = numba.njit(cache=True, **options)(fn)
    try:
        cache = dispatcher._cache
        stamp = Path(cache._cache_path) / f"{fn.__module__}.{fn.__qualname__}.engine-sha256"
        digest = source_digest(*callees)
        if not stamp.exists() or stamp.read_text() != digest:
            cache.flush()
            stamp.write_text(digest)
    except (AttributeError, OSError):       # no disk cache there: compiled in each process
        dispatcher = numba.njit(cache=False, **options)(fn)
    return dispatcher


def warm_up() -> float:
    """Compile (or load from numba's cache) every entry point now, not at the first sample;
    return the seconds it took."""
    import time

    start = time.perf_counter()
    n = 2
    buf = np.zeros(N_COLUMNS + n + scratch_size(n))
    iv = np.zeros(N_IV, dtype=np.int64)
    fv = np.zeros(N_FV)
    mats = np.zeros(256)
    iv[V_N_LOADS], iv[V_N_X], iv[V_RAMP_SAMPLES], iv[V_START_SAMPLES] = 1, n, 1, 1
    command(buf, iv, fv, mats, C_CLEAR, 0)
    cycle(buf, iv, fv, mats, 0)
    answered(buf, iv, fv, math.nan)
    allocate(np.zeros(4), mats, 0, False, 0.0, 1.0, 0.5, 1.0, 1.0, 0.5, np.zeros(6))
    return time.perf_counter() - start
