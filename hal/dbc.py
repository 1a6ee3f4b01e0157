"""The DBC contract with the DAQ firmware, loaded once and compiled into codecs.

Each message becomes a ``FrameCodec``: shifts, masks and scales derived from the DBC signal
definitions, so decoding a frame in the loop is integer arithmetic on one ``int`` (no DBC
parsing, no dict building). Every message of the contract carries end-to-end protection
(hal/e2e.py): ``encode`` fills its ``crc`` byte, ``crc_ok`` checks it. Tests check the codecs
against cantools on random values.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import cantools

from beamctl.hal.base import HalConfigurationError
from beamctl.hal.e2e import frame_crc

STRAIN_SIGNALS = ("strain_y1", "strain_z1", "strain_y2", "strain_z2")
VOLTAGE_SIGNALS = ("voltage_a1", "voltage_a2", "voltage_a3", "voltage_b1", "voltage_b2", "voltage_b3")
MESSAGES = {
    "strains": ("DAQ_Strains", STRAIN_SIGNALS + ("sequence", "crc")),
    "load": ("DAQ_Load", ("axial_load", "sequence", "crc")),
    "voltages": ("CTRL_Voltages", VOLTAGE_SIGNALS + ("sequence", "crc")),
    "status": ("CTRL_Status", ("state", "fault", "flags", "sequence", "crc")),
}
DEFAULT_DBC = "beamctl.dbc"


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


class FrameCodec:
    """Encode/decode one message. ``decode_into(data, out)`` writes the physical values of
    the signals in DBC order into ``out`` (a list) and returns False when a value lies outside
    the DBC range; ``encode(values)`` returns the frame bytes (ValueError when out of range),
    with the CRC computed into the ``crc`` byte whatever value ``values`` gives it;
    ``crc_ok(data)`` checks a received frame's CRC."""

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
        self.sequence_modulus = 1 << self.signals[self.names.index("sequence")].length \
            if "sequence" in self.names else 0
        self.crc_byte = None
        if "crc" in self.names:
            crc = self.signals[self.names.index("crc")]
            if crc.length != 8 or crc.start % 8 or crc.signed or crc.scale != 1 or crc.offset != 0:
                raise HalConfigurationError(f"DBC message {message.name}: signal crc must be one whole "
                                            f"unsigned byte (start a multiple of 8, length 8, scale 1)")
            self.crc_byte = crc.start // 8
            if self.crc_byte >= self.length:
                raise HalConfigurationError(f"DBC message {message.name}: crc lies outside its "
                                            f"{self.length} bytes")
        self._plan = [(s.start, s.mask, (1 << (s.length - 1)) if s.signed else 0, 1 << s.length,
                       s.scale, s.offset, s.minimum, s.maximum) for s in self.signals]

    def index(self, name: str) -> int:
        return self.names.index(name)

    def order(self, names) -> list[int]:
        """Positions of ``names`` among this message's signals (decided once, used per frame)."""
        return [self.names.index(n) for n in names]

    def decode_into(self, data: bytes | bytearray, out: list) -> bool:
        word = int.from_bytes(data, "little")
        ok = True
        for i, (start, mask, sign, span, scale, offset, lo, hi) in enumerate(self._plan):
            raw = (word >> start) & mask
            if sign and raw & sign:
                raw -= span
            value = raw * scale + offset
            if value < lo or value > hi:
                ok = False
            out[i] = value
        return ok

    def reject(self, msg, out: list) -> str | None:
        """Validate a received frame of this message and decode it into ``out``: None when it
        is good, else the kind of fault, the name of its counter: ``extended_ids``,
        ``remote_frames``, ``wrong_length``, ``crc_errors``, ``out_of_range``."""
        if msg.is_extended_id:
            return "extended_ids"
        if msg.is_remote_frame:
            return "remote_frames"
        data = msg.data
        if msg.dlc != self.length or len(data) != self.length:
            return "wrong_length"
        if not self.crc_ok(data):
            return "crc_errors"
        if not self.decode_into(data, out):
            return "out_of_range"
        return None

    def crc_ok(self, data: bytes | bytearray) -> bool:
        """The frame's CRC byte is right (always True for a message without one)."""
        if self.crc_byte is None:
            return True
        return data[self.crc_byte] == frame_crc(self.frame_id, data, self.crc_byte)

    def encode(self, values) -> bytes:
        word = 0
        for (start, mask, _sign, _span, scale, offset, lo, hi), value, s in zip(
                self._plan, values, self.signals, strict=True):
            if s.name == "crc":
                continue
            if not lo <= value <= hi:
                raise ValueError(f"{self.name}.{s.name} = {value!r} outside the DBC range [{lo}, {hi}]")
            raw = round((value - offset) / scale)
            word |= (raw & mask) << start
        data = bytearray(word.to_bytes(self.length, "little"))
        if self.crc_byte is not None:
            data[self.crc_byte] = frame_crc(self.frame_id, data, self.crc_byte)
        return bytes(data)


class Contract:
    """The shipped (or a configured) DBC: the four messages the HAL needs, compiled."""

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
            self.codecs[role] = FrameCodec(message)
        self.strains = self.codecs["strains"]
        self.load = self.codecs["load"]
        self.voltages = self.codecs["voltages"]
        self.status = self.codecs["status"]
        # the DAQ's duty when the controller falls silent (CTRL_Voltages attributes)
        self.silence_timeout_s = float(self.voltages.attributes.get("SilenceTimeoutMs", 0)) / 1e3
        self.fallback_ramp_s = float(self.voltages.attributes.get("FallbackRampMs", 0)) / 1e3
