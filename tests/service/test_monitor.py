"""``beamctl monitor``'s server: what reaches the page, and who may send operator commands."""

import http.client
import json
import os
import socket
import urllib.parse

import numpy as np
import pytest

from beamctl.rt.live import LiveError, LivePublisher
from beamctl.service.monitor import Monitor
from beamctl.tools.cli import main

COLUMNS = ["time_s", "sequence", "state", "fault", "flags", "load_N", "not_for_the_page"]
RATE_HZ = 2500.0


@pytest.fixture
def monitor(short_dir):
    with Monitor(os.path.join(short_dir, "live.sock"), port=0,
                 control_path=os.path.join(short_dir, "control.sock")) as m:
        yield m


def _request(monitor, method: str, path: str, body: bytes | None = None, headers: dict | None = None,
             token: str | None = "right") -> tuple[int, bytes]:
    if token is not None:
        query = urllib.parse.urlencode({"token": monitor.token if token == "right" else token})
        path += ("&" if "?" in path else "?") + query
    connection = http.client.HTTPConnection("127.0.0.1", monitor.port, timeout=60)
    try:
        connection.request(method, path, body=body, headers=headers or {})
        response = connection.getresponse()
        return response.status, response.read()
    finally:
        connection.close()


def _first_event_with_rows(monitor) -> dict:
    """The first server-sent event that carries rows (the page's view of the window)."""
    connection = http.client.HTTPConnection("127.0.0.1", monitor.port, timeout=60)
    try:
        connection.request("GET", f"/events?token={monitor.token}")
        response = connection.getresponse()
        assert response.status == 200
        for line in response:
            if line.startswith(b"data: "):
                event = json.loads(line[6:])
                if "data" in event:
                    return event
    finally:
        connection.close()
    raise AssertionError("the event stream ended without rows")


def _rows(first: int, n: int) -> np.ndarray:
    i = np.arange(first, first + n, dtype=float)
    return np.column_stack([i / RATE_HZ, i, np.full(n, 2.0), np.zeros(n), np.zeros(n), 1000.0 + 0.1 * i,
                            np.full(n, 7.0)])


@pytest.mark.parametrize("token", [None, "", "wrong-token"])
def test_a_command_without_the_token_or_with_a_wrong_one_is_refused_403(monitor, token):
    status, body = _request(monitor, "POST", "/command", b'{"command": "stop"}',
                            {"Content-Type": "application/json"}, token=token)
    assert status == 403, body
    assert json.loads(body)["ok"] is False and "token" in json.loads(body)["message"]


def test_the_token_in_a_header_is_accepted_as_in_the_url(monitor):
    status, body = _request(monitor, "POST", "/command", b'{"command": 5}',
                            {"X-Beamctl-Token": monitor.token}, token=None)
    assert status == 400, "admitted, then refused for its body"


@pytest.mark.parametrize(("body", "why"), [
    (b"{not json", "not JSON"),
    (b"[1, 2]", "not a JSON object"),
    (b'{"command": "explode"}', "'explode': expected one of status, start, stop, rearm, gains"),
    (b'{"command": "gains"}', "gains needs 'table'"),
    (b'{"command": "stop", "table": "x.yaml"}', "stop takes no 'table'"),
    (b'{"command": "stop", "force": true}', "unknown key 'force'"),
])
def test_a_malformed_command_is_refused_400_in_one_line(monitor, body, why):
    status, reply = _request(monitor, "POST", "/command", body)
    assert status == 400, reply
    assert reply.count(b"\n") == 1 and reply.endswith(b"\n"), reply
    assert why in json.loads(reply)["message"], reply


def test_a_body_larger_than_a_command_is_refused_before_it_is_read(monitor):
    status, reply = _request(monitor, "POST", "/command", b"{" + b" " * 10_000 + b"}")
    assert status == 400 and b"at most 4096 bytes" in reply


def test_a_request_for_another_host_name_is_refused_however_it_reached_127_0_0_1(monitor):
    """DNS rebinding: a name an attacker controls, resolved to 127.0.0.1, carries its own Host."""
    status, reply = _request(monitor, "POST", "/command", b'{"command": "stop"}', {"Host": "evil.example:80"})
    assert status == 403 and b"Host" in reply
    status, _ = _request(monitor, "GET", "/", headers={"Host": "evil.example"})
    assert status == 403


def test_a_command_sent_from_another_site_is_refused(monitor):
    status, reply = _request(monitor, "POST", "/command", b'{"command": "stop"}',
                             {"Origin": "http://evil.example"})
    assert status == 403 and b"another site" in reply


def test_the_page_needs_the_token_and_is_served_whole_with_nothing_from_elsewhere(monitor):
    assert _request(monitor, "GET", "/", token=None)[0] == 403
    status, page = _request(monitor, "GET", "/")
    assert status == 200 and b"<canvas" in page
    assert b"://" not in page.replace(b"http://www.w3.org", b""), "the page loads nothing from another host"


def test_a_command_for_a_service_that_is_not_running_says_so(monitor):
    status, reply = _request(monitor, "POST", "/command", b'{"command": "status"}')
    answer = json.loads(reply)
    assert status == 503 and answer["ok"] is False and "no service at" in answer["message"], answer


def test_the_page_gets_the_service_s_rows_and_its_own_columns_only(monitor):
    publisher = LivePublisher(monitor.live_path, COLUMNS, RATE_HZ, meta={"label": "test run"})
    publisher.publish([_rows(0, 2500)], 0)
    event = _first_event_with_rows(monitor)
    assert event["reset"] is True and event["run"]["label"] == "test run"
    data = event["data"]
    assert "not_for_the_page" not in data and "columns" not in event["run"]
    k = publisher.decimation
    np.testing.assert_allclose(data["sequence"], np.arange(k - 1, 2500, k))
    np.testing.assert_allclose(data["load_N"], 1000.0 + 0.1 * np.arange(k - 1, 2500, k), rtol=1e-6,
                               err_msg="sent with 7 significant digits")
    assert event["status"]["datagrams"] == publisher.sent and event["status"]["datagrams_missed"] == 0


def test_a_new_run_replaces_the_old_one_on_the_page(monitor):
    first = LivePublisher(monitor.live_path, COLUMNS, RATE_HZ, meta={"label": "first"})
    first.publish([_rows(0, 500)], 0)
    second = LivePublisher(monitor.live_path, COLUMNS, RATE_HZ, meta={"label": "second"})
    second.publish([_rows(0, 100)], 0)
    event = _first_event_with_rows(monitor)
    if event["run"]["label"] == "first":         # the page connected between the two
        event = _first_event_with_rows(monitor)
    assert event["run"]["label"] == "second" and event["reset"] is True
    assert len(event["data"]["sequence"]) == 100 // second.decimation, "nothing of the first run"


def test_a_second_monitor_on_the_same_socket_is_refused_and_a_stale_socket_is_replaced(short_dir):
    path = os.path.join(short_dir, "live.sock")
    with Monitor(path, port=0):
        with pytest.raises(LiveError, match="another monitor listens there"):
            Monitor(path, port=0)
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    stale.bind(path)
    stale.close()           # the file stays: a monitor killed with -9 leaves it so
    assert os.path.exists(path)
    with Monitor(path, port=0) as monitor:
        LivePublisher(path, COLUMNS, RATE_HZ).publish([_rows(0, 100)], 0)
        assert _first_event_with_rows(monitor)["data"]["sequence"]
    assert not os.path.exists(path), "the monitor removes its socket when it stops"


def test_monitor_refuses_a_port_in_use_in_one_line(short_dir, capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["monitor", "--port", str(port), "--live", os.path.join(short_dir, "live.sock")]) == 2
    err = capsys.readouterr().err
    assert f"--port {port}" in err and "--port 0" in err and len(err.strip().splitlines()) == 1, err
    assert not os.path.exists(os.path.join(short_dir, "live.sock")), "nothing left behind"


@pytest.mark.parametrize("argv", [["monitor", "--port", "70000"], ["monitor", "--window", "0"],
                                  ["monitor", "--live", "/tmp/" + "x" * 120]])
def test_bad_monitor_flags_are_refused_with_exit_2(argv, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "expected" in err or "at most 107 bytes" in err, err
    assert len(err.strip().splitlines()) == 1, err
