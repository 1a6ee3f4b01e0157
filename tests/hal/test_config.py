"""The ``hal`` section of a service config."""

import pytest

from beamctl.config.schema import ConfigError
from beamctl.hal.config import RENAMED_KEYS, hal_config


@pytest.mark.parametrize(("can", "key"), [
    ({"bitrate_bit_s": 1}, "hal.can.bitrate_bit_s"),
    ({"bitrate_bit_s": 5_000_000}, "hal.can.bitrate_bit_s"),
    ({"fd": True, "data_bitrate_bit_s": 20_000_000}, "hal.can.data_bitrate_bit_s"),
    ({"fd": True, "bitrate_bit_s": 1_000_000, "data_bitrate_bit_s": 500_000}, "hal.can.data_bitrate_bit_s"),
])
def test_a_bit_rate_no_can_bus_has_is_refused_naming_the_key(can, key):
    with pytest.raises(ConfigError) as info:
        hal_config({"can": can}, "lab.yaml")
    assert info.value.key == key and str(info.value).startswith(f"lab.yaml: {key} = ")


def test_the_data_phase_rate_matters_only_with_can_fd():
    classic = hal_config({"can": {"fd": False, "bitrate_bit_s": 500_000, "data_bitrate_bit_s": 100_000}})
    assert classic.can["bitrate_bit_s"] == 500_000
    fd = hal_config({"can": {"fd": True, "data_bitrate_bit_s": 8_000_000}})
    assert fd.can["data_bitrate_bit_s"] == 8_000_000


@pytest.mark.parametrize(("section", "old", "new"), [
    ({"can": {"bitrate": 500_000}}, "hal.can.bitrate", "hal.can.bitrate_bit_s"),
    ({"can": {"data_bitrate": 4_000_000}}, "hal.can.data_bitrate", "hal.can.data_bitrate_bit_s"),
    ({"sim": {"actuators": {"force_constant": 2.5}}}, "hal.sim.actuators.force_constant",
     "hal.sim.actuators.force_constant_n_per_v"),
    ({"sim": {"actuators": {"bias_voltage": 70.0}}}, "hal.sim.actuators.bias_voltage",
     "hal.sim.actuators.bias_voltage_v"),
])
def test_a_key_renamed_to_carry_its_unit_is_refused_naming_the_new_key(section, old, new):
    assert set(RENAMED_KEYS) == {"can.bitrate", "can.data_bitrate", "sim.actuators.force_constant",
                                 "sim.actuators.bias_voltage"}
    with pytest.raises(ConfigError) as info:
        hal_config(section, "lab.yaml")
    message = str(info.value)
    assert info.value.key == old and f"{new} in its place" in message and "\n" not in message, message
