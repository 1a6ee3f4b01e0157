"""``beamctl ctl``: operator commands to a running ``beamctl run`` over its control socket, and
what they leave in the service's state, its log and its telemetry."""

import json
import os
import socket
import stat
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from beamctl.gains.defaults import default_table_path, paper_table_path
from beamctl.gains.table import load_table
from beamctl.rt.controller import COL
from beamctl.rt.loop import operator_labels
from beamctl.rt.safety import State
from beamctl.rt.telemetry import read_telemetry
from beamctl.service import control
from beamctl.service.control import ControlError, default_socket_path, request
from beamctl.tools.cli import main
from tests.processes import beamctl

DEADLINE_S = 60.0       # for a state to be reached, on a slow shared machine
V = slice(COL["voltage_a1_V"], COL["voltage_a1_V"] + 6)
# the simulated beam at wall-clock pace at 1000 N, bowed as in the paper, under the paper's design
SIM = {"gains": {"table": str(paper_table_path())},
       "hal": {"backend": "sim", "sim": {"pace": "wallclock"}}, "controller": {"pacing": "sample"},
       "plant": {"load": {"start": 1000.0, "end": 1000.0}, "bow": {"amplitude": 5e-5, "angle_deg": 234.0}}}


class Service:
    """A ``beamctl run`` in its own process, its output in files."""

    def __init__(self, tmp_path: Path, flags: tuple, sections: dict) -> None:
        self.telemetry = tmp_path / "run.btl"
        config = tmp_path / "service.yaml"
        config.write_text(yaml.safe_dump({**SIM, "run": {"telemetry": str(self.telemetry)}, **sections}))
        self.config = str(config)
        self.err_path = tmp_path / "service.err"
        with open(tmp_path / "service.out", "wb") as out, open(self.err_path, "wb") as err:
            self.process = beamctl("run", "--config", self.config, *flags, cwd=tmp_path, stdout=out,
                                   stderr=err)

    @property
    def log(self) -> str:
        return self.err_path.read_text()

    def wait_for(self, what: str, condition, socket_path: Path | None = None) -> dict:
        """Poll ``ctl status`` until ``condition(status)`` holds (the service may still be starting);
        fail naming the last status, or the service's log if it ended."""
        deadline = time.monotonic() + DEADLINE_S
        last: object = None
        while True:
            try:
                last = request(socket_path or default_socket_path(), {"command": "status"})["status"]
            except ControlError as exc:
                last = str(exc)
            if isinstance(last, dict) and condition(last):
                return last
            assert self.process.poll() is None, (f"the service ended ({self.process.returncode}) while "
                                                 f"waiting for {what}:\n{self.log}")
            assert time.monotonic() < deadline, f"no {what} within {DEADLINE_S:g} s; last status: {last}"
            time.sleep(0.1)

    def ended(self) -> int:
        """The exit status once the service has ended by itself (killed if it does not)."""
        try:
            return self.process.wait(timeout=DEADLINE_S)
        except Exception:
            self.process.kill()
            raise

    def commands(self) -> list[tuple[str, str]]:
        """[(operator command label, state)] at the rows where the telemetry records one."""
        _, rows = read_telemetry(self.telemetry)
        codes = rows[:, COL["operator_command"]]
        labels = operator_labels()
        return [(labels[int(codes[i])], State(int(rows[i, COL["state"]])).name)
                for i in np.flatnonzero(codes)]


@pytest.fixture
def service(tmp_path, compiled_engine):
    """Starts ``beamctl run`` (``service(*flags, **sections)``); whatever is still running at the
    end of the test is killed."""
    started = []

    def start(*flags, **sections) -> Service:
        directory = tmp_path / f"service{len(started)}"
        directory.mkdir()
        s = Service(directory, flags, sections)
        started.append(s)
        return s

    yield start
    for s in started:
        if s.process.poll() is None:
            s.process.kill()
        s.process.wait(timeout=DEADLINE_S)


def running(status: dict) -> bool:
    return status["state"] == "RUNNING"


def _ctl(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(["ctl", *argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _raw(path: Path, data: bytes, timeout_s: float = DEADLINE_S) -> dict:
    """Send bytes as they are and read the one-line reply."""
    with socket.socket(socket.AF_UNIX) as s:
        s.settimeout(timeout_s)
        s.connect(str(path))
        s.sendall(data)
        reply = b""
        while not reply.endswith(b"\n"):
            chunk = s.recv(65536)
            assert chunk, f"the service closed the connection without a reply to {data[:40]!r}"
            reply += chunk
    return json.loads(reply)


def test_a_running_service_refuses_what_it_cannot_do_answers_malformed_requests_and_stops(
        service, other_table, control_socket, capsys):
    """One running service, in turn (starting a service is most of a test's time; each step fails
    saying what broke):

    - the socket file, left by an earlier service that died, is taken over and made 0660;
    - a second service on its live socket is refused in one line before it records anything;
    - malformed requests are answered saying why, and a client that connects and says nothing
      holds its connection (answered when its read times out) while the others are served;
    - rearm, gains and start are refused saying why (exit 1) and change nothing;
    - stop ramps to bias and ends the service with exit 0.

    Only the operator's commands reach the control loop: each is in the telemetry at the sample
    it was decided at, and in the service's log; the socket file is removed at the end."""
    with socket.socket(socket.AF_UNIX) as dead:     # a socket file nobody listens at any more
        dead.bind(str(control_socket))
    svc = service()
    before = svc.wait_for("RUNNING", running)
    assert stat.S_IMODE(os.stat(control_socket).st_mode) == 0o660, "the socket's owner and group command"

    with socket.socket(socket.AF_UNIX) as silent:
        silent.settimeout(DEADLINE_S)
        silent.connect(str(control_socket))         # connects and says nothing

        second = svc.telemetry.parent / "second.btl"
        assert main(["run", "--config", svc.config, "--telemetry", str(second)]) == 2
        err = capsys.readouterr().err
        assert "another service is running" in err and len(err.strip().splitlines()) == 1, err
        assert not second.exists(), "the refused second service left a recording"

        for data, why in [
            (b"stop now\n", "not JSON"),
            (b"\xff\xfe{}\n", "not UTF-8"),
            (b"[1, 2]\n", "not an object"),
            (b'{"command": "explode"}\n', "unknown command 'explode'"),
            (b'{"command": "stop", "table": "/x.yaml"}\n', "unexpected key 'table'"),
            (b'{"command": "gains"}\n', 'needs "table"'),
            (b'{"command": "gains", "table": "gains.yaml"}\n', "absolute path"),
            (b"x" * (70 * 1024), "longer than 65536 bytes"),
        ]:
            reply = _raw(control_socket, data)
            assert reply["ok"] is False and why in reply["message"], (data[:40], reply)
            assert reply["status"]["state"] == "RUNNING", reply

        for argv, why in ((["rearm"], "no fault to re-arm"), (["gains", str(other_table)], "only at bias"),
                          (["start"], "already running")):
            code, out, err = _ctl(capsys, *argv)
            assert code == 1, (argv, out, err)
            assert why in err and len(err.strip().splitlines()) == 1, err
        # the silent client holds its connection: the others were answered meanwhile
        code, out, _ = _ctl(capsys, "status", "--json")
        status = json.loads(out)["status"]
        assert code == 0 and status["state"] == "RUNNING" and status["cycles"] > before["cycles"], status
        assert status["table"] == str(paper_table_path()) and status["table_sha256"] == load_table(
            paper_table_path()).sha256, "a refused gains command changed the table"
        answer = json.loads(silent.recv(65536))
    assert answer["ok"] is False and "no complete request" in answer["message"], answer

    code, out, err = _ctl(capsys, "stop")
    assert code == 0 and "RUNNING -> STOPPING" in out, (out, err)
    assert svc.ended() == 0, svc.log
    assert svc.commands() == [("rearm refused", "RUNNING"), ("gains refused", "RUNNING"),
                              ("start refused", "RUNNING"), ("stop", "STOPPING")], (
        "the operator's commands, and nothing else (a malformed request reached the control loop?)")
    _, rows = read_telemetry(svc.telemetry)
    assert rows[-1, COL["state"]] == State.STOPPED
    np.testing.assert_array_equal(rows[-1, V], 75.0, err_msg="the service ended with the stacks off bias")
    log = svc.log
    for line in ("operator rearm: refused", f"operator gains {other_table}: refused",
                 "operator start: refused", "operator stop: carried out (RUNNING -> STOPPING)"):
        assert line in log, f"{line!r} is not in the service's log:\n{log}"
    # the eight malformed requests, the silent client and the second service's probe (it
    # connects to see whether a service answers, and sends nothing)
    assert log.count("control socket: refused a request") == 10, log
    assert "(stopped by operator)" in (svc.telemetry.parent / "service.out").read_text()
    assert not control_socket.exists(), "the socket file outlived its service"


def test_a_held_service_takes_another_gain_table_at_bias_then_starts(service, other_table, control_socket,
                                                                    tmp_path, capsys):
    """``--hold``: armed at bias. A changed table and one at another rate are refused as at a
    start (the table in use is kept); a good one is swapped in; start controls the beam with it."""
    tampered = tmp_path / "tampered.yaml"
    tampered.write_text(paper_table_path().read_text().replace("velocity_cutoff_hz: 145.5",
                                                               "velocity_cutoff_hz: 150.0"))
    sock = control_socket.parent / "held.sock"       # the config's control.socket, given to ctl
    svc = service("--hold", control={"socket": str(sock)})
    held = svc.wait_for("ARMED at bias", lambda s: s["state"] == "ARMED" and s["at_bias"], sock)
    paper_sha = load_table(paper_table_path()).sha256
    assert held["table_sha256"] == paper_sha

    for table, why in ((tampered, "sha256"), (default_table_path(), "design.sample_rate_hz")):
        code, out, err = _ctl(capsys, "gains", str(table), "--control-socket", str(sock))
        assert code == 1 and why in err and "refused" in err, (out, err)
        code, out, _ = _ctl(capsys, "status", "--control-socket", str(sock), "--json")
        assert json.loads(out)["status"]["table_sha256"] == paper_sha, f"{table} replaced the table in use"

    code, out, err = _ctl(capsys, "gains", str(other_table), "--control-socket", str(sock), "--json")
    reply = json.loads(out)
    assert code == 0 and reply["ok"], reply
    assert reply["status"]["table"] == str(other_table)
    assert reply["status"]["table_sha256"] == load_table(other_table).sha256
    code, out, err = _ctl(capsys, "start", "--control-socket", str(sock))
    assert code == 0 and "ARMED -> RUNNING" in out, (out, err)
    svc.wait_for("RUNNING", running, sock)
    time.sleep(0.5)     # let the law work a moment: what it did is read from the telemetry below
    assert _ctl(capsys, "stop", "--control-socket", str(sock))[0] == 0
    assert svc.ended() == 0, svc.log

    assert svc.commands() == [("gains refused", "ARMED"), ("gains refused", "ARMED"), ("gains", "ARMED"),
                              ("start", "RUNNING"), ("stop", "STOPPING")]
    _, rows = read_telemetry(svc.telemetry)
    start = int(np.flatnonzero(rows[:, COL["operator_command"]])[3])
    np.testing.assert_array_equal(rows[:start, V], 75.0, err_msg="the stacks left bias before the start")
    driven = np.abs(rows[start:, V] - 75.0).max()
    assert driven > 0.1, f"the law hardly drove the stacks after the start ({driven:.3f} V)"
    assert f"operator gains {other_table}: carried out" in svc.log


def test_rearm_at_bias_after_a_fault_restarts_the_controller(service, control_socket, capsys):
    """The load cell reads 1300 N against a 1100 N range: the controller faults at once and ramps
    to bias. Once the load is back in range (the plant's load falls to 1000 N), a re-arm clears
    the fault and the controller runs again."""
    sock = control_socket.parent / "flag.sock"
    # the load back in range within 0.6 s of the start (the rate only sets how long that takes)
    svc = service("--control-socket", str(sock),
                  controller={"pacing": "sample", "safety": {"load_range_n": [-200.0, 1100.0]}},
                  plant={**SIM["plant"], "load": {"start": 1300.0, "end": 1000.0, "rate": 400.0}})
    faulted = svc.wait_for(
        "FAULT at bias with the load back in range",
        lambda s: s["state"] == "FAULT" and s["at_bias"] and s["axial_load_n"] < 1090.0, sock)
    assert faulted["fault"] == "LOAD_OUT_OF_SENSOR_RANGE", faulted
    code, out, err = _ctl(capsys, "rearm", "--control-socket", str(sock))
    assert code == 0 and "FAULT -> RUNNING" in out, (out, err)
    status = svc.wait_for("RUNNING", running, sock)
    assert status["fault"] == "NONE"
    assert _ctl(capsys, "stop", "--control-socket", str(sock))[0] == 0
    assert svc.ended() == 0, svc.log
    assert svc.commands() == [("rearm", "RUNNING"), ("stop", "STOPPING")]
    _, rows = read_telemetry(svc.telemetry)
    rearm = int(np.flatnonzero(rows[:, COL["operator_command"]])[0])
    assert np.all(rows[rearm:, COL["fault"]] == 0), "a fault came back after the re-arm"


def test_without_a_service_ctl_says_so_in_one_line_and_exits_2(control_socket, capsys):
    code, _, err = _ctl(capsys, "status")
    assert code == 2 and f"no service at {control_socket}" in err and len(err.splitlines()) == 1, err
    with socket.socket(socket.AF_UNIX) as dead:
        dead.bind(str(control_socket))
    code, _, err = _ctl(capsys, "stop")
    assert code == 2 and "a service that has ended" in err and len(err.splitlines()) == 1, err
    code, _, err = _ctl(capsys, "status", "--control-socket", "/tmp/" + "x" * 120)
    assert code == 2 and "at most 107" in err and len(err.splitlines()) == 1, err


def test_a_socket_path_too_long_for_unix_sockets_is_refused_before_the_service_starts(tmp_path, capsys):
    config = tmp_path / "service.yaml"
    config.write_text(yaml.safe_dump({**SIM, "run": {"telemetry": str(tmp_path / "run.btl")},
                                      "control": {"socket": "/tmp/" + "s" * 110}}))
    assert main(["run", "--config", str(config)]) == 2
    err = capsys.readouterr().err
    assert "at most 107" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "run.btl").exists()


def test_the_default_socket_path(monkeypatch, tmp_path):
    """$BEAMCTL_CONTROL_SOCKET; else /run/beamctl when it can be used, then $XDG_RUNTIME_DIR,
    then /tmp/beamctl-<uid>; a socket already in one of them is found first."""
    monkeypatch.setenv("BEAMCTL_CONTROL_SOCKET", "/somewhere/c.sock")
    assert default_socket_path() == Path("/somewhere/c.sock")
    monkeypatch.delenv("BEAMCTL_CONTROL_SOCKET")
    (tmp_path / "run").mkdir()
    monkeypatch.setattr(control, "RUN_DIR", tmp_path / "run" / "beamctl")
    (tmp_path / "xdg").mkdir()
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "xdg"))
    assert default_socket_path() == tmp_path / "run" / "beamctl" / "control.sock"
    (tmp_path / "not-a-dir").write_text("")           # a /run this user cannot make beamctl in
    monkeypatch.setattr(control, "RUN_DIR", tmp_path / "not-a-dir" / "beamctl")
    assert default_socket_path() == tmp_path / "xdg" / "beamctl" / "control.sock"
    monkeypatch.delenv("XDG_RUNTIME_DIR")
    assert default_socket_path() == Path(f"/tmp/beamctl-{os.getuid()}/control.sock")
    # a service's socket is found wherever it is, before a directory that could hold one
    monkeypatch.setattr(control, "RUN_DIR", tmp_path / "run" / "beamctl")
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "xdg"))
    (tmp_path / "xdg" / "beamctl").mkdir()
    (tmp_path / "xdg" / "beamctl" / "control.sock").write_text("")
    assert default_socket_path() == tmp_path / "xdg" / "beamctl" / "control.sock"


def test_a_table_swap_is_read_off_the_service_and_checked_as_at_a_start(tmp_path):
    """The checks of ``ctl gains`` without a running service: a table written for another I/O
    chain (the rig's delay and filters) or changed after it was built is refused naming the
    field; a good one comes back prepared for the controller; ``close`` ends the reader."""
    import dataclasses

    from beamctl.assembly.run import build_hal, load_gain_table, load_service_config
    from beamctl.gains.table import write_table
    from beamctl.models.iochain import IOChain
    from beamctl.rt.controller import Controller
    from beamctl.service.swaps import TableSwaps

    cfg = dataclasses.replace(load_service_config(None), table_path=paper_table_path())
    table = load_gain_table(cfg)
    controller = Controller(table, cfg.controller)
    # another I/O chain (its ride-through analysis, which depends on the chain, left out: the
    # table is consistent, only its chain differs from the rig's)
    delayed = write_table(dataclasses.replace(table, design=dataclasses.replace(
        table.design, io=IOChain(delay_samples=1.0)), ride_through=None), tmp_path / "delayed.yaml")
    changed = tmp_path / "changed.yaml"
    changed.write_text(paper_table_path().read_text().replace("velocity_cutoff_hz: 145.5",
                                                              "velocity_cutoff_hz: 150.0"))
    swaps = TableSwaps(cfg, build_hal(cfg, table), controller)
    try:
        with pytest.raises(ValueError, match=r"design\.io"):
            swaps.prepare(delayed)
        with pytest.raises(ValueError, match="sha256.*changed after it was built"):
            swaps.prepare(changed)
        prepared = swaps.prepare(paper_table_path())
        reader = swaps._reader
    finally:
        swaps.close()
    assert prepared.table.sha256 == table.sha256
    assert prepared.nb >= controller.record.size + 4, "a buffer for the record and the 4 compensator states"
    assert reader.returncode == 0, "the reader process did not end with the swaps"


@pytest.mark.parametrize("argv, old", [(["ctl", "status", "--socket", "/tmp/x.sock"], "--socket"),
                                       (["monitor", "--control", "/tmp/x.sock"], "--control")])
def test_the_old_names_of_the_control_socket_flag_are_refused_naming_the_one_name(argv, old, capsys):
    """run, ctl and monitor all say --control-socket."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"{old} is now --control-socket" in err and len(err.strip().splitlines()) == 1, err
