"""``beamctl study`` on Dask: the laws, the same rows whatever runs them, a resumed study, a
worker lost mid-study, and censored samples (never failed) kept apart from failures."""

import csv
import json
import signal
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml

from beamctl.config.schema import ConfigError
from beamctl.gains.defaults import paper_table_path
from beamctl.simulation.study import draw, study_from_dict, summarise, survival
from beamctl.tools.cli import main

distributed = pytest.importorskip("distributed")

# a small linear study: 6 rigs of a box-like scatter, coarse load steps, against the paper's
# design (it assumes a direct I/O chain, so every rig fails within the table and the delay
# matters most; the shipped design holds most of these rigs to the table's end)
STUDY = {"study": {
    "kind": "linear", "samples": 6, "seed": 3, "designs": [str(paper_table_path())],
    "parameters": {
        "model.beam.youngs_modulus": {"law": "uniform", "low": 72.0e9, "high": 79.6e9},
        "model.supports.rotational_stiffness": {"law": "normal", "mean": 192.4, "std": 15.0},
        "io.delay_samples": {"law": "truncated-normal", "mean": 0.5, "std": 0.2, "low": 0.0, "high": 1.0},
        "actuators.force_constant_n_per_v": {"law": "uniform", "low": 2.4, "high": 3.6}},
    "linear": {"max_step_n": 200, "fine_step_n": 40, "resolution_n": 5.0}}}


def _on(design) -> dict:
    """The small study against ``design``. The tests that run it on Dask take the paper's design
    on its coarser 250 N grid (tests/conftest.py's other_table): each sample's full walk from the
    table's first load checks a quarter of the loads of the shipped 50 N grid (0.4 s instead of
    1.4 s), and it loses the same six rigs within its table, the delay moving the onset most and
    down (Spearman -0.89 on either grid)."""
    return {"study": {**STUDY["study"], "designs": [str(design)]}}


def _write(tmp_path: Path, data: dict, name: str = "study.yaml") -> str:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return str(path)


def _rows(folder: Path) -> list[dict]:
    with open(folder / "samples.csv", newline="") as f:
        return sorted(csv.DictReader(f), key=lambda r: (int(r["sample"]), r["design"]))


def test_the_laws_stay_within_their_bounds_and_the_seed_fixes_the_draw():
    study = study_from_dict({"study": {**STUDY["study"], "samples": 2000}})
    values = draw(study)
    e, kr, delay, k = values.T
    assert e.min() >= 72.0e9 and e.max() <= 79.6e9
    assert delay.min() >= 0.0 and delay.max() <= 1.0, "truncated to [0, 1]"
    assert abs(kr.mean() - 192.4) < 3 * 15.0 / np.sqrt(2000) and abs(kr.std() - 15.0) < 1.0
    np.testing.assert_array_equal(values, draw(study))
    lhs = study_from_dict({"study": {**STUDY["study"], "samples": 50, "sampling": "latin-hypercube",
                                     "parameters": {"model.beam.youngs_modulus": STUDY["study"]["parameters"][
                                         "model.beam.youngs_modulus"]}}})
    strata = np.floor((draw(lhs)[:, 0] - 72.0e9) / (7.6e9 / 50)).astype(int)
    assert sorted(strata.tolist()) == list(range(50)), "one sample in each of 50 strata"


@pytest.mark.parametrize("change, key", [
    ({"parameters": {"model.beam.colour": {"law": "uniform", "low": 0, "high": 1}}},
     "study.parameters.model.beam.colour"),
    ({"parameters": {"model.beam.radius": {"law": "gamma", "k": 2}}},
     "study.parameters.model.beam.radius.law"),
    ({"parameters": {"model.beam.radius": {"law": "normal", "mean": 4e-3, "std": -1}}},
     "study.parameters.model.beam.radius.std"),
    ({"sampling": "latin-hypercube"}, "study.sampling"),
    ({"samples": 0}, "study.samples"),
    ({"kind": "nonlinear"}, "study.kind"),
    ({"designs": ["no-such-table.yaml"]}, "study.designs"),
    ({"linear": {"resolution_n": 0}}, "study.linear.resolution_n"),
])
def test_a_bad_study_file_is_refused_naming_the_key(change, key):
    with pytest.raises(ConfigError) as info:
        study_from_dict({"study": {**STUDY["study"], **change}})
    assert info.value.key == key


@pytest.fixture(scope="module")
def study(other_table) -> dict:
    return _on(other_table)


@pytest.fixture(scope="module")
def embedded(tmp_path_factory, study):
    """The study on the embedded local cluster (two worker processes)."""
    folder = tmp_path_factory.mktemp("embedded")
    config = _write(folder, study)
    assert main(["study", "--config", config, "--out", str(folder / "out"), "--workers", "2"]) == 0
    return folder / "out"


def test_the_study_writes_one_row_per_sample_a_summary_and_figures(embedded):
    """Each row: the onset (unstable from there, within the table) or, censored, the table's end
    4000 N; the worst ratio is a failure's."""
    rows = _rows(embedded)
    assert [int(r["sample"]) for r in rows] == list(range(6))
    for r in rows:
        onset, critical = float(r["onset_n"]), float(r["critical_load_n"])
        assert 2500 < critical < 3500, "the rig's own critical load, E and kr scattered"
        assert float(r["ratio"]) == pytest.approx(onset / critical)
        assert r["censored"] in ("true", "false"), f"censored is written true or false: {r}"
        if r["censored"] == "true":
            assert onset == 4000.0 and r["reason"] == "stable to the end of the table (4000 N)", r
        else:
            assert onset < 4000.0 and r["reason"].startswith(f"unstable from {onset:.0f} N"), r
    failed = [float(r["ratio"]) for r in rows if r["censored"] == "false"]
    assert failed, "the paper's design loses these rigs within the table (censored rows: tests below)"
    summary = json.loads((embedded / "summary.json").read_text())
    design = next(iter(summary["designs"].values()))
    assert summary["samples"] == 6 and design["censored"] == 6 - len(failed)
    assert summary["worst_ratio"] == (pytest.approx(min(failed)) if failed else None), (
        "the worst ratio is the lowest of a failure, never a censored sample's lower bound")
    delay = design["sensitivity"]["io.delay_samples"]
    assert list(design["sensitivity"])[0] == "io.delay_samples" and delay < 0, (
        f"a design that assumes no delay: the delay moves the onset most, and down: {design['sensitivity']}")
    for name in ("study_ratio.png", "study_failure_probability.png"):
        assert (embedded / name).read_bytes()[:4] == b"\x89PNG"


def test_a_stopped_study_resumes_where_it_stopped(embedded, study, dask_cluster, tmp_path, capsys):
    """Run again on a folder cut short, the study keeps its rows and runs the others (on the
    shared cluster: what is tested is the folder, the embedded cluster is tested above)."""
    folder = tmp_path / "out"
    folder.mkdir()
    for name in ("study.json",):
        (folder / name).write_text((embedded / name).read_text())
    lines = (embedded / "samples.csv").read_text().splitlines()
    (folder / "samples.csv").write_text("\n".join(lines[:3]) + "\n" + lines[3][:20])   # 2 rows and a cut one
    config = _write(tmp_path, study)
    assert main(["study", "--config", config, "--out", str(folder), "--scheduler", dask_cluster.address,
                 "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["resumed"] == 2 and summary["run"] == 4
    assert _rows(folder) == _rows(embedded)


def test_a_folder_of_another_study_is_refused(embedded, study, tmp_path, capsys):
    config = _write(tmp_path, {"study": {**study["study"], "seed": 4}})
    assert main(["study", "--config", config, "--out", str(embedded)]) == 2
    assert "another study" in capsys.readouterr().err


def test_an_existing_cluster_gives_the_rows_of_the_embedded_one(dask_cluster, embedded, study, tmp_path):
    config = _write(tmp_path, study)
    out = tmp_path / "out"
    assert main(["study", "--config", config, "--out", str(out), "--scheduler", dask_cluster.address]) == 0
    assert _rows(tmp_path / "out") == _rows(embedded)


def test_a_worker_killed_mid_study_loses_no_sample(study, dask_cluster, tmp_path):
    """The rows of a worker that died are computed again elsewhere: every sample once. (The
    shared cluster's worker is killed: the fixture starts a new one for the next test.)"""
    from beamctl.simulation.study import study_from_dict as parse
    from beamctl.simulation.study_run import run_study

    eight = parse({"study": {**study["study"], "samples": 8}})
    killed = threading.Event()
    victim = dask_cluster.workers[0]

    def kill_after_the_first_row(done, total, label):
        if not killed.is_set():
            victim.kill()
            killed.set()

    with distributed.Client(dask_cluster.address, timeout=30) as client:
        rows, counts = run_study(eight, tmp_path, client, progress=kill_after_the_first_row)
    assert killed.is_set() and victim.wait(timeout=10) == -signal.SIGKILL
    assert sorted(r["sample"] for r in rows) == list(range(8))
    assert [int(r["sample"]) for r in _rows(tmp_path)] == list(range(8)), "written once each"


def test_an_experiment_sample_runs_the_load_ramp_on_its_own_rig():
    """The time-domain kind, one sample: the rig's own beam (E drawn), its stacks, the shipped
    scenario's bow; the controller holds it past the rig's own critical load until the stacks
    run out, and a rig whose parameters give no valid model is a row with the reason."""
    from beamctl.simulation.study import run_task, tasks

    study = study_from_dict({"study": {
        "kind": "experiment", "samples": 1, "seed": 1,
        "parameters": {"model.beam.youngs_modulus": {"law": "uniform", "low": 75.0e9, "high": 77.0e9},
                       "actuators.force_constant_n_per_v": {"law": "uniform", "low": 2.9, "high": 3.1}},
        "experiment": {"plant": {"load": {"start": 1500.0, "end": 3800.0, "rate": 400.0, "hold": 0.2}}}}})
    row = run_task(tasks(study)[0])
    assert row["critical_load_n"] == pytest.approx(3194.0, rel=0.02), "Table 1's beam, E within 1.3 %"
    assert 1.0 < row["ratio"] < 1.1, f"held past its own Fx,cr until the stacks ran out: {row}"
    assert row["reason"].startswith("deflection passed 1.5 mm") and row["censored"] is False, row
    short = study_from_dict({"study": {**study.to_dict(), "experiment": {"plant": {"load": {
        "start": 1500.0, "end": 2500.0, "rate": 400.0, "hold": 0.2}}}}})
    row = run_task(tasks(short)[0])
    assert row["censored"] is True and row["onset_n"] == pytest.approx(2500.0, abs=1.0), (
        f"a ramp that ends below Fx,cr with the beam held is censored at its end: {row}")
    assert row["reason"].startswith("ramp ended at 2500 N"), row
    bad = study_from_dict({"study": {"kind": "experiment", "samples": 1, "seed": 1, "parameters": {
        "model.damping.ratios[0]": {"law": "uniform", "low": 0.5, "high": 0.6}}}})
    row = run_task(tasks(bad)[0])
    assert np.isnan(row["ratio"]) and row["reason"].startswith("invalid rig: damping.ratios")
    assert row["censored"] is False, "an invalid rig is no observation, censored or failed"


def test_a_whole_list_key_scales_every_element():
    """model.damping.ratios as a factor (box B's damping x[0.5, 2]): both ratios scale together,
    which is what keeps the Rayleigh damping positive."""
    from beamctl.simulation.study import run_task, tasks

    factor = {"law": "uniform", "low": 2.0, "high": 2.0 + 1e-9}
    study = study_from_dict({"study": {"kind": "linear", "samples": 1, "seed": 1,
                                       "linear": STUDY["study"]["linear"],
                                       "parameters": {"model.damping.ratios": factor}}})
    row = run_task(tasks(study)[0])
    assert np.isfinite(row["ratio"]) and row["critical_load_n"] == pytest.approx(3193.5, abs=0.5), (
        "damping does not move the critical load")


def test_a_worker_needs_no_copy_of_the_design_files(study, tmp_path):
    """The client sends the tables' contents: a design path the worker cannot read still runs."""
    from beamctl.simulation.study import design_texts, run_task, tasks

    study = study_from_dict(study)
    texts = design_texts(study)
    task = tasks(study)[0]
    elsewhere = "/nonexistent/on/this/worker/paper.yaml"
    moved = type(task)(**{**task.__dict__, "design": elsewhere})
    row = run_task(moved, {elsewhere: texts[study.designs[0]]})
    assert row == {**run_task(task, texts), "design": elsewhere}


def test_a_drawn_list_element_keeps_the_design_s_other_elements():
    """An experiment sample builds its rig from the design's own model (a fitted one, say), not
    from Table 1: drawing damping.ratios[1] leaves the design's ratios[0] as it was."""
    import dataclasses

    from beamctl.gains.defaults import default_table_path
    from beamctl.gains.table import load_table
    from beamctl.models.params import parameters_from_dict
    from beamctl.simulation.study import drawn_rig, tasks

    table = load_table(default_table_path())
    model = table.model_parameters.to_dict()
    model["damping"]["ratios"] = [0.0225, 0.00675]          # a design of its own damping
    table = dataclasses.replace(table, model_parameters=parameters_from_dict(model))

    def ratios(key: str, value: float) -> list[float]:
        law = {"law": "uniform", "low": value, "high": value * (1 + 1e-12)}
        study = study_from_dict({"study": {"kind": "linear", "samples": 1, "seed": 1,
                                           "parameters": {key: law}}})
        return drawn_rig(tasks(study)[0], table).params.to_dict()["damping"]["ratios"]

    assert ratios("model.damping.ratios[1]", 0.005) == pytest.approx([0.0225, 0.005], rel=1e-11)
    assert ratios("model.damping.ratios", 2.0) == pytest.approx([0.045, 0.0135], rel=1e-11), (
        "a whole list is scaled")


def _linear_row(design: str, youngs_modulus: float) -> dict:
    """The row of a linear sample of ``design`` on Table 1's beam with its E set."""
    from beamctl.simulation.study import run_task, tasks

    e = {"law": "uniform", "low": youngs_modulus, "high": youngs_modulus * (1 + 1e-9)}
    study = study_from_dict({"study": {"kind": "linear", "samples": 1, "seed": 1, "designs": [design],
                                       "linear": STUDY["study"]["linear"],
                                       "parameters": {"model.beam.youngs_modulus": e}}})
    return run_task(tasks(study)[0])


def test_a_linear_sample_unstable_before_the_end_of_the_table_has_its_onset():
    """The paper's design loses a beam 5 % softer at about 3000 N, below the rig's own Fx,cr of
    3057 N, and holds the nominal beam to the end of its table, 4000 N (README, "Known limits")."""
    from beamctl.gains.defaults import default_table_path

    paper = str(Path(default_table_path()).with_name("paper.yaml"))
    soft = _linear_row(paper, 0.95 * 75.8e9)
    assert soft["censored"] is False, f"unstable within the table, not censored: {soft}"
    assert 2950.0 < soft["onset_n"] < soft["critical_load_n"] < 3100.0, (
        f"the paper's design loses the softer beam near 3000 N, below its own Fx,cr: {soft}")
    assert soft["reason"].startswith(f"unstable from {soft['onset_n']:.0f} N"), soft
    nominal = _linear_row(paper, 75.8e9)
    assert nominal["censored"] is True and nominal["onset_n"] == 4000.0, (
        f"the nominal beam is stable to the end of the paper's table: {nominal}")
    assert nominal["ratio"] == pytest.approx(4000.0 / nominal["critical_load_n"]), "a lower bound"
    assert nominal["reason"] == "stable to the end of the table (4000 N)"


def _hand_rows(design: str, onsets_n: list[float], censored: list[bool]) -> list[dict]:
    """Rows of rigs of Fx,cr 3200 N with these onsets (censored: the end, a lower bound)."""
    return [{"sample": i, "design": design, "model.beam.youngs_modulus": 75.8e9 + i * 1e8,
             "onset_n": x, "critical_load_n": 3200.0, "ratio": x / 3200.0, "censored": c,
             "reason": "", "seed": 1} for i, (x, c) in enumerate(zip(onsets_n, censored, strict=True))]


def test_kaplan_meier_quantiles_of_censored_rows_agree_with_a_hand_calculation():
    """Eight rows, four censored (c). The product-limit estimate by hand, at risk n and failing d
    at each failure, F = 1 - S:

    ratio  0.95  1.00c  1.05  1.10  1.15c  1.20  1.25c  1.25c
    n, d   8, 1         6, 1  5, 1         3, 1
    S      7/8          7/8 5/6 = 35/48   35/48 4/5 = 28/48   28/48 2/3 = 7/18
    F      1/8          13/48             20/48               11/18

    so the 1 % and 5 % quantiles are 0.95, the median 1.20 (F first reaches 1/2 there; counting
    the censored as failures would give 1.10, dropping them 1.05), and the 95 % quantile is
    undetermined: F ends at 11/18 at the largest ratio observed, 1.25."""
    onsets_n = [3040.0, 3200.0, 3360.0, 3520.0, 3680.0, 3840.0, 4000.0, 4000.0]     # the ratios x 3200 N
    censored = [False, True, False, False, True, False, True, True]
    rows = _hand_rows("a.yaml", onsets_n, censored)
    km = survival(rows)
    np.testing.assert_allclose(km.probability, [1 / 8, 13 / 48, 20 / 48, 11 / 18], rtol=1e-12,
                               err_msg="the Kaplan-Meier failure probability at 0.95, 1.05, 1.10, 1.20")
    d = summarise(rows, ["model.beam.youngs_modulus"], 0.0)["designs"]["a.yaml"]
    assert d["ratio_quantiles"] == {"1": 0.95, "5": 0.95, "50": 1.20, "95": None}, (
        f"Kaplan-Meier quantiles, the 95 % one beyond the data: {d['ratio_quantiles']}")
    assert d["ratio_quantiles_beyond"] == {"95": 1.25}, "the undetermined quantile lies above 1.25"
    assert (d["failures"], d["censored"], d["censored_from_ratio"], d["worst_ratio"]) == (4, 4, 1.00, 0.95)
    assert "4 censored ones at their lower bound" in d["sensitivity_basis"]


def test_a_design_whose_samples_all_held_has_no_worst_ratio_only_a_lower_bound():
    d = summarise(_hand_rows("held.yaml", [4000.0, 4000.0, 4000.0], [True, True, True]), [], 0.0)
    assert d["worst_ratio"] is None and d["worst_ratio_at_least"] == 1.25, (
        "no sample failed: no worst ratio, the lowest censored ratio as its lower bound")
    design = d["designs"]["held.yaml"]
    assert design["worst_ratio"] is None and design["worst_ratio_at_least"] == 1.25
    assert all(q is None for q in design["ratio_quantiles"].values()), design["ratio_quantiles"]


def test_a_censored_row_is_never_a_failure_of_the_failure_probability(tmp_path):
    """Three rigs unstable from 3400, 3600 and 3800 N and two stable to the table's end, 4000 N:
    the probability of failure rises at the three onsets only (1/5, 2/5, 3/5) and stays at 3/5 up
    to 4000 N, where the estimate ends: no step at 4000 N. The figures draw this estimate."""
    rows = _hand_rows("t.yaml", [3400.0, 3600.0, 3800.0, 4000.0, 4000.0], [False, False, False, True, True])
    km = survival(rows, "onset_n")
    np.testing.assert_allclose(km.failure_at, [3400.0, 3600.0, 3800.0],
                               err_msg="only the onsets are failures, never the censored 4000 N")
    np.testing.assert_allclose(km.at([3399.0, 3400.0, 3700.0, 3999.0, 4000.0]), [0.0, 0.2, 0.4, 0.6, 0.6],
                               err_msg="the estimate is flat from 3800 N to 4000 N")
    assert km.end == 4000.0 and km.censored_at.tolist() == [4000.0, 4000.0]
    from beamctl.reports import plots

    paths = plots.study_figures(rows, ["t.yaml"], tmp_path)
    assert [p.read_bytes()[:4] for p in paths] == [b"\x89PNG"] * 2


def test_a_delay_drawn_below_zero_is_an_invalid_rig_not_a_rig_without_delay():
    """A normal law can draw a negative delay: the sample's row says the rig is invalid (its
    drawn value would otherwise stand in the row for a rig run with no delay)."""
    from beamctl.gains.defaults import default_table_path
    from beamctl.gains.table import load_table
    from beamctl.simulation.study import drawn_rig, tasks

    law = {"law": "uniform", "low": -2.0, "high": -1.9}
    for kind in ("linear", "experiment"):
        study = study_from_dict({"study": {"kind": kind, "samples": 1, "seed": 1,
                                           "parameters": {"io.delay_samples": law}}})
        with pytest.raises(ConfigError, match="io.delay_samples"):
            drawn_rig(tasks(study)[0], load_table(default_table_path()))
