"""Live telemetry for a viewer (``beamctl monitor``): decimated records sent as datagrams from
the telemetry writer's thread, never from the control loop.

The writer (rt/telemetry.py) hands the publisher the rows of each drain. The publisher keeps
one row in ``decimation`` (the last of each group, by the row's index since the run began, so
that drains of any length pick the same rows), and the run's last row (its final state); the
``flags`` column of a kept row is the OR of its whole group, so that a saturation shorter than
a group still shows. It sends the kept rows to a UNIX datagram socket that the viewer binds,
without waiting: when nobody listens (no socket file, or a stale one) or the viewer reads too
slowly (its queue is full), the datagram is dropped and counted. A viewer that stops, stalls
or was never started costs the service a failed ``sendto`` per datagram and nothing else.

Datagram: ``MAGIC``, a 4-byte little-endian length, a JSON header of that length, then
``header["rows"]`` rows of ``len(header["run"]["columns"])`` little-endian float64. The
header carries the datagram's ``sequence`` (the receiver counts the ones it missed), the
run's description ``run`` (columns, sample rate, decimation, labels: every datagram is
readable alone, so a viewer started mid-run needs nothing else) and a ``status`` of counters
taken when it was sent (the loop's overruns, say).
"""

from __future__ import annotations

import json
import math
import os
import socket
import struct
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MAGIC = b"BEAMCTL-LIVE 1\n"
_LENGTH = struct.Struct("<I")
DEFAULT_RATE_HZ = 200.0         # rows a second: enough for a page, a fraction of a loop's rate
MAX_DATAGRAM_BYTES = 32768
MAX_SOCKET_PATH_BYTES = 107     # sun_path holds 108 bytes with the terminating zero


class LiveError(ValueError):
    """A live-view address or datagram that cannot be used."""


def check_socket_path(path: str | Path, what: str) -> str:
    """``path`` as a string, refused when the kernel cannot bind it (too long for sun_path)."""
    text = os.fspath(path)
    if not text:
        raise LiveError(f"{what}: empty socket path")
    if len(os.fsencode(text)) > MAX_SOCKET_PATH_BYTES:
        raise LiveError(f"{what} {text}: a UNIX socket path holds at most {MAX_SOCKET_PATH_BYTES} bytes "
                        f"(this one has {len(os.fsencode(text))}); choose a shorter one")
    return text


@dataclass(frozen=True)
class Derived:
    """Columns computed from the kept rows (``compute(rows) -> [m x len(columns)]``), appended to
    them: what a viewer needs but the record does not hold (the deflection in metres, say)."""

    columns: tuple[str, ...]
    compute: Callable[[np.ndarray], np.ndarray]


class LivePublisher:
    """Decimates a writer's drained rows and sends them, never waiting. ``status``, if set, is
    called once per datagram (in the writer's thread) for counters to send along."""

    def __init__(self, path: str | Path, columns: Sequence[str], sample_rate_hz: float, *,
                 rate_hz: float = DEFAULT_RATE_HZ, meta: dict | None = None,
                 derived: Derived | None = None) -> None:
        if not (rate_hz > 0 and math.isfinite(rate_hz)):
            raise LiveError(f"live rate {rate_hz!r} Hz: expected a positive number")
        self.path = check_socket_path(path, "live view")
        self.record_columns = list(columns)
        self.derived = derived
        self.columns = self.record_columns + (list(derived.columns) if derived else [])
        self.sample_rate_hz = float(sample_rate_hz)
        self.decimation = max(1, math.ceil(self.sample_rate_hz / rate_hz))
        # a drain that brings more (the writer was held up) sends its newest second only
        self.max_rows = max(1, math.ceil(self.sample_rate_hz / self.decimation))
        self._rows_per_datagram = max(1, (MAX_DATAGRAM_BYTES - 8192) // (8 * len(self.columns)))
        self._i_flags = self.record_columns.index("flags") if "flags" in self.record_columns else None
        self._meta = dict(meta or {})
        self.status: Callable[[], dict] | None = None
        self.sequence = 0           # datagrams sent or dropped
        self.sent = 0
        self.dropped = 0
        self.last_error = ""        # why the last datagram was dropped
        self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._socket.setblocking(False)
        self.begin_run()

    def begin_run(self, **meta) -> None:
        """A new run (its rows count from 0 again): its description, over the publisher's."""
        self._flags_carry = 0
        self._last_kept = -1            # the index of the last row kept
        run = {**self._meta, **meta, "columns": self.columns, "sample_rate_hz": self.sample_rate_hz,
               "decimation": self.decimation, "run_id": f"{os.getpid()}-{time.time_ns()}"}
        self._run_json = json.dumps(run)

    def publish(self, chunks: Sequence[np.ndarray], first_index: int, final: bool = False) -> None:
        """Rows ``first_index``, ``first_index + 1``, ... of the run (``chunks`` in order, as the
        writer drained them): keep one in ``decimation`` and send them. The ``final`` drain also
        sends the run's last row (its final state)."""
        n = sum(len(c) for c in chunks)
        if n == 0:
            return
        block = chunks[0] if len(chunks) == 1 else np.concatenate(chunks)
        k = self.decimation
        picks = np.arange((k - 1 - first_index) % k, n, k)
        if final and (not len(picks) or picks[-1] != n - 1) and first_index + n - 1 != self._last_kept:
            picks = np.append(picks, n - 1)
        if len(picks):
            self._last_kept = first_index + int(picks[-1])
        kept = block[picks]
        if self._i_flags is not None:
            flags = block[:, self._i_flags].astype(np.int64)
            starts = np.concatenate(([0], picks + 1))
            ors = np.bitwise_or.reduceat(flags, starts[starts < n])
            if len(picks):
                kept[:, self._i_flags] = ors[:len(picks)]
                kept[0, self._i_flags] = int(ors[0]) | self._flags_carry
                self._flags_carry = int(ors[len(picks)]) if len(ors) > len(picks) else 0
            else:
                self._flags_carry |= int(ors[0])
        if not len(kept):
            return
        kept = kept[-self.max_rows:]
        if self.derived is not None:
            kept = np.hstack([kept, self.derived.compute(kept)])
        for start in range(0, len(kept), self._rows_per_datagram):
            self._send(kept[start:start + self._rows_per_datagram])

    def _send(self, rows: np.ndarray) -> None:
        status = dict(self.status()) if self.status is not None else {}
        status["live_dropped"] = self.dropped
        header = (f'{{"sequence":{self.sequence},"rows":{len(rows)},"status":{json.dumps(status)},'
                  f'"run":{self._run_json}}}').encode()
        self.sequence += 1
        data = b"".join((MAGIC, _LENGTH.pack(len(header)), header, rows.astype("<f8").tobytes()))
        try:
            self._socket.sendto(data, self.path)
        except OSError as exc:      # nobody listens (ENOENT, ECONNREFUSED), the viewer is behind (EAGAIN)
            self.dropped += 1
            self.last_error = exc.strerror or str(exc)
        else:
            self.sent += 1

    def close(self) -> None:
        self._socket.close()


def decode(datagram: bytes) -> tuple[dict, np.ndarray]:
    """(header, rows [m x columns]) of one datagram; ``LiveError`` names what is wrong with it."""
    if not datagram.startswith(MAGIC) or len(datagram) < len(MAGIC) + _LENGTH.size:
        raise LiveError("not a beamctl live datagram")
    start = len(MAGIC) + _LENGTH.size
    (length,) = _LENGTH.unpack_from(datagram, len(MAGIC))
    try:
        header = json.loads(datagram[start:start + length])
        columns = header["run"]["columns"]
        m = int(header["rows"])
    except (ValueError, KeyError, TypeError):
        raise LiveError("damaged live datagram header") from None
    body = datagram[start + length:]
    if not columns or len(body) != 8 * m * len(columns):
        raise LiveError(f"live datagram: {len(body)} bytes of rows, expected {m} rows of "
                        f"{len(columns)} columns")
    return header, np.frombuffer(body, dtype="<f8").reshape(m, len(columns)).astype(float)
