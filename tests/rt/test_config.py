"""The controller's settings: the amplifiers' limits are not negotiable."""

import pytest

from beamctl.config.schema import ConfigError, merge, nested
from beamctl.rt.config import (
    CONTROLLER_DEFAULTS,
    MAX_AMPLIFIER_VOLTAGE_V,
    RENAMED_KEYS,
    controller_config,
    settings_by_key,
)


def test_the_amplifiers_150_V_is_the_highest_voltage_a_configuration_may_ask_for():
    """The piezo amplifiers of the rig give at most 150 V; a limit above it would let the
    allocation ask the stacks for a voltage they cannot take."""
    assert MAX_AMPLIFIER_VOLTAGE_V == 150.0
    assert controller_config({"actuators": {"max_voltage_v": 150.0}}).actuators.max_voltage_v == 150.0
    for too_high in (150.01, 200.0, float("inf")):
        with pytest.raises(ConfigError) as err:
            controller_config({"actuators": {"max_voltage_v": too_high}}, prefix="controller.")
        assert err.value.key == "controller.actuators.max_voltage_v", str(err.value)
        assert "<= 150" in str(err.value), str(err.value)


@pytest.mark.parametrize(("actuators", "key"), [
    ({"min_voltage_v": 150.0}, "actuators.min_voltage_v"),
    ({"bias_voltage_v": 151.0}, "actuators.bias_voltage_v"),
    ({"bias_voltage_v": -1.0}, "actuators.bias_voltage_v"),
    ({"force_constant_n_per_v": 0.0}, "actuators.force_constant_n_per_v"),
])
def test_inconsistent_stack_settings_are_refused_naming_the_key(actuators, key):
    with pytest.raises(ConfigError) as err:
        controller_config({"actuators": actuators})
    assert err.value.key == key, str(err.value)


def _nested(dotted: str, value) -> dict:
    *parents, leaf = dotted.split(".")
    data = {leaf: value}
    for part in reversed(parents):
        data = {part: data}
    return data


def _keys(mapping: dict, prefix: str = "") -> set[str]:
    out = set()
    for key, value in mapping.items():
        out |= _keys(value, f"{prefix}{key}.") if isinstance(value, dict) else {prefix + key}
    return out


@pytest.mark.parametrize(("old", "new"), sorted(RENAMED_KEYS.items()))
def test_a_key_renamed_to_carry_its_unit_is_refused_naming_the_new_key(old, new):
    """A lab file written before the keys carried their units (safety.ramp_time: 0.5) must not
    be read as if the setting were absent: it is refused, naming the key to write instead."""
    assert new in _keys(CONTROLLER_DEFAULTS), f"{new} is not a controller key"
    with pytest.raises(ConfigError) as err:
        controller_config(_nested(old, 0.5), "lab.yaml", "controller.")
    message = str(err.value)
    assert err.value.key == f"controller.{old}", message
    assert f"controller.{new} in its place" in message and "\n" not in message, message


def test_the_allocation_is_scale_unless_set_to_the_paper_s_clip_and_nothing_else():
    assert controller_config().allocation == "scale", "the default keeps the force's direction"
    assert controller_config({"allocation": "clip"}).allocation == "clip"
    with pytest.raises(ConfigError) as err:
        controller_config({"allocation": "spread"}, "lab.yaml", "controller.")
    assert err.value.key == "controller.allocation", str(err.value)
    assert "'scale', 'clip'" in str(err.value)


def test_the_settings_by_key_are_the_configuration_keys_and_read_back_to_the_same_settings():
    """A recording states its settings under the keys a file sets (rt/telemetry.py); every key,
    each once, and a file written from them gives the same settings."""
    changed = controller_config({"allocation": "clip", "safety": {"ramp_time_s": 0.7},
                                 "actuators": {"orientation_deg": [10.0, 20.0]}})
    flat = settings_by_key(changed)
    assert set(flat) == _keys(CONTROLLER_DEFAULTS)
    data: dict = {}
    for key, value in flat.items():
        data = merge(data, nested(key, value))
    assert controller_config(data) == changed
