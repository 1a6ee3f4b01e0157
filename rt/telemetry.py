"""Telemetry: every sample's record into a preallocated ring buffer, drained to disk by a
writer thread.

The loop never waits for the disk: ``push`` copies one row into the ring (into a row view
made before the loop) or, if the writer has fallen a whole buffer behind, drops the record
and counts it. The writer appends whole rows and flushes at least every ``flush_interval_s``
(<= 0.5 s), so after a ``kill -9`` the file holds everything up to the last flush.

What the file keeps is the writer thread's choice (``Recording``), never the loop's: every
sample (``full``); every k-th sample and every sample where a coded or bit-field column (state,
fault, flags) changes (``decimated``); or, around each trigger (a change of a coded column, a
sample with a trigger flag such as a saturation), the samples from ``pre_trigger_s`` before to
``post_trigger_s`` after it (``triggered``). Every row keeps its own time stamp (the record's
``time_s``), so a thinned recording's time base stays exact.

A live view (rt/live.py) may watch: the writer hands each drain's rows to its publisher, in
the writer's thread and at the writer's own pace (a drain every ``flush_interval_s``: a view
does not wake the writer more often, whose work would then compete with the loop's); the
loop's side is the same with or without it. The view sees every sample, whatever the
recording keeps. A writer without a file (``path`` None) only feeds the view.

File format (``.btl``): the line ``BEAMCTL-TELEMETRY 1``, an 8-byte little-endian length,
a JSON header (columns, and where the writer knows them the sample rate, the units, the labels
of coded columns and bits, the recording mode, and run metadata), then rows of little-endian
float64. A reader ignores an incomplete last row (a writer killed mid-write) and says how many
bytes it ignored.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import struct
import threading
from collections.abc import Iterator, Mapping
from pathlib import Path

import numpy as np

from beamctl.rt.config import MAX_PRE_TRIGGER_S, RECORDING_MODES, Recording  # noqa: F401 (re-exported)
from beamctl.rt.live import LivePublisher
from beamctl.rt.record import (
    RECORD_COLUMNS,
    TRIGGER_FLAGS,
    code_labels,
    column_unit,
    controller_meta,
    flag_labels,
)

MAGIC = b"BEAMCTL-TELEMETRY 1\n"


class TelemetryError(ValueError):
    """A telemetry file could not be read."""


class _Events:
    """Per row of a chunk: did a coded or bit-field column change from the row before (the row
    before the chunk remembered from the last call), and does a trigger flag stand."""

    def __init__(self, event_columns: list[int], trigger_bits: dict[int, int]) -> None:
        self._columns = event_columns
        self._trigger_bits = trigger_bits
        self._last: np.ndarray | None = None

    def changed(self, rows: np.ndarray, first_is_event: bool) -> np.ndarray:
        events = rows[:, self._columns]
        changed = np.empty(len(rows), dtype=bool)
        changed[1:] = np.any(events[1:] != events[:-1], axis=1)
        changed[0] = first_is_event if self._last is None else bool(np.any(events[0] != self._last))
        self._last = events[-1].copy()
        return changed

    def flagged(self, rows: np.ndarray) -> np.ndarray:
        out = np.zeros(len(rows), dtype=bool)
        for column, bits in self._trigger_bits.items():
            out |= (rows[:, column].astype(np.int64) & bits) != 0
        return out


class _Decimator:
    """Every ``k``-th sample (counted from the first) and every sample that changes an event
    column."""

    def __init__(self, k: int, events: _Events) -> None:
        self._k = k
        self._events = events

    def select(self, rows: np.ndarray, first: int) -> list[np.ndarray]:
        keep = self._events.changed(rows, first_is_event=True)
        keep[(-first) % self._k::self._k] = True
        return [rows[keep]]


class _Trigger:
    """The samples from ``pre`` before to ``post`` after each trigger (a change of a coded
    column, or a trigger flag). The last ``pre`` samples wait in a history ring of their own,
    so that a trigger can still write them."""

    def __init__(self, pre: int, post: int, width: int, changes: _Events, flags: _Events) -> None:
        self._pre, self._post = pre, post
        self._changes, self._flags = changes, flags
        self._history = np.zeros((max(pre, 1), width))
        self._written = 0       # absolute index after the last sample written
        self._until = 0         # absolute index after the current post-trigger window

    def select(self, rows: np.ndarray, first: int) -> list[np.ndarray]:
        m = len(rows)
        changed = self._changes.changed(rows, first_is_event=False)
        triggers = np.flatnonzero(changed | self._flags.flagged(rows))
        keep = np.zeros(m + 1, dtype=np.int64)      # a difference array of the windows
        if self._until > first:
            keep[0] += 1
            keep[min(m, self._until - first)] -= 1
        out = []
        if triggers.size:
            starts = np.maximum(triggers - self._pre, 0)
            ends = np.minimum(triggers + self._post + 1, m)
            np.add.at(keep, starts, 1)
            np.add.at(keep, ends, -1)
            self._until = max(self._until, first + int(triggers[-1]) + self._post + 1)
            # the history holds the samples [first - min(first, pre), first)
            earliest = max(first + int(triggers[0]) - self._pre, self._written, first - min(first, self._pre))
            if earliest < first:
                out.append(self._history[np.arange(earliest, first) % len(self._history)])
        mask = np.cumsum(keep[:m]) > 0
        kept = np.flatnonzero(mask)
        if kept.size:
            out.append(rows[mask])
            self._written = first + int(kept[-1]) + 1
        self._remember(rows, first)
        return out

    def _remember(self, rows: np.ndarray, first: int) -> None:
        if self._pre:
            tail = rows[-self._pre:]
            start = first + len(rows) - len(tail)
            self._history[np.arange(start, start + len(tail)) % self._pre] = tail


class TelemetryWriter:
    """Ring buffer plus writer thread. Use ``start()``, ``push(record)`` per sample, ``close()``.

    ``units`` ({column: unit}), ``labels`` ({column: {code: label}}) and ``bits`` ({column:
    {bit: label}}) go into the header for readers and exporters; the coded and bit-field
    columns are the events a decimated recording always keeps and (the coded ones, and the bits
    in ``trigger_bits`` {column: mask}) the triggers of a triggered one, which needs
    ``sample_rate_hz``. ``received`` counts the records taken from the ring, ``written`` the
    rows in the file, ``dropped`` the records the ring had no room for.
    """

    def __init__(self, path: str | Path | None, columns: list[str], capacity: int,
                 flush_interval_s: float = 0.25, meta: dict | None = None, *,
                 live: LivePublisher | None = None,
                 sample_rate_hz: float | None = None, recording: Recording | None = None,
                 units: Mapping[str, str] | None = None,
                 labels: Mapping[str, Mapping[int, str]] | None = None,
                 bits: Mapping[str, Mapping[int, str]] | None = None,
                 trigger_bits: Mapping[str, int] | None = None) -> None:
        self.path = None if path is None else Path(path)
        self.columns = list(columns)
        self.capacity = int(capacity)
        self.flush_interval_s = float(flush_interval_s)
        self.recording = recording = recording or Recording()
        if recording.mode == "triggered" and not sample_rate_hz:
            raise ValueError("a triggered recording needs the sample rate (its windows are in seconds)")
        self._select = self._selector(recording, sample_rate_hz, labels or {}, bits or {}, trigger_bits or {})
        self._ring = np.zeros((self.capacity, len(columns)))
        self._rows = [self._ring[i] for i in range(self.capacity)]   # views made once
        self._head = 0        # records pushed (loop thread only)
        self._tail = 0        # records taken (writer thread only)
        self.dropped = 0
        self.received = 0
        self.written = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.live = live
        self.live_error = ""    # why the live view was switched off (a viewer's fault never stops the file)
        self._file = None
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        header = {"columns": self.columns,
                  "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                  "recording": recording.header(sample_rate_hz)}
        if sample_rate_hz:
            header["sample_rate_hz"] = float(sample_rate_hz)
        for key, table in (("units", units), ("labels", labels), ("bits", bits)):
            if table:
                header[key] = {c: v if key == "units" else {str(k): t for k, t in v.items()}
                               for c, v in table.items() if c in self.columns}
        encoded = json.dumps({**header, "meta": meta or {}}).encode()
        self._file = open(self.path, "wb")  # noqa: SIM115 (closed in close())
        self._file.write(MAGIC + struct.pack("<Q", len(encoded)) + encoded)
        self._file.flush()

    def _selector(self, recording: Recording, sample_rate_hz: float | None, labels: Mapping, bits: Mapping,
                  trigger_bits: Mapping[str, int]) -> _Decimator | _Trigger | None:
        """What picks the rows to keep (None: every row)."""
        if recording.mode == "full":
            return None
        index = {name: i for i, name in enumerate(self.columns)}
        coded = [index[c] for c in labels if c in index]
        if recording.mode == "decimated":
            flagged = [index[c] for c in bits if c in index]
            return _Decimator(recording.decimation, _Events(coded + flagged, {}))
        pre, post = recording.window_samples(sample_rate_hz)
        return _Trigger(pre, post, len(self.columns), _Events(coded, {}),
                        _Events([], {index[c]: int(m) for c, m in trigger_bits.items() if c in index}))

    @classmethod
    def for_controller(cls, path: str | Path | None, controller, meta: dict | None = None,
                       live: LivePublisher | None = None) -> TelemetryWriter:
        """A writer for a controller's records, sized and set by its ``telemetry`` settings, with
        the record's units, code labels and flag bits, the sample rate and the gain table's
        SHA-256 (``meta["gain_table_sha256"]``) in the header; the header's meta holds what a
        reader needs to interpret the run (``controller_meta``) under the caller's ``meta``."""
        settings = controller.config.telemetry
        return cls(path, RECORD_COLUMNS, capacity=int(settings.buffer_time_s * controller.sample_rate_hz),
                   flush_interval_s=settings.flush_interval_s,
                   meta={"gain_table_sha256": controller.table.sha256, **controller_meta(controller),
                         **(meta or {})},
                   sample_rate_hz=controller.sample_rate_hz, recording=settings.recording,
                   units={c: column_unit(c) for c in RECORD_COLUMNS}, labels=code_labels(),
                   bits=flag_labels(), trigger_bits={column: TRIGGER_FLAGS for column in flag_labels()},
                   live=live)

    def start(self) -> TelemetryWriter:
        self._thread = threading.Thread(target=self._run, name="telemetry-writer", daemon=True)
        self._thread.start()
        return self

    def push(self, record: np.ndarray) -> None:
        """Copy one record into the ring; drop it (counted) if the ring is full."""
        head = self._head
        if head - self._tail >= self.capacity:
            self.dropped += 1
            return
        np.copyto(self._rows[head % self.capacity], record)
        self._head = head + 1

    def _drain(self, final: bool = False) -> None:
        head, tail = self._head, self._tail
        if head == tail:
            if final and head:          # the view's last word: the run's final row
                last = (head - 1) % self.capacity
                self._publish([self._ring[last:last + 1]], head - 1, final)
            return
        start, end = tail % self.capacity, head % self.capacity
        if start < end:
            chunks = [self._ring[start:end]]
        else:
            chunks = [self._ring[start:], self._ring[:end]] if end else [self._ring[start:]]
        if self._file is not None:
            first = tail                # the sample index of the chunk's first record
            for chunk in chunks:
                for rows in ([chunk] if self._select is None else self._select.select(chunk, first)):
                    # the ring's rows as they are (no copy: the interpreter's lock is let go
                    # while the kernel copies them, and the loop may need it)
                    self._file.write(memoryview(np.ascontiguousarray(rows, dtype="<f8")).cast("B"))
                    self.written += len(rows)
                first += len(chunk)
        self._publish(chunks, tail, final)     # before the tail moves on: the loop may then reuse the rows
        self._tail = head
        self.received = head

    def _publish(self, chunks: list[np.ndarray], first_index: int, final: bool) -> None:
        if self.live is None:
            return
        try:
            self.live.publish(chunks, first_index, final)
        except Exception as exc:        # a fault of the view must not cost the recording
            self.live_error = f"{type(exc).__name__}: {exc}"
            self.live = None

    def _run(self) -> None:
        while not self._stop.is_set():
            self._drain()
            if self._file is not None:
                self._file.flush()
            self._stop.wait(self.flush_interval_s)

    def close(self) -> None:
        """Write everything pushed so far (what the recording keeps of it) and close the file
        (the live view gets it too)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self._file is None or not self._file.closed:
            self._drain(final=True)
        if self._file is not None and not self._file.closed:
            self._file.flush()
            self._file.close()

    def __enter__(self) -> TelemetryWriter:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


class TelemetryReader:
    """A telemetry file opened for reading: its ``header``, the number of complete ``rows``
    (counted when opened: a file still being written is read as far as it was then), and the
    rows in chunks (``chunks``) or whole (``read_all``)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self._file = open(self.path, "rb")  # noqa: SIM115 (closed in close())
        except OSError as exc:
            raise TelemetryError(f"{self.path}: cannot read ({exc.strerror or exc})") from None
        try:
            self.header = self._read_header()
        except BaseException:
            self._file.close()
            raise
        self.columns: list[str] = self.header["columns"]
        self.row_bytes = 8 * len(self.columns)
        size = os.fstat(self._file.fileno()).st_size - self._data_offset
        self.rows = size // self.row_bytes
        self.header["incomplete_row_bytes"] = size - self.rows * self.row_bytes

    def _read_header(self) -> dict:
        p = self.path
        try:
            start = self._file.read(len(MAGIC) + 8)
        except OSError as exc:
            raise TelemetryError(f"{p}: cannot read ({exc.strerror or exc})") from None
        if not start.startswith(MAGIC) or len(start) < len(MAGIC) + 8:
            raise TelemetryError(f"{p}: not a beamctl telemetry file (no {MAGIC.strip().decode()!r} header)")
        (length,) = struct.unpack("<Q", start[len(MAGIC):])
        room = os.fstat(self._file.fileno()).st_size - len(start)
        if length > room:
            raise TelemetryError(f"{p}: damaged header (it says {length} bytes, the file ends {room} "
                                 f"bytes after it begins: cut off or overwritten)")
        raw = self._file.read(length)
        try:
            header = json.loads(raw)
            columns = header["columns"]
            if not (isinstance(columns, list) and columns and all(isinstance(c, str) for c in columns)):
                raise TypeError
        except (ValueError, KeyError, TypeError):
            raise TelemetryError(f"{p}: damaged header") from None
        self._data_offset = len(MAGIC) + 8 + length
        return header

    def chunks(self, rows_per_chunk: int) -> Iterator[np.ndarray]:
        """The complete rows, ``rows_per_chunk`` at a time, each [k x columns] in one buffer that
        the next chunk overwrites (copy what you keep)."""
        buffer = np.empty((min(max(1, rows_per_chunk), max(self.rows, 1)), len(self.columns)), dtype="<f8")
        self._file.seek(self._data_offset)
        done = 0
        while done < self.rows:
            k = min(len(buffer), self.rows - done)
            view = buffer[:k]
            got = self._readinto(view)
            if got != k * self.row_bytes:
                raise TelemetryError(f"{self.path}: the file shrank while it was read "
                                     f"(at row {done + got // self.row_bytes})")
            done += k
            yield view

    def read_all(self) -> np.ndarray:
        """Every complete row [n x columns], read into memory once."""
        rows = np.empty((self.rows, len(self.columns)), dtype="<f8")
        self._file.seek(self._data_offset)
        got = self._readinto(rows) if self.rows else 0
        if got != rows.nbytes:
            raise TelemetryError(f"{self.path}: the file shrank while it was read")
        return rows.astype(float, copy=False)

    def _readinto(self, array: np.ndarray) -> int:
        try:
            return self._file.readinto(memoryview(array).cast("B"))
        except OSError as exc:
            raise TelemetryError(f"{self.path}: cannot read ({exc.strerror or exc})") from None

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> TelemetryReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_telemetry(path: str | Path) -> tuple[dict, np.ndarray]:
    """(header, data [n x columns]) of a telemetry file. An incomplete last row is ignored;
    ``header["incomplete_row_bytes"]`` gives its length (0 when the file ends on a row)."""
    with TelemetryReader(path) as reader:
        return reader.header, reader.read_all()
