"""The service's control socket: operator commands to a running ``beamctl run`` over a local
UNIX stream socket, the client that sends them (``beamctl ctl``, the live page) and where the
socket is; the server is service/control_server.py (this module stays free of numpy, so that
``beamctl ctl`` answers at once).

Protocol: one request per connection, one JSON object on one line (UTF-8, newline-terminated,
at most 64 KiB)::

    {"command": "status" | "start" | "stop" | "rearm" | "gains", "table": "/abs/path.yaml"}

(``table`` with ``gains`` only, an absolute path), answered by one line::

    {"ok": true | false, "command": "...", "message": "...", "status": {...}}

``status`` holds the state, the fault and its reason, whether the stacks are at bias, the
load-cell reading in N, the cycles run, and the gain table's path and SHA-256. A command is
answered once the loop has decided it (within a few cycles); ``gains`` once the table has
also been read and checked, which takes seconds the first time (service/swaps.py
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
import socket
import stat
import time
from pathlib import Path

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


def _directory_can_be_made(directory: Path) -> None:
    """``directory`` is one this user can put a socket in, or make (nothing is made)."""
    d = directory
    while not d.exists() and d != d.parent:
        d = d.parent
    if not d.is_dir():
        raise ControlError(f"control socket directory {directory}: {d} is not a directory")
    if not os.access(d, os.W_OK | os.X_OK):
        raise ControlError(f"control socket directory {directory}: {d} is not writable by this user")


def socket_place(path: str | Path, make_directory: bool = True) -> bool:
    """What ``bind_socket`` checks before it binds: the path can hold a socket address, its
    directory is there (made with ``make_directory``; else only checked), nothing but a socket
    file is at the path and no service answers there. Returns whether a socket file left by a
    service that has ended is there (bind replaces it). ControlError otherwise."""
    p = check_socket_path(path)
    if make_directory:
        prepare_socket_directory(p.parent)
    else:
        _directory_can_be_made(p.parent)
    try:
        st = os.lstat(p)
    except FileNotFoundError:
        return False
    except OSError as exc:
        raise ControlError(f"control socket {p}: {exc.strerror or exc}") from None
    if not stat.S_ISSOCK(st.st_mode):
        raise ControlError(f"control socket {p}: the path exists and is not a socket")
    if _answers(p):
        raise ControlError(f"control socket {p}: another service is running there (stop it, or "
                           f"give this one its own --control-socket)")
    return True


def bind_socket(path: str | Path) -> socket.socket:
    """A listening socket at ``path``, its file 0660. A socket file left by a service that has
    ended is replaced; one a service answers at is refused, as is any other file."""
    p = check_socket_path(path)
    if socket_place(p):
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
