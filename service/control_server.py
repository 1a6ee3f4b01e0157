"""The server side of the control socket (the protocol and the client: service/control.py): a
running control loop's socket, answering operator commands in two threads of its own and
handing each command to the loop (``OperatorCommand``, rt/loop.py)."""

from __future__ import annotations

import json
import os
import queue
import selectors
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from beamctl.rt.controller import PreparedTable
from beamctl.rt.loop import ControlLoop, OperatorCommand
from beamctl.service.control import (
    COMMANDS,
    MAX_REQUEST_BYTES,
    _group_name,
    bind_socket,
    check_socket_path,
)


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
    the running service and returns it prepared for the controller (service/swaps.py
    ``TableSwaps.prepare``), raising ValueError (a ConfigError) with why it was refused; ``log``
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
        self._later: queue.SimpleQueue[str] = queue.SimpleQueue()    # lines for log_later
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

    def log_later(self, line: str) -> None:
        """Log ``line`` from the server's own thread, soon: for the control loop's thread, which
        must not wait for the log's output (journald can block a write) nor fail with it."""
        self._later.put(line)

    def _log_pending(self) -> None:
        while True:
            try:
                line = self._later.get_nowait()
            except queue.Empty:
                return
            try:
                self._log(line)
            except Exception:           # the log is gone: the service carries on without it
                pass

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
            self._log_pending()
            try:
                conn, name, table = self._commands.get(timeout=0.2)
            except queue.Empty:
                if self._closing.is_set():
                    self._log_pending()
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
