"""Bus load of the DBC's frames at a sample rate, with worst-case bit stuffing.

Classic CAN (ISO 11898-1), 11-bit identifier, n data bytes: 47 + 8n bits, of which the
34 + 8n bits from start of frame to the CRC can be stuffed, worst case one stuff bit per four:
floor((34 + 8n - 1) / 4). (29-bit identifiers: 67 + 8n bits, 54 + 8n stuffable.)

CAN FD, 11-bit identifier, bit-rate switch: at the nominal rate the arbitration field
(17 bits + 4 stuff) and the end of frame (CRC delimiter, ACK, EOF, intermission: 13 bits);
at the data rate ESI, DLC, the data, the stuff count (4), the CRC (17 bits up to 16 bytes, 21
above) with its fixed stuff bits (one per four), and dynamic stuffing of ESI, DLC and data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from beamctl.hal.base import HalConfigurationError
from beamctl.hal.dbc import Contract

LIMIT = 0.80


def classic_frame_bits(data_bytes: int, extended: bool = False) -> int:
    fixed = 67 if extended else 47
    stuffable = (54 if extended else 34) + 8 * data_bytes
    return fixed + 8 * data_bytes + (stuffable - 1) // 4


def fd_frame_time(data_bytes: int, nominal_bitrate_bit_s: float, data_bitrate_bit_s: float,
                  extended: bool = False) -> float:
    """Seconds one CAN FD frame (bit-rate switch) takes on the bus."""
    arbitration = (37 if extended else 17)
    nominal_bits = arbitration + (arbitration - 1) // 4 + 13
    crc = 17 if data_bytes <= 16 else 21
    dynamic = 1 + 4 + 8 * data_bytes
    data_bits = dynamic + (dynamic - 1) // 4 + 4 + crc + math.ceil(crc / 4)
    return nominal_bits / nominal_bitrate_bit_s + data_bits / data_bitrate_bit_s


@dataclass(frozen=True)
class Budget:
    sample_rate_hz: float
    load: float                   # fraction of the bus time in use
    per_message: dict             # name -> fraction
    max_sample_rate_hz: float     # highest whole-hertz rate within LIMIT
    description: str


def bus_budget(contract: Contract, sample_rate_hz: float, bitrate_bit_s: float, fd: bool = False,
               data_bitrate_bit_s: float | None = None) -> Budget:
    """Bus load of all four messages at ``sample_rate_hz``."""
    data_rate = data_bitrate_bit_s or bitrate_bit_s
    per_sample = {}
    for codec in contract.codecs.values():
        if fd:
            seconds = fd_frame_time(codec.length, bitrate_bit_s, data_rate, codec.is_extended)
        else:
            seconds = classic_frame_bits(codec.length, codec.is_extended) / bitrate_bit_s
        per_sample[codec.name] = seconds / codec.divisor
    total = sum(per_sample.values())
    kind = f"CAN FD {bitrate_bit_s / 1e3:g}/{data_rate / 1e3:g} kbit/s" if fd \
        else f"classic CAN {bitrate_bit_s / 1e3:g} kbit/s"
    return Budget(sample_rate_hz=sample_rate_hz, load=total * sample_rate_hz,
                  per_message={k: v * sample_rate_hz for k, v in per_sample.items()},
                  max_sample_rate_hz=float(math.floor(LIMIT / total)), description=kind)


def check_budget(contract: Contract, sample_rate_hz: float, bitrate_bit_s: float, fd: bool = False,
                 data_bitrate_bit_s: float | None = None) -> Budget:
    """The budget, or HalConfigurationError when it exceeds 80 %, saying what would fit."""
    b = bus_budget(contract, sample_rate_hz, bitrate_bit_s, fd, data_bitrate_bit_s)
    if b.load > LIMIT:
        hint = f"at most {b.max_sample_rate_hz:.0f} Hz fits on {b.description}"
        if not fd:
            fd_budget = bus_budget(contract, sample_rate_hz, bitrate_bit_s, True, 4 * bitrate_bit_s)
            hint += (f"; CAN FD with a {4 * bitrate_bit_s / 1e6:g} Mbit/s data phase would carry "
                     f"{fd_budget.max_sample_rate_hz:.0f} Hz ({100 * fd_budget.load:.0f} % at this rate)")
        raise HalConfigurationError(
            f"bus load {100 * b.load:.1f} % at {sample_rate_hz:g} Hz on {b.description} exceeds "
            f"{100 * LIMIT:.0f} %: {hint}")
    return b
