"""The FE model of section 2.1 against the paper and against beam theory."""

import numpy as np
import pytest
import scipy.linalg as sla

from beamctl.models import critical_load, eigenfrequencies, fe_frequency_response, state_space
from beamctl.models.analysis import buckling_mode, eigenvalues
from beamctl.models.fe import (
    DOF_PER_NODE,
    PHI_Y,
    PHI_Z,
    V,
    W,
    assemble,
    dof,
    element_matrices,
    plane_indices,
)
from tests.rounding import assert_within, eigenvalue_rounding, symmetric_pencil

E_AL, R_B, L_B = 75.8e9, 4.0e-3, 0.400
EI = E_AL * np.pi * R_B**4 / 4


def test_critical_load_of_the_paper_beam_is_3194_N(paper_model):
    fcr = critical_load(paper_model)
    assert abs(fcr - 3194.0) <= 3.0, f"critical load {fcr:.1f} N, paper (eq. 12): 3194 N"


def test_eigenfrequencies_at_2000_N_are_the_paper_s_123_6_and_466_2_Hz(paper_model):
    f = eigenfrequencies(paper_model, 2000.0, 2)
    assert abs(f[0] - 123.6) <= 0.5, f"f1 = {f[0]:.2f} Hz at 2000 N, expected 123.6 +- 0.5 Hz"
    assert abs(f[1] - 466.2) <= 0.5, f"f2 = {f[1]:.2f} Hz at 2000 N, expected 466.2 +- 0.5 Hz"


@pytest.mark.parametrize("load", [0.0, 1000.0, 2000.0, 3000.0])
def test_circular_section_has_identical_y_and_z_frequencies(paper_model, load):
    fy = eigenfrequencies(paper_model, load, 4, "y")
    fz = eigenfrequencies(paper_model, load, 4, "z")
    # to what a symmetric eigensolver guarantees of each plane's eigenvalue (eps lambda_max /
    # lambda), halved for a frequency, twice for two solves
    idx = plane_indices(paper_model.n_nodes, "y")
    k = paper_model.load_stiffness(load)
    lam = symmetric_pencil(k[np.ix_(idx, idx)], paper_model.mass[np.ix_(idx, idx)])
    assert_within(fz, fy, eigenvalue_rounding(lam)[:4] * fy, f"y and z frequencies at {load} N")
    # and the full 4N problem has each of them twice
    lam = sla.eigh(paper_model.load_stiffness(load), paper_model.mass, eigvals_only=True,
                   subset_by_index=[0, 7])
    np.testing.assert_allclose(np.sqrt(lam[::2]) / (2 * np.pi), fy, rtol=1e-6)
    np.testing.assert_allclose(np.sqrt(lam[1::2]) / (2 * np.pi), fy, rtol=1e-6)
    assert critical_load(paper_model, "z") == pytest.approx(critical_load(paper_model, "y"), rel=1e-10)


def test_geometric_element_stiffness_is_eq_1():
    l = 0.0125
    _, _, kg = element_matrices(l, 1.0, 1.0)
    first_two_rows = np.array([
        [6 / 5, 0, 0, l / 10, -6 / 5, 0, 0, l / 10],
        [0, 6 / 5, -l / 10, 0, 0, -6 / 5, -l / 10, 0],
    ]) / l
    np.testing.assert_allclose(kg[:2], first_two_rows, atol=1e-12)
    assert kg[2, 2] == pytest.approx(2 / 15 * l) and kg[2, 6] == pytest.approx(-l / 30)
    np.testing.assert_allclose(kg, kg.T)


def test_element_stiffness_has_exactly_the_rigid_body_modes_and_mass_is_conserved():
    l, mu = 0.0125, 2789.0 * np.pi * R_B**2
    m, ke, _ = element_matrices(l, EI, mu)
    # two rigid motions per plane (translation, rotation) cost no strain energy
    assert np.sum(np.abs(np.linalg.eigvalsh(ke)) < 1e-9 * np.abs(ke).max()) == 4
    translate_y = np.zeros(8)
    translate_y[[V, DOF_PER_NODE + V]] = 1.0
    assert translate_y @ m @ translate_y == pytest.approx(mu * l, rel=1e-12)
    # rigid rotation about z: v = x, phi_z = +1
    rotate_z = np.zeros(8)
    rotate_z[[PHI_Z, DOF_PER_NODE + V, DOF_PER_NODE + PHI_Z]] = [1.0, l, 1.0]
    assert rotate_z @ ke @ rotate_z == pytest.approx(0.0, abs=1e-9 * EI / l)
    # about y with the paper's sign convention: w = x means phi_y = -1
    rotate_y = np.zeros(8)
    rotate_y[[PHI_Y, DOF_PER_NODE + W, DOF_PER_NODE + PHI_Y]] = [-1.0, l, -1.0]
    assert rotate_y @ ke @ rotate_y == pytest.approx(0.0, abs=1e-9 * EI / l)


def test_total_mass_of_beam_and_extensions(paper_model):
    p = paper_model.params
    expected = (p.beam.density * np.pi * p.beam.radius**2 * p.beam.length
                + 2 * p.extension.density * np.pi * p.extension.radius**2 * p.extension.length)
    for lateral in (V, W):
        u = np.zeros(paper_model.n_dof)
        u[lateral::DOF_PER_NODE] = 1.0
        assert u @ paper_model.mass @ u == pytest.approx(expected, rel=1e-12)


def _uniform_beam_critical_load(elements: int, clamped: bool) -> float:
    """Critical load of a uniform beam without extensions, supports by removing DOFs."""
    x = np.linspace(0.0, L_B, elements + 1)
    _, ke, kg = assemble(x, np.full(elements, EI), np.full(elements, 1.0))
    last = elements
    fixed = [dof(n, d) for n in (0, last) for d in (V, W)]
    if clamped:
        fixed += [dof(n, d) for n in (0, last) for d in (PHI_Y, PHI_Z)]
    free = np.intersect1d(np.setdiff1d(np.arange(ke.shape[0]), fixed), plane_indices(elements + 1, "y"))
    mu = sla.eigh(kg[np.ix_(free, free)], ke[np.ix_(free, free)], eigvals_only=True)
    return 1.0 / mu.max()


@pytest.mark.parametrize(("clamped", "factor"), [(False, 1.0), (True, 4.0)])
def test_uniform_beam_converges_to_euler_buckling_load(clamped, factor):
    exact = factor * np.pi**2 * EI / L_B**2
    errors = [_uniform_beam_critical_load(n, clamped) / exact - 1 for n in (4, 8, 16, 32)]
    case = "clamped-clamped" if clamped else "pinned-pinned"
    assert all(e > 0 for e in errors), f"{case}: FE buckling loads must approach from above: {errors}"
    assert all(b < a for a, b in zip(errors, errors[1:], strict=False)), f"{case}: not converging: {errors}"
    assert errors[-1] < 1e-4, f"{case}: {errors[-1]:.2e} relative error with 32 elements"


def test_first_frequency_falls_monotonically_with_load_and_vanishes_at_buckling(paper_model):
    fcr = critical_load(paper_model)
    loads = np.linspace(0.0, 0.999 * fcr, 60)
    f1 = np.array([eigenfrequencies(paper_model, f, 1)[0] for f in loads])
    assert np.all(np.diff(f1) < 0), "f1 must decrease with every load step"
    assert f1[-1] > 0
    f_at_fcr = np.sqrt(abs(eigenvalues(paper_model, fcr, 1)[0])) / (2 * np.pi)
    assert f_at_fcr < 0.1, f"f1 = {f_at_fcr:.3f} Hz at the critical load, expected 0"
    assert eigenfrequencies(paper_model, 1.01 * fcr, 1)[0] == 0.0
    assert eigenvalues(paper_model, 1.01 * fcr, 1)[0] < 0, "beyond Fx,cr the beam diverges"


def test_buckling_mode_is_a_nontrivial_solution_of_eq_12(paper_model):
    fcr, mode = buckling_mode(paper_model, "y")
    residual = paper_model.load_stiffness(fcr) @ mode
    assert np.linalg.norm(residual) < 1e-8 * np.linalg.norm(paper_model.elastic_stiffness @ mode)
    v = mode[paper_model.beam_nodes * DOF_PER_NODE + V]
    assert v.max() == pytest.approx(1.0) and np.all(v > 0), "first buckling mode: one half-wave"


def test_strain_output_is_minus_radius_times_curvature(paper_model):
    """A parabola v = c x^2 is represented exactly by cubic elements: eps = -rb 2c."""
    c = 0.01
    x = paper_model.node_x
    r = np.zeros(paper_model.n_dof)
    r[V::DOF_PER_NODE], r[PHI_Z::DOF_PER_NODE] = c * x**2, 2 * c * x
    r[W::DOF_PER_NODE], r[PHI_Y::DOF_PER_NODE] = -c * x**2, 2 * c * x  # phi_y = -w'
    eps = paper_model.output_matrix @ r
    np.testing.assert_allclose(eps, [-R_B * 2 * c, R_B * 2 * c] * 2, rtol=1e-10)


def test_actuator_forces_act_laterally_at_nodes_1_and_N(paper_model):
    b0 = paper_model.input_matrix
    last = paper_model.n_nodes - 1
    expected = {(dof(0, V), 0), (dof(0, W), 1), (dof(last, V), 2), (dof(last, W), 3)}
    assert set(zip(*np.nonzero(b0), strict=True)) == expected
    assert np.all(b0[tuple(np.array(sorted(expected)).T)] == 1.0)


def test_rayleigh_damping_gives_the_identified_ratios_on_the_loaded_beam(paper_model):
    a, _, _ = state_space(paper_model, 2000.0)
    idx = plane_indices(paper_model.n_nodes, "y")
    states = np.concatenate([idx, paper_model.n_dof + idx])
    poles = np.linalg.eigvals(a[np.ix_(states, states)])
    poles = poles[poles.imag > 0]
    poles = poles[np.argsort(np.abs(poles))][:2]
    zeta = -poles.real / np.abs(poles)
    np.testing.assert_allclose(zeta, [0.015, 0.0045], rtol=1e-3)
    np.testing.assert_allclose(np.abs(poles) / (2 * np.pi), eigenfrequencies(paper_model, 2000.0, 2),
                               rtol=1e-6)
    assert paper_model.rayleigh_alpha > 0 and paper_model.rayleigh_beta > 0


def test_frequency_response_equals_a_direct_solve_and_python_control(paper_model):
    control = pytest.importorskip("control")
    freqs = np.array([0.0, 50.0, 123.0, 300.0, 466.0, 1000.0])
    g = fe_frequency_response(paper_model, 2000.0, freqs)
    m, d, k = paper_model.mass, paper_model.damping, paper_model.load_stiffness(2000.0)
    for i, f in enumerate(freqs):
        s = 2j * np.pi * f
        direct = paper_model.output_matrix @ np.linalg.solve(s * s * m + s * d + k, paper_model.input_matrix)
        np.testing.assert_allclose(g[i], direct, rtol=1e-7, atol=1e-9 * np.abs(direct).max(),
                                   err_msg=f"G_FE at {f} Hz")
    a, b, c = state_space(paper_model, 2000.0)
    resp = control.ss(a, b[:, [0]], c[[0]], 0).frequency_response(2 * np.pi * freqs[1:])
    np.testing.assert_allclose(np.squeeze(resp.complex), g[1:, 0, 0], rtol=1e-6)
    # the planes do not couple: a y force gives no z strain
    assert np.all(g[:, 1, 0] == 0) and np.all(g[:, 0, 1] == 0)
