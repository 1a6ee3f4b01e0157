"""The live view end to end: ``beamctl run --live`` and ``beamctl monitor`` in their own
processes, the page in a real headless Chromium; a viewer that stalls or dies; the experiment's
runs on the view."""

import contextlib
import json
import os
import select
import signal
import socket
import subprocess
import threading
import time

import numpy as np
import pytest
import yaml

from beamctl.gains.defaults import paper_table_path
from beamctl.rt.live import decode
from beamctl.rt.safety import State
from beamctl.rt.telemetry import TelemetryError, read_telemetry
from beamctl.tools.cli import main
from tests.processes import beamctl
from tests.service.browser import HeadlessChromium, find_browser

DEADLINE_S = 60.0
LOAD_RATE_N_PER_S = 10.0
BROWSER = find_browser()
NO_BROWSER = ("no Chromium on PATH (chromium, chromium-browser or google-chrome); .ci/run installs "
              "Debian's chromium when it runs as root")

# the paper's design at 2500 Hz against the simulated plant on the wall clock; the load cell is
# noiseless, so that the load the page shows rises exactly at the ramp's rate
SERVICE = {"gains": {"table": str(paper_table_path())},
           "hal": {"backend": "sim", "sim": {"pace": "wallclock"}},
           "controller": {"pacing": "sample"},
           "plant": {"load": {"start": 500.0, "end": 3000.0, "rate": LOAD_RATE_N_PER_S},
                     "bow": {"amplitude": 5e-5, "angle_deg": 234.0},
                     "noise": {"strain": 2e-7, "load": 0.0, "seed": 1}}}


def _service(tmp_path, telemetry, live: str | None, *flags: str) -> subprocess.Popen:
    """``beamctl run --live [live]`` until stopped, recording into ``telemetry``."""
    path = tmp_path / "service.yaml"
    path.write_text(yaml.safe_dump({**SERVICE, "run": {"telemetry": str(telemetry), "duration_s": 0}}))
    return beamctl("run", "--config", str(path), *flags, "--live", *([live] if live else []), cwd=tmp_path)


def _url_of(monitor: subprocess.Popen) -> str:
    """The URL the monitor prints on stdout once it serves."""
    deadline = time.monotonic() + DEADLINE_S
    while time.monotonic() < deadline:
        assert monitor.poll() is None, f"beamctl monitor ended: {monitor.communicate()[1].decode()}"
        if select.select([monitor.stdout], [], [], 0.5)[0]:
            return monitor.stdout.readline().decode().strip()
    raise AssertionError(f"beamctl monitor printed no URL within {DEADLINE_S} s")


def _records(path) -> int:
    try:
        return len(read_telemetry(path)[1])
    except TelemetryError:      # not created yet, or its header on its way
        return 0


def _records_reach(path, count: int, service: subprocess.Popen) -> None:
    """Wait until the running service has recorded ``count`` records."""
    deadline = time.monotonic() + DEADLINE_S
    while _records(path) < count:
        assert service.poll() is None, f"the service ended: {service.communicate()[1].decode()}"
        assert time.monotonic() < deadline, f"the service recorded {_records(path)} of {count} records " \
                                            f"within {DEADLINE_S} s: it is held up"
        time.sleep(0.1)


def _stop(process: subprocess.Popen | None) -> tuple[bytes, bytes]:
    """SIGINT (the operator's stop), then SIGKILL if it has not ended within the deadline."""
    if process is None:
        return b"", b""
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
    try:
        return process.communicate(timeout=DEADLINE_S)
    except subprocess.TimeoutExpired:
        process.kill()
        return process.communicate()


PAGE_VALUES = """(() => {
  const text = (id) => document.getElementById(id).textContent;
  return {state: text("value-state"), fault: text("value-fault"), connection: text("connection"),
          time: parseFloat(text("value-time")), load: parseFloat(text("value-load")),
          cycles: parseInt(text("value-cycles")), points: (buf.time_s || []).length,
          reply: text("value-reply")};
})()"""


def _page_when(browser: HeadlessChromium, condition, what: str) -> dict:
    deadline = time.monotonic() + DEADLINE_S
    values = None
    while time.monotonic() < deadline:
        values = browser.evaluate(PAGE_VALUES)
        if condition(values):
            return values
        time.sleep(0.2)
    raise AssertionError(f"the page did not show {what} within {DEADLINE_S} s; it shows {values}")


@contextlib.contextmanager
def _page_of_a_service(tmp_path, *service_flags: str):
    """``beamctl monitor`` and ``beamctl run --live`` with their default sockets (the test's own:
    tests/conftest.py), the monitor's page open in a headless Chromium: (service, browser). Every
    process is ended afterwards."""
    monitor = beamctl("monitor", "--port", "0", cwd=tmp_path)
    service = browser = None
    try:
        # the three start side by side (a second or two each); what the service sends before the
        # monitor listens is dropped and counted, as whenever no viewer listens
        service = _service(tmp_path, tmp_path / "run.btl", None, *service_flags)
        browser = HeadlessChromium(BROWSER, width=1400, height=900)     # a lab PC's window
        browser.open(_url_of(monitor))
        yield service, browser
    finally:
        if browser is not None:
            browser.close()
        _stop(service)
        _stop(monitor)


@pytest.mark.skipif(BROWSER is None, reason=NO_BROWSER)
def test_the_page_s_buttons_command_the_service_and_the_page_shows_its_values_as_they_change(
        tmp_path, other_table, compiled_engine):
    """A service started with --hold waits ARMED at bias. The page's Switch gains swaps the table
    there, and the page's title then names the table the service runs, not the one it started
    with; the page's Start runs it, and the values it shows change as the service runs (the
    load at the ramp's rate); its Stop ends it (the operator's stop: the stacks ramp to bias, the
    service exits 0), each reply on the page. One service, monitor and browser for all of it:
    starting them is most of the test's time; each step fails saying what the page did not show."""
    with _page_of_a_service(tmp_path, "--hold") as (service, browser):
        armed = _page_when(browser, lambda v: v["state"] == "ARMED" and v["connection"] == "live",
                           "ARMED (--hold), live")
        started_with = browser.evaluate("document.getElementById('run-label').textContent")
        layout = browser.evaluate(
            "({width: document.documentElement.scrollWidth, window: window.innerWidth,"
            " height: window.innerHeight,"
            " start: document.getElementById('button-start').getBoundingClientRect().bottom,"
            " voltages: document.getElementById('chart-voltages').getBoundingClientRect().bottom,"
            " scheduled: document.getElementById('value-scheduled').textContent})")
        browser.evaluate(f"document.getElementById('gains-table').value = {json.dumps(str(other_table))};"
                         "document.getElementById('button-gains').click()")
        swapped = _page_when(browser, lambda v: "gains: done" in v["reply"] or "refused" in v["reply"],
                             "the reply to Switch gains")
        title = ""
        deadline = time.monotonic() + DEADLINE_S
        while str(other_table) not in title and time.monotonic() < deadline:
            title = browser.evaluate("document.getElementById('run-label').textContent")
            time.sleep(0.2)
        browser.evaluate("document.getElementById('button-start').click()")
        started = _page_when(browser, lambda v: v["state"] == "RUNNING" and v["load"] == v["load"],
                             "RUNNING after Start")
        later = _page_when(browser, lambda v: v["time"] >= started["time"] + 2.0,
                           f"a time 2 s past {started['time']} s")
        browser.evaluate("document.getElementById('button-stop').click()")
        stopped = _page_when(browser, lambda v: v["state"] == "STOPPED", "STOPPED after Stop")
        out, err = service.communicate(timeout=DEADLINE_S)
    assert armed["fault"].startswith("NONE"), armed
    # at 1400 x 900 the page fits the window's width, and the buttons and the voltages are in view;
    # ARMED, the schedule has no point yet (it said "0.0 N")
    assert layout["width"] <= layout["window"], layout
    assert layout["start"] <= layout["height"] and layout["voltages"] <= layout["height"], layout
    assert layout["scheduled"].startswith("none yet: ARMED"), layout
    assert str(paper_table_path()) in started_with, started_with
    assert "gains: done" in swapped["reply"], swapped["reply"]
    assert title.endswith(f"gain table {other_table}"), (
        f"the page's title after the swap: {title!r}; the service runs {other_table}")
    assert "start: done" in started["reply"] and "ARMED -> RUNNING" in started["reply"], started
    assert started["fault"].startswith("NONE"), started
    assert later["cycles"] > started["cycles"] and later["points"] > 0, (started, later)
    # shown with 0.1 N and 1 ms: over at least 2 s (20 N) the rate is good to 1 %
    rate = (later["load"] - started["load"]) / (later["time"] - started["time"])
    assert rate == pytest.approx(LOAD_RATE_N_PER_S, rel=0.02), (started, later)
    assert "stop: done" in stopped["reply"], stopped
    assert service.returncode == 0 and b"ended STOPPED" in out and b"stopped by operator" in out, (
        out.decode(), err.decode())


def test_a_viewer_that_stalls_and_dies_never_holds_up_the_service(tmp_path, short_dir, compiled_engine):
    """The monitor is stopped (SIGSTOP: its queue fills), then killed (its socket file stays):
    the service records on, then stops normally, every record written; the view's datagrams
    are dropped and counted."""
    live = os.path.join(short_dir, "live.sock")
    telemetry = tmp_path / "run.btl"
    monitor = beamctl("monitor", "--port", "0", "--live", live, cwd=tmp_path)
    service = None
    try:
        service = _service(tmp_path, telemetry, live)     # starting while the monitor starts
        _url_of(monitor)
        # a second of control once the monitor listens: it has been fed
        _records_reach(telemetry, _records(telemetry) + 2500, service)
        monitor.send_signal(signal.SIGSTOP)
        _records_reach(telemetry, _records(telemetry) + 2 * 2500, service)
        monitor.kill()
        # a second: four drains, each sent to a socket nobody reads any more (dropped at once)
        _records_reach(telemetry, _records(telemetry) + 2500, service)
        service.send_signal(signal.SIGINT)
        out, err = service.communicate(timeout=DEADLINE_S)
    finally:
        _stop(service)
        monitor.kill()
        monitor.communicate()
    assert service.returncode == 0, err.decode()
    text = out.decode()
    assert "ended STOPPED" in text and "0 dropped," in text, text
    line = next(x for x in text.splitlines() if "live view" in x)
    sent = int(line.split(" datagrams sent, ")[0].split()[-1])
    dropped = int(line.split(" datagrams sent, ")[1].split()[0])
    assert sent > 0 and dropped > 0, line


def test_run_with_nobody_listening_records_everything(tmp_path, short_dir, capsys):
    cfg = {**SERVICE, "hal": {"backend": "sim"},
           "run": {"telemetry": str(tmp_path / "r.btl"), "duration_s": 0.4}}
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(cfg))
    assert main(["run", "--config", str(tmp_path / "s.yaml"), "--live", os.path.join(short_dir, "no.sock"),
                 "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["telemetry"]["dropped"] == 0 and _records(tmp_path / "r.btl") == summary["cycles"]
    assert summary["live"]["sent"] == 0 and summary["live"]["dropped"] > 0, summary["live"]


def test_the_experiment_shows_each_run_on_the_view_under_its_own_name(tmp_path, short_dir):
    path = os.path.join(short_dir, "live.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(0.2)
    received, done = [], threading.Event()

    def read():         # a viewer that keeps up
        while not done.is_set():
            try:
                received.append(decode(sock.recv(1 << 17)))
            except TimeoutError:
                pass

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    scenario = tmp_path / "fast.yaml"
    scenario.write_text("plant:\n  load: {start: 1800.0, end: 2800.0, rate: 200.0, hold: 0.1}\n")
    try:
        assert main(["experiment", "--config", str(scenario), "--out", str(tmp_path / "report"), "--no-paper",
                     "--live", path, "--json"]) == 0
    finally:
        done.set()
        reader.join(DEADLINE_S)
        sock.close()
    runs: dict[str, list[np.ndarray]] = {}
    for header, rows in received:
        columns = header["run"]["columns"]
        runs.setdefault(header["run"]["label"].split(",")[1].split()[0], []).append(
            rows[:, [columns.index(c) for c in ("time_s", "load_N", "deflection_m", "state")]])
    assert sorted(runs) == ["interpolate", "uncontrolled"], sorted(runs)
    for mode, blocks in runs.items():
        rows = np.concatenate(blocks)
        assert np.all(np.diff(rows[:, 0]) > 0), f"{mode}: the run's time runs forward on the view"
    uncontrolled, controlled = (np.concatenate(runs[m]) for m in ("uncontrolled", "interpolate"))
    # near the critical load the bowed beam bends (0.16 mm x F / (Fcr - F): 0.75 mm at 2650 N); while
    # the controller runs it stays within 0.1 mm (README: at four times the paper's load rate, 200 N/s)
    # (after the ramp's end the stacks ramp to bias and the beam bends: not under control)
    high = lambda rows: rows[rows[:, 1] > 2650.0]        # noqa: E731
    assert high(uncontrolled)[:, 2].max() > 0.5e-3, high(uncontrolled)[:, 2].max()
    running = high(controlled)[high(controlled)[:, 3] == State.RUNNING]
    assert len(running) and running[:, 2].max() < 0.1e-3, running[:, 2].max()
