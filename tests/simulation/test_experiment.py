"""``beamctl experiment``: the acceptance of the main job on a faster load ramp (200 N/s
instead of 50 N/s; the loads at 0.5 mm and 1.0 mm move by less than 0.3 %)."""

import json
import signal

import numpy as np
import pytest

from beamctl.assembly.run import load_gain_table, plant_parameters
from beamctl.common.signals import Interrupted, stop_on_signals
from beamctl.config.schema import ConfigError
from beamctl.models import build_model, critical_load, load_parameters
from beamctl.models.iochain import IOChain
from beamctl.reports import plots
from beamctl.rt.controller import COL
from beamctl.rt.safety import State
from beamctl.rt.telemetry import read_telemetry
from beamctl.simulation.experiment import (
    BOW_AMPLITUDE_M,
    direction_at,
    experiment_config,
    first_crossing,
    paper_table,
    run_mode,
)
from beamctl.tools import experiment_cmd
from beamctl.tools.cli import main
from beamctl.tools.experiment_cmd import REPORT_FILES
from tests.processes import beamctl, interrupt_when

CRITICAL_LOAD_N = 3193.5
FAST_RAMP = {"start": 260.0, "end": 3400.0, "rate": 200.0, "hold": 0.2}


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    out = tmp_path_factory.mktemp("experiment")
    scenario = out / "fast.yaml"
    scenario.write_text("plant:\n  load: {start: 260.0, end: 3400.0, rate: 200.0, hold: 0.2}\n")
    import contextlib
    import io

    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        code = main(["experiment", "--config", str(scenario), "--out", str(out / "report"), "--json",
                     "--telemetry"])
    assert code == 0
    return json.loads(buffer.getvalue()), out / "report"


def test_uncontrolled_beam_reaches_the_paper_s_deflections_within_5_percent(report):
    s, _ = report
    u = s["uncontrolled"]
    assert u["load_at_0.5mm_N"] == pytest.approx(2438.0, rel=0.05), u
    assert u["load_at_1.0mm_N"] == pytest.approx(2723.0, rel=0.05), u
    assert u["buckling_angle_deg"] == pytest.approx(234.0, abs=2.0), "passive buckling direction"


def test_controlled_beam_stays_straight_to_3000_N_and_holds_beyond_the_critical_load(report):
    s, _ = report
    c = s["controlled"]
    # the integral action follows the load ramp with a lag in proportion to its rate: at the
    # paper's 50 N/s 0.034 mm (the README's experiment; the test below bounds it by 0.05 mm),
    # four times that on this ramp four times faster is 0.14 mm (0.11 mm measured)
    assert c["max_deflection_below_3000N_mm"] < 0.15, c
    assert 0.0 <= c["min_voltage_V"] and c["max_voltage_V"] <= 150.0, "voltages within range"
    assert c["load_at_1.0mm_N"] >= CRITICAL_LOAD_N, c
    assert s["critical_load_N"] == pytest.approx(CRITICAL_LOAD_N, abs=1.0)


def test_at_the_paper_s_ramp_rate_the_beam_stays_within_0_05_mm_up_to_3000_N():
    """At 50 N/s (the paper's rate) the deflection the gauges see stays below 0.05 mm up to
    3000 N (the README's experiment: 0.034 mm; the paper's figure 7a: straight there)."""
    cfg, settings = experiment_config({"plant": {"load": {"start": 260.0, "end": 3000.0, "rate": 50.0,
                                                          "hold": 0.0}}})
    trace = run_mode("interpolate", cfg, settings, load_gain_table(cfg))
    load, deflection = np.asarray(trace.load_n), np.asarray(trace.deflection_m)
    assert load.max() >= 2990.0, f"the run ended at {load.max():.0f} N: {trace.end}"
    worst = int(np.argmax(deflection))
    assert deflection[worst] < 0.05e-3, (
        f"{deflection[worst] * 1e3:.3f} mm at {load[worst]:.0f} N: more than 0.05 mm below 3000 N")


def test_the_shipped_design_and_the_paper_switching_both_hold_until_the_stacks_run_out(report):
    """Both hold the beam beyond its critical load until the stacks run out of force (150 V):
    within 1.5 % of each other (the shipped design's slower integral action leaves a little more
    deflection on the fast ramp, so its stacks saturate a few tens of newtons earlier)."""
    s, _ = report
    controlled, paper = s["controlled"]["load_at_1.0mm_N"], s["paper_switching"]["load_at_1.0mm_N"]
    assert controlled >= CRITICAL_LOAD_N and paper >= CRITICAL_LOAD_N, s
    assert controlled == pytest.approx(paper, rel=0.015), s
    assert s["controlled"]["max_voltage_V"] == pytest.approx(150.0), "the stacks ran out of force"
    assert s["paper_switching"]["load_at_1.0mm_N"] == pytest.approx(3223.0, rel=0.01), (
        "the force constant makes the paper's setup fail near its 3223 N")


def test_json_has_the_documented_keys(report):
    s, _ = report
    assert set(s["uncontrolled"]) >= {"load_at_0.5mm_N", "load_at_1.0mm_N", "buckling_angle_deg"}
    assert set(s["controlled"]) >= {"load_at_1.0mm_N", "max_voltage_V", "max_deflection_below_3000N_mm",
                                    "buckling_angle_deg", "design"}
    designed = load_gain_table(experiment_config()[0]).design.io
    assert s["io_chain"]["description"] == designed.describe(), "the rig has the chain its design declares"


def test_report_folder_has_figures_summary_and_readable_telemetry(report):
    s, folder = report
    for name in ("fig7a_deflection_vs_load.png", "fig7b_path_yz.png", "voltages_vs_load.png"):
        assert (folder / name).stat().st_size > 10_000, name
    assert "load at 1.0 mm" in (folder / "summary.txt").read_text()
    assert json.loads((folder / "summary.json").read_text())["controlled"] == s["controlled"]
    for mode in ("uncontrolled", "interpolate", "paper"):
        header, rows = read_telemetry(folder / f"telemetry_{mode}.btl")
        assert header["meta"]["mode"] == mode and len(rows) > 10_000


def test_scenario_overrides_the_plant_separately_from_the_model():
    cfg, settings = experiment_config({"plant": {"model": {"beam": {"radius": 4.05e-3}},
                                                 "bow": {"amplitude": 2e-4}}})
    assert cfg.model.beam.radius == 4.0e-3, "the gains' model is untouched"
    assert cfg.plant_model == {"beam": {"radius": 4.05e-3}}
    assert cfg.plant["bow"]["amplitude"] == 2e-4 and cfg.plant["bow"]["angle_deg"] == 234.0
    assert experiment_config()[0].plant["bow"]["amplitude"] == BOW_AMPLITUDE_M


@pytest.mark.parametrize(("data", "key"), [
    ({"experiment": {"deflection_limt": 1}}, "experiment.deflection_limt"),
    ({"plant": {"load": {"rate": -5}}}, "plant.load.rate"),
    ({"plants": {}}, "plants"),
    ({"experiment": {"paper_allocation": "spread"}}, "experiment.paper_allocation"),
])
def test_bad_scenario_is_refused_naming_the_key(tmp_path, capsys, data, key):
    import yaml

    f = tmp_path / "bad.yaml"
    f.write_text(yaml.safe_dump(data))
    assert main(["experiment", "--config", str(f), "--out", str(tmp_path / "r")]) == 2
    assert key in capsys.readouterr().err
    with pytest.raises(ConfigError):
        cfg, _ = experiment_config(data)
        from beamctl.assembly.run import build_plant, load_gain_table

        build_plant(cfg, load_gain_table(cfg))


def _scenario(tmp_path, load: str) -> str:
    f = tmp_path / "scenario.yaml"
    f.write_text(f"plant:\n  load: {load}\n")
    return str(f)


def test_full_rate_telemetry_is_recorded_only_when_asked(tmp_path, capsys):
    scenario = _scenario(tmp_path, "{start: 260.0, end: 500.0, rate: 200.0, hold: 0.0}")
    out = tmp_path / "report"
    assert main(["experiment", "--config", scenario, "--out", str(out), "--no-paper", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert sorted(p.name for p in out.iterdir()) == sorted(REPORT_FILES), "figures and summaries only"
    assert summary["controlled"]["telemetry"] == "" and summary["uncontrolled"]["telemetry"] == ""


def test_a_signal_during_a_run_ramps_to_bias_and_raises_interrupted(tmp_path):
    """SIGINT as the operator's Ctrl-C, delivered while the loop runs (from its own progress
    report): the run ends through the loop's ramp to bias, and is no result."""
    cfg, settings = experiment_config({"plant": {"load": {"start": 260.0, "end": 400.0, "rate": 200.0}}})

    def ctrl_c(fraction, label):
        signal.raise_signal(signal.SIGINT)

    with pytest.raises(Interrupted) as info, stop_on_signals() as stop:
        run_mode("uncontrolled", cfg, settings, load_gain_table(cfg), tmp_path, progress=ctrl_c, stop=stop)
    assert str(info.value) == "SIGINT during the uncontrolled run" and info.value.exit_status == 130
    header, rows = read_telemetry(tmp_path / "telemetry_uncontrolled.btl")
    assert len(rows) > 500, "what was recorded is kept"
    assert rows[-1, COL["state"]] == State.STOPPED, "the loop stopped through its ramp"


def test_ctrl_c_while_the_report_is_written_leaves_no_report(tmp_path, monkeypatch, capsys):
    out = tmp_path / "report"
    out.mkdir()
    (out / "summary.txt").write_text("an earlier experiment's summary")
    (out / "telemetry_paper.btl").write_bytes(b"an earlier recording")

    def one_figure_then_ctrl_c(summary, traces, out_dir):
        (out_dir / plots.FIG7A).write_bytes(b"a complete figure")
        raise KeyboardInterrupt

    monkeypatch.setattr(experiment_cmd, "run_experiment", lambda *a, **k: ({"critical_load_N": 3193.5}, {}))
    monkeypatch.setattr(plots, "experiment_figures", one_figure_then_ctrl_c)
    assert main(["experiment", "--out", str(out)]) == 130
    assert capsys.readouterr().err.splitlines()[-1] == "beamctl experiment: interrupted (SIGINT)"
    assert sorted(p.name for p in out.iterdir()) == ["telemetry_paper.btl"], "recordings are never deleted"


def test_ctrl_c_during_the_experiment_exits_130_with_no_summary_or_figure(tmp_path):
    """The real thing: ``beamctl experiment`` in its own process, SIGINT once it reports
    progress from inside the first run."""
    scenario = _scenario(tmp_path, "{start: 260.0, end: 4000.0, rate: 20.0}")   # minutes of plant time
    out = tmp_path / "report"
    process = beamctl("experiment", "--config", scenario, "--out", str(out), "--telemetry", cwd=tmp_path)
    status, err = interrupt_when(process, b"experiment:")
    assert status == 130, err
    last = err.splitlines()[-1]
    assert last.startswith("beamctl experiment: interrupted (SIGINT"), err
    assert "Traceback" not in err
    left = sorted(p.name for p in out.iterdir())
    assert not set(left) & set(REPORT_FILES), f"no summary or figure of a run cut short: {left}"
    assert left and all(name.startswith("telemetry_") for name in left), left
    for name in left:
        read_telemetry(out / name)


def test_a_run_is_recorded_until_its_end_not_through_the_stop(tmp_path, capsys):
    """A ramp that ends at 2800 N, below the critical load: the controlled beam stays straight
    to the end; the stop's ramp to bias afterwards (when the uncontrolled beam sags back to its
    2800 N equilibrium) is not part of the run and must not show as a deflection."""
    scenario = tmp_path / "short.yaml"
    scenario.write_text("plant:\n  load: {start: 260.0, end: 2800.0, rate: 400.0, hold: 0.1}\n")
    assert main(["experiment", "--config", str(scenario), "--out", str(tmp_path / "r"), "--no-paper",
                 "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    c = s["controlled"]
    assert c["end"] == "ramp ended at 2800 N" and c["fault"] == "", c
    # a stop shown as a deflection would be the uncontrolled sag at 2800 N, over 1 mm; the
    # controller's lag on this fast (400 N/s) ramp is a tenth of a millimetre
    assert c["max_deflection_below_3000N_mm"] < 0.3, c


def test_an_experiment_on_another_backend_is_refused(tmp_path, capsys):
    f = tmp_path / "can.yaml"
    f.write_text("hal: {backend: can}\n")
    assert main(["experiment", "--config", str(f), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "hal.backend" in err and "simulated rig" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(("plant", "key"), [
    ({"io": {"delay_samples": -1}}, "plant.io.delay_samples"),
    ({"io": {"anti_alias": {"type": "chebyshev", "order": 2, "cutoff_hz": 100}}}, "plant.io.anti_alias.type"),
    ({"io": {"reconstruction": {"type": "bessel", "order": 0, "cutoff_hz": 100}}},
     "plant.io.reconstruction.order"),
    ({"io": {"anti_alias": {"type": "butterworth", "order": 2, "cutoff_hz": "1 kHz"}}},
     "plant.io.anti_alias.cutoff_hz"),
    ({"io": {"delay": 1}}, "plant.io.delay"),
    ({"sample_rate": 2500}, "plant.sample_rate"),
])
def test_a_bad_rig_io_chain_is_refused_in_one_line_before_any_run(tmp_path, capsys, plant, key):
    import yaml

    f = tmp_path / "rig.yaml"
    f.write_text(yaml.safe_dump({"plant": plant}))
    assert main(["experiment", "--config", str(f), "--out", str(tmp_path / "r")]) == 2
    captured = capsys.readouterr()
    assert captured.err.startswith(f"beamctl experiment: error: {f}: {key} = "), captured.err
    assert len(captured.err.strip().splitlines()) == 1 and captured.out == "", captured
    assert not (tmp_path / "r").exists(), "refused before the report folder is touched"


def test_the_old_sample_rate_key_is_refused_naming_the_new_one_without_a_traceback(tmp_path, capsys):
    """As an operator with last year's scenario file sees it: one line naming the new key, exit
    status 2 (the command's own; the real process's exit codes are tested with Ctrl-C)."""
    f = tmp_path / "old.yaml"
    f.write_text("plant:\n  sample_rate: 2500\n")
    status = main(["experiment", "--config", str(f), "--out", str(tmp_path / "r")])
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert status == 2 and len(lines) == 1, err
    assert "plant.sample_rate = 2500: expected plant.sample_rate_hz in its place" in lines[0], lines
    assert out == ""


def test_an_experiment_on_a_delayed_rig_runs_and_its_report_states_the_chain_and_the_design(tmp_path, capsys):
    """One sample of transport delay, the shipped gains (designed for 0.35 sample): the
    experiment runs end to end and says so in its summary, text and JSON."""
    f = tmp_path / "delayed.yaml"
    f.write_text("plant:\n  load: {start: 260.0, end: 800.0, rate: 400.0, hold: 0.0}\n"
                 "  io: {delay_samples: 1}\n")
    out = tmp_path / "report"
    assert main(["experiment", "--config", str(f), "--out", str(out), "--no-paper", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    designed = load_gain_table(experiment_config()[0]).design.io
    # the rig keeps the chain the design declares (its anti-alias filter) but for the delay given
    assert summary["io_chain"] == {"description": IOChain(1.0, designed.anti_alias).describe(),
                                   "delay_samples": 1.0, "anti_alias": designed.anti_alias.to_dict(),
                                   "reconstruction": "none"}
    assert summary["controlled"]["design"].startswith("lqg, 6000 Hz"), summary["controlled"]
    assert summary["uncontrolled"]["design"].startswith("none"), summary["uncontrolled"]
    assert summary["controlled"]["end"] == "ramp ended at 800 N", summary["controlled"]
    text = (out / "summary.txt").read_text()
    assert "rig I/O chain: delay 1 samples" in text and "design (interpolated): lqg, 6000 Hz" in text, text
    assert json.loads((out / "summary.json").read_text())["io_chain"] == summary["io_chain"]


def test_the_shipped_design_holds_a_stiffer_late_rig_beyond_its_own_critical_load():
    """The robust design's promise in the time domain: a rig whose beam is 4 % stiffer than the
    model and whose voltages arrive a whole sample late (the design assumed 0.35 sample), with
    stacks of 6 N/V so that force is not the limit, is held beyond its own critical load."""
    youngs = 1.04 * load_parameters().beam.youngs_modulus
    cfg, settings = experiment_config({
        "plant": {"load": {"start": 2600.0, "end": 3500.0, "rate": 50.0, "hold": 3.0},
                  "model": {"beam": {"youngs_modulus": youngs}}, "io": {"delay_samples": 1.0}},
        "controller": {"actuators": {"force_constant_n_per_v": 6.0}}})
    table = load_gain_table(cfg)
    assert table.design.kind == "lqg", "the shipped default is the robust design"
    own_critical = critical_load(build_model(plant_parameters(cfg)))
    assert own_critical == pytest.approx(1.04 * CRITICAL_LOAD_N, rel=0.01)
    trace = run_mode("interpolate", cfg, settings, table)
    load, deflection = np.asarray(trace.load_n), np.asarray(trace.deflection_m)
    lost = first_crossing(load, deflection, 1e-3)
    assert lost is None or lost > own_critical, (
        f"the beam passed 1 mm at {lost:.0f} N, below its own Fx,cr {own_critical:.0f} N ({trace.end})")
    assert load.max() > own_critical, f"the run ended at {load.max():.0f} N: {trace.end}"
    # once the start's transient (from the imperfect beam's 0.6 mm sag at 2600 N) has settled
    below = deflection[(load > 2800.0) & (load < own_critical)]
    assert below.max() < 0.5e-3, f"largest deflection below Fx,cr {below.max() * 1e3:.3f} mm"


# Rigs of box B (gains/robust.py DEFAULT_BOX, box-relative values). The first is the worst rig of
# an earlier design (the loop unstable from 0.948 of its own Fx,cr, mode 5 at 2.68 kHz; the beam
# passed 1 mm at 0.968 in the time domain); the second is the worst rig the robust check's search
# (seed 1) finds for the shipped design (mode 1 at 188 Hz, unstable from 1.101); the third the
# worst of the design before it (mode 7 folded to 1.18 kHz, unstable from 0.934).
WORST_RIGS = {
    "stiff, lightly damped, strong stacks, 0.4 sample late": {
        "beam.youngs_modulus": 1.05, "supports.rotational_stiffness": 1.2, "supports.lateral_stiffness": 1.2,
        "supports.actuator_stiffness": 1.2, "damping.ratios": 0.5, "actuators.force_constant_n_per_v": 1.2,
        "sensors.strain_gauge_positions[0]": -1e-3, "sensors.strain_gauge_positions[1]": 1e-3,
        "io.delay_samples": 0.4, "sample_rate_hz": 0.99},
    "the search's worst, seed 1: stiff beam, soft kr and kp, strong stacks, a sample late": {
        "beam.youngs_modulus": 1.05, "supports.rotational_stiffness": 0.8, "supports.lateral_stiffness": 1.2,
        "supports.actuator_stiffness": 0.8, "damping.ratios": 0.5, "actuators.force_constant_n_per_v": 1.2,
        "sensors.strain_gauge_positions[0]": 1e-3, "sensors.strain_gauge_positions[1]": -1e-3,
        "io.delay_samples": 1.0, "sample_rate_hz": 0.99},
    "a previous design's worst: mode 7 folded to 1.2 kHz": {
        "beam.youngs_modulus": 0.95, "supports.rotational_stiffness": 0.8, "supports.lateral_stiffness": 1.2,
        "supports.actuator_stiffness": 0.8, "damping.ratios": 0.5, "actuators.force_constant_n_per_v": 1.2,
        "sensors.strain_gauge_positions[0]": 1e-3, "sensors.strain_gauge_positions[1]": -1e-3,
        "io.delay_samples": 0.435, "sample_rate_hz": 1.01},
}


@pytest.mark.parametrize("name", list(WORST_RIGS))
def test_the_shipped_design_holds_the_worst_rigs_of_the_box_to_their_own_critical_load(name):
    """In the time domain, through the loop the service runs: the rig's own beam, I/O delay and
    DAQ clock, stacks whose force per volt the controller believes 4 x 3 N/V and that give that
    times the rig's stack gain (force does not limit: the voltages stay inside 0..150 V). The load
    ramps at 50 N/s from 2200 N through the rig's own Fx,cr; the beam must not pass 1 mm before it."""
    from beamctl.gains.defaults import default_table_path
    from beamctl.gains.robust import DEFAULT_BOX, rig_of
    from beamctl.gains.table import load_table
    from beamctl.simulation.experiment import rig_scenario

    table = load_table(default_table_path())
    rig = rig_of(table, DEFAULT_BOX, WORST_RIGS[name])
    scenario = rig_scenario(table, str(default_table_path()), rig)
    own = critical_load(build_model(plant_parameters(experiment_config(scenario)[0])))
    # from 2200 N: the bowed beam's sag there (0.4 mm at most in the box) is pulled in before the
    # load nears Fx,cr
    scenario["plant"]["load"] = {"start": 2200.0, "end": own + 100.0, "rate": 50.0, "hold": 0.5}
    cfg, settings = experiment_config(scenario)
    assert cfg.plant["sample_rate_hz"] == pytest.approx(6000.0 * WORST_RIGS[name]["sample_rate_hz"])
    trace = run_mode("interpolate", cfg, settings, table)
    load, deflection = np.asarray(trace.load_n), np.asarray(trace.deflection_m)
    lost = first_crossing(load, deflection, 1e-3)
    assert lost is None or lost > own, f"{name}: the beam passed 1 mm at {lost:.0f} N, own Fx,cr {own:.0f} N"
    assert load.max() > own, f"{name}: the run ended at {load.max():.0f} N ({trace.end}), before {own:.0f} N"
    assert 0.0 < min(trace.v_min) and max(trace.v_max) < 150.0, "the stacks' force limited the run"


# -- the paper's run with the paper's allocation: each stack clipped at its own limit ------------

def _clipped_paper_run(directory, **controller):
    cfg, settings = experiment_config({"plant": {"load": FAST_RAMP}, "controller": controller,
                                       "experiment": {"paper_allocation": "clip"}})
    trace = run_mode("paper", cfg, settings, paper_table(cfg), telemetry_dir=directory)
    return trace, directory / "telemetry_paper.btl"


@pytest.fixture(scope="module")
def clipped(tmp_path_factory):
    """The paper's run with clipped stacks on the fast ramp, under the shipped safety settings."""
    return _clipped_paper_run(tmp_path_factory.mktemp("clip"))


def _turn_when_saturated_deg(path) -> np.ndarray:
    """Per controlled sample with a saturated support: the angle in deg between the force the
    law asked of support A and the one its stacks gave."""
    _, rows = read_telemetry(path)
    running = rows[:, COL["state"]] == State.RUNNING
    saturated = running & ((rows[:, COL["flags"]].astype(int) & 1) != 0) & (rows[:, COL["scale_A"]] > 0)
    asked = rows[saturated][:, [COL["force_y_A_N"], COL["force_z_A_N"]]]
    given = rows[saturated][:, [COL["applied_force_y_A_N"], COL["applied_force_z_A_N"]]]
    turn = np.degrees(np.arctan2(given[:, 1], given[:, 0]) - np.arctan2(asked[:, 1], asked[:, 0]))
    return np.abs((turn + 180.0) % 360.0 - 180.0)


def test_clipped_stacks_turn_the_force_where_the_scaled_allocation_keeps_it(report, clipped):
    """Saturated, the scaled allocation gives less force in the direction the law asks; the
    clipped one gives the stacks that still have room their share, in another direction: by a
    little when the first stack just reaches its limit, more as its shortfall grows (about
    1 deg after the 0.5 s the shipped safety lets it last)."""
    _, folder = report
    scaled = _turn_when_saturated_deg(folder / "telemetry_paper.btl")
    turned = _turn_when_saturated_deg(clipped[1])
    assert scaled.size and turned.size, "both runs saturate"
    assert scaled.max() < 1e-6, f"scale turned the force by {scaled.max()} deg"
    assert np.median(turned) > 0.1 and turned.max() > 0.5, (
        f"clip turned the force by a median {np.median(turned):.3f} deg, at most {turned.max():.3f} deg")


def test_with_clipped_stacks_the_first_stack_reaches_150_V_alone_and_early(report, clipped):
    """Around the bias, without the centring of the scaled allocation, the stack the force
    points at runs out first (150 V) while the other two still have room: near 2950 N, 270 N
    before the scaled allocation runs out. The saturation then lasts: the shipped safety lets
    go after 0.5 s (100 N of this ramp) and the beam fails early, in the bow's direction."""
    trace, path = clipped
    _, rows = read_telemetry(path)
    running = rows[:, COL["state"]] == State.RUNNING
    v = rows[:, COL["voltage_a1_V"]:COL["voltage_a1_V"] + 6]
    at_limit = (v == 0.0) | (v == 150.0)
    first = int(np.flatnonzero(running & at_limit.any(axis=1))[0])
    assert at_limit[first].reshape(2, 3).sum(axis=1).max() == 1, f"one stack a support: {v[first]}"
    first_load = rows[first, COL["load_N"]]
    assert 2900.0 < first_load < 3050.0, f"first stack at its limit at {first_load:.0f} N"
    assert trace.fault.startswith("PERSISTENT_SATURATION"), trace.fault
    a = trace.arrays()
    lost = first_crossing(a["load_n"], a["deflection_m"], 1e-3)
    s, _ = report
    assert lost < s["paper_switching"]["load_at_1.0mm_N"] - 100.0, (lost, s["paper_switching"])
    angle = direction_at(a["deflection_m"], a["deflection_y_m"], a["deflection_z_m"], 1e-3)
    assert angle == pytest.approx(234.0, abs=2.0), "the stacks at bias: the bow's direction"


def test_clipped_stacks_that_keep_trying_hold_as_long_and_fail_near_the_bow_s_direction(report, tmp_path):
    """Without the saturation fault (as the paper's setup, whose other stacks "continuously try
    to stabilize"): the unclipped stacks hold the beam until they too run out, within 1 % of the
    scaled allocation's load. The beam then fails within 10 deg of the bow's direction, not at
    the paper's 128 deg: the simulated rig does not reproduce that turn."""
    trace, _ = _clipped_paper_run(tmp_path, safety={"saturation_time_s": 1000.0})
    assert trace.fault == "", trace.fault
    a = trace.arrays()
    lost = first_crossing(a["load_n"], a["deflection_m"], 1e-3)
    s, _ = report
    assert lost == pytest.approx(s["paper_switching"]["load_at_1.0mm_N"], rel=0.01)
    angle = direction_at(a["deflection_m"], a["deflection_y_m"], a["deflection_z_m"], 1e-3)
    assert 234.0 <= angle < 244.0, f"failed at {angle:.1f} deg"
