"""``beamctl identify`` and ``beamctl model fit``: the lab's round, as a user runs it."""

import json

import numpy as np
import pytest
import scipy.io
import yaml

from beamctl.assembly.run import load_model_file, service_config
from beamctl.identification.frf_files import read_frf
from beamctl.models import build_model, critical_load
from beamctl.tools.cli import main
from tests.identification.test_identify import RIG
from tests.processes import beamctl, interrupt_when

# a short identification: 3 averaged periods of 0.5 s per input
SHORT = ("--load", "2000", "--averages", "3", "--resolution", "2")


@pytest.fixture(scope="module")
def identified(tmp_path_factory):
    folder = tmp_path_factory.mktemp("identify")
    rig = folder / "rig.yaml"
    rig.write_text(yaml.safe_dump(RIG))
    status = main(["identify", "--config", str(rig), *SHORT, "--out", str(folder / "id-2000")])
    assert status == 0
    return folder


def test_identify_writes_npz_and_mat_with_the_load_and_the_settings(identified):
    data = read_frf(identified / "id-2000.npz")
    assert abs(data.load_n - 2000.0) < 5.0, "the mean of the load cell, 2 N of noise"
    assert data.sample_rate_hz == 6000.0 and data.force_constant_n_per_v == 3.0
    assert data.settings["identify"]["averages"] == 3 and data.settings["inputs"] == ["yA", "zA", "yB", "zB"]
    mat = scipy.io.loadmat(identified / "id-2000.mat")
    assert mat["frf"].shape == (len(data.frequencies_hz), 4, 4) and np.iscomplexobj(mat["frf"])
    np.testing.assert_allclose(mat["frf"], data.frf)


def test_identify_reports_the_rig_s_resonances(identified, capsys, tmp_path):
    rig = identified / "rig.yaml"
    assert main(["identify", "--config", str(rig), *SHORT, "--supports", "A", "--json",
                 "--out", str(tmp_path / "a")]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["inputs"] == ["yA", "zA"]
    y = report["resonances_hz"]["y"]
    # the rig's own first two eigenfrequencies at 2000 N are 124.8 and 468.9 Hz (FE model of its
    # parameters); 2 Hz lines and a parabola through the peak place them within 0.5 Hz
    assert abs(y[0] - 124.8) < 0.5 and abs(y[1] - 468.9) < 0.5, y


def test_fit_json_has_the_dotted_model_keys_and_the_file_feeds_model_and_gains(identified, capsys, tmp_path):
    out = tmp_path / "fitted.yaml"
    assert main(["model", "fit", str(identified / "id-2000.npz"), "--out", str(out), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    keys = {"beam.youngs_modulus", "supports.rotational_stiffness", "supports.lateral_stiffness",
            "supports.actuator_stiffness", "damping.ratios", "actuators.force_constant_n_per_v"}
    assert set(result["parameters"]) == keys and set(result["std_errors"]) == keys
    assert result["cost"] < result["start_cost"]
    # the identification kept the static strains: this rig is straight (no bow, no eccentric load),
    # so holding it straight takes next to none of the stacks' swing; one load is a rough estimate
    stacks = result["stacks"]
    assert 0 <= stacks["at_critical"] < 0.02 and stacks["limit_n"] is None, stacks["text"]
    assert "rough" in stacks["method"] and stacks["warnings"], stacks
    fitted = load_model_file(out)
    assert fitted.beam.youngs_modulus == result["parameters"]["beam.youngs_modulus"]
    assert main(["model", "--config", str(out), "--json"]) == 0
    reported = json.loads(capsys.readouterr().out)["critical_load_N"]
    assert reported == pytest.approx(critical_load(build_model(fitted)))
    assert abs(reported - 3224.7) < 0.01 * 3224.7, "the rig's own critical load, not Table 1's 3193.5 N"
    table = tmp_path / "table.yaml"
    assert main(["gains", "build", "--design", "integral-lqr", "--no-robust", "--grid", "0:1000:1000",
                 "--config", str(out), "--out", str(table)]) == 0
    rig = {**RIG, "model": str(out), "gains": {"table": str(table)}}
    assert service_config(rig).model == fitted, "a rig's configuration takes the fitted model by its path"


def test_figure_5a_draws_the_measurement_against_the_model_before_and_after(identified, tmp_path, capsys):
    fitted = tmp_path / "fitted.yaml"
    assert main(["model", "fit", str(identified / "id-2000.npz"), "--out", str(fitted),
                 "--plot", str(tmp_path / "fit")]) == 0
    assert main(["model", "--frf", str(identified / "id-2000.npz"), "--fitted", str(fitted),
                 "--plot", str(tmp_path / "figs")]) == 0
    figs = tmp_path / "figs"
    for png in (tmp_path / "fit" / "fig5a_frequency_response.png", figs / "fig5a_frequency_response.png",
                figs / "fig5b_eigenfrequencies.png"):
        # a drawn figure, not an empty canvas (in 128 palette colours, a blank one is under 5 kB)
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000, png


def test_a_fit_that_did_not_converge_writes_nothing_and_exits_1(identified, tmp_path, capsys):
    out = tmp_path / "fitted.yaml"
    assert main(["model", "fit", str(identified / "id-2000.npz"), "--max-evaluations", "2",
                 "--out", str(out)]) == 1
    assert "not converged" in capsys.readouterr().out and not out.exists()


@pytest.mark.parametrize("argv, named", [
    (["model", "fit", "{frf}", "--params", "kr,stiffness", "--out", "{tmp}/m.yaml"], "--params"),
    (["model", "fit", "{frf}", "--band", "600:50", "--out", "{tmp}/m.yaml"], "--band"),
    (["model", "fit", "{tmp}/missing.npz", "--out", "{tmp}/m.yaml"], "missing.npz"),
    (["model", "fit", "{frf}", "--eigenfrequencies", "{tmp}/missing.csv", "--out", "{tmp}/m.yaml"],
     "--eigenfrequencies"),
    (["identify", "--load", "2000", "--amplitude", "90", "--out", "{tmp}/x"], "--amplitude"),
    (["identify", "--load", "2000", "--out", "{tmp}/x.txt"], "--out"),
    (["identify", "--load", "3150", "--out", "{tmp}/x"], "--closed-loop"),
    (["model", "--frf", "{frf}"], "--plot"),
    (["model", "--frf", "{frf}", "--fitted", "{tmp}/none.yaml", "--plot", "{tmp}/f"], "--fitted"),
    (["model", "fit", "{frf}", "--out", "{tmp}/m.yaml", "--plot", "{tmp}/m.yaml"], "--plot"),
])
def test_bad_input_is_refused_in_one_line_naming_it(identified, tmp_path, capsys, argv, named):
    args = [a.format(frf=identified / "id-2000.npz", tmp=tmp_path) for a in argv]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert named in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err


def test_ctrl_c_during_identify_exits_130_and_writes_no_result(identified, tmp_path):
    process = beamctl("identify", "--config", str(identified / "rig.yaml"), "--load", "2000",
                      "--out", str(tmp_path / "cut"), cwd=tmp_path)
    status, err = interrupt_when(process, b"force yA")
    assert status == 130, err
    assert "interrupted" in err and "Traceback" not in err, err
    assert not list(tmp_path.glob("cut*")), "a cut-short identification is no measurement"
