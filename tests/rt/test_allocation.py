"""Allocation of the lateral force to three stacks at 120 deg (property-based): ``scale`` keeps
the direction of a force it cannot give, ``clip`` (the paper's) clips each stack on its own."""

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from beamctl.rt.allocation import Allocator
from beamctl.rt.config import ALLOCATION_MODES, Actuators

any_float = st.floats(allow_nan=True, allow_infinity=True, width=64)
force = st.floats(min_value=-1e4, max_value=1e4, allow_nan=False)
actuators = st.builds(
    Actuators,
    force_constant_n_per_v=st.floats(min_value=0.05, max_value=50.0),
    bias_voltage_v=st.just(75.0),
    min_voltage_v=st.floats(min_value=-30.0, max_value=20.0),
    max_voltage_v=st.floats(min_value=100.0, max_value=150.0),
    orientation_deg=st.tuples(st.floats(min_value=-360, max_value=360),
                              st.floats(min_value=-360, max_value=360)),
)


def _allocate(act, u, mode="scale"):
    alloc = Allocator(act, mode)
    v = np.full(6, np.nan)
    alloc.allocate(np.asarray(u, dtype=float), v)
    return alloc, v


@pytest.mark.parametrize("mode", ALLOCATION_MODES)
@settings(max_examples=400)
@given(act=actuators, u=st.lists(any_float, min_size=4, max_size=4))
def test_no_voltage_ever_leaves_the_range(mode, act, u):
    _, v = _allocate(act, u, mode)
    assert np.all(np.isfinite(v)), f"non-finite voltage {v} for demand {u} ({mode})"
    assert np.all(v >= act.min_voltage_v) and np.all(v <= act.max_voltage_v), (v, u, mode)


@pytest.mark.parametrize("mode", ALLOCATION_MODES)
@settings(max_examples=300)
@given(act=actuators, fy=force, fz=force)
def test_reachable_forces_are_reproduced_exactly(mode, act, fy, fz):
    alloc, v = _allocate(act, [fy, fz, -fz, fy], mode)
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
    act = Actuators(force_constant_n_per_v=2.5, bias_voltage_v=75.0, min_voltage_v=0.0, max_voltage_v=150.0,
                    orientation_deg=(90.0, 90.0))
    alloc, v = _allocate(act, [0.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(v, 75.0)
    alloc, v = _allocate(act, [math.nan, 1.0, math.inf, 2.0])
    np.testing.assert_array_equal(v, 75.0)
    assert alloc.scale_a == 0.0 and alloc.scale_b == 0.0


def test_a_stack_pointing_along_the_force_takes_the_largest_voltage():
    """Stack 1 at +y: a +y force raises stack 1 and lowers the other two equally."""
    act = Actuators(force_constant_n_per_v=2.0, bias_voltage_v=75.0, min_voltage_v=0.0, max_voltage_v=150.0,
                    orientation_deg=(0.0, 0.0))
    _, v = _allocate(act, [60.0, 0.0, 0.0, 0.0])
    # f = 2/3 e.F = (40, -20, -20) N -> (20, -10, -10) V around the centre
    np.testing.assert_allclose(v[:3], [75.0 + 15.0, 75.0 - 15.0, 75.0 - 15.0], atol=1e-12)


def test_a_force_that_needs_exactly_the_whole_range_is_reachable():
    """100 N along stack 1 at 1 N/V needs stack forces (66.7, -33.3, -33.3) N: a spread of
    exactly the 100 V span, which rounding makes 100 V + 1 ulp. It is reproduced exactly, so
    it must not be reported as saturated (scale 1 - eps would hold the integrator)."""
    act = Actuators(force_constant_n_per_v=1.0, bias_voltage_v=50.0, min_voltage_v=0.0, max_voltage_v=100.0,
                    orientation_deg=(0.0, 0.0))
    alloc, v = _allocate(act, [100.0, 0.0, 0.0, 0.0])
    assert alloc.scale_a == 1.0, f"scale {alloc.scale_a!r} for a force inside the range"
    assert np.all((v >= 0.0) & (v <= 100.0)), v
    np.testing.assert_allclose(alloc.forces(v)[:2], [100.0, 0.0], atol=1e-9)


# -- clip: the paper's per-stack clipping ---------------------------------------------------------

def _stack_axes(orientation_deg: float) -> np.ndarray:
    return np.array([[math.cos(math.radians(orientation_deg + 120.0 * i)),
                      math.sin(math.radians(orientation_deg + 120.0 * i))] for i in range(3)])


def _angle_deg(f: np.ndarray) -> float:
    return math.degrees(math.atan2(f[1], f[0]))


@st.composite
def one_stack_clipped(draw):
    """Stacks, and a force at least 2 deg off every stack's axis (the axes and their opposites
    lie every 60 deg from stack 1: by symmetry, clipping cannot turn a force along an axis) and
    of a size between the ones at which the first and the second stack reach a limit."""
    act = draw(actuators)
    t1 = act.orientation_deg[0]
    theta = t1 + 60.0 * draw(st.integers(0, 5)) + draw(st.floats(2.0, 58.0))
    share = (2.0 / 3.0 * np.cos(np.radians(theta - t1 - 120.0 * np.arange(3)))
             / act.force_constant_n_per_v)  # V per N
    room = np.where(share > 0, act.max_voltage_v - act.bias_voltage_v, act.min_voltage_v - act.bias_voltage_v)
    first, second = np.sort(room / share)[:2]
    size = first + draw(st.floats(0.01, 0.99)) * (second - first)
    return act, size * math.cos(math.radians(theta)), size * math.sin(math.radians(theta))


@settings(max_examples=300)
@given(case=one_stack_clipped())
def test_clip_turns_a_force_when_one_stack_reaches_its_limit_and_scale_keeps_it(case):
    """A stack at its limit gives less than its share and the others still give theirs: the
    force turns away from the clipped stack. The reported fraction is the force delivered along
    the demand, F_applied . F / |F|^2. ``scale`` keeps the direction of the same demand."""
    act, fy, fz = case
    alloc, v = _allocate(act, [fy, fz, 0.0, 0.0], "clip")
    at_limit = (v[:3] == act.min_voltage_v) | (v[:3] == act.max_voltage_v)
    assert at_limit.sum() == 1 and alloc.scale_a < 1.0, (v, alloc.scale_a)
    demand, applied = np.array([fy, fz]), alloc.forces(v)[:2]
    turn = abs(_angle_deg(applied) - _angle_deg(demand))
    turn = min(turn, 360.0 - turn)
    assert turn > 1e-6, f"a clipped stack left the force's direction unchanged ({applied} for {demand})"
    np.testing.assert_allclose(alloc.scale_a, applied @ demand / (demand @ demand), rtol=1e-9)
    scale, v = _allocate(act, [fy, fz, 0.0, 0.0], "scale")
    kept = scale.forces(v)[:2]
    assert abs(kept[0] * fz - kept[1] * fy) <= 1e-9 * np.linalg.norm(kept) * np.linalg.norm(demand), (
        f"scale turned the force: {kept} for {demand}")


def test_the_paper_s_rig_clips_the_stack_nearest_the_force_and_the_force_turns_away_from_it():
    """Stacks at 90, 210 and 330 deg, 3 N/V, 75 V bias: 400 N at 230 deg (20 deg off stack 2)
    asks stack 2 for 75 + 2/3 * 400 cos(20 deg) / 3 = 158.5 V. Clipped at 150 V it gives
    8.5 V * 3 N/V = 25.4 N less than its share along 210 deg; stacks 1 and 3 still give theirs
    (6.9 V and 59.6 V), so the force turns away from 210 deg by 1.3 deg, to 231.3 deg."""
    act = Actuators(force_constant_n_per_v=3.0, bias_voltage_v=75.0, min_voltage_v=0.0, max_voltage_v=150.0,
                    orientation_deg=(90.0, 90.0))
    demand = 400.0 * np.array([math.cos(math.radians(230.0)), math.sin(math.radians(230.0))])
    clip, v = _allocate(act, [*demand, 0.0, 0.0], "clip")
    np.testing.assert_allclose(v[:3], [6.9, 150.0, 59.6], atol=0.05)
    shortfall = (75.0 + 2.0 / 3.0 * 400.0 * math.cos(math.radians(20.0)) / 3.0 - 150.0) * 3.0
    expected = demand - shortfall * np.array([math.cos(math.radians(210.0)), math.sin(math.radians(210.0))])
    np.testing.assert_allclose(clip.forces(v)[:2], expected, atol=1e-9)
    assert _angle_deg(expected) % 360.0 == pytest.approx(231.3, abs=0.05), "turned away from stack 2"
    scale, v = _allocate(act, [*demand, 0.0, 0.0], "scale")
    # scale: the spread 158.5 - 6.9 = 151.6 V exceeds the 150 V span; 150/151.6 of the force, at 230 deg
    np.testing.assert_allclose(scale.forces(v)[:2], demand * scale.scale_a, atol=1e-9)
    assert scale.scale_a == pytest.approx(150.0 / 151.6, abs=1e-3)


def test_clip_gives_no_force_for_a_non_finite_demand():
    act = Actuators(force_constant_n_per_v=2.5, bias_voltage_v=70.0, min_voltage_v=0.0, max_voltage_v=150.0,
                    orientation_deg=(90.0, 90.0))
    alloc, v = _allocate(act, [math.nan, 1.0, math.inf, 2.0], "clip")
    np.testing.assert_array_equal(v, 70.0)
    assert alloc.scale_a == 0.0 and alloc.scale_b == 0.0
    alloc, v = _allocate(act, [1e300, 1e300, 0.0, 0.0], "clip")
    np.testing.assert_array_equal(v[:3], 70.0, "a demand that overflows is no demand")


def test_an_unknown_mode_is_refused():
    act = Actuators(force_constant_n_per_v=2.5, bias_voltage_v=75.0, min_voltage_v=0.0, max_voltage_v=150.0,
                    orientation_deg=(90.0, 90.0))
    with pytest.raises(ValueError, match="'spread'.*scale, clip"):
        Allocator(act, "spread")
