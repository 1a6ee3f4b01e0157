"""The local bus (``beamctl_local``): CAN frames between processes of one machine, intact and in
order, over UNIX datagram sockets in a private directory; its raw datagrams (the CAN backend's
fast path) interchangeable with python-can's messages."""

import os
import select
import socket
import stat
import subprocess
import sys
import time
import uuid

import can
import pytest

from beamctl.hal.localbus import (
    BASE_DIR_ENV,
    EXTENDED_ID,
    FD_FRAME,
    FRAME,
    HEADER,
    RAW_BUFFER_SIZE,
    RAW_DATA,
    RAW_TIME,
    SEND_TIME,
    SOCKET_SUFFIX,
    VERSION,
    LocalBus,
)

READY_ID, STOP_ID = 0x7F0, 0x7FF    # a child process announces itself, is told to end

# A child process on the channel argv[1]: announces itself, then echoes every frame with its
# identifier plus one until the stop frame (or 30 s of silence).
ECHO_CHILD = f"""
import sys, can
with can.Bus(interface="beamctl_local", channel=sys.argv[1]) as bus:
    bus.send(can.Message(arbitration_id={READY_ID}, is_extended_id=False))
    while True:
        msg = bus.recv(timeout=30.0)
        if msg is None or msg.arbitration_id == {STOP_ID}:
            break
        msg.arbitration_id += 1
        bus.send(msg)
"""

# A child process that joins argv[1], announces itself and waits to be killed.
SLEEPING_CHILD = f"""
import sys, time, can
bus = can.Bus(interface="beamctl_local", channel=sys.argv[1])
bus.send(can.Message(arbitration_id={READY_ID}, is_extended_id=False))
time.sleep(60)
"""

FIELDS = ("arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame", "is_fd", "bitrate_switch",
          "error_state_indicator", "dlc", "data")

FRAMES = {
    "classic": can.Message(arbitration_id=0x123, is_extended_id=False, data=bytes(range(8))),
    "fd-64-bytes": can.Message(arbitration_id=0x456, is_extended_id=False, is_fd=True, bitrate_switch=True,
                               error_state_indicator=True, data=bytes(range(100, 164))),
    "extended-id": can.Message(arbitration_id=0x1ABCDEF0, is_extended_id=True, data=b"\x01\x02\x03"),
    "remote": can.Message(arbitration_id=0x7E0, is_extended_id=False, is_remote_frame=True, dlc=5),
    "error": can.Message(arbitration_id=0x40, is_error_frame=True, data=bytes(8)),
}


@pytest.fixture
def base_dir(short_dir, monkeypatch):
    """The base directory of this test's buses (and of its child processes')."""
    base = short_dir / "b"
    monkeypatch.setenv(BASE_DIR_ENV, str(base))
    return base


@pytest.fixture
def channel(base_dir):
    return uuid.uuid4().hex[:8]


@pytest.fixture
def open_bus(channel):
    """Opens buses on the test's channel; shuts them down after the test."""
    buses = []

    def _open(**kwargs) -> LocalBus:
        buses.append(LocalBus(channel, **kwargs))
        return buses[-1]

    yield _open
    for bus in buses:
        bus.shutdown()


def sockets(base_dir, channel) -> list[str]:
    return sorted(name for name in os.listdir(base_dir / channel) if name.endswith(SOCKET_SUFFIX.decode()))


def differences(sent: can.Message, received: can.Message) -> list[str]:
    return [f"{name}: sent {getattr(sent, name)!r}, received {getattr(received, name)!r}"
            for name in FIELDS if getattr(sent, name) != getattr(received, name)]


def start_child(code: str, channel: str, cwd) -> subprocess.Popen:
    """A child process running ``code`` on ``channel``, started in ``cwd``: ``python -c`` puts its
    working directory first on the path, where a stale ``beamctl.egg-info`` (a checkout built
    before the entry point existed) would hide the installed ``beamctl_local`` interface."""
    return subprocess.Popen([sys.executable, "-c", code, channel], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=cwd)


def await_ready(bus: LocalBus, child: subprocess.Popen) -> None:
    msg = bus.recv(timeout=60.0)
    if msg is None or msg.arbitration_id != READY_ID:
        child.kill()
        _, stderr = child.communicate()
        pytest.fail(f"the child process did not announce itself on the bus (got {msg}); "
                    f"its stderr:\n{stderr}")


@pytest.mark.parametrize("kind", FRAMES)
def test_a_frame_crosses_with_every_field_intact(open_bus, channel, kind):
    sender, receiver = open_bus(), open_bus()
    sent = FRAMES[kind]
    before = time.time()
    sender.send(sent)
    after = time.time()
    received = receiver.recv(timeout=5.0)
    assert received is not None, f"the {kind} frame never arrived"
    changed = differences(sent, received)
    assert not changed, f"the {kind} frame changed on the way: {changed}"
    assert received.is_rx and received.channel == channel, (received.is_rx, received.channel)
    assert before <= received.timestamp <= after, \
        f"time stamp {received.timestamp} is not the send time (between {before} and {after})"


def test_a_bus_receives_its_own_frames_only_when_asked_to(open_bus):
    quiet, other, loud = open_bus(), open_bus(), open_bus(receive_own_messages=True)
    quiet.send(can.Message(arbitration_id=1))
    assert other.recv(timeout=5.0).arbitration_id == 1
    assert loud.recv(timeout=5.0).arbitration_id == 1
    assert quiet.recv(timeout=0) is None, "a bus received its own frame without receive_own_messages"
    loud.send(can.Message(arbitration_id=2))
    own = loud.recv(timeout=5.0)
    assert own is not None and own.arbitration_id == 2, "receive_own_messages=True did not loop a frame back"
    assert not own.is_rx, "a bus's own frame is flagged as received (is_rx), not as sent"
    assert quiet.recv(timeout=5.0).arbitration_id == 2 and other.recv(timeout=5.0).arbitration_id == 2


def test_a_bus_that_joins_receives_the_very_next_frame(open_bus):
    sender, first = open_bus(), open_bus()
    sender.send(can.Message(arbitration_id=1))
    late = open_bus()
    sender.send(can.Message(arbitration_id=2))
    assert [first.recv(timeout=5.0).arbitration_id for _ in range(2)] == [1, 2]
    msg = late.recv(timeout=0)
    assert msg is not None and msg.arbitration_id == 2, \
        "a bus that joined after the sender had listed the members missed the next frame"


def test_frames_reach_a_separate_process_and_come_back_in_order(open_bus, channel, tmp_path):
    bus = open_bus()
    child = start_child(ECHO_CHILD, channel, tmp_path)
    try:
        await_ready(bus, child)
        for i in range(200):
            bus.send(can.Message(arbitration_id=2 * i, is_extended_id=False, data=i.to_bytes(2, "little")))
            echo = bus.recv(timeout=10.0)
            assert echo is not None, f"no echo of frame {i} from the child process within 10 s"
            assert (echo.arbitration_id, bytes(echo.data)) == (2 * i + 1, i.to_bytes(2, "little")), \
                f"frame {i}: expected the echo of id {2 * i}, got {echo}"
        bus.send(can.Message(arbitration_id=STOP_ID, is_extended_id=False))
        _, stderr = child.communicate(timeout=30)
        assert child.returncode == 0, f"the echo process ended with {child.returncode}:\n{stderr}"
    finally:
        if child.poll() is None:
            child.kill()
            child.communicate()
    assert bus.dropped == 0


def test_recv_with_nobody_sending_times_out(open_bus):
    bus = open_bus()
    assert bus.recv(timeout=0) is None
    start = time.monotonic()
    assert bus.recv(timeout=0.05) is None
    assert time.monotonic() - start < 1.0, "recv(timeout=0.05) on a silent bus took a second or more"


def test_a_member_that_shut_down_is_dropped_and_sending_goes_on(open_bus, base_dir, channel):
    sender, stays, leaves = open_bus(), open_bus(), open_bus()
    sender.send(can.Message(arbitration_id=1))
    assert leaves.recv(timeout=5.0).arbitration_id == 1
    leaves.shutdown()
    leaves.shutdown()
    assert len(sockets(base_dir, channel)) == 2, "shutdown() left its socket file behind"
    sender.send(can.Message(arbitration_id=2))
    assert [stays.recv(timeout=5.0).arbitration_id for _ in range(2)] == [1, 2]
    assert sender.dropped == 0
    with pytest.raises(can.CanOperationError, match="shut down"):
        leaves.send(can.Message(arbitration_id=3))


def test_a_member_killed_without_shutdown_is_dropped_and_its_file_removed(open_bus, base_dir, channel,
                                                                         tmp_path):
    sender, stays = open_bus(), open_bus()
    child = start_child(SLEEPING_CHILD, channel, tmp_path)
    try:
        await_ready(sender, child)
        assert stays.recv(timeout=5.0).arbitration_id == READY_ID
    finally:
        child.kill()
        child.communicate()
    assert len(sockets(base_dir, channel)) == 3, "the killed process's socket file is not there to test with"
    sender.send(can.Message(arbitration_id=1))
    assert stays.recv(timeout=5.0).arbitration_id == 1
    assert len(sockets(base_dir, channel)) == 2, "the killed process's stale socket file was not removed"
    sender.send(can.Message(arbitration_id=2))
    assert stays.recv(timeout=5.0).arbitration_id == 2


def test_a_receiver_that_does_not_read_loses_frames_without_blocking_the_sender(open_bus):
    sender, idle = open_bus(), open_bus()
    n_frames = 1000
    for i in range(n_frames):
        sender.send(can.Message(arbitration_id=i))
    assert sender.dropped > 0, f"{n_frames} frames to a receiver that never read were all queued"
    received = []
    while (msg := idle.recv(timeout=0)) is not None:
        received.append(msg.arbitration_id)
    assert len(received) + sender.dropped == n_frames, \
        f"{len(received)} received + {sender.dropped} counted as dropped != {n_frames} sent"
    assert received == list(range(len(received))), "the frames that were queued arrived out of order"


def test_a_malformed_datagram_is_counted_and_skipped(open_bus, base_dir, channel):
    receiver = open_bus()
    (path,) = sockets(base_dir, channel)
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as raw:
        raw.sendto(b"short", str(base_dir / channel / path))
        raw.sendto(b"\xff" + bytes(FRAME.size - 1), str(base_dir / channel / path))   # unknown version
    open_bus().send(can.Message(arbitration_id=7))
    msg = receiver.recv(timeout=5.0)
    assert msg is not None and msg.arbitration_id == 7, f"expected the frame after two bad ones, got {msg}"
    assert receiver.malformed == 2


def test_fileno_is_readable_when_a_frame_is_queued(open_bus):
    sender, receiver = open_bus(), open_bus()
    assert select.select([receiver], [], [], 0)[0] == []
    sender.send(can.Message(arbitration_id=1))
    assert select.select([receiver], [], [], 5.0)[0] == [receiver], "fileno() did not become readable"


@pytest.mark.parametrize("name", ["../x", "a/b", "", ".", ".."])
def test_a_channel_name_that_is_a_path_is_refused(base_dir, name):
    with pytest.raises(can.CanInitializationError, match="expected a simple name"):
        LocalBus(name)


def test_the_base_directory_is_private(channel, open_bus, base_dir):
    open_bus()
    assert stat.S_IMODE(base_dir.stat().st_mode) == 0o700
    assert stat.S_IMODE((base_dir / channel).stat().st_mode) == 0o700


@pytest.mark.parametrize("mode", [0o777, 0o770], ids=oct)
def test_a_base_directory_others_may_write_to_is_refused(base_dir, channel, mode):
    base_dir.mkdir()
    base_dir.chmod(mode)
    with pytest.raises(can.CanInitializationError) as err:
        LocalBus(channel)
    assert str(base_dir) in str(err.value) and "writable by group or others" in str(err.value), err.value


@pytest.mark.skipif(os.geteuid() != 0, reason="giving a directory to another user takes root")
def test_a_base_directory_of_another_user_is_refused(base_dir, channel):
    base_dir.mkdir(mode=0o700)
    os.chown(base_dir, 65534, 65534)
    with pytest.raises(can.CanInitializationError, match="belongs to uid 65534"):
        LocalBus(channel)


def test_python_can_opens_it_by_name(channel):
    with can.Bus(interface="beamctl_local", channel=channel) as bus:
        assert isinstance(bus, LocalBus), type(bus)


def test_a_channel_named_by_digits_alone_works_through_python_can(base_dir):
    """python-can turns a channel string of digits into an int before the bus sees it
    (``beamctl_local:42`` on a command line): it is still that channel."""
    sender = can.Bus(interface="beamctl_local", channel="12345678")
    receiver = can.Bus(interface="beamctl_local", channel="12345678")
    try:
        sender.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))
        msg = receiver.recv(5.0)
        assert msg is not None and msg.arbitration_id == 0x123
        assert (base_dir / "12345678").is_dir()
    finally:
        sender.shutdown()
        receiver.shutdown()


def test_a_raw_datagram_arrives_as_a_message_and_a_message_as_a_raw_datagram(open_bus, channel):
    sender, receiver = open_bus(), open_bus()
    frame = sender.raw_frame(0x123, 8, is_fd=True)
    frame[RAW_DATA:RAW_DATA + 8] = bytes(range(8))
    before = time.time()
    sender.send_raw(frame)
    after = time.time()
    sender.send_raw(frame)                      # as often as wanted, each send stamped anew
    first, second = receiver.recv(timeout=5.0), receiver.recv(timeout=5.0)
    for msg in (first, second):
        assert msg is not None, "the raw datagram never arrived"
        fields = (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, msg.is_fd, msg.dlc,
                  bytes(msg.data), msg.is_rx, msg.channel)
        assert fields == (0x123, False, False, True, 8, bytes(range(8)), True, channel), msg
    assert before <= first.timestamp <= after <= second.timestamp, "not stamped with the send time"

    sender.send(FRAMES["extended-id"])
    buffer = bytearray(RAW_BUFFER_SIZE)
    before_recv = time.time()
    assert receiver.recv_raw_into(buffer, 5.0), "the message never arrived as a datagram"
    version, flags, dlc, length, arbitration_id, _, stamp = HEADER.unpack_from(buffer)
    assert (version, flags & (EXTENDED_ID | FD_FRAME), dlc, length, arbitration_id) == (
        VERSION, EXTENDED_ID, 3, 3, 0x1ABCDEF0)
    assert bytes(buffer[RAW_DATA:RAW_DATA + length]) == b"\x01\x02\x03"
    assert SEND_TIME.unpack_from(buffer, RAW_TIME)[0] == stamp <= before_recv


def test_recv_raw_into_times_out_and_skips_what_is_no_frame(open_bus, base_dir, channel):
    receiver = open_bus()
    buffer = bytearray(RAW_BUFFER_SIZE)
    assert not receiver.recv_raw_into(buffer, 0)
    start = time.monotonic()
    assert not receiver.recv_raw_into(buffer, 0.05)
    assert time.monotonic() - start < 1.0
    (path,) = sockets(base_dir, channel)
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as raw:
        raw.sendto(b"short", str(base_dir / channel / path))
        raw.sendto(bytes([VERSION]) + bytes(FRAME.size), str(base_dir / channel / path))   # a byte too long
    sender = open_bus()
    sender.send(can.Message(arbitration_id=7))
    assert receiver.recv_raw_into(buffer, 5.0)
    assert HEADER.unpack_from(buffer)[4] == 7 and receiver.malformed == 2
    with pytest.raises(ValueError, match="receive buffer"):
        receiver.recv_raw_into(bytearray(FRAME.size), 0)
    with pytest.raises(ValueError, match="raw_frame"):
        sender.send_raw(bytearray(10))
