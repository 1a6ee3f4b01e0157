"""The controller's settings: the amplifiers' limits are not negotiable."""

import pytest

from beamctl.config.schema import ConfigError
from beamctl.rt.config import MAX_AMPLIFIER_VOLTAGE, controller_config


def test_the_amplifiers_150_V_is_the_highest_voltage_a_configuration_may_ask_for():
    """The piezo amplifiers of the rig give at most 150 V; a limit above it would let the
    allocation ask the stacks for a voltage they cannot take."""
    assert MAX_AMPLIFIER_VOLTAGE == 150.0
    assert controller_config({"actuators": {"max_voltage": 150.0}}).actuators.max_voltage == 150.0
    for too_high in (150.01, 200.0, float("inf")):
        with pytest.raises(ConfigError) as err:
            controller_config({"actuators": {"max_voltage": too_high}}, prefix="controller.")
        assert err.value.key == "controller.actuators.max_voltage", str(err.value)
        assert "<= 150" in str(err.value), str(err.value)


@pytest.mark.parametrize(("actuators", "key"), [
    ({"min_voltage": 150.0}, "actuators.min_voltage"),
    ({"bias_voltage": 151.0}, "actuators.bias_voltage"),
    ({"bias_voltage": -1.0}, "actuators.bias_voltage"),
    ({"force_constant": 0.0}, "actuators.force_constant"),
])
def test_inconsistent_stack_settings_are_refused_naming_the_key(actuators, key):
    with pytest.raises(ConfigError) as err:
        controller_config({"actuators": actuators})
    assert err.value.key == key, str(err.value)
