"""Gain schedule K(Fx): interpolation, the paper's switching with hysteresis, edges."""

from dataclasses import replace

import numpy as np
import pytest

from beamctl.gains.build import build_table
from beamctl.gains.defaults import DEFAULT_DESIGN
from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import GainTable, ScheduleSettings


@pytest.fixture(scope="module")
def table(paper_model):
    return build_table(paper_model, [0.0, 500.0, 1000.0, 1500.0, 2000.0], check=False)


def test_interpolation_is_exact_at_grid_points_and_linear_between(table):
    s = GainSchedule(table)
    for i, load in enumerate(table.loads_n):
        np.testing.assert_array_equal(s.gain_at(load), table.gains[i])
    np.testing.assert_allclose(s.gain_at(750.0), 0.5 * (table.gains[1] + table.gains[2]), rtol=1e-12)
    np.testing.assert_allclose(s.gain_at(1100.0), 0.8 * table.gains[2] + 0.2 * table.gains[3],
                               rtol=1e-12)
    assert not s.out_of_range


@pytest.mark.parametrize("mode", ["interpolate", "paper"])
def test_outside_the_grid_the_edge_gain_is_held_and_flagged(table, mode):
    s = GainSchedule(replace(table, schedule=replace(table.schedule, mode=mode)))
    np.testing.assert_array_equal(s.gain_at(2600.0), table.gains[-1])
    assert s.out_of_range
    s.reset(-50.0)
    np.testing.assert_array_equal(s.update(-50.0), table.gains[0])
    assert s.out_of_range


def test_update_reuses_one_array(table):
    s = GainSchedule(table)
    first = s.update(700.0)
    assert s.update(900.0) is first


def test_load_cell_value_is_low_pass_filtered(table):
    """First order at 5 Hz: after one time constant 63 % of a step."""
    s = GainSchedule(table)
    s.reset(1000.0)
    rate = table.design.sample_rate_hz
    tau_samples = int(round(rate / (2 * np.pi * table.schedule.load_filter_hz)))
    for _ in range(tau_samples):
        s.update(2000.0)
    assert s.filtered_load_n == pytest.approx(1000.0 + 1000.0 * (1 - np.exp(-1)), abs=5.0)


def _switches(schedule, loads) -> int:
    indices = []
    for load in loads:
        schedule.update(load)
        indices.append(schedule.index)
    return int(np.count_nonzero(np.diff(indices)))


@pytest.mark.parametrize(("hysteresis", "chatters"), [(50.0, False), (0.0, True)])
def test_paper_switching_does_not_chatter_on_a_noisy_load_cell(table, hysteresis, chatters):
    """A slow ramp through 1000 N with 30 N RMS load-cell noise: one switch with the 50 N
    band; without it the filtered noise flips between the gains."""
    settings = ScheduleSettings(mode="paper", load_filter_hz=5.0, hysteresis_n=hysteresis)
    s = GainSchedule(replace(table, schedule=settings))
    rng = np.random.default_rng(1)
    rate = table.design.sample_rate_hz
    ramp = np.linspace(900.0, 1100.0, int(10 * rate)) + 30.0 * rng.standard_normal(int(10 * rate))
    s.reset(900.0)
    n = _switches(s, ramp)
    if chatters:
        assert n > 1, "without hysteresis the noise should make the gain chatter"
    else:
        assert n == 1, f"{n} switches through one threshold"
        np.testing.assert_array_equal(s.update(1100.0), table.gains[3])


def test_paper_mode_uses_the_gain_of_the_next_grid_point(table):
    """The operator switched on to the next gain as the load passed each grid point."""
    s = GainSchedule(replace(table, schedule=replace(table.schedule, mode="paper")))
    np.testing.assert_array_equal(s.gain_at(1400.0), table.gains[3])
    np.testing.assert_array_equal(s.gain_at(1500.0), table.gains[3])
    np.testing.assert_array_equal(s.gain_at(1501.0), table.gains[4])


def test_non_finite_load_keeps_the_previous_gain_and_raises_the_flag(table):
    s = GainSchedule(table)
    s.reset(1200.0)
    before = s.update(1200.0).copy()
    for bad in (float("nan"), float("inf"), -float("inf")):
        np.testing.assert_array_equal(s.update(bad), before)
        assert s.out_of_range
    assert s.filtered_load_n == pytest.approx(1200.0)


def test_paper_switching_loads_rising_and_falling():
    """Rising, the gain of grid point i + 1 takes over once the load passes L_i + h/2 (the
    operator switched on to the next gain as the load passed each point); falling, the gain of
    point i - 1 comes back below L_(i-1) - h/2. Swept in 0.1 N steps with the load filter made
    transparent, each switch lies within one step of its load."""
    loads = [0.0, 500.0, 1000.0, 1500.0, 2000.0]
    gains = np.arange(len(loads), dtype=float)[:, None, None] * np.ones((len(loads), 4, 12))
    table = GainTable(
        loads_n=np.array(loads), gains=gains, c0_phi_inv=np.eye(4), design=DEFAULT_DESIGN,
        schedule=ScheduleSettings(mode="paper", load_filter_hz=1e12, hysteresis_n=50.0),
        model_parameters=None)
    s = GainSchedule(table)

    def switches(sweep):
        s.reset(sweep[0])
        found, index = [], s.index
        for load in sweep:
            s.update(load)
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
