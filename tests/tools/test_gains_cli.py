"""``beamctl gains build|check|show``."""

import contextlib
import io
import json

import pytest

from beamctl.gains.table import load_table
from beamctl.tools.cli import main
from beamctl.tools.gains_cmd import parse_grid

# the paper's design (integral LQR, 2500 Hz) builds in seconds; the robust check is left out
PAPER_BUILD = ("gains", "build", "--design", "integral-lqr", "--no-robust")


def test_build_writes_a_checked_table_and_shows_progress(tmp_path, capsys, paper_params):
    out = tmp_path / "g.yaml"
    assert main([*PAPER_BUILD, "--grid", "0:2000:1000", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "gains build:" in captured.err and "100 %" in captured.err, "progress on stderr"
    assert "3 grid points" in captured.out and f"wrote {out}" in captured.out
    assert "robust check skipped (--no-robust)" in captured.out, "a build that skips the robust part says so"
    table = load_table(out, paper_params)
    assert list(table.loads_n) == [0.0, 1000.0, 2000.0] and table.all_stable


def test_unstable_table_is_not_written_without_force(tmp_path, capsys):
    out = tmp_path / "beyond.yaml"
    assert main([*PAPER_BUILD, "--grid", "4000:4500:500", "--out", str(out)]) == 1
    assert not out.exists()
    assert "UNSTABLE" in capsys.readouterr().out
    assert main([*PAPER_BUILD, "--grid", "4000:4500:500", "--out", str(out), "--force"]) == 0
    assert "forced" in capsys.readouterr().out and out.exists()


def test_check_json_lists_every_point_and_midpoint(tmp_path, capsys):
    out = tmp_path / "g.yaml"
    main([*PAPER_BUILD, "--grid", "0:2000:1000", "--out", str(out)])
    capsys.readouterr()
    assert main(["gains", "check", str(out), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert [p["load_N"] for p in result["points"]] == [0.0, 500.0, 1000.0, 1500.0, 2000.0]
    assert result["all_stable"] is True
    assert set(result["points"][0]) == {"load_N", "spectral_radius", "stable", "min_damping", "gain_load_N"}


def test_show_prints_the_design_and_plots_gains(tmp_path, capsys):
    assert main(["gains", "show", "--plot", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "design lqg for 6000 Hz" in out and "interpolate" in out and "all stable" in out
    assert (tmp_path / "gains_vs_load.png").stat().st_size > 10_000


@pytest.mark.parametrize("grid", ["0:4000", "a:b:c", "100:0:50", "0:4000:0", "0:1e9:1"])
def test_bad_grid_is_refused(grid, capsys):
    assert main([*PAPER_BUILD, "--grid", grid, "--out", "/dev/null"]) == 2
    assert "--grid" in capsys.readouterr().err


def test_grid_includes_its_end():
    assert list(parse_grid("0:4000:50"))[-1] == 4000.0 and len(parse_grid("0:4000:50")) == 81


def test_mismatched_table_is_a_clean_error(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: beamctl-gain-table/3\nloads_N: [0, .nan]\n")
    assert main(["gains", "check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "loads_N" in err and "Traceback" not in err


# -- the robust check: a search for the worst rig -------------------------------------------------

# every phase of the search on a budget of a few rigs each: the command's output, status and
# worst-rig file are what these tests are about (the search's own are tests/gains/test_robust.py)
SMALL_BOX = """box:
  parameters:
    beam.youngs_modulus: {factor: [0.95, 1.05]}
    io.delay_samples: {value: [0.0, 1.0]}
  seed: 7
  population: 6
  generations: 1
  margin: 4
  refine: 4
  starts: 1
  verify: 1
"""


@pytest.fixture(scope="module")
def robust_run(tmp_path_factory, other_table):
    """``gains check --robust --json --worst-rig`` over a small box, once: in this process, its
    output captured (the command's output and status are what is tested), and with ``--workers 1``
    its rigs evaluated here too (starting worker processes costs seconds; the worker processes'
    search is the build's below, and Ctrl-C's). The table is the paper's design on its 250 N grid
    (tests/conftest.py): its nominal check and the verification's walk take a quarter of the
    loads of the shipped 50 N grid."""
    where = tmp_path_factory.mktemp("robust")
    box = where / "box.yaml"
    box.write_text(SMALL_BOX)
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(["gains", "check", str(other_table), "--robust", "--box", str(box), "--json",
                       "--worst-rig", str(where / "worst.yaml"), "--workers", "1"])
    return status, json.loads(out.getvalue()), err.getvalue(), where


def test_the_robust_check_reports_the_worst_rig_it_found_as_json(robust_run):
    status, report, err, _ = robust_run
    robust = report["robust"]
    assert set(robust) >= {"worst_ratio", "worst_rig", "onset_N", "critical_load_N", "pole_hz", "evaluated",
                           "worst_rig_si", "verified", "box"}, sorted(robust)
    assert set(robust["worst_rig"]) == {"beam.youngs_modulus", "io.delay_samples"}
    assert robust["worst_ratio"] == pytest.approx(robust["onset_N"] / robust["critical_load_N"])
    assert 6 * 2 <= robust["evaluated"] <= 6 * 2 + 4 + 4 + 1 + 1, robust["evaluated"]
    # the paper's design loses rigs of this box below their own Fx,cr (README: a sample late, E x0.95;
    # on the 250 N grid, the stiff beam early in the sample is lost first)
    assert robust["worst_ratio"] < 1.0 and status == 1, (status, robust["worst_ratio"])
    assert "robust check:" in err and "100 %" in err, "no progress on stderr with --json"
    assert "Traceback" not in err


def test_the_worst_rig_is_written_as_a_scenario_of_the_experiment(robust_run):
    """The scenario names the rig's own beam and delay, and stacks that do not limit: the
    controller believes 4 x 3 N/V, and the rig's own stacks give as much (a stack gain of 1)."""
    from beamctl.assembly.run import plant_parameters
    from beamctl.models import load_parameters
    from beamctl.simulation.experiment import experiment_config

    _, report, _, where = robust_run
    robust = report["robust"]
    cfg, settings = experiment_config(__import__("yaml").safe_load((where / "worst.yaml").read_text()))
    assert settings["paper_mode"] is False
    rig = plant_parameters(cfg)
    assert rig.beam.youngs_modulus == pytest.approx(
        robust["worst_rig"]["beam.youngs_modulus"] * load_parameters().beam.youngs_modulus, rel=1e-12)
    assert cfg.plant["io"]["delay_samples"] == pytest.approx(robust["worst_rig"]["io.delay_samples"])
    assert cfg.controller.actuators.force_constant_n_per_v == 12.0
    assert cfg.hal.sim["own_actuators"] and cfg.hal.sim["actuators"]["force_constant_n_per_v"] == 12.0


def test_ctrl_c_ends_the_robust_check_with_130_and_no_traceback(tmp_path, other_table):
    from tests.processes import beamctl, interrupt_when

    box = tmp_path / "box.yaml"
    box.write_text(SMALL_BOX.replace("generations: 1", "generations: 50"))
    # the paper's design on its 250 N grid: its nominal check before the search takes a quarter
    # of a second, the shipped table's three; the search it interrupts runs in worker processes
    # all the same
    process = beamctl("gains", "check", str(other_table), "--robust", "--box", str(box), "--json",
                      cwd=tmp_path)
    status, err = interrupt_when(process, b"robust check: ")
    assert status == 130, err[-2000:]
    assert "Traceback" not in err, err[-2000:]


def test_a_dask_cluster_finds_the_worst_rig_the_search_here_finds(robust_run, other_table, dask_cluster,
                                                                   capsys):
    """The search spread over a Dask scheduler and two workers (processes on 127.0.0.1) is the
    same search: the same seed evaluates the same rigs and finds the same worst one."""
    _, here, _, where = robust_run
    main(["gains", "check", str(other_table), "--robust", "--box", str(where / "box.yaml"), "--json",
          "--scheduler", dask_cluster.address])
    out, err = capsys.readouterr()
    there = json.loads(out)["robust"]
    assert there["worst_rig"] == here["robust"]["worst_rig"], err[-2000:]
    assert there["onset_N"] == here["robust"]["onset_N"] and there["evaluated"] == here["robust"]["evaluated"]


def test_build_runs_the_robust_check_over_its_box_with_progress(tmp_path, capsys):
    """The robust part of a build says what it will do and how long it has left, and reports the
    worst rig; the paper's design loses rigs of the small box: exit status 1, the table written."""
    box = tmp_path / "box.yaml"
    box.write_text(SMALL_BOX)
    out = tmp_path / "g.yaml"
    status = main(["gains", "build", "--design", "integral-lqr", "--grid", "0:4000:500", "--box", str(box),
                   "--out", str(out)])
    captured = capsys.readouterr()
    assert "robust check: searching" in captured.err and "robust check: 100 %" in captured.err, captured.err
    assert "worst onset / own Fx,cr" in captured.out and "NOT HELD" in captured.out, captured.out
    assert status == 1 and out.exists()
    from beamctl.gains.table import load_table
    recorded = load_table(out, verify=False).robust
    assert recorded is not None and recorded["worst_ratio"] < 1.0 and recorded["evaluated"] >= 12, recorded
    assert main(["gains", "show", str(out)]) == 0
    assert "robust check: NOT HELD" in capsys.readouterr().out, "the table says what its check found"


@pytest.mark.parametrize("flags", [["--seed", "3"], ["--box", "b.yaml"], ["--scheduler", "tcp://x:1"],
                                   ["--worst-rig", "w.yaml"], ["--workers", "2"], ["--record"]])
def test_a_robust_flag_without_robust_is_refused(flags, capsys):
    assert main(["gains", "check", *flags]) == 2
    err = capsys.readouterr().err
    assert flags[0] in err and "--robust" in err and "Traceback" not in err


def test_recording_into_the_shipped_table_is_refused(capsys):
    assert main(["gains", "check", "--robust", "--record"]) == 2
    err = capsys.readouterr().err
    assert "--record" in err and "shipped tables are not changed" in err
    assert len(err.strip().splitlines()) == 1, err


def test_show_answers_in_json(capsys):
    assert main(["gains", "show", "--json"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown["design"] == "lqg" and shown["all_stable"] and shown["content_matches"], shown.keys()
    assert len(shown["gains_A_y"]["D"]) == len(shown["loads_N"]) and "unit" in shown["gains_A_y"]


def test_build_answers_in_json_with_its_lines_on_stderr(tmp_path, capsys):
    out = tmp_path / "g.yaml"
    assert main(["gains", "build", "--design", "integral-lqr", "--grid", "0:4000:500", "--no-robust",
                 "--out", str(out), "--json"]) == 0
    captured = capsys.readouterr()
    built = json.loads(captured.out)
    assert built["written"] and built["file"] == str(out), built
    assert built["all_stable"] and built["grid_points"] == 9, built
    assert "wrote" in captured.err and "robust check skipped" in captured.err


def test_stalls_compares_the_live_limit_with_the_survival_edge_as_json(capsys):
    """At 3300 N (past the nominal Fx,cr of 3194 N) the shipped table's limit is finite and a
    stall of it is survived on the simulated rig; the edge the search finds lies above it."""
    assert main(["gains", "stalls", "--loads", "3300", "--rig", "nominal", "--json"]) == 0
    captured = capsys.readouterr()
    row, = json.loads(captured.out)["nominal"]
    assert row["held_without_stall"] and 1 <= row["limit_samples"] < row["edge_samples"], row
    assert not row["edge_beyond_cap"], f"no stall up to the cap was lost at 3300 N: {row}"
    assert "stalls, nominal" in captured.err and "100 %" in captured.err, "progress on stderr"


@pytest.mark.parametrize("flags, named", [(["--loads", "3950"], "--loads"),
                                          (["--loads", "3300,x"], "--loads"),
                                          (["--rig", "softest"], "--rig")])
def test_stalls_refuses_loads_beyond_the_table_and_unknown_rigs(flags, named, capsys):
    assert main(["gains", "stalls", *flags]) == 2
    err = capsys.readouterr().err
    assert named in err and "Traceback" not in err, err
