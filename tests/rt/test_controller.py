"""The control step: equations, anti-windup, bumpless start, fault ramps, no allocation."""

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
import scipy.signal

from beamctl.gains.compensator import MATRICES
from beamctl.gains.defaults import paper_table_path
from beamctl.gains.discrete import velocity_filter
from beamctl.gains.table import load_table
from beamctl.hal.base import Sample
from beamctl.rt.config import controller_config
from beamctl.rt.controller import FLAG_INTEGRATOR_HELD, Controller
from beamctl.rt.safety import Fault, State, TransitionError
from tests.rounding import assert_within, gamma, product_rounding


@pytest.fixture(scope="module")
def table():
    return load_table(paper_table_path())


def _sample(strains=(0.0, 0.0, 0.0, 0.0), load=1000.0):
    s = Sample()
    s.strains[:] = strains
    s.axial_load = load
    return s


def _velocity_filter(table):
    return velocity_filter(table.design.velocity_cutoff_hz, table.design.sample_rate_hz)


def _velocity_estimate(c):
    """The paper's modal velocity estimate v_k of the step just run. The compensator's state is
    the high-pass filter's state scaled by omega_c (gains.compensator.from_integral_lqr), and
    the step leaves the next one, x_c,k+1 = omega_c b1 q_k - a1 v_k."""
    filt = _velocity_filter(c.table)
    return (filt.scale * filt.b1 * c.q - c.compensator_state) / filt.a1


def _gain_at(table, load):
    """K interpolated linearly between the grid points around ``load``."""
    i = int(np.searchsorted(table.loads_n, load, side="right")) - 1
    w = (load - table.loads_n[i]) / (table.loads_n[i + 1] - table.loads_n[i])
    return table.gains[i] + w * (table.gains[i + 1] - table.gains[i])


def _running(table, **overrides):
    c = Controller(table, controller_config(overrides))
    first = _sample()
    c.arm(first)
    c.start()
    return c


def test_step_computes_q_velocity_integral_and_u_as_specified(table):
    """q = (C0 Phi)^-1 y, qdot = omega_c x Butterworth high-pass of q (scipy.signal.lfilter
    as reference), xi = sum T q, u = -K(Fx) [q, qdot, xi] with K interpolated at the
    filtered load."""
    c = _running(table, start_ramp_time_s=0.0)
    rng = np.random.default_rng(3)
    ys = 2e-6 * rng.standard_normal((300, 4))
    loads = 1234.0 + 3.0 * rng.standard_normal(300)
    qs, qdots, xis = [], [], []
    for y, load in zip(ys, loads, strict=True):
        c.step(_sample(y, load))
        qs.append(c.q.copy())
        qdots.append(_velocity_estimate(c))
        xis.append(c.xi.copy())
    q_ref = ys @ table.c0_phi_inv.T
    # the engine sums its products in its own order, numpy's BLAS in the kernel's: each quantity
    # to the rounding of what it sums (tests/rounding.py); the velocity filter's recursion
    # (|a1| < 1) and the integral's running sum add one rounding per sample at most
    assert_within(qs, q_ref, product_rounding(ys, table.c0_phi_inv.T), "q = (C0 Phi)^-1 y")
    filt = _velocity_filter(table)
    hp = scipy.signal.lfilter([filt.b0, filt.b1], [1.0, filt.a1], np.vstack([np.zeros((1, 4)), q_ref]),
                              axis=0, zi=-filt.b0 * np.zeros((1, 4)))[0]
    # the controller starts its filter at rest on the first sample (all zero here)
    steps = len(ys)
    q_mag = np.abs(ys) @ np.abs(table.c0_phi_inv.T)
    qdot_mag = filt.scale * (abs(filt.b0) + abs(filt.b1)) * np.max(q_mag) / (1 - abs(filt.a1))
    assert_within(qdots, filt.scale * hp[1:], 2 * gamma(steps + 4) * qdot_mag, "the velocity estimate")
    assert_within(xis, np.cumsum(q_ref, axis=0) * c.period_s,
                  2 * gamma(steps + 4) * np.cumsum(q_mag, axis=0) * c.period_s, "the integral")
    load = c.filtered_load_n
    assert 1200 < load < 1250 and load % 50.0 != 0.0, "between two grid points"
    x = np.concatenate([qs[-1], qdots[-1], xis[-1]])
    x_mag = np.concatenate([q_mag[-1], np.full(4, qdot_mag), np.sum(q_mag, axis=0) * c.period_s])
    gain = _gain_at(table, load)
    # u from the compensator form (C s + D y + Ki xi) against K x: the rounding of x carried
    # through |K|, and of the two ways to sum
    assert_within(c.u, -gain @ x, 2 * gamma(steps + 16) * (np.abs(gain) @ x_mag), "u = -K(Fx) x")


def test_velocity_estimate_starts_without_a_kick(table):
    """Bumpless: a beam already deflected when the controller starts shows no velocity."""
    c = Controller(table, controller_config())
    s = _sample((3e-5, -1e-5, 2e-5, 4e-6))
    c.arm(s)
    c.start()
    c.step(s)
    assert np.abs(_velocity_estimate(c)).max() < 1e-12
    np.testing.assert_allclose(c.xi, c.q * c.period_s, rtol=1e-12)


def test_start_fades_the_voltages_in_from_bias(table):
    c = Controller(table, controller_config({"start_ramp_time_s": 0.1}))
    s = _sample((2e-5, 2e-5, 1e-5, 1e-5))
    c.arm(s)
    np.testing.assert_array_equal(c.voltages, 75.0)
    c.start()
    steps = []
    for _ in range(400):
        steps.append(c.step(s).copy())
    steps = np.array(steps)
    jumps = np.abs(np.diff(np.vstack([np.full(6, 75.0), steps]), axis=0)).max()
    assert jumps < 1.0, f"largest voltage change per sample during start {jumps:.3f} V"
    assert np.abs(steps[0] - 75.0).max() < 0.05


def test_anti_windup_stops_the_integrator_winding_into_saturation(table):
    """A large constant deflection saturates the stacks; with anti-windup the integral stops
    growing, without it keeps winding (the paper's beam buckled once 150 V was hit)."""
    results = {}
    for enabled in (True, False):
        c = _running(table, anti_windup=enabled, start_ramp_time_s=0.0,
                     safety={"saturation_time_s": 10.0})
        s = _sample((4e-4, 0.0, 4e-4, 0.0), 3000.0)
        while c.allocator.scale_a == 1.0:
            c.step(s)
        at_saturation = c.xi[0]
        held = 0
        for _ in range(2000):
            c.step(s)
            held += bool(int(c.record[4]) & FLAG_INTEGRATOR_HELD)
        assert c.allocator.scale_a < 1.0, "the demand must stay saturated for this test"
        results[enabled] = (abs(c.xi[0] - at_saturation), held)
    (growth_on, held_on), (growth_off, held_off) = results[True], results[False]
    assert held_on == 2000 and held_off == 0
    assert growth_on < 1e-3 * growth_off, (
        f"integral grew by {growth_on:.3g} with anti-windup, {growth_off:.3g} without")


@pytest.mark.parametrize(("strains", "load", "fault"), [
    ((np.nan, 0, 0, 0), 1000.0, Fault.STRAIN_NOT_FINITE),
    ((0, 0, 5e-3, 0), 1000.0, Fault.STRAIN_OUT_OF_RANGE),
    ((0, 0, 0, 0), np.inf, Fault.LOAD_NOT_FINITE),
    ((0, 0, 0, 0), 6000.0, Fault.LOAD_OUT_OF_SENSOR_RANGE),
])
def test_bad_input_faults_and_ramps_to_bias_without_a_jump(table, strains, load, fault):
    c = _running(table, start_ramp_time_s=0.0, safety={"ramp_time_s": 0.1})
    deflected = _sample((1e-4, -5e-5, 5e-5, 2e-5), 1500.0)
    for _ in range(300):
        c.step(deflected)
    before = c.voltages.copy()
    assert np.abs(before - 75.0).max() > 1.0, "voltages away from bias before the fault"
    out = [c.step(_sample(strains, load)).copy()]
    for _ in range(400):
        out.append(c.step(deflected).copy())
    out = np.array(out)
    assert c.state == State.FAULT and c.supervisor.fault == fault, c.supervisor.reason()
    ramp_samples = 0.1 * c.sample_rate_hz
    largest = np.abs(np.diff(np.vstack([before, out]), axis=0)).max()
    bound = np.abs(before - 75.0).max() / ramp_samples
    assert largest <= bound * (1 + 1e-9), f"voltage jumped by {largest:.3f} V (ramp step {bound:.3f} V)"
    np.testing.assert_array_equal(out[-1], 75.0)
    assert np.all((out >= 0.0) & (out <= 150.0))


def test_a_fault_is_latched_until_an_operator_rearms(table):
    c = _running(table)
    c.step(_sample((np.nan, 0, 0, 0)))
    c.fault(Fault.HAL_ERROR, "second fault")
    assert c.supervisor.fault == Fault.STRAIN_NOT_FINITE, "the first reason stays"
    for _ in range(2000):
        c.step(_sample())
    assert c.state == State.FAULT
    with pytest.raises(TransitionError):
        c.start()
    c.rearm(_sample())
    assert c.state == State.ARMED and np.all(c.xi == 0)
    c.start()
    c.step(_sample())
    assert c.state == State.RUNNING


def test_load_beyond_the_paper_table_faults(table):
    comp = table.compensator
    paper = replace(table, loads_n=table.loads_n[:71], gains=table.gains[:71],
                    compensator=replace(comp, **{m: getattr(comp, m)[:71] for m in MATRICES}),
                    schedule=replace(table.schedule, mode="paper"))
    c = Controller(paper, controller_config())
    c.arm(_sample(load=3400.0))
    c.start()
    for _ in range(2500):
        c.step(_sample(load=3700.0))
    assert c.supervisor.fault == Fault.LOAD_OUT_OF_TABLE_RANGE


def test_the_step_calls_no_scipy(table):
    c = _running(table)
    rng = np.random.default_rng(0)
    samples = [_sample(1e-6 * rng.standard_normal(4), 1000.0 + 500 * k / 50) for k in range(50)]
    for s in samples:
        c.step(s)
    calls = set()

    def profile(frame, event, arg):
        if event == "c_call":
            calls.add(getattr(arg, "__module__", None) or type(arg).__name__)
        elif event == "call":
            calls.add(frame.f_globals.get("__name__"))

    sys.setprofile(profile)          # this thread only
    try:
        for s in samples:
            c.step(s)
    finally:
        sys.setprofile(None)
    assert not [m for m in calls if m and m.startswith("scipy")], calls


# tracemalloc counts every thread's allocations: measured in a fresh interpreter that runs
# nothing but the controller, so no other thread of the test session adds to the figures;
# the largest transient allocation of each step is taken on its own (peak reset per step).
# One interpreter probes the three cases in turn, each with a controller of its own and
# tracemalloc started afresh (starting one costs a second and a half of imports).
_ALLOCATION_PROBE = """
import json, sys, tracemalloc
import numpy as np
from beamctl.gains.compensator import MATRICES
from beamctl.gains.defaults import paper_table_path
from beamctl.gains.discrete import velocity_filter
from beamctl.gains.table import load_table
from beamctl.hal.base import Sample
from beamctl.rt.config import controller_config
from beamctl.rt.controller import Controller

table = load_table(paper_table_path())
for ALLOCATION, OFFSET in json.loads(sys.argv[1]):
    # a saturation that lasts the whole probe is no fault here (the fault's message is allocated once)
    c = Controller(table,
                   controller_config({"allocation": ALLOCATION, "safety": {"saturation_time_s": 100.0}}))
    rng = np.random.default_rng(0)
    samples = []
    for k in range(50):
        s = Sample()
        s.strains[:] = OFFSET + 1e-6 * rng.standard_normal(4)
        s.axial_load = 1000.0 + 500 * k / 50
        samples.append(s)
    c.arm(samples[0])
    c.start()
    many = samples * 20
    for s in many:
        c.step(s)
    step, get, reset = c.step, tracemalloc.get_traced_memory, tracemalloc.reset_peak
    tracemalloc.start()
    worst = 0
    saturated = 0
    start, _ = get()
    for s in many:
        reset()
        base, _ = get()
        step(s)
        _, peak = get()
        worst = max(worst, peak - base)
        saturated += c.allocator.scale_a < 1.0
    end, _ = get()
    tracemalloc.stop()
    print(json.dumps({"kept": end - start, "peak": worst, "state": c.state.name, "saturated": saturated,
                      "array_bytes": int(np.zeros(4).__sizeof__())}), flush=True)
"""


# a beam vibrating about straight: the stacks have room; bent (a strain offset the integral
# action answers): the allocation saturates, and ``clip`` clips stacks
ALLOCATION_CASES = [("scale", 0.0), ("scale", 1e-4), ("clip", 1e-4)]


@pytest.fixture(scope="module")
def allocation_probes(tmp_path_factory, compiled_engine) -> dict:
    """{(allocation, offset): the probe's figures} for every case, from one fresh interpreter."""
    out = subprocess.run([sys.executable, "-c", _ALLOCATION_PROBE, json.dumps(ALLOCATION_CASES)],
                         capture_output=True, text=True, cwd=tmp_path_factory.mktemp("probe"), timeout=120,
                         check=False)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert len(lines) == len(ALLOCATION_CASES), out.stdout
    return {case: json.loads(line) for case, line in zip(ALLOCATION_CASES, lines, strict=True)}


@pytest.mark.parametrize(("allocation", "offset"), ALLOCATION_CASES)
def test_the_step_allocates_no_arrays(allocation_probes, allocation, offset):
    probe = allocation_probes[(allocation, offset)]
    assert probe["state"] == "RUNNING"
    assert (probe["saturated"] > 0) == (offset > 0), f"saturated in {probe['saturated']} of 1000 steps"
    # A step's scalar arithmetic keeps a few Python floats (24 bytes each) alive at a time; one
    # more ndarray (over 100 bytes for the object and its data) on top of them exceeds 256 bytes.
    assert probe["peak"] < 256, (
        f"{probe['peak']} bytes allocated at once within one step (a 4-element array is "
        f"{probe['array_bytes']} bytes): the step allocated an array")
    assert probe["kept"] < 256, f"{probe['kept']} bytes kept by 1000 steps: a leak"


def test_rearm_waits_for_the_ramp_to_reach_bias(table):
    c = _running(table, start_ramp_time_s=0.0)
    for _ in range(300):
        c.step(_sample((1e-4, -5e-5, 5e-5, 2e-5), 1500.0))
    c.fault(Fault.OPERATOR, "test")
    c.step(_sample())
    with pytest.raises(TransitionError, match="ramped to bias"):
        c.rearm(_sample())
    while not c.at_bias:
        c.step(_sample())
    c.rearm(_sample())
    assert c.state == State.ARMED


def test_a_start_after_a_long_armed_dwell_has_no_velocity_kick(table):
    """The velocity filter starts at rest on the sample the controller starts on, however far
    the beam moved while armed."""
    c = Controller(table, controller_config({"start_ramp_time_s": 0.0}))
    c.arm(_sample((0.0, 0.0, 0.0, 0.0)))
    for k in range(2000):   # the beam deflects while the controller is only armed
        c.step(_sample((4e-5 * k / 2000, 0.0, 2e-5 * k / 2000, 0.0)))
    c.start()
    c.step(_sample((4e-5, 0.0, 2e-5, 0.0)))
    true_rate = table.c0_phi_inv @ np.array([4e-5, 0.0, 2e-5, 0.0]) / 2000 * c.sample_rate_hz
    estimate = _velocity_estimate(c)
    assert np.all(np.abs(estimate) <= np.abs(true_rate) + 1e-12), (
        f"estimate {estimate} exceeds the beam's own velocity {true_rate}")


def test_a_start_on_a_non_finite_strain_faults(table):
    c = Controller(table, controller_config())
    c.arm(_sample())
    c.step(_sample((np.nan, 0.0, 0.0, 0.0)))
    c.start()
    assert c.state == State.FAULT and c.supervisor.fault == Fault.STRAIN_NOT_FINITE
    np.testing.assert_array_equal(c.step(_sample()), 75.0)


def test_a_missing_sample_holds_the_voltages_until_the_stale_input_fault(table):
    """No new sample, no new measurement: the law does not integrate or filter the last one
    again; the stacks hold for stale_periods missing samples, and the one after them faults."""
    c = _running(table, start_ramp_time_s=0.0, safety={"stale_periods": 5})
    deflected = _sample((1e-4, -5e-5, 5e-5, 2e-5), 1500.0)
    for _ in range(300):
        c.step(deflected)
    voltages, xi = c.voltages.copy(), c.xi.copy()
    assert np.abs(voltages - 75.0).max() > 1.0, "the controller drives the stacks"
    for k in range(5):
        np.testing.assert_array_equal(c.step(None), voltages, err_msg=f"missing sample {k + 1}")
        np.testing.assert_array_equal(c.xi, xi)
        assert c.state == State.RUNNING
    c.step(None)
    assert c.supervisor.fault == Fault.STALE_INPUT, c.supervisor.reason()


@pytest.mark.parametrize("law", [False, True])
def test_an_excitation_never_drives_a_stack_beyond_the_voltage_limits(table, law):
    """Rows that would push every stack to 200 V or -50 V: the voltages stop at 150 V and 0 V,
    open loop and on top of the law."""
    config = controller_config({"start_ramp_time_s": 0.0})
    rows = np.vstack([np.full((5, 6), 125.0), np.full((5, 6), -125.0)])
    c = Controller(table, config, excitation=rows, law=law)
    c.arm(_sample())
    c.start()
    seen = [c.step(_sample()).copy() for _ in range(12)]
    np.testing.assert_allclose(seen[2], 150.0)
    np.testing.assert_allclose(seen[7], 0.0)
    np.testing.assert_allclose(seen[11], 75.0, atol=1e-6 if not law else 5.0,
                               err_msg="after the rows, bias (or the law's voltages near it)")
    assert c.excitation_index == len(rows)


def test_an_excitation_waits_while_disabled(table):
    config = controller_config({"start_ramp_time_s": 0.0})
    c = Controller(table, config, excitation=np.ones((3, 6)), law=False)
    c.excitation_enabled = False
    c.arm(_sample())
    c.start()
    np.testing.assert_allclose(c.step(_sample()), 75.0)
    c.excitation_enabled = True
    np.testing.assert_allclose(c.step(_sample()), 76.0)
    assert c.excitation_index == 1
