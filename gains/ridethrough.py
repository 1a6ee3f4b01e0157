"""How long the closed loop rides through a stall (samples missing, or answers late: to the beam
the same, the stacks hold a stale voltage), in absolute terms: computed when a table is built and
stored in it (``ride_through:``); the real-time engine turns it into a live limit from what it
measures while it runs (rt/engine.py, ``_live_limit``).

Survival. A gap of N samples is survived when, through the gap and the recovery after it, the
beam's deflection stays within the strain limit the supervisor enforces and the stacks' voltages
within their range, with ``confidence_sigma`` (3.5) standard deviations to spare. The strain limit
is the deflection limit: at the shipped 0.5 x the proportional limit it is reached at about 13 mm,
well inside the end stops (models/plant.py, 20 mm for the paper's beam). What a gap does to the
beam is the loop's linear physics, per load: the table stores, for every gap length N of a grid
(``gap_grid_samples``), how much the spread of the buckling mode's deflection and of the stacks'
forces grows, the growth g(N) = the largest RMS at any sample of the gap and its recovery over the
stationary RMS. The size of what must be survived comes from the rig itself: the engine measures,
while it runs, the spread (RMS) and the mean of its own estimate of mode 1 (q_1 in each plane, in
the strains it puts at the gauges) and of every stack's voltage, and takes the headroom the
operating point leaves (the strain limit less the largest mean strain; the nearer voltage limit
less each stack's mean). A gap of N is allowed while

    confidence_sigma x g_deflection(N) x spread_deflection <= strain headroom   and
    confidence_sigma x g_voltage(N) x spread_voltage       <= voltage headroom,

and the live limit is the longest gap allowed (of the grid, and on to where the growth,
interpolated linearly in its logarithm towards the next grid gap, reaches what is allowed). The
let-go, past which a stall faults, is the same at ``LET_GO_SIGMA`` (1) instead of k: the gap
where the recovery's expected peak reaches the headroom. A rig with a larger spread, or less
headroom (more load, a larger bow), gets a shorter limit; below the critical load the growth
stays near 1 and the limit is the cap. The relative criterion of earlier tables ("the RMS at most
doubles") is gone: a gap is lost when the beam or the stacks reach a limit, and the margin is the
k-sigma bound on a linear model evaluated on the rigs below, not a factor on a small number.

Rigs. The growth is analysed on the nominal rig (the model's FE plane with the design's I/O chain,
``gains.build.nominal_rig``) and, where the table records a robust check, on its worst rig too
(its own beam, supports, damping, stacks, delay, gauges and DAQ clock, gains/robust.py): the
stored growth is the larger at every load and gap. A rig whose loop is unstable at a load is not
held there at all and has no stationary state to ride through from: it does not count at that
load (its onset is what the robust check reports).

Bridges. When a gap ends the engine has ``missed`` samples to bridge before it answers the newest
one. It catches up (``catch_up``, the one stored): the compensator's state makes one step per
sample missed on the newest strains and the forces the stacks held, x_c <- A^N x_c + S_N (B y + E
u_held) with S_N = sum_{j<N} A^j (at most ``CATCH_UP_SAMPLES`` of them), the integral stays, and
the newest sample enters the normal step. During the gap itself that is the hold's loop (``hold``:
the compensator frozen, which it may be, since it does not reach the beam until it answers); the
catch-up is a map of the loop's state at the gap's end (``CatchUp``). Holding the compensator after
the gap too (the bridge stored before) runs it slower than the beam when samples keep missing; a
table that stores the hold's growth is read as the catch-up's (on the shipped table the two agree
within 7 % for the deflection, and the hold's is the larger for the voltages: `beamctl gains build`
analyses the catch-up). The other way, ``predict`` (N prediction steps of the compensator, y_hat =
P x_c, x_c <- A x_c + B y_hat + E u_held, then the normal step), has a growth of its spread close
to hold's here, but in the time domain it drifts from the operating point the beam is held at (the
static deflection of the bow under load, which the prediction does not hold): over CAN at 2800 to
3300 N on the simulated rig, a 1 ms gap bridged by prediction moved the stacks by 3 to 85 V, held
by 0.2 to 1 V. ``gap_matrix`` builds both (tests/gains/test_ridethrough.py compares them in the
time domain); the table stores the growth of the bridge the engine runs.

The plant does not see the compensator while the voltages are held, so running those steps late
or on time is the same loop: per missing sample, x <- Ad x + g (B_now + B_before) u_held (the
delayed ZOH with every force in it held; g the rig's stack gain), and the compensator as above
(``gap_matrix``); then the normal loop again.

How. The loop runs stationary, driven by a force disturbance at the stacks, white per sample and
entering the plant as the LQG design's force noise does (only ratios are stored, so its size
cancels). A gap starts after a normal sample; the state covariance is propagated exactly through
the N missing samples (the disturbance still acting) and then through the normal loop until a
bound says no later sample can exceed the largest so far (or 1.1 x stationary): with Delta_m the
covariance's excess over the stationary Sigma after m normal samples (Delta_m+1 = M Delta_m M^T),
once Delta_m <= alpha Pi (Pi = Sigma + 1e-6 Y, Y = M Y M^T + I, so that Pi >= M Pi M^T) no later
sample's variance exceeds the stationary one plus alpha times out Pi out^T. The stationary
covariance by a Lyapunov solve (states scaled by their stationary RMS); the gap's trajectory, the
same for every N, by rows out G^j; the covariance after N missing samples by binary powers of G
from the last N's. The growth is made non-decreasing in N (the largest up to N), and a growth past
``GROWTH_CAP`` is stored as the cap (no headroom allows it).

The deflection is the modal displacement of mode 1 (the lowest mode of the plane's FE model at
that load, mass-normalised, projected with the mass matrix): the buckling mode, which the loop
holds and which diverges when it is open beyond Fx,cr; the voltage the larger of the plane's two
support forces (a stack's voltage is its support's y and z forces combined: the planes are
independent, so its growth is at most the larger of theirs).

Loads. The analysed loads are those of the table's closed-loop check (``gains.build.check_plan``:
grid points, midpoints, paper mode's band ends) and, from 0.95 of the nominal Fx,cr up, every
25 N (``gains.build.ride_through_plan``: the growth rises steeply with the load there); the engine
takes the larger growth of the two analysed loads around its filtered load.

Delay. The largest extra output delay, on a grid of ``DELAY_STEP_SAMPLES`` up to
``DELAY_CAP_SAMPLES``, on top of the design's own (``design.io.delay_samples``), with which the
nominal loop is stable (spectral radius < 1) at that load and at every delay of the grid below
it; the engine's answer budget is the design's delay plus half of it (``DELAY_MARGIN``), per grid
load (``answer_budgets_periods``). An answer sent later counts as late; a run of late answers
longer than the live limit faults. Stability need not fall with the delay (a pole can be unstable
in a window of delays only), so every grid load walks the grid up from the nominal; the other
check loads are tested at their interval's limit (and walked below it only where unstable there).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg as sla

from beamctl.gains.closedloop import closed_loop_matrix
from beamctl.gains.compensator import PLANE_CHANNELS, CompensatorPoint
from beamctl.gains.rig import RigPlane
from beamctl.models.fe import FEModel, plane_eigen, plane_indices
from beamctl.models.iochain import (
    DelayedZOH,
    _gamma,  # the one matrix exponential of a ZOH
)
from beamctl.rt.engine import CATCH_UP_SAMPLES, GROWTH_CAP, gap_allowed

CONFIDENCE_SIGMA = 3.5      # the k of the k-sigma bound (one-sided 2.3e-4 at the recovery's peak, on
                            # spreads measured with the gauges' noise in them, which does not grow in a
                            # gap: in the time domain the survival edge is 1.3 to 2.3 x the limit
                            # past Fx,cr on the nominal and the worst rig, `beamctl gains stalls`)
# the let-go: a stall, or a streak of stale answers, faults once it is longer than the gap whose
# growth the headroom allows over the spreads taken at this many sigma instead of k (or over the
# excursion a recovery under way shows beyond the k spreads, whole): where the recovery's
# expected peak reaches the strain or the voltage limit, the beam is more likely lost than held.
# Up to the live limit a stall is survived with k sigma to spare; between the two it is ridden
# through and recorded: letting go sooner holds no beam past its critical load (the stacks at bias
# do not), the stacks stay clamped within their range either way, and once the samples come back
# the supervisor sees what the beam did (strain limit, saturation). Measured against the survival
# edge in the time domain: simulation/stall.py, tests/simulation/test_stall.py.
LET_GO_SIGMA = 1.0          # (rt/controller.py, rt/engine.py ``_live_limit``)
# GROWTH_CAP (rt/engine.py, 2000): a growth beyond it is stored as it, and the engine never allows
# it (at 3.5 sigma no headroom would: 75 V over 3.5 x 0.05 V RMS is 429; 3200 ue over 3.5 x 0.5 ue
# 1830; at the let-go's 1 sigma one might, but a loop that far gone has diverged)
SETTLED = 1.1               # the recovery is followed until nothing later exceeds max(peak, 1.1 x stationary)
GAP_HORIZON_S = 0.1         # the gap grid ends at this long a gap: the DAQ has stopped, not paused
DELAY_STEP_SAMPLES = 0.05   # grid of the extra output delay
DELAY_CAP_SAMPLES = 1.0     # the delay search stops here: a whole sample late, the next one is due
DELAY_MARGIN = 2.0          # the answer budget is the design's delay plus the tolerated extra / this
BOUND_EPS = 1e-6            # regularisation of the settling bound (see GrowthAnalysis)
GAP_BLOCK = 64              # samples of the gap's trajectory and the recovery computed at once
RECOVERY_CAP_SAMPLES = 1 << 18   # a recovery not bounded by then counts as past the cap
BRIDGES = ("catch_up",)     # the bridges stored (see "Bridges" above)
LEGACY_BRIDGE = "hold"      # the one stored before the catch-up (read as it: a longer growth, safe)
OUTPUTS = ("deflection", "voltage")
# the reference operating point ``gains show`` quotes the limit at: the spreads and headroom of
# the simulated rig at 3300 N with 0.2 ue gauge noise (stacks 66-84 V, 0.14-0.19 V RMS; mode 1 a
# few ue at the gauges against 3200 ue)
REFERENCE = {"deflection_spread": 2.0e-6, "deflection_headroom": 3.0e-3,
             "voltage_spread_v": 0.2, "voltage_headroom_v": 60.0}


def gap_grid(cap: int) -> tuple[int, ...]:
    """The gap lengths whose growth is stored: every sample to 8, then about 12 % apart, to
    ``cap``."""
    grid, n = [], 1
    while n < cap:
        grid.append(n)
        n = n + 1 if n < 8 else max(n + 1, int(round(n * 1.12)))
    grid.append(int(cap))
    return tuple(grid)


def gap_horizon_samples(sample_rate_hz: float) -> int:
    """The gap grid's cap: GAP_HORIZON_S of samples (600 at 6000 Hz, 250 at 2500 Hz)."""
    return max(int(round(GAP_HORIZON_S * sample_rate_hz)), 1)


@dataclass(frozen=True)
class RideThrough:
    """A table's ride-through analysis (see the module docstring), stored under ``ride_through``.
    ``growth`` [bridge, output, analysed load, grid gap]: BRIDGES x OUTPUTS x ``loads_n`` x
    ``gap_grid_samples``. The delay part per grid load (``table.loads_n``)."""

    confidence_sigma: float
    gap_grid_samples: tuple[int, ...]
    loads_n: tuple[float, ...]
    rigs: tuple[str, ...]
    growth: np.ndarray
    max_extra_delay_samples_per_load: tuple[float, ...]
    answer_budgets_periods: tuple[float, ...]
    delay_step_samples: float
    delay_cap_samples: float
    elapsed_s: float
    criterion: str = "absolute"

    FIELDS = ("criterion", "confidence_sigma", "gap_grid_samples", "loads_N", "rigs", "growth",
              "max_extra_delay_samples_per_load", "answer_budgets_periods", "delay_step_samples",
              "delay_cap_samples", "elapsed_s")

    def __post_init__(self) -> None:
        object.__setattr__(self, "gap_grid_samples", tuple(int(v) for v in self.gap_grid_samples))
        object.__setattr__(self, "loads_n", tuple(float(v) for v in self.loads_n))
        object.__setattr__(self, "rigs", tuple(str(v) for v in self.rigs))
        object.__setattr__(self, "growth", np.asarray(self.growth, dtype=float))
        object.__setattr__(self, "max_extra_delay_samples_per_load",
                           tuple(float(v) for v in self.max_extra_delay_samples_per_load))
        object.__setattr__(self, "answer_budgets_periods",
                           tuple(float(v) for v in self.answer_budgets_periods))

    @property
    def gap_cap_samples(self) -> int:
        return self.gap_grid_samples[-1]

    @property
    def answer_budget_periods(self) -> float:
        """The least answer budget over the grid loads."""
        return min(self.answer_budgets_periods)

    def to_dict(self) -> dict[str, Any]:
        return {"criterion": self.criterion, "confidence_sigma": float(self.confidence_sigma),
                "gap_grid_samples": list(self.gap_grid_samples), "loads_N": list(self.loads_n),
                "rigs": list(self.rigs),
                "growth": {b: {o: [[float(round(v, 6)) for v in row] for row in self.growth[i, k]]
                               for k, o in enumerate(OUTPUTS)} for i, b in enumerate(BRIDGES)},
                "max_extra_delay_samples_per_load": list(self.max_extra_delay_samples_per_load),
                "answer_budgets_periods": list(self.answer_budgets_periods),
                "delay_step_samples": float(self.delay_step_samples),
                "delay_cap_samples": float(self.delay_cap_samples), "elapsed_s": float(self.elapsed_s)}

    def interval_growth(self, grid_loads: Sequence[float]) -> np.ndarray:
        """[interval, bridge, output, gap]: per interval [L_j, L_j+1] of ``grid_loads`` (the
        last, L_last alone) the largest growth of every analysed load in it, ends included (the
        engine's intervals are those between the analysed loads)."""
        grid_loads = np.asarray(grid_loads, dtype=float)
        loads = np.asarray(self.loads_n)
        out = np.zeros((len(grid_loads), *self.growth.shape[:2], self.growth.shape[3]))
        for j, low in enumerate(grid_loads):
            high = grid_loads[min(j + 1, len(grid_loads) - 1)]
            inside = (loads >= low - 1e-9) & (loads <= high + 1e-9)
            if not inside.any():
                raise ValueError(f"no analysed load in the grid interval [{low:g}, {high:g}] N")
            out[j] = self.growth[:, :, inside, :].max(axis=2)
        return out

    def reference_limits(self, grid_loads: Sequence[float], let_go: bool = False) -> list[tuple[int, str]]:
        """At each of ``grid_loads``: the live limit (``let_go``: the let-go) at the ``REFERENCE``
        operating point in samples, as the engine computes it there (rt/engine.py ``gap_allowed``,
        over the interval of analysed loads the load starts), and the bridge."""
        k = self.confidence_sigma
        at = min(LET_GO_SIGMA, k) if let_go else k
        allowed_q = REFERENCE["deflection_headroom"] / (at * REFERENCE["deflection_spread"])
        allowed_v = REFERENCE["voltage_headroom_v"] / (at * REFERENCE["voltage_spread_v"])
        grid = np.asarray(self.gap_grid_samples, dtype=float)
        breaks = np.unique(np.asarray(self.loads_n))
        growth = self.interval_growth(breaks)
        out = []
        for load in grid_loads:
            j = max(int(np.searchsorted(breaks, float(load), side="right")) - 1, 0)
            flat = np.ascontiguousarray(growth[j]).ravel()
            limits = [int(gap_allowed(flat, b * 2 * len(grid), grid, 0, len(grid), allowed_q, allowed_v))
                      for b in range(len(BRIDGES))]
            best = int(np.argmax(limits))
            out.append((limits[best], BRIDGES[best]))
        return out

    def reference_text(self, grid_loads: Sequence[float], sample_rate_hz: float) -> str:
        """What the reference operating point's limits are, and the limit per grid load in ms."""
        rows = self.reference_limits(grid_loads)
        go = self.reference_limits(grid_loads, let_go=True)
        cap = self.gap_cap_samples
        parts = [f"{load:g} N {1e3 * n / sample_rate_hz:.1f}{'+' if n >= cap else ''}"
                 + (f" (let go {1e3 * m / sample_rate_hz:.1f})" if m > n else "")
                 for load, (n, _), (m, _) in zip(grid_loads, rows, go, strict=True)]
        return ("ride-through per load in ms at the reference operating point (mode 1 spread "
                f"{REFERENCE['deflection_spread'] * 1e6:g} ue at the gauges, "
                f"{REFERENCE['deflection_headroom'] * 1e6:g} "
                f"ue to the strain limit; stacks {REFERENCE['voltage_spread_v']:g} V RMS, "
                f"{REFERENCE['voltage_headroom_v']:g} V to their range; the engine measures its own): "
                + ", ".join(parts) + f" ('+': the grid's end, {1e3 * cap / sample_rate_hz:g} ms; let go: a "
                "longer stall faults, where the recovery's expected peak reaches the headroom)")

    def describe(self, grid_loads: Sequence[float], sample_rate_hz: float) -> str:
        rows = self.reference_limits(grid_loads)
        ms = [1e3 * n / sample_rate_hz for n, _ in rows]
        worst = int(np.argmin(ms))
        rigs = " and ".join(self.rigs)
        return (f"absolute: {self.confidence_sigma:g} sigma within the strain and voltage limits, on {rigs}; "
                f"at the reference operating point {ms[0]:.1f} ms at {grid_loads[0]:g} N, the least "
                f"{ms[worst]:.1f} ms at {grid_loads[worst]:g} N (bridge {rows[worst][1]}); answers up to "
                f"{self.answer_budget_periods:.2f} to {max(self.answer_budgets_periods):.2f} periods after "
                f"their sample")


def answer_budget(design_delay_samples: float, max_extra_delay_samples: float) -> float:
    """The engine's answer budget in periods: the design's own output delay (an answer within it
    is what the design assumes) plus the tolerated extra delay over DELAY_MARGIN."""
    return float(design_delay_samples) + max_extra_delay_samples / DELAY_MARGIN


# ---------------------------------------------------------------------------------------------
# the loop's matrices


@dataclass(frozen=True)
class GapLoop:
    """The matrices of one plane's loop at one load (closed-loop state z as in gains/closedloop.py):

    normal: z <- M z + W w;  a missing sample: [z; y_held] <- G [z; y_held] + [W; 0] w, entered
    from the last normal sample by [z; y_held] = [M; Cz] z + [W; 0] w (y_held: that sample's
    strains, which a table without a prediction feeds its compensator); ``outputs`` the rows of
    z giving mode 1's modal displacement and the plane's two applied support forces."""

    m: np.ndarray
    g: np.ndarray
    entry: np.ndarray
    w: np.ndarray
    outputs: np.ndarray
    catch: CatchUp | None = None

    @property
    def n(self) -> int:
        return self.m.shape[0]


class CatchUp:
    """The engine's catch-up at the end of a gap of N samples (rt/engine.py ``_catch_up``), as a
    map of the loop's state z <- J_N z: the compensator steps once per sample missed (at most
    ``cap``) on the newest strains y = C x and the forces the stacks held, x_c <- A^N x_c +
    S_N (B C x + E u_held), S_N = sum_{j<N} A^j; the integral stays. The gap itself is the
    hold's (the compensator frozen: it does not reach the beam until it answers)."""

    def __init__(self, total: int, ic: int, ii: int, a: np.ndarray, feed: np.ndarray, cap: int) -> None:
        self.total, self.ic, self.ii = total, ic, ii
        self.a, self.feed, self.cap = a, feed, int(cap)
        nc = a.shape[0]
        self._n = 0
        self._power = np.eye(nc)                # A^n
        self._sum = np.zeros((nc, nc))          # S_n

    def matrix(self, n_gap: int) -> np.ndarray:
        """J_N for a gap of ``n_gap`` samples (asked for in increasing length)."""
        n = min(int(n_gap), self.cap)
        if n < self._n:
            raise ValueError("the gaps are analysed in increasing length")
        while self._n < n:
            self._sum = np.eye(self.a.shape[0]) + self.a @ self._sum
            self._power = self.a @ self._power
            self._n += 1
        ic, ii = self.ic, self.ii
        j = np.eye(self.total)
        j[ic:ii] = self._sum @ self.feed
        j[ic:ii, ic:ii] += self._power
        return j


def gap_matrix(plant: DelayedZOH, comp: CompensatorPoint, bridge: str = "predict",
               force_gain: float = 1.0) -> np.ndarray:
    """The loop during a missing sample, on [z; y_held] (see the module docstring): the plant
    runs on the force of the last answer (the newest entry of the force buffer) times the rig's
    stack gain, the compensator predicts (``predict``) or holds (``hold``), the integral and the
    held strains stay. ``comp`` of one plane."""
    if bridge not in ("hold", "predict"):
        raise ValueError(f"bridge {bridge!r}: expected hold or predict")
    n = plant.ad.shape[0]
    whole = plant.whole
    nb = 2 * (whole + 1)
    nc = comp.a.shape[0]
    total = n + nb + nc + 2
    ib, ic, ii, iy = n, n + nb, n + nb + nc, n + nb + nc + 2
    g = np.zeros((total + 2, total + 2))
    g[:n, :n] = plant.ad

    def force(k_back: int, matrix: np.ndarray) -> None:
        """x_k+1 += g matrix u_k-k_back, u_k = the held force (buffer entry u_k-1)."""
        col = ib + 2 * max(k_back - 1, 0)
        g[:n, col:col + 2] += force_gain * matrix

    force(whole, plant.b_now)
    if plant.fraction > 0.0:
        force(whole + 1, plant.b_before)
    # buffer [u_k-1, ..., u_k-whole-1] <- [u_k = u_k-1, u_k-1, ..., u_k-whole]
    g[ib:ib + 2, ib:ib + 2] = np.eye(2)
    for j in range(1, whole + 1):
        g[ib + 2 * j:ib + 2 * j + 2, ib + 2 * (j - 1):ib + 2 * j] = np.eye(2)
    if bridge == "hold":
        g[ic:ii, ic:ii] = np.eye(nc)
    else:
        g[ic:ii, ic:ii] = comp.a
        g[ic:ii, ib:ib + 2] = comp.e
        if comp.predict is not None:
            g[ic:ii, ic:ii] += comp.b @ comp.predict
        else:
            g[ic:ii, iy:iy + 2] = comp.b
    g[ii:ii + 2, ii:ii + 2] = np.eye(2)
    g[iy:, iy:] = np.eye(2)
    return g


def _plant_offset(rig: RigPlane) -> int:
    """Where the beam's states start in the sampled plant's state (after a reconstruction
    filter's)."""
    f = rig.chain.reconstruction
    return 0 if f is None else 2 * f.state_space()[0].shape[0]


def mode1_row(model: FEModel, rig: RigPlane, load_n: float, n_plant: int) -> np.ndarray:
    """The row of the sampled plant's state giving the modal displacement of mode 1 at
    ``load_n`` (mass-normalised shape of Ke - Fx Kg in the rig's plane, projected with M)."""
    idx = plane_indices(model.n_nodes, rig.plane)
    _, phi = plane_eigen(model.load_stiffness(load_n), model.mass, rig.plane, 1)
    row = np.zeros(n_plant)
    off = _plant_offset(rig)
    row[off:off + len(idx)] = phi[idx, 0] @ model.mass[np.ix_(idx, idx)]
    return row


def gap_loop(rig: RigPlane, load_n: float, point: CompensatorPoint, h: np.ndarray,
             plane_states: Sequence[int], period_s: float, bridge: str = "predict") -> GapLoop:
    """The matrices of ``rig``'s loop at ``load_n`` with the compensator ``point`` of the whole
    beam (its block of the rig's plane is taken), bridging a gap by ``bridge``."""
    plant, c = rig.sampled(load_n)
    io = list(PLANE_CHANNELS[rig.plane])
    part = point.plane(list(plane_states), rig.plane)
    m = closed_loop_matrix(plant, c, part, h[np.ix_(io, io)], period_s, rig.force_gain)
    g = gap_matrix(plant, part, "hold" if bridge == "catch_up" else bridge, rig.force_gain)
    n = plant.ad.shape[0]
    total = m.shape[0]
    catch = None
    if bridge == "catch_up":
        nb = 2 * (plant.whole + 1)
        ic, ii = n + nb, n + nb + part.a.shape[0]
        feed = np.zeros((part.a.shape[0], total))
        feed[:, :n] = part.b @ c
        feed[:, n:n + 2] = part.e                   # the forces the stacks held (the newest entry)
        catch = CatchUp(total, ic, ii, part.a, feed, CATCH_UP_SAMPLES)
    cz = np.zeros((2, total))
    cz[:, :n] = c
    w = np.zeros((total, 2))
    w[:n] = plant.b_now + plant.b_before
    outputs = np.zeros((3, total))
    outputs[0, :n] = mode1_row(rig.model, rig, load_n, n)
    outputs[1, n] = outputs[2, n + 1] = 1.0         # the newest applied forces (supports A, B)
    return GapLoop(m=m, g=g, entry=np.vstack([m, cz]), w=w, outputs=outputs, catch=catch)


# ---------------------------------------------------------------------------------------------
# the growth at one load


class GrowthAnalysis:
    """The outputs' variance through a gap of N samples and the recovery after it, at one load
    (see the module docstring). States are scaled by their stationary RMS: in SI they span ten
    decades, where the Lyapunov solve keeps three digits (``scale``: a neighbouring load's
    ``rms``, near enough, instead of a Lyapunov solve for it)."""

    def __init__(self, loop: GapLoop, scale: np.ndarray | None = None) -> None:
        n = loop.n
        if scale is None or scale.shape != (n,):
            scale = np.sqrt(np.abs(np.diag(_Stein(loop.m).solve(loop.w @ loop.w.T))))
        scale = np.where((scale > 1e-300) & np.isfinite(scale), scale, 1.0)
        self.m = loop.m / scale[:, None] * scale[None, :]
        self.w = loop.w / scale[:, None]
        ww = self.w @ self.w.T
        stein = _Stein(self.m)
        self.sigma = stein.solve(ww)
        # Sigma is singular (states tied to others, e.g. the strain FIR's raw and predicted past
        # strains): the settling bound uses Pi = Sigma + eps Y (Y = M Y M^T + I), for which
        # Pi - M Pi M^T = W W^T + eps I >= 0 too; eps 1e-6 of the states' stationary variance
        pi = stein.solve(ww + BOUND_EPS * np.eye(n))
        self._bound_inverse = sla.solve_triangular(sla.cholesky(pi, lower=True), np.eye(n), lower=True)
        self.rms = scale * np.sqrt(np.abs(np.diag(self.sigma)))
        self.out = loop.outputs * scale[None, :]
        self.k = self.out.shape[0]
        self.variance = np.einsum("ij,jk,ik->i", self.out, self.sigma, self.out)
        self.bound_variance = np.einsum("ij,jk,ik->i", self.out, pi, self.out)
        entry = loop.entry * scale[None, :]
        wa = np.vstack([loop.w, np.zeros((2, 2))])
        start = entry @ self.sigma @ entry.T + wa @ wa.T
        held = np.sqrt(np.abs(np.diag(start)[n:]))
        held[held <= 1e-300] = 1.0
        s_aug = np.concatenate([scale, held])
        self.start = _sym(start / s_aug[:, None] / s_aug[None, :])
        self._s_aug = s_aug
        self.g = loop.g / s_aug[:, None] * s_aug[None, :]
        self.wa = np.vstack([self.w, np.zeros((2, 2))])
        self._out_aug = np.hstack([self.out, np.zeros((self.k, 2))])
        self._gap_var = np.zeros((0, self.k))      # the outputs' variance after j missing samples
        self._gap_rows: np.ndarray | None = None
        self._gap_step: np.ndarray | None = None
        self._gap_noise = np.zeros(self.k)
        self._block: np.ndarray | None = None         # out M^m, m < GAP_BLOCK, [m, output, state]
        self._block_step: np.ndarray | None = None    # M^GAP_BLOCK
        self._powers: list[tuple[np.ndarray, np.ndarray]] = []   # (G^2^b, sum_{i<2^b} G^i W G^iT)
        self._after_n = 0
        self._after_cov = self.start
        self._catch = loop.catch
        self._scale = scale

    def _caught_up(self, cov: np.ndarray, n_gap: int) -> np.ndarray:
        """The covariance of z after the engine's catch-up at the end of a gap (``CatchUp``), in
        the analysis' scaled states; unchanged for a loop without one."""
        if self._catch is None:
            return cov
        j = self._catch.matrix(n_gap) / self._scale[:, None] * self._scale[None, :]
        return _sym(j @ cov @ j.T)

    def bridged(self, g: np.ndarray) -> GrowthAnalysis:
        """The same loop with another gap matrix ``g`` (another bridge, ``gap_matrix``): the
        stationary state and the recovery's matrices are shared, the gap's computed anew."""
        other = object.__new__(GrowthAnalysis)
        other.__dict__.update(self.__dict__)
        other.g = g / self._s_aug[:, None] * self._s_aug[None, :]
        other._gap_var = np.zeros((0, self.k))
        other._gap_rows = other._gap_step = None
        other._gap_noise = np.zeros(self.k)
        other._powers = []
        other._after_n, other._after_cov = 0, self.start
        return other

    def _extend_gap(self, j: int) -> None:
        """The gap's trajectory up to j missing samples: the rows out G^i in blocks of GAP_BLOCK
        (the next block is this one times G^GAP_BLOCK)."""
        while len(self._gap_var) <= j:
            if self._gap_rows is None:
                rows = [self._out_aug]
                for _ in range(GAP_BLOCK - 1):
                    rows.append(rows[-1] @ self.g)
                self._gap_rows = np.concatenate(rows)
                self._gap_step = np.linalg.matrix_power(self.g, GAP_BLOCK)
            else:
                self._gap_rows = self._gap_rows @ self._gap_step
            rows = self._gap_rows
            with np.errstate(over="ignore", invalid="ignore"):
                noise = np.sum((rows @ self.wa) ** 2, axis=1).reshape(GAP_BLOCK, self.k)
                values = np.sum((rows @ self.start) * rows, axis=1).reshape(GAP_BLOCK, self.k)
                cum = np.cumsum(noise, axis=0)
                values += self._gap_noise + np.vstack([np.zeros((1, self.k)), cum[:-1]])
            self._gap_noise = self._gap_noise + cum[-1]
            values[~np.isfinite(values)] = np.inf
            self._gap_var = np.vstack([self._gap_var, values])

    def _after_gap(self, n_gap: int) -> np.ndarray:
        """Covariance of z after ``n_gap`` missing samples (n_gap not less than the last asked
        for): from the last one by binary powers of G."""
        if n_gap < self._after_n:
            raise ValueError("the gaps are analysed in increasing length")
        cov = self._after_cov
        k, b = n_gap - self._after_n, 0
        while (1 << b) <= k:
            if len(self._powers) <= b:
                if b == 0:
                    self._powers.append((self.g, self.wa @ self.wa.T))
                else:
                    p, s = self._powers[b - 1]
                    self._powers.append((p @ p, s + p @ s @ p.T))
            if k >> b & 1:
                p, s = self._powers[b]
                cov = p @ cov @ p.T + s
            b += 1
        cov = _sym(cov)
        self._after_n, self._after_cov = n_gap, cov
        return cov[:-2, :-2]

    def _excess_bound(self, delta: np.ndarray, enough: float) -> float:
        """An alpha >= 0 with delta <= alpha Pi: the least (the largest eigenvalue of
        L^-1 delta L^-T, Pi = L L^T), or, where it already is at most ``enough``, the Frobenius
        norm of that matrix, which is not less."""
        x = _sym(self._bound_inverse @ delta @ self._bound_inverse.T)
        frobenius = float(np.sqrt(np.sum(x * x)))
        if frobenius <= enough:
            return frobenius
        return max(float(np.linalg.eigvalsh(x)[-1]), 0.0)

    def _recovery_peak(self, delta: np.ndarray, floor: np.ndarray) -> np.ndarray:
        """The largest variance of each output any sample of the recovery from the excess
        ``delta`` can have: followed in blocks of GAP_BLOCK until, at m = 64, 128, 256, ..., the
        bound on every later sample is within max(largest so far, ``floor``)."""
        if self._block is None:
            rows = [self.out]
            for _ in range(GAP_BLOCK - 1):
                rows.append(rows[-1] @ self.m)
            self._block = np.concatenate(rows)
            self._block_step = np.linalg.matrix_power(self.m, GAP_BLOCK)
        rows = self._block
        power = self._block_step
        top = np.zeros(self.k)
        m, checkpoint = 0, GAP_BLOCK
        while True:
            with np.errstate(over="ignore", invalid="ignore"):
                v = self.variance + np.sum((rows @ delta) * rows, axis=1).reshape(
                    GAP_BLOCK, self.k).max(axis=0)
            if not np.all(np.isfinite(v)):
                return np.full(self.k, np.inf)
            top = np.maximum(top, v)
            m += GAP_BLOCK
            if m == checkpoint:
                d = _sym(power @ delta @ power.T)
                if not np.all(np.isfinite(d)):
                    return np.full(self.k, np.inf)
                target = np.maximum(top, floor)
                enough = float(np.min((target - self.variance) / self.bound_variance))
                bound = self.variance + self._excess_bound(d, enough) * self.bound_variance
                if np.all(bound <= target):
                    return np.maximum(top, bound)
                if m >= RECOVERY_CAP_SAMPLES:
                    return np.full(self.k, np.inf)
                checkpoint *= 2
                power = power @ power
            rows = rows @ self._block_step

    def growth(self, grid: Sequence[int]) -> np.ndarray:
        """[output, gap of ``grid``]: the largest RMS of each output at any sample of the gap and
        its recovery over its stationary RMS, non-decreasing in the gap's length; past
        GROWTH_CAP the cap."""
        out = np.full((self.k, len(grid)), GROWTH_CAP)
        floor = SETTLED**2 * self.variance
        top = np.zeros(self.k)
        for i, n_gap in enumerate(grid):
            self._extend_gap(n_gap)
            gap_peak = self._gap_var[:n_gap + 1].max(axis=0)
            delta = self._caught_up(self._after_gap(n_gap), n_gap) - self.sigma
            peak = np.maximum(gap_peak, self._recovery_peak(delta, np.maximum(floor, gap_peak)))
            top = np.maximum(top, np.sqrt(peak / self.variance))
            if not np.all(np.isfinite(top)) or top.max() >= GROWTH_CAP:
                out[:, i] = np.minimum(np.where(np.isfinite(top), top, GROWTH_CAP), GROWTH_CAP)
                break
            out[:, i] = top
        return out


class _DelayedPlant:
    """The rig's plane at one load sampled with output delays of a grid (``step`` samples apart):
    the delayed zero-order hold of models.iochain.delayed_zoh, with the partial integrals
    Gamma(t) = int_0^t exp(A s) ds B of every t on the grid from one matrix exponential and a
    recursion, Gamma(t + h) = Gamma(t) + exp(A t) Gamma(h), instead of one exponential a delay."""

    def __init__(self, rig: RigPlane, load_n: float, step: float) -> None:
        self.a, self.b, self.c = rig.continuous(load_n)
        self.period_s = rig.period_s
        self.step = step
        self.ad, self.g_full = _gamma(self.a, self.b, self.period_s)
        self._grid: list[tuple[np.ndarray, np.ndarray]] | None = None
        self._rest: dict[float, np.ndarray] = {}

    def _gamma_at(self, u: float) -> np.ndarray:
        """Gamma(u T), 0 < u < 1."""
        if self._grid is None:
            e_h, g_h = _gamma(self.a, self.b, self.step * self.period_s)
            e, g = np.eye(self.a.shape[0]), np.zeros_like(self.b)
            self._grid = [(e, g)]
            for _ in range(int(round(1.0 / self.step))):
                e, g = e @ e_h, g + e @ g_h
                self._grid.append((e, g))
        j = min(int(math.floor(u / self.step + 1e-9)), len(self._grid) - 1)
        rest = round(u - j * self.step, 12)
        e, g = self._grid[j]
        if rest <= 1e-12:
            return g
        if rest not in self._rest:
            self._rest[rest] = _gamma(self.a, self.b, rest * self.period_s)[1]
        return g + e @ self._rest[rest]

    def sampled(self, delay_samples: float) -> tuple[DelayedZOH, np.ndarray]:
        whole = int(math.floor(delay_samples))
        fraction = float(delay_samples - whole)
        if fraction == 0.0:
            b_now, b_before = self.g_full, np.zeros_like(self.g_full)
        else:
            b_now = self._gamma_at(1.0 - fraction)
            b_before = self.g_full - b_now
        zoh = DelayedZOH(ad=self.ad, b_now=b_now, b_before=b_before, b_direct=np.zeros((self.a.shape[0], 0)),
                         whole=whole, fraction=fraction)
        return zoh, self.c


def _sym(x: np.ndarray) -> np.ndarray:
    return 0.5 * (x + x.T)


class _Stein:
    """X = M X M^T + Q for several Q with one Schur decomposition: scipy's
    solve_discrete_lyapunov (the bilinear transform to a continuous Lyapunov equation, solved by
    Bartels-Stewart with LAPACK's trsyl) with the decomposition kept."""

    def __init__(self, m: np.ndarray) -> None:
        eye = np.eye(m.shape[0])
        self._left = np.linalg.inv(m + eye)
        self._right = np.linalg.inv(m.T + eye)
        b = (m.T - eye) @ self._right
        self._t, self._u = sla.schur(b.T, output="real")
        self._trsyl = sla.get_lapack_funcs("trsyl", (self._t,))

    def solve(self, q: np.ndarray) -> np.ndarray:
        c = 2.0 * self._left @ q @ self._right
        f = self._u.T @ -c @ self._u
        y, scale, info = self._trsyl(self._t, self._t, f, tranb="T")
        if info < 0:
            raise ValueError(f"trsyl: argument {-info} is wrong")
        return _sym(self._u @ (y / scale) @ self._u.T)


# ---------------------------------------------------------------------------------------------
# the table


Plan = Sequence[tuple[float, Any, CompensatorPoint]]
BuildProgress = Callable[[int, int, str], None]


def steps(plan: Plan) -> int:
    """Progress steps of ``analyse`` for a check plan: one per load for the gap, one for the delay."""
    return 2 * len(plan)


def _places(plan: Plan, loads: np.ndarray) -> tuple[list[int], list[tuple[int, int, int]]]:
    """Where the check loads of ``plan`` sit on the grid ``loads``: the plan entry of each grid
    load (its own matrices, as the settled schedule has them there), and every other entry as
    (entry, j, k): between grid loads j and k = j + 1, or at grid load j = k (paper mode's
    matrices of a neighbouring grid point there)."""
    own: list[int | None] = [None] * len(loads)
    others: list[tuple[int, int, int]] = []
    for e, (load, gain_load, _) in enumerate(plan):
        i = int(np.searchsorted(loads, load))
        at = i < len(loads) and math.isclose(load, loads[i], rel_tol=0.0, abs_tol=1e-9)
        if at and gain_load is None and own[i] is None:
            own[i] = e
        elif at:
            others.append((e, i, i))
        else:
            j = min(max(i - 1, 0), len(loads) - 1)
            others.append((e, j, min(i, len(loads) - 1)))
    missing = [float(loads[i]) for i, e in enumerate(own) if e is None]
    if missing:
        raise ValueError(f"the check plan has no entry for the grid loads {missing} N")
    others.sort(key=lambda x: -plan[x[0]][0])
    return [int(e) for e in own], others


def _fold(values: list, sources: list[float], j: int, k: int, value, load: float) -> None:
    """A check load between grid loads j and k (or at j = k) whose limit ``value`` is less than
    the engine's there, the lesser of the two ends: that end (the upper on a tie) takes it, so
    that the lesser end of every grid interval is at most the limit of every check load in it."""
    end = k if values[k] <= values[j] else j
    values[end], sources[end] = value, load


def _stable(matrix: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(matrix))) and float(np.max(np.abs(np.linalg.eigvals(matrix)))) < 1.0


def load_growth(rigs: Sequence[RigPlane], load: float, point: CompensatorPoint, table, grid: Sequence[int],
                scales: dict | None = None) -> np.ndarray:
    """[bridge, output, gap of ``grid``] at ``load``: the largest growth over the ``rigs`` whose
    loop is stable there (the first, the nominal rig, must be); ``scales`` keeps each rig's
    stationary RMS for the next load's analysis."""
    comp = table.compensator
    out = np.zeros((len(BRIDGES), len(OUTPUTS), len(grid)))
    scales = {} if scales is None else scales
    for r, rig in enumerate(rigs):
        states = comp.plane_states[rig.plane]
        loop = gap_loop(rig, load, point, comp.h, states, comp.period_s, BRIDGES[0])
        if not _stable(loop.m):
            if r == 0:
                raise ValueError(f"the nominal loop is unstable at {load:g} N: no ride-through")
            continue
        first = GrowthAnalysis(loop, scales.get(r))
        scales[r] = first.rms
        for b, bridge in enumerate(BRIDGES):
            analysis = first if b == 0 else first.bridged(gap_matrix(
                rig.sampled(load)[0], point.plane(list(states), rig.plane), bridge, rig.force_gain))
            g = analysis.growth(grid)
            out[b, 0] = np.maximum(out[b, 0], g[0])
            out[b, 1] = np.maximum(out[b, 1], g[1:].max(axis=0))
    return out


def analyse(rigs: Sequence[RigPlane], table, plan: Plan, progress: BuildProgress | None = None,
            done: int = 0, total: int | None = None, *, rig_names: Sequence[str] | None = None,
            gap_cap: int | None = None, delay_step: float = DELAY_STEP_SAMPLES,
            delay_cap: float = DELAY_CAP_SAMPLES) -> RideThrough:
    """The ride-through analysis of ``table``'s loop on ``rigs`` (the nominal rig first, then
    e.g. the robust check's worst) at every load of its closed-loop check ``plan`` ((load, gain
    load, matrices), as ``gains.build.check_plan`` gives); see the module docstring.
    ``gap_cap``: the gap grid's end (default ``gap_horizon_samples`` of the rig's rate)."""
    started = time.perf_counter()
    total = total if total is not None else done + steps(plan)
    nominal = rigs[0]
    comp = table.compensator
    states = comp.plane_states[nominal.plane]
    loads = np.asarray(table.loads_n, dtype=float)
    grid = gap_grid(gap_horizon_samples(nominal.sample_rate_hz) if gap_cap is None else int(gap_cap))
    step = done

    def tick(label: str) -> None:
        nonlocal step
        step += 1
        if progress:
            progress(step, total, label)

    order = sorted(range(len(plan)), key=lambda e: -plan[e][0])
    growth = np.zeros((len(BRIDGES), len(OUTPUTS), len(plan), len(grid)))
    scales: dict = {}
    for e in order:
        load, _, point = plan[e]
        growth[:, :, e] = load_growth(rigs, load, point, table, grid, scales)
        tick(f"ride-through gap {load:7.1f} N")
    # the delay: on the nominal rig, every grid load walked, the other check loads at their limit
    own, others = _places(plan, loads)
    top_down = sorted(range(len(loads)), key=lambda i: -loads[i])
    count = int(round(delay_cap / delay_step))
    dgrid = [round(k * delay_step, 10) for k in range(count + 1)]
    plants: dict[int, _DelayedPlant] = {}

    def stable(e: int, k: int) -> bool:
        load, _, point = plan[e]
        if e not in plants:
            plants[e] = _DelayedPlant(nominal, load, delay_step)
        plant, c = plants[e].sampled(round(nominal.chain.delay_samples + dgrid[k], 10))
        io = list(PLANE_CHANNELS[nominal.plane])
        matrix = closed_loop_matrix(plant, c, point.plane(list(states), nominal.plane),
                                    comp.h[np.ix_(io, io)], comp.period_s, nominal.force_gain)
        return float(np.max(np.abs(np.linalg.eigvals(matrix)))) < 1.0

    def walk(e: int, top: int) -> int:
        """The grid delays up to ``top`` walked up from the nominal (stable by the check): the
        last before the first unstable one. Stability need not fall with the delay (a pole can
        be unstable in a window of delays only), so a bisection could step over a window."""
        for k in range(1, top + 1):
            if not stable(e, k):
                plants.pop(e, None)
                return k - 1
        plants.pop(e, None)
        return top

    delays = [0] * len(loads)          # grid steps
    sources = [float(x) for x in loads]
    for i in top_down:
        delays[i] = walk(own[i], count)
        tick(f"ride-through delay {loads[i]:7.1f} N")
    for e, j, k in others:
        bound = min(delays[j], delays[k])
        if bound > 0 and not stable(e, bound):
            _fold(delays, sources, j, k, walk(e, bound - 1), plan[e][0])
        plants.pop(e, None)
        tick(f"ride-through delay {plan[e][0]:7.1f} N")
    design_delay = float(table.design.io.delay_samples)
    names = tuple(rig_names) if rig_names is not None else ("the nominal rig",) + tuple(
        f"rig {i}" for i in range(1, len(rigs)))
    return RideThrough(confidence_sigma=CONFIDENCE_SIGMA, gap_grid_samples=grid,
                       loads_n=tuple(float(p[0]) for p in plan), rigs=names, growth=growth,
                       max_extra_delay_samples_per_load=tuple(dgrid[k] for k in delays),
                       answer_budgets_periods=tuple(answer_budget(design_delay, dgrid[k]) for k in delays),
                       delay_step_samples=delay_step, delay_cap_samples=delay_cap,
                       elapsed_s=round(time.perf_counter() - started, 2))
