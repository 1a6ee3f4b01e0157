"""The compensator form: the shipped table's matrices, plane by plane."""

import numpy as np
import pytest

from beamctl.gains.build import integral_lqr_compensator
from beamctl.gains.compensator import MATRICES, PLANE_CHANNELS
from beamctl.gains.defaults import paper_table_path
from beamctl.gains.discrete import velocity_filter
from beamctl.gains.table import load_table
from tests.rounding import EPS, assert_within, product_rounding


@pytest.fixture(scope="module")
def table():
    return load_table(paper_table_path())


def test_the_z_plane_block_of_the_compensator_equals_its_y_plane_block(table):
    """At every grid point the compensator acts on the z plane (its states, gauges and forces)
    as on the y plane, to rounding, and the two planes do not couple: with the plants' equal
    spectra (tests/gains/test_closedloop.py), checking the y plane's loop checks both."""
    comp = table.compensator
    ys, zs = comp.plane_states["y"], comp.plane_states["z"]
    yio, zio = list(PLANE_CHANNELS["y"]), list(PLANE_CHANNELS["z"])
    for i, load in enumerate(table.loads_n):
        point = comp.point(i)
        y, z = point.plane(ys, "y"), point.plane(zs, "z")
        for m in MATRICES:
            a, b = getattr(y, m), getattr(z, m)
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-12 * max(np.abs(a).max(), 1e-300),
                                       err_msg=f"{m} at {load:g} N: the planes differ")
        assert not np.any(point.a[np.ix_(ys, zs)]) and not np.any(point.a[np.ix_(zs, ys)])
        for m, rows, cols in (("b", ys, zio), ("b", zs, yio), ("e", ys, zio), ("e", zs, yio),
                              ("c", yio, zs), ("c", zio, ys), ("d", yio, zio), ("d", zio, yio),
                              ("ki", yio, zio), ("ki", zio, yio)):
            assert not np.any(getattr(point, m)[np.ix_(rows, cols)]), f"{m} couples the planes at {load:g} N"
    np.testing.assert_array_equal(comp.h[np.ix_(zio, zio)], comp.h[np.ix_(yio, yio)])
    assert not np.any(comp.h[np.ix_(yio, zio)]) and not np.any(comp.h[np.ix_(zio, yio)])


def test_the_shipped_compensator_is_the_paper_s_controller_of_its_gains(table):
    """The table's design information (K, the velocity filter) and the matrices the step runs
    agree: the compensator is from_integral_lqr of K. Every matrix but D is a copy or an
    elementwise product of K, (C0 Phi)^-1 and the filter's coefficients, the same on every CPU;
    D = (Kq + scale b0 Kv) Ti is a matrix product, summed in the order of the BLAS kernel the CPU
    selects (and of the one the table was built with): equal to two products' rounding."""
    again = integral_lqr_compensator(table.gains, table.c0_phi_inv, table.design)
    for m in (*MATRICES, "h", "start"):
        if m != "d":
            np.testing.assert_array_equal(getattr(table.compensator, m), getattr(again, m), err_msg=m)
    filt = velocity_filter(table.design.velocity_cutoff_hz, table.design.sample_rate_hz)
    kq, kv = table.gains[:, :, 0:4], table.gains[:, :, 4:8]
    # the sum Kq + scale b0 Kv rounds once more before the product: one more unit of |Kq| + |s b0 Kv|
    terms = np.abs(kq) + np.abs(filt.scale * filt.b0 * kv)
    bound = product_rounding(terms, table.c0_phi_inv) + 2 * EPS * terms @ np.abs(table.c0_phi_inv)
    assert_within(table.compensator.d, again.d, bound, "D of the shipped table and of its gains")
    assert again.plane_states == table.compensator.plane_states
