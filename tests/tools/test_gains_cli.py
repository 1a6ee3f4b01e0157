"""``beamctl gains build|check|show``."""

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
