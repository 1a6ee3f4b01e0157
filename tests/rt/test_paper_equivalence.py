"""The paper's design run as the one controller form gives the voltages of the paper's step
written out: q, the high-pass velocity estimate, the integral with anti-windup, u = -K(Fx) x
with K interpolated (or switched, in paper mode), allocation and fade-in.

``PaperStep`` below is the control step as beamctl ran it before the compensator form (the
arithmetic of its Controller and GainSchedule, the running state only), kept here as the
reference; the allocation is the same Allocator, whose own tests cover it.
"""

import bisect
import math
from dataclasses import replace

import numpy as np
import pytest

from beamctl.gains.compensator import MATRICES
from beamctl.gains.defaults import paper_table_path
from beamctl.gains.discrete import velocity_filter
from beamctl.gains.table import load_table
from beamctl.hal.base import Sample
from beamctl.rt.allocation import Allocator
from beamctl.rt.config import controller_config
from beamctl.rt.controller import FLAG_FADING_IN, FLAG_INTEGRATOR_HELD, Controller


class PaperStep:
    """The paper's law per sample, from the table's gains K and velocity filter cut-off."""

    def __init__(self, table, config):
        filt = velocity_filter(table.design.velocity_cutoff_hz, table.design.sample_rate_hz)
        self.period_s = 1.0 / table.design.sample_rate_hz
        self.ti = table.c0_phi_inv
        self.filt = filt
        self.loads = [float(x) for x in table.loads_n]
        self.gains = table.gains
        self.slopes = np.zeros_like(self.gains)
        self.slopes[:-1] = np.diff(self.gains, axis=0) / np.diff(table.loads_n)[:, None, None]
        self.paper = table.schedule.mode == "paper"
        self.half_band = 0.5 * table.schedule.hysteresis_n
        self.alpha = 1.0 - math.exp(-2.0 * math.pi * table.schedule.load_filter_hz
                                    / table.design.sample_rate_hz)
        self.allocator = Allocator(config.actuators)
        self.anti_windup = config.anti_windup
        self.bias = config.actuators.bias_voltage_v
        self.start_samples = max(1, round(config.start_ramp_time_s * table.design.sample_rate_hz))

    def start(self, strains, load):
        """Armed on, and started from, the same sample."""
        self.load = load
        last = len(self.loads) - 1
        if self.paper:
            self.index = min(bisect.bisect_left(self.loads, load), last)
        else:
            self.index = min(max(bisect.bisect_right(self.loads, load) - 1, 0), last)
        self.locate()
        self.hp = -self.filt.scale * self.filt.b0 * (self.ti @ strains)
        self.xi = np.zeros(4)
        self.u = np.zeros(4)
        self.steps = 0

    def locate(self):
        loads, last = self.loads, len(self.loads) - 1
        self.offset = 0.0
        if self.paper:
            i = self.index
            while i < last and self.load > loads[i] + self.half_band:
                i += 1
            while i > 0 and self.load < loads[i - 1] - self.half_band:
                i -= 1
            self.index = i
        elif self.load <= loads[0]:
            self.index = 0
        elif self.load >= loads[-1]:
            self.index = last
        else:
            self.index = bisect.bisect_right(loads, self.load) - 1
            self.offset = self.load - loads[self.index]

    def step(self, strains, load):
        self.load += self.alpha * (load - self.load)
        self.locate()
        k = self.gains[self.index] + self.offset * self.slopes[self.index]
        q = self.ti @ strains
        qdot = self.filt.scale * self.filt.b0 * q + self.hp
        self.hp = self.filt.scale * self.filt.b1 * q - self.filt.a1 * qdot
        dxi = self.period_s * q
        alloc = self.allocator
        held = False
        if self.anti_windup and (alloc.scale_a < 1.0 or alloc.scale_b < 1.0):
            du = -k[:, 8:12] @ dxi
            u = self.u
            held = ((alloc.scale_a < 1.0 and du[0] * u[0] + du[1] * u[1] > 0.0)
                    or (alloc.scale_b < 1.0 and du[2] * u[2] + du[3] * u[3] > 0.0))
        if not held:
            self.xi = self.xi + dxi
        self.u = -k @ np.concatenate([q, qdot, self.xi])
        target = np.zeros(6)
        alloc.allocate(self.u, target)
        self.steps += 1
        if self.steps < self.start_samples:
            return (target - self.bias) * (self.steps / self.start_samples) + self.bias
        return target


def _inputs(top_n: float, n: int = 4000, seed: int = 11):
    """Random strains of a few micro-strain with bursts that saturate the stacks (a constant
    deflection the integral winds up against, random kicks, a large vibration), on a load
    rising from 500 N to ``top_n``."""
    rng = np.random.default_rng(seed)
    loads = np.linspace(500.0, top_n, n) + 2.0 * rng.standard_normal(n)
    strains = 3e-6 * rng.standard_normal((n, 4))
    strains[1200:1900] += 4e-4 * np.array([1.0, -0.6, 0.8, 0.3])
    strains[2500:2600] += 3e-4 * rng.standard_normal((100, 4))
    strains[3000:3400] += 6e-4 * np.sin(np.arange(400) / 9.0)[:, None] * np.array([1.0, 0.5, -0.7, 0.2])
    return strains, loads


@pytest.fixture(scope="module")
def table():
    return load_table(paper_table_path())


def _paper_switching(table):
    """The shipped gains up to 3500 N, switched as in the paper's experiment."""
    comp = table.compensator
    return replace(table, loads_n=table.loads_n[:71], gains=table.gains[:71],
                   compensator=replace(comp, **{m: getattr(comp, m)[:71] for m in MATRICES}),
                   schedule=replace(table.schedule, mode="paper"))


@pytest.mark.parametrize(("mode", "anti_windup"), [("interpolate", True), ("interpolate", False),
                                                   ("paper", True)])
def test_the_paper_design_as_a_compensator_gives_the_paper_step_s_voltages(table, mode, anti_windup):
    if mode == "paper":
        table = _paper_switching(table)
    strains, loads = _inputs(3900.0 if mode == "interpolate" else 3400.0)
    config = controller_config({"start_ramp_time_s": 0.1, "anti_windup": anti_windup,
                                "safety": {"saturation_time_s": 10.0}})
    controller = Controller(table, config)
    reference = PaperStep(table, config)
    sample = Sample()
    sample.strains[:] = strains[0]
    sample.axial_load = loads[0]
    controller.arm(sample)
    controller.start()
    reference.start(strains[0], loads[0])
    worst, saturated, held, fading = 0.0, 0, 0, 0
    for y, load in zip(strains, loads, strict=True):
        sample.strains[:] = y
        sample.axial_load = load
        voltages = controller.step(sample)
        worst = max(worst, float(np.abs(voltages - reference.step(y, load)).max()))
        flags = int(controller.record[4])
        saturated += controller.allocator.scale_a < 1.0 or controller.allocator.scale_b < 1.0
        held += bool(flags & FLAG_INTEGRATOR_HELD)
        fading += bool(flags & FLAG_FADING_IN)
    assert controller.state.name == "RUNNING", controller.supervisor.reason()
    assert saturated > 500 and fading > 200 and (held > 400 or not anti_windup), (
        f"the run must cover saturation ({saturated}), anti-windup ({held}) and the fade-in ({fading})")
    assert worst <= 1e-9, f"voltages differ from the paper's step by up to {worst:.3g} V"
