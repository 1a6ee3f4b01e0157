"""The DBC contract with the DAQ firmware, loaded once and compiled into codecs.

Each message becomes a ``FrameCodec``: its plan, integer and float arrays derived from the DBC
signal definitions (start bit, length, signedness; scale, offset, range) and its Data ID, which
the compiled arithmetic of hal/frames.py runs on (numba; no DBC parsing, no dict building, no
Python object per frame). Every message of the contract carries end-to-end protection
(hal/e2e.py): the DBC gives each a 16-bit ``DataID`` of its own, ``encode`` fills the ``crc``
byte, ``crc_ok`` checks it. ``FrameCodec``'s methods are the Python face of that one compiled
implementation (the CAN backend calls it directly, hal/can_backend.py). Tests check the codecs
against cantools on random values.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import cantools
import numpy as np

from beamctl.hal import frames
from beamctl.hal.base import HalConfigurationError
from beamctl.hal.e2e import _bytes

STRAIN_SIGNALS = ("strain_y1", "strain_z1", "strain_y2", "strain_z2")
VOLTAGE_SIGNALS = ("voltage_a1", "voltage_a2", "voltage_a3", "voltage_b1", "voltage_b2", "voltage_b3")
MESSAGES = {
    "strains": ("DAQ_Strains", STRAIN_SIGNALS + ("sequence", "crc")),
    "load": ("DAQ_Load", ("axial_load", "sequence", "crc")),
    "voltages": ("CTRL_Voltages", VOLTAGE_SIGNALS + ("sequence", "crc")),
    "status": ("CTRL_Status", ("state", "fault", "flags", "sequence", "crc")),
}
DEFAULT_DBC = "beamctl.dbc"
DATA_ID_ATTRIBUTE = "DataID"
DATA_ID_MAX = 0xFFFF


def default_dbc_path() -> Path:
    return Path(str(resources.files("beamctl.hal") / DEFAULT_DBC))


@dataclass(frozen=True)
class SignalCodec:
    name: str
    start: int
    length: int
    signed: bool
    scale: float
    offset: float
    minimum: float
    maximum: float

    @property
    def mask(self) -> int:
        return (1 << self.length) - 1


def _whole_byte(codec_name: str, s: SignalCodec, what: str) -> None:
    if s.signed or s.scale != 1 or s.offset != 0 or (what == "crc" and (s.length != 8 or s.start % 8)):
        shape = ("one whole unsigned byte (start a multiple of 8, length 8, scale 1, offset 0)"
                 if what == "crc" else "an unsigned counter (scale 1, offset 0)")
        raise HalConfigurationError(f"DBC message {codec_name}: signal {what} must be {shape}")


class FrameCodec:
    """Encode/decode one message. ``decode_into(data, out)`` writes the physical values of
    the signals in DBC order into ``out`` (a list or a float array) and returns False when a
    value lies outside the DBC range; ``encode(values)`` returns the frame bytes (ValueError
    when out of range), with the CRC computed into the ``crc`` byte whatever value ``values``
    gives it; ``crc_ok(data)`` checks a received frame's CRC; ``reject(msg, out)`` validates a
    received python-can message. All four run the compiled arithmetic of hal/frames.py on the
    plan (``plan_int``, ``plan_float``)."""

    def __init__(self, message: cantools.database.Message) -> None:
        self.name = message.name
        self.frame_id = message.frame_id
        self.length = message.length
        self.is_extended = message.is_extended_frame
        attrs = message.dbc.attributes if message.dbc else {}
        self.attributes = {name: a.value for name, a in attrs.items()}
        self.divisor = int(self.attributes.get("SampleDivisor", 1))
        self.signals: list[SignalCodec] = []
        for s in message.signals:
            if s.byte_order != "little_endian":
                raise HalConfigurationError(f"DBC message {message.name}: signal {s.name} is big-endian; "
                                            f"the compiled codecs read little-endian (Intel) signals only")
            lo = s.minimum if s.minimum is not None else -float("inf")
            hi = s.maximum if s.maximum is not None else float("inf")
            self.signals.append(SignalCodec(s.name, s.start, s.length, s.is_signed, float(s.scale),
                                            float(s.offset), lo, hi))
        self.names = [s.name for s in self.signals]
        for s in self.signals:
            bits = frames.MAX_SIGNAL_BITS
            if not 1 <= s.length <= bits or s.start < 0 or s.start + s.length > 8 * self.length:
                raise HalConfigurationError(
                    f"DBC message {message.name}: signal {s.name} (bits {s.start}..{s.start + s.length - 1}) "
                    f"must lie within its {self.length} bytes and have 1 to {bits} bits")
            if not (s.scale != 0 and np.isfinite(s.scale) and np.isfinite(s.offset)):
                raise HalConfigurationError(f"DBC message {message.name}: signal {s.name} has scale "
                                            f"{s.scale} and offset {s.offset}; expected finite numbers, a "
                                            f"scale not 0")
        self.sequence_modulus = 0
        if "sequence" in self.names:
            sequence = self.signals[self.names.index("sequence")]
            _whole_byte(message.name, sequence, "sequence")
            self.sequence_modulus = 1 << sequence.length
        self.crc_byte = None
        self.data_id = None
        if "crc" in self.names:
            crc = self.signals[self.names.index("crc")]
            _whole_byte(message.name, crc, "crc")
            self.crc_byte = crc.start // 8
            data_id = self.attributes.get(DATA_ID_ATTRIBUTE)
            if data_id is None:
                raise HalConfigurationError(
                    f"DBC message {message.name}: no {DATA_ID_ATTRIBUTE} attribute; a message with a crc "
                    f"needs a 16-bit Data ID of its own "
                    f"(BA_ \"{DATA_ID_ATTRIBUTE}\" BO_ {message.frame_id} <0..65535>;)")
            if not (isinstance(data_id, int) and 0 <= data_id <= DATA_ID_MAX):
                raise HalConfigurationError(f"DBC message {message.name}: {DATA_ID_ATTRIBUTE} {data_id!r} "
                                            f"is not a 16-bit value (0..65535)")
            self.data_id = int(data_id)
        self.plan_int, self.plan_float = self._plan()
        self._values = np.zeros(len(self.signals))
        self._buffer = np.zeros(max(self.length, 1), dtype=np.uint8)

    def _plan(self) -> tuple[np.ndarray, np.ndarray]:
        """The plan the compiled functions run on (layout: hal/frames.py, ``P_*``)."""
        n = len(self.signals)
        ints = np.zeros(frames.P_FIRST + frames.SIGNAL_INTS * n, dtype=np.int64)
        floats = np.zeros(frames.SIGNAL_FLOATS * n)
        ints[frames.P_ID] = self.frame_id
        ints[frames.P_LENGTH] = self.length
        ints[frames.P_CRC_BYTE] = -1 if self.crc_byte is None else self.crc_byte
        ints[frames.P_CRC_SIGNAL] = self.names.index("crc") if "crc" in self.names else -1
        ints[frames.P_DATA_ID] = self.data_id or 0
        ints[frames.P_SIGNALS] = n
        ints[frames.P_SEQUENCE] = self.names.index("sequence") if "sequence" in self.names else -1
        for k, s in enumerate(self.signals):
            p, q = frames.P_FIRST + frames.SIGNAL_INTS * k, frames.SIGNAL_FLOATS * k
            ints[p:p + 3] = s.start, s.length, int(s.signed)
            floats[q:q + 4] = s.scale, s.offset, s.minimum, s.maximum
        return ints, floats

    def index(self, name: str) -> int:
        return self.names.index(name)

    def order(self, names) -> list[int]:
        """Positions of ``names`` among this message's signals (decided once, used per frame)."""
        return [self.names.index(n) for n in names]

    def _out(self, out) -> None:
        out[:len(self.signals)] = self._values.tolist()

    def decode_into(self, data: bytes | bytearray, out) -> bool:
        ok = bool(frames.decode(self.plan_int, self.plan_float, _bytes(data), len(data), self._values))
        self._out(out)
        return ok

    def reject(self, msg, out) -> str | None:
        """Validate a received frame of this message and decode it into ``out``: None when it
        is good, else the kind of fault, the name of its counter: ``extended_ids``,
        ``remote_frames``, ``wrong_length``, ``crc_errors``, ``out_of_range``."""
        flags = ((frames.EXTENDED_ID if msg.is_extended_id else 0)
                 | (frames.REMOTE_FRAME if msg.is_remote_frame else 0))
        data = msg.data
        return self.reject_data(flags, msg.dlc, _bytes(data), len(data), out)

    def reject_data(self, flags: int, dlc: int, data: np.ndarray, length: int, out) -> str | None:
        """``reject`` of a frame given as its flags (``frames.EXTENDED_ID``, ``REMOTE_FRAME``),
        DLC and the first ``length`` bytes of ``data`` (uint8)."""
        code = frames.validate(self.plan_int, self.plan_float, flags, dlc, data, length, self._values)
        if code in (frames.R_OK, frames.R_RANGE):
            self._out(out)
        return frames.REJECT_NAMES[code]

    def crc_ok(self, data: bytes | bytearray) -> bool:
        """The frame's CRC byte is right (always True for a message without one)."""
        if self.crc_byte is None:
            return True
        if len(data) <= self.crc_byte:
            return False
        crc = frames.frame_crc(self.data_id, _bytes(data), len(data), self.crc_byte)
        return data[self.crc_byte] == crc

    def encode(self, values) -> bytes:
        values = list(values)
        if len(values) != len(self.signals):
            raise ValueError(f"{self.name}: {len(values)} values for {len(self.signals)} signals")
        try:
            array = np.array(values, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{self.name}: values {values!r} are not all numbers") from None
        code = frames.encode(self.plan_int, self.plan_float, array, self._buffer)
        if code:
            s = self.signals[code - 1]
            raise ValueError(f"{self.name}.{s.name} = {values[code - 1]!r} outside the DBC range "
                             f"[{s.minimum}, {s.maximum}]")
        return self._buffer[:self.length].tobytes()


class Contract:
    """The shipped (or a configured) DBC: the four messages the HAL needs, compiled. Their plans
    are the rows of ``plan_int`` and ``plan_float`` (in ``MESSAGES`` order, ``ROWS``), which each
    codec's plan is a view of."""

    ROWS = {role: row for row, role in enumerate(MESSAGES)}

    def __init__(self, path: str | Path | None = None) -> None:
        self.path = Path(path) if path else default_dbc_path()
        try:
            db = cantools.database.load_file(str(self.path))
        except (OSError, cantools.database.UnsupportedDatabaseFormatError, ValueError) as exc:
            raise HalConfigurationError(f"DBC {self.path}: cannot load ({exc})") from None
        self.codecs: dict[str, FrameCodec] = {}
        for role, (message_name, signals) in MESSAGES.items():
            try:
                message = db.get_message_by_name(message_name)
            except KeyError:
                raise HalConfigurationError(f"DBC {self.path}: message {message_name} missing") from None
            missing = [s for s in signals if s not in [x.name for x in message.signals]]
            if missing:
                raise HalConfigurationError(f"DBC {self.path}: {message_name} lacks signals {missing}")
            if message.is_extended_frame:
                raise HalConfigurationError(f"DBC {self.path}: {message_name} has an extended (29-bit) "
                                            f"identifier; the contract uses standard 11-bit identifiers")
            try:
                self.codecs[role] = FrameCodec(message)
            except HalConfigurationError as exc:
                raise HalConfigurationError(f"DBC {self.path}: {str(exc).removeprefix('DBC ')}") from None
        seen_ids: dict[int, str] = {}
        seen_data_ids: dict[int, str] = {}
        for codec in self.codecs.values():
            if codec.frame_id in seen_ids:
                raise HalConfigurationError(f"DBC {self.path}: {codec.name} and {seen_ids[codec.frame_id]} "
                                            f"share the identifier 0x{codec.frame_id:X}")
            seen_ids[codec.frame_id] = codec.name
            if codec.data_id in seen_data_ids:
                raise HalConfigurationError(
                    f"DBC {self.path}: {codec.name} has the {DATA_ID_ATTRIBUTE} 0x{codec.data_id:04X} of "
                    f"{seen_data_ids[codec.data_id]}; each message of the contract needs a Data ID of its "
                    f"own")
            seen_data_ids[codec.data_id] = codec.name
        self.strains = self.codecs["strains"]
        self.load = self.codecs["load"]
        self.voltages = self.codecs["voltages"]
        self.status = self.codecs["status"]
        # one plan for the contract, each codec's a row of it
        codecs = [self.codecs[role] for role in MESSAGES]
        self.plan_int = np.zeros((len(codecs), max(c.plan_int.size for c in codecs)), dtype=np.int64)
        self.plan_float = np.zeros((len(codecs), max(max(c.plan_float.size for c in codecs), 1)))
        for row, codec in enumerate(codecs):
            ints, floats = codec.plan_int, codec.plan_float
            self.plan_int[row, :ints.size] = ints
            self.plan_float[row, :floats.size] = floats
            codec.plan_int = self.plan_int[row, :ints.size]
            codec.plan_float = self.plan_float[row, :floats.size]
        self.max_signals = max(len(c.signals) for c in codecs)
        # the DAQ's duty when the controller falls silent (CTRL_Voltages attributes)
        self.silence_timeout_s = float(self.voltages.attributes.get("SilenceTimeoutMs", 0)) / 1e3
        self.fallback_ramp_s = float(self.voltages.attributes.get("FallbackRampMs", 0)) / 1e3
