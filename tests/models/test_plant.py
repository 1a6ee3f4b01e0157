"""The sampled plant: Southwell's law, exact discretisation, load tolerance, imperfections."""

from dataclasses import replace

import numpy as np
import pytest

from beamctl.config.schema import ConfigError
from beamctl.models import critical_load, eigenfrequencies
from beamctl.models.plant import (
    ANCHOR_CELLS,
    END_STOP_FRACTION,
    LoadRamp,
    Plant,
    clear_discretisations,
    load_plant_config,
    plant_config,
    shared_discretisations,
)

ZERO = np.zeros(4)


def _run_until(plant: Plant, loads, forces=ZERO):
    """Step the plant and record (load, deflection, angle) when each load is first passed."""
    out = {}
    pending = sorted(loads)
    while pending:
        plant.step(forces)
        while pending and plant.axial_load >= pending[0]:
            out[pending.pop(0)] = (plant.axial_load, *plant.deflection())
    return out


def test_bowed_beam_under_slowly_rising_load_follows_southwell(paper_model):
    """Elastic deflection = Fx / (Fcr - Fx) x bow for a bow shaped like the buckling mode."""
    fcr = critical_load(paper_model)
    bow = 1e-4
    cfg = plant_config({"bow": {"amplitude": bow, "angle_deg": 234.0},
                        "load": {"start": 0.0, "end": fcr, "rate": 100.0}})
    plant = Plant(paper_model, cfg)
    results = _run_until(plant, [f * fcr for f in (0.2, 0.4, 0.6, 0.8, 0.9)])
    for load, deflection, angle in results.values():
        expected = bow * load / (fcr - load)
        assert deflection == pytest.approx(expected, rel=0.02), (
            f"at {load:.0f} N ({load / fcr:.2f} Fcr): {deflection * 1e3:.4f} mm, "
            f"Southwell {expected * 1e3:.4f} mm")
        assert angle == pytest.approx(234.0, abs=1e-6)


def test_plant_has_the_fe_model_s_critical_load_and_frequencies(paper_model):
    plant = Plant(paper_model, plant_config())
    mu = np.linalg.eigvals(np.linalg.solve(plant._k_elastic, plant._k_geometric))
    assert 1 / mu.real.max() == pytest.approx(critical_load(paper_model), rel=1e-6)
    a, _ = plant.continuous(2000.0)
    im = np.sort(np.linalg.eigvals(a).imag)
    plant_f = np.unique(np.round(im[im > 0] / (2 * np.pi), 6))[:3]
    np.testing.assert_allclose(plant_f, eigenfrequencies(paper_model, 2000.0, 3), rtol=1e-3)


@pytest.mark.parametrize("load", [260.0, 2000.0, 3000.0])
def test_steady_actuator_force_gives_the_full_model_s_static_strain(paper_model, load):
    """The static shapes in the basis make the force-to-strain gain right (a purely modal
    basis does not even get its sign right at low load)."""
    cfg = plant_config({"load": {"start": load, "end": load}})
    plant = Plant(paper_model, cfg)
    force = np.array([5.0, -3.0, 2.0, 4.0])
    for _ in range(int(1.5 * cfg.sample_rate_hz)):
        plant.step(force)
    strain, _ = plant.measure()
    expected = paper_model.output_matrix @ np.linalg.solve(
        paper_model.load_stiffness(load), paper_model.input_matrix @ force)
    np.testing.assert_allclose(strain, expected, rtol=0.01, err_msg=f"static strain at {load} N")


def test_zero_order_hold_is_exact_whatever_the_sample_rate(paper_model):
    """Piecewise constant forces: sampling at 2 kHz or 8 kHz gives the same states at the
    common instants (an approximate discretisation would not). 1504 N is an anchor of the
    load grid (94 x 16 N), where the plant's discretisation is the exact one."""
    states = []
    for rate in (2000.0, 8000.0):
        plant = Plant(paper_model, plant_config({"sample_rate_hz": rate,
                                                 "load": {"start": 1504.0, "end": 1504.0}}))
        per = int(rate / 2000.0)
        for k in range(200):
            force = np.array([10.0 * np.sin(k / 7.0), 0.0, -5.0, 3.0 * (k % 3)])
            for _ in range(per):
                plant.step(force)
        states.append(plant.displacement())
    np.testing.assert_allclose(states[1], states[0], rtol=1e-8, atol=1e-12 * np.abs(states[0]).max())


def test_discretisation_load_never_differs_from_the_applied_load_by_more_than_the_tolerance(paper_model):
    tol = 2.0
    cfg = plant_config({"load_tolerance": tol, "load": {"start": 260.0, "end": 1000.0, "rate": 400.0}})
    clear_discretisations()         # discretisations are shared by the process's plants
    plant = Plant(paper_model, cfg)
    worst = 0.0
    while plant.axial_load < 1000.0:
        plant.step(ZERO)
        worst = max(worst, abs(plant._bin * 2 * tol - plant.axial_load))
    assert worst <= tol + 1e-9
    anchors = (1000 - 260) / (2 * tol * ANCHOR_CELLS)
    assert plant.discretisations == pytest.approx(anchors, abs=3), (
        "one exact discretisation per anchor of the load grid spanned, the cells between interpolated")


@pytest.mark.parametrize("rate", [2000.0, 6000.0])
def test_interpolated_cells_are_a_hundred_times_closer_than_the_load_grid_is(paper_model, rate):
    """A cell between anchors interpolates the exact discretisations; its static response
    (I - Ad)^-1 Bd (the most sensitive: I - Ad is small) differs from the exact one at the cell's
    load by at most 1/100 of what stepping at the cell's load instead of the applied one (up to
    ``load_tolerance`` away, which the grid accepts) changes. The beam alone at 2 kHz is the
    least favourable chain measured; loads from low to just below Fx,cr."""
    plant = Plant(paper_model, plant_config({"sample_rate_hz": rate}))
    tol = plant.config.load_tolerance
    cell = 2.0 * tol

    def static(ad, bd):
        return np.linalg.solve(np.eye(len(ad)) - ad, bd[:, :4])

    def exact(load):
        zoh = plant.discretise(load)
        return static(zoh.ad, np.hstack([zoh.b_now, zoh.b_direct]))

    critical = critical_load(paper_model)
    for load in (263.0, 1501.0, 2999.0, round(critical - 20.0), round(critical - 3.0)):
        index = round(load / cell)
        assert index % ANCHOR_CELLS != 0, "the loads checked lie between anchors"
        reference = exact(index * cell)
        interpolated = static(*plant._cell_matrices(index))
        grid = np.abs(exact(index * cell + tol) - reference).max()
        error = np.abs(interpolated - reference).max()
        assert error <= grid / 100, (
            f"{rate:g} Hz, {load:g} N: the interpolated cell's static response is {error:.2e} off the "
            f"exact one, more than 1/100 of the grid's own {grid:.2e}: fewer cells between anchors "
            f"(ANCHOR_CELLS) or another interpolation")


def test_plants_of_one_rig_share_discretisations_and_step_the_same(paper_model):
    """A second plant of the same rig discretises nothing and steps exactly as the first; a plant
    with another I/O chain (a different system) computes its own."""
    cfg = plant_config({"load": {"start": 260.0, "end": 400.0, "rate": 2000.0}})
    clear_discretisations()
    first, second = Plant(paper_model, cfg), Plant(paper_model, cfg)
    force = np.array([0.3, -0.2, 0.1, 0.4])
    while first.axial_load < 400.0:
        first.step(force)
        second.step(force)
    assert first.discretisations > 5 and shared_discretisations() > 100, "the ramp crosses many cells"
    assert second.discretisations == 0, (
        f"the second plant of the same rig discretised {second.discretisations} cells itself")
    np.testing.assert_array_equal(second.displacement(), first.displacement())
    delayed = Plant(paper_model, replace(cfg, io=replace(cfg.io, delay_samples=0.5)))
    delayed.step(force)
    assert delayed.discretisations >= 1, "another I/O chain is another system: no shared cell"


def test_a_prepared_plant_makes_no_discretisation_on_its_way(paper_model):
    """``prepare`` makes every cell the load programme passes (a wall-clock DAQ must not stop to
    make one: an exact cell takes milliseconds): stepping the whole ramp then makes none."""
    cfg = plant_config({"load": {"start": 300.0, "end": 420.0, "rate": 3000.0}})
    clear_discretisations()
    plant = Plant(paper_model, cfg)
    cells = plant.prepare()
    assert cells == 121, "1 N cells from 300 to 420 N"
    made = plant.discretisations
    while plant.axial_load < 420.0:
        plant.step(ZERO)
    assert plant.discretisations == made, (
        f"{plant.discretisations - made} cells made while stepping a prepared programme")


def test_eccentric_load_bows_the_beam_away_from_the_load_line(paper_model):
    """A load applied at an offset compresses the fibres on its side more; the beam curves
    concave towards the offset and its middle moves the other way, so the lever arm grows."""
    cfg = plant_config({"eccentricity": {"amplitude": 2e-4, "angle_deg": 30.0},
                        "load": {"start": 0.0, "end": 2000.0, "rate": 400.0}})
    results = _run_until(Plant(paper_model, cfg), [1000.0, 1999.0])
    (_, d1, a1), (_, d2, a2) = results[1000.0], results[1999.0]
    assert a1 == pytest.approx(210.0, abs=1e-6) and a2 == pytest.approx(210.0, abs=1e-6)
    assert 0 < d1 < d2, "deflection grows with load"


def test_reset_places_the_beam_in_static_equilibrium(paper_model):
    cfg = plant_config({"bow": {"amplitude": 1e-4, "angle_deg": 90.0},
                        "load": {"start": 2500.0, "end": 2500.0}})
    plant = Plant(paper_model, cfg)
    before, _ = plant.deflection()
    for _ in range(500):
        plant.step(ZERO)
    after, _ = plant.deflection()
    assert before == pytest.approx(1e-4 * 2500 / (critical_load(paper_model) - 2500), rel=1e-6)
    assert after == pytest.approx(before, rel=1e-9), "no start-up transient"


def test_measurement_noise_has_the_configured_rms_and_a_reproducible_seed(paper_model):
    cfg = plant_config({"noise": {"strain": 1e-7, "load": 2.0, "seed": 7},
                        "load": {"start": 1000.0, "end": 1000.0}})
    runs = []
    for _ in range(2):
        plant = Plant(paper_model, cfg)
        samples = []
        for _ in range(6000):
            strain, load = plant.measure()
            samples.append([*strain, load])
        runs.append(np.array(samples))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert np.std(runs[0][:, :4], axis=0) == pytest.approx([1e-7] * 4, rel=0.05)
    assert np.std(runs[0][:, 4]) == pytest.approx(2.0, rel=0.05)
    assert np.mean(runs[0][:, 4]) == pytest.approx(1000.0, abs=0.1)


def test_load_ramp_holds_then_ramps_then_stays():
    ramp = LoadRamp(start=260.0, end=4000.0, rate=100.0, hold=1.0)
    assert ramp.load_at(0.5) == 260.0
    assert ramp.load_at(2.0) == pytest.approx(360.0)
    assert ramp.load_at(100.0) == 4000.0
    assert ramp.duration() == pytest.approx(1.0 + 37.4)


def test_plant_config_is_validated(tmp_path):
    with pytest.raises(ConfigError, match=r"noise\.strain"):
        plant_config({"noise": {"strain": -1.0}})
    with pytest.raises(ConfigError, match=r"bow\.amplitud"):
        plant_config({"bow": {"amplitud": 1e-4}})
    with pytest.raises(ConfigError, match="modes_per_plane"):
        plant_config({"modes_per_plane": 1})
    f = tmp_path / "plant.yaml"
    f.write_text("bow: {amplitude: 1.5e-4, angle_deg: 234}\n")
    assert load_plant_config(f).bow.amplitude == 1.5e-4


@pytest.mark.parametrize("section, key, value", [("bow", "amplitude", 0.161),
                                                 ("eccentricity", "amplitude", 0.2),
                                                 ("noise", "strain", 0.2)])
def test_an_imperfection_or_noise_in_the_wrong_unit_is_refused_naming_it(section, key, value):
    """A bow of 0.161 (m for mm) was taken: every run then failed at 260 N."""
    expected = rf"{section}\.{key} = {value:g}: expected a finite number from 0 to"
    with pytest.raises(ConfigError, match=expected):
        plant_config({section: {key: value}}, "plant.yaml")


def test_a_beam_nobody_holds_past_its_critical_load_comes_to_rest_on_its_end_stops(paper_model):
    """Before, the lost beam grew without bound: numpy overflowed and every later figure said
    nan. Now it rests on the stops, 5 % of its length (20 mm) from straight, whichever way it
    goes (45 deg: both components under the stop, the radius not), with finite strains."""
    fcr = critical_load(paper_model)
    stop = END_STOP_FRACTION * paper_model.params.beam.length
    for angle in (30.0, 45.0):
        cfg = plant_config({"bow": {"amplitude": 1e-4, "angle_deg": angle},
                            "load": {"start": 0.9 * fcr, "end": 1.05 * fcr, "rate": 2000.0}})
        plant = Plant(paper_model, cfg)
        assert plant.on_stops_since is None, "at rest, 0.9 Fx,cr: nowhere near the stops"
        forces = np.zeros(4)
        with np.errstate(all="raise"):          # an overflow fails the test
            for _ in range(int(2.0 / plant.period_s)):
                plant.step(forces)
                strains, _ = plant.measure()
        deflection, direction = plant.deflection()
        assert plant.on_stops_since is not None and plant.on_stops_since < 1.5, "it reached the stops"
        assert 0.9 * stop < deflection <= 1.05 * stop, f"{angle} deg: {deflection * 1e3:.2f} mm"
        assert np.all(np.isfinite(strains)) and np.max(np.abs(strains)) < 0.01, strains
        assert direction == pytest.approx(angle, abs=5.0), "it rests where it was going"


def test_a_beam_set_at_rest_past_its_stops_starts_on_them(paper_model):
    """Loaded uncontrolled to 99.5 % of Fx,cr, the bowed beam's static shape is past 20 mm: the
    run starts with it on its stops, not beyond them."""
    fcr = critical_load(paper_model)
    cfg = plant_config({"bow": {"amplitude": 1.61e-4, "angle_deg": 234.0},
                        "load": {"start": 0.995 * fcr, "end": 0.995 * fcr, "rate": 100.0}})
    plant = Plant(paper_model, cfg)
    assert plant.on_stops_since == 0.0
    assert plant.deflection()[0] <= 1.0001 * END_STOP_FRACTION * paper_model.params.beam.length
