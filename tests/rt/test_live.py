"""The live view's publisher: what it keeps of the records, and that it never waits for a viewer."""

import os
import socket
import struct
import threading

import numpy as np
import pytest

from beamctl.rt.live import MAGIC, MAX_SOCKET_PATH_BYTES, Derived, LiveError, LivePublisher, decode
from beamctl.rt.telemetry import TelemetryWriter, read_telemetry

COLUMNS = ["time_s", "index", "flags", "load_N"]
RATE_HZ = 2500.0


@pytest.fixture
def receiver(short_dir):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = os.path.join(short_dir, "live.sock")
    sock.bind(path)
    sock.settimeout(10.0)
    yield path, sock
    sock.close()


def _rows(first: int, n: int, flags: dict | None = None) -> np.ndarray:
    i = np.arange(first, first + n, dtype=float)
    rows = np.column_stack([i / RATE_HZ, i, np.zeros(n), 1000.0 + 0.5 * i])
    for index, bits in (flags or {}).items():
        if first <= index < first + n:
            rows[index - first, 2] = bits
    return rows


def _returns_within(function, deadline_s: float = 60.0) -> None:
    """Run ``function`` in a thread; fail if it has not returned by the (generous) deadline: a
    blocked send would hold it forever."""
    worker = threading.Thread(target=function, daemon=True)
    worker.start()
    worker.join(deadline_s)
    assert not worker.is_alive(), f"publishing did not return within {deadline_s} s: it waits for the viewer"


def _drain(sock) -> list[tuple[dict, np.ndarray]]:
    received = []
    sock.setblocking(False)
    try:
        while True:
            received.append(decode(sock.recv(1 << 17)))
    except BlockingIOError:
        pass
    finally:
        sock.settimeout(10.0)
    return received


def test_publishing_with_nobody_listening_returns_and_counts_every_datagram_dropped(short_dir):
    publisher = LivePublisher(os.path.join(short_dir, "nobody.sock"), COLUMNS, RATE_HZ)

    def publish_a_minute_of_records():
        for k in range(600):
            publisher.publish([_rows(250 * k, 250)], 250 * k)

    _returns_within(publish_a_minute_of_records)
    assert publisher.sent == 0 and publisher.dropped == publisher.sequence == 600, \
        (publisher.sent, publisher.dropped, publisher.sequence)
    assert publisher.last_error, "a dropped datagram says why"


def test_a_viewer_that_never_reads_fills_its_queue_and_the_rest_is_dropped(receiver):
    path, sock = receiver
    publisher = LivePublisher(path, COLUMNS, RATE_HZ)

    def publish_a_minute_of_records():
        for k in range(600):
            publisher.publish([_rows(250 * k, 250)], 250 * k)

    _returns_within(publish_a_minute_of_records)
    assert publisher.sent >= 1 and publisher.dropped >= 1, (publisher.sent, publisher.dropped)
    assert publisher.sent + publisher.dropped == publisher.sequence
    header, rows = decode(sock.recv(1 << 17))       # what did get through is intact
    assert header["sequence"] == 0 and header["run"]["columns"] == COLUMNS
    np.testing.assert_array_equal(rows[:, 1] % publisher.decimation, publisher.decimation - 1)


@pytest.mark.parametrize("sample_rate_hz", [100.0, 1000.0, 2500.0, 6000.0, 20000.0])
def test_the_view_gets_at_most_200_rows_a_second_at_any_loop_rate(sample_rate_hz, short_dir):
    publisher = LivePublisher(os.path.join(short_dir, "x.sock"), COLUMNS, sample_rate_hz)
    rows_per_s = sample_rate_hz / publisher.decimation
    assert rows_per_s <= 200.0, rows_per_s
    assert rows_per_s >= min(sample_rate_hz, 100.0), f"decimated further than needed: {rows_per_s} rows/s"


def test_decimation_keeps_the_same_rows_however_the_writer_drains_and_ors_the_flags_of_each_group(receiver):
    """Rows i with i % k == k - 1 are kept; a flag raised on any row of a group shows on the
    group's kept row, also when the group straddles two drains or the ring's end."""
    path, sock = receiver
    n = 400
    flags = {5: 1, 30: 2, 31: 4, 51: 1}     # k = 13 at 2500 Hz: groups 0..12, 13..25, 26..38, 39..51
    whole = LivePublisher(path, COLUMNS, RATE_HZ)
    k = whole.decimation
    assert k == 13
    whole.publish([_rows(0, n, flags)], 0)
    expected = np.concatenate([rows for _, rows in _drain(sock)])

    pieces = LivePublisher(path, COLUMNS, RATE_HZ)
    rng = np.random.default_rng(3)
    start, received = 0, []
    while start < n:
        length = int(min(rng.integers(1, 40), n - start))
        split = int(rng.integers(0, length + 1))        # a drain across the ring's end: two chunks
        block = _rows(start, length, flags)
        pieces.publish([block[:split], block[split:]] if 0 < split < length else [block], start)
        received += _drain(sock)        # read as a viewer does (the kernel queues a few datagrams only)
        start += length
    assert pieces.dropped == 0
    got = np.concatenate([rows for _, rows in received])

    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(got[:, 1], np.arange(k - 1, n, k))
    kept_flags = dict(zip(got[:, 1].astype(int), got[:, 2].astype(int), strict=True))
    assert kept_flags[12] == 1 and kept_flags[25] == 0 and kept_flags[38] == 2 | 4 and kept_flags[51] == 1
    assert sum(kept_flags.values()) == 1 + 6 + 1, kept_flags


def test_derived_columns_follow_the_record_s(receiver):
    path, sock = receiver
    twice_load = Derived(("twice_load_N",), lambda rows: 2.0 * rows[:, 3:4])
    publisher = LivePublisher(path, COLUMNS, RATE_HZ, derived=twice_load)
    publisher.publish([_rows(0, 100)], 0)
    header, rows = decode(sock.recv(1 << 17))
    assert header["run"]["columns"] == [*COLUMNS, "twice_load_N"]
    np.testing.assert_array_equal(rows[:, 4], 2.0 * rows[:, 3])


def test_a_drain_after_a_stall_sends_only_its_newest_second(receiver):
    """A writer held up for 8 s drains 20000 rows at once: the view gets the newest second (the
    past is in the recording), in datagrams that fit."""
    path, sock = receiver
    publisher = LivePublisher(path, COLUMNS, RATE_HZ)
    publisher.publish([_rows(0, 20000)], 0)
    got = np.concatenate([rows for _, rows in _drain(sock)])
    assert publisher.dropped == 0
    assert got[-1, 1] == 19999 - (19999 + 1) % publisher.decimation
    row_spacing_s = publisher.decimation / publisher.sample_rate_hz
    assert got[-1, 0] - got[0, 0] == pytest.approx(1.0, abs=2 * row_spacing_s)


def test_the_writer_feeds_the_view_and_the_file_gets_every_record(tmp_path, receiver):
    path, sock = receiver
    publisher = LivePublisher(path, COLUMNS, RATE_HZ)
    received, written = [], threading.Event()

    def read():         # as a viewer does, until the writer has closed and the queue is empty
        sock.settimeout(0.2)
        while True:
            try:
                received.append(decode(sock.recv(1 << 17)))
            except TimeoutError:
                if written.is_set():
                    return

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    with TelemetryWriter(tmp_path / "t.btl", COLUMNS, capacity=8192, live=publisher) as writer:
        for i in range(5000):
            writer.push(_rows(i, 1)[0])
            if i % 200 == 0:        # let the writer drain now and then, as a loop's period does
                threading.Event().wait(0.01)
    written.set()
    reader.join(60)
    _, rows = read_telemetry(tmp_path / "t.btl")
    np.testing.assert_array_equal(rows[:, 1], np.arange(5000))
    kept = np.concatenate([r for _, r in received])[:, 1]
    assert np.all(kept[:-1] % publisher.decimation == publisher.decimation - 1)
    assert kept[-1] == 4999, "and the run's last row"
    assert np.all(np.diff(kept) > 0), "rows arrive in order"


def test_a_failing_view_is_switched_off_and_the_recording_goes_on(tmp_path, short_dir):
    def broken(rows):
        raise RuntimeError("a bug in the view")

    publisher = LivePublisher(os.path.join(short_dir, "x.sock"), COLUMNS, RATE_HZ,
                              derived=Derived(("x",), broken))
    with TelemetryWriter(tmp_path / "t.btl", COLUMNS, capacity=4096, live=publisher) as writer:
        for i in range(3000):
            writer.push(_rows(i, 1)[0])
    _, rows = read_telemetry(tmp_path / "t.btl")
    np.testing.assert_array_equal(rows[:, 1], np.arange(3000))
    assert writer.live is None and "a bug in the view" in writer.live_error


def test_a_socket_path_too_long_for_the_kernel_is_refused_naming_it():
    path = "/tmp/" + "x" * MAX_SOCKET_PATH_BYTES + ".sock"
    with pytest.raises(LiveError, match="at most 107 bytes") as error:
        LivePublisher(path, COLUMNS, RATE_HZ)
    assert path in str(error.value)


def _datagram(header: bytes, body: bytes) -> bytes:
    return MAGIC + struct.pack("<I", len(header)) + header + body


@pytest.mark.parametrize(("datagram", "why"), [
    (b"", "not a beamctl live datagram"),
    (b"hello", "not a beamctl live datagram"),
    (_datagram(b"{bad}", b""), "damaged"),
    (_datagram(b'{"rows": 2, "run": {"columns": ["a"]}}', b"\0" * 8), "8 bytes of rows, expected 2 rows"),
])
def test_a_damaged_datagram_is_refused_saying_why(datagram, why):
    with pytest.raises(LiveError, match=why):
        decode(datagram)


def test_the_view_gets_the_run_s_final_row_whether_or_not_decimation_keeps_it(tmp_path, receiver):
    """The final state (STOPPED after a ramp to bias) is one row: the last drain sends it."""
    path, sock = receiver
    for n in (26, 30):          # k = 13: row 25 is kept by decimation, row 29 is not
        publisher = LivePublisher(path, COLUMNS, RATE_HZ)
        with TelemetryWriter(tmp_path / f"{n}.btl", COLUMNS, capacity=64, live=publisher) as writer:
            for i in range(n):
                writer.push(_rows(i, 1)[0])
        kept = np.concatenate([rows for _, rows in _drain(sock)])[:, 1]
        assert kept[-1] == n - 1 and np.all(np.diff(kept) > 0), (n, kept)
