"""The rig's I/O chain: analogue filters as state space, the exact delayed zero-order hold, and
the validation of an ``io`` section."""

import numpy as np
import pytest
import scipy.linalg as sla
import scipy.signal as sig

from beamctl.config.schema import ConfigError
from beamctl.models.iochain import AnalogFilter, IOChain, delayed_zoh, io_chain, with_filters


@pytest.mark.parametrize("kind", ["butterworth", "bessel", "elliptic"])
@pytest.mark.parametrize("order", [1, 2, 3, 4, 5, 6])
def test_filter_state_space_has_the_prototype_s_frequency_response(kind, order):
    """The cascade of sections realises scipy's analogue prototype exactly (to rounding) and is
    normalised to unit gain at 0 Hz, the amplifier's calibration."""
    f = AnalogFilter(kind, order, 1000.0)
    a, b, c, d = f.state_space()
    z, p, k = f.zpk()
    w = 2 * np.pi * np.array([0.0, 10.0, 300.0, 1000.0, 2500.0, 8000.0])
    ours = np.array([(c @ np.linalg.solve(1j * wi * np.eye(len(a)) - a, b) + d)[0, 0] for wi in w])
    _, theirs = sig.freqs_zpk(z, p, k, w)
    assert np.max(np.abs(ours - theirs)) < 1e-12, f"{kind} order {order}: state space differs from zpk"
    assert abs(ours[0] - 1.0) < 1e-12, f"{kind} order {order}: DC gain {abs(ours[0])}, expected 1"
    # a low-pass: far above the cut-off the gain is small (elliptic: below its stop-band level)
    assert abs(ours[-1]) < 0.5, f"{kind} order {order} passes {abs(ours[-1]):.2f} at 8 kHz"


def _fine_simulation(a, b, u, period, delay):
    """x at the end of the record, integrating the delayed staircase input on a 1000x finer grid."""
    steps = 1000
    dt = period / steps
    ad = sla.expm(a * dt)
    bd = np.linalg.solve(a, (ad - np.eye(len(a))) @ b)
    x = np.zeros(len(a))
    for i in range(len(u) * steps):
        t = (i + 0.5) * dt - delay * period
        k = int(np.floor(t / period))
        x = ad @ x + bd[:, 0] * (u[k] if 0 <= k < len(u) else 0.0)
    return x


@pytest.mark.parametrize("delay", [0.0, 0.3, 1.0, 1.7])
def test_delayed_zoh_matches_a_fine_simulation_of_the_delayed_staircase(delay):
    """x_k+1 = Ad x_k + B_now u_k-m + B_before u_k-m-1 is exact for a delay of m + f samples: the
    sampled state equals a 1000x finer integration to the accuracy of that integration."""
    a = np.array([[0.0, 1.0], [-400.0, -2.0]])
    b = np.array([[0.0], [1.0]])
    period = 1e-2
    u = np.random.default_rng(3).standard_normal(12)
    z = delayed_zoh(a, b, period, delay)
    x = np.zeros(2)
    for k in range(len(u)):
        now = u[k - z.whole] if k - z.whole >= 0 else 0.0
        before = u[k - z.whole - 1] if k - z.whole - 1 >= 0 else 0.0
        x = z.ad @ x + z.b_now[:, 0] * now + z.b_before[:, 0] * before
    reference = _fine_simulation(a, b, u, period, delay)
    assert np.allclose(x, reference, rtol=1e-6, atol=1e-9), f"delay {delay}: {x} vs {reference}"


def test_filters_join_the_plant_in_series_and_keep_its_static_gain():
    """With unit-DC-gain filters on both sides, the plant's static gain is unchanged; the
    undelayed extra input (the axial load) bypasses the reconstruction filter."""
    a = np.array([[-5.0]])
    b = np.array([[2.0, 1.0]])        # input 0: a force (filtered), input 1: the load (not)
    c = np.array([[3.0]])
    chain = IOChain(anti_alias=AnalogFilter("butterworth", 2, 50.0),
                    reconstruction=AnalogFilter("elliptic", 3, 80.0))
    fa, fb, fc, fd = with_filters(a, b, c, chain, n_control=1)
    static = fd - fc @ np.linalg.solve(fa, fb)
    assert np.allclose(static, [[6.0 / 5.0, 3.0 / 5.0]], rtol=1e-12)
    assert fa.shape == (1 + 3 + 2, 1 + 3 + 2)


@pytest.mark.parametrize("data, key", [
    ({"delay_samples": -0.5}, "io.delay_samples"),
    ({"delay_samples": "one"}, "io.delay_samples"),
    ({"anti_alias": {"type": "chebyshev", "order": 2, "cutoff_hz": 1e3}}, "io.anti_alias.type"),
    ({"anti_alias": {"type": "butterworth", "order": 0, "cutoff_hz": 1e3}}, "io.anti_alias.order"),
    ({"reconstruction": {"type": "bessel", "order": 2, "cutoff_hz": "1k"}}, "io.reconstruction.cutoff_hz"),
    ({"reconstruction": {"type": "bessel", "order": 2}}, "io.reconstruction.cutoff_hz"),
    ({"anti_alias": {"type": "elliptic", "order": 4, "cutoff_hz": 1e3, "ripple_db": 3,
                     "attenuation_db": 2}}, "io.anti_alias.attenuation_db"),
    ({"latency": 1}, "io.latency"),
])
def test_a_bad_io_section_is_refused_naming_the_key(data, key):
    with pytest.raises(ConfigError) as err:
        io_chain(data)
    assert err.value.key == key, f"refused {err.value.key!r}, expected {key!r}: {err.value}"


def test_an_io_section_round_trips_through_its_dict():
    chain = io_chain({"delay_samples": 0.5,
                      "anti_alias": {"type": "elliptic", "order": 4, "cutoff_hz": 1500}})
    assert io_chain(chain.to_dict()) == chain
    assert io_chain({}).is_direct


def test_the_description_names_what_an_elliptic_filter_needs_to_be_built_again():
    """A rig is wired from the chain a table states: an elliptic filter's ripple and stop-band
    attenuation are part of it (the shipped table's 30 dB is not the configuration default)."""
    shipped = IOChain(0.35, AnalogFilter("elliptic", 4, 1750.0, 0.5, 30.0)).describe()
    default = IOChain(0.35, AnalogFilter("elliptic", 4, 1750.0)).describe()
    assert shipped == ("delay 0.35 samples, anti-alias elliptic order 4 at 1750 Hz "
                       "(0.5 dB ripple, 30 dB attenuation)")
    assert default != shipped, "two different filters, one description"
    assert IOChain(1.0, AnalogFilter("butterworth", 2, 1250.0)).describe() == (
        "delay 1 samples, anti-alias butterworth order 2 at 1250 Hz")
