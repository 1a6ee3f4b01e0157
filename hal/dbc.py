"""The DBC contract with the DAQ firmware, loaded once and compiled into codecs.

Each message becomes a ``FrameCodec``: shifts, masks and scales derived from the DBC signal
definitions, so decoding a frame in the loop is integer arithmetic on one ``int`` (no DBC
parsing, no dict building). Tests check the codecs against cantools on random values.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import cantools

from beamctl.hal.base import HalConfigurationError

STRAIN_SIGNALS = ("strain_y1", "strain_z1", "strain_y2", "strain_z2")
VOLTAGE_SIGNALS = ("voltage_a1", "voltage_a2", "voltage_a3", "voltage_b1", "voltage_b2", "voltage_b3")
MESSAGES = {
    "strains": ("DAQ_Strains", STRAIN_SIGNALS + ("sequence",)),
    "load": ("DAQ_Load", ("axial_load", "sequence")),
    "voltages": ("CTRL_Voltages", VOLTAGE_SIGNALS + ("sequence",)),
    "status": ("CTRL_Status", ("state", "fault", "flags", "sequence")),
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
    the DBC range; ``encode(values)`` returns the frame bytes (ValueError when out of range)."""

    def __init__(self, message: cantools.database.Message) -> None:
        self.name = message.name
        self.frame_id = message.frame_id
        self.length = message.length
        self.is_extended = message.is_extended_frame
        attrs = message.dbc.attributes if message.dbc else {}
        self.divisor = int(attrs["SampleDivisor"].value) if "SampleDivisor" in attrs else 1
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

    def encode(self, values) -> bytes:
        word = 0
        for (start, mask, _sign, _span, scale, offset, lo, hi), value, s in zip(
                self._plan, values, self.signals, strict=True):
            if not lo <= value <= hi:
                raise ValueError(f"{self.name}.{s.name} = {value!r} outside the DBC range [{lo}, {hi}]")
            raw = round((value - offset) / scale)
            word |= (raw & mask) << start
        return word.to_bytes(self.length, "little")


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
            self.codecs[role] = FrameCodec(message)
        self.strains = self.codecs["strains"]
        self.load = self.codecs["load"]
        self.voltages = self.codecs["voltages"]
        self.status = self.codecs["status"]
