"""The plant with the rig's I/O chain (``plant.io``): transport delay on the forces, the
reconstruction filter before the beam and the anti-aliasing filter before the strain gauges'
readings."""

import numpy as np
import pytest
import scipy.signal as sig

from beamctl.config.schema import ConfigError
from beamctl.models.iochain import analog_filter
from beamctl.models.plant import Plant, load_plant_config, plant_config

RATE_HZ = 2500.0
# a load on an anchor of the plant's load grid (94 x 16 N): its discretisation is the exact one,
# not interpolated (models/plant.py), so the exactness checks below can ask for 1e-9
STEADY = {"start": 1504.0, "end": 1504.0}
FORCE_STEP = np.array([5.0, -3.0, 2.0, 4.0])


def _plant(model, io=None, **settings) -> Plant:
    """The beam at a steady 1504 N (no imperfection: at rest, no strain) with the chain ``io``."""
    return Plant(model, plant_config({"sample_rate_hz": RATE_HZ, "load": STEADY, "io": io or {},
                                      **settings}))


def _strains(plant: Plant, forces) -> np.ndarray:
    """Measured strains before each step, with ``forces[k]`` applied at step k."""
    out = []
    for f in forces:
        out.append(plant.measure()[0].copy())
        plant.step(f)
    return np.array(out)


def _varying_forces(samples: int) -> np.ndarray:
    k = np.arange(samples)[:, None]
    return np.hstack([10.0 * np.sin(k / 7.0), -4.0 + 0.0 * k, 3.0 * (k % 5), 6.0 * np.cos(k / 3.0)])


def test_default_chain_is_the_beam_alone_sampled_with_a_zero_order_hold(paper_model):
    """No delay, no filter: the strains over 400 samples of varying forces on a ramping,
    bowed beam are those of the beam's own (A, B) discretised with a zero-order hold (the
    plant before the I/O chain existed), to 1e-6 of their size (the interpolated cells)."""
    plant = Plant(paper_model, plant_config({"sample_rate_hz": RATE_HZ,
                                             "load": {"start": 1800.0, "end": 2600.0, "rate": 2000.0},
                                             "bow": {"amplitude": 1e-4, "angle_deg": 234.0}}))
    assert plant.config.io.is_direct and plant.n_states == 2 * plant.n_coordinates
    n, cell = plant.n_coordinates, 2.0 * plant.config.load_tolerance
    c0 = paper_model.output_matrix @ plant.basis
    forces = _varying_forces(400)
    # the reference: x_k+1 = Ad(Fx_k) x_k + Bd(Fx_k) [u_k, Fx_k] (A and B at the load's
    # tolerance cell), strain = C0 q, from static equilibrium
    a, b = plant.continuous(plant.axial_load)
    x = np.zeros(2 * n)
    x[:n] = -np.linalg.solve(a, b[:, 4] * plant.axial_load)[:n]
    time_s, load, expected = 0.0, plant.axial_load, []
    for f in forces:
        expected.append(c0 @ x[:n])
        a, b = plant.continuous(round(load / cell) * cell)
        ad, bd, *_ = sig.cont2discrete((a, b, np.eye(2 * n), np.zeros((2 * n, 5))), plant.period_s)
        x = ad @ x + bd @ np.append(f, load)
        time_s += plant.period_s
        load = plant.config.load.load_at(time_s)
    measured = _strains(plant, forces)
    scale = np.abs(expected).max()
    # the plant interpolates the cells between exact anchors (static response within 1e-6 of
    # itself, models/plant.py)
    np.testing.assert_allclose(measured, expected, rtol=0, atol=1e-6 * scale,
                               err_msg="default I/O chain: strains differ from the beam's own ZOH")
    assert np.ptp(measured, axis=0).min() > 1e-3 * scale, "the forces must move every strain"


def test_a_one_sample_delay_shifts_the_strain_response_by_exactly_one_sample(paper_model):
    """A force step commanded at sample 0: the undelayed strains change from sample 1 on, the
    delayed ones from sample 2 on, and are the undelayed ones one sample later."""
    forces = np.tile(FORCE_STEP, (300, 1))
    direct = _strains(_plant(paper_model), forces)
    delayed = _strains(_plant(paper_model, {"delay_samples": 1}), forces)
    assert np.all(direct[0] == 0.0) and np.all(np.abs(direct[1]) > 0), "beam at rest, moved at once"
    assert np.all(delayed[:2] == 0.0), "nothing before the delayed force arrives"
    np.testing.assert_allclose(delayed[1:], direct[:-1], rtol=1e-12, atol=1e-12 * np.abs(direct).max(),
                               err_msg="delay 1: the undelayed response one sample later")


def test_a_half_sample_delay_moves_the_first_sample_by_the_response_half_a_sample_in(paper_model):
    """Delay 0.5: the strains move at the first sample after the step (a whole-sample delay
    would leave it at rest) by the undelayed step response half a sample after the step, taken
    from the same beam sampled twice as fast. The strains ring within a sample (modes up to
    20 kHz), so that value is not smaller than the undelayed one at a whole sample."""
    fast = _strains(_plant(paper_model, sample_rate_hz=2 * RATE_HZ), np.tile(FORCE_STEP, (4, 1)))
    half = _strains(_plant(paper_model, {"delay_samples": 0.5}), np.tile(FORCE_STEP, (2, 1)))
    assert np.all(half[0] == 0.0) and np.all(np.abs(half[1]) > 0), half
    np.testing.assert_allclose(half[1], fast[1], rtol=1e-9, err_msg="delay 0.5: first sample after the step")


@pytest.mark.parametrize(("delay", "finer"), [(0.5, 2), (1.5, 2), (1.7, 10), (3.25, 4)])
def test_a_fractional_delay_is_a_whole_delay_of_a_finer_sampling(paper_model, delay, finer):
    """Exactness of the delayed zero-order hold: delay d at T gives the strains of the beam
    sampled at T / M with a delay of d M of those samples (each force held for M of them), to
    1e-9 of their size."""
    forces = _varying_forces(200)
    coarse = _strains(_plant(paper_model, {"delay_samples": delay}), forces)
    fine_plant = _plant(paper_model, {"delay_samples": round(delay * finer)},
                        sample_rate_hz=finer * RATE_HZ)
    fine = _strains(fine_plant, np.repeat(forces, finer, axis=0))[::finer]
    np.testing.assert_allclose(coarse, fine, rtol=0, atol=1e-9 * np.abs(fine).max(),
                               err_msg=f"delay {delay} at T against {round(delay * finer)} at T/{finer}")


@pytest.mark.parametrize("where", ["anti_alias", "reconstruction"])
def test_a_force_far_above_the_filter_cut_off_is_attenuated_by_the_filter_s_gain(paper_model, where):
    """A 500 Hz force through a 4th-order Butterworth low-pass at 100 Hz: the strain amplitude
    at 500 Hz is the unfiltered one times |H(j 2 pi 500 Hz)| (1/625, from the filter's zeros,
    poles and gain), within 10 % (the zero-order hold's images near 2000 Hz alias onto 500 Hz
    and are filtered differently)."""
    low_pass = {"type": "butterworth", "order": 4, "cutoff_hz": 100.0}
    freq_hz, samples = 500.0, 5000
    k = np.arange(samples)[:, None]
    forces = 10.0 * np.sin(2 * np.pi * freq_hz * k / RATE_HZ) * np.array([1.0, 0.5, -0.7, 0.2])

    def amplitude(strains):
        last = strains[-2500:]                 # the last second, 500 whole periods
        phase = np.exp(-2j * np.pi * freq_hz * np.arange(len(last)) / RATE_HZ)
        return 2 * np.abs(phase @ last) / len(last)

    plain = amplitude(_strains(_plant(paper_model), forces))
    filtered = amplitude(_strains(_plant(paper_model, {where: low_pass}), forces))
    z, p, gain = analog_filter(low_pass, "io.anti_alias").zpk()
    _, h = sig.freqs_zpk(z, p, gain, [2 * np.pi * freq_hz])
    np.testing.assert_allclose(filtered / plain, abs(h[0]), rtol=0.10,
                               err_msg=f"{where} filter: attenuation at {freq_hz:g} Hz")


@pytest.mark.parametrize("io", [
    {"anti_alias": {"type": "butterworth", "order": 3, "cutoff_hz": 300.0}},
    {"anti_alias": {"type": "elliptic", "order": 4, "cutoff_hz": 500.0}},
    {"reconstruction": {"type": "bessel", "order": 2, "cutoff_hz": 800.0}, "delay_samples": 1.3},
], ids=["butterworth-3", "elliptic-4", "bessel-2-delay-1.3"])
def test_filters_have_unit_gain_at_dc_and_start_at_rest(paper_model, io):
    """The filters leave static strains alone: the bowed, eccentrically loaded beam at rest reads
    the same strains with and without the chain, and keeps reading them (the filters start in
    their steady state, nothing is in the delay); a steady force gives the same static strain."""
    imperfect = {"bow": {"amplitude": 1e-4, "angle_deg": 234.0},
                 "eccentricity": {"amplitude": 1e-4, "angle_deg": 30.0}}
    plain, chained = _plant(paper_model, **imperfect), _plant(paper_model, io, **imperfect)
    at_rest = plain.measure()[0].copy()
    assert np.abs(at_rest).min() > 1e-6, "the imperfections must strain the beam"
    rest = _strains(chained, np.zeros((1000, 4)))
    np.testing.assert_allclose(rest, np.tile(at_rest, (1000, 1)), rtol=1e-9,
                               err_msg="at rest the chain must not move the strains")
    steady = np.tile(FORCE_STEP, (7500, 1))        # 3 s: the beam's transient has decayed
    np.testing.assert_allclose(_strains(chained, steady)[-1], _strains(plain, steady)[-1], rtol=1e-4,
                               err_msg="static strain under a steady force")


def test_reset_empties_the_delay_and_settles_the_filters(paper_model):
    io = {"delay_samples": 2.5, "anti_alias": {"type": "bessel", "order": 2, "cutoff_hz": 400.0}}
    plant = _plant(paper_model, io)
    first = _strains(plant, np.tile(FORCE_STEP, (40, 1)))
    plant.reset()
    np.testing.assert_array_equal(_strains(plant, np.tile(FORCE_STEP, (40, 1))), first)
    assert np.all(first[:3] == 0.0) and np.all(first[3] != 0.0), "delay 2.5: first moved at sample 3"


@pytest.mark.parametrize(("io", "key"), [
    ({"delay_samples": -1}, "io.delay_samples"),
    ({"anti_alias": {"type": "chebyshev", "order": 2, "cutoff_hz": 100}}, "io.anti_alias.type"),
    ({"reconstruction": {"type": "bessel", "order": 0, "cutoff_hz": 100}}, "io.reconstruction.order"),
    ({"anti_alias": {"type": "butterworth", "order": 2, "cutoff_hz": "100"}}, "io.anti_alias.cutoff_hz"),
    ({"delay": 1}, "io.delay"),
])
def test_bad_io_values_are_refused_naming_the_key(io, key):
    with pytest.raises(ConfigError) as info:
        plant_config({"io": io}, "rig.yaml", "plant.")
    assert info.value.key == f"plant.{key}", str(info.value)
    assert str(info.value).startswith(f"rig.yaml: plant.{key} = ")


def test_the_old_sample_rate_key_is_refused_naming_the_new_one(tmp_path):
    with pytest.raises(ConfigError) as info:
        plant_config({"sample_rate": 2500.0}, "rig.yaml", "plant.")
    assert info.value.key == "plant.sample_rate" and "plant.sample_rate_hz" in str(info.value)
    assert len(str(info.value).splitlines()) == 1
    f = tmp_path / "plant.yaml"
    f.write_text("sample_rate: 2500\n")
    with pytest.raises(ConfigError, match=r"sample_rate = 2500: expected sample_rate_hz in its place"):
        load_plant_config(f)
    f.write_text("sample_rate_hz: 2500\nio: {delay_samples: 1.5}\n")
    cfg = load_plant_config(f)
    assert cfg.sample_rate_hz == 2500.0 and cfg.io.delay_samples == 1.5
