"""``beamctl model``: what a user sees."""

import json
import subprocess
import sys
from pathlib import Path

from beamctl.models import build_model, critical_load, load_parameters
from beamctl.tools.cli import main


def test_json_reports_critical_load_and_eigenfrequencies_by_load(capsys):
    assert main(["model", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert abs(out["critical_load_N"] - 3194.0) <= 3.0
    for load in ("0", "1000", "2000", "3000"):
        f = out["eigenfrequencies_Hz"][load]
        assert len(f) == 3 and f == sorted(f), f"three ascending frequencies at {load} N: {f}"
    assert abs(out["eigenfrequencies_Hz"]["2000"][0] - 123.6) <= 0.5
    assert out["eigenfrequencies_Hz"]["0"][0] > out["eigenfrequencies_Hz"]["3000"][0]


def test_table_names_the_critical_load(capsys):
    assert main(["model"]) == 0
    out = capsys.readouterr().out
    assert "Fx,cr = 3193.5 N" in out
    assert "123.57" in out and "466.19" in out


def test_plot_writes_figures_5b_and_6(tmp_path, capsys):
    assert main(["model", "--plot", str(tmp_path / "figs")]) == 0
    for name in ("fig5b_eigenfrequencies.png", "fig6_frequency_response.png"):
        png = tmp_path / "figs" / name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", f"{name} is not a PNG"
        assert png.stat().st_size > 10_000


def test_bad_config_exits_2_naming_the_key(tmp_path, capsys):
    f = tmp_path / "bad.yaml"
    f.write_text("supports: {lateral_stiffness: -3}\n")
    assert main(["model", "--config", str(f)]) == 2
    err = capsys.readouterr().err
    assert "supports.lateral_stiffness" in err and "-3" in err and "expected" in err


def test_plot_into_a_file_path_is_refused(tmp_path, capsys):
    f = tmp_path / "not-a-dir"
    f.write_text("")
    assert main(["model", "--plot", str(f)]) == 2
    assert "directory" in capsys.readouterr().err


def test_console_script_is_installed():
    script = Path(sys.executable).parent / "beamctl"
    assert script.exists(), f"{script} missing: install the package (pip install -e .)"
    result = subprocess.run([str(script), "model", "--json"], capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stderr
    assert "critical_load_N" in json.loads(result.stdout)


def test_a_model_buckling_below_3000_N_is_reported_with_its_buckled_rows(tmp_path, capsys):
    f = tmp_path / "soft.yaml"
    f.write_text("supports: {lateral_stiffness: 2.0e6, actuator_stiffness: 5.0e6}\n")
    assert main(["model", "--config", str(f)]) == 0
    out = capsys.readouterr().out
    critical = critical_load(build_model(load_parameters(f)))
    assert critical < 2500.0, "soft supports: the beam buckles below 2500 N"
    assert f"Fx,cr = {critical:.1f} N" in out and "(0.78 Fx,cr)" in out, out
    assert out.count("buckled") == 2, "f1 has buckled at 2500 N and 3000 N"
    assert main(["model", "--config", str(f), "--json"]) == 0
    reduced = json.loads(capsys.readouterr().out)["reduced_model"]
    assert reduced["relative_error"]["3000"][0] is None and reduced["reference_load_fraction"] == 0.78
