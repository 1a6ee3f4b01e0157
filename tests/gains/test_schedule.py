"""Gain schedule: the matrices it reports (``matrices_at``, what the closed-loop checks analyse)
interpolated exactly, the paper's next grid point, edges held. The schedule keeps no running
state: the engine runs the load filter, the switching and the products on its blocks, and
tests/rt/test_schedule_engine.py checks them against these matrices."""

from dataclasses import replace

import numpy as np
import pytest

from beamctl.gains.build import build_table
from beamctl.gains.compensator import MATRICES
from beamctl.gains.schedule import GainSchedule


@pytest.fixture(scope="module")
def table(paper_model):
    return build_table(paper_model, [0.0, 500.0, 1000.0, 1500.0, 2000.0], check=False)


def _schedule(table, **settings):
    return GainSchedule.from_table(replace(table, schedule=replace(table.schedule, **settings)))


def _assert_matrices(point, expected, rtol=0.0, what=""):
    for m in MATRICES:
        np.testing.assert_allclose(getattr(point, m), getattr(expected, m), rtol=rtol, atol=0,
                                   err_msg=f"{m} {what}")


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


@pytest.mark.parametrize("mode", ["interpolate", "paper"])
def test_outside_the_grid_the_edge_matrices_are_held(table, mode):
    """Nothing is extrapolated: beyond either end the edge point's matrices."""
    s = _schedule(table, mode=mode)
    comp = table.compensator
    _assert_matrices(s.matrices_at(2600.0), comp.point(len(table.loads_n) - 1))
    _assert_matrices(s.matrices_at(-50.0), comp.point(0))


def test_paper_mode_uses_the_matrices_of_the_next_grid_point(table):
    """The operator switched on to the next gain as the load passed each grid point."""
    s = _schedule(table, mode="paper")
    comp = table.compensator
    _assert_matrices(s.matrices_at(1400.0), comp.point(3))
    _assert_matrices(s.matrices_at(1500.0), comp.point(3))
    _assert_matrices(s.matrices_at(1501.0), comp.point(4))


def test_matrices_at_returns_arrays_of_its_own(table):
    """At a grid point too: changing what it returns leaves the table's compensator alone."""
    s = GainSchedule.from_table(table)
    point = s.matrices_at(1000.0)
    point.c[...] = 0.0
    assert np.any(table.compensator.c[2] != 0.0)
    _assert_matrices(s.matrices_at(1000.0), table.compensator.point(2))
