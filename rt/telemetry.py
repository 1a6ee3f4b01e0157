"""Telemetry: every sample's record into a preallocated ring buffer, drained to disk by a
writer thread.

The loop never waits for the disk: ``push`` copies one row into the ring (into a row view
made before the loop) or, if the writer has fallen a whole buffer behind, drops the record
and counts it. The writer appends whole rows and flushes at least every ``flush_interval_s``
(<= 0.5 s), so after a ``kill -9`` the file holds everything up to the last flush.

File format (``.btl``): the line ``BEAMCTL-TELEMETRY 1``, an 8-byte little-endian length,
a JSON header (columns, sample rate, run metadata), then rows of little-endian float64.
A reader ignores an incomplete last row (a writer killed mid-write) and says how many bytes
it ignored.
"""

from __future__ import annotations

import json
import struct
import threading
from pathlib import Path

import numpy as np

MAGIC = b"BEAMCTL-TELEMETRY 1\n"


class TelemetryError(ValueError):
    """A telemetry file could not be read."""


class TelemetryWriter:
    """Ring buffer plus writer thread. Use ``start()``, ``push(record)`` per sample, ``close()``."""

    def __init__(self, path: str | Path, columns: list[str], capacity: int,
                 flush_interval_s: float = 0.25, meta: dict | None = None) -> None:
        self.path = Path(path)
        self.columns = list(columns)
        self.capacity = int(capacity)
        self.flush_interval_s = float(flush_interval_s)
        self._ring = np.zeros((self.capacity, len(columns)))
        self._rows = [self._ring[i] for i in range(self.capacity)]   # views made once
        self._head = 0        # records pushed (loop thread only)
        self._tail = 0        # records written (writer thread only)
        self.dropped = 0
        self.written = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        header = json.dumps({"columns": self.columns, "meta": meta or {}}).encode()
        self._file = open(self.path, "wb")  # noqa: SIM115 (closed in close())
        self._file.write(MAGIC + struct.pack("<Q", len(header)) + header)
        self._file.flush()

    @classmethod
    def for_controller(cls, path: str | Path, controller, meta: dict | None = None) -> TelemetryWriter:
        """A writer for a controller's records, sized by its ``telemetry`` settings. The header's
        meta holds what a reader needs to interpret the run (``controller_meta``) under the
        caller's ``meta``."""
        from beamctl.rt.controller import RECORD_COLUMNS

        settings = controller.config.telemetry
        return cls(path, RECORD_COLUMNS, capacity=int(settings.buffer_time_s * controller.sample_rate_hz),
                   flush_interval_s=settings.flush_interval_s,
                   meta={**controller_meta(controller), **(meta or {})})

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

    def _drain(self) -> None:
        head, tail = self._head, self._tail
        if head == tail:
            return
        start, end = tail % self.capacity, head % self.capacity
        if start < end:
            chunks = [self._ring[start:end]]
        else:
            chunks = [self._ring[start:], self._ring[:end]]
        for chunk in chunks:
            self._file.write(chunk.astype("<f8", copy=False).tobytes())
        self._tail = head
        self.written = head

    def _run(self) -> None:
        while not self._stop.is_set():
            self._drain()
            self._file.flush()
            self._stop.wait(self.flush_interval_s)

    def close(self) -> None:
        """Write everything pushed so far and close the file."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if not self._file.closed:
            self._drain()
            self._file.flush()
            self._file.close()

    def __enter__(self) -> TelemetryWriter:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


def controller_meta(controller) -> dict:
    """The settings a recording is read with: the sample rate, the controller's settings
    (allocation, actuators, safety limits), the gain table's design and its model's parameters
    (a reader turns modal displacements into millimetres with them)."""
    from beamctl.rt.config import settings_by_key

    table = controller.table
    design = table.design
    return {"sample_rate_hz": controller.sample_rate_hz,
            "controller": settings_by_key(controller.config),
            "design": {"kind": design.kind, "sample_rate_hz": design.sample_rate_hz,
                       "schedule": table.schedule.mode, "loads_n": [float(table.loads_n[0]),
                                                                     float(table.loads_n[-1])]},
            "model": table.model_parameters.to_dict()}


def read_telemetry(path: str | Path) -> tuple[dict, np.ndarray]:
    """(header, data [n x columns]) of a telemetry file. An incomplete last row is ignored;
    ``header["incomplete_row_bytes"]`` gives its length (0 when the file ends on a row)."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise TelemetryError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if not raw.startswith(MAGIC) or len(raw) < len(MAGIC) + 8:
        raise TelemetryError(f"{p}: not a beamctl telemetry file (no {MAGIC.strip().decode()!r} header)")
    (length,) = struct.unpack("<Q", raw[len(MAGIC):len(MAGIC) + 8])
    body = len(MAGIC) + 8
    try:
        header = json.loads(raw[body:body + length])
        columns = header["columns"]
    except (ValueError, KeyError, TypeError):
        raise TelemetryError(f"{p}: damaged header") from None
    data = raw[body + length:]
    row_bytes = 8 * len(columns)
    n = len(data) // row_bytes
    rows = np.frombuffer(data[:n * row_bytes], dtype="<f8").reshape(n, len(columns))
    header["incomplete_row_bytes"] = len(data) - n * row_bytes
    return header, rows.astype(float)


def export(header: dict, rows: np.ndarray, out: str | Path, fmt: str) -> Path:
    """Write telemetry (as ``read_telemetry`` returns it) as MATLAB ``mat`` (one variable per
    column plus ``columns`` and ``meta_json``) or ``csv`` (a header row of column names)."""
    out = Path(out)
    if fmt == "mat":
        import scipy.io

        variables = {name: rows[:, i] for i, name in enumerate(header["columns"])}
        variables["columns"] = np.array(header["columns"], dtype=object)
        variables["meta_json"] = json.dumps(header.get("meta", {}))
        scipy.io.savemat(out, variables, do_compression=True, appendmat=False)
    elif fmt == "csv":
        np.savetxt(out, rows, delimiter=",", header=",".join(header["columns"]), comments="",
                   fmt="%.10g")
    else:
        raise TelemetryError(f"unknown export format {fmt!r}: expected 'mat' or 'csv'")
    return out
