"""The service's control socket: operator commands to a running ``beamctl run`` over a local
UNIX stream socket, and the client that sends them (``beamctl ctl``, the live page).

Protocol: one request per connection, one JSON object on one line (UTF-8, newline-terminated,
at most 64 KiB)::

    {"command": "status" | "start" | "stop" | "rearm" | "gains", "table": "/abs/path.yaml"}

(``table`` with ``gains`` only, an absolute path), answered by one line::

    {"ok": true | false, "command": "...", "message": "...", "status": {...}}

``status`` holds the state, the fault and its reason, whether the stacks are at bias, the
load-cell reading in N, the cycles run, and the gain table's path and SHA-256. A command is
answered once the loop has decided it (within a few cycles); ``gains`` once the table has
also been read and checked, which takes seconds the first time (service/setup.py
``TableSwaps``): a client allows it two minutes. A request that cannot be read (not UTF-8,
not JSON, too long, an unknown command, nothing within the read time-out) is answered
``ok: false`` saying why, and the server goes on serving.

Who may command is whoever may connect: the socket file is made 0660, so the service's user and
its group. The server runs in two threads of its own and never changes the controller: a
command goes to the control loop (``OperatorCommand``, rt/loop.py), which carries it out or
refuses it between two cycles and records it in the telemetry; a gain table is read (in a
process of its own) and checked off the loop, and reaches the loop ready to swap in. A client
that stalls costs nothing but its read time-out.

Where the socket is (``default_socket_path``): ``$BEAMCTL_CONTROL_SOCKET``, else
``/run/beamctl/control.sock`` when ``/run/beamctl`` is there to be used (the lab's service: systemd
makes it), else ``$XDG_RUNTIME_DIR/beamctl/control.sock``, else ``/tmp/beamctl-<uid>/control.sock``
(a directory of the user's own, 0700). A client takes the first of these where a socket exists, so
that ``beamctl ctl status`` finds a service started with the defaults.
"""

from __future__ import annotations

import errno
import grp
import json
import os
import queue
import selectors
import socket
import stat
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from beamctl.rt.controller import PreparedTable
    from beamctl.rt.loop import ControlLoop

COMMANDS = ("status", "start", "stop", "rearm", "gains")
MAX_REQUEST_BYTES = 64 * 1024
SOCKET_ENV = "BEAMCTL_CONTROL_SOCKET"
RUN_DIR = Path("/run/beamctl")
SOCKET_NAME = "control.sock"
SOCKET_MODE = 0o660
# sun_path holds 108 bytes on Linux, the terminating NUL included
MAX_PATH_BYTES = 107


class ControlError(Exception):
    """The control socket could not be used (no service, permission, time-out, a bad path);
    the message is one line."""


# -- where the socket is --------------------------------------------------------------------------
def _directories() -> list[Path]:
    dirs = [RUN_DIR]
    runtime = os.environ.get("XDG_RUNTIME_DIR", "")
    if runtime:
        dirs.append(Path(runtime) / "beamctl")
    dirs.append(_private_directory())
    return dirs


def _private_directory() -> Path:
    return Path("/tmp") / f"beamctl-{os.getuid()}"


def _usable(directory: Path) -> bool:
    """This user may make a socket in ``directory`` (or make the directory)."""
    if directory.is_dir():
        return os.access(directory, os.W_OK | os.X_OK)
    parent = directory.parent
    return not directory.exists() and parent.is_dir() and os.access(parent, os.W_OK | os.X_OK)


def default_socket_path() -> Path:
    """``$BEAMCTL_CONTROL_SOCKET``; else the first of /run/beamctl, $XDG_RUNTIME_DIR/beamctl and
    /tmp/beamctl-<uid> holding a ``control.sock``; else the first this user may make it in."""
    env = os.environ.get(SOCKET_ENV, "")
    if env:
        return Path(env)
    dirs = _directories()
    for d in dirs:
        if (d / SOCKET_NAME).exists():
            return d / SOCKET_NAME
    for d in dirs:
        if _usable(d):
            return d / SOCKET_NAME
    return dirs[-1] / SOCKET_NAME


def check_socket_path(path: str | Path) -> Path:
    """``path`` as a Path, refused when a UNIX socket address cannot hold it."""
    p = Path(path)
    size = len(os.fsencode(str(p)))
    if not str(p):
        raise ControlError("the control socket's path is empty")
    if size > MAX_PATH_BYTES:
        raise ControlError(f"control socket {p}: the path is {size} bytes long, a UNIX socket's at most "
                           f"{MAX_PATH_BYTES}: choose a shorter one")
    return p


def _group_name(gid: int) -> str:
    try:
        return grp.getgrgid(gid).gr_name
    except KeyError:
        return str(gid)


# -- the client -------------------------------------------------------------------------------------
def request(path: str | Path, payload: dict, timeout_s: float = 10.0) -> dict:
    """Send ``payload`` to the service at ``path`` and return its reply (a dict with ``ok``,
    ``command``, ``message``, ``status``). ControlError when there is no service, the socket may
    not be used, or no reply comes within ``timeout_s``."""
    p = check_socket_path(path)
    data = (json.dumps(payload) + "\n").encode()
    if len(data) > MAX_REQUEST_BYTES + 1:
        raise ControlError(f"the request is {len(data)} bytes long, at most {MAX_REQUEST_BYTES}")
    deadline = time.monotonic() + timeout_s
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        try:
            s.settimeout(timeout_s)
            s.connect(str(p))
            s.sendall(data)
            reply = _read_line(s, deadline)
        except (FileNotFoundError, NotADirectoryError):
            raise ControlError(f"no service at {p} (no socket there: is `beamctl run` running, with this "
                               f"control socket?)") from None
        except ConnectionRefusedError:
            raise ControlError(f"no service at {p} (the socket is left from a service that has "
                               f"ended)") from None
        except PermissionError:
            raise ControlError(f"permission denied for {p}: commanding the service takes membership "
                               f"of the socket's group ({_socket_group(p)})") from None
        except TimeoutError:
            raise ControlError(f"time-out: the service at {p} did not answer within "
                               f"{timeout_s:g} s") from None
        except OSError as exc:
            raise ControlError(f"control socket {p}: {exc.strerror or exc}") from None
    try:
        answer = json.loads(reply)
    except ValueError:
        answer = None
    if not isinstance(answer, dict) or not isinstance(answer.get("ok"), bool):
        raise ControlError(f"the service at {p} answered something other than a beamctl reply: "
                           f"{reply[:80]!r}")
    return answer


def _socket_group(p: Path) -> str:
    try:
        return _group_name(p.stat().st_gid)
    except OSError:
        return "unknown: the path cannot be read"


def _read_line(s: socket.socket, deadline: float) -> bytes:
    """Bytes up to the first newline (or the end of the stream)."""
    buf = bytearray()
    while b"\n" not in buf:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise TimeoutError
        s.settimeout(remaining)
        chunk = s.recv(65536)
        if not chunk:
            break
        buf += chunk
    return bytes(buf.split(b"\n", 1)[0])


# -- the server -------------------------------------------------------------------------------------
def prepare_socket_directory(directory: Path) -> None:
    """Make the socket's directory if missing (0700 for the private one in /tmp, 0755 else: the
    socket file's own mode decides who may command). The private directory must be the user's
    own and writable by nobody else."""
    private = directory == _private_directory()
    if not directory.exists():
        try:
            directory.mkdir(parents=True, mode=0o700 if private else 0o755)
            os.chmod(directory, 0o700 if private else 0o755)   # whatever the umask
        except OSError as exc:
            raise ControlError(f"control socket directory {directory}: {exc.strerror or exc}") from None
    if private:
        st = os.lstat(directory)
        if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o022:
            raise ControlError(f"control socket directory {directory} is not a directory of this user's "
                               f"writable by nobody else: remove it, or give --control-socket")


def _answers(path: Path) -> bool:
    """A service listens at ``path`` (False for a socket file left by a dead one)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(2.0)
        try:
            s.connect(str(path))
        except (ConnectionRefusedError, FileNotFoundError):
            return False
        except PermissionError:
            raise ControlError(f"control socket {path} belongs to another user's service "
                               f"(permission denied)") from None
        except OSError as exc:
            if exc.errno in (errno.ECONNREFUSED, errno.ENOENT):
                return False
            raise ControlError(f"control socket {path}: {exc.strerror or exc}") from None
    return True


def bind_socket(path: str | Path) -> socket.socket:
    """A listening socket at ``path``, its file 0660. A socket file left by a service that has
    ended is replaced; one a service answers at is refused, as is any other file."""
    p = check_socket_path(path)
    prepare_socket_directory(p.parent)
    try:
        st = os.lstat(p)
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise ControlError(f"control socket {p}: {exc.strerror or exc}") from None
    if st is not None:
        if not stat.S_ISSOCK(st.st_mode):
            raise ControlError(f"control socket {p}: the path exists and is not a socket")
        if _answers(p):
            raise ControlError(f"control socket {p}: another service is running there (stop it, or "
                               f"give this one its own --control-socket)")
        p.unlink(missing_ok=True)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.bind(str(p))
        os.chmod(p, SOCKET_MODE)         # before listen: nobody connects meanwhile
        sock.listen(16)
    except OSError as exc:
        sock.close()
        raise ControlError(f"control socket {p}: {exc.strerror or exc}") from None
    return sock


class _Client:
    """A connection being read: what it sent so far and by when its request must be complete."""

    __slots__ = ("conn", "buffer", "deadline")

    def __init__(self, conn: socket.socket, deadline: float) -> None:
        self.conn = conn
        self.buffer = bytearray()
        self.deadline = deadline


class ControlServer:
    """The control socket of a running control loop. ``ControlServer(path)`` binds (refusals
    come before the service starts); ``serve(loop, ...)`` answers requests; ``close()`` stops
    answering and removes the socket file.

    One thread reads every connection without blocking (a selector: a client that stalls costs
    nothing but its deadline) and answers status and unreadable requests itself; a second
    thread takes the commands one at a time: it loads a gain table, posts the command to the
    loop and waits for the outcome. ``prepare_table(path)`` loads and checks a gain table for
    the running service and returns it prepared for the controller (service/setup.py
    ``table_for_swap``), raising ValueError (a ConfigError) with why it was refused; ``log``
    takes one line per command and its outcome, and per refused request.
    """

    def __init__(self, path: str | Path, *, read_timeout_s: float = 5.0, command_timeout_s: float = 5.0,
                 max_clients: int = 32, max_queued_commands: int = 4) -> None:
        self.path = check_socket_path(path)
        self.read_timeout_s = read_timeout_s
        self.command_timeout_s = command_timeout_s
        self.max_clients = max_clients
        self._socket = bind_socket(self.path)
        st = os.stat(self.path)
        self._identity = (st.st_dev, st.st_ino)
        self.group = _group_name(st.st_gid)
        self._commands: queue.Queue = queue.Queue(max_queued_commands)
        self._closing = threading.Event()
        self._threads: list[threading.Thread] = []
        self._loop: ControlLoop | None = None
        self._prepare_table: Callable[[str], PreparedTable] | None = None
        self._log: Callable[[str], None] = lambda line: None
        self.table = ""
        self.table_sha256 = ""

    def serve(self, loop: ControlLoop, *, table: str, table_sha256: str,
              prepare_table: Callable[[str], PreparedTable], log: Callable[[str], None]) -> ControlServer:
        """Answer requests for ``loop`` (whose gain table is ``table``) from now on."""
        self._loop = loop
        self.table, self.table_sha256 = table, table_sha256
        self._prepare_table = prepare_table
        self._log = log
        self._threads = [threading.Thread(target=self._read_requests, name="control-socket", daemon=True),
                         threading.Thread(target=self._carry_out_commands, name="control-commands",
                                          daemon=True)]
        for thread in self._threads:
            thread.start()
        return self

    def close(self) -> None:
        """Stop answering (a command under way is answered first) and remove the socket file if
        it is still this server's. Once is enough; again does nothing."""
        if self._socket.fileno() < 0:
            return
        self._closing.set()
        for thread in self._threads:
            thread.join()
        self._socket.close()
        try:
            st = os.stat(self.path)
            if (st.st_dev, st.st_ino) == self._identity:
                self.path.unlink()
        except OSError:
            pass

    def __enter__(self) -> ControlServer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- connections --------------------------------------------------------------------------------
    def _read_requests(self) -> None:
        selector = selectors.DefaultSelector()
        self._socket.setblocking(False)
        selector.register(self._socket, selectors.EVENT_READ)
        clients: dict[socket.socket, _Client] = {}
        try:
            while not self._closing.is_set():
                now = time.monotonic()
                wait = min([0.5, *(c.deadline - now for c in clients.values())])
                for key, _ in selector.select(max(wait, 0.0)):
                    if key.fileobj is self._socket:
                        self._accept(selector, clients)
                    else:
                        self._read(selector, clients, clients[key.fileobj])
                now = time.monotonic()
                for client in [c for c in clients.values() if c.deadline <= now]:
                    self._finish(selector, clients, client,
                                 self._logged_refusal("", f"no complete request (one JSON line) within "
                                                          f"{self.read_timeout_s:g} s"))
        finally:
            for client in list(clients.values()):
                self._finish(selector, clients, client, self._refusal("", "the service is ending"))
            selector.close()

    def _accept(self, selector: selectors.BaseSelector, clients: dict) -> None:
        try:
            conn, _ = self._socket.accept()
        except OSError:
            return
        if len(clients) >= self.max_clients:
            self._send(conn, self._refusal("", f"the service is reading {len(clients)} other requests: "
                                               f"try again"))
            conn.close()
            return
        conn.setblocking(False)
        clients[conn] = _Client(conn, time.monotonic() + self.read_timeout_s)
        selector.register(conn, selectors.EVENT_READ)

    def _read(self, selector: selectors.BaseSelector, clients: dict, client: _Client) -> None:
        try:
            chunk = client.conn.recv(65536)
        except BlockingIOError:
            return
        except OSError:
            chunk = b""
            client.buffer.clear()
        buf = client.buffer
        buf += chunk
        end = buf.find(b"\n")
        if end > MAX_REQUEST_BYTES or (end < 0 and len(buf) > MAX_REQUEST_BYTES):
            self._finish(selector, clients, client,
                         self._logged_refusal("", f"the request is longer than {MAX_REQUEST_BYTES} bytes"))
        elif end >= 0 or not chunk:     # a line, or the end of the client's stream
            if end < 0 and not buf:
                self._finish(selector, clients, client, self._logged_refusal("", "an empty request"))
                return
            line = bytes(buf[:end] if end >= 0 else buf)
            selector.unregister(client.conn)
            del clients[client.conn]
            reply, command = self.answer(line)
            if command is None:
                self._send(client.conn, reply)
                client.conn.close()
                return
            try:
                self._commands.put_nowait((client.conn, *command))
            except queue.Full:
                self._send(client.conn, self._logged_refusal(command[0], "too many commands waiting: "
                                                                         "try again"))
                client.conn.close()

    def _finish(self, selector: selectors.BaseSelector, clients: dict, client: _Client, reply: dict) -> None:
        selector.unregister(client.conn)
        del clients[client.conn]
        self._send(client.conn, reply)
        client.conn.close()

    def _send(self, conn: socket.socket, reply: dict) -> None:
        try:
            conn.settimeout(1.0)        # a reply of a few hundred bytes: the socket's buffer takes it
            conn.sendall((json.dumps(reply) + "\n").encode())
        except OSError:
            pass                        # the client went away: nothing to tell it

    def _carry_out_commands(self) -> None:
        while True:
            try:
                conn, name, table = self._commands.get(timeout=0.2)
            except queue.Empty:
                if self._closing.is_set():
                    return
                continue
            try:
                reply = self._command(name, table)
            except Exception as exc:    # a bug must not end the serving: say so, keep serving
                reply = self._logged_refusal(name, f"internal error: {type(exc).__name__}: {exc}")
            self._send(conn, reply)
            conn.close()

    # -- requests -----------------------------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        """The loop's status with the gain table in use."""
        return {**self._loop.status(), "table": self.table, "table_sha256": self.table_sha256}

    def _refusal(self, command: str, message: str) -> dict:
        return {"ok": False, "command": command, "message": message,
                "status": self.status() if self._loop is not None else {}}

    def _logged_refusal(self, command: str, message: str) -> dict:
        self._log(f"control socket: refused a request: {message}")
        return self._refusal(command, message)

    def answer(self, raw: bytes) -> tuple[dict | None, tuple[str, str] | None]:
        """(the reply, None) to a status or an unreadable request line; (None, (command, table))
        for a command to carry out."""
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            return self._logged_refusal("", f"the request is not UTF-8 text (byte {exc.start})"), None
        try:
            req = json.loads(text)
        except ValueError as exc:
            return self._logged_refusal("", f"the request is not JSON ({exc})"), None
        if not isinstance(req, dict):
            return self._logged_refusal("", f"the request is JSON but not an object: {text[:60]!r}"), None
        command = req.get("command")
        name = command if isinstance(command, str) else ""
        if command not in COMMANDS:
            return self._logged_refusal(name, f"unknown command {command!r}: expected one of "
                                              f"{', '.join(COMMANDS)}"), None
        allowed = {"command", "table"} if command == "gains" else {"command"}
        extra = sorted(set(req) - allowed)
        if extra:
            return self._logged_refusal(name, f"unexpected key {extra[0]!r} with {command} (the keys are "
                                              f"{', '.join(sorted(allowed))})"), None
        if command == "status":
            return {"ok": True, "command": "status", "message": "", "status": self.status()}, None
        table = req.get("table")
        if command == "gains":
            if not isinstance(table, str) or not table:
                return self._logged_refusal(name, 'gains needs "table": the path of a gain table file'), None
            if not os.path.isabs(table):
                return self._logged_refusal(name, f"table {table!r}: expected an absolute path (a relative "
                                                  f"one would be taken from the service's directory)"), None
        return None, (command, table or "")

    def _command(self, name: str, table: str) -> dict:
        """Post the command to the loop, wait for its outcome, log it, and reply."""
        from beamctl.rt.loop import OperatorCommand

        what = f"gains {table}" if name == "gains" else name
        prepared, sha256, refusal = None, "", ""
        if name == "gains":
            # running or ramping: refused without reading the table (the loop decides again)
            refusal = self._loop.refusal("gains")
            if not refusal:
                try:
                    prepared = self._prepare_table(table)
                    sha256 = prepared.table.sha256
                except (ValueError, OSError) as exc:
                    refusal = f"the table is refused as at start: {exc}"
        command = OperatorCommand(name, prepared, refusal)
        self._loop.post(command)
        if not command.wait(self.command_timeout_s) and command.cancel():
            message = (f"time-out: the control loop did not take the command within "
                       f"{self.command_timeout_s:g} s (withdrawn)")
            self._log(f"operator {what}: {message}")
            return self._refusal(name, message)
        command.wait(self.command_timeout_s)    # taken: decided within the cycle
        if command.outcome == "carried out":
            message = f"carried out ({command.transition})"
            if name == "gains":
                self.table, self.table_sha256 = table, sha256
                message += f"; table sha256 {sha256}"
        else:
            message = f"refused: {command.refusal}"
        self._log(f"operator {what}: {message}")
        return {"ok": command.outcome == "carried out", "command": name, "message": message,
                "status": self.status()}
