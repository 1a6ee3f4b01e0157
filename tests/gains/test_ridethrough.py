"""Ride-through: the compensator's strain prediction and the limits of the loop a table carries
(gains/ridethrough.py), checked against the estimator's own model and in the time domain."""

from dataclasses import replace

import numpy as np
import pytest
import yaml

from beamctl.gains import lqg
from beamctl.gains.build import build_lqg_table, build_table, check_plan, nominal_rig, ride_through_plan
from beamctl.gains.compensator import PLANE_CHANNELS
from beamctl.gains.defaults import LQG_CHAIN, LQG_SETTINGS, default_table_path, paper_table_path
from beamctl.gains.ridethrough import (
    BRIDGES,
    CONFIDENCE_SIGMA,
    GrowthAnalysis,
    RideThrough,
    _DelayedPlant,
    _fold,
    _places,
    gap_loop,
    mode1_row,
)
from beamctl.gains.rig import RigPlane
from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import GainTableError, content_sha256, load_table, write_table
from beamctl.models.analysis import critical_load
from beamctl.models.fe import build_model, plane_indices
from beamctl.models.modal import reduce
from tests.rounding import EPS, assert_within, eigenvector_rounding, product_rounding, symmetric_pencil

# libyaml where it is installed: the same YAML documents as the pure-Python reader and writer
# make, read and written ten times faster (a table of the small LQG is 140 kB of matrices)
_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
_DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


@pytest.fixture(scope="module")
def shipped():
    return load_table(default_table_path())


@pytest.fixture(scope="module")
def small_lqg(paper_model):
    """The shipped LQG's design on two grid points, checked and analysed."""
    return build_lqg_table(paper_model, [2000.0, 3000.0])


def _estimator_model(model, settings, load, plane, period):
    """Phi, Gamma and Cf of the Kalman filter's design model at ``load`` (gains/lqg.py)."""
    ref = settings.reference_load_fraction * critical_load(model)
    pm = lqg.plane_model(model, plane, settings.n_modes, ref)
    s = settings.at_load(load)
    k_el = pm.k_elastic.copy()
    k_el[0, 0] -= s.estimator_mode1_load_offset_n * pm.k_geometric[0, 0]
    sm = lqg.sampled_model(replace(pm, k_elastic=k_el), load, period, LQG_CHAIN)
    phi, gamma, cf, _ = lqg._with_fir(sm, tuple(s.strain_fir))
    return phi, gamma, cf


def _modal_rounding(model, settings, plane):
    """Relative error of the design model's mode shapes on any CPU: the estimator's Phi, Gamma and
    Cf are built linearly from the plane's first n_modes eigenvectors at the reference load, which
    a backward-stable solver gets to eps lambda_max / gap (tests/rounding.py: 7e-9 for the paper's
    beam; OpenBLAS's kernels were seen to differ by up to 3e-10 of the largest entry)."""
    ref = settings.reference_load_fraction * critical_load(model)
    idx = plane_indices(model.n_nodes, plane)
    lam = symmetric_pencil(model.load_stiffness(ref)[np.ix_(idx, idx)], model.mass[np.ix_(idx, idx)])
    return eigenvector_rounding(lam, settings.n_modes)


@pytest.mark.parametrize("load", [0.0, 2000.0, 3300.0, 4000.0])
def test_a_prediction_step_of_the_shipped_table_is_the_estimator_s_time_update(paper_model, shipped, load):
    """x_c = [p; r] (p the estimator's prediction of the design state and the FIR's past strains,
    r the raw past strains): with y = P x_c the step x_c <- A x_c + B y + E u gives exactly
    p <- Phi p + Gamma u, the time update without a measurement, and feeds r the predicted raw
    strain P x_c. The model is rebuilt here, the table was built on another CPU: they agree to the
    rounding of the mode shapes (``_modal_rounding``); what the step adds is a product's rounding."""
    comp = shipped.compensator
    i = list(shipped.loads_n).index(load)
    point = comp.point(i)
    assert shipped.design.parameters == LQG_SETTINGS.to_dict()
    for plane in ("y", "z"):
        modal = _modal_rounding(paper_model, LQG_SETTINGS, plane)
        part = point.plane(comp.plane_states[plane], plane)
        phi, gamma, cf = _estimator_model(paper_model, LQG_SETTINGS, load, plane, comp.period_s)
        na = phi.shape[0]
        step = part.a + part.b @ part.predict
        rounding = product_rounding(part.b, part.predict) + EPS * np.abs(part.a)
        scale = np.abs(phi).max()
        assert_within(step[:na, :na], phi, modal * scale + rounding[:na, :na], f"{plane}: A + B P, Phi")
        assert_within(step[:na, na:], 0.0, modal * scale + rounding[:na, na:], f"{plane}: A + B P, strains")
        assert_within(part.e[:na], gamma, modal * np.abs(gamma).max(), f"{plane}: E against Gamma")
        # the raw past strains: the newest is the predicted strain, the older ones shift
        assert_within(step[na:na + 2], part.predict, rounding[na:na + 2], f"{plane}: the newest raw strain")
        np.testing.assert_array_equal(step[na + 2:, na:na + 2], np.eye(2))
        # and the filtered value of the predicted raw strain is the estimator's expected one:
        # b0 (x / b0) and b0 (-b_j / b0) + b_j are each within two roundings of x and of 0
        b = LQG_SETTINGS.strain_fir
        filtered = b[0] * part.predict + np.hstack([np.zeros((2, na)), b[1] * np.eye(2), b[2] * np.eye(2)])
        assert_within(filtered[:, :na], cf, modal * np.abs(cf).max(), f"{plane}: b0 P against Cf")
        assert_within(filtered[:, na:], 0.0, 2 * EPS * np.abs(b).max(), f"{plane}: b0 P + F")


def test_without_the_strain_filter_the_prediction_is_cf_p(paper_model):
    """nf = 0: x_c = p and y_hat = Cf p, so A + B P = Phi and E = Gamma."""
    settings = replace(LQG_SETTINGS, strain_fir=(1.0,))
    h = reduce(paper_model).c0_phi_inv
    comp = lqg.design(paper_model, [3000.0], 6000.0, LQG_CHAIN, h, settings)
    part = comp.point(0).plane(comp.plane_states["y"], "y")
    phi, gamma, cf = _estimator_model(paper_model, settings, 3000.0, "y", comp.period_s)
    np.testing.assert_allclose(part.predict, cf, rtol=0, atol=0)
    np.testing.assert_allclose(part.a + part.b @ part.predict, phi, rtol=0, atol=1e-9 * np.abs(phi).max())
    np.testing.assert_array_equal(part.e, gamma)


def test_the_planes_predict_apart_and_the_paper_s_design_predicts_nothing(shipped):
    comp = shipped.compensator
    assert comp.predict.shape == (comp.n_points, 4, comp.n_states)
    for plane, other in (("y", "z"), ("z", "y")):
        rows = list(PLANE_CHANNELS[plane])
        assert not np.any(comp.predict[:, rows][:, :, comp.plane_states[other]])
    assert load_table(paper_table_path()).compensator.predict is None


def test_the_schedule_interpolates_the_prediction_like_the_other_matrices(shipped):
    schedule = GainSchedule.from_table(shipped)
    p = shipped.compensator.predict
    np.testing.assert_allclose(schedule.matrices_at(2050.0).predict, 0.5 * (p[20] + p[21]), rtol=1e-12,
                               atol=1e-12 * np.abs(p).max())
    np.testing.assert_array_equal(schedule.matrices_at(2000.0).predict, p[20])


# ---------------------------------------------------------------------------------------------
# the table file


def test_a_table_with_prediction_and_ride_through_reads_back_as_written(tmp_path, small_lqg, paper_params):
    rt = small_lqg.ride_through
    assert rt is not None and rt.criterion == "absolute" and small_lqg.compensator.predict is not None
    path = write_table(small_lqg, tmp_path / "t.yaml")
    back = load_table(path, paper_params)
    np.testing.assert_array_equal(back.compensator.predict, small_lqg.compensator.predict)
    assert back.intact and back.sha256 == small_lqg.sha256
    b = back.ride_through
    assert (b.gap_grid_samples, b.loads_n, b.rigs) == (rt.gap_grid_samples, rt.loads_n, rt.rigs)
    # written to 6 decimals: a growth is read back to within 5e-7 of it
    np.testing.assert_allclose(b.growth, rt.growth, rtol=0, atol=5.1e-7)
    assert b.answer_budgets_periods == rt.answer_budgets_periods
    data = yaml.load(path.read_text(), Loader=_LOADER)
    assert set(data["ride_through"]) == set(RideThrough.FIELDS)
    critical = critical_load(build_model(small_lqg.model_parameters))
    assert data["ride_through"]["loads_N"] == [p[0] for p in ride_through_plan(small_lqg, critical)], (
        "every check load analysed, and every 25 N near and above the critical load")


def test_the_growth_is_a_curve_per_analysed_load_that_starts_near_one_and_does_not_fall(small_lqg):
    """Shape of what the engine reads: [bridge, output, analysed load, gap]; a one-sample gap
    barely moves the spread (the first sample's growth is within 50 % of 1: the stacks hold one
    answer), and a longer gap grows it no less."""
    rt = small_lqg.ride_through
    assert rt.growth.shape == (len(BRIDGES), 2, len(rt.loads_n), len(rt.gap_grid_samples))
    assert np.all(rt.growth >= 1.0) and np.all(np.diff(rt.growth, axis=3) >= 0.0)
    assert np.all(rt.growth[..., 0] < 1.5), rt.growth[..., 0]
    assert rt.gap_grid_samples[:8] == tuple(range(1, 9)) and rt.gap_cap_samples == 600


@pytest.fixture(scope="module")
def small_lqg_text(small_lqg, tmp_path_factory) -> str:
    """The small LQG's table as ``write_table`` writes it, once: the tests that change it start
    from a copy of the file."""
    return write_table(small_lqg, tmp_path_factory.mktemp("written") / "t.yaml").read_text()


def _written(text: str, tmp_path):
    path = tmp_path / "t.yaml"
    path.write_text(text)
    return path


def _rewrite(path, edit, rehash: bool) -> None:
    data = yaml.load(path.read_text(), Loader=_LOADER)
    edit(data)
    if rehash:
        data["sha256"] = content_sha256(data)
    path.write_text(yaml.dump(data, Dumper=_DUMPER, sort_keys=False))


def _smaller_growth(d):
    rows = d["ride_through"]["growth"]["catch_up"]["deflection"]
    rows[-1] = [1.0] * len(rows[-1])


@pytest.mark.parametrize("edit", [
    _smaller_growth,
    lambda d: d["ride_through"]["answer_budgets_periods"].__setitem__(0, 0.0),
    lambda d: d["ride_through"].__setitem__("confidence_sigma", 1.0),
    lambda d: d["compensator"]["predict"][0][0].__setitem__(0, 1.0),
    lambda d: d.pop("ride_through"),
], ids=["growth", "budget-per-load", "sigma", "predict", "ride-through-removed"])
def test_a_changed_ride_through_or_prediction_is_refused_by_the_content_hash(tmp_path, small_lqg_text, edit):
    path = _written(small_lqg_text, tmp_path)
    _rewrite(path, edit, rehash=False)
    with pytest.raises(GainTableError) as err:
        load_table(path)
    assert err.value.key == "sha256" and "changed after it was built" in str(err.value)


def _falling_growth(d):
    row = d["ride_through"]["growth"]["catch_up"]["voltage"][0]
    row[-1] = row[0] - 0.5 if row[0] > 1.5 else 1.0
    row[-2] = max(row[-1] + 1.0, 2.0)


@pytest.mark.parametrize(("edit", "key", "words"), [
    (lambda d: d["compensator"]["predict"][1].pop(), "compensator.predict", "shape"),
    (lambda d: d["ride_through"].__setitem__("criterion", "relative"), "ride_through.criterion",
     "'absolute'"),
    (lambda d: d["ride_through"].pop("confidence_sigma"), "ride_through.confidence_sigma", "this field"),
    (lambda d: d["ride_through"].__setitem__("confidence_sigma", 0.0), "ride_through.confidence_sigma",
     "> 0"),
    (lambda d: d["ride_through"].__setitem__("note", 1), "ride_through.note", "only the fields"),
    (lambda d: d.__setitem__("ride_through", [1, 2]), "ride_through", "mapping"),
    (lambda d: d["ride_through"]["gap_grid_samples"].__setitem__(1, 1), "ride_through.gap_grid_samples",
     "increasing"),
    (lambda d: d["ride_through"]["gap_grid_samples"].__setitem__(0, 0.5), "ride_through.gap_grid_samples",
     "whole numbers >= 1"),
    (lambda d: d["ride_through"]["growth"]["catch_up"]["deflection"].pop(),
     "ride_through.growth.catch_up.deflection", "one curve per analysed load"),
    (lambda d: d["ride_through"]["growth"]["catch_up"]["voltage"][0].pop(),
     "ride_through.growth.catch_up.voltage[0]", "one growth >= 1 per gap of the grid"),
    (lambda d: d["ride_through"]["growth"]["catch_up"]["voltage"][0].__setitem__(0, 0.5),
     "ride_through.growth.catch_up.voltage[0]", ">= 1"),
    (_falling_growth, "ride_through.growth.catch_up.voltage[0]", "does not fall"),
    (lambda d: d["ride_through"]["growth"].__setitem__("predict", {}), "ride_through.growth", "bridges"),
    (lambda d: d["ride_through"]["growth"]["catch_up"].pop("voltage"), "ride_through.growth.catch_up",
     "outputs"),
    (lambda d: d["ride_through"].__setitem__("rigs", []), "ride_through.rigs", "naming the rigs"),
    (lambda d: d["ride_through"]["answer_budgets_periods"].pop(), "ride_through.answer_budgets_periods",
     "one per grid load"),
    (lambda d: d["ride_through"]["max_extra_delay_samples_per_load"].__setitem__(1, -0.05),
     "ride_through.max_extra_delay_samples_per_load", ">= 0"),
    (lambda d: d["ride_through"]["answer_budgets_periods"].__setitem__(1, 0.0),
     "ride_through.answer_budgets_periods", "the design's delay"),
], ids=["predict-shape", "criterion", "sigma-missing", "sigma-zero", "unknown-field", "not-a-mapping",
        "grid-not-increasing", "grid-not-whole", "curve-missing", "curve-short", "growth-below-one",
        "growth-falls", "unknown-bridge", "output-missing", "no-rigs", "short-list", "negative-delay",
        "budget-without-design-delay"])
def test_a_malformed_ride_through_or_prediction_is_refused_in_one_line_naming_the_key(
        tmp_path, small_lqg_text, edit, key, words):
    """Even with a hash that matches (a file written by something else): each field checked."""
    path = _written(small_lqg_text, tmp_path)
    _rewrite(path, edit, rehash=True)
    with pytest.raises(GainTableError) as err:
        load_table(path)
    assert err.value.key == key and words in str(err.value), str(err.value)
    assert "\n" not in str(err.value)


def test_a_table_written_before_the_prediction_and_the_ride_through_still_loads(tmp_path, small_lqg_text):
    path = _written(small_lqg_text, tmp_path)
    _rewrite(path, lambda d: (d.pop("ride_through"), d["compensator"].pop("predict")), rehash=True)
    old = load_table(path)
    assert old.ride_through is None and old.compensator.predict is None and old.intact
    assert GainSchedule.from_table(old).matrices_at(2500.0).predict is None


def test_a_table_of_the_relative_criterion_loads_and_the_engine_uses_its_fixed_limits(
        tmp_path, small_lqg_text):
    """A section of an earlier version ('the RMS at most doubles': growth_limit) is not a
    survival criterion: the table loads, its section is not used (None), and the controller
    takes the fixed limits of a table without an analysis."""
    from beamctl.rt.config import controller_config
    from beamctl.rt.controller import LEGACY_GAP_LIMIT, ride_through_limits

    path = _written(small_lqg_text, tmp_path)
    old = {"growth_limit": 2.0, "margin": 2.0, "max_gap_samples": 8, "gap_limit_samples": 4}
    _rewrite(path, lambda d: d.__setitem__("ride_through", old), rehash=True)
    table = load_table(path)
    assert table.ride_through is None and table.intact
    limits = ride_through_limits(table, controller_config())
    assert limits.grid[0] == LEGACY_GAP_LIMIT and "without a ride-through analysis" in limits.source


def test_an_unstable_table_carries_no_ride_through(paper_model):
    """No stationary loop to ride through from."""
    table = build_table(paper_model, [4000.0, 4500.0], force=True)
    assert not table.all_stable and table.ride_through is None


# ---------------------------------------------------------------------------------------------
# the growth, against an independent computation


@pytest.fixture(scope="module")
def paper():
    return load_table(paper_table_path())


def test_the_shipped_tables_carry_an_absolute_ride_through_over_their_rigs(shipped, paper):
    for table in (shipped, paper):
        rt = table.ride_through
        assert rt is not None and rt.criterion == "absolute" and rt.confidence_sigma == CONFIDENCE_SIGMA
        analysed = set(rt.loads_n)
        assert {c.load_n for c in table.checks} <= analysed, "every check load analysed"
        fine = [x for x in np.arange(3050.0, table.loads_n[-1], 25.0) if x not in analysed]
        assert not fine, f"near and above the critical load every 25 N: {fine} N missing"
        assert rt.rigs[0] == "the nominal rig"
    assert shipped.robust is not None and len(shipped.ride_through.rigs) == 2, (
        "the shipped table records its robust check and is analysed on its worst rig too")
    assert "worst rig" in shipped.ride_through.rigs[1]


def _time_domain_growth(model, table, load, gap, runs, events, spacing, seed):
    """RMS over the stationary RMS of mode 1's modal displacement and of support A's applied
    force at each sample from a gap's first missing sample, in the time domain: the nominal rig's
    sampled plane (delayed ZOH), the compensator step written out, ``runs`` loops side by side
    driven by a white force disturbance at the stacks, each with ``events`` gaps ``spacing``
    samples apart. In a gap, as the engine bridges it (hold): the stacks hold the last answer's
    force, the compensator's state and the integral stay."""
    rng = np.random.default_rng(seed)
    comp = table.compensator
    point = GainSchedule.from_table(table).matrices_at(load).plane(comp.plane_states["y"], "y")
    io = list(PLANE_CHANNELS["y"])
    h, period = comp.h[np.ix_(io, io)], comp.period_s
    rig = nominal_rig(model, table)
    plant, c = rig.sampled(load)
    n, whole = plant.ad.shape[0], plant.whole
    out = mode1_row(model, rig, load, n)
    noise = plant.b_now + plant.b_before
    x = np.zeros((n, runs))
    xc = np.zeros((point.a.shape[0], runs))
    xi = np.zeros((2, runs))
    applied = [np.zeros((2, runs)) for _ in range(whole + 2)]       # u_k-1, u_k-2, ...

    def plant_step(u):
        nonlocal x, applied
        applied = [u, *applied[:-1]]
        x = (plant.ad @ x + plant.b_now @ applied[whole] + plant.b_before @ applied[whole + 1]
             + noise @ rng.standard_normal((2, runs)))
        applied = applied[:whole + 2]

    def sample():
        nonlocal xc, xi
        y = c @ x
        xi = xi + period * h @ y
        u = -(point.c @ xc + point.d @ y + point.ki @ xi)
        xc = point.a @ xc + point.b @ y + point.e @ u
        plant_step(u)

    for _ in range(3000):
        sample()
    q_st, f_st = [], []
    q_after, f_after = np.zeros(spacing), np.zeros(spacing)
    for _ in range(events):
        for j in range(spacing):
            q_after[j] += np.mean((out @ x) ** 2)
            f_after[j] += np.mean(applied[0][0] ** 2)
            plant_step(applied[0]) if j < gap else sample()
        for _ in range(100):
            q_st.append(np.mean((out @ x) ** 2))
            f_st.append(np.mean(applied[0][0] ** 2))
            sample()
    return np.sqrt(q_after / events / np.mean(q_st)), np.sqrt(f_after / events / np.mean(f_st))


def test_the_growth_of_a_gap_is_the_time_domain_s_at_3300_n(paper_model, shipped):
    """200 loops with 20 gaps each: the RMS at each sample after a gap's start from 4000
    samples, to about 1.1 % (sqrt(1/2 x 2 / 4000) of the RMS), the stationary RMS from 2000 x
    200 to 0.2 %; the largest of 250 such estimates exceeds the true largest by up to about 3
    sigma: 4 % above, and at most 4 % below the analysis' peak (the analysis bounds every later
    sample, the time domain follows 250). Support A's force is bounded by the voltage growth
    (the larger of the plane's two supports)."""
    load = 3300.0
    rt = shipped.ride_through
    e = rt.loads_n.index(load)
    for gap in (8, 40):
        i = rt.gap_grid_samples.index(gap) if gap in rt.gap_grid_samples else None
        comp = shipped.compensator
        point = GainSchedule.from_table(shipped).matrices_at(load)
        analysis = GrowthAnalysis(gap_loop(nominal_rig(paper_model, shipped), load, point, comp.h,
                                           comp.plane_states["y"], comp.period_s, "hold"))
        expected = analysis.growth([gap])[:, 0]
        q, f = _time_domain_growth(paper_model, shipped, load, gap, runs=200, events=20, spacing=250,
                                   seed=gap)
        assert q.max() == pytest.approx(expected[0], rel=0.04), (gap, q.max(), expected)
        assert f.max() <= 1.04 * expected[1:].max(), (gap, f.max(), expected)
        if i is not None:
            assert rt.growth[0, 0, e, i] >= expected[0] * (1 - 1e-6), "the table stores no less"
    assert q.max() > 1.5, "a 40-sample gap at 3300 N grows the deflection's spread"


def test_the_engine_s_limit_is_the_longest_gap_the_headroom_allows(shipped):
    """gap_allowed (the engine's function): the longest grid gap N with k g(N) spread <=
    headroom for both outputs, against a direct scan of the table's curves, and on from it to
    where the growth interpolated linearly in its logarithm reaches what is allowed (never as far
    as the next grid gap, whose growth is not allowed)."""
    from beamctl.rt.engine import GROWTH_CAP, gap_allowed

    rt = shipped.ride_through
    grid = np.asarray(rt.gap_grid_samples, dtype=float)
    for e in (0, len(rt.loads_n) // 2, len(rt.loads_n) - 1):
        curves = np.ascontiguousarray(rt.growth[:, :, e, :])
        assert np.all(np.diff(curves, axis=-1) >= 0.0), "the stored growth does not fall with the gap"
        for aq, av in ((1e9, 1e9), (300.0, 80.0), (30.0, 5.0), (1.0, 1.0), (0.5, 1e9)):
            # a growth at the stored cap (a loop that diverged) is never allowed
            within = []
            for n, gq, gv in zip(grid, curves[0, 0], curves[0, 1], strict=True):
                if not (gq <= aq and gv <= av and max(gq, gv) < GROWTH_CAP):
                    break
                within.append(n)
            direct = int(max(within)) if within else 0
            got = gap_allowed(curves.ravel(), 0, grid, 0, len(grid), aq, av)
            case = (rt.loads_n[e], aq, av, got, direct)
            if not within or direct == grid[-1]:
                assert got == direct, case
                continue
            i = len(within)
            if max(curves[0, 0, i], curves[0, 1, i]) >= GROWTH_CAP:
                assert got == direct, f"interpolated towards a capped growth: {case}"
                continue
            assert direct <= got < grid[i], case
            # at ``got`` the log-interpolated growth of the output that binds is what is allowed
            f = (got - grid[i - 1]) / (grid[i] - grid[i - 1])
            at = [np.exp((1 - f) * np.log(curves[0, o, i - 1]) + f * np.log(curves[0, o, i]))
                  for o in (0, 1)]
            assert at[0] <= aq * (1 + 1e-9) and at[1] <= av * (1 + 1e-9), case
            assert np.isclose(at[0], aq, rtol=1e-9) or np.isclose(at[1], av, rtol=1e-9), case


# ---------------------------------------------------------------------------------------------
# the delay


def _per_load_cases(table):
    """(grid index, load, the check loads next to it with their matrices) of three grid loads."""
    loads = list(table.loads_n)
    picks = [0, len(loads) // 2, len(loads) - 1]
    plan = check_plan(table)
    cases = []
    for i in picks:
        near = [(load, point) for load, _, point in plan
                if loads[max(i - 1, 0)] <= load <= loads[min(i + 1, len(loads) - 1)]]
        cases.append((i, loads[i], near))
    return cases


def _radius(model, table, point, load, extra):
    chain = replace(table.design.io, delay_samples=round(table.design.io.delay_samples + extra, 10))
    rig = RigPlane(model, chain, table.design.sample_rate_hz)
    comp = table.compensator
    m = rig.loop_matrix(load, point, comp.h, comp.plane_states["y"], comp.period_s)
    return float(np.max(np.abs(np.linalg.eigvals(m))))


@pytest.mark.parametrize("which", ["shipped", "paper"])
def test_the_per_load_delay_is_stable_up_to_it_with_rig_plane_s_own_sampling(paper_model, shipped, paper,
                                                                              which):
    """At grid loads, with one matrix exponential a delay: stable at every grid delay up to the
    load's limit, unstable one step above it (unless the cap)."""
    table = {"shipped": shipped, "paper": paper}[which]
    rt = table.ride_through
    step = rt.delay_step_samples
    for i, load, near in _per_load_cases(table)[1:]:
        point = dict(near)[load]
        limit = rt.max_extra_delay_samples_per_load[i]
        grid = [round(k * step, 10) for k in range(int(round(limit / step)) + 1)]
        assert all(_radius(paper_model, table, point, load, d) < 1.0 for d in grid), (load, limit)
        if limit < rt.delay_cap_samples:
            assert _radius(paper_model, table, point, load, limit + step) >= 1.0, (load, limit)
        assert rt.answer_budgets_periods[i] == table.design.io.delay_samples + limit / 2


def test_a_check_load_between_grid_loads_that_survives_less_lowers_the_lesser_end():
    """The delay's limits per grid load: a check load inside an interval with a lower limit than
    its lesser end replaces that end (the upper on a tie); one at a grid load replaces that load's."""
    loads = np.array([0.0, 100.0, 200.0])
    plan = [(0.0, None, None), (50.0, None, None), (100.0, None, None), (150.0, None, None),
            (175.0, 100.0, None), (200.0, None, None), (100.0, 0.0, None)]
    own, others = _places(plan, loads)
    assert own == [0, 2, 5]
    assert others == [(4, 1, 2), (3, 1, 2), (6, 1, 1), (1, 0, 1)], "highest load first"
    values, sources = [30, 20, 20], [0.0, 100.0, 200.0]
    _fold(values, sources, 1, 2, 12, 150.0)
    assert values == [30, 20, 12] and sources[2] == 150.0
    _fold(values, sources, 0, 1, 5, 50.0)
    assert values == [30, 5, 12] and sources[1] == 50.0


def test_the_delay_grid_s_sampling_is_rig_plane_s(paper_model, shipped):
    """The recursion over the grid's partial integrals gives the delayed ZOH of
    models.iochain.delayed_zoh to 1e-8."""
    rig = nominal_rig(paper_model, shipped)
    plant = _DelayedPlant(rig, 3500.0, 0.05)
    for extra in (0.05, 0.3, 0.65, 0.8, 1.0):
        delay = round(rig.chain.delay_samples + extra, 10)
        ours, _ = plant.sampled(delay)
        chain = replace(rig.chain, delay_samples=delay)
        theirs, _ = RigPlane(paper_model, chain, rig.sample_rate_hz).sampled(3500.0)
        assert (ours.whole, ours.fraction) == pytest.approx((theirs.whole, theirs.fraction))
        for name in ("ad", "b_now", "b_before"):
            a, b = getattr(ours, name), getattr(theirs, name)
            assert np.abs(a - b).max() <= 1e-8 * np.abs(b).max() + 1e-300, (extra, name)
