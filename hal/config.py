"""The ``hal`` section of a service config: which backend, and its settings."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from beamctl.models.schema import boolean, choice, merge, number, number_list, path, positive, text, validate

HAL_DEFAULTS: dict[str, Any] = {
    "backend": "sim",
    "sim": {"pace": "simulated", "own_actuators": False,
            "actuators": {"force_constant": 3.0, "bias_voltage": 75.0, "orientation_deg": [90.0, 90.0]}},
    "can": {"interface": "socketcan", "channel": "can0", "bitrate": 1_000_000, "fd": False,
            "data_bitrate": 4_000_000, "dbc": "", "record": "", "rate_tolerance": 0.05},
}

_SCHEMA = {
    "backend": choice("sim", "can"),
    "sim": {"pace": choice("simulated", "wallclock"), "own_actuators": boolean(),
            "actuators": {"force_constant": positive("N/V"), "bias_voltage": number("V"),
                          "orientation_deg": number_list(number("deg"), 2, "angles (supports A and B)")}},
    "can": {"interface": text(), "channel": text(), "bitrate": positive("bit/s"), "fd": boolean(),
            "data_bitrate": positive("bit/s"), "dbc": path(), "record": path(),
            "rate_tolerance": number(low=0.0, high=0.5)},
}


@dataclass(frozen=True)
class HalConfig:
    backend: str
    sim: dict
    can: dict


def hal_config(overrides: dict[str, Any] | None = None, source: str = "", prefix: str = "hal.") -> HalConfig:
    v = validate(merge(HAL_DEFAULTS, overrides or {}), _SCHEMA, source, prefix)
    return HalConfig(backend=v["backend"], sim=v["sim"], can=v["can"])
