"""The robust check: rigs of an uncertainty box, the loads they are checked at, and the facts the
first design's study measured (it loses a softer or a late-answering rig below that rig's own
critical load)."""

import math

import numpy as np
import pytest

from beamctl.config.schema import ConfigError
from beamctl.gains.build import build_table
from beamctl.gains.robust import (
    DEFAULT_BOX,
    Box,
    Range,
    box_from_dict,
    check_loads,
    evaluate,
    rig_of,
    robust_check,
)
from beamctl.gains.schedule import GainSchedule
from beamctl.models import build_model, load_parameters


@pytest.fixture(scope="module")
def paper_design():
    """The first design (integral LQR, 2500 Hz, gains every 50 N), built without its check."""
    return build_table(build_model(load_parameters()), check=False)


def test_a_rig_of_the_box_applies_factors_offsets_and_values(paper_design):
    values = {"beam.youngs_modulus": 0.95, "io.delay_samples": 0.75,
              "sensors.strain_gauge_positions[1]": 1e-3, "damping.ratios": 2.0,
              "actuators.force_constant_n_per_v": 1.2, "sample_rate_hz": 0.99}
    rig = rig_of(paper_design, DEFAULT_BOX, values)
    nominal = paper_design.model_parameters
    assert rig.params.beam.youngs_modulus == pytest.approx(0.95 * nominal.beam.youngs_modulus, rel=1e-15)
    assert rig.params.sensors.strain_gauge_positions == pytest.approx(
        (nominal.sensors.strain_gauge_positions[0], nominal.sensors.strain_gauge_positions[1] + 1e-3))
    assert rig.params.damping.ratios == pytest.approx(tuple(2 * r for r in nominal.damping.ratios))
    assert rig.chain.delay_samples == 0.75
    assert rig.force_gain == 1.2
    assert rig.sample_rate_hz == pytest.approx(0.99 * paper_design.design.sample_rate_hz)


def test_check_loads_cover_the_grid_in_steps_of_at_most_50_n_and_finely_near_fx_cr():
    grid = np.arange(0.0, 4000.0 + 1e-9, 100.0)
    loads = check_loads(grid, critical_n=3057.5, box=DEFAULT_BOX)
    assert loads[0] == 0.0 and loads[-1] == 4000.0
    assert np.max(np.diff(loads)) <= 50.0 + 1e-9, "a gap wider than 50 N"
    assert set(grid) | set(grid[:-1] + 50.0) <= set(loads.tolist()), "grid loads and midpoints are checked"
    near = loads[(loads > 3057.5 * 0.97) & (loads < 3057.5 * 1.03)]
    assert np.max(np.diff(near)) <= DEFAULT_BOX.fine_step_n + 1e-9, "coarse steps near the critical load"


def test_the_first_design_holds_the_nominal_rig_beyond_its_critical_load(paper_design):
    schedule = GainSchedule.from_table(paper_design)
    r = evaluate(paper_design, schedule, DEFAULT_BOX, "nominal", {})
    assert r.held_load_n == 4000.0 and r.ratio > 1.2, r


@pytest.mark.parametrize("values, low, high", [
    # measured by the robustness study with 100 N steps: stable to 3000 N (E x0.95, own Fx,cr 3057 N)
    ({"beam.youngs_modulus": 0.95}, 2950.0, 3057.0),
    # one sample late: stable to 3100 N, below the nominal beam's 3194 N
    ({"io.delay_samples": 1.0}, 3050.0, 3194.0),
])
def test_the_first_design_loses_a_mismatched_rig_below_its_own_critical_load(paper_design, values, low, high):
    """The fact that motivates the robust design: the first design does not hold a rig 5 %
    softer, or one that answers a sample late, up to that rig's own critical load."""
    schedule = GainSchedule.from_table(paper_design)
    r = evaluate(paper_design, schedule, DEFAULT_BOX, "case", values)
    assert low <= r.held_load_n < high, f"held {r.held_load_n} N, expected in [{low}, {high}) N"
    assert r.ratio < 1.0 and r.limit.spectral_radius >= 1.0
    assert r.limit.load_n > r.held_load_n


def test_robust_check_runs_its_scenarios_in_worker_processes(paper_design):
    box = Box(parameters={"io.delay_samples": Range("value", 0.0, 1.0),
                          "beam.youngs_modulus": Range("factor", 0.99, 1.01)},
              corner_parameters=1, random=1, seed=3, max_step_n=50.0)
    progress = []
    result = robust_check(paper_design, box, workers=2, progress=lambda d, t, s: progress.append((d, t)))
    names = [s.name for s in result.scenarios]
    # nominal, 2 parameters x 2 ends (the delay's low end is its nominal 0: not run twice), 2 corners, 1 draw
    assert names[0] == "nominal" and len(names) == 1 + 3 + 2 + 1, names
    assert result.worst_ratio == min(s.ratio for s in result.scenarios)
    assert result.corner_parameters == ("io.delay_samples",), "the delay did the most harm"
    assert progress[-1][0] == progress[-1][1] == len(names)
    data = result.to_dict()["robust"]
    assert data["worst_ratio"] == result.worst_ratio and data["worst_scenario"]["name"] == result.worst.name
    assert all(math.isfinite(s["ratio"]) for s in data["scenarios"])


@pytest.mark.parametrize("data, key", [
    ({"parameters": {"beam.colour": {"factor": [0.9, 1.1]}}}, "box.parameters.beam.colour"),
    ({"parameters": {"beam.youngs_modulus": {"scale": [0.9, 1.1]}}}, "box.parameters.beam.youngs_modulus"),
    ({"parameters": {"beam.youngs_modulus": {"factor": [1.1, 0.9]}}},
     "box.parameters.beam.youngs_modulus.factor"),
    ({"parameters": {"io.delay_samples": {"value": [-1, 1]}}}, "box.parameters.io.delay_samples.value"),
    ({"parameters": {"sample_rate_hz": {"offset": [-1, 1]}}}, "box.parameters.sample_rate_hz"),
    ({"parameters": {"beam.youngs_modulus": {"factor": [0.9, 1.1]}}, "random": -1}, "box.random"),
    ({"parameters": {"beam.youngs_modulus": {"factor": [0.9, 1.1]}}, "corners": ["beam.radius"]},
     "box.corners"),
    ({"parameters": {}}, "box.parameters"),
    ({"parameters": {"beam.youngs_modulus": {"factor": [0.9, 1.1]}}, "seeds": 1}, "box.seeds"),
])
def test_a_bad_box_is_refused_naming_the_key(data, key):
    with pytest.raises(ConfigError) as err:
        box_from_dict(data, load_parameters())
    assert err.value.key == key, f"refused {err.value.key!r}, expected {key!r}: {err.value}"


def test_the_default_box_round_trips_through_its_dict():
    params = load_parameters()
    again = box_from_dict(DEFAULT_BOX.to_dict(), params)
    assert again == DEFAULT_BOX
