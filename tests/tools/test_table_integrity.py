"""A gain table runs only as it was built and checked: ``beamctl run`` refuses a changed,
unchecked, unstable, forced or old-format table in one line that says what to run;
``beamctl gains check`` still analyses a changed table and says its hash does not match."""

import json

import pytest
import yaml

from beamctl.config.schema import read_yaml
from beamctl.gains.defaults import paper_table_path
from beamctl.gains.table import GainTableError
from beamctl.simulation.experiment import experiment_config, paper_table
from beamctl.tools.cli import main

# the paper's design (integral LQR, 2500 Hz) builds in seconds; the robust check is left out
PAPER_BUILD = ("gains", "build", "--design", "integral-lqr", "--no-robust")

# the simulated beam as fast as it computes: these runs are about the table they start with
SIM = {"hal": {"backend": "sim", "sim": {"pace": "simulated"}}, "controller": {"pacing": "sample"},
       "plant": {"load": {"start": 1000.0, "end": 1000.0}}}


def _service(tmp_path, table) -> str:
    f = tmp_path / "service.yaml"
    f.write_text(yaml.safe_dump({**SIM, "gains": {"table": str(table)}, "run": {"duration_s": 0.02,
                                 "telemetry": str(tmp_path / "run.btl")}}))
    return str(f)


def _refusal(capsys, argv) -> str:
    """The one line ``beamctl`` prints when it refuses (exit code 2)."""
    code = main(argv)
    captured = capsys.readouterr()
    assert code == 2, f"expected a refusal (exit 2), got {code}: {captured.out}{captured.err}"
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in captured.err, f"one line, no traceback: {captured.err}"
    return lines[0]


@pytest.fixture(scope="module")
def tampered(tmp_path_factory, other_table):
    """A table of the paper's design with one gain times 10 at 3500 N (the compensator's D[0, 0],
    the one from the first gauge to Fay,A), otherwise valid. The design on its 250 N grid
    (tests/conftest.py): ``gains check`` analyses its 33 loads in a quarter of the time it takes
    for the 161 of the shipped 50 N grid."""
    data = read_yaml(other_table)
    i = data["loads_N"].index(3500.0)
    data["compensator"]["d"][i][0][0] *= 10.0
    path = tmp_path_factory.mktemp("tampered") / "tampered.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_run_refuses_a_table_changed_by_hand_in_one_line_saying_what_to_run(tmp_path, capsys, tampered):
    line = _refusal(capsys, ["run", "--config", _service(tmp_path, tampered)])
    assert "sha256" in line and "changed after it was built" in line, line
    # the paper's design is rebuilt as that design, not as the build's default LQG
    assert f"beamctl gains build --design integral-lqr --out {tampered}" in line, line
    assert f"beamctl gains check {tampered}" in line, line
    assert not (tmp_path / "run.btl").exists(), "refused before anything ran"


def test_experiment_refuses_a_changed_table(tmp_path, capsys, tampered):
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text(yaml.safe_dump({"gains": {"table": str(tampered)}}))
    line = _refusal(capsys, ["experiment", "--config", str(scenario), "--out", str(tmp_path / "r")])
    assert "sha256" in line and "changed after it was built" in line, line


def test_gains_check_analyses_a_changed_table_and_says_its_hash_does_not_match(capsys, tampered):
    assert main(["gains", "check", str(tampered)]) == 1
    captured = capsys.readouterr()
    rows = {line.split()[0]: line.split()[-1] for line in captured.out.splitlines()
            if line.strip()[:1].isdigit()}
    assert rows["3500.0"] == "NO" and rows["3000.0"] == "yes", "the x10 gain at 3500 N is unstable there"
    assert "all stable: NO" in captured.out
    assert "content SHA-256: DOES NOT MATCH" in captured.out, captured.out
    assert "does not match its SHA-256" in captured.err
    assert "beamctl gains build --design integral-lqr --out" in captured.err, captured.err
    assert main(["gains", "check", str(tampered), "--json"]) == 1
    result = json.loads(capsys.readouterr().out)
    assert result["sha256_matches"] is False and result["all_stable"] is False


def test_gains_show_warns_about_a_changed_table(capsys, tampered):
    assert main(["gains", "show", str(tampered)]) == 0
    captured = capsys.readouterr()
    assert "content sha256: DOES NOT MATCH" in captured.out, captured.out
    assert "does not match its SHA-256" in captured.err


def test_run_refuses_a_table_built_without_its_check(tmp_path, capsys, paper_model):
    from beamctl.gains.build import build_table
    from beamctl.gains.table import write_table

    path = write_table(build_table(paper_model, [0.0, 1000.0, 2000.0], check=False), tmp_path / "u.yaml")
    line = _refusal(capsys, ["run", "--config", _service(tmp_path, path)])
    assert "check.points" in line and "built without it" in line and "beamctl gains check" in line, line


def test_run_refuses_a_forced_unstable_table(tmp_path, capsys):
    path = tmp_path / "forced.yaml"
    assert main([*PAPER_BUILD, "--grid", "4000:4500:500", "--out", str(path), "--force"]) == 0
    capsys.readouterr()
    line = _refusal(capsys, ["run", "--config", _service(tmp_path, path)])
    assert "check.forced" in line and "unstable at" in line and "--force" in line, line


def test_run_refuses_a_format_1_table_asking_to_rebuild_it(tmp_path, capsys):
    data = read_yaml(paper_table_path())
    data["format"] = "beamctl-gain-table/1"
    del data["sha256"]
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    line = _refusal(capsys, ["run", "--config", _service(tmp_path, path)])
    assert "beamctl-gain-table/1" in line and "no SHA-256" in line, line
    assert f"beamctl gains build --out {path}" in line, line
    assert "beamctl-gain-table/1" in _refusal(capsys, ["gains", "check", str(path)])


def test_run_accepts_a_table_as_built_and_checked(tmp_path, capsys):
    path = tmp_path / "genuine.yaml"
    assert main([*PAPER_BUILD, "--grid", "0:2000:1000", "--out", str(path)]) == 0
    assert main(["run", "--config", _service(tmp_path, path)]) == 0, capsys.readouterr().err
    assert "ended STOPPED" in capsys.readouterr().out


def test_the_paper_switching_table_is_built_with_its_check_and_stable_for_the_paper_beam():
    cfg, _ = experiment_config()
    table = paper_table(cfg)
    assert table.checked and table.all_stable and not table.forced
    settled = [c.load_n for c in table.checks if c.gain_load_n is None]
    assert settled == [250.0 * k for k in range(15)], "every grid point and midpoint"
    assert sum(c.gain_load_n is not None for c in table.checks) == 13, (
        "and each gain at both ends of its reach through the 50 N hysteresis band")
    worst = max(c.spectral_radius for c in table.checks)
    assert worst < 1.0, f"largest spectral radius {worst}"


def test_the_paper_switching_table_is_refused_where_it_is_unstable():
    """Soft supports buckle at 2381 N; the 500 N switching gains do not hold them beyond."""
    cfg, _ = experiment_config({"model": {"supports": {"lateral_stiffness": 2.0e6,
                                                       "actuator_stiffness": 5.0e6}}})
    with pytest.raises(GainTableError) as err:
        paper_table(cfg)
    message = str(err.value)
    assert err.value.key == "check.points" and "2250.0" in message, message
    assert "--no-paper" in message, message
