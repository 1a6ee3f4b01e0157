"""The robust check: rigs of an uncertainty box, where each one's loop goes unstable, and the search
for the worst of them (it must find rigs that only hurt in combination)."""

from dataclasses import replace

import numpy as np
import pytest

from beamctl.config.schema import ConfigError
from beamctl.gains.build import build_table
from beamctl.gains.rig import RigPlane
from beamctl.gains.robust import (
    DEFAULT_BOX,
    Box,
    Margin,
    Onset,
    Range,
    Refused,
    box_from_dict,
    check_loads,
    dask_evaluator,
    describe,
    evaluate,
    local_evaluator,
    rig_of,
    search_loads,
    search_worst,
)
from beamctl.gains.schedule import GainSchedule
from beamctl.models import build_model, load_parameters

# the paper's design over a small box of E and the delay: cheap enough to search in a test. Every
# phase of the search runs (a generation after the first, the climbs, two refinements, the
# verification) on a budget of 49 rigs, 40 or so evaluated; the search of three generations of
# 10 rigs and more than twice the budget finds the same worst rig, the box's corner
SMALL_BOX = Box(parameters={"beam.youngs_modulus": Range("factor", 0.95, 1.05),
                            "io.delay_samples": Range("value", 0.0, 1.0)},
                seed=7, population=8, generations=1, margin=16, refine=12, starts=2, verify=1)


@pytest.fixture(scope="module")
def paper_design():
    """The first design (integral LQR, 2500 Hz, gains every 50 N), built without its check."""
    return build_table(build_model(load_parameters()), check=False)


@pytest.fixture(scope="module")
def schedule(paper_design):
    return GainSchedule.from_table(paper_design)


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


def test_the_search_walks_every_load_from_the_first_and_finely_above_half_fx_cr():
    grid = np.arange(0.0, 4000.0 + 1e-9, 100.0)
    loads = search_loads(grid, critical_n=3000.0, step_n=200.0)
    assert loads[0] == 0.0 and loads[-1] == 4000.0
    steps = np.diff(loads)
    assert np.all(steps > 0)
    assert np.max(steps[loads[1:] > 1500.0]) <= 200.0 + 1e-9, "steps above half Fx,cr wider than 200 N"
    assert np.max(steps) <= 800.0 + 1e-9


def test_the_first_design_holds_the_nominal_rig_to_the_end_of_its_table(paper_design, schedule):
    r = evaluate(paper_design, schedule, DEFAULT_BOX, {})
    assert r.censored and r.onset_n is None, f"the nominal rig went unstable at {r.onset_n} N"
    assert r.stable_to_n == 4000.0 and r.ratio == pytest.approx(4000.0 / r.critical_load_n)
    assert r.ratio > 1.2, r


@pytest.mark.parametrize("values, low, high", [
    # measured by the robustness study with 100 N steps: stable to 3000 N (E x0.95, own Fx,cr 3057 N)
    ({"beam.youngs_modulus": 0.95}, 2950.0, 3057.0),
    # one sample late: stable to 3100 N, below the nominal beam's 3194 N
    ({"io.delay_samples": 1.0}, 3050.0, 3194.0),
])
def test_the_first_design_loses_a_mismatched_rig_below_its_own_critical_load(paper_design, schedule, values,
                                                                               low, high):
    """The fact that motivates the robust design: the first design does not hold a rig 5 %
    softer, or one that answers a sample late, up to that rig's own critical load. The onset is
    bisected: the loop is stable at ``stable_to_n`` and unstable at ``onset_n``, within 1 N."""
    r = evaluate(paper_design, schedule, DEFAULT_BOX, values)
    assert not r.censored and low <= r.onset_n < high, f"onset {r.onset_n} N, expected in [{low}, {high}) N"
    assert 0 < r.onset_n - r.stable_to_n <= DEFAULT_BOX.resolution_n, (r.stable_to_n, r.onset_n)
    assert r.ratio == pytest.approx(r.onset_n / r.critical_load_n) and r.ratio < 1.0
    rig = rig_of(paper_design, DEFAULT_BOX, values)
    plane = RigPlane(build_model(rig.params), rig.chain, rig.sample_rate_hz, rig.force_gain)
    comp = paper_design.compensator

    def radius(load):
        m = plane.loop_matrix(load, schedule.matrices_at(load), comp.h, comp.plane_states["y"], comp.period_s)
        return np.max(np.abs(np.linalg.eigvals(m)))

    assert radius(r.stable_to_n) < 1.0 <= radius(r.onset_n), "the bisection's ends are not stable/unstable"


def test_the_search_and_full_walks_agree_on_a_rig_s_onset(paper_design, schedule):
    """The search's coarse walk (200 N steps) and the check's full walk (50 N, 10 N near Fx,cr)
    bisect to the same onset when the loop has one crossing: within the 1 N resolution."""
    values = {"beam.youngs_modulus": 0.97, "io.delay_samples": 0.6}
    coarse = evaluate(paper_design, schedule, DEFAULT_BOX, values, mode="search")
    full = evaluate(paper_design, schedule, DEFAULT_BOX, values, mode="full")
    assert abs(coarse.onset_n - full.onset_n) <= 1.0, (coarse.onset_n, full.onset_n)
    assert coarse.points < full.points, "the search's walk is not cheaper than the full one"


def test_the_search_finds_the_worst_of_a_small_box_as_a_grid_scan_does(paper_design, schedule):
    """An independent look: a 3 x 3 grid over (E, delay) evaluated rig by rig. The search (40 or so
    rigs) must find a rig at least as bad as the grid's worst, less a margin of 0.005 (the grid's
    points are not where the search lands), and report it as it evaluates again. The box's worst
    lies at a corner (the stiffest beam a sample late, 0.933): the 5 x 5 grid over the box finds
    the same worst there as this one, which holds the corners, the edges' middles and the centre."""
    grid = [evaluate(paper_design, schedule, SMALL_BOX, {"beam.youngs_modulus": e, "io.delay_samples": d},
                     mode="search").ratio
            for e in np.linspace(0.95, 1.05, 3) for d in np.linspace(0.0, 1.0, 3)]
    progress = []
    with local_evaluator(paper_design, SMALL_BOX, workers=1) as evaluator:
        result = search_worst(paper_design, SMALL_BOX, evaluator, lambda d, t, s: progress.append((d, t)))
    assert result.worst_ratio <= min(grid) + 0.005, f"search {result.worst_ratio:.4f}, grid {min(grid):.4f}"
    again = evaluate(paper_design, schedule, SMALL_BOX, result.worst.values)
    assert again.onset_n == result.worst.onset_n and again.ratio == result.worst_ratio
    counted = len(result.evaluated) + len(result.margins) + len(result.verified)
    assert result.count == counted <= SMALL_BOX.budget
    assert progress[-1][0] == progress[-1][1] == result.count, progress[-3:]
    data = result.to_dict(paper_design)["robust"]
    assert data["worst_ratio"] == result.worst_ratio and data["evaluated"] == result.count
    assert set(data["worst_rig"]) == set(SMALL_BOX.parameters)
    assert data["worst_rig_si"]["beam.youngs_modulus"] == pytest.approx(
        data["worst_rig"]["beam.youngs_modulus"] * paper_design.model_parameters.beam.youngs_modulus)


def _interacting(jobs, each=None):
    """A made-up box of four parameters that do no harm alone: the ratio drops below 1 only where
    u0 and u1 are both high and u2 lies near 0.4 (a delay inside the sample); u3 does nothing."""
    out = []
    for values, _mode, _band in jobs:
        u = [values[f"p{i}"] for i in range(4)]
        ratio = 1.2 - 0.3 * u[0] ** 2 * u[1] ** 2 * max(0.0, 1.0 - abs(u[2] - 0.4) / 0.2)
        out.append(Onset(values=dict(values), critical_load_n=3000.0, onset_n=3000.0 * ratio,
                         stable_to_n=3000.0 * ratio - 1, ratio=ratio, pole_hz=100.0, spectral_radius=1.0,
                         points=1))
        if each:
            each(out[-1])
    return out


def test_the_search_finds_parameters_that_only_hurt_together(paper_design):
    """One parameter at a time (each at its ends, the others nominal) sees 1.2 everywhere; the
    worst, 0.9, needs u0 = u1 = 1 and u2 = 0.4 together. The search gets within 0.02 of it."""
    box = Box(parameters={f"p{i}": Range("value", 0.0, 1.0) for i in range(4)}, seed=3, population=16,
              generations=6, refine=200, starts=2, verify=2)
    one_at_a_time = _interacting([({**{f"p{j}": 0.5 for j in range(4)}, f"p{i}": end}, "search", None)
                                  for i in range(4) for end in (0.0, 1.0)])
    assert min(r.ratio for r in one_at_a_time) > 1.1
    result = search_worst(paper_design, box, _interacting)
    assert result.worst_ratio < 0.92, f"the search stopped at {result.worst_ratio:.4f}: {result.worst.values}"
    again = search_worst(paper_design, box, _interacting)
    assert again.worst.values == result.worst.values, "the same seed found another rig"


def _two_ways(jobs, each=None):
    """A made-up box where the loop fails two ways: the 30-300 Hz band at 1.1 + 0.1 u0 nearly
    everywhere, and the 300-1300 Hz band at 1.35 - 0.5 g with g = u1^2 u2^2 (1 - |u3 - 0.4| / 0.3)+:
    below 1.1 only in a small corner, 0.85 at its bottom. The growth rate of a band at load ratio r
    is 10 (r - its onset ratio); the walk goes from 0.5 to the onset in steps of 0.05."""
    out = []
    for values, mode, ratio in jobs:
        u = [values[f"p{i}"] for i in range(4)]
        g = u[1] ** 2 * u[2] ** 2 * max(0.0, 1.0 - abs(u[3] - 0.4) / 0.3)
        onsets = np.array([np.inf, 1.1 + 0.1 * u[0], 1.35 - 0.5 * g, np.inf])

        def growth(r, onsets=onsets):
            return tuple(float(x) for x in np.where(np.isfinite(onsets), 10.0 * (r - onsets), -np.inf))

        if mode == "margin":
            out.append(Margin(values=dict(values), critical_load_n=3000.0, load_n=3000.0 * ratio,
                              growth=growth(ratio)))
        else:
            first = float(onsets.min())
            walk = np.arange(0.5, first, 0.05)
            out.append(Onset(values=dict(values), critical_load_n=3000.0, onset_n=3000.0 * first,
                             stable_to_n=3000.0 * first - 1.0, ratio=first, pole_hz=100.0,
                             spectral_radius=1.0, points=1, mode=mode, walk_loads_n=tuple(3000.0 * walk),
                             walk_growth=tuple(growth(r) for r in walk)))
        if each:
            each(out[-1])
    return out


def test_the_search_climbs_to_a_way_of_failing_that_another_hides(paper_design):
    """Where one way of failing comes first nearly everywhere, a small global search sees only it
    (1.1); climbing the other band's growth rate at the worst ratio so far finds the corner where
    the other fails first (0.85). Without the climb the same search stops near 1.1."""
    box = Box(parameters={f"p{i}": Range("value", 0.0, 1.0) for i in range(4)}, seed=5, population=8,
              generations=1, margin=300, refine=120, starts=2, verify=2)
    found = search_worst(paper_design, box, _two_ways)
    assert found.worst_ratio < 0.87, f"the search stopped at {found.worst_ratio:.4f}: {found.worst.values}"
    blind = search_worst(paper_design, replace(box, margin=0), _two_ways)
    assert blind.worst_ratio > 1.0, f"without the climb the search found {blind.worst_ratio:.4f}: not hidden"


def test_a_dask_cluster_evaluates_the_rigs_of_the_processes_here(paper_design, dask_cluster):
    """The same rigs on a Dask cluster (a scheduler and two worker processes on 127.0.0.1, shared
    with the other tests that send it work: tests/conftest.py) and in worker processes here: the
    same onsets, in the order asked."""
    import distributed

    jobs = [({"beam.youngs_modulus": 0.96, "io.delay_samples": 0.8}, "search", None),
            ({"beam.youngs_modulus": 1.04, "io.delay_samples": 0.1}, "search", 2),
            ({"beam.youngs_modulus": 1.0, "io.delay_samples": 0.5}, "full", None)]
    with local_evaluator(paper_design, SMALL_BOX, workers=2) as evaluator:
        here = evaluator(jobs)
    with distributed.Client(dask_cluster.address, timeout=30) as client:
        there = dask_evaluator(client, paper_design, SMALL_BOX)(jobs)
    assert [(r.onset_n, r.critical_load_n, r.mode) for r in there] == \
        [(r.onset_n, r.critical_load_n, r.mode) for r in here]


def test_a_rig_is_described_in_a_line_with_units():
    text = describe({"beam.youngs_modulus": 1.05, "io.delay_samples": 0.4,
                     "sensors.strain_gauge_positions[0]": -1e-3, "sample_rate_hz": 0.99})
    assert text == "E x1.050, delay 0.40, gauge 1 -1.00 mm, rate x0.990", text


@pytest.mark.parametrize("data, key", [
    ({"parameters": {"beam.colour": {"factor": [0.9, 1.1]}}}, "box.parameters.beam.colour"),
    ({"parameters": {"beam.youngs_modulus": {"scale": [0.9, 1.1]}}}, "box.parameters.beam.youngs_modulus"),
    ({"parameters": {"beam.youngs_modulus": {"factor": [1.1, 0.9]}}},
     "box.parameters.beam.youngs_modulus.factor"),
    ({"parameters": {"io.delay_samples": {"value": [-1, 1]}}}, "box.parameters.io.delay_samples.value"),
    ({"parameters": {"sample_rate_hz": {"offset": [-1, 1]}}}, "box.parameters.sample_rate_hz"),
    ({"parameters": {"beam.youngs_modulus": {"factor": [0.9, 1.1]}}, "population": 2}, "box.population"),
    ({"parameters": {"beam.youngs_modulus": {"factor": [0.9, 1.1]}}, "strategy": "guess"}, "box.strategy"),
    ({"parameters": {"beam.youngs_modulus": {"factor": [0.9, 1.1]}}, "resolution_n": 0}, "box.resolution_n"),
    ({"parameters": {"beam.youngs_modulus": {"factor": [0.9, 1.1]}}, "corners": 5}, "box.corners"),
    ({"parameters": {}}, "box.parameters"),
    ({"parameters": {"beam.youngs_modulus": {"factor": [0.9, 1.1]}}, "seeds": 1}, "box.seeds"),
])
def test_a_bad_box_is_refused_naming_the_key(data, key):
    with pytest.raises(ConfigError) as err:
        box_from_dict(data, load_parameters())
    assert err.value.key == key, f"refused {err.value.key!r}, expected {key!r}: {err.value}"


def test_a_box_file_s_load_steps_are_spelled_as_the_study_file_s():
    """``max_step_n`` in a box file as in a study file's ``linear:``; the spelling of before
    (``max_step_N``) is refused in one line naming the key to write instead."""
    base = {"parameters": {"beam.youngs_modulus": {"factor": [0.9, 1.1]}}}
    assert box_from_dict({**base, "max_step_n": 25.0}, load_parameters()).max_step_n == 25.0
    for old in ("max_step_N", "fine_step_N", "resolution_N", "search_step_N"):
        with pytest.raises(ConfigError) as err:
            box_from_dict({**base, old: 10.0}, load_parameters())
        message = str(err.value)
        assert err.value.key == f"box.{old}" and f"box.{old[:-2]}_n in its place" in message, message


def test_the_default_box_round_trips_through_its_dict():
    params = load_parameters()
    again = box_from_dict(DEFAULT_BOX.to_dict(), params)
    assert again == DEFAULT_BOX
    assert box_from_dict(replace(DEFAULT_BOX, seed=9).to_dict(), params).seed == 9


def test_rigs_the_model_refuses_are_counted_and_named_not_a_dead_search(paper_design):
    """A box part of which is no rig (a rotational stiffness of 0 N m/rad or below, which the
    model refuses): searched in two worker processes, those rigs are counted and named with the
    model's refusal, the search keeps to the rest and finds its worst; the refusal crosses the
    process boundary as itself (a refusal that did not pickle broke the pool before)."""
    box = Box(parameters={"beam.youngs_modulus": Range("factor", 0.95, 1.05),
                          "supports.rotational_stiffness": Range("value", -150.0, 250.0)},
              seed=7, population=8, generations=1, margin=16, refine=12, starts=2, verify=1)
    with local_evaluator(paper_design, box, workers=2) as evaluator:
        result = search_worst(paper_design, box, evaluator)
    assert result.refused, "the search drew no rig from the refused part of the box (a third of it)"
    assert all(isinstance(r, Refused) and r.values["supports.rotational_stiffness"] <= 0.0
               and "supports.rotational_stiffness" in r.reason for r in result.refused), result.refused[:3]
    assert result.worst.values["supports.rotational_stiffness"] > 0.0 and np.isfinite(result.worst_ratio)
    data = result.to_dict(paper_design)["robust"]
    assert data["refused"] == len(result.refused) and data["refused_rigs"][0]["refused"]
    text = result.refused_text()
    assert f"{len(result.refused)} rigs of the box" in text and "partly invalid" in text, text


def test_a_box_of_no_rig_at_all_is_refused_naming_the_box(paper_design):
    box = Box(parameters={"supports.rotational_stiffness": Range("value", -100.0, -1.0)},
              seed=7, population=8, generations=1, margin=16, refine=12, starts=2, verify=1)
    with local_evaluator(paper_design, box, workers=1) as evaluator, pytest.raises(ConfigError) as info:
        search_worst(paper_design, box, evaluator)
    assert info.value.key == "box" and "every rig searched was refused" in str(info.value)

