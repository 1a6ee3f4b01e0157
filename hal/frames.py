"""The compiled per-frame arithmetic of the CAN contract: one implementation, numba.

Everything the controller does per frame is here, compiled with ``numba.njit(cache=True,
nogil=True)``: the CRC (CRC-8/SAE-J1850 over a message's Data ID and its data bytes), the
validation of a received frame (identifier format, remote frame, length, CRC, DBC ranges), the
decoding of its signals into a preallocated float array, the alive counter's window
(hal/e2e.py), the CAN backend's handling of a received frame (hal/can_backend.py: counters, the
latest load value, the measured rate, the sample) and the encoding of its voltage frame into a
preallocated byte buffer. Nothing here creates a Python object per frame.

The arithmetic is driven by plans, integer and float arrays derived once from the DBC
(hal/dbc.py builds them): one row per message, a header (``P_*``) and per signal its start bit,
length and signedness (ints) and its scale, offset, minimum and maximum (floats). The backend's
configuration and state are two arrays as well (``K_*`` ints, ``F_*`` floats), which also hold
a copy of the contract's plans and the latest sample's strains, so that its per-frame calls take
four arguments (each argument costs time in every call); the alive counter's state is a block
of each (``A_*``, ``AF_*``). Classic frames (up to 8 bytes) are read and written as one 64-bit
word; longer ones (CAN FD) bit field by bit field. Every layout, flag bit and code is passed in
or defined in this file, which is the one file of compiled code: numba's disk cache is
invalidated by a change of the file that defines a function, not of the files it calls into, so
a compiled function here never uses anything compiled elsewhere.

The entry points (the names without a leading underscore) have explicit signatures: they are
compiled, or loaded from numba's cache, when this module is imported, and a call with other
argument types is a TypeError, never a compilation in the middle of a run. Plans and states are
checked where they are built (hal/dbc.py, hal/can_backend.py): every index in them lies inside
the arrays the functions are given, and the functions check the lengths that arrive per frame.
The plain-Python callers are ``FrameCodec`` (hal/dbc.py), ``crc8_sae_j1850``, ``frame_crc`` and
``AliveCounter`` (hal/e2e.py) and ``CanBackend``.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import types as nt

# -- CRC-8/SAE-J1850 -------------------------------------------------------------------------------------
CRC8_POLYNOMIAL = 0x1D
CRC8_INIT = 0xFF
CRC8_XOR_OUT = 0xFF


def _crc_table() -> np.ndarray:
    table = np.zeros(256, dtype=np.uint8)
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ CRC8_POLYNOMIAL) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table[byte] = crc
    return table


CRC8_TABLE = _crc_table()          # a global array: numba compiles it in as a constant

# -- a message's plan: header slots, then three ints / four floats per signal -----------------------------
P_ID = 0            # frame identifier
P_LENGTH = 1        # data bytes
P_CRC_BYTE = 2      # the byte that carries the CRC (-1: none)
P_CRC_SIGNAL = 3    # the index of the crc signal (-1: none)
P_DATA_ID = 4       # the 16-bit Data ID the CRC covers
P_SIGNALS = 5       # number of signals
P_SEQUENCE = 6      # the index of the sequence signal (-1: none)
P_FIRST = 8         # signal k: start bit at P_FIRST + 3k, length next, signed (0/1) next
SIGNAL_INTS = 3
SIGNAL_FLOATS = 4   # signal k: scale at 4k, offset, minimum, maximum
MAX_SIGNAL_BITS = 62

# -- frame flags (the backend's, and the local bus's datagram flags are mapped onto them) ------------------
EXTENDED_ID = 1
REMOTE_FRAME = 2
ERROR_FRAME = 4

# -- why a frame is refused (``validate``); the names are the backend's counters ---------------------------
R_OK, R_EXTENDED, R_REMOTE, R_LENGTH, R_CRC, R_RANGE = 0, 1, 2, 3, 4, 5
REJECT_NAMES = (None, "extended_ids", "remote_frames", "wrong_length", "crc_errors", "out_of_range")

# -- the alive counter's state: ints, then floats ------------------------------------------------------------
A_MODULUS = 0       # counter values (a power of two)
A_JITTER = 1        # periods a forward jump may exceed the periods elapsed by
A_SYNC = 2          # consecutive frames, each one ahead of the previous, that resynchronise
A_LAST = 3          # the counter of the last accepted frame (-1: none yet)
A_CANDIDATE = 4     # the counter of the last refused frame (a new stream's candidate)
A_RUN = 5           # refused frames in a row, each one ahead of the previous
A_SKIPPED = 6       # counter values skipped by the last accepted frame (its jump minus one)
A_GAPS = 7          # forward jumps accepted
A_MISSED = 8        # counter values skipped by them
A_REPEATED = 9      # frames refused as repeats
A_BEHIND = 10       # frames refused as behind (1 to modulus/2 back)
A_IMPLAUSIBLE = 11  # frames refused as further ahead than the elapsed time allows
A_RESYNCS = 12      # resynchronisations to a new stream
A_INTS = 13
AF_PERIOD = 0       # s, the sender's frame period
AF_LAST_TIME = 1    # s, arrival of the last accepted frame
A_FLOATS = 2

# what ``window`` makes of a frame: accepted (NEW, RESYNC) or dropped (the rest)
NEW, RESYNC, REPEATED, BEHIND, IMPLAUSIBLE = 0, 1, 2, 3, 4

# -- the CAN backend's state: counters first (in COUNTER_NAMES order), then configuration and state ----------
COUNTER_NAMES = ("frames_in", "frames_out", "extended_ids", "remote_frames", "unknown_ids", "wrong_length",
                 "crc_errors", "out_of_range", "error_frames", "bus_off", "backlog_discarded",
                 "unanswered_writes")
(C_FRAMES_IN, C_FRAMES_OUT, C_EXTENDED, C_REMOTE, C_UNKNOWN, C_WRONG_LENGTH, C_CRC, C_RANGE, C_ERROR_FRAMES,
 C_BUS_OFF, C_BACKLOG, C_UNANSWERED) = range(len(COUNTER_NAMES))
K_STRAINS = 12          # plan row of DAQ_Strains
K_LOAD = 13             # of DAQ_Load
K_VOLTAGES = 14         # of CTRL_Voltages
K_STATUS = 15           # of CTRL_Status
K_LOAD_INDEX = 16       # the axial_load signal's index in DAQ_Load
K_N_STRAINS = 17        # strains per sample (4)
K_STRAIN_ORDER = 18     # their signals' indices in DAQ_Strains (K_N_STRAINS slots)
K_N_VOLTAGES = 22       # voltages per answer (6)
K_VOLTAGE_ORDER = 23    # their signals' indices in CTRL_Voltages (K_N_VOLTAGES slots)
K_BUSOFF_MASK = 29      # the error frame identifier bit of bus-off
K_LOAD_SILENCE = 30     # samples a load value may be used for
K_RATE_WINDOW = 31      # strain frames per measurement of the rate
K_PENDING = 32          # a delivered sample waits for its answer (0/1)
K_ANSWER_SEQ = 33       # its sequence
K_HAVE_LOAD = 34        # a load value has arrived (0/1)
K_SINCE_LOAD = 35       # samples delivered since
K_DISCARDING = 36       # taking a backlog: no rate measurement (0/1)
K_RATE_COUNT = 37       # strain frames in the current rate window
K_VOLTAGE_FRAMES = 38   # voltage frames encoded
K_STATUS_DIVISOR = 39   # a status frame every this many voltage frames
K_RAW_FLAGS = 40        # a local-bus datagram: offsets of its flags byte,
K_RAW_DLC = 41          # DLC byte,
K_RAW_LENGTH = 42       # data length byte,
K_RAW_ID = 43           # identifier (4 bytes, little-endian),
K_RAW_TIME = 44         # send time (8 bytes, little-endian double),
K_RAW_DATA = 45         # data;
K_RAW_EXTENDED = 46     # and the bits of its flags byte: extended identifier,
K_RAW_REMOTE = 47       # remote frame,
K_RAW_ERROR = 48        # error frame
K_DELIVERED = 49        # a sample has been delivered since the reset (0/1)
K_TX_OFFSET = 50        # where the voltage frame's data go in the send buffer
K_PLAN_WIDTH = 51       # ints per message in the plans below
K_FPLAN_WIDTH = 52      # floats per message in the float plans
K_FPLANS = 53           # where the float plans start in the float state
K_SEQUENCE = 56         # the strains' alive counter (A_INTS slots)
K_LOAD_SEQUENCE = K_SEQUENCE + A_INTS      # the load's
K_PLANS = K_LOAD_SEQUENCE + A_INTS         # the contract's plans, one row of K_PLAN_WIDTH per message
F_ARRIVAL = 0           # s, arrival of the pending sample
F_LOAD = 1              # N, the latest load value
F_RATE_START = 2        # s, start of the rate window (NaN: none)
F_RATE = 3              # Hz, the measured rate (NaN: not yet)
F_RATE_TOLERANCE = 4    # fraction the rate may be off by (0: not checked)
F_SAMPLE_RATE = 5       # Hz, the rate the gains are designed for
F_STAMP_WINDOW = 6      # s, a bus time stamp this recent is the arrival time
F_SCRATCH = 7           # one double's bytes (a datagram's time stamp)
F_SEQUENCE = 8          # the strains' alive counter (A_FLOATS slots)
F_LOAD_SEQUENCE = F_SEQUENCE + A_FLOATS    # the load's
F_STRAINS = F_LOAD_SEQUENCE + A_FLOATS     # the latest sample's strains (K_N_STRAINS slots; the
                                           # backend's Sample.strains is a view of them)
F_MAX_STRAINS = 8
F_VALUES = F_STRAINS + F_MAX_STRAINS       # decoded or to-be-encoded signal values (one per signal),
                                           # then the float plans (at K_FPLANS)

# what ``take_frame`` / ``take_record`` make of a frame
T_NONE = 0          # nothing for the reader (dropped and counted, a load value, an own frame)
T_SAMPLE = 1        # a complete sample
T_BUS_OFF = 2       # a bus-off error frame
T_LOAD_STALE = 3    # a sample whose load value is too old (K_SINCE_LOAD samples)
T_RATE = 4          # the measured rate (F_RATE) is off the design rate
# what ``answer`` makes of a write (codes above 0: the signal index + 1 of a value out of range)
W_SENT = 0
W_NOTHING = -1      # no sample waits for an answer
W_SHAPE = -2        # not one voltage per signal


def _jit(signature=None):
    """numba.njit(cache=True, nogil=True), compiled at once for ``signature``; where no cache can
    be written or read (a read-only install without a user cache), compiled per process."""
    def decorate(function):
        try:
            if signature is None:
                return numba.njit(cache=True, nogil=True)(function)
            return numba.njit(signature, cache=True, nogil=True)(function)
        except RuntimeError:          # "cannot cache function ...: no locator available"
            if signature is None:
                return numba.njit(nogil=True)(function)
            return numba.njit(signature, nogil=True)(function)
    return decorate


U8 = nt.Array(nt.uint8, 1, "C")
I64 = nt.Array(nt.int64, 1, "C")
F64 = nt.Array(nt.float64, 1, "C")
F64_ANY = nt.Array(nt.float64, 1, "A")
TAKE_RESULT = nt.Tuple((nt.int64, nt.int64, nt.int64, nt.float64, nt.float64))
ANSWER_RESULT = nt.Tuple((nt.int64, nt.float64, nt.int64))


# -- CRC ---------------------------------------------------------------------------------------------------
@_jit(nt.int64(U8, nt.int64))
def crc8(data, n):
    """CRC-8/SAE-J1850 of ``data[:n]``."""
    crc = np.int64(CRC8_INIT)
    for i in range(min(n, data.shape[0])):
        crc = np.int64(CRC8_TABLE[crc ^ np.int64(data[i])])
    return crc ^ CRC8_XOR_OUT


@_jit()
def _frame_crc(data_id, data, offset, n, crc_byte):
    crc = np.int64(CRC8_TABLE[CRC8_INIT ^ (data_id & 0xFF)])
    crc = np.int64(CRC8_TABLE[crc ^ ((data_id >> 8) & 0xFF)])
    for i in range(n):
        if i != crc_byte:
            crc = np.int64(CRC8_TABLE[crc ^ np.int64(data[offset + i])])
    return crc ^ CRC8_XOR_OUT


@_jit(nt.int64(nt.int64, U8, nt.int64, nt.int64))
def frame_crc(data_id, data, n, crc_byte):
    """The CRC of a frame of Data ID ``data_id``: over the Data ID's low byte, its high byte,
    then ``data[:n]`` without byte ``crc_byte``."""
    return _frame_crc(data_id, data, 0, min(n, data.shape[0]), crc_byte)


# -- signals -------------------------------------------------------------------------------------------------
@_jit()
def _raw(data, offset, n, start, length):
    """The unsigned raw value of a little-endian signal (bytes at or beyond ``n`` read as 0)."""
    value = 0
    got = 0
    bit = start
    while got < length:
        i = bit >> 3
        shift = bit & 7
        take = min(8 - shift, length - got)
        byte = np.int64(data[offset + i]) if i < n else np.int64(0)
        value |= ((byte >> shift) & ((1 << take) - 1)) << got
        got += take
        bit += take
    return value


@_jit()
def _word(data, offset, n):
    """Up to eight bytes as one little-endian unsigned word."""
    word = np.uint64(0)
    for i in range(n):
        word |= np.uint64(data[offset + i]) << np.uint64(8 * i)
    return word


@_jit()
def _decode(plan, fplan, data, offset, n, out, out_offset):
    """The physical values of every signal into ``out[out_offset:]``; False when one lies
    outside its DBC range."""
    ok = True
    short = n <= 8                                 # a classic frame's bytes fit one word
    word = _word(data, offset, n) if short else np.uint64(0)
    for k in range(plan[P_SIGNALS]):
        p = P_FIRST + SIGNAL_INTS * k
        length = plan[p + 1]
        if short:
            raw = np.int64((word >> np.uint64(plan[p])) & np.uint64((1 << length) - 1))
        else:
            raw = _raw(data, offset, n, plan[p], length)
        if plan[p + 2] and raw & (1 << (length - 1)):
            raw -= 1 << length
        q = SIGNAL_FLOATS * k
        value = raw * fplan[q] + fplan[q + 1]
        if value < fplan[q + 2] or value > fplan[q + 3]:
            ok = False
        out[out_offset + k] = value
    return ok


@_jit()
def _validate(plan, fplan, flags, dlc, data, offset, n, out, out_offset):
    """R_OK and the values decoded into ``out[out_offset:]``, or why the frame is refused."""
    if flags & EXTENDED_ID:
        return R_EXTENDED
    if flags & REMOTE_FRAME:
        return R_REMOTE
    length = plan[P_LENGTH]
    if dlc != length or n != length:
        return R_LENGTH
    crc_byte = plan[P_CRC_BYTE]
    if crc_byte >= 0 and data[offset + crc_byte] != _frame_crc(plan[P_DATA_ID], data, offset, n, crc_byte):
        return R_CRC
    if not _decode(plan, fplan, data, offset, n, out, out_offset):
        return R_RANGE
    return R_OK


@_jit()
def _encode(plan, fplan, values, values_offset, buf, offset):
    """The frame's data bytes into ``buf[offset:]``, the CRC computed into its byte (whatever
    value the crc signal has): 0, or the index + 1 of the first signal out of its DBC range."""
    length = plan[P_LENGTH]
    for i in range(length):
        buf[offset + i] = 0
    short = length <= 8                            # a classic frame's bytes fit one word
    word = np.uint64(0)
    crc_signal = plan[P_CRC_SIGNAL]
    for k in range(plan[P_SIGNALS]):
        if k == crc_signal:
            continue
        q = SIGNAL_FLOATS * k
        value = values[values_offset + k]
        if not (fplan[q + 2] <= value <= fplan[q + 3]):
            return k + 1
        scaled = np.rint((value - fplan[q + 1]) / fplan[q])
        if not abs(scaled) < 4.0e18:           # an unbounded DBC range: no integer holds it
            return k + 1
        raw = np.int64(scaled)
        p = P_FIRST + SIGNAL_INTS * k
        length_bits = plan[p + 1]
        if short:
            word |= (np.uint64(raw) & np.uint64((1 << length_bits) - 1)) << np.uint64(plan[p])
            continue
        got = 0
        bit = plan[p]
        while got < length_bits:
            i = offset + (bit >> 3)
            shift = bit & 7
            take = min(8 - shift, length_bits - got)
            chunk = (raw >> got) & ((1 << take) - 1)
            buf[i] = buf[i] | (chunk << shift)
            got += take
            bit += take
    if short:
        for i in range(length):
            buf[offset + i] = (word >> np.uint64(8 * i)) & np.uint64(0xFF)
    crc_byte = plan[P_CRC_BYTE]
    if crc_byte >= 0:
        buf[offset + crc_byte] = _frame_crc(plan[P_DATA_ID], buf, offset, length, crc_byte)
    return 0


@_jit(nt.boolean(I64, F64, U8, nt.int64, F64))
def decode(plan, fplan, data, n, out):
    """``_decode`` of ``data[:n]`` (bytes beyond read as 0) into ``out``."""
    if out.shape[0] < plan[P_SIGNALS]:
        return False
    return _decode(plan, fplan, data, 0, min(n, data.shape[0]), out, 0)


@_jit(nt.int64(I64, F64, nt.int64, nt.int64, U8, nt.int64, F64))
def validate(plan, fplan, flags, dlc, data, n, out):
    """``_validate`` of a received frame with ``data[:n]``."""
    if out.shape[0] < plan[P_SIGNALS]:
        return R_RANGE
    return _validate(plan, fplan, flags, dlc, data, 0, min(n, data.shape[0]), out, 0)


@_jit(nt.int64(I64, F64, F64, U8))
def encode(plan, fplan, values, buf):
    """``_encode`` of ``values`` (one per signal) into ``buf``."""
    if values.shape[0] < plan[P_SIGNALS] or buf.shape[0] < plan[P_LENGTH]:
        return plan[P_SIGNALS] + 1
    return _encode(plan, fplan, values, 0, buf, 0)


# -- the alive counter's window (hal/e2e.py says what and why) -----------------------------------------------
@_jit()
def _accept(k, f, counter, time_s, skipped):
    k[A_LAST] = counter
    k[A_SKIPPED] = skipped
    k[A_RUN] = 0
    f[AF_LAST_TIME] = time_s


@_jit()
def _window(k, f, counter, time_s):
    modulus = k[A_MODULUS]
    counter = counter % modulus
    last = k[A_LAST]
    if last < 0:                                   # the first frame since the reset
        _accept(k, f, counter, time_s, 0)
        return NEW
    delta = (counter - last) % modulus
    if delta == 0:
        k[A_REPEATED] += 1
        return REPEATED
    half = modulus // 2
    if delta < half:
        elapsed = (time_s - f[AF_LAST_TIME]) / f[AF_PERIOD]
        if not elapsed > 0.0:                     # earlier, or a NaN time stamp
            elapsed = 0.0
        if delta <= elapsed + k[A_JITTER]:
            if delta > 1:
                k[A_GAPS] += 1
                k[A_MISSED] += delta - 1
            _accept(k, f, counter, time_s, delta - 1)
            return NEW
        result = IMPLAUSIBLE
    else:
        result = BEHIND
    # refused; a run of refused frames that follow each other by one is a new stream
    if k[A_RUN] > 0 and counter == (k[A_CANDIDATE] + 1) % modulus:
        k[A_RUN] += 1
    else:
        k[A_RUN] = 1
    k[A_CANDIDATE] = counter
    if k[A_RUN] >= k[A_SYNC]:
        k[A_RESYNCS] += 1
        _accept(k, f, counter, time_s, 0)
        return RESYNC
    if result == IMPLAUSIBLE:
        k[A_IMPLAUSIBLE] += 1
    else:
        k[A_BEHIND] += 1
    return result


@_jit(nt.int64(I64, F64, nt.int64, nt.float64))
def window(k, f, counter, time_s):
    """Classify a frame with a good CRC and counter ``counter``, arrived at ``time_s``: NEW or
    RESYNC (accepted: remembered, ``k[A_SKIPPED]`` the counter values skipped), REPEATED, BEHIND
    or IMPLAUSIBLE (counted; the frame must be dropped)."""
    return _window(k, f, counter, time_s)


# -- the CAN backend's frames --------------------------------------------------------------------------------
@_jit()
def _none():
    return (T_NONE, np.int64(0), np.int64(0), 0.0, 0.0)


@_jit()
def _count_reject(ks, code):
    if code == R_EXTENDED:
        ks[C_EXTENDED] += 1
    elif code == R_REMOTE:
        ks[C_REMOTE] += 1
    elif code == R_LENGTH:
        ks[C_WRONG_LENGTH] += 1
    elif code == R_CRC:
        ks[C_CRC] += 1
    elif code == R_RANGE:
        ks[C_RANGE] += 1


@_jit()
def _rate_off(ks, fs, stamp, samples):
    """Count ``samples`` of the DAQ (a strain frame and the samples its counter says were skipped
    before it: frames lost on the way do not slow the DAQ's clock) into the rate measurement;
    True when a window ends with the rate off by more than the tolerance (the rate in F_RATE)."""
    if fs[F_RATE_START] != fs[F_RATE_START]:
        fs[F_RATE_START] = stamp
        ks[K_RATE_COUNT] = 0
        return False
    ks[K_RATE_COUNT] += samples
    if ks[K_RATE_COUNT] < ks[K_RATE_WINDOW]:
        return False
    elapsed = stamp - fs[F_RATE_START]
    counted = ks[K_RATE_COUNT]
    fs[F_RATE_START] = stamp
    ks[K_RATE_COUNT] = 0
    if elapsed <= 0.0:
        return False
    rate = counted / elapsed
    fs[F_RATE] = rate
    return abs(rate / fs[F_SAMPLE_RATE] - 1.0) > fs[F_RATE_TOLERANCE]


@_jit()
def _plans(ks, fs, row):
    """The plan of message ``row`` (its ints, its floats), views of the state."""
    i = K_PLANS + row * ks[K_PLAN_WIDTH]
    f = ks[K_FPLANS] + row * ks[K_FPLAN_WIDTH]
    return ks[i:i + ks[K_PLAN_WIDTH]], fs[f:f + ks[K_FPLAN_WIDTH]]


@_jit()
def _frame_id(ks, row):
    return ks[K_PLANS + row * ks[K_PLAN_WIDTH] + P_ID]


@_jit()
def _take(flags, frame_id, dlc, data, offset, n, stamp, now, ks, fs):
    ks[C_FRAMES_IN] += 1
    if flags & ERROR_FRAME:
        ks[C_ERROR_FRAMES] += 1
        if frame_id & ks[K_BUSOFF_MASK]:
            ks[C_BUS_OFF] += 1
            return (T_BUS_OFF, np.int64(0), np.int64(0), 0.0, 0.0)
        return _none()
    if flags & EXTENDED_ID:
        ks[C_EXTENDED] += 1
        return _none()
    if flags & REMOTE_FRAME:
        ks[C_REMOTE] += 1
        return _none()
    strains_row, load_row = ks[K_STRAINS], ks[K_LOAD]
    if frame_id == _frame_id(ks, strains_row):
        row = strains_row
    elif frame_id == _frame_id(ks, load_row):
        row = load_row
    else:
        if frame_id != _frame_id(ks, ks[K_VOLTAGES]) and frame_id != _frame_id(ks, ks[K_STATUS]):
            ks[C_UNKNOWN] += 1
        return _none()
    plan, fplan = _plans(ks, fs, row)
    code = _validate(plan, fplan, 0, dlc, data, offset, n, fs, F_VALUES)
    if code != R_OK:
        _count_reject(ks, code)
        return _none()
    arrival = stamp if 0.0 <= now - stamp < fs[F_STAMP_WINDOW] else now
    seq = np.int64(fs[F_VALUES + plan[P_SEQUENCE]])
    if row == load_row:
        verdict = _window(ks[K_LOAD_SEQUENCE:K_LOAD_SEQUENCE + A_INTS],
                          fs[F_LOAD_SEQUENCE:F_LOAD_SEQUENCE + A_FLOATS], seq, arrival)
        if verdict == NEW or verdict == RESYNC:
            fs[F_LOAD] = fs[F_VALUES + ks[K_LOAD_INDEX]]
            ks[K_HAVE_LOAD] = 1
            ks[K_SINCE_LOAD] = 0
        return _none()
    verdict = _window(ks[K_SEQUENCE:K_SEQUENCE + A_INTS], fs[F_SEQUENCE:F_SEQUENCE + A_FLOATS], seq, arrival)
    if verdict != NEW and verdict != RESYNC:
        return _none()
    if verdict == RESYNC:                            # a new stream: its rate is measured afresh
        fs[F_RATE_START] = np.nan
    if (fs[F_RATE_TOLERANCE] > 0.0 and ks[K_DISCARDING] == 0
            and _rate_off(ks, fs, arrival, 1 + ks[K_SEQUENCE + A_SKIPPED])):
        return (T_RATE, seq, np.int64(0), arrival, 0.0)
    if ks[K_HAVE_LOAD] == 0:
        return _none()                               # no load value yet: not a complete sample
    ks[K_SINCE_LOAD] += 1 + ks[K_SEQUENCE + A_SKIPPED]   # samples of the DAQ's clock, lost ones too
    if ks[K_SINCE_LOAD] > ks[K_LOAD_SILENCE]:
        return (T_LOAD_STALE, seq, np.int64(0), arrival, 0.0)
    for i in range(ks[K_N_STRAINS]):
        fs[F_STRAINS + i] = fs[F_VALUES + ks[K_STRAIN_ORDER + i]]
    ks[K_ANSWER_SEQ] = seq
    ks[K_PENDING] = 1
    fs[F_ARRIVAL] = arrival
    missed = ks[K_SEQUENCE + A_SKIPPED] if ks[K_DELIVERED] else np.int64(0)
    ks[K_DELIVERED] = 1
    return (T_SAMPLE, seq, missed, arrival, fs[F_LOAD])


@_jit(TAKE_RESULT(nt.int64, nt.int64, nt.int64, U8, nt.int64, nt.float64, nt.float64, I64, F64))
def take_frame(flags, frame_id, dlc, data, n, stamp, now, ks, fs):
    """One received frame (a python-can ``Message``'s fields: ``flags`` of EXTENDED_ID,
    REMOTE_FRAME, ERROR_FRAME; ``data[:n]``; its bus time stamp), validated, counted and applied
    at ``now`` (s, the clock of the stamps): (code T_*, sequence, samples missed, arrival, load);
    the strains of a complete sample are in ``fs[F_STRAINS:]``."""
    return _take(flags, frame_id, dlc, data, 0, min(n, data.shape[0]), stamp, now, ks, fs)


@_jit(TAKE_RESULT(U8, nt.float64, I64, F64))
def take_record(record, now, ks, fs):
    """``take_frame`` of one local-bus datagram (hal/localbus.py; its layout in K_RAW_*)."""
    flags_byte = record[ks[K_RAW_FLAGS]]
    flags = 0
    if flags_byte & ks[K_RAW_EXTENDED]:
        flags |= EXTENDED_ID
    if flags_byte & ks[K_RAW_REMOTE]:
        flags |= REMOTE_FRAME
    if flags_byte & ks[K_RAW_ERROR]:
        flags |= ERROR_FRAME
    o = ks[K_RAW_ID]
    frame_id = (np.int64(record[o]) | np.int64(record[o + 1]) << 8 | np.int64(record[o + 2]) << 16
                | np.int64(record[o + 3]) << 24)
    scratch = fs.view(np.uint8)
    o = ks[K_RAW_TIME]
    for i in range(8):
        scratch[8 * F_SCRATCH + i] = record[o + i]
    offset = ks[K_RAW_DATA]
    n = np.int64(record[ks[K_RAW_LENGTH]])
    if n > record.shape[0] - offset:
        n = record.shape[0] - offset
    return _take(flags, frame_id, np.int64(record[ks[K_RAW_DLC]]), record, offset, n, fs[F_SCRATCH], now,
                 ks, fs)


@_jit(ANSWER_RESULT(F64_ANY, I64, F64, U8))
def answer(voltages, ks, fs, buf):
    """The voltage frame answering the pending sample into ``buf[ks[K_TX_OFFSET]:]``: (W_SENT,
    the sample's arrival, 1 when a status frame is due after it); (W_NOTHING, ...) when no sample
    waits for an answer (counted), (W_SHAPE, ...) for a wrong number of voltages, (k + 1, ...)
    when signal k is out of its DBC range. The frame counts as sent: the caller sends it."""
    if ks[K_PENDING] == 0:
        ks[C_UNANSWERED] += 1
        return (W_NOTHING, 0.0, np.int64(0))
    count = ks[K_N_VOLTAGES]
    if voltages.shape[0] != count:
        return (W_SHAPE, 0.0, np.int64(0))
    plan, fplan = _plans(ks, fs, ks[K_VOLTAGES])
    offset = ks[K_TX_OFFSET]
    if buf.shape[0] < offset + plan[P_LENGTH]:
        return (W_SHAPE, 0.0, np.int64(0))
    for i in range(plan[P_SIGNALS]):
        fs[F_VALUES + i] = 0.0
    for i in range(count):
        fs[F_VALUES + ks[K_VOLTAGE_ORDER + i]] = voltages[i]
    fs[F_VALUES + plan[P_SEQUENCE]] = ks[K_ANSWER_SEQ]
    code = _encode(plan, fplan, fs, F_VALUES, buf, offset)
    if code != 0:
        return (code, 0.0, np.int64(0))
    ks[K_PENDING] = 0
    ks[C_FRAMES_OUT] += 1
    ks[K_VOLTAGE_FRAMES] += 1
    due = np.int64(1) if ks[K_VOLTAGE_FRAMES] % ks[K_STATUS_DIVISOR] == 0 else np.int64(0)
    return (W_SENT, fs[F_ARRIVAL], due)
