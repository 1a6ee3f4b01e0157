"""``beamctl monitor``: the live view of a running service, served on 127.0.0.1.

A ``Monitor`` binds the UNIX datagram socket the service's ``--live`` sends to (rt/live.py),
keeps the newest ``window_s`` seconds of the current run in a ``LiveStore``, and serves, with
the standard library's threaded HTTP server:

- ``GET /`` the page (service/monitor_page.html: one self-contained file, its own drawing on
  canvas, nothing fetched from elsewhere: the lab PC may be offline);
- ``GET /events`` the rows as server-sent events (JSON, columns of numbers): all of the window
  first, then what is new, at least once a second (a heartbeat with the data's age);
- ``POST /command`` an operator command (``{"command": "start"|"stop"|"rearm"|"status"|"gains",
  "table": PATH}``), forwarded to the service's control socket (service/control.py) and answered
  with the service's reply.

Every request must name the monitor's token, a random string made at each start and printed in
the page's URL (``?token=``, or the ``X-Beamctl-Token`` header), and carry a ``Host`` of this
server (and an ``Origin``, if any, of this server): another web page in the operator's browser
can send a request to 127.0.0.1 but cannot know the token, and a host name that resolves to
127.0.0.1 (DNS rebinding) is refused by the ``Host`` check.

A page that stalls holds its own handler thread only, until its socket's time-out; the service
never waits for the monitor (rt/live.py), so nothing here can hold up the control loop.
"""

from __future__ import annotations

import collections
import hmac
import http.server
import json
import math
import os
import secrets
import socket
import stat
import threading
import time
import urllib.parse
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from beamctl.rt.live import LiveError, check_socket_path, decode
from beamctl.service import control
from beamctl.service.control import COMMANDS, SOCKET_MODE
from beamctl.service.live import default_live_path

MAX_BODY_BYTES = 4096
# the columns the page draws or shows (a run without one of them sends the others)
PAGE_COLUMNS = ("time_s", "sequence", "state", "fault", "flags", "load_N", "load_filtered_N",
                "q_1y", "q_1z", "q_2y", "q_2z",
                *(f"voltage_{s}_V" for s in ("a1", "a2", "a3", "b1", "b2", "b3")),
                "scale_A", "scale_B", "step_us", "input_period_us", "answer_age_us", "late_answers",
                "operator_command", "deflection_m", "deflection_y_m", "deflection_z_m")
MAX_WINDOW_ROWS = 20_000        # the store's bound whatever the rate


class CommandError(ValueError):
    """An operator command the page sent that cannot be forwarded (a bad body)."""


@dataclass
class Snapshot:
    """What a page has not seen yet: the rows after ``count`` of run ``generation`` (all of the
    run's window when the page saw another run: ``reset``)."""

    generation: int
    count: int
    reset: bool
    run: dict | None
    status: dict
    rows: np.ndarray | None
    age_s: float | None
    window_s: float


class LiveStore:
    """The newest ``window_s`` seconds (of the run's own time) of the current run's rows. A
    datagram of another run (another ``run_id``) starts afresh. Thread-safe; readers wait for
    new rows with ``wait_since``."""

    def __init__(self, window_s: float = 20.0) -> None:
        self.window_s = float(window_s)
        self._cond = threading.Condition()
        self._blocks: collections.deque[tuple[int, np.ndarray]] = collections.deque()
        self._rows_held = 0
        self.run: dict | None = None
        self.status: dict = {}
        self.generation = 0
        self.count = 0              # rows of the current run received
        self.datagrams = 0
        self.missed = 0             # datagrams of the run that never arrived (sequence gaps)
        self.invalid = 0            # datagrams that could not be read
        self._sequence: int | None = None
        self._received_at: float | None = None
        self._i_time: int | None = None

    def add(self, header: dict, rows: np.ndarray) -> None:
        with self._cond:
            run = header["run"]
            if self.run is None or run.get("run_id") != self.run.get("run_id"):
                self.run = run
                self.generation += 1
                self._blocks.clear()
                self._rows_held = self.count = 0
                self._sequence = None
                columns = run["columns"]
                self._i_time = columns.index("time_s") if "time_s" in columns else None
            sequence = int(header["sequence"])
            if self._sequence is not None and sequence > self._sequence + 1:
                self.missed += sequence - self._sequence - 1
            self._sequence = sequence
            self.datagrams += 1
            self._blocks.append((self.count, rows))
            self.count += len(rows)
            self._rows_held += len(rows)
            self._trim()
            self.status = header.get("status", {})
            self._received_at = time.monotonic()
            self._cond.notify_all()

    def refuse(self) -> None:
        """Count a datagram that could not be read."""
        with self._cond:
            self.invalid += 1

    def _trim(self) -> None:
        newest = self._blocks[-1][1]
        latest = newest[-1, self._i_time] if self._i_time is not None and len(newest) else math.nan
        while len(self._blocks) > 1:
            first = self._blocks[0][1]
            too_old = self._i_time is not None and first[-1, self._i_time] < latest - self.window_s
            if not (too_old or self._rows_held - len(first) >= MAX_WINDOW_ROWS):
                break
            self._blocks.popleft()
            self._rows_held -= len(first)

    def wait_since(self, generation: int, count: int, timeout_s: float) -> Snapshot:
        """The rows after ``count`` of ``generation`` once there are any, or after ``timeout_s``
        whatever there is."""
        with self._cond:
            self._cond.wait_for(lambda: self.generation != generation or self.count > count, timeout_s)
            reset = self.generation != generation
            start = 0 if reset else count
            parts = [rows[max(0, start - first):] for first, rows in self._blocks
                     if first + len(rows) > start]
            rows = np.concatenate(parts) if parts else None
            age = None if self._received_at is None else time.monotonic() - self._received_at
            status = {**self.status, "datagrams": self.datagrams, "datagrams_missed": self.missed,
                      "datagrams_invalid": self.invalid}
            return Snapshot(self.generation, self.count, reset, self.run, status, rows, age, self.window_s)


def _numbers(values: np.ndarray) -> str:
    return "[" + ",".join(f"{v:.7g}" if math.isfinite(v) else "null" for v in values.tolist()) + "]"


def event_json(snapshot: Snapshot) -> str:
    """One server-sent event's data: the new rows of the page's columns, column by column."""
    parts = [f'"reset":{json.dumps(snapshot.reset)}', f'"window_s":{snapshot.window_s:g}',
             f'"age_s":{"null" if snapshot.age_s is None else f"{snapshot.age_s:.3f}"}',
             f'"status":{json.dumps(snapshot.status, allow_nan=False, default=str)}']
    if snapshot.reset and snapshot.run is not None:
        parts.append(f'"run":{json.dumps({k: v for k, v in snapshot.run.items() if k != "columns"})}')
    if snapshot.rows is not None and snapshot.run is not None:
        columns = snapshot.run["columns"]
        data = ",".join(f'"{name}":{_numbers(snapshot.rows[:, columns.index(name)])}'
                        for name in PAGE_COLUMNS if name in columns)
        parts.append(f'"data":{{{data}}}')
    return "{" + ",".join(parts) + "}"


def parse_command(body: bytes) -> dict:
    """The payload of ``POST /command``, checked: ``CommandError`` says in one line what is wrong."""
    try:
        payload = json.loads(body)
    except (ValueError, UnicodeDecodeError):
        raise CommandError("the body is not JSON: expected {\"command\": ...}") from None
    if not isinstance(payload, dict):
        raise CommandError("the body is not a JSON object: expected {\"command\": ...}")
    extra = sorted(set(payload) - {"command", "table"})
    if extra:
        raise CommandError(f"unknown key {extra[0]!r}: expected 'command' and, for gains, 'table'")
    command = payload.get("command")
    if command not in COMMANDS:
        raise CommandError(f"command {command!r}: expected one of {', '.join(COMMANDS)}")
    table = payload.get("table")
    if command == "gains":
        if not isinstance(table, str) or not table.strip():
            raise CommandError("gains needs 'table': the path of a gain table file")
        return {"command": command, "table": table.strip()}
    if table is not None:
        raise CommandError(f"{command} takes no 'table'")
    return {"command": command}


def forward_command(control_path: str, payload: dict) -> tuple[int, dict]:
    """(HTTP status, reply) of a checked command sent to the service's control socket: the
    service's reply (which may refuse it, saying why), or 503 when no service answers."""
    try:
        return 200, control.request(control_path, payload, timeout_s=10.0)
    except control.ControlError as exc:
        return 503, {"ok": False, "command": payload["command"], "message": str(exc)}


def bind_live_socket(path: str) -> socket.socket:
    """The monitor's end of the live view, bound at ``path``. Its directory and its file's mode
    are the control socket's (service/control.py: the private directory in /tmp made 0700, the
    file 0660): who may command the service may feed the page. A socket file left by a monitor
    that was killed is replaced; one that a running monitor holds is refused."""
    path = check_socket_path(path, "--live")
    try:
        control.prepare_socket_directory(Path(path).parent)      # the same rules as the control socket's
    except control.ControlError as exc:
        raise LiveError(f"--live {path}: {exc}") from None
    if os.path.lexists(path):
        if not stat.S_ISSOCK(os.lstat(path).st_mode):
            raise LiveError(f"--live {path}: the path exists and is not a socket")
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as probe:
            try:
                probe.connect(path)
            except ConnectionRefusedError:      # left behind by a monitor that was killed
                os.unlink(path)
            except OSError as exc:
                raise LiveError(f"--live {path}: {exc.strerror}") from None
            else:
                raise LiveError(f"--live {path}: another monitor listens there")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        sock.bind(path)
        os.chmod(path, SOCKET_MODE)
    except OSError as exc:
        sock.close()
        raise LiveError(f"--live {path}: cannot listen there ({exc.strerror})") from None
    sock.settimeout(0.25)
    return sock


class _Handler(http.server.BaseHTTPRequestHandler):
    server: _Server
    timeout = 30.0              # a page that stops reading is dropped after this long
    server_version = "beamctl-monitor"
    sys_version = ""

    def log_message(self, format, *args) -> None:     # noqa: A002 (the base class's name)
        pass

    def _reply(self, status: int, body: bytes, content_type: str) -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()
        self.wfile.write(body)

    def _json(self, status: int, reply: dict) -> None:
        self._reply(status, (json.dumps(reply) + "\n").encode(), "application/json")

    def _refuse(self, status: int, message: str) -> None:
        if self.path.startswith("/command"):
            self._json(status, {"ok": False, "message": message})
        else:
            self._reply(status, (message + "\n").encode(), "text/plain; charset=utf-8")

    def _admitted(self) -> str | None:
        """The request's path once its Host, Origin and token are this monitor's, else None
        (refused)."""
        server = self.server
        if self.headers.get("Host", "") not in server.hosts:
            self._refuse(403, f"refused: Host {self.headers.get('Host', '')!r} is not this monitor "
                              f"(open http://127.0.0.1:{server.port}/)")
            return None
        origin = self.headers.get("Origin")
        if origin is not None and origin not in server.origins:
            self._refuse(403, f"refused: a request from another site ({origin})")
            return None
        url = urllib.parse.urlsplit(self.path)
        token = self.headers.get("X-Beamctl-Token") or urllib.parse.parse_qs(url.query).get("token", [""])[0]
        if not hmac.compare_digest(token.encode(), server.token.encode()):
            self._refuse(403, "refused: no token or a wrong one (open the URL that beamctl monitor printed)")
            return None
        return url.path

    def do_GET(self) -> None:
        path = self._admitted()
        if path is None:
            return
        if path == "/":
            self._reply(200, self.server.page, "text/html; charset=utf-8")
        elif path == "/events":
            self._events()
        else:
            self._refuse(404, f"no {path} here")

    def do_POST(self) -> None:
        path = self._admitted()
        if path is None:
            return
        if path != "/command":
            self._refuse(404, f"no {path} here")
            return
        try:
            length = int(self.headers.get("Content-Length", ""))
        except ValueError:
            self._refuse(400, "bad request: a JSON body with its Content-Length expected")
            return
        if not 0 <= length <= MAX_BODY_BYTES:
            self._refuse(400, f"bad request: a body of at most {MAX_BODY_BYTES} bytes expected")
            return
        try:
            payload = parse_command(self.rfile.read(length))
        except CommandError as exc:
            self._refuse(400, f"bad request: {exc}")
            return
        status, reply = forward_command(self.server.control_path, payload)
        self._json(status, reply)

    def _events(self) -> None:
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.send_header("Cache-Control", "no-store")
        self.end_headers()
        store, generation, count = self.server.store, -1, 0
        try:
            while not self.server.closing.is_set():
                snapshot = store.wait_since(generation, count, timeout_s=1.0)
                generation, count = snapshot.generation, snapshot.count
                self.wfile.write(f"data: {event_json(snapshot)}\n\n".encode())
                self.wfile.flush()
                self.server.closing.wait(0.05)      # at most 20 events a second, however datagrams come
        except OSError:             # the page went away, or stopped reading for `timeout`
            pass


class _Server(http.server.ThreadingHTTPServer):
    daemon_threads = True
    store: LiveStore
    token: str
    port: int
    hosts: frozenset[str]
    origins: frozenset[str]
    page: bytes
    control_path: str
    closing: threading.Event


class Monitor:
    """The receiver and the web server; ``start()``, then ``url``; ``close()``."""

    def __init__(self, live_path: str | None = None, port: int = 8750, control_path: str | None = None,
                 window_s: float = 20.0) -> None:
        self.live_path = live_path or default_live_path()
        self.store = LiveStore(window_s)
        self.token = secrets.token_urlsafe(24)
        self._socket = bind_live_socket(self.live_path)
        self._inode = os.stat(self.live_path).st_ino
        try:
            server = _Server(("127.0.0.1", port), _Handler, bind_and_activate=False)
            server.allow_reuse_address = True
            server.server_bind()
            server.server_activate()
        except OSError as exc:
            self._close_socket()
            raise LiveError(f"--port {port}: cannot serve on 127.0.0.1:{port} ({exc.strerror}); "
                            f"--port 0 takes a free one") from None
        self.port = server.server_address[1]
        server.store, server.token, server.port = self.store, self.token, self.port
        server.hosts = frozenset({f"127.0.0.1:{self.port}", f"localhost:{self.port}"})
        server.origins = frozenset(f"http://{h}" for h in server.hosts)
        server.page = resources.files("beamctl.service").joinpath("monitor_page.html").read_bytes()
        server.control_path = str(control_path or control.default_socket_path())
        server.closing = threading.Event()
        self.control_path = server.control_path
        self._server = server
        self._threads: list[threading.Thread] = []

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/?token={self.token}"

    def start(self) -> Monitor:
        self._threads = [threading.Thread(target=self._receive, name="monitor-receiver", daemon=True),
                         threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.25},
                                          name="monitor-http", daemon=True)]
        for thread in self._threads:
            thread.start()
        return self

    def _receive(self) -> None:
        while not self._server.closing.is_set():
            try:
                datagram = self._socket.recv(1 << 17)
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                header, rows = decode(datagram)
                self.store.add(header, rows)
            except (LiveError, KeyError, TypeError, ValueError):
                self.store.refuse()

    def _close_socket(self) -> None:
        self._socket.close()
        try:
            if os.stat(self.live_path).st_ino == self._inode:   # still ours, not a newer monitor's
                os.unlink(self.live_path)
        except OSError:
            pass

    def close(self) -> None:
        self._server.closing.set()
        if self._threads:
            self._server.shutdown()
        self._server.server_close()
        for thread in self._threads:
            thread.join(timeout=2.0)
        self._close_socket()

    def __enter__(self) -> Monitor:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()
