"""The ``hal`` section of a service config: which backend, and its settings."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from beamctl.config.schema import (
    ConfigError,
    boolean,
    choice,
    merge,
    number,
    number_list,
    path,
    positive,
    refuse_renamed,
    text,
    validate,
)

# The bit rates a CAN bus can have. Classic CAN, and the arbitration phase of CAN FD: 10 kbit/s
# (the slowest of the standard rates, CiA 301) to 1 Mbit/s (the most ISO 11898-2 allows). The
# CAN FD data phase: from the arbitration rate (it is never slower) up to 8 Mbit/s, the fastest
# transceivers specified for it (ISO 11898-2:2016 with signal improvement, CiA 601-4).
BITRATE_RANGE_BIT_S = (10e3, 1e6)
DATA_BITRATE_MAX_BIT_S = 8e6

HAL_DEFAULTS: dict[str, Any] = {
    "backend": "sim",
    # wallclock: `beamctl run` on the simulated beam runs in real time like the rig (the
    # experiment and the benchmarks choose `simulated`, as fast as the loop, themselves)
    "sim": {"pace": "wallclock", "own_actuators": False,
            "actuators": {"force_constant_n_per_v": 3.0, "bias_voltage_v": 75.0,
                          "orientation_deg": [90.0, 90.0]}},
    "can": {"interface": "socketcan", "channel": "can0", "bitrate_bit_s": 1_000_000, "fd": True,
            "data_bitrate_bit_s": 4_000_000, "dbc": "", "record": "", "rate_tolerance": 0.05,
            # poll the bus for the last spin_s before each sample is due instead of sleeping
            # (hal/can_backend.py): the answer's latency for a share of a CPU; 0 sleeps always; at
            # most half the period (SPIN_SHARE_MAX: Linux throttles a real-time thread that takes
            # 95 % of its CPU, a 50 ms stall a second: 120 us at 6000 Hz did)
            "spin_s": 6.0e-5},
}

# Keys renamed to carry their unit: a file that still sets an old one is refused, naming the new.
RENAMED_KEYS = {
    "sim.actuators.force_constant": "sim.actuators.force_constant_n_per_v",
    "sim.actuators.bias_voltage": "sim.actuators.bias_voltage_v",
    "can.bitrate": "can.bitrate_bit_s",
    "can.data_bitrate": "can.data_bitrate_bit_s",
}

_SCHEMA = {
    "backend": choice("sim", "can"),
    "sim": {"pace": choice("simulated", "wallclock"), "own_actuators": boolean(),
            "actuators": {"force_constant_n_per_v": positive("N/V"), "bias_voltage_v": number("V"),
                          "orientation_deg": number_list(number("deg"), 2, "angles (supports A and B)")}},
    "can": {"interface": text(), "channel": text(), "bitrate_bit_s": positive("bit/s"), "fd": boolean(),
            "data_bitrate_bit_s": positive("bit/s"), "dbc": path(), "record": path(),
            "rate_tolerance": number(low=0.0, high=0.5), "spin_s": number("s", low=0.0, high=0.01)},
}


@dataclass(frozen=True)
class HalConfig:
    backend: str
    sim: dict
    can: dict


def check_bitrates(bitrate_bit_s: float, data_bitrate_bit_s: float, fd: bool, keys: tuple[str, str],
                   source: str = "") -> None:
    """Refuse a bit rate no CAN bus has (the data phase's only with ``fd``), naming ``keys``."""
    low, high = BITRATE_RANGE_BIT_S
    if not low <= bitrate_bit_s <= high:
        raise ConfigError(keys[0], bitrate_bit_s,
                          f"a CAN bit rate from {low / 1e3:g} kbit/s to {high / 1e6:g} Mbit/s "
                          f"(classic CAN, and the arbitration phase of CAN FD)", source)
    if fd and not bitrate_bit_s <= data_bitrate_bit_s <= DATA_BITRATE_MAX_BIT_S:
        raise ConfigError(keys[1], data_bitrate_bit_s,
                          f"a CAN FD data-phase bit rate from the arbitration rate "
                          f"({bitrate_bit_s / 1e3:g} kbit/s) to {DATA_BITRATE_MAX_BIT_S / 1e6:g} Mbit/s",
                          source)


def hal_config(overrides: dict[str, Any] | None = None, source: str = "", prefix: str = "hal.") -> HalConfig:
    refuse_renamed(overrides or {}, RENAMED_KEYS, source, prefix)
    v = validate(merge(HAL_DEFAULTS, overrides or {}), _SCHEMA, source, prefix)
    can = v["can"]
    check_bitrates(can["bitrate_bit_s"], can["data_bitrate_bit_s"], can["fd"],
                   (f"{prefix}can.bitrate_bit_s", f"{prefix}can.data_bitrate_bit_s"), source)
    return HalConfig(backend=v["backend"], sim=v["sim"], can=can)
