"""End-to-end protection of the data frames: CRC-8/SAE-J1850 over a Data ID, and the alive counter.

Every data frame of the contract (``DAQ_Strains``, ``DAQ_Load``, ``CTRL_Voltages``,
``CTRL_Status``) carries a ``crc`` byte and a ``sequence`` counter (hal/beamctl.dbc). The
arithmetic is compiled (hal/frames.py); this module says what it does and wraps it for callers
outside the per-frame path.

CRC: CRC-8/SAE-J1850 (polynomial 0x1D, initial value 0xFF, final XOR 0xFF, not reflected;
check value 0x4B over the ASCII bytes "123456789"), computed over the message's 16-bit Data ID
(the DBC attribute ``DataID``: its low byte, then its high byte), then the frame's data bytes in
order, the CRC byte itself left out (as AUTOSAR E2E profile 1 with both bytes of the Data ID).
The Data ID names the message, not its identifier's low byte, which 0x000, 0x100 and 0x200
share: a frame that arrives under another message's identifier (a bit error in the arbitration
field, a wrong gateway) fails its check.

Counter: the receiver keeps the counter of the last frame it accepted and that frame's arrival
time, and knows the sender's frame period (strains: one sample period; load: ``SampleDivisor``
periods). With ``delta`` the new counter minus that one, modulo the counter's span:

- ``delta == 0``: a repeat, dropped (``repeated``);
- ``1 <= delta <= elapsed + JITTER_PERIODS``, with ``elapsed`` the frame periods between the two
  arrivals, and at most ``modulus/2 - 1``: new, accepted; ``delta - 1`` frames were skipped (lost
  or dropped; ``skipped``, summed in ``missed``). A frame cannot be further ahead than the frames
  the sender can have sent since: the allowance of ``JITTER_PERIODS`` (2) takes the jitter of the
  time stamps, and frames queued in a burst (they arrive together, in order);
- further ahead, up to ``modulus/2 - 1``: implausible, dropped (``implausible``): a frame from
  another time, e.g. one replayed 200 samples later whose 8-bit counter looks 56 ahead;
- ``modulus/2`` ahead or more: behind, an old or overtaken frame, dropped (``behind``).

A refused frame never locks the stream out: when ``SYNC_FRAMES`` (3) frames refused as behind
or implausible follow each other by +1, they are a consistent new stream (the sender restarted,
or its counter moved on while its frames were lost) and the receiver resynchronises to the last
of them, which is accepted (``resyncs``; it skipped none, as far as the counter tells). An
accepted frame ends such a run; a repeat leaves it as it is. The first frame after a reset is
accepted as it comes. After a silence of half the counter's span or more the counter may have
wrapped: a jump is then the smallest one consistent with it (the arrival times tell how long the
silence was). There is no resynchronisation by time alone: a frame that arrives after a long
silence is judged by its counter like any other.
"""

from __future__ import annotations

import numpy as np

from beamctl.hal import frames
from beamctl.hal.frames import BEHIND, IMPLAUSIBLE, NEW, REPEATED, RESYNC

CRC8_POLYNOMIAL = frames.CRC8_POLYNOMIAL
CRC8_INIT = frames.CRC8_INIT
CRC8_XOR_OUT = frames.CRC8_XOR_OUT
JITTER_PERIODS = 2      # a forward jump may exceed the elapsed frame periods by this many
SYNC_FRAMES = 3         # refused frames in a row, each one ahead of the previous, that resynchronise
ACCEPTED = (NEW, RESYNC)


def _bytes(data: bytes | bytearray | memoryview) -> np.ndarray:
    """A writable uint8 array of ``data`` (the compiled functions take nothing else)."""
    return np.frombuffer(data if isinstance(data, bytearray) else bytearray(data), dtype=np.uint8)


def crc8_sae_j1850(data: bytes | bytearray) -> int:
    """CRC-8/SAE-J1850 of ``data``."""
    return int(frames.crc8(_bytes(data), len(data)))


def frame_crc(data_id: int, data: bytes | bytearray, crc_byte: int) -> int:
    """The CRC a frame of the message with Data ID ``data_id`` carries in byte ``crc_byte`` of
    ``data``: over the Data ID's low byte, its high byte, and every data byte but that one."""
    return int(frames.frame_crc(int(data_id), _bytes(data), len(data), int(crc_byte)))


class AliveCounter:
    """The receiver's side of a rolling counter of ``modulus`` values sent every ``period_s``
    (see the module). ``state``: the (ints, floats) arrays to keep it in (views into a larger
    state, as the CAN backend's), else its own."""

    def __init__(self, modulus: int = 256, period_s: float = 1.0, jitter_periods: int = JITTER_PERIODS,
                 sync_frames: int = SYNC_FRAMES, state: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        modulus, period_s = int(modulus), float(period_s)
        if modulus < 4 or modulus & (modulus - 1):
            raise ValueError(f"alive counter of {modulus} values: expected a power of two, at least 4")
        if not period_s > 0:
            raise ValueError(f"alive counter period {period_s!r} s: expected a positive time")
        if jitter_periods < 0 or sync_frames < 1:
            raise ValueError(f"alive counter: jitter {jitter_periods} periods, {sync_frames} frames to "
                             f"resynchronise; expected at least 0 and 1")
        if state is None:
            state = (np.zeros(frames.A_INTS, dtype=np.int64), np.zeros(frames.A_FLOATS))
        self._k, self._f = state
        if self._k.shape != (frames.A_INTS,) or self._f.shape != (frames.A_FLOATS,):
            raise ValueError("alive counter state: wrong shape")
        self._k[frames.A_MODULUS] = modulus
        self._k[frames.A_JITTER] = int(jitter_periods)
        self._k[frames.A_SYNC] = int(sync_frames)
        self._f[frames.AF_PERIOD] = period_s
        self.reset()

    def reset(self) -> None:
        """Forget the stream (the next frame is accepted as it comes) and zero the counts."""
        self._k[frames.A_LAST:] = 0
        self._k[frames.A_LAST] = -1
        self._f[frames.AF_LAST_TIME] = 0.0

    def accept(self, counter: int, time_s: float) -> int:
        """Classify a frame with a good CRC and counter ``counter`` that arrived at ``time_s``:
        NEW or RESYNC (accepted and remembered; ``skipped`` tells the frames skipped), REPEATED,
        BEHIND or IMPLAUSIBLE (counted; the frame must be dropped)."""
        return int(frames.window(self._k, self._f, int(counter), float(time_s)))

    modulus = property(lambda self: int(self._k[frames.A_MODULUS]))
    period_s = property(lambda self: float(self._f[frames.AF_PERIOD]))
    last = property(lambda self: None if self._k[frames.A_LAST] < 0 else int(self._k[frames.A_LAST]),
                    doc="the counter of the last accepted frame (None: none since the reset)")
    skipped = property(lambda self: int(self._k[frames.A_SKIPPED]),
                       doc="counter values skipped by the last accepted frame (0 in order, after a resync)")
    gaps = property(lambda self: int(self._k[frames.A_GAPS]), doc="forward jumps accepted")
    missed = property(lambda self: int(self._k[frames.A_MISSED]), doc="counter values skipped by them")
    repeated = property(lambda self: int(self._k[frames.A_REPEATED]), doc="repeats dropped")
    behind = property(lambda self: int(self._k[frames.A_BEHIND]), doc="old or overtaken frames dropped")
    implausible = property(lambda self: int(self._k[frames.A_IMPLAUSIBLE]),
                           doc="frames dropped as further ahead than the elapsed time allows")
    resyncs = property(lambda self: int(self._k[frames.A_RESYNCS]), doc="resynchronisations to a new stream")


__all__ = ["ACCEPTED", "BEHIND", "IMPLAUSIBLE", "JITTER_PERIODS", "NEW", "REPEATED", "RESYNC", "SYNC_FRAMES",
           "AliveCounter", "crc8_sae_j1850", "frame_crc"]
