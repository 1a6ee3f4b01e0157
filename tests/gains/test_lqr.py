"""Integral LQR (section 3.2) against python-control, an independent implementation."""

import numpy as np
import pytest

from beamctl.gains.defaults import DEFAULT_WEIGHTS
from beamctl.gains.lqr import augmented_system, lqr_gain

control = pytest.importorskip("control")


@pytest.mark.parametrize("load", [0.0, 1500.0, 3000.0, 3194.0, 3600.0, 4000.0])
def test_gain_equals_python_control_lqr_on_the_augmented_system(paper_reduced, load):
    k = lqr_gain(paper_reduced, load, DEFAULT_WEIGHTS)
    a, b = augmented_system(paper_reduced, load)
    q, r = DEFAULT_WEIGHTS.matrices()
    k_ref, _, _ = control.lqr(a, b, q, r)
    np.testing.assert_allclose(k, k_ref, rtol=1e-6, atol=1e-6 * np.abs(k_ref).max(),
                               err_msg=f"K_LQR at {load} N differs from python-control")


def test_gain_equals_python_control_integral_action_form(paper_reduced):
    """python-control's integral_action builds the same augmented system from the 8-state
    modal model and C = [I 0]."""
    load = 2500.0
    sys8 = control.ss(paper_reduced.system_matrix(load), paper_reduced.input_matrix,
                      np.hstack([np.eye(4), np.zeros((4, 4))]), 0)
    q, r = DEFAULT_WEIGHTS.matrices()
    k_ref, _, _ = control.lqr(sys8, q, r, integral_action=sys8.C)
    k = lqr_gain(paper_reduced, load, DEFAULT_WEIGHTS)
    np.testing.assert_allclose(k, k_ref, rtol=1e-6, atol=1e-6 * np.abs(k_ref).max())


@pytest.mark.parametrize("load", [0.0, 2000.0, 3500.0, 4000.0])
def test_continuous_closed_loop_of_the_design_model_is_stable(paper_reduced, load):
    """Including beyond the critical load, where the open loop diverges."""
    a, b = augmented_system(paper_reduced, load)
    k = lqr_gain(paper_reduced, load, DEFAULT_WEIGHTS)
    open_loop = np.linalg.eigvals(a).real.max()
    closed = np.linalg.eigvals(a - b @ k).real.max()
    assert closed < 0, f"closed loop at {load} N has an eigenvalue with real part {closed}"
    if load > paper_reduced.critical_load():
        assert open_loop > 0


def test_planes_do_not_couple_in_the_gain(paper_reduced):
    k = lqr_gain(paper_reduced, 3000.0, DEFAULT_WEIGHTS)
    y_rows, z_cols = [0, 2], [1, 3, 5, 7, 9, 11]
    assert np.abs(k[np.ix_(y_rows, z_cols)]).max() < 1e-8 * np.abs(k).max()
