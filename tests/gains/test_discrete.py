"""The controller's velocity estimate and the discrete closed-loop check."""

import math

import numpy as np
import pytest

from beamctl.gains.defaults import DEFAULT_DESIGN
from beamctl.gains.discrete import check_load, velocity_filter
from beamctl.gains.lqr import lqr_gain


@pytest.mark.parametrize("freq", [2.0, 5.0, 14.55])
def test_velocity_estimate_tracks_the_derivative_well_below_the_cutoff(freq):
    """For f <= fc/10 the scaled high-pass output follows d/dt of a sinusoid within 2 % in
    amplitude, lagging by atan(f / fc) (5.7 deg at fc/10). The amplitude is 1.1 % low even
    at DC: the bilinear transform is pre-warped to fc, so scaling by omega_c gives the
    low-frequency gain x / tan(x), x = pi fc / fs."""
    filt = velocity_filter(145.5, 2500.0)
    t = np.arange(0, 2.0, 1 / 2500.0)
    q = np.sin(2 * np.pi * freq * t)
    s, v = 0.0, np.empty_like(q)
    for k, qk in enumerate(q):
        h = filt.b0 * qk + s
        s = filt.b1 * qk - filt.a1 * h
        v[k] = filt.scale * h
    tail = slice(len(t) // 2, None)
    amplitude = np.sqrt(2 * np.mean(v[tail] ** 2)) / (2 * np.pi * freq)
    assert amplitude == pytest.approx(1.0, rel=0.02), f"{amplitude:.4f} of dq/dt at {freq} Hz"
    x = math.pi * 145.5 / 2500.0
    expected = x / math.tan(x) / math.sqrt(1 + (freq / 145.5) ** 2)
    assert amplitude == pytest.approx(expected, rel=2e-3)
    lag = filt.phase_lag_deg(freq)
    assert lag == pytest.approx(math.degrees(math.atan(freq / 145.5)), abs=0.5)
    assert 0 < lag < 6, f"{lag:.1f} deg lag at {freq} Hz"


def test_velocity_filter_refuses_a_cutoff_above_nyquist():
    with pytest.raises(ValueError, match="Nyquist"):
        velocity_filter(1300.0, 2500.0)


def test_z_plane_check_equals_y_plane_check(paper_model, paper_reduced):
    """Why checking one plane suffices: the circular section gives both the same spectrum."""
    filt = velocity_filter(DEFAULT_DESIGN.velocity_cutoff_hz, DEFAULT_DESIGN.sample_rate_hz)
    k = lqr_gain(paper_reduced, 3500.0, DEFAULT_DESIGN.weights)
    y = check_load(paper_model, 3500.0, k, paper_reduced.c0_phi_inv, filt, "y")
    z = check_load(paper_model, 3500.0, k, paper_reduced.c0_phi_inv, filt, "z")
    assert z.spectral_radius == pytest.approx(y.spectral_radius, rel=1e-9)


def test_uncontrolled_beam_beyond_buckling_is_unstable_in_the_check(paper_model, paper_reduced):
    """The check can fail: zero gain at 3500 N leaves the divergent first mode."""
    filt = velocity_filter(DEFAULT_DESIGN.velocity_cutoff_hz, DEFAULT_DESIGN.sample_rate_hz)
    result = check_load(paper_model, 3500.0, np.zeros((4, 12)), paper_reduced.c0_phi_inv, filt)
    assert not result.stable and result.spectral_radius > 1.05
    below = check_load(paper_model, 3000.0, np.zeros((4, 12)), paper_reduced.c0_phi_inv, filt)
    assert below.spectral_radius == pytest.approx(1.0, abs=1e-9), "integrators without feedback"


@pytest.mark.parametrize("load", [1000.0, 3525.0])
def test_the_loop_the_check_analyses_is_the_loop_the_controller_runs(paper_model, load):
    """The rt controller (estimator, filter, integrator, interpolated gain, allocation) closed
    around the zero-order-hold FE plant follows, step by step, the closed-loop matrix that
    ``gains check`` computes its spectral radius from: one law, not two copies that drift.
    Tolerance 1e-9 of the largest state: rounding only (the forces stay far inside the stacks'
    range, so the allocation reproduces them exactly)."""
    from beamctl.gains.defaults import default_table_path
    from beamctl.gains.discrete import closed_loop_matrix, discrete_fe_plane
    from beamctl.gains.schedule import GainSchedule
    from beamctl.gains.table import load_table
    from beamctl.hal.base import Sample
    from beamctl.rt.config import controller_config
    from beamctl.rt.controller import Controller

    table = load_table(default_table_path())
    rate = table.design.sample_rate_hz
    filt = velocity_filter(table.design.velocity_cutoff_hz, rate)
    ad, bd, c = discrete_fe_plane(paper_model, load, 1.0 / rate, "y")
    a_cl = closed_loop_matrix(ad, bd, c, GainSchedule(table).gain_at(load), table.c0_phi_inv, filt, "y")

    controller = Controller(table, controller_config({"start_ramp_time_s": 0.0}))
    rng = np.random.default_rng(7)
    x = 1e-9 * rng.standard_normal(ad.shape[0])         # a few micro-strain at the gauges
    sample = Sample()
    sample.axial_load = load

    def measure(state):
        sample.strains[:] = 0.0
        sample.strains[[0, 2]] = c @ state               # the y plane's gauges
        return sample

    controller.arm(measure(x))
    controller.start()
    q0 = table.c0_phi_inv[np.ix_([0, 2], [0, 2])] @ c @ x
    z = np.concatenate([x, -filt.b0 * q0, np.zeros(2)])  # filter at rest on q0, integrator empty
    forces_per_volt = controller.allocator.geometry
    worst, scale = 0.0, np.abs(x).max()
    for _ in range(300):
        voltages = controller.step(measure(x))
        assert controller.allocator.scale_a == 1.0 and controller.allocator.scale_b == 1.0
        forces = forces_per_volt.forces(voltages)
        x = ad @ x + bd @ forces[[0, 2]]
        z = a_cl @ z
        worst = max(worst, np.abs(x - z[:len(x)]).max())
        scale = max(scale, np.abs(x).max())
    assert worst <= 1e-9 * scale, (
        f"controller and checked closed loop differ by {worst:.3g} (states up to {scale:.3g}) at "
        f"{load:g} N: gains/discrete.py no longer analyses what rt/controller.py runs")
