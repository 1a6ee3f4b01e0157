"""``beamctl commission``: a simulated rig that differs from the model, from identification to a
gain table that holds it; Ctrl-C in the middle ends it with 130 and nothing half-written, and it
goes on where it stopped."""

import json

import numpy as np
import pytest
import yaml

from beamctl.commission.workflow import FLOOR, STATE, calibrated_box
from beamctl.gains.robust import box_from_dict
from beamctl.gains.table import load_table
from beamctl.models import build_model, critical_load, load_parameters, parameters_from_dict
from beamctl.models.analysis import fe_frequency_response
from beamctl.models.measured import FrfData
from beamctl.tools.cli import main
from tests.processes import beamctl, interrupt_when

# a rig that differs from Table 1 (E x1.02, kr x0.8, damping x1.5, stacks 3.3 N/V where the
# controller believes 3.0), bowed, with strain and load-cell noise; its load ramps past its own
# critical load (3225 N) to 3700 N at 50 N/s in the experiment
MODEL = {"beam": {"youngs_modulus": 77.316e9}, "supports": {"rotational_stiffness": 153.92},
         "damping": {"ratios": [0.0225, 0.00675]}}
RIG = {"hal": {"backend": "sim", "sim": {"pace": "simulated", "own_actuators": True,
                                         "actuators": {"force_constant_n_per_v": 3.3}}},
       "plant": {"noise": {"strain": 2e-7, "load": 2.0, "seed": 1},
                 "bow": {"amplitude": 5e-5, "angle_deg": 234.0},
                 "load": {"start": 2000.0, "end": 3700.0, "rate": 50.0}, "model": MODEL}}
FAST = ["--averages", "3", "--no-robust", "--grid", "0:4000:200"]


@pytest.fixture
def rig(tmp_path):
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump(RIG))
    return path


def test_an_interrupted_commissioning_goes_on_where_it_stopped_and_its_table_holds_the_rig(rig, tmp_path):
    out = tmp_path / "out"
    process = beamctl("commission", "--config", str(rig), "--out", str(out), *FAST, cwd=tmp_path)
    code, err = interrupt_when(process, b"step 5/7 gains ...")
    assert code == 130 and "interrupted (SIGINT" in err and "Traceback" not in err, err
    state = json.loads((out / STATE).read_text())
    assert state["done"] == ["identify", "fit", "stacks", "box"], state
    assert not (out / "gains.yaml").exists() and not list(out.glob("*.tmp*")) and not list(out.glob(".*")), (
        sorted(p.name for p in out.iterdir()))
    measured = (out / "frf_2000N.npz").stat().st_mtime_ns

    assert main(["commission", "--config", str(rig), "--out", str(out), *FAST, "--json"]) == 0
    assert (out / "frf_2000N.npz").stat().st_mtime_ns == measured, "a step done before was run again"
    state = json.loads((out / STATE).read_text())
    assert state["done"] == ["identify", "fit", "stacks", "box", "gains", "experiment", "report"], state

    # the fit: the rig's own E and kr within 1 %, its damping within 10 %, each inside its interval
    fit = json.loads((out / "fit.json").read_text())
    truth = {"beam.youngs_modulus": 77.316e9, "supports.rotational_stiffness": 153.92,
             "damping.ratios": [0.0225, 0.00675]}
    for key, tolerance in (("beam.youngs_modulus", 0.01), ("supports.rotational_stiffness", 0.01),
                           ("damping.ratios", 0.10)):
        values = np.atleast_1d(fit["parameters"][key])
        error = np.abs(values / np.atleast_1d(truth[key]) - 1)
        assert error.max() < tolerance, (key, values, truth[key])
    # the table was designed on the fitted model and holds the rig past its own critical load
    table = load_table(out / "gains.yaml")
    fitted = yaml.safe_load((out / "fitted.yaml").read_text())["model"]
    assert table.model_parameters.to_dict() == parameters_from_dict(fitted).to_dict()
    own = critical_load(build_model(parameters_from_dict({**load_parameters().to_dict(), **MODEL})))
    summary = json.loads((out / "experiment" / "summary.json").read_text())["commission"]
    assert summary["own_critical_load_N"] == pytest.approx(own, rel=1e-9)
    assert summary["held_past_own_critical_load"], summary
    # the stacks' use predicted from the two measurements' static strains is what the controlled
    # run on the rig used: near its critical load and midway (the run's voltages also carry the
    # control's own motion and the noise: 6 %)
    stacks = json.loads((out / "stacks.json").read_text())
    run = np.array(summary["stack_use"])
    for low, high in ((0.95 * own, own), (2400.0, 2600.0)):
        near = run[(run[:, 0] > low) & (run[:, 0] < high), 1]
        predicted = np.interp(0.5 * (low + high), stacks["loads_n"], stacks["fraction"])
        assert near.size > 5 and np.median(near) == pytest.approx(predicted, rel=0.06), (low, near, predicted)
    report = (out / "report.html").read_text()
    for figure in ("fig5a_frequency_response.png", "stacks_vs_load.png", *(f"experiment/{p.name}"
                                                     for p in (out / "experiment").glob("*.png"))):
        assert f"src='{figure}'" in report and (out / figure).exists(), figure


def test_a_folder_of_another_commissioning_or_bad_settings_are_refused_in_one_line(rig, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / STATE).write_text(json.dumps({"config": "/elsewhere.yaml", "config_sha256": "0",
                                         "settings": {}, "done": ["identify"]}))
    for argv, key in ((["--out", str(out)], "--out"),
                      (["--out", str(tmp_path / "o2"), "--loads", "x"], "--loads"),
                      (["--out", str(tmp_path / "o3"), "--grid", "5:1:1"], "--grid"),
                      (["--out", str(tmp_path / "o4"), "--params", "E,bogus"], "--params")):
        assert main(["commission", "--config", str(rig), *FAST, *argv]) == 2, argv
        err = capsys.readouterr().err
        assert key in err and len(err.strip().splitlines()) == 1, err
    missing = tmp_path / "missing.yaml"
    assert main(["commission", "--config", str(missing), "--out", str(tmp_path / "o5")]) == 2
    assert "missing.yaml" in capsys.readouterr().err


def test_the_calibrated_box_widens_the_fit_s_intervals_and_keeps_what_identification_cannot_see():
    fitted = {"beam.youngs_modulus": 7.7e10, "supports.rotational_stiffness": 150.0,
              "damping.ratios": [0.02, 0.006], "actuators.force_constant_n_per_v": 3.3}
    errors = {"beam.youngs_modulus": 7.7e10 * 0.004, "supports.rotational_stiffness": 0.1,
              "damping.ratios": [0.0001, 0.00003], "actuators.force_constant_n_per_v": 0.001}
    box = calibrated_box(fitted, errors)
    e = box["parameters"]["beam.youngs_modulus"]["factor"]
    assert e[1] - 1 == pytest.approx(3.0 * 1.959964 * 0.004, abs=1e-6), (
        "3 x the 95 % interval, above the floor")
    kr = box["parameters"]["supports.rotational_stiffness"]["factor"]
    assert kr == [1 - FLOOR["supports.rotational_stiffness"], 1 + FLOOR["supports.rotational_stiffness"]]
    for unseen in ("io.delay_samples", "actuators.force_constant_n_per_v",
                   "sensors.strain_gauge_positions[0]"):
        assert unseen in box["parameters"], unseen
    box_from_dict(box, load_parameters())          # a valid box file


def test_a_step_whose_files_are_gone_is_run_again_with_every_step_after_it(rig, tmp_path):
    from beamctl.commission.workflow import STEPS, Commission, CommissionSettings

    out = tmp_path / "out"
    settings = CommissionSettings(averages=3, robust=False)
    first = Commission(rig, out, settings, log=lambda line: None)
    (out / STATE).write_text(json.dumps({**first.identity, "done": list(STEPS)}))
    for name in ("frf_1000N.npz", "frf_2000N.npz", "fit.json", "fitted.yaml", "stacks.json", "gains.yaml",
                 "report.html"):
        (out / name).write_text("")         # box.yaml and the experiment are gone
    again = Commission(rig, out, settings, log=lambda line: None)
    assert again.done == ["identify", "fit", "stacks"], again.done


def test_a_changed_model_file_the_configuration_names_makes_it_another_commissioning(tmp_path):
    """The configuration's own bytes are the same; the model file it names is not."""
    from beamctl.commission.workflow import Commission, CommissionSettings

    model = tmp_path / "model.yaml"
    model.write_text(yaml.safe_dump(MODEL))
    config = tmp_path / "rig.yaml"
    config.write_text(yaml.safe_dump({**RIG, "model": str(model)}))
    out = tmp_path / "out"
    settings = CommissionSettings(averages=3, robust=False)
    first = Commission(config, out, settings, log=lambda line: None)
    (out / STATE).write_text(json.dumps({**first.identity, "done": ["identify"]}))
    (out / "frf_1000N.npz").write_text("")
    (out / "frf_2000N.npz").write_text("")
    assert Commission(config, out, settings, log=lambda line: None).done == ["identify"], "the same rig"
    model.write_text(yaml.safe_dump({**MODEL, "supports": {"rotational_stiffness": 160.0}}))
    with pytest.raises(Exception, match="another commissioning"):
        Commission(config, out, settings, log=lambda line: None)


def test_a_parameter_not_fitted_keeps_box_b_s_range_in_the_calibrated_box():
    box = calibrated_box({"supports.rotational_stiffness": 150.0}, {"supports.rotational_stiffness": 0.1})
    assert box["parameters"]["beam.youngs_modulus"] == {"factor": [0.97, 1.03]}, "E not fitted: +-3 %"
    assert calibrated_box({"damping.ratios": [0.0, 0.0]}, {"damping.ratios": [0.0, 0.0]})[
        "parameters"]["damping.ratios"] == {"factor": [0.7, 1.3]}, "no relative error to take: the floor"


def test_a_fitted_parameter_the_data_leave_undetermined_keeps_the_prior_s_range():
    """kl fitted to a tight-looking interval but undetermined by the data (it moves with kr and
    kp along what they determine together): the box keeps box B's x[0.8, 1.2] for it, and says
    which parameters were calibrated and which were not."""
    from beamctl.commission.workflow import UNSEEN, calibration

    fitted = {"supports.rotational_stiffness": 150.0, "supports.lateral_stiffness": 3.0e7}
    errors = {"supports.rotational_stiffness": 0.1, "supports.lateral_stiffness": 3.0e4}
    box = calibrated_box(fitted, errors, ["supports.lateral_stiffness"])
    assert box["parameters"]["supports.lateral_stiffness"] == UNSEEN["supports.lateral_stiffness"]
    assert box["parameters"]["supports.rotational_stiffness"]["factor"] == [0.9, 1.1], "calibrated: the floor"
    how = calibration(fitted, ["supports.lateral_stiffness"])
    assert how["supports.lateral_stiffness"].startswith("kept at the prior's range"), how
    # an undetermined damping keeps the prior's asymmetric x[0.5, 2], not a range symmetric about 1
    loose = calibrated_box({"damping.ratios": [0.01, 0.003]}, {"damping.ratios": [0.0003, 0.00009]},
                           ["damping.ratios[0]"])
    assert loose["parameters"]["damping.ratios"]["factor"] == [0.5, 2.0], loose
    assert how["supports.rotational_stiffness"] == "calibrated from the fit", how
    box_from_dict(box, load_parameters())


def test_a_fit_that_does_not_explain_the_measurements_stops_commissioning_with_advice(rig, tmp_path,
                                                                                    monkeypatch):
    """A misfit of 40 (the model misses what the data show): nothing is calibrated on it; the
    one line says what to free and what to check."""
    from dataclasses import replace as with_

    from beamctl.commission import workflow
    from beamctl.commission.workflow import Commission, CommissionError, CommissionSettings

    real_fit = workflow.fit

    def poor_fit(*args, **kwargs):
        return with_(real_fit(*args, **kwargs), misfit=40.0)

    monkeypatch.setattr(workflow, "fit", poor_fit)
    freqs = np.arange(10.0, 1201.0, 4.0)
    g = fe_frequency_response(build_model(load_parameters()), 2000.0, freqs)
    measured = FrfData(frequencies_hz=freqs, frf=g, coherence=np.full(g.shape, 0.99), load_n=2000.0,
                       force_constant_n_per_v=3.0, settings={"identify": {"averages": 8}}, source="synthetic")
    monkeypatch.setattr(workflow, "read_frf", lambda path: measured)
    monkeypatch.setattr(Commission, "_frf_paths", lambda self: [tmp_path / "frf_2000N.npz"])
    lines = []
    c = Commission(rig, tmp_path / "out", CommissionSettings(averages=3, robust=False), log=lines.append)
    with pytest.raises(CommissionError, match="residual is 40 x the data's noise") as caught:
        c._fit()
    assert "--params" in str(caught.value) and "gauge positions" in str(caught.value), caught.value
    assert not (tmp_path / "out" / "fit.json").exists(), "nothing written to calibrate on"


def test_the_default_grid_ends_where_a_design_can_hold_the_fitted_model():
    """A rig 1.5 % softer than Table 1 (Fx,cr 3146 N): its LQG table was unstable at 4000 N
    (spectral radius 1.0017), so the grid ends at 1.2 x its critical load; a stiffer one keeps
    the shipped design's 4000 N."""
    from beamctl.commission.workflow import default_grid

    soft = default_grid(3146.4)
    assert soft[0] == 0.0 and soft[-1] == 3700.0 and np.allclose(np.diff(soft), 100.0), soft
    assert default_grid(3500.0)[-1] == 4000.0


def test_a_beam_lost_because_the_stacks_ran_out_is_said_so():
    from beamctl.commission.workflow import held_text

    text = held_text({"own_critical_load_N": 3230.0, "let_go_at_N": 3134.0, "max_load_N": 3136.0,
                      "fault": "PERSISTENT_SATURATION: the stack voltages stayed saturated for too long"})
    assert "3134 N" in text and "their force, not the gains, is the limit" in text, text
    predicted = held_text({"own_critical_load_N": 3230.0, "let_go_at_N": 3134.0, "max_load_N": 3136.0,
                           "stacks_limit_N": 3024.6, "fault": "PERSISTENT_SATURATION: ..."})
    assert "predicted a stack at its limit from about 3025 N" in predicted, predicted
    held = held_text({"own_critical_load_N": 3214.0, "let_go_at_N": None, "max_load_N": 3900.0, "fault": ""})
    assert held.endswith("held below 1 mm to the ramp's end, 3900 N"), held


def test_against_a_real_rig_the_stop_says_how_far_the_stacks_will_hold_the_beam(rig, tmp_path):
    """Stopped before the beam is loaded past Fx,cr: where the stacks step found they run out
    below it, the next step names a load below that, not just 'raise the load'."""
    from dataclasses import replace

    from beamctl.commission.workflow import Commission, CommissionSettings

    c = Commission(rig, tmp_path / "out", CommissionSettings(averages=3, robust=False), log=lambda line: None)
    c.cfg = replace(c.cfg, hal=replace(c.cfg.hal, backend="can"))
    (c.out / "stacks.json").write_text(json.dumps({"critical_load_n": 3200.0, "limit_n": 3000.0,
                                                   "not_enough": True}))
    text = c._experiment()
    assert "stopped here" in text and "no further than about 2850 N" in text and "3000 N" in text, text
    (c.out / "stacks.json").write_text(json.dumps({"critical_load_n": 3200.0, "limit_n": 3500.0,
                                                   "not_enough": False}))
    assert c._experiment().endswith("`beamctl run --hold` and raise the load")


def _measurement(load, static, k=3.0, source="frf.npz"):
    from beamctl.models.measured import FrfData, nan_matrix

    frf, coherence = nan_matrix(1)
    return FrfData(frequencies_hz=np.array([10.0]), frf=frf, coherence=coherence, load_n=load,
                   force_constant_n_per_v=k, settings={"static": static} if static is not None else {},
                   source=source)


def test_the_stacks_step_leaves_out_what_it_cannot_use_naming_it_and_never_fails():
    from beamctl.assembly.run import service_config
    from beamctl.commission.workflow import stack_authority

    cfg, params = service_config({}), load_parameters()
    good = [_measurement(1000.0, {"strain": [1e-6, -1e-6, 1e-6, -1e-6]}, source="frf_1000N.npz"),
            _measurement(2000.0, {"strain": [3e-6, -3e-6, 3e-6, -3e-6]}, source="frf_2000N.npz")]
    for bad, needle in ((_measurement(1500.0, None, source="hand.mat"), "hand.mat carries no static strains"),
                        (_measurement(1500.0, {"strain": [1e-6, 2e-6, 3e-6]}, source="/x/frf_1500N.npz"),
                         "frf_1500N.npz: its static strains are not 4 numbers"),
                        (_measurement(1500.0, {"strain": "1234"}, source="s.npz"),
                         "s.npz: its static strains"),
                        (_measurement(1500.0, [1, 2, 3, 4], source="l.npz"),
                         "l.npz: its static strains are not a"),
                        (_measurement(1500.0, {"strain": [1e300] * 4}, source="h.npz"),
                         "h.npz at 1500 N are left out: beyond any elastic strain"),
                        (_measurement(4000.0, {"strain": [1e-6] * 4}, source="frf_4000N.npz"),
                         "frf_4000N.npz at 4000 N are left out")):
        result = stack_authority(cfg, params, None, [*good, bad])
        assert "fraction" in result and any(needle in w for w in result["warnings"]), (
            needle, result["warnings"])
        alone = stack_authority(cfg, params, None, [bad])
        assert alone["text"].startswith("not predicted"), alone["text"]


def test_without_a_fitted_force_constant_the_measurements_own_is_taken_as_the_fit_takes_it():
    from beamctl.assembly.run import service_config
    from beamctl.commission.workflow import stack_authority

    data = [_measurement(f, {"strain": [1e-6 * f / 1000] * 4}, k=3.3) for f in (1000.0, 2000.0)]
    result = stack_authority(service_config({}), load_parameters(), None, data)
    assert result["force_constant_n_per_v"] == 3.3, "the configuration believes 3.0"


def test_forces_recorded_with_the_controller_s_force_constant_are_taken_at_the_fitted_one():
    """A closed-loop measurement records k_config (V - bias); the stacks give k_fitted (V - bias):
    the same voltages, so the same fraction of the swing whichever constant the file was
    measured with."""
    from beamctl.assembly.run import service_config
    from beamctl.commission.workflow import stack_authority

    cfg, params = service_config({}), load_parameters()
    volts = {1000.0: np.array([13.0, -8.0, 13.0, -8.0]), 2000.0: np.array([29.0, -18.0, 29.0, -18.0])}
    measured = {}
    for k in (3.0, 3.3):     # the file's own force constant: forces = k (V - bias) of the same V
        data = [_measurement(f, {"strain": [0.0] * 4, "force_n": list(k * v)}, k=k) for f, v in volts.items()]
        measured[k] = [fraction for _, fraction in stack_authority(cfg, params, 3.3, data)["measured"]]
    assert measured[3.0] == pytest.approx(measured[3.3], rel=1e-9), measured


def test_a_folder_without_the_stacks_step_runs_it_and_the_report_again_alone(rig, tmp_path):
    from beamctl.commission.workflow import STEPS, Commission, CommissionSettings

    out = tmp_path / "out"
    settings = CommissionSettings(averages=3, robust=False)
    first = Commission(rig, out, settings, log=lambda line: None)
    (out / STATE).write_text(json.dumps({**first.identity, "done": [s for s in STEPS if s != "stacks"]}))
    for name in ("frf_1000N.npz", "frf_2000N.npz", "fit.json", "fitted.yaml", "box.yaml", "gains.yaml",
                 "report.html"):
        (out / name).write_text("")
    (out / "experiment").mkdir()
    (out / "experiment" / "summary.json").write_text("{}")
    again = Commission(rig, out, settings, log=lambda line: None)
    assert again.done == ["identify", "fit", "box", "gains", "experiment"], again.done


def test_the_refusal_of_another_commissioning_names_what_differs(rig, tmp_path, capsys):
    from beamctl.commission.workflow import Commission, CommissionSettings

    out = tmp_path / "out"
    first = Commission(rig, out, CommissionSettings(loads_n=(2000.0,), averages=3, robust=False),
                       log=lambda line: None)
    (out / STATE).write_text(json.dumps({**first.identity, "done": ["identify"]}))
    assert main(["commission", "--config", str(rig), "--out", str(out), *FAST]) == 2
    err = capsys.readouterr().err
    assert "its loads_n [2000.0], here [1000.0, 2000.0]" in err and len(err.strip().splitlines()) == 1, err
