"""The shipped LQG design: it is what `beamctl gains build` makes, and it is built for the I/O
chain it declares."""

import numpy as np
import pytest

from beamctl.gains.build import build_lqg_table
from beamctl.gains.compensator import MATRICES
from beamctl.gains.defaults import LQG_CHAIN, LQG_SETTINGS, default_table_path
from beamctl.gains.lqg import design
from beamctl.gains.table import load_table
from beamctl.models import build_model, load_parameters
from beamctl.models.iochain import AnalogFilter, IOChain
from beamctl.models.modal import reduce


def test_the_shipped_default_is_the_lqg_that_gains_build_makes():
    """Rebuilt from the paper's parameters, every compensator matrix equals the shipped one to
    1e-6 of its largest entry (BLAS kernels differ from machine to machine by far less; a changed
    design or setting differs by far more)."""
    shipped = load_table(default_table_path())
    assert shipped.design.kind == "lqg" and shipped.design.io == LQG_CHAIN
    rebuilt = build_lqg_table(build_model(load_parameters()), check=False)
    for name in MATRICES:
        ours, theirs = getattr(rebuilt.compensator, name), getattr(shipped.compensator, name)
        scale = max(np.max(np.abs(theirs)), 1e-300)
        assert np.max(np.abs(ours - theirs)) <= 1e-6 * scale, f"compensator matrix {name} differs"
    assert shipped.all_stable and not shipped.forced


def test_the_design_does_not_pretend_to_model_a_reconstruction_filter():
    model = build_model(load_parameters())
    chain = IOChain(delay_samples=0.5, reconstruction=AnalogFilter("butterworth", 2, 2000.0))
    with pytest.raises(ValueError, match="reconstruction filter"):
        design(model, [0.0, 100.0], 6000.0, chain, reduce(model).c0_phi_inv, LQG_SETTINGS)


def _response(point, states, io, frequency_hz, rate_hz):
    """The compensator's y -> u frequency response of one plane (E u fed back, integral left
    out): -(I + C R E)^-1 (C R B + D) with R = (zI - A)^-1."""
    s = np.asarray(states)
    a, b = point.a[np.ix_(s, s)], point.b[np.ix_(s, io)]
    e, c, d = point.e[np.ix_(s, io)], point.c[np.ix_(io, s)], point.d[np.ix_(io, io)]
    z = np.exp(2j * np.pi * frequency_hz / rate_hz)
    r = np.linalg.inv(z * np.eye(len(s)) - a)
    return -np.linalg.solve(np.eye(len(io)) + c @ r @ e, c @ r @ b + d)


def test_a_strain_filter_that_passes_the_strains_changes_nothing_but_the_states():
    """(1, 0) keeps the last strains as states, weighted by nothing: the compensator's response
    from strains to forces is that without a filter, to 1e-6 (the Riccati solutions of the two
    models differ by rounding only)."""
    from dataclasses import replace

    model = build_model(load_parameters())
    h = reduce(model).c0_phi_inv
    plain = replace(LQG_SETTINGS, strain_fir=(1.0,))
    padded = replace(LQG_SETTINGS, strain_fir=(1.0, 0.0))
    one = design(model, [2000.0, 3000.0], 6000.0, LQG_CHAIN, h, plain)
    two = design(model, [2000.0, 3000.0], 6000.0, LQG_CHAIN, h, padded)
    assert two.n_states == one.n_states + 8, "two past strains per plane in the estimator and the raw buffer"
    io = [0, 2]
    for i in range(2):
        for f in (20.0, 150.0, 1000.0, 2700.0):
            ours = _response(two.point(i), two.plane_states["y"], io, f, 6000.0)
            theirs = _response(one.point(i), one.plane_states["y"], io, f, 6000.0)
            assert np.max(np.abs(ours - theirs)) <= 1e-6 * np.max(np.abs(theirs)), (i, f)


def test_the_strain_filter_starts_where_the_strains_are():
    """Bumpless start: with the strains constant, the raw past strains and their predictions
    start at the strains, so the filtered strain equals them from the first sample (the taps sum
    to 1), and a step of the filter's buffer keeps them there."""
    table = load_table(default_table_path())
    comp = table.compensator
    taps = LQG_SETTINGS.strain_fir
    assert sum(taps) == pytest.approx(1.0) and len(taps) == 3
    y = np.array([3e-6, -1e-6, 2e-6, 4e-6])
    x = comp.start @ y
    for plane, io in (("y", [0, 2]), ("z", [1, 3])):
        states = comp.plane_states[plane]
        buffer = states[-4:]                        # y_k-1, y_k-2 of this plane's two gauges
        assert np.allclose(x[buffer], np.tile(y[io], 2)), plane
        point = comp.point(0)
        nxt = point.a[np.ix_(buffer, np.arange(comp.n_states))] @ x + point.b[buffer] @ y
        assert np.allclose(nxt, np.tile(y[io], 2)), f"plane {plane}'s buffer moves under constant strains"


def test_the_estimator_offset_follows_its_schedule_linearly_and_holds_beyond_its_ends():
    from dataclasses import replace

    settings = replace(LQG_SETTINGS, estimator_mode1_offset_schedule=((1000.0, 100.0), (2000.0, 300.0)))
    assert settings.at_load(1500.0).estimator_mode1_load_offset_n == pytest.approx(200.0)
    assert settings.at_load(0.0).estimator_mode1_load_offset_n == 100.0
    assert settings.at_load(4000.0).estimator_mode1_load_offset_n == 300.0
    assert replace(settings, estimator_mode1_offset_schedule=()).at_load(1500.0) == replace(
        settings, estimator_mode1_offset_schedule=())
