"""Stalls in the time domain: the controller's engine (rt/controller.py) in lockstep with the
simulated rig (models/plant.py), a stall of N samples injected at a load (the stacks hold the last
answer for N samples the controller never sees, then the newest sample arrives with N missed, as
the CAN backend delivers it), and what the beam and the stacks went through. Deterministic: the
plant's noise from its seed, no clock but the samples.

``stall_run`` runs one stall and says whether it was survived: no fault, no stack at the end of
its range, the strain within the supervisor's limit, through the stall and ``after_s`` of
recovery. ``survival_edge`` lifts the engine's limit (its growth curves all 1, its caps off, so
that it bridges any stall) and searches the shortest stall that is lost: the time-domain edge the
table's live limit must stay below (gains/ridethrough.py; tests/simulation/test_stall.py, the
figure in docs/pages/controller.md).

The rigs: the nominal (the table's model) and any ``models.rig.Rig`` (the robust check's worst,
``gains.robust.rig_of``): its own beam, supports, damping, gauges, I/O delay and DAQ rate, and
its stacks' force per volt ``force_gain`` times what the controller believes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from beamctl.gains import robust
from beamctl.gains.table import GainTable
from beamctl.hal.base import Sample
from beamctl.models.fe import build_model
from beamctl.models.plant import Plant, plant_config
from beamctl.models.rig import Rig
from beamctl.rt import engine as e
from beamctl.rt.allocation import geometry
from beamctl.rt.config import ControllerConfig, controller_config
from beamctl.rt.controller import Controller

# the simulated rig of the acceptance runs: a 20 um bow, 0.2 ue gauge noise, 2 N load noise
RIG_SETTINGS = {"bow": {"amplitude": 2e-5, "angle_deg": 30.0}, "noise": {"strain": 2e-7, "load": 2.0}}
RAMP_N_PER_S = 1000.0     # the load is brought from the table's start to the stall's load at this
START_N = 2000.0          # ... from here (the controller started below the critical load)
SETTLE_S = 1.0            # held at the load this long before the stall (the spreads settle: 0.1 s,
                          # from what the ramp adds to the stacks' moving variance)
AFTER_S = 0.2             # followed this long after the stall (the recovery)


@dataclass(frozen=True)
class StallOutcome:
    """What one stall did: ``survived`` (no fault, no stack at its range's end, the strain
    within the limit), the live limit and let-go when it began (samples), the largest strain's fraction of
    the supervisor's limit and the largest stack excursion from the operating point (V) during
    the stall and after it, the fault (name, or "")."""

    load_n: float
    gap_samples: int
    survived: bool
    limit_samples: float
    strain_fraction: float
    voltage_excursion_v: float
    saturated: bool
    fault: str
    let_go_samples: float = math.nan


class _Lockstep:
    """A controller and the simulated rig in lockstep: the newest sample into ``sample``
    (``measure``, returns its largest strain), the stacks' voltages onto the beam for one sample
    (``apply``), and the start (``bring``: armed, started, brought to the load and held)."""

    def __init__(self, rig: StallRig, plant: Plant, controller: Controller) -> None:
        self.rig, self.plant, self.c = rig, plant, controller
        self.sample = Sample()
        self.forces = np.zeros(4)
        self.seq = 0

    def measure(self) -> float:
        strains, load = self.plant.measure()
        s = self.sample
        s.strains[:] = strains
        s.axial_load = load
        s.sequence = self.seq
        s.timestamp = self.plant.time
        self.seq += 1
        return float(np.abs(strains).max())

    def apply(self, voltages: np.ndarray) -> None:
        np.dot(self.rig.force_matrix, voltages - self.rig.bias, out=self.forces)
        self.plant.step(self.forces)

    def bring(self, settle_s: float) -> None:
        c, sample = self.c, self.sample
        self.measure()
        c.arm(sample)
        c.start()
        reach = self.plant.config.load.duration() + settle_s
        while self.plant.time < reach and c.state.name == "RUNNING":
            self.measure()
            sample.missed = 0
            self.apply(c.step(sample))


class StallRig:
    """A controller of ``table`` (``config``: the shipped settings by default) on a simulated
    rig (``rig``: None for the nominal), ready to bring to a load and stall."""

    def __init__(self, table: GainTable, rig: Rig | None = None, config: ControllerConfig | None = None,
                 seed: int = 1) -> None:
        self.table = table
        self.nominal = rig is None
        self.config = config or controller_config()
        params = table.model_parameters if rig is None else rig.params
        rate = table.design.sample_rate_hz if rig is None else rig.sample_rate_hz
        chain = table.design.io if rig is None else rig.chain
        self.force_gain = 1.0 if rig is None else float(rig.force_gain)
        self.model = build_model(params)
        self.rate = float(rate)
        self.table_rate = float(table.design.sample_rate_hz)
        self.io = chain.to_dict()        # the rig's own I/O chain (anti-alias filter, delay)
        self.seed = seed
        self.geometry = geometry(self.config.actuators)
        self.force_matrix = self.geometry.force_matrix() * self.force_gain
        self.bias = self.geometry.bias_voltage_v
        a = self.config.actuators
        self.v_range = (a.min_voltage_v, a.max_voltage_v)
        beam = table.model_parameters.beam
        self.strain_limit = (self.config.safety.strain_limit_fraction * beam.proportional_limit
                             / beam.youngs_modulus)

    def stall_samples(self, table_samples: float) -> int:
        """The longest stall (in the rig's samples) that the engine, counting in the table's
        periods, holds as at most ``table_samples`` (``held``: the silence since the sample before,
        rounded, rt/engine.py): the same on the nominal rig, fewer on a rig whose DAQ clock is
        slower than the table's rate."""
        ratio = self.table_rate / self.rate
        n = int(np.floor(table_samples))
        while n > 0 and np.floor((n + 1) * ratio - 0.5) > table_samples:
            n -= 1
        return n

    def _plant(self, load_n: float) -> Plant:
        start = min(START_N, load_n)
        settings = {**RIG_SETTINGS, "sample_rate_hz": self.rate,
                    "load": {"start": start, "end": load_n, "rate": RAMP_N_PER_S, "hold": 0.02},
                    "io": self.io}
        settings["noise"] = {**RIG_SETTINGS["noise"], "seed": self.seed}
        return Plant(self.model, plant_config(settings))

    def run(self, load_n: float, gap: int | None, lift: bool = False, settle_s: float = SETTLE_S,
            after_s: float = AFTER_S, before: tuple[int, int] = (0, 0)) -> StallOutcome:
        """A stall of ``gap`` samples at ``load_n`` (None: as long as the live limit when it
        begins; ``lift``: the engine's limit lifted, so that it bridges the stall whatever its
        length); ``before``: (stall, samples answered) a first stall and the samples answered
        after it before this one begins (within its recovery: the live limit then is lower)."""
        plant = self._plant(load_n)
        c = Controller(self.table, self.config)
        if lift:
            o, n, gl = int(c.iv[e.O_GROWTH]), int(c.iv[e.V_N_GRID]), int(c.iv[e.V_N_GLOADS])
            c._mats[o:o + gl * 2 * n] = 1.0
            c.fv[e.P_GAP_CAP] = c.fv[e.P_LET_GO_CAP] = c.fv[e.P_LATE_CAP] = np.inf
        bench = _Lockstep(self, plant, c)
        sample, measure, apply = bench.sample, bench.measure, bench.apply
        strain_top, swing, saturated = 0.0, 0.0, False

        def stall(samples: int) -> np.ndarray:
            """The stacks hold the last answer for ``samples`` samples the controller never
            sees; then the newest arrives with them missed (not yet answered)."""
            nonlocal strain_top
            held = c.voltages.copy()
            for _ in range(samples):
                measure()
                strain_top = max(strain_top, float(np.abs(sample.strains).max()))
                apply(held)
            measure()
            sample.missed = samples
            return held

        def answer(samples: int, held: np.ndarray) -> bool:
            """The sample in hand and ``samples`` - 1 more answered; False once not RUNNING."""
            nonlocal strain_top, swing, saturated
            for k in range(samples):
                if k:
                    measure()
                    sample.missed = 0
                v = c.step(sample)
                if c.state.name != "RUNNING":
                    return False
                saturated |= bool(np.any(v <= self.v_range[0]) or np.any(v >= self.v_range[1]))
                swing = max(swing, float(np.abs(v - held).max()))
                strain_top = max(strain_top, float(np.abs(sample.strains).max()))
                apply(v)
            return True

        bench.bring(settle_s)
        limit, let_go = c.gap_limit, c.let_go
        first, between = before
        if first > 0 and not answer(max(between, 1), stall(first)):
            gap = 0
        else:
            limit, let_go = c.gap_limit, c.let_go
            if gap is None:
                gap = self.stall_samples(limit)
            answer(int(round(after_s * self.rate)) + 1, stall(gap))
        fault = c.supervisor.fault.name if c.supervisor.fault.name != "NONE" else ""
        fraction = strain_top / self.strain_limit
        survived = not fault and not saturated and fraction < 1.0
        return StallOutcome(load_n=float(load_n), gap_samples=int(gap), survived=survived,
                            limit_samples=float(limit), strain_fraction=fraction,
                            voltage_excursion_v=swing, saturated=saturated, fault=fault,
                            let_go_samples=float(let_go))

    def loss(self, load_n: float, every: int, duration_s: float, after_s: float = AFTER_S) -> StallOutcome:
        """A loss that persists: for ``duration_s`` at ``load_n`` only every ``every``-th sample
        reaches the controller (the others lost on the bus: the stacks hold the last answer, the
        next sample arrives with them missed), then ``after_s`` of every sample. ``gap_samples``
        of the outcome: the samples lost."""
        c = Controller(self.table, self.config)
        bench = _Lockstep(self, self._plant(load_n), c)
        sample, measure, apply = bench.sample, bench.measure, bench.apply
        bench.bring(SETTLE_S)
        held = c.voltages.copy()
        before = held.copy()                # the operating point the excursion is measured from
        lossy = int(round(duration_s * self.rate))
        total = lossy + int(round(after_s * self.rate))
        strain_top, swing, saturated, lost, since = 0.0, 0.0, False, 0, 0
        for k in range(total):
            strain_top = max(strain_top, measure())
            if k < lossy and k % every:
                apply(held)                 # lost: the stacks hold the last answer
                since += 1
                lost += 1
                continue
            sample.missed = since
            since = 0
            v = c.step(sample)
            if c.state.name != "RUNNING":
                break
            saturated |= bool(np.any(v <= self.v_range[0]) or np.any(v >= self.v_range[1]))
            swing = max(swing, float(np.abs(v - before).max()))
            held = v.copy()
            apply(held)
        fault = c.supervisor.fault.name if c.supervisor.fault.name != "NONE" else ""
        fraction = strain_top / self.strain_limit
        return StallOutcome(load_n=float(load_n), gap_samples=lost, survived=not fault and not saturated
                            and fraction < 1.0, limit_samples=float(c.gap_limit), strain_fraction=fraction,
                            voltage_excursion_v=swing, saturated=saturated, fault=fault)

    def edge(self, load_n: float, cap: int, start: int = 1) -> int:
        """The shortest stall (samples) lost at ``load_n`` with the limit lifted, by a galloping
        search from ``start`` and a bisection (survival taken to fall with the stall's length);
        ``cap + 1`` when a stall of ``cap`` is survived."""
        low, high = 0, None                 # low: survived (0: none tried), high: lost
        n = max(int(start), 1)
        while high is None:
            if self.run(load_n, n, lift=True).survived:
                low = n
                if n >= cap:
                    return cap + 1
                n = min(2 * n, cap)
            else:
                high = n
        while high - low > 1:
            mid = (low + high) // 2
            if self.run(load_n, mid, lift=True).survived:
                low = mid
            else:
                high = mid
        return high


def worst_rig(table: GainTable) -> Rig | None:
    """The robust check's worst rig that ``table`` records (gains/robust.py), or None."""
    record = table.robust or {}
    if not (record.get("worst_rig") and isinstance(record.get("box"), dict)):
        return None
    box = robust.box_from_dict(record["box"], table.model_parameters, "the table's robust check")
    return robust.rig_of(table, box, record["worst_rig"])


@dataclass(frozen=True)
class EdgeRow:
    """At one load: the live limit when the stall began (the longest stall it rides through) and
    the time-domain survival edge (the shortest stall lost with the limit lifted; ``cap + 1``:
    none up to the cap, the cap being the stall faulted as a stopped DAQ), in samples of the
    rig's rate; ``held``: the rig is held at this load without a stall (where it is not, beyond
    its loop's stability onset, the edge is 0); ``let_go_samples``: the let-go then (a longer
    stall faults)."""

    load_n: float
    limit_samples: float
    edge_samples: int
    cap_samples: int
    rate_hz: float
    held: bool = True
    let_go_samples: float = math.nan


def edges(stall_rig: StallRig, loads, progress=None) -> list[EdgeRow]:
    """The limit and the survival edge at each of ``loads`` (``edge``: from the limit up)."""
    table = stall_rig.table
    cap = stall_rig.stall_samples(table.ride_through.gap_cap_samples if table.ride_through else 600) - 1
    rows = []
    for i, load in enumerate(loads):
        still = stall_rig.run(float(load), 0)       # no stall: is the rig held here at all?
        limit = stall_rig.stall_samples(still.limit_samples)
        edge = stall_rig.edge(float(load), cap, start=max(limit, 1)) if still.survived else 0
        let_go = stall_rig.stall_samples(still.let_go_samples)
        rows.append(EdgeRow(float(load), float(limit), int(edge), cap, stall_rig.rate, still.survived,
                            float(let_go)))
        if progress:
            said = (f"limit {limit:g}, let-go {let_go:g}, edge {edge} samples" if still.survived
                    else "not held without a stall")
            progress(i + 1, len(loads), f"{load:7.1f} N: {said}")
    return rows


def edge_figure(curves: dict[str, list[EdgeRow]], path) -> None:
    """Limit, let-go and survival edge (ms) versus load, one colour per rig; an edge beyond the cap is
    drawn at the cap with an open marker; loads where a rig is not held are left out."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    for (name, rows), colour in zip(curves.items(), ("C0", "C3", "C2", "C1"), strict=False):
        rows = [r for r in rows if r.held]
        loads = [r.load_n for r in rows]
        limit = [1e3 * r.limit_samples / r.rate_hz for r in rows]
        edge = [1e3 * min(r.edge_samples, r.cap_samples) / r.rate_hz for r in rows]
        beyond = [r.edge_samples > r.cap_samples for r in rows]
        ax.plot(loads, limit, "-o", color=colour, label=f"live limit, {name}")
        let_go = [1e3 * r.let_go_samples / r.rate_hz for r in rows]
        ax.plot(loads, let_go, ":", color=colour, label=f"let-go, {name}")
        ax.plot(loads, edge, "--", color=colour, label=f"survival edge, {name}")
        for x, y, b in zip(loads, edge, beyond, strict=True):
            ax.plot([x], [y], "^" if b else "s", color=colour, markerfacecolor="none" if b else colour)
    ax.set_yscale("log")
    ax.set_xlabel("axial load (N)")
    ax.set_ylabel("stall (ms)")
    ax.set_title("live limit: survived with 3.5 sigma to spare; let-go: faulted beyond;\n"
                 "edge: the shortest stall lost (open marker: none lost up to the cap)")
    ax.title.set_fontsize(9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
