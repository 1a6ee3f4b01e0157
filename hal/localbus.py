"""A python-can bus between processes of one user on one machine: ``beamctl_local``.

For tests and benchmarks that run the DAQ emulator (``beamctl plant``) and the controller
(``beamctl run``) as separate processes on a machine without SocketCAN (no ``vcan``), where
python-can's ``virtual`` interface only connects buses inside one process. The lab PC talks
to the DAQ over ``socketcan``; nothing here is on that path.

It is not a CAN bus: there is no arbitration, no bit timing and no bus load, and a frame
takes as long as a datagram between two processes, not its time on the wire. Frames of one
sender arrive in the order it sent them; frames of different senders interleave as the
kernel delivers them. Every frame a bus sends goes to every other bus on its channel (to
itself too with ``receive_own_messages``), time-stamped with the sender's ``time.time()``
when it was sent (as the ``virtual`` interface does), flagged ``is_rx`` unless it is the
bus's own frame.

A channel is a directory under a per-user base directory: ``$BEAMCTL_LOCALBUS_DIR``, else
``$XDG_RUNTIME_DIR/beamctl-localbus``, else ``/tmp/beamctl-localbus-<uid>``, created with
mode 0700 and refused when another user owns it or others may write to it. Each bus binds a
UNIX datagram socket (``AF_UNIX``, never a network socket) in the channel directory and
removes it on ``shutdown()``. A bus that joins rewrites the channel's ``generation`` file
(8 bytes, mapped into every member), so the others re-read the member list before their
next send: a bus receives every frame sent after its constructor returned. Members that
went away (shut down, or killed and left a socket file behind) are dropped, and their stale
files removed, when a send to them, or connecting to them, fails.

A receiver's queue is short: Linux holds ``net.unix.max_dgram_qlen`` datagrams (10 by
default) per receiving socket. Sends never wait: a frame for a full queue is dropped and
counted in the sender's ``dropped``, as a CAN bus loses frames to a node that does not
read. A receiver that must not lose frames reads at least as fast as frames arrive (the
emulator's ``lockstep`` pace keeps one sample in flight).

A bus sends through one datagram socket per member, connected to that member's socket (a
connected socket's send skips the path lookup of ``sendto``, about half its cost).

Besides python-can's ``send``/``recv``, a fast path moves the datagrams themselves, without a
``can.Message`` per frame (the CAN backend uses it, hal/can_backend.py): ``recv_raw_into``
receives the next frame's datagram into a buffer of the caller's, ``raw_frame`` makes a datagram
of this bus for a frame that the caller fills in, and ``send_raw`` stamps and sends it. The
layout of a datagram: ``HEADER`` (version, flags, DLC, data length, arbitration identifier,
sender, send time), the ``RAW_*`` offsets of its fields, then the data (``RAW_DATA``; padded to
``MAX_DATA_BYTES``). The fast path bypasses python-can's software filters (``set_filters``).

Usage, in any process once beamctl is installed (python-can finds the interface through the
``can.interface`` entry point)::

    bus = can.Bus(interface="beamctl_local", channel="bench")
"""

from __future__ import annotations

import errno
import mmap
import os
import select
import socket
import stat
import struct
import time
from contextlib import suppress
from typing import Any

import can

BASE_DIR_ENV = "BEAMCTL_LOCALBUS_DIR"   # the base directory, when set (tests point it at tmp_path)
VERSION = 1                             # first byte of every datagram: another version's frames are malformed
MAX_DATA_BYTES = 64                     # a CAN FD frame's payload
SOCKET_SUFFIX = b".sock"
GENERATION_FILE = "generation"
SUN_PATH_BYTES = 108                    # Linux's sockaddr_un.sun_path, the longest socket path

# version, flags, dlc, data length, arbitration id, sender id, send time (s, time.time());
# the payload follows, padded to MAX_DATA_BYTES: every datagram has the same size
HEADER = struct.Struct("<BBBBIId")
FRAME = struct.Struct(HEADER.format + f"{MAX_DATA_BYTES}s")

EXTENDED_ID, REMOTE_FRAME, ERROR_FRAME, FD_FRAME, BITRATE_SWITCH, ERROR_STATE_INDICATOR = 1, 2, 4, 8, 16, 32

# the byte offsets of HEADER's fields in a datagram, and of the data after it
RAW_VERSION, RAW_FLAGS, RAW_DLC, RAW_LENGTH, RAW_ID, RAW_SENDER, RAW_TIME = (
    struct.calcsize(HEADER.format[:i]) for i in range(1, len(HEADER.format)))
RAW_DATA = HEADER.size
RAW_SIZE = FRAME.size               # every datagram's size
RAW_BUFFER_SIZE = FRAME.size + 1    # a receive buffer: one byte more, so a longer datagram shows as too long
SEND_TIME = struct.Struct("<d")

QUEUE_FULL_ERRNOS = frozenset({errno.EAGAIN, errno.ENOBUFS})       # the receiver's queue is full
PEER_GONE_ERRNOS = frozenset({errno.ECONNREFUSED, errno.ENOENT})   # a stale socket file, a removed one


def base_directory() -> str:
    """The per-user directory that holds the channels (not checked or created here)."""
    configured = os.environ.get(BASE_DIR_ENV)
    if configured:
        return configured
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    if runtime:
        return os.path.join(runtime, "beamctl-localbus")
    return f"/tmp/beamctl-localbus-{os.geteuid()}"


def private_directory(path: str, what: str) -> None:
    """Create ``path`` with mode 0700 unless it exists, then refuse it unless it is a real
    directory of this user that nobody else may write to: whoever can create files in it can
    inject frames or take a channel's place."""
    try:
        os.mkdir(path, 0o700)
    except FileExistsError:
        pass
    except OSError as exc:
        raise can.CanInitializationError(f"local bus: cannot create the {what} {path}: {exc.strerror} "
                                         f"(${BASE_DIR_ENV} chooses the base directory)") from None
    info = os.lstat(path)
    if not stat.S_ISDIR(info.st_mode):
        kind = "a symbolic link" if stat.S_ISLNK(info.st_mode) else "not a directory"
        raise can.CanInitializationError(f"local bus: the {what} {path} is {kind}; expected a directory")
    if info.st_uid != os.geteuid():
        raise can.CanInitializationError(
            f"local bus: the {what} {path} belongs to uid {info.st_uid}, not to this user (uid "
            f"{os.geteuid()}); refused, another user could read or inject frames")
    if info.st_mode & 0o022:
        raise can.CanInitializationError(
            f"local bus: the {what} {path} is writable by group or others (mode "
            f"{stat.S_IMODE(info.st_mode):04o}); refused, another user could inject frames: "
            f"`chmod go-w` it or choose another base directory with ${BASE_DIR_ENV}")


def check_channel_name(channel: Any) -> str:
    """A channel is one directory name: no path, so it cannot leave the base directory. A name of
    digits alone arrives as an int (python-can casts channel strings that look like numbers)."""
    if isinstance(channel, int) and not isinstance(channel, bool) and channel >= 0:
        channel = str(channel)
    if (not isinstance(channel, str) or channel in ("", ".", "..") or "/" in channel
            or "\0" in channel):
        raise can.CanInitializationError(
            f"local bus channel {channel!r}: expected a simple name (a non-empty string without '/', "
            f"not '.' or '..')")
    return channel


def map_generation(path: str) -> mmap.mmap:
    """The channel's 8-byte generation file, created if missing, mapped shared."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
    try:
        if os.fstat(fd).st_size < 8:      # ftruncate to the same size keeps what another member wrote
            os.ftruncate(fd, 8)
        return mmap.mmap(fd, 8)
    finally:
        os.close(fd)


class LocalBus(can.BusABC):
    """A bus on ``channel`` (a simple name) of the local transport; see the module docstring.

    ``dropped`` counts frames not delivered because a receiver's queue was full (once per
    receiver), ``malformed`` the datagrams received that were not frames of this version.
    """

    def __init__(self, channel: str, receive_own_messages: bool = False, **kwargs: Any) -> None:
        self.channel = check_channel_name(channel)
        self.receive_own_messages = bool(receive_own_messages)
        self.dropped = 0
        self.malformed = 0
        self._sock: socket.socket | None = None
        self._links: dict[bytes, socket.socket] = {}     # member's socket path -> a socket connected to it
        self._peers: tuple[tuple[bytes, socket.socket], ...] = ()
        self._path: bytes | None = None
        self._generation: mmap.mmap | None = None
        try:
            base = base_directory()
            private_directory(base, "base directory")
            directory = os.path.join(base, self.channel)
            private_directory(directory, "channel directory")
            self._directory = os.fsencode(directory)
            self._sender_id = int.from_bytes(os.urandom(4), "little")   # tells own frames from others'
            self._own_name = f"{os.getpid()}-{self._sender_id:08x}".encode() + SOCKET_SUFFIX
            path = os.path.join(self._directory, self._own_name)
            if len(path) >= SUN_PATH_BYTES:
                raise can.CanInitializationError(
                    f"local bus: socket path {os.fsdecode(path)} is {len(path)} bytes, longer than a UNIX "
                    f"socket path may be ({SUN_PATH_BYTES - 1}); use a shorter channel name or a shorter "
                    f"base directory (${BASE_DIR_ENV})")
            self._generation = map_generation(os.path.join(directory, GENERATION_FILE))
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self._sock = sock
            sock.setblocking(False)
            try:
                sock.bind(path)
            except OSError as exc:
                raise can.CanInitializationError(
                    f"local bus: cannot bind {os.fsdecode(path)}: {exc.strerror or exc}") from None
            self._path, self._owner_pid = path, os.getpid()
            self._generation[:] = os.urandom(8)      # a new generation: the members re-read the list
            self._rescan()
            self._rx = bytearray(RAW_BUFFER_SIZE)
            self._poll = select.poll()
            self._poll.register(sock, select.POLLIN)
            self._readers = (sock,)
            self.channel_info = f"beamctl local bus {self.channel} ({os.fsdecode(path)})"
            self._can_protocol = can.CanProtocol.CAN_FD
            super().__init__(channel=self.channel, receive_own_messages=receive_own_messages, **kwargs)
        except BaseException:
            self._release()
            raise

    # -- members -------------------------------------------------------------------------------------
    def _rescan(self) -> None:
        """Read the member list: every socket in the channel directory but this bus's own (and
        its own too with ``receive_own_messages``), each with a socket connected to it. The
        generation is read first, so a member joining during the scan makes the next send scan
        again. A socket file nobody is bound to (its process was killed) is removed."""
        self._seen_generation = self._generation[:]
        own = None if self.receive_own_messages else self._own_name
        try:
            names = os.listdir(self._directory)
        except OSError as exc:
            raise can.CanOperationError(f"local bus: cannot list the channel directory "
                                        f"{os.fsdecode(self._directory)}: {exc.strerror}",
                                        exc.errno) from None
        old, links = self._links, {}
        for name in names:
            if not name.endswith(SOCKET_SUFFIX) or name == own:
                continue
            path = os.path.join(self._directory, name)
            link = old.pop(path, None) or self._connect(path)
            if link is not None:
                links[path] = link
        for link in old.values():
            link.close()
        self._links = links
        self._peers = tuple(links.items())

    def _connect(self, path: bytes) -> socket.socket | None:
        """A non-blocking datagram socket connected to the member at ``path``; None when nobody
        is bound there (a stale file, removed, or one removed meanwhile)."""
        link = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        link.setblocking(False)
        try:
            link.connect(path)
        except OSError as exc:
            link.close()
            if exc.errno == errno.ECONNREFUSED:      # nobody is bound to it: its process was killed
                with suppress(FileNotFoundError):
                    os.unlink(path)
            elif exc.errno != errno.ENOENT:
                raise can.CanOperationError(f"{self.channel_info}: cannot reach {os.fsdecode(path)}: "
                                            f"{exc.strerror or exc}", exc.errno) from None
            return None
        return link

    # -- send and receive ----------------------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send ``msg`` to every member of the channel. Never waits, whatever ``timeout``: a
        member whose queue is full misses the frame (counted in ``dropped``)."""
        if self._sock is None:
            raise can.CanOperationError(f"{self.channel_info}: send on a bus that is shut down")
        data = msg.data
        if len(data) > MAX_DATA_BYTES:
            raise ValueError(f"local bus: {len(data)} data bytes; a frame carries at most {MAX_DATA_BYTES}")
        flags = (msg.is_extended_id | msg.is_remote_frame << 1 | msg.is_error_frame << 2 | msg.is_fd << 3
                 | msg.bitrate_switch << 4 | msg.error_state_indicator << 5)
        try:
            frame = FRAME.pack(VERSION, flags, msg.dlc, len(data), msg.arbitration_id, self._sender_id,
                               time.time(), data)
        except struct.error as exc:
            raise ValueError(f"local bus: cannot encode arbitration id {msg.arbitration_id!r}, "
                             f"dlc {msg.dlc!r}: {exc}") from None
        self._deliver(frame)

    def raw_frame(self, arbitration_id: int, length: int, is_extended_id: bool = False,
                  is_fd: bool = False) -> bytearray:
        """A datagram of this bus for a data frame of ``length`` bytes on ``arbitration_id``, its
        data zero: write the data at ``RAW_DATA`` and send it with ``send_raw`` (as often as
        wanted; each send stamps its own time)."""
        if not 0 <= length <= MAX_DATA_BYTES:
            raise ValueError(f"local bus: {length} data bytes; a frame carries 0 to {MAX_DATA_BYTES}")
        flags = (EXTENDED_ID if is_extended_id else 0) | (FD_FRAME if is_fd else 0)
        try:
            return bytearray(FRAME.pack(VERSION, flags, length, length, arbitration_id, self._sender_id, 0.0,
                                        b""))
        except struct.error as exc:
            raise ValueError(f"local bus: cannot encode arbitration id {arbitration_id!r}: {exc}") from None

    def send_raw(self, frame: bytearray) -> None:
        """Send a datagram made by ``raw_frame`` (its data filled in), stamped with the time now;
        as ``send``, without a ``can.Message``."""
        if self._sock is None:
            raise can.CanOperationError(f"{self.channel_info}: send on a bus that is shut down")
        if len(frame) != RAW_SIZE:
            raise ValueError(f"local bus: a datagram of {len(frame)} bytes; raw_frame() makes {RAW_SIZE}")
        SEND_TIME.pack_into(frame, RAW_TIME, time.time())
        self._deliver(frame)

    def _deliver(self, frame) -> None:
        """Send one datagram to every member (see ``send``)."""
        if self._generation[:] != self._seen_generation:
            self._rescan()
        gone = False
        for peer, link in self._peers:
            try:
                link.send(frame)
            except OSError as exc:
                if exc.errno in QUEUE_FULL_ERRNOS:
                    self.dropped += 1
                elif exc.errno in PEER_GONE_ERRNOS:
                    if exc.errno == errno.ECONNREFUSED:   # nobody is bound to it: its process was killed
                        with suppress(FileNotFoundError):
                            os.unlink(peer)
                    gone = True
                else:
                    raise can.CanOperationError(f"{self.channel_info}: send to {os.fsdecode(peer)} failed: "
                                                f"{exc.strerror or exc}", exc.errno) from None
        if gone:
            self._rescan()     # the members that went away are no longer listed

    def recv_raw_into(self, frame: bytearray, timeout: float | None) -> bool:
        """Receive the next frame's datagram into ``frame`` (a buffer of at least
        ``RAW_BUFFER_SIZE`` bytes; layout in the module docstring), waiting up to ``timeout``
        seconds (None: forever, 0: only what is queued): False when none came. Malformed
        datagrams are counted and skipped."""
        sock = self._sock
        if sock is None:
            raise can.CanOperationError(f"{self.channel_info}: receive on a bus that is shut down")
        if len(frame) < RAW_BUFFER_SIZE:
            raise ValueError(f"local bus: a receive buffer of {len(frame)} bytes; expected {RAW_BUFFER_SIZE}")
        deadline = None
        while True:
            try:
                size = sock.recv_into(frame)
            except BlockingIOError:
                if timeout is None:
                    self._poll.poll()
                    continue
                now = time.monotonic()
                if deadline is None:
                    deadline = now + timeout
                remaining_s = deadline - now
                if remaining_s <= 0:
                    return False
                # select, not poll: poll waits whole milliseconds, and a time-out of a fraction of
                # a sample period must not become a millisecond
                select.select(self._readers, (), (), remaining_s)
                continue
            except OSError as exc:
                raise can.CanOperationError(f"{self.channel_info}: receive failed: {exc.strerror or exc}",
                                            exc.errno) from None
            if size == RAW_SIZE and frame[RAW_VERSION] == VERSION and frame[RAW_LENGTH] <= MAX_DATA_BYTES:
                return True
            self.malformed += 1

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        """One frame, waiting up to ``timeout`` seconds (None: forever, 0: only what is queued);
        malformed datagrams are counted and skipped."""
        if not self.recv_raw_into(self._rx, timeout):
            return None, False
        _, flags, dlc, length, arbitration_id, sender, timestamp = HEADER.unpack_from(self._rx)
        return can.Message(timestamp=timestamp, arbitration_id=arbitration_id,
                           is_extended_id=bool(flags & EXTENDED_ID),
                           is_remote_frame=bool(flags & REMOTE_FRAME),
                           is_error_frame=bool(flags & ERROR_FRAME), is_fd=bool(flags & FD_FRAME),
                           bitrate_switch=bool(flags & BITRATE_SWITCH),
                           error_state_indicator=bool(flags & ERROR_STATE_INDICATOR),
                           dlc=dlc, data=self._rx[RAW_DATA:RAW_DATA + length],
                           is_rx=sender != self._sender_id, channel=self.channel), False

    # -- lifecycle -----------------------------------------------------------------------------------
    def fileno(self) -> int:
        """The socket's file descriptor: readable when a frame is queued (for ``can.Notifier``)."""
        if self._sock is None:
            raise can.CanOperationError(f"{self.channel_info}: the bus is shut down")
        return self._sock.fileno()

    def _release(self) -> None:
        """Close the socket and remove its file, unmap the generation; safe to repeat. A forked
        child that inherited the bus closes its copy but leaves the file to the parent."""
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        for link in self._links.values():
            link.close()
        self._links, self._peers = {}, ()
        if self._path is not None:
            if self._owner_pid == os.getpid():
                with suppress(FileNotFoundError):
                    os.unlink(self._path)
            self._path = None
        if self._generation is not None:
            self._generation.close()
            self._generation = None

    def shutdown(self) -> None:
        """Leave the channel (idempotent)."""
        super().shutdown()
        self._release()
