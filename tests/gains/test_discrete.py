"""The paper's velocity estimate (the high-pass filter the paper's compensator runs)."""

import math

import numpy as np
import pytest

from beamctl.gains.discrete import velocity_filter


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
