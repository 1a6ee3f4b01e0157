"""``beamctl run``: the service, its refusals and its operator re-arm."""

import json
import signal
import time

import can
import numpy as np
import pytest
import yaml

from beamctl.gains.defaults import paper_table_path
from beamctl.hal.budget import bus_budget
from beamctl.hal.dbc import Contract
from beamctl.hal.emulator import CanPlantEmulator
from beamctl.rt.controller import COL
from beamctl.rt.telemetry import TelemetryError, read_telemetry
from beamctl.tools.cli import main
from tests.hal.rigs import GEOMETRY, make_plant, service_backends, wait_until
from tests.processes import beamctl

# the paper's design (integral LQR, 2500 Hz) builds in seconds; the robust check is left out
PAPER_BUILD = ("gains", "build", "--design", "integral-lqr", "--no-robust")


def _has_records(path) -> bool:
    """The file exists with at least one record (its header may still be on its way)."""
    try:
        return len(read_telemetry(path)[1]) > 0
    except TelemetryError:
        return False


def _config(tmp_path, **sections):
    """A service file; unless a test says otherwise it runs the paper's design (2500 Hz), whose
    frames fit on classic CAN, so that the loop and the CAN path are tested at the rate they
    have been measured at."""
    sections.setdefault("gains", {"table": str(paper_table_path())})
    can = sections.get("hal", {}).get("can")
    if can is not None:
        can.setdefault("fd", False)
    f = tmp_path / "service.yaml"
    f.write_text(yaml.safe_dump(sections))
    return str(f)


# the simulated beam as fast as it computes (what these runs record is counted in samples; the
# tests of the wall clock's pace say "wallclock")
SIM = {"hal": {"backend": "sim", "sim": {"pace": "simulated"}}, "controller": {"pacing": "sample"},
       "plant": {"load": {"start": 1000.0, "end": 1000.0}, "bow": {"amplitude": 5e-5, "angle_deg": 234.0}}}


def test_run_for_a_duration_writes_telemetry_and_exits_0(tmp_path, capsys):
    tel = tmp_path / "run.btl"
    cfg = _config(tmp_path, **SIM, run={"telemetry": str(tel), "duration_s": 0.4})
    assert main(["run", "--config", cfg]) == 0
    out = capsys.readouterr().out
    assert "ended STOPPED" in out and "0 dropped" in out
    _, rows = read_telemetry(tel)
    assert 1000 + 1250 <= len(rows) <= 1000 + 1250 + 2, "0.4 s of control, then 0.5 s of ramp to bias"
    np.testing.assert_array_equal(rows[-1, COL["voltage_a1_V"]:COL["voltage_a1_V"] + 6], 75.0)


def test_a_table_for_another_model_is_refused(tmp_path, capsys):
    cfg = _config(tmp_path, **SIM, model={"supports": {"rotational_stiffness": 200.0}})
    assert main(["run", "--config", cfg]) == 2
    err = capsys.readouterr().err
    assert "model.sha256" in err and "regenerate" in err


def test_a_bus_over_budget_is_refused_with_what_would_fit(tmp_path, capsys):
    cfg = _config(tmp_path, hal={"backend": "can", "can": {"interface": "virtual", "channel": "budget",
                                                            "bitrate_bit_s": 500000}})
    assert main(["run", "--config", cfg]) == 2
    err = capsys.readouterr().err
    highest = int(bus_budget(Contract(), 2500.0, 500e3).max_sample_rate_hz)
    assert f"{cfg}: hal.can:" in err and "bus load" in err, err
    assert f"at most {highest} Hz" in err and "CAN FD" in err, err
    assert len(err.strip().splitlines()) == 1, err


def test_a_forced_table_is_refused(tmp_path, capsys):
    table = tmp_path / "forced.yaml"
    assert main([*PAPER_BUILD, "--grid", "4000:4500:500", "--out", str(table), "--force"]) == 0
    capsys.readouterr()
    cfg = _config(tmp_path, **SIM, gains={"table": str(table)})
    assert main(["run", "--config", cfg]) == 2
    assert "forced" in capsys.readouterr().err


def test_service_against_the_plant_emulator_over_virtual_can(tmp_path, capsys, monkeypatch):
    """The service at the shipped safety (the gain table's ride-through limits) against the DAQ
    emulator in lockstep: its CAN backend is the rig's (tests/hal/rigs.py: on a clock of the
    test's own, waiting for each sample while the emulator runs), so that this machine's
    scheduling neither starves it of samples nor makes its answers late."""
    bus = can.Bus(interface="virtual", channel="service")
    emulator = CanPlantEmulator(bus, make_plant(), GEOMETRY, pace="lockstep")
    service_backends(monkeypatch, emulator)
    emulator.start()
    cfg = _config(tmp_path, hal={"backend": "can", "can": {"interface": "virtual", "channel": "service",
                                                            "rate_tolerance": 0.0}},
                  controller={"pacing": "sample"},
                  run={"telemetry": str(tmp_path / "can.btl"), "duration_s": 0.4})
    try:
        assert main(["run", "--config", cfg, "--json"]) == 0
        # the emulator takes the status frame the service ended with
        wait_until(lambda: emulator.last_state == 5, "the DAQ hearing STOPPED")
    finally:
        emulator.stop()
        bus.shutdown()
    summary = json.loads(capsys.readouterr().out)
    assert summary["state"] == "STOPPED" and summary["stopped_by"] == "cycle limit", summary["reason"]
    assert summary["cycles"] >= 1000 and summary["late_answers"] == 0
    assert summary["hal"]["sequence_gaps"] == 0
    assert summary["hal"]["bus_load_percent"] == pytest.approx(
        100 * bus_budget(Contract(), 2500.0, 1e6).load, rel=1e-9), "classic CAN at 1 Mbit/s, 2500 Hz"
    assert emulator.status_frames > 0
    assert emulator.last_state == 5, "the DAQ's last word from the controller is STOPPED"


@pytest.mark.parametrize(("sections", "new_key"), [
    ({"controller": {"safety": {"ramp_time": 0.5}}}, "controller.safety.ramp_time_s"),
    ({"hal": {"can": {"bitrate": 1_000_000}}}, "hal.can.bitrate_bit_s"),
    ({"run": {"duration": 10.0}}, "run.duration_s"),
])
def test_a_config_with_a_key_from_before_the_units_were_named_is_refused_in_one_line(tmp_path, capsys,
                                                                                     sections, new_key):
    assert main(["run", "--config", _config(tmp_path, **sections)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"expected {new_key} in its place" in err, err


def test_a_voltage_range_the_dbc_cannot_carry_is_refused(tmp_path, capsys):
    cfg = _config(tmp_path, hal={"backend": "can", "can": {"interface": "virtual", "channel": "range"}},
                  controller={"actuators": {"min_voltage_v": -20.0, "bias_voltage_v": 60.0}})
    assert main(["run", "--config", cfg]) == 2
    err = capsys.readouterr().err
    assert "controller.actuators.min_voltage_v" in err and "[0, 150] V" in err


def test_a_run_longer_than_the_telemetry_ring_loses_nothing(tmp_path, capsys):
    """The writer thread drains the ring while the loop runs (a 0.6 s ring, a 1.5 s run)."""
    tel = tmp_path / "long.btl"
    controller = {"pacing": "sample", "telemetry": {"buffer_time_s": 0.6, "flush_interval_s": 0.1}}
    cfg = _config(tmp_path, **{**SIM, "controller": controller,
                               "hal": {"backend": "sim", "sim": {"pace": "wallclock"}},
                               "run": {"telemetry": str(tel), "duration_s": 1.5}})
    assert main(["run", "--config", cfg, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["telemetry"]["dropped"] == 0
    _, rows = read_telemetry(tel)
    assert len(rows) == summary["cycles"] == summary["telemetry"]["written"]


def test_a_ring_shorter_than_two_flushes_is_refused(tmp_path, capsys):
    cfg = _config(tmp_path, controller={"telemetry": {"buffer_time_s": 0.2, "flush_interval_s": 0.25}})
    assert main(["run", "--config", cfg]) == 2
    assert "controller.telemetry.buffer_time_s" in capsys.readouterr().err


def test_timer_pacing_with_the_can_backend_is_refused(tmp_path, capsys):
    cfg = _config(tmp_path, hal={"backend": "can"}, controller={"pacing": "timer"})
    assert main(["run", "--config", cfg]) == 2
    assert "controller.pacing" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [
    ["run", "--config", "x.yaml", "--duration", "nan"],
    ["run", "--config", "x.yaml", "--duration", "-1"],
    ["bus-budget", "--bitrate", "0"],
    ["bench", "--steps", "0"],
])
def test_bad_flags_are_refused_with_exit_2(argv, capsys):
    assert main(argv) == 2
    assert "expected" in capsys.readouterr().err


def test_a_single_point_grid_cannot_be_interpolated(tmp_path, capsys):
    assert main([*PAPER_BUILD, "--grid", "100:100:1", "--out", str(tmp_path / "g.yaml")]) == 2
    assert "--grid" in capsys.readouterr().err and not (tmp_path / "g.yaml").exists()


def test_json_prints_exactly_one_object_and_the_banner_goes_to_stderr(tmp_path, capsys):
    cfg = _config(tmp_path, **SIM, run={"telemetry": str(tmp_path / "run.btl"), "duration_s": 0.1})
    assert main(["run", "--config", cfg, "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["state"] == "STOPPED"
    assert captured.err.startswith("beamctl run: sim backend")


def test_ctrl_c_is_the_operator_s_stop_and_exits_0(tmp_path, compiled_engine):
    """For the service SIGINT is a normal stop: ramp to bias, flush telemetry, exit 0."""
    tel = tmp_path / "run.btl"
    cfg = _config(tmp_path, **{**SIM, "hal": {"backend": "sim", "sim": {"pace": "wallclock"}},
                               "run": {"telemetry": str(tel), "duration_s": 0}})
    process = beamctl("run", "--config", cfg, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 300
        # the loop is running (and handles SIGINT) once its records reach the file
        while not _has_records(tel):
            assert process.poll() is None and time.monotonic() < deadline, process.communicate()
            time.sleep(0.05)
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=300)
    finally:
        process.kill()
    assert process.returncode == 0, err
    assert b"stopped by SIGINT" in out and b"ended STOPPED" in out and b"Traceback" not in err


def test_a_recording_is_never_overwritten(tmp_path, capsys):
    """The lab's service restarts with the same configuration: a telemetry path that holds a
    recording is refused before anything runs, and a name with the time in it gives each
    start its own file."""
    tel = tmp_path / "run.btl"
    tel.write_bytes(b"the recording of an earlier run")
    cfg = _config(tmp_path, **SIM, run={"telemetry": str(tel), "duration_s": 0.1})
    assert main(["run", "--config", cfg]) == 2
    err = capsys.readouterr().err
    assert str(tel) in err and "never overwritten" in err and len(err.strip().splitlines()) == 1, err
    assert tel.read_bytes() == b"the recording of an earlier run"
    pattern = _config(tmp_path, **SIM, run={"telemetry": str(tmp_path / "run-%Y%m%d-%H%M%S.btl"),
                                            "duration_s": 0.1})
    assert main(["run", "--config", pattern]) == 0
    made = sorted(p.name for p in tmp_path.glob("run-*.btl"))
    assert len(made) == 1 and made[0] != "run-%Y%m%d-%H%M%S.btl", made
    assert len(read_telemetry(tmp_path / made[0])[1]) > 0


def test_a_refused_real_time_start_leaves_no_telemetry_file(tmp_path, capsys, monkeypatch):
    """--require-rt on a machine that refuses SCHED_FIFO: exit 2 in one line, and no empty
    recording left behind."""
    from beamctl.rt import realtime

    def refuse(settings, require=False):
        raise realtime.RealtimeError("real-time privileges refused (--require-rt): scheduler refused")

    monkeypatch.setattr(realtime, "acquire", refuse)
    tel = tmp_path / "rt.btl"
    cfg = _config(tmp_path, **SIM, run={"telemetry": str(tel), "duration_s": 0.1})
    assert main(["run", "--config", cfg, "--require-rt"]) == 2
    err = capsys.readouterr().err
    assert "--require-rt" in err and "Traceback" not in err
    assert not tel.exists(), "a stub telemetry file was left behind"


def test_a_missing_gain_table_is_refused_naming_the_key_and_what_to_run(tmp_path, capsys):
    cfg = _config(tmp_path, **SIM, gains={"table": str(tmp_path / "nothere.yaml")})
    assert main(["run", "--config", cfg]) == 2
    err = capsys.readouterr().err
    assert "gains.table" in err and cfg in err and "beamctl gains build --out" in err, err
    assert len(err.strip().splitlines()) == 1, err
