"""How far the closed loop rides through missing samples and late answers: computed when a
table is built and stored in it (``ride_through:``), so that the real-time engine bridges
missing samples by the compensator's prediction and faults only past limits that come from
analysis.

What the engine does, and what is analysed here: the nominal rig (the model's FE plane with the
I/O chain the design declares, ``gains.build.nominal_rig``) at every load of the table's
closed-loop check (``gains.build.check_plan``: grid points, midpoints, paper mode's band ends),
in the loop of gains/closedloop.py (state z = [plant x, applied forces of the last whole+1
samples, compensator x_c, integral xi]).

Gap. The DAQ's samples stop for N sample periods (a stall, lost frames). Nothing is answered,
so the stacks hold the voltages of the last answer: the plant runs on with the force u_held of
the last sample's answer. When the next sample arrives the engine first runs N prediction steps
of the compensator, y_hat = P x_c (``Compensator.predict``; a table without one: the strains
last measured), xi unchanged, x_c <- A x_c + B y_hat + E u_held, then the normal step on the new
sample. The plant does not see the compensator while the voltages are held, so running those
steps late or on time is the same loop: per missing sample

    x  <- Ad x + (B_now + B_before) u_held        (the delayed ZOH, every force in it held)
    x_c <- (A + B P) x_c + E u_held ;  xi <- xi

and then the normal loop again (``gap_matrix``).

Survival. The loop runs stationary, driven by a force disturbance at the stacks, white per
sample and entering the plant as the LQG design's force noise does (held over the sample:
B_now + B_before per unit force; only ratios matter, so its size cancels). A gap starts after a
normal sample; the state covariance is propagated exactly through the N missing samples (the
disturbance still acting) and then through the normal loop until it has settled. The gap is
survived when the RMS of the beam's lateral deflection at every sampling instant of the gap and
of the recovery stays at most ``growth_limit`` (2: it at most doubles) times its stationary
RMS. The deflection is the modal displacement of mode 1 (the lowest mode of the plane's FE
model at that load, mass-normalised, projected with the mass matrix): the buckling mode, which
the loop holds and which diverges when it is open beyond Fx,cr. The strains are not used: the
disturbance excites modes 3 and 5, which weigh 8 to 90 times as much in the strains as in the
deflection and which the loop barely changes, so their share would hide mode 1's growth.

How: the stationary covariance by a Lyapunov solve (states scaled by their stationary RMS); the
gap's trajectory, the same for every N, by rows out G^j; the covariance after N missing samples
by binary powers of G (and their noise sums), from the longest gap's computed so far; the
recovery sample by sample while a bound says whether a later sample can still pass the limit:
with Delta_m the covariance's excess over the
stationary Sigma after m normal samples (Delta_m+1 = M Delta_m M^T), once Delta_m <= alpha Pi
(Pi = Sigma + 1e-6 Y, Y = M Y M^T + I, so that Pi >= M Pi M^T) no later sample's variance
exceeds the stationary one plus alpha times out Pi out^T. A recovery not bounded within the
limit after RECOVERY_CAP_SAMPLES counts as lost. Settling is thus exact, not a guess at a time
constant (the integral's poles take 10^4 to 10^5 samples; what they carry is small).

Per load. The limits are found for every load of the table's grid (``table.loads_n``) and
stored one value per grid load (``max_gap_samples_per_load``, ``gap_limits_samples``,
``max_extra_delay_samples_per_load``, ``answer_budgets_periods``): the engine applies per grid
interval the lesser of its two ends. The loop between grid points (the check plan's midpoints,
and in paper mode the band ends where a grid point's matrices act away from it) is covered by
testing each such check load at its interval's limits: where it fails them, its own limit
(found below them) replaces the lesser end's, so that the lesser end of every interval is at
most the limit of every check load in it. The scalars (``max_gap_samples``, ``gap_load_N``,
``max_extra_delay_samples``, ``delay_load_N`` and the limits from them) are the worst over all
of these: the least value and the check load it was found at.

Gap search. Capped at a practical horizon, ``GAP_HORIZON_S`` (0.1 s: 600 samples at 6000 Hz,
250 at 2500 Hz; a DAQ silent that long has stopped, it is not a gap to ride through): a load
that rides through that long reports the cap (``RideThrough.gap_capped``, ``gap_cap_samples``).
The grid loads are walked from the top down, each search started from the answer of the load
above (the gap grows as the load falls): the gap of that length is tested at this load and the
search gallops up (or down, where it is lost here: the gap need not grow at every step, e.g.
12 samples at 3400 N and 13 at 3500 N in the shipped LQG) and bisects, testing about 2 log2 of
the distance; the answer is always a gap tested and survived at that load. Survival need not fall
with the gap's length near the limit either (the recovery's peak follows the phase of the
loop's oscillation at the gap's end: at 0 N in the shipped LQG every other gap from 522 to 530
samples is lost, 531 to 546 survived, then 548 and 553 among lost ones), so the answer is an
edge of that band (survived, the next gap lost), and gaps somewhat shorter may be lost: in the
shipped tables the first gap lost is at least 92 % of the answer at every check load (walked
gap by gap), so the engine's limit, half the answer, is far below it. ``gap_limits_samples`` =
floor(max_gap_samples_per_load / margin), margin 2: the run of missing samples (or late
answers) the engine bridges before it faults.

Delay. The largest extra output delay, on a grid of ``DELAY_STEP_SAMPLES`` up to
``DELAY_CAP_SAMPLES``, on top of the design's own (``design.io.delay_samples``), with which the
loop is stable (spectral radius < 1) at that load and at every delay of the grid below it.
Stability need not fall with the delay (a pole can be unstable in a window of delays only), so
every grid load walks the grid up from the nominal, a loop's poles per grid delay (about 3 to 5
ms); the other check loads are tested at their interval's limit (and walked below it only where
unstable there). The engine's answer budget counts from the sample's arrival and the design
already assumes its own delay, an answer within it being on time: ``answer_budgets_periods`` =
design delay + max_extra_delay_samples_per_load / margin (``answer_budget_periods`` likewise at
the worst load). An answer sent later than that counts as late, and a run of more than the gap
limit of late answers faults.

Cost (``RideThrough.elapsed_s``): about 8 s for either shipped table on a shared 2-core machine
(the search to 2000 samples at every grid load took 70 to 80 s): the gap about 40 ms a check
load (the Lyapunov solves of its loop, a neighbouring load's stationary RMS as its scale, and
about 5 survival tests a grid load), the delay half of it, a loop's poles (3 to 5 ms) per grid
delay walked, 20 at every grid load that holds the cap.
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

GROWTH_LIMIT = 2.0          # the deflection's RMS may at most double during a gap and its recovery
MARGIN = 2.0                # the engine's limits are the analysis' divided by this
GAP_HORIZON_S = 0.1         # the gap search stops at this long a gap: the DAQ has stopped, not paused
DELAY_STEP_SAMPLES = 0.05   # grid of the extra output delay
DELAY_CAP_SAMPLES = 1.0     # the delay search stops here: a whole sample late, the next one is due
SETTLED = 0.01              # the recovery has settled when its excess is within 1 % of stationary
BOUND_EPS = 1e-6            # regularisation of the settling bound (see GapAnalysis)
GAP_BLOCK = 64              # samples of the gap's trajectory and the recovery computed at once
RECOVERY_CAP_SAMPLES = 1 << 20   # a recovery not bounded within the limit by then counts as lost


@dataclass(frozen=True)
class RideThrough:
    """The ride-through limits of a table's loop (see the module docstring); stored in the
    table file under ``ride_through``. The scalars are the worst over the table's loads; the
    ``*_per_load`` and plural fields hold one value per grid load (``table.loads_n``), the
    engine's limits per grid interval being the lesser of its two ends (None: a table written
    before them, whose scalars are all it has; its answer budget did not count the design's
    own delay)."""

    growth_limit: float
    margin: float
    max_gap_samples: int
    gap_limit_samples: int
    gap_load_n: float                   # the worst load of the gap analysis
    gap_cap_samples: int
    max_extra_delay_samples: float
    answer_budget_periods: float
    delay_load_n: float | None          # the worst load of the delay analysis (None: the cap held)
    delay_step_samples: float
    delay_cap_samples: float
    elapsed_s: float
    max_gap_samples_per_load: tuple[int, ...] | None = None
    gap_limits_samples: tuple[int, ...] | None = None
    max_extra_delay_samples_per_load: tuple[float, ...] | None = None
    answer_budgets_periods: tuple[float, ...] | None = None

    FIELDS = ("growth_limit", "margin", "max_gap_samples", "gap_limit_samples", "gap_load_N",
              "gap_cap_samples", "max_extra_delay_samples", "answer_budget_periods", "delay_load_N",
              "delay_step_samples", "delay_cap_samples", "max_gap_samples_per_load", "gap_limits_samples",
              "max_extra_delay_samples_per_load", "answer_budgets_periods", "elapsed_s")
    PER_LOAD = ("max_gap_samples_per_load", "gap_limits_samples", "max_extra_delay_samples_per_load",
                "answer_budgets_periods")

    def __post_init__(self) -> None:
        for name, kind in zip(self.PER_LOAD, (int, int, float, float), strict=True):
            values = getattr(self, name)
            if values is not None:
                object.__setattr__(self, name, tuple(kind(v) for v in values))

    @property
    def per_load(self) -> bool:
        """The limits are given per grid load (a table analysed since they are)."""
        return self.max_gap_samples_per_load is not None

    @property
    def gap_capped(self) -> bool:
        """No gap up to the search's cap was lost."""
        return self.max_gap_samples >= self.gap_cap_samples

    @property
    def delay_capped(self) -> bool:
        """The loop was stable with every extra delay up to the search's cap."""
        return self.delay_load_n is None

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "growth_limit": float(self.growth_limit), "margin": float(self.margin),
            "max_gap_samples": int(self.max_gap_samples), "gap_limit_samples": int(self.gap_limit_samples),
            "gap_load_N": float(self.gap_load_n), "gap_cap_samples": int(self.gap_cap_samples),
            "max_extra_delay_samples": float(self.max_extra_delay_samples),
            "answer_budget_periods": float(self.answer_budget_periods),
            "delay_load_N": None if self.delay_load_n is None else float(self.delay_load_n),
            "delay_step_samples": float(self.delay_step_samples),
            "delay_cap_samples": float(self.delay_cap_samples)}
        for name in self.PER_LOAD:
            values = getattr(self, name)
            if values is not None:
                d[name] = list(values)
        d["elapsed_s"] = float(self.elapsed_s)
        return d

    def describe(self) -> str:
        gap = (f"{self.max_gap_samples} samples or more (the search's cap)" if self.gap_capped
               else f"{self.max_gap_samples} samples at {self.gap_load_n:g} N")
        delay = (f"{self.max_extra_delay_samples:g} samples or more (the search's cap)" if self.delay_capped
                 else f"{self.max_extra_delay_samples:g} samples at {self.delay_load_n:g} N")
        text = (f"ride-through: longest gap survived {gap} (deflection RMS at most x{self.growth_limit:g}), "
                f"limit {self.gap_limit_samples}; extra output delay tolerated {delay}, answer budget "
                f"{self.answer_budget_periods:g} periods (margin {self.margin:g})")
        if self.per_load:
            text += (f"; per grid load gap limits {min(self.gap_limits_samples)} to "
                     f"{max(self.gap_limits_samples)} samples, answer budgets "
                     f"{min(self.answer_budgets_periods):g} to {max(self.answer_budgets_periods):g} periods")
        return text + f"; {self.elapsed_s:.1f} s"


def limits(max_gap_samples: int, max_extra_delay_samples: float, margin: float = MARGIN,
           design_delay_samples: float = 0.0) -> tuple[int, float]:
    """(gap_limit_samples, answer_budget_periods), the engine's limits: floor(max_gap_samples /
    margin), and the design's own output delay (an answer within it is what the design assumes)
    plus max_extra_delay_samples / margin."""
    return (int(math.floor(max_gap_samples / margin)),
            float(design_delay_samples) + max_extra_delay_samples / margin)


# ---------------------------------------------------------------------------------------------
# the loop's matrices


@dataclass(frozen=True)
class GapLoop:
    """The matrices of one plane's loop at one load (closed-loop state z as in gains/closedloop.py):

    normal: z <- M z + W w;  a missing sample: [z; y_held] <- G [z; y_held] + [W; 0] w, entered
    from the last normal sample by [z; y_held] = [M; Cz] z + [W; 0] w (y_held: that sample's
    strains, which a table without a prediction feeds its compensator); ``deflection`` the row
    of z giving mode 1's modal displacement."""

    m: np.ndarray
    g: np.ndarray
    entry: np.ndarray
    w: np.ndarray
    deflection: np.ndarray

    @property
    def n(self) -> int:
        return self.m.shape[0]


def gap_matrix(plant: DelayedZOH, comp: CompensatorPoint) -> np.ndarray:
    """The loop during a missing sample, on [z; y_held] (see the module docstring): the plant
    runs on the force of the last answer (the newest entry of the force buffer), the compensator
    predicts, the integral and the held strains stay. ``comp`` of one plane."""
    n = plant.ad.shape[0]
    whole = plant.whole
    nb = 2 * (whole + 1)
    nc = comp.a.shape[0]
    total = n + nb + nc + 2
    ib, ic, ii, iy = n, n + nb, n + nb + nc, n + nb + nc + 2
    g = np.zeros((total + 2, total + 2))
    g[:n, :n] = plant.ad

    def force(k_back: int, matrix: np.ndarray) -> None:
        """x_k+1 += matrix u_k-k_back, u_k = the held force (buffer entry u_k-1)."""
        col = ib + 2 * max(k_back - 1, 0)
        g[:n, col:col + 2] += matrix

    force(whole, plant.b_now)
    if plant.fraction > 0.0:
        force(whole + 1, plant.b_before)
    # buffer [u_k-1, ..., u_k-whole-1] <- [u_k = u_k-1, u_k-1, ..., u_k-whole]
    g[ib:ib + 2, ib:ib + 2] = np.eye(2)
    for j in range(1, whole + 1):
        g[ib + 2 * j:ib + 2 * j + 2, ib + 2 * (j - 1):ib + 2 * j] = np.eye(2)
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


def gap_loop(model: FEModel, rig: RigPlane, load_n: float, point: CompensatorPoint, h: np.ndarray,
             plane_states: Sequence[int], period_s: float) -> GapLoop:
    """The matrices of the nominal loop at ``load_n`` with the compensator ``point`` of the
    whole beam (its block of the rig's plane is taken)."""
    plant, c = rig.sampled(load_n)
    io = list(PLANE_CHANNELS[rig.plane])
    part = point.plane(list(plane_states), rig.plane)
    m = closed_loop_matrix(plant, c, part, h[np.ix_(io, io)], period_s)
    g = gap_matrix(plant, part)
    n = plant.ad.shape[0]
    total = m.shape[0]
    cz = np.zeros((2, total))
    cz[:, :n] = c
    w = np.zeros((total, 2))
    w[:n] = plant.b_now + plant.b_before
    deflection = np.zeros(total)
    deflection[:n] = mode1_row(model, rig, load_n, n)
    return GapLoop(m=m, g=g, entry=np.vstack([m, cz]), w=w, deflection=deflection)


# ---------------------------------------------------------------------------------------------
# the gap at one load


class GapAnalysis:
    """The deflection's variance through a gap of N samples and the recovery after it, at one
    load (see the module docstring). States are scaled by their stationary RMS: in SI they span
    ten decades, where the Lyapunov solve keeps three digits (``scale``: a neighbouring load's
    ``rms``, near enough, instead of a Lyapunov solve for it)."""

    def __init__(self, loop: GapLoop, growth_limit: float = GROWTH_LIMIT,
                 scale: np.ndarray | None = None) -> None:
        self.growth_limit = growth_limit
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
        self._bound_factor = sla.cholesky(pi, lower=True)
        # the states' stationary RMS: a neighbouring load's analysis may take it as its scale
        # (``scale``), which saves a Lyapunov solve and serves as well
        self.rms = scale * np.sqrt(np.abs(np.diag(self.sigma)))
        self.out = loop.deflection * scale
        self.variance = float(self.out @ self.sigma @ self.out)
        self.bound_variance = float(self.out @ pi @ self.out)
        self.limit = growth_limit**2 * self.variance
        # [z; y_held] at the gap's first missing sample: after the last normal step
        entry = loop.entry * scale[None, :]
        wa = np.vstack([loop.w, np.zeros((2, 2))])
        start = entry @ self.sigma @ entry.T + wa @ wa.T
        held = np.sqrt(np.abs(np.diag(start)[n:]))
        held[held <= 1e-300] = 1.0
        s_aug = np.concatenate([scale, held])
        self.start = _sym(start / s_aug[:, None] / s_aug[None, :])
        self.g = loop.g / s_aug[:, None] * s_aug[None, :]
        self.wa = np.vstack([self.w, np.zeros((2, 2))])
        self._gap_var = np.zeros(0)        # the deflection's variance after j missing samples
        self._gap_top = np.zeros(0)        # and its largest up to j
        self._gap_block: np.ndarray | None = None
        self._gap_step: np.ndarray | None = None
        self._gap_noise = 0.0
        self._block: np.ndarray | None = None         # out M^m, m < GAP_BLOCK
        self._block_step: np.ndarray | None = None    # M^GAP_BLOCK
        self._powers: list[tuple[np.ndarray, np.ndarray]] = []   # (G^2^b, sum_{i<2^b} G^i W G^iT)
        self._tested: dict[int, bool] = {}     # survives(N) of the gaps tested
        self._after: dict[int, np.ndarray] = {}   # covariance of [z; y_held] after N missing samples

    # -- the gap: one trajectory for every N -------------------------------------------------
    def _extend_gap(self, j: int) -> None:
        """The gap's trajectory up to j missing samples: the rows out G^i in blocks of
        GAP_BLOCK (the next block is this one times G^GAP_BLOCK)."""
        while len(self._gap_var) <= j:
            if self._gap_block is None:
                rows = [np.concatenate([self.out, np.zeros(2)])]
                for _ in range(GAP_BLOCK - 1):
                    rows.append(rows[-1] @ self.g)
                self._gap_block = np.array(rows)
                self._gap_step = np.linalg.matrix_power(self.g, GAP_BLOCK)
            else:
                self._gap_block = self._gap_block @ self._gap_step
            rows = self._gap_block
            with np.errstate(over="ignore", invalid="ignore"):
                noise = np.cumsum(np.sum((rows @ self.wa) ** 2, axis=1))
                values = np.sum((rows @ self.start) * rows, axis=1)
                values += self._gap_noise + np.concatenate([[0.0], noise[:-1]])
            self._gap_noise += noise[-1]
            values[~np.isfinite(values)] = np.inf
            self._gap_var = np.concatenate([self._gap_var, values])
        self._gap_top = np.maximum.accumulate(self._gap_var)

    def gap_variance(self, j: int) -> float:
        """The deflection's variance after j missing samples (0: at the first of them)."""
        self._extend_gap(j)
        return float(self._gap_var[j])

    def gap_peak(self, n_gap: int) -> float:
        """The deflection's largest variance during a gap of ``n_gap`` samples."""
        self._extend_gap(n_gap)
        return float(self._gap_top[n_gap])

    def first_lost_in_gap(self, cap: int) -> int | None:
        """The least j <= cap after which many missing samples the deflection's RMS is past the
        limit already during the gap, or None."""
        j = GAP_BLOCK
        while True:
            self._extend_gap(min(j, cap))
            lost = np.flatnonzero(self._gap_var[:cap + 1] > self.limit)
            if lost.size:
                return int(lost[0])
            if j >= cap:
                return None
            j *= 2

    def after_gap(self, n_gap: int) -> np.ndarray:
        """Covariance of z after ``n_gap`` missing samples: from the longest gap's covariance
        computed so far that is not longer (or the gap's start), by binary powers of G."""
        base = max((n for n in self._after if n <= n_gap), default=0)
        cov = self._after[base] if base else self.start
        k, b = n_gap - base, 0
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
        if n_gap:
            self._after[n_gap] = cov
        return cov[:-2, :-2]

    # -- the recovery ------------------------------------------------------------------------
    def _excess_bound(self, delta: np.ndarray) -> float:
        """The least alpha >= 0 with delta <= alpha Pi."""
        lf = self._bound_factor
        x = sla.solve_triangular(lf, delta, lower=True)
        x = sla.solve_triangular(lf, x.T, lower=True)
        return max(float(np.linalg.eigvalsh(_sym(x))[-1]), 0.0)

    def recovery(self, delta: np.ndarray, done: Callable[[float, float], bool],
                 max_samples: int = RECOVERY_CAP_SAMPLES) -> tuple[np.ndarray, float]:
        """The deflection's variance m = 0, 1, ... samples into the recovery from the excess
        ``delta`` over stationary, sample by sample (in blocks of GAP_BLOCK) until, at m = 64,
        128, 256, ..., ``done(largest so far, bound)``, ``bound`` the largest variance any sample
        from m on can have (or the cap). (variances, bound)."""
        if self._block is None:
            rows = [self.out]
            for _ in range(GAP_BLOCK - 1):
                rows.append(rows[-1] @ self.m)
            self._block = np.array(rows)
            self._block_step = np.linalg.matrix_power(self.m, GAP_BLOCK)
        rows = self._block
        power = self._block_step                    # M^m at the next checkpoint m
        values: list[np.ndarray] = []
        m, checkpoint = 0, GAP_BLOCK
        while True:
            values.append(self.variance + np.sum((rows @ delta) * rows, axis=1))
            m += GAP_BLOCK
            if m == checkpoint:
                d = _sym(power @ delta @ power.T)
                if not np.all(np.isfinite(d)):
                    return np.concatenate(values), math.inf
                bound = self.variance + self._excess_bound(d) * self.bound_variance
                top = float(max(v.max() for v in values))
                if done(top, bound) or m >= max_samples:
                    return np.concatenate(values), bound
                checkpoint *= 2
                power = power @ power
            rows = rows @ self._block_step

    def survives(self, n_gap: int) -> bool:
        """The deflection's RMS stays within growth_limit x stationary at every sample of a gap
        of ``n_gap`` samples and of the whole recovery after it."""
        if n_gap <= 0:
            return True
        if n_gap not in self._tested:
            self._tested[n_gap] = self._survives(n_gap)
        return self._tested[n_gap]

    def _survives(self, n_gap: int) -> bool:
        if self.gap_peak(n_gap) > self.limit:
            return False
        delta = self.after_gap(n_gap) - self.sigma
        if not np.all(np.isfinite(delta)):
            return False
        values, bound = self.recovery(delta, lambda top, bound: top > self.limit or bound <= self.limit)
        return bool(values.max() <= self.limit and bound <= self.limit)

    def ratios(self, n_gap: int) -> tuple[np.ndarray, float]:
        """The deflection's RMS over its stationary RMS at every sample from the gap's first
        missing sample, followed until no later sample can exceed the largest so far or has
        settled within SETTLED of stationary, and the most that any later sample can have."""
        self._extend_gap(n_gap)
        gap = self._gap_var[:n_gap + 1].copy()
        delta = self.after_gap(n_gap) - self.sigma
        floor = max(float(gap.max()), (1.0 + SETTLED) ** 2 * self.variance)
        values, bound = self.recovery(delta, lambda top, bound: bound <= max(top, floor))
        ratio = np.sqrt(np.concatenate([gap, values[1:]]) / self.variance)
        return ratio, math.sqrt(bound / self.variance)

    def max_gap(self, cap: int, below: int | None = None, start: int | None = None) -> int:
        """The longest gap survived, at most ``cap``: a gap N survived with N + 1 lost (or the
        cap), by doubling and bisection, or with ``start`` (a guess, e.g. a neighbouring load's
        answer) by galloping from it (up while survived: start + 1, + 2, + 4, ...; down while
        lost) and bisection, which costs about 2 log2 of the distance from the guess.

        Survival need not fall with the gap's length near the limit (the recovery's peak
        follows the phase of the loop's oscillation at the gap's end; at 0 N in the shipped LQG
        gaps of 522 to 530 samples are lost every other one, 531 to 546 survived, 548 and 553
        survived among lost ones): the answer is then one edge of that band, a gap tested and
        survived with the next one lost, as is every gap tested below it.

        With ``below``: only whether it is less than that matters; if the gap of ``below``
        samples is survived, ``below`` is returned."""
        lost = self.first_lost_in_gap(cap if below is None else below)
        hi = cap + 1 if lost is None else lost          # lost (or beyond the cap)
        if below is not None:
            if below < hi and self.survives(below):
                return below
            hi = min(hi, below)
            lo = 0
        elif start is not None:
            lo, hi = self._gallop(min(max(int(start), 0), hi - 1), hi)
        else:
            lo, n = 0, 1
            while n < hi and self.survives(n):
                lo, n = n, 2 * n
            hi = min(hi, n)
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if self.survives(mid):
                lo = mid
            else:
                hi = mid
        return min(lo, cap)

    def _gallop(self, start: int, hi: int) -> tuple[int, int]:
        """(lo, hi): survived (or 0) and lost (or beyond the cap), found from ``start`` < hi by
        growing steps, for the bisection between them."""
        if self.survives(start):
            lo, step = start, 1
            while lo + 1 < hi:
                n = min(lo + step, hi - 1)
                if not self.survives(n):
                    return lo, n
                lo, step = n, 2 * step
            return lo, hi
        hi, step = start, 1
        while hi > 1:
            n = max(hi - step, 0)
            if n == 0 or self.survives(n):
                return n, hi
            hi, step = n, 2 * step
        return 0, hi


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


def gap_horizon_samples(sample_rate_hz: float) -> int:
    """The gap search's cap: GAP_HORIZON_S of samples (600 at 6000 Hz, 250 at 2500 Hz)."""
    return max(int(round(GAP_HORIZON_S * sample_rate_hz)), 1)


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


def _worst(values: list, sources: list[float]) -> tuple[Any, float]:
    """The least of ``values`` and the load it was found at (the highest of equal ones)."""
    least = min(values)
    return least, max(src for v, src in zip(values, sources, strict=True) if v == least)


def analyse(model: FEModel, rig: RigPlane, table, plan: Plan, progress: BuildProgress | None = None,
            done: int = 0, total: int | None = None, *, growth_limit: float = GROWTH_LIMIT,
            margin: float = MARGIN, gap_cap: int | None = None,
            delay_step: float = DELAY_STEP_SAMPLES, delay_cap: float = DELAY_CAP_SAMPLES) -> RideThrough:
    """The ride-through limits of ``table``'s loop on ``rig`` (the nominal rig) per load of its
    grid, covering every load of its closed-loop check ``plan`` ((load, gain load, matrices), as
    ``gains.build.check_plan`` gives); see the module docstring. ``gap_cap``: the gap search's
    cap (default ``gap_horizon_samples`` of the rig's rate)."""
    started = time.perf_counter()
    total = total if total is not None else done + steps(plan)
    comp = table.compensator
    states = comp.plane_states[rig.plane]
    loads = np.asarray(table.loads_n, dtype=float)
    own, others = _places(plan, loads)
    top_down = sorted(range(len(loads)), key=lambda i: -loads[i])
    cap = gap_horizon_samples(rig.sample_rate_hz) if gap_cap is None else int(gap_cap)
    step = done

    def tick(label: str) -> None:
        nonlocal step
        step += 1
        if progress:
            progress(step, total, label)

    scales: dict[int, np.ndarray] = {}      # the states' stationary RMS at the grid loads

    def gap_analysis(e: int, scale: np.ndarray | None) -> GapAnalysis:
        load, _, point = plan[e]
        return GapAnalysis(gap_loop(model, rig, load, point, comp.h, states, comp.period_s), growth_limit,
                           scale)

    # the gap at every grid load, from the top down, each search started from the answer above
    gaps = [0] * len(loads)
    gap_sources = [float(x) for x in loads]
    above, scale = None, None
    for i in top_down:
        analysis = gap_analysis(own[i], scale)
        gaps[i] = above = analysis.max_gap(cap, start=above)
        scales[i] = scale = analysis.rms
        tick(f"ride-through gap {loads[i]:7.1f} N")
    # the other check loads, each tested at its interval's limit (the lesser end)
    for e, j, k in others:
        bound = min(gaps[j], gaps[k])
        if bound > 0:
            found = gap_analysis(e, scales[j]).max_gap(cap, below=bound)
            if found < bound:
                _fold(gaps, gap_sources, j, k, found, plan[e][0])
        tick(f"ride-through gap {plan[e][0]:7.1f} N")

    count = int(round(delay_cap / delay_step))
    grid = [round(k * delay_step, 10) for k in range(count + 1)]
    plants: dict[int, _DelayedPlant] = {}

    def stable(e: int, k: int) -> bool:
        load, _, point = plan[e]
        if e not in plants:
            plants[e] = _DelayedPlant(rig, load, delay_step)
        plant, c = plants[e].sampled(round(rig.chain.delay_samples + grid[k], 10))
        io = list(PLANE_CHANNELS[rig.plane])
        matrix = closed_loop_matrix(plant, c, point.plane(list(states), rig.plane), comp.h[np.ix_(io, io)],
                                    comp.period_s, rig.force_gain)
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
    delay_sources = [float(x) for x in loads]
    for i in top_down:
        delays[i] = walk(own[i], count)
        tick(f"ride-through delay {loads[i]:7.1f} N")
    # the other check loads at their interval's limit; below it only if unstable there
    for e, j, k in others:
        bound = min(delays[j], delays[k])
        if bound > 0 and not stable(e, bound):
            _fold(delays, delay_sources, j, k, walk(e, bound - 1), plan[e][0])
        plants.pop(e, None)
        tick(f"ride-through delay {plan[e][0]:7.1f} N")

    design_delay = float(table.design.io.delay_samples)
    per_load = [limits(g, grid[k], margin, design_delay) for g, k in zip(gaps, delays, strict=True)]
    best_gap, gap_load = _worst(gaps, gap_sources)
    best_k, delay_load = _worst(delays, delay_sources)
    gap_limit, budget = limits(best_gap, grid[best_k], margin, design_delay)
    return RideThrough(growth_limit=growth_limit, margin=margin, max_gap_samples=int(best_gap),
                       gap_limit_samples=gap_limit, gap_load_n=float(gap_load), gap_cap_samples=cap,
                       max_extra_delay_samples=grid[best_k], answer_budget_periods=budget,
                       delay_load_n=None if best_k == count else float(delay_load),
                       delay_step_samples=delay_step, delay_cap_samples=delay_cap,
                       elapsed_s=round(time.perf_counter() - started, 2),
                       max_gap_samples_per_load=tuple(int(g) for g in gaps),
                       gap_limits_samples=tuple(lim for lim, _ in per_load),
                       max_extra_delay_samples_per_load=tuple(grid[k] for k in delays),
                       answer_budgets_periods=tuple(b for _, b in per_load))
