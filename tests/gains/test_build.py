"""Building a table: the closed-loop check covers every gain where the schedule can run it."""

import numpy as np
import pytest

from beamctl.gains.build import build_table, check_load, check_plan, check_points
from beamctl.gains.compensator import MATRICES
from beamctl.gains.schedule import GainSchedule


@pytest.fixture(scope="module")
def paper_table(paper_model):
    return build_table(paper_model, [0.0, 500.0, 1000.0, 1500.0], mode="paper")


def test_paper_switching_is_checked_at_the_ends_of_each_gain_s_hysteresis_band(paper_table):
    """Rising, gain i stays on up to L_i + h/2; falling, down to L_(i-1) - h/2: there the loop
    runs a gain the settled schedule never shows at that load, so the check must look."""
    edges = {(c.load_n, c.gain_load_n) for c in paper_table.checks if c.gain_load_n is not None}
    assert edges == {(25.0, 0.0), (525.0, 500.0), (1025.0, 1000.0),
                     (475.0, 1000.0), (975.0, 1500.0)}, sorted(edges)
    settled = [c.load_n for c in paper_table.checks if c.gain_load_n is None]
    assert settled == check_points(paper_table.loads_n)
    assert paper_table.all_stable and not paper_table.forced


def test_each_check_uses_the_matrices_it_names(paper_model, paper_table):
    """Where the schedule settles, the check takes the schedule's own matrices_at; at a band
    end, the matrices of the grid point it names."""
    schedule = GainSchedule.from_table(paper_table)
    for load, gain_load, point in check_plan(paper_table):
        expected = (schedule.matrices_at(load) if gain_load is None
                    else paper_table.compensator.point(list(paper_table.loads_n).index(gain_load)))
        for m in MATRICES:
            np.testing.assert_array_equal(getattr(point, m), getattr(expected, m),
                                          err_msg=f"{m} of the check at {load} N")
    c = next(c for c in paper_table.checks if c.gain_load_n == 500.0)
    direct = check_load(paper_model, c.load_n, paper_table.compensator.point(1), paper_table)
    assert c.spectral_radius == direct.spectral_radius


def test_an_interpolated_table_is_checked_at_points_and_midpoints_only(paper_model):
    table = build_table(paper_model, [0.0, 1000.0, 2000.0])
    assert [c.load_n for c in table.checks] == check_points(table.loads_n)
    assert all(c.gain_load_n is None for c in table.checks)


def test_force_marks_only_a_table_written_in_spite_of_an_unstable_point(paper_model):
    """`--force` on a grid that turns out stable gives an ordinary table the service runs."""
    assert not build_table(paper_model, [0.0, 1000.0], force=True).forced
    unstable = build_table(paper_model, [4000.0, 4500.0], force=True)
    assert unstable.forced and not unstable.all_stable
