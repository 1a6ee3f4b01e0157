"""Gain schedule: interpolation, the paper's switching with hysteresis, edges, and products
that are the matrices it reports."""

from dataclasses import replace

import numpy as np
import pytest

from beamctl.gains.build import build_table
from beamctl.gains.compensator import MATRICES, Compensator
from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import ScheduleSettings


@pytest.fixture(scope="module")
def table(paper_model):
    return build_table(paper_model, [0.0, 500.0, 1000.0, 1500.0, 2000.0], check=False)


def _schedule(table, **settings):
    return GainSchedule.from_table(replace(table, schedule=replace(table.schedule, **settings)))


def _assert_matrices(point, expected, rtol=0.0, what=""):
    for m in MATRICES:
        np.testing.assert_allclose(getattr(point, m), getattr(expected, m), rtol=rtol, atol=0,
                                   err_msg=f"{m} {what}")


def _products(s, n, rng):
    """The three products at the schedule's current load for random signals."""
    signals = rng.standard_normal(12 + n)
    dxi = rng.standard_normal(4)
    u, x_c, du = np.zeros(4), np.zeros(n), np.zeros(4)
    s.output(signals, u)
    s.update(signals, x_c)
    s.integral_effect(dxi, du)
    return signals, dxi, u, x_c, du


def test_interpolation_is_exact_at_grid_points_and_linear_between(table):
    s = GainSchedule.from_table(table)
    comp = table.compensator
    for i, load in enumerate(table.loads_n):
        _assert_matrices(s.matrices_at(load), comp.point(i), what=f"at {load} N")
    mid = comp.point(1), comp.point(2)
    _assert_matrices(s.matrices_at(750.0), type(mid[0])(*(0.5 * (getattr(mid[0], m) + getattr(mid[1], m))
                                                           for m in MATRICES)), rtol=1e-12)
    p2, p3 = comp.point(2), comp.point(3)
    _assert_matrices(s.matrices_at(1100.0), type(p2)(*(0.8 * getattr(p2, m) + 0.2 * getattr(p3, m)
                                                       for m in MATRICES)), rtol=1e-12)
    # the paper's design: K interpolates like the matrices (they are linear in K)
    np.testing.assert_allclose(s.matrices_at(1100.0).ki, (0.8 * table.gains[2] + 0.2 * table.gains[3])[:, 8:],
                               rtol=1e-12)
    assert not s.out_of_range


@pytest.mark.parametrize("mode", ["interpolate", "paper"])
def test_the_products_are_the_matrices_the_schedule_reports(table, mode):
    """What the step computes, (M_i + offset S_i) s without forming the matrices, equals
    matrices_at(filtered load) applied to the signals: the check analyses what the step runs."""
    s = _schedule(table, mode=mode)
    rng = np.random.default_rng(2)
    s.reset(100.0)
    n = s.n_states
    for load in np.linspace(100.0, 1900.0, 400) + 20.0 * rng.standard_normal(400):
        s.follow(load)
        signals, dxi, u, x_c, du = _products(s, n, rng)
        if mode == "paper":      # switched with hysteresis: the grid point in use
            point = table.compensator.point(s.index)
        else:
            point = s.matrices_at(s.filtered_load_n)
        y, xi, applied, xc = signals[:4], signals[4:8], signals[8:12], signals[12:]
        _assert_product(u, [(-point.c, xc), (-point.d, y), (-point.ki, xi)])
        _assert_product(x_c, [(point.a, xc), (point.b, y), (point.e, applied)])
        _assert_product(du, [(-point.ki, dxi)])


def _assert_product(actual, terms):
    """actual == sum of matrix @ vector to rounding: within 1e-12 of the sum of the terms'
    magnitudes (the gains span ten decades, so the sum cancels)."""
    expected = sum(m @ v for m, v in terms)
    scale = sum(np.abs(m) @ np.abs(v) for m, v in terms)
    assert np.all(np.abs(actual - expected) <= 1e-12 * scale), (actual, expected)


@pytest.mark.parametrize("mode", ["interpolate", "paper"])
def test_outside_the_grid_the_edge_matrices_are_held_and_flagged(table, mode):
    s = _schedule(table, mode=mode)
    comp = table.compensator
    _assert_matrices(s.matrices_at(2600.0), comp.point(len(table.loads_n) - 1))
    _assert_matrices(s.matrices_at(-50.0), comp.point(0))
    rng = np.random.default_rng(0)
    for load, edge in ((2600.0, comp.point(len(table.loads_n) - 1)), (-50.0, comp.point(0))):
        s.reset(load)
        s.follow(load)
        assert s.out_of_range
        signals, _, u, _, _ = _products(s, s.n_states, rng)
        _assert_product(u, [(-edge.c, signals[12:]), (-edge.d, signals[:4]), (-edge.ki, signals[4:8])])


def test_load_cell_value_is_low_pass_filtered(table):
    """First order at 5 Hz: after one time constant 63 % of a step."""
    s = GainSchedule.from_table(table)
    s.reset(1000.0)
    rate = table.design.sample_rate_hz
    tau_samples = int(round(rate / (2 * np.pi * table.schedule.load_filter_hz)))
    for _ in range(tau_samples):
        s.follow(2000.0)
    assert s.filtered_load_n == pytest.approx(1000.0 + 1000.0 * (1 - np.exp(-1)), abs=5.0)


def _switches(schedule, loads) -> int:
    indices = []
    for load in loads:
        schedule.follow(load)
        indices.append(schedule.index)
    return int(np.count_nonzero(np.diff(indices)))


@pytest.mark.parametrize(("hysteresis", "chatters"), [(50.0, False), (0.0, True)])
def test_paper_switching_does_not_chatter_on_a_noisy_load_cell(table, hysteresis, chatters):
    """A slow ramp through 1000 N with 30 N RMS load-cell noise: one switch with the 50 N
    band; without it the filtered noise flips between the gains."""
    s = _schedule(table, mode="paper", load_filter_hz=5.0, hysteresis_n=hysteresis)
    rng = np.random.default_rng(1)
    rate = table.design.sample_rate_hz
    ramp = np.linspace(900.0, 1100.0, int(10 * rate)) + 30.0 * rng.standard_normal(int(10 * rate))
    s.reset(900.0)
    n = _switches(s, ramp)
    if chatters:
        assert n > 1, "without hysteresis the noise should make the gain chatter"
    else:
        assert n == 1, f"{n} switches through one threshold"
        s.follow(1100.0)
        assert s.index == 3


def test_paper_mode_uses_the_matrices_of_the_next_grid_point(table):
    """The operator switched on to the next gain as the load passed each grid point."""
    s = _schedule(table, mode="paper")
    comp = table.compensator
    _assert_matrices(s.matrices_at(1400.0), comp.point(3))
    _assert_matrices(s.matrices_at(1500.0), comp.point(3))
    _assert_matrices(s.matrices_at(1501.0), comp.point(4))


def test_non_finite_load_keeps_the_previous_matrices_and_raises_the_flag(table):
    s = GainSchedule.from_table(table)
    s.reset(1234.0)
    s.follow(1234.0)
    rng = np.random.default_rng(4)
    signals = rng.standard_normal(12 + s.n_states)
    before, after = np.zeros(4), np.zeros(4)
    s.output(signals, before)
    for bad in (float("nan"), float("inf"), -float("inf")):
        s.follow(bad)
        s.output(signals, after)
        np.testing.assert_array_equal(after, before)
        assert s.out_of_range
    assert s.filtered_load_n == pytest.approx(1234.0)


def test_matrices_at_leaves_the_schedule_as_it_was(table):
    s = GainSchedule.from_table(table)
    s.reset(1234.0)
    index, load = s.index, s.filtered_load_n
    s.matrices_at(300.0)
    assert (s.index, s.filtered_load_n) == (index, load)


def test_paper_switching_loads_rising_and_falling():
    """Rising, the matrices of grid point i + 1 take over once the load passes L_i + h/2 (the
    operator switched on to the next gain as the load passed each point); falling, those of
    point i - 1 come back below L_(i-1) - h/2. Swept in 0.1 N steps with the load filter made
    transparent, each switch lies within one step of its load."""
    loads = [0.0, 500.0, 1000.0, 1500.0, 2000.0]
    level = np.arange(len(loads), dtype=float)[:, None, None]
    comp = Compensator(a=level * np.ones((5, 2, 2)), b=level * np.ones((5, 2, 4)),
                       e=np.zeros((5, 2, 4)), c=level * np.ones((5, 4, 2)), d=level * np.ones((5, 4, 4)),
                       ki=level * np.ones((5, 4, 4)), h=np.eye(4), start=np.zeros((2, 4)),
                       period_s=1 / 2500.0, plane_states={"y": [0], "z": [1]})
    s = GainSchedule(np.array(loads), comp, ScheduleSettings(mode="paper", load_filter_hz=1e12,
                                                              hysteresis_n=50.0))

    def switches(sweep):
        s.reset(sweep[0])
        found, index = [], s.index
        for load in sweep:
            s.follow(load)
            if s.index != index:
                found.append((round(load, 1), index, s.index))
                index = s.index
        return found

    up = switches(np.arange(0.0, 2000.05, 0.1))
    assert [(a, b) for _, a, b in up] == [(0, 1), (1, 2), (2, 3), (3, 4)], up
    step = 0.1 + 1e-6
    for load, i, _ in up:
        assert loads[i] + 25.0 < load <= loads[i] + 25.0 + step, f"switched up from {loads[i]} N at {load} N"
    down = switches(np.arange(2000.0, -0.05, -0.1))
    assert [(a, b) for _, a, b in down] == [(4, 3), (3, 2), (2, 1)], down
    for load, i, _ in down:
        assert loads[i - 1] - 25.0 - step <= load < loads[i - 1] - 25.0, (
            f"switched down from {loads[i]} N at {load} N")
    u = np.zeros(4)
    s.output(np.ones(14), u)       # point 1's matrices are all ones: u = -(2 + 4 + 4)
    assert s.index == 1
    np.testing.assert_array_equal(u, np.full(4, -10.0))
