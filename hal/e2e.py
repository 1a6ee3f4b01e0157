"""End-to-end protection of the data frames: CRC-8/SAE-J1850 and the alive counter.

Every data frame of the contract (``DAQ_Strains``, ``DAQ_Load``, ``CTRL_Voltages``,
``CTRL_Status``) carries a ``crc`` byte and a ``sequence`` counter (hal/beamctl.dbc).

CRC: CRC-8/SAE-J1850 (polynomial 0x1D, initial value 0xFF, final XOR 0xFF, not reflected;
check value 0x4B over the ASCII bytes "123456789"), computed over the low byte of the frame's
identifier followed by the frame's data bytes in order, the CRC byte itself left out. The
identifier in the CRC makes a frame that arrives under another identifier (a bit error in the
arbitration field, a wrong gateway) fail its check.

Counter: the receiver keeps the counter of the last frame it accepted. A frame whose counter is
1 to ``modulus/2 - 1`` ahead is new (the difference minus one is the number of frames missed in
between); equal is a repeat; further ahead counts as behind (an old frame overtaken by newer
ones, since a forward jump of half the counter's span is not told apart from a backward one).
Repeats and old frames never reach the receiver's user. After ``resync_s`` of time without an
accepted frame the counter's position is unknown (it wrapped, or the sender restarted), and the
next frame with a good CRC is accepted whatever its counter.
"""

from __future__ import annotations

CRC8_POLYNOMIAL = 0x1D
CRC8_INIT = 0xFF
CRC8_XOR_OUT = 0xFF


def _table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ CRC8_POLYNOMIAL) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


CRC8_TABLE = _table()


def crc8_sae_j1850(data: bytes | bytearray, first: int | None = None) -> int:
    """CRC-8/SAE-J1850 of ``first`` (one byte, if given) followed by ``data``."""
    table = CRC8_TABLE
    crc = CRC8_INIT
    if first is not None:
        crc = table[crc ^ (first & 0xFF)]
    for b in data:
        crc = table[crc ^ b]
    return crc ^ CRC8_XOR_OUT


def frame_crc(frame_id: int, data: bytes | bytearray, crc_byte: int) -> int:
    """The CRC a frame with identifier ``frame_id`` carries in byte ``crc_byte`` of ``data``:
    over the identifier's low byte and every data byte but that one."""
    table = CRC8_TABLE
    crc = table[CRC8_INIT ^ (frame_id & 0xFF)]
    for i, b in enumerate(data):
        if i != crc_byte:
            crc = table[crc ^ b]
    return crc ^ CRC8_XOR_OUT


# what a received counter is, relative to the last accepted one
NEW, REPEATED, BEHIND = 0, 1, 2


class AliveCounter:
    """The receiver's side of a rolling counter of ``modulus`` values (see the module)."""

    __slots__ = ("modulus", "resync_s", "last", "last_time", "missed", "gaps", "repeated", "behind",
                 "resyncs")

    def __init__(self, modulus: int = 256, resync_s: float = 0.0) -> None:
        self.modulus = int(modulus)
        self.resync_s = float(resync_s)
        self.reset()

    def reset(self) -> None:
        self.last = None
        self.last_time = 0.0
        self.missed = 0          # frames skipped by forward jumps (never received or dropped)
        self.gaps = 0            # forward jumps
        self.repeated = 0        # frames whose counter equals the last accepted one
        self.behind = 0          # frames older than the last accepted one
        self.resyncs = 0         # frames accepted after ``resync_s`` without one

    def accept(self, counter: int, time_s: float) -> int:
        """Classify a frame with a good CRC received at ``time_s``: NEW (and remember it),
        REPEATED or BEHIND (counted; the frame must be dropped)."""
        last = self.last
        if last is None:
            self.last, self.last_time = counter, time_s
            return NEW
        if self.resync_s and time_s - self.last_time > self.resync_s:
            self.resyncs += 1
            self.last, self.last_time = counter, time_s
            return NEW
        delta = (counter - last) % self.modulus
        if delta == 0:
            self.repeated += 1
            return REPEATED
        if delta >= self.modulus // 2:
            self.behind += 1
            return BEHIND
        if delta > 1:
            self.gaps += 1
            self.missed += delta - 1
        self.last, self.last_time = counter, time_s
        return NEW
