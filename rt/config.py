"""Settings of the real-time controller (the ``controller`` section of a service config),
validated on load: an unknown key or a wrong value is refused with the key and what was
expected."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from beamctl.config.schema import (
    ConfigError,
    boolean,
    choice,
    integer,
    merge,
    nonnegative,
    number,
    number_list,
    positive,
    validate,
)

MAX_AMPLIFIER_VOLTAGE = 150.0

CONTROLLER_DEFAULTS: dict[str, Any] = {
    "pacing": "sample",
    "anti_windup": True,
    "start_ramp_time": 0.2,
    "actuators": {
        # Stack force per volt, a rig parameter the paper does not give. 3.0 N/V is chosen so
        # that the paper's setup (500 N gain switching, 150 V) fails at 3225 N in the simulated
        # experiment, as the paper's did at 3223 N; at 150 V a support then gives 390 to 450 N
        # depending on the direction. Measure it on the rig.
        "force_constant": 3.0,
        "bias_voltage": 75.0,
        "min_voltage": 0.0,
        "max_voltage": MAX_AMPLIFIER_VOLTAGE,
        # direction of stack 1 at supports A and B, degrees from +y towards +z; stacks 2 and 3
        # follow at +120 and +240 deg
        "orientation_deg": [90.0, 90.0],
    },
    "safety": {
        "strain_limit_fraction": 0.5,   # of the proportional-limit strain sigma_p / E
        "load_range": [-200.0, 5000.0],  # N, load-cell range; the gain table's range applies too
        "stale_periods": 5,
        "overrun_streak": 10,
        "saturation_time": 0.5,         # s of continuous saturation before a fault
        "ramp_time": 0.5,               # s to ramp the voltages to bias on a fault or stop
    },
    "telemetry": {"buffer_time": 20.0, "flush_interval": 0.25},
    "realtime": {"priority": 80, "cpu": -1, "lock_memory": True},
}

_SCHEMA = {
    "pacing": choice("timer", "sample"),
    "anti_windup": boolean(),
    "start_ramp_time": nonnegative("s"),
    "actuators": {
        "force_constant": positive("N/V"),
        "bias_voltage": number("V"),
        "min_voltage": number("V"),
        "max_voltage": number("V", high=MAX_AMPLIFIER_VOLTAGE),
        "orientation_deg": number_list(number("deg"), 2, "angles (supports A and B)"),
    },
    "safety": {
        "strain_limit_fraction": number(low=0.0, high=1.0, low_open=True),
        "load_range": number_list(number("N"), 2, "loads [low, high]"),
        "stale_periods": integer(low=1),
        "overrun_streak": integer(low=1),
        "saturation_time": positive("s"),
        "ramp_time": positive("s"),
    },
    "telemetry": {"buffer_time": positive("s"), "flush_interval": number("s", low=0.01, high=0.5)},
    "realtime": {"priority": integer(low=1, high=99), "cpu": integer(low=-1), "lock_memory": boolean()},
}


@dataclass(frozen=True)
class Actuators:
    force_constant: float
    bias_voltage: float
    min_voltage: float
    max_voltage: float
    orientation_deg: tuple[float, float]


@dataclass(frozen=True)
class Safety:
    strain_limit_fraction: float
    load_range: tuple[float, float]
    stale_periods: int
    overrun_streak: int
    saturation_time: float
    ramp_time: float


@dataclass(frozen=True)
class Telemetry:
    buffer_time: float
    flush_interval: float


@dataclass(frozen=True)
class Realtime:
    priority: int
    cpu: int
    lock_memory: bool


@dataclass(frozen=True)
class ControllerConfig:
    pacing: str
    anti_windup: bool
    start_ramp_time: float
    actuators: Actuators
    safety: Safety
    telemetry: Telemetry
    realtime: Realtime


def controller_config(overrides: dict[str, Any] | None = None, source: str = "",
                      prefix: str = "") -> ControllerConfig:
    """Validate ``overrides`` over the defaults. ``prefix`` names the section in messages."""
    v = validate(merge(CONTROLLER_DEFAULTS, overrides or {}), _SCHEMA, source, prefix)
    a = v["actuators"]
    if not a["min_voltage"] < a["max_voltage"]:
        raise ConfigError(f"{prefix}actuators.min_voltage", a["min_voltage"],
                          f"less than actuators.max_voltage = {a['max_voltage']:g} V", source)
    if not a["min_voltage"] <= a["bias_voltage"] <= a["max_voltage"]:
        raise ConfigError(f"{prefix}actuators.bias_voltage", a["bias_voltage"],
                          f"a voltage within [{a['min_voltage']:g}, {a['max_voltage']:g}] V", source)
    t = v["telemetry"]
    if t["buffer_time"] < 2 * t["flush_interval"]:
        raise ConfigError(f"{prefix}telemetry.buffer_time", t["buffer_time"],
                          f"at least twice telemetry.flush_interval ({2 * t['flush_interval']:g} s): the "
                          f"ring must hold what arrives between two flushes", source)
    s = v["safety"]
    if not s["load_range"][0] < s["load_range"][1]:
        raise ConfigError(f"{prefix}safety.load_range", list(s["load_range"]), "low < high", source)
    return ControllerConfig(
        pacing=v["pacing"], anti_windup=v["anti_windup"], start_ramp_time=v["start_ramp_time"],
        actuators=Actuators(**a), safety=Safety(**s), telemetry=Telemetry(**v["telemetry"]),
        realtime=Realtime(**v["realtime"]))
