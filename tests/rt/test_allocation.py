"""Allocation of the lateral force to three stacks at 120 deg (property-based)."""

import math

import numpy as np
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from beamctl.rt.allocation import Allocator
from beamctl.rt.config import Actuators

any_float = st.floats(allow_nan=True, allow_infinity=True, width=64)
force = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False)
actuators = st.builds(
    Actuators,
    force_constant=st.floats(min_value=0.05, max_value=50.0),
    bias_voltage=st.just(75.0),
    min_voltage_v=st.floats(min_value=-30.0, max_value=20.0),
    max_voltage_v=st.floats(min_value=100.0, max_value=150.0),
    orientation_deg=st.tuples(st.floats(min_value=-360, max_value=360),
                              st.floats(min_value=-360, max_value=360)),
)


def _allocate(act, u):
    alloc = Allocator(act)
    v = np.full(6, np.nan)
    alloc.allocate(np.asarray(u, dtype=float), v)
    return alloc, v


@settings(max_examples=400)
@given(act=actuators, u=st.lists(any_float, min_size=4, max_size=4))
def test_no_voltage_ever_leaves_the_range(act, u):
    _, v = _allocate(act, u)
    assert np.all(np.isfinite(v)), f"non-finite voltage {v} for demand {u}"
    assert np.all(v >= act.min_voltage_v) and np.all(v <= act.max_voltage_v), (v, u)


@settings(max_examples=300)
@given(act=actuators, fy=force, fz=force)
def test_reachable_forces_are_reproduced_exactly(act, fy, fz):
    alloc, v = _allocate(act, [fy, fz, -fz, fy])
    assume(alloc.scale_a == 1.0 and alloc.scale_b == 1.0)
    np.testing.assert_allclose(alloc.forces(v), [fy, fz, -fz, fy],
                               atol=1e-9 * max(1.0, math.hypot(fy, fz)))


@settings(max_examples=300)
@given(act=actuators, fy=force, fz=force)
def test_unreachable_forces_keep_their_direction_and_touch_the_limits(act, fy, fz):
    alloc, v = _allocate(act, [fy, fz, 0.0, 0.0])
    assume(alloc.scale_a < 1.0)
    fa = alloc.forces(v)[:2]
    demand = np.array([fy, fz])
    cross = fa[0] * demand[1] - fa[1] * demand[0]
    assert abs(cross) <= 1e-9 * np.linalg.norm(fa) * np.linalg.norm(demand), "force turned"
    assert fa @ demand > 0 and np.linalg.norm(fa) < np.linalg.norm(demand)
    np.testing.assert_allclose(np.linalg.norm(fa), alloc.scale_a * np.linalg.norm(demand), rtol=1e-9)
    assert min(v[:3]) == act.min_voltage_v or math.isclose(min(v[:3]), act.min_voltage_v, abs_tol=1e-9)
    assert math.isclose(max(v[:3]), act.max_voltage_v, abs_tol=1e-9)


@settings(max_examples=200)
@given(act=actuators, fy=force, fz=force)
def test_common_mode_centres_the_voltages_in_the_range(act, fy, fz):
    """As far from both limits as possible: equal margins to min and max."""
    _, v = _allocate(act, [fy, fz, fy, fz])
    for support in (v[:3], v[3:]):
        below, above = support.min() - act.min_voltage_v, act.max_voltage_v - support.max()
        assert math.isclose(below, above, abs_tol=1e-9 * (act.max_voltage_v - act.min_voltage_v))


def test_zero_force_puts_every_stack_mid_range_and_non_finite_demand_gives_no_force():
    act = Actuators(force_constant=2.5, bias_voltage=75.0, min_voltage_v=0.0, max_voltage_v=150.0,
                    orientation_deg=(90.0, 90.0))
    alloc, v = _allocate(act, [0.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(v, 75.0)
    alloc, v = _allocate(act, [math.nan, 1.0, math.inf, 2.0])
    np.testing.assert_array_equal(v, 75.0)
    assert alloc.scale_a == 0.0 and alloc.scale_b == 0.0


def test_a_stack_pointing_along_the_force_takes_the_largest_voltage():
    """Stack 1 at +y: a +y force raises stack 1 and lowers the other two equally."""
    act = Actuators(force_constant=2.0, bias_voltage=75.0, min_voltage_v=0.0, max_voltage_v=150.0,
                    orientation_deg=(0.0, 0.0))
    _, v = _allocate(act, [60.0, 0.0, 0.0, 0.0])
    # f = 2/3 e.F = (40, -20, -20) N -> (20, -10, -10) V around the centre
    np.testing.assert_allclose(v[:3], [75.0 + 15.0, 75.0 - 15.0, 75.0 - 15.0], atol=1e-12)


def test_a_force_that_needs_exactly_the_whole_range_is_reachable():
    """100 N along stack 1 at 1 N/V needs stack forces (66.7, -33.3, -33.3) N: a spread of
    exactly the 100 V span, which rounding makes 100 V + 1 ulp. It is reproduced exactly, so
    it must not be reported as saturated (scale 1 - eps would hold the integrator)."""
    act = Actuators(force_constant=1.0, bias_voltage=50.0, min_voltage_v=0.0, max_voltage_v=100.0,
                    orientation_deg=(0.0, 0.0))
    alloc, v = _allocate(act, [100.0, 0.0, 0.0, 0.0])
    assert alloc.scale_a == 1.0, f"scale {alloc.scale_a!r} for a force inside the range"
    assert np.all((v >= 0.0) & (v <= 100.0)), v
    np.testing.assert_allclose(alloc.forces(v)[:2], [100.0, 0.0], atol=1e-9)
