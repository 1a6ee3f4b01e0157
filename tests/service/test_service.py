"""The lab service started in this process (service/run.py), commanded over its control socket
as ``beamctl ctl`` commands it, and stopped: what a test or a script can do without a
subprocess."""

import time

import numpy as np
import pytest

from beamctl.assembly.run import service_config
from beamctl.gains.defaults import paper_table_path
from beamctl.rt.controller import COL
from beamctl.rt.safety import State
from beamctl.rt.telemetry import read_telemetry
from beamctl.service.control import ControlError, request
from beamctl.service.run import Service, ServiceError

DEADLINE_S = 30.0       # for a state to be reached on a slow shared machine
V = slice(COL["voltage_a1_V"], COL["voltage_a1_V"] + 6)
BIAS_V = 75.0
# the simulated beam at 1000 N, bowed as in the paper, under the paper's design; simulated pace:
# the loop runs as fast as the machine lets it, the commands reach it between two cycles
SIM = {"gains": {"table": str(paper_table_path())}, "hal": {"backend": "sim", "sim": {"pace": "simulated"}},
       "controller": {"pacing": "sample"},
       "plant": {"load": {"start": 1000.0, "end": 1000.0}, "bow": {"amplitude": 5e-5, "angle_deg": 234.0}}}


def _status(path) -> dict:
    return request(path, {"command": "status"})["status"]


def _wait_for(path, what: str, condition) -> dict:
    deadline = time.monotonic() + DEADLINE_S
    status = _status(path)
    while not condition(status):
        if time.monotonic() > deadline:
            pytest.fail(f"the service did not reach {what} within {DEADLINE_S:g} s; last status {status}")
        time.sleep(0.02)
        status = _status(path)
    return status


@pytest.fixture
def service(tmp_path):
    svc = Service(service_config(SIM), tmp_path / "run.btl", control_socket=tmp_path / "ctl.sock", hold=True,
                  acquire_rt=False)
    yield svc
    svc.request_stop()
    if svc._thread is not None:
        svc._thread.join(DEADLINE_S)
    svc.close()


def test_the_service_holds_starts_and_stops_on_the_operator_s_commands(service, tmp_path):
    sock = tmp_path / "ctl.sock"
    service.start()
    held = _wait_for(sock, "ARMED, held at bias", lambda s: s["state"] == "ARMED")
    assert held["at_bias"], f"held (--hold) but the stacks are off bias: {held}"
    assert held["table"] == str(paper_table_path()), held

    reply = request(sock, {"command": "start"})
    assert reply["ok"], reply
    running = _wait_for(sock, "RUNNING with cycles counted",
                        lambda s: s["state"] == "RUNNING" and s["cycles"] > 0)
    assert running["fault"] == "NONE", running

    reply = request(sock, {"command": "stop"})
    assert reply["ok"], reply
    outcome = service.join(DEADLINE_S)
    assert outcome.result.state == "STOPPED", outcome.summary
    assert outcome.summary["cycles"] > running["cycles"], "the loop ran on after the status was read"
    with pytest.raises(ControlError):
        request(sock, {"command": "status"}, timeout_s=2.0)       # the socket closed with the run

    _, rows = read_telemetry(tmp_path / "run.btl")
    assert len(rows) == outcome.summary["cycles"], "every cycle recorded"
    states = rows[:, COL["state"]]
    assert State.RUNNING in states, "the telemetry never saw the controller running"
    assert rows[-1, COL["state"]] == State.STOPPED
    np.testing.assert_array_equal(rows[-1, V], BIAS_V, err_msg="the service ended with the stacks off bias")


def test_a_second_service_on_the_same_socket_is_refused_before_anything_moves(service, tmp_path):
    service.start()
    _wait_for(tmp_path / "ctl.sock", "ARMED", lambda s: s["state"] == "ARMED")
    with pytest.raises(ServiceError, match="ctl.sock"):
        Service(service_config(SIM), tmp_path / "second.btl", control_socket=tmp_path / "ctl.sock",
                acquire_rt=False)
    assert not (tmp_path / "second.btl").exists(), "the refused service began a recording"
    assert _status(tmp_path / "ctl.sock")["state"] == "ARMED", "the first service was disturbed"


def test_request_stop_ends_a_running_service_with_the_stacks_at_bias(tmp_path):
    svc = Service(service_config(SIM), tmp_path / "run.btl", control_socket=tmp_path / "ctl.sock",
                  acquire_rt=False)
    svc.start()
    _wait_for(tmp_path / "ctl.sock", "RUNNING", lambda s: s["state"] == "RUNNING" and s["cycles"] > 100)
    svc.request_stop()
    outcome = svc.join(DEADLINE_S)
    assert outcome.result.state == "STOPPED" and outcome.result.stop_requested_by, outcome.summary
    _, rows = read_telemetry(tmp_path / "run.btl")
    np.testing.assert_array_equal(rows[-1, V], BIAS_V, err_msg="stopped with the stacks off bias")


def test_sigusr1_s_rearm_is_logged_off_the_loop_and_a_failing_log_does_not_stop_control(tmp_path):
    """The re-arm a signal asks for (``loop.request_rearm``, what SIGUSR1 calls) is decided in the
    loop and logged by the control socket's thread: a log that fails (stderr gone) costs the line,
    not the run. The load cell reads 1300 N against a 1100 N range, so the service faults at once;
    once the load is back in range and the stacks at bias, the re-arm runs the controller again."""
    lines: list[str] = []

    def failing_log(line: str) -> None:
        lines.append(line)
        raise BrokenPipeError("stderr is gone")

    config = {**SIM, "controller": {"pacing": "sample", "safety": {"load_range_n": [-200.0, 1100.0]}},
              "plant": {**SIM["plant"], "load": {"start": 1300.0, "end": 1000.0, "rate": 400.0}}}
    svc = Service(service_config(config), tmp_path / "run.btl", control_socket=tmp_path / "ctl.sock",
                  acquire_rt=False, log=failing_log)
    svc.start()
    try:
        sock = tmp_path / "ctl.sock"
        _wait_for(sock, "FAULT at bias with the load back in range",
                  lambda s: s["state"] == "FAULT" and s["at_bias"] and s["axial_load_n"] < 1090.0)
        svc.loop.request_rearm()
        running = _wait_for(sock, "RUNNING after the re-arm", lambda s: s["state"] == "RUNNING")
        assert running["fault"] == "NONE", running
        deadline = time.monotonic() + DEADLINE_S
        while not lines and time.monotonic() < deadline:
            time.sleep(0.02)
        assert lines == ["operator rearm (SIGUSR1): carried out (FAULT -> RUNNING)"], lines
        later = _status(sock)
        assert later["state"] == "RUNNING" and later["cycles"] > running["cycles"], later
    finally:
        svc.request_stop()
        outcome = svc.join(DEADLINE_S)
    assert outcome.result.state == "STOPPED", outcome.summary
