"""The closed-loop check: the loop it analyses is the loop the controller runs, with the I/O
chain the design declares."""

from dataclasses import replace

import numpy as np
import pytest

from beamctl.gains.build import check_load, nominal_rig
from beamctl.gains.closedloop import closed_loop_matrix
from beamctl.gains.compensator import MATRICES, PLANE_CHANNELS, CompensatorPoint
from beamctl.gains.defaults import paper_table_path
from beamctl.gains.rig import RigPlane
from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import load_table
from beamctl.hal.base import Sample
from beamctl.models.iochain import IOChain
from beamctl.rt.config import controller_config
from beamctl.rt.controller import Controller
from tests.rounding import assert_within, spectral_radius_rounding


@pytest.fixture(scope="module")
def table():
    return load_table(paper_table_path())


def _with_estimator_feedback(table):
    """The shipped compensator with a small E (the applied force fed back into its state), as
    a model-based design has: the paper's has E = 0."""
    comp = table.compensator
    e = 1e-9 * np.random.default_rng(5).standard_normal(comp.e.shape[1:])
    for states, plane in ((comp.plane_states["y"], "y"), (comp.plane_states["z"], "z")):
        e[np.ix_(states, PLANE_CHANNELS["z" if plane == "y" else "y"])] = 0.0   # planes stay apart
    return replace(table, compensator=replace(comp, e=np.broadcast_to(e, comp.e.shape).copy()))


@pytest.mark.parametrize(("load", "delay", "feedback"), [
    (1000.0, 0.0, False), (3525.0, 0.0, False), (1000.0, 0.5, False), (2000.0, 1.0, False),
    (1000.0, 0.0, True), (2000.0, 1.5, True)])
def test_the_loop_the_check_analyses_is_the_loop_the_controller_runs(paper_model, table, load, delay,
                                                                     feedback):
    """The rt controller (integral action, interpolated compensator, allocation, the force its
    voltages give fed back) closed around the delayed zero-order-hold FE plant follows, step by
    step, the closed-loop matrix ``gains check`` takes its spectral radius from: the plant's
    states and the compensator's. Tolerance 1e-9 of the largest state: rounding only (the forces
    stay far inside the stacks' range, so the allocation reproduces them exactly)."""
    if feedback:
        table = _with_estimator_feedback(table)
    comp = table.compensator
    period = comp.period_s
    plant, c = RigPlane(paper_model, IOChain(delay_samples=delay), 1.0 / period).sampled(load)
    states, io = comp.plane_states["y"], list(PLANE_CHANNELS["y"])
    point = GainSchedule.from_table(table).matrices_at(load)
    a_cl = closed_loop_matrix(plant, c, point.plane(states, "y"), comp.h[np.ix_(io, io)], period)

    controller = Controller(table, controller_config({"start_ramp_time_s": 0.0}))
    n = plant.ad.shape[0]
    x = 1e-9 * np.random.default_rng(7).standard_normal(n)       # a few micro-strain at the gauges
    sample = Sample()
    sample.axial_load = load

    def measure(state):
        sample.strains[:] = 0.0
        sample.strains[io] = c @ state                           # the y plane's gauges
        return sample

    controller.arm(measure(x))
    controller.start()
    nb = 2 * (plant.whole + 1)
    z = np.concatenate([x, np.zeros(nb), controller.compensator_state[states], np.zeros(2)])
    applied = [np.zeros(2)] * (plant.whole + 2)                   # u_k-1, u_k-2, ...: at bias before
    worst, scale = 0.0, np.abs(x).max()
    worst_c, scale_c = 0.0, np.abs(z[n + nb:n + nb + 2]).max()
    for _ in range(300):
        voltages = controller.step(measure(x))
        assert controller.allocator.scale_a == 1.0 and controller.allocator.scale_b == 1.0
        applied.insert(0, controller.allocator.forces(voltages)[io])
        x = plant.ad @ x + plant.b_now @ applied[plant.whole] + plant.b_before @ applied[plant.whole + 1]
        z = a_cl @ z
        worst = max(worst, np.abs(x - z[:n]).max())
        scale = max(scale, np.abs(x).max())
        xc = controller.compensator_state[states]
        worst_c = max(worst_c, np.abs(xc - z[n + nb:n + nb + 2]).max())
        scale_c = max(scale_c, np.abs(xc).max())
    assert worst <= 1e-9 * scale and worst_c <= 1e-9 * scale_c, (
        f"controller and checked closed loop differ by {worst:.3g} in the plant (states up to "
        f"{scale:.3g}) and {worst_c:.3g} in the compensator ({scale_c:.3g}) at {load:g} N: "
        f"gains/closedloop.py no longer analyses what rt/controller.py runs")


def test_z_plane_check_equals_y_plane_check(paper_model, table):
    """Why checking one plane suffices: the circular section gives both planes the same plant
    spectrum (and the compensator the same block, tests/gains/test_compensator.py)."""
    point = GainSchedule.from_table(table).matrices_at(3500.0)
    y = check_load(paper_model, 3500.0, point, table, "y")
    z = check_load(paper_model, 3500.0, point, table, "z")
    # two eigenvalue solves of two matrices equal to rounding: within what the solver guarantees
    # of the dominant pole (8e-7 here, 1.4 % of the table's stability margin 5.8e-5; seen: 4e-15)
    matrix = nominal_rig(paper_model, table, "y").loop_matrix(3500.0, point, table.compensator.h,
                                                              table.compensator.plane_states["y"],
                                                              table.compensator.period_s)
    bound = spectral_radius_rounding(matrix)
    assert bound < 0.05 * (1.0 - max(c.spectral_radius for c in table.checks)), "too coarse to tell"
    assert_within(z.spectral_radius, y.spectral_radius, bound, "spectral radius of the z and the y plane")


def test_uncontrolled_beam_beyond_buckling_is_unstable_in_the_check(paper_model, table):
    """The check can fail: a compensator of zeros at 3500 N leaves the divergent first mode."""
    point = table.compensator.point(0)
    zero = CompensatorPoint(*(np.zeros_like(getattr(point, m)) for m in MATRICES))
    result = check_load(paper_model, 3500.0, zero, table)
    assert not result.stable and result.spectral_radius > 1.05
    below = check_load(paper_model, 3000.0, zero, table)
    # a physical tolerance: a pole within 1e-9 of 1 is an integrator (a time constant of 1e9 samples)
    assert below.spectral_radius == pytest.approx(1.0, abs=1e-9), "integrators without feedback"


def test_the_check_uses_the_io_chain_the_design_declares(paper_model, table):
    """The same matrices checked for a rig whose voltages arrive a sample late: the paper's
    design, stable at 3500 N without delay, is not (README: unstable from about 3200 N)."""
    point = GainSchedule.from_table(table).matrices_at(3500.0)
    assert check_load(paper_model, 3500.0, point, table).stable
    late = replace(table, design=replace(table.design, io=IOChain(delay_samples=1.0)))
    assert not check_load(paper_model, 3500.0, point, late).stable
