"""Excitation signals: periodic, peak 1, their power where the band is, and the stack voltages
that push along one force axis only."""

import numpy as np
import pytest

from beamctl.config.schema import ConfigError
from beamctl.identification.excitation import force_gains, periodic_signal, voltage_directions
from beamctl.models.actuators import StackGeometry

RATE_HZ = 6000.0
BAND_HZ = (50.0, 800.0)


def _power_in_band(values: np.ndarray, band: tuple[float, float]) -> float:
    power = np.abs(np.fft.rfft(values)) ** 2
    f = np.fft.rfftfreq(len(values), 1 / RATE_HZ)
    inside = (f >= band[0]) & (f <= band[1])
    return power[inside].sum() / power[1:].sum()


@pytest.mark.parametrize("kind", ["multisine", "chirp", "prbs"])
def test_every_signal_has_peak_one_and_zero_mean(kind):
    e = periodic_signal(kind, RATE_HZ, BAND_HZ, 2.0, seed=3)
    assert np.max(np.abs(e.values)) == pytest.approx(1.0), "peak 1: the amplitude flag is the stack swing"
    assert abs(e.values.mean()) < 1e-12, "no static offset: the beam is not pushed sideways on average"


def test_a_multisine_puts_all_its_power_on_the_band_s_lines_with_equal_amplitude():
    e = periodic_signal("multisine", RATE_HZ, BAND_HZ, 2.0, seed=1)
    assert e.period_samples == 3000, "6000 Hz / 2 Hz = 3000 samples a period"
    spectrum = np.abs(np.fft.rfft(e.values))
    lines = np.arange(25, 401)                     # 50..800 Hz every 2 Hz
    assert _power_in_band(e.values, BAND_HZ) > 1 - 1e-12
    assert np.ptp(spectrum[lines]) / spectrum[lines].mean() < 1e-9, "equal amplitude on every line"


def test_two_seeds_give_different_phases_the_same_seed_the_same_signal():
    a, b = (periodic_signal("multisine", RATE_HZ, BAND_HZ, 2.0, seed=s).values for s in (1, 2))
    assert not np.allclose(a, b)
    assert np.array_equal(a, periodic_signal("multisine", RATE_HZ, BAND_HZ, 2.0, seed=1).values)


@pytest.mark.parametrize("kind, share", [("chirp", 0.95), ("prbs", 0.35)])
def test_chirp_and_prbs_put_their_power_where_the_band_is(kind, share):
    # a linear chirp leaks a little beyond its ends; a PRBS spreads its power from 0 Hz to its
    # bit rate, 2.5 x the band's top: a third of it lies in 50..800 Hz
    e = periodic_signal(kind, RATE_HZ, BAND_HZ, 2.0, seed=1)
    assert _power_in_band(e.values, BAND_HZ) > share


def test_the_prbs_is_flat_within_3_db_across_the_band():
    e = periodic_signal("prbs", RATE_HZ, BAND_HZ, 2.0, seed=1)
    power = np.abs(np.fft.rfft(e.values)) ** 2
    f = np.fft.rfftfreq(e.period_samples, 1 / RATE_HZ)
    inside = (f >= BAND_HZ[0]) & (f <= BAND_HZ[1]) & (power > 0)
    smooth = np.convolve(power, np.ones(64) / 64, mode="same")[inside]
    assert 10 * np.log10(smooth.max() / smooth.min()) < 3.0


@pytest.mark.parametrize("band, resolution, flag", [
    ((50.0, 3100.0), 2.0, "--band"), ((800.0, 50.0), 2.0, "--band"), ((50.0, 60.0), 5.0, "--resolution")])
def test_a_band_or_resolution_that_cannot_be_measured_is_refused_naming_the_flag(band, resolution, flag):
    with pytest.raises(ConfigError) as info:
        periodic_signal("multisine", RATE_HZ, band, resolution)
    assert info.value.key == flag


@pytest.mark.parametrize("orientation", [(90.0, 90.0), (0.0, 37.0)])
def test_each_voltage_direction_pushes_along_its_own_force_axis_only(orientation):
    g = StackGeometry(3.0, 75.0, orientation)
    d = voltage_directions(g)
    forces = g.force_matrix() @ d.T                # column j: the forces of direction j
    np.testing.assert_allclose(np.abs(d).max(axis=1), 1.0, err_msg="largest stack swing 1 V")
    np.testing.assert_allclose(forces - np.diag(np.diag(forces)), 0.0, atol=1e-12)
    np.testing.assert_allclose(np.diag(forces), force_gains(g))
    assert np.all(force_gains(g) > 0), "a positive swing pushes along the positive axis"
