"""The ``hal`` section of a service config."""

import pytest

from beamctl.config.schema import ConfigError
from beamctl.hal.config import hal_config


@pytest.mark.parametrize(("can", "key"), [
    ({"bitrate": 1}, "hal.can.bitrate"),
    ({"bitrate": 5_000_000}, "hal.can.bitrate"),
    ({"fd": True, "data_bitrate": 20_000_000}, "hal.can.data_bitrate"),
    ({"fd": True, "bitrate": 1_000_000, "data_bitrate": 500_000}, "hal.can.data_bitrate"),
])
def test_a_bit_rate_no_can_bus_has_is_refused_naming_the_key(can, key):
    with pytest.raises(ConfigError) as info:
        hal_config({"can": can}, "lab.yaml")
    assert info.value.key == key and str(info.value).startswith(f"lab.yaml: {key} = ")


def test_the_data_phase_rate_matters_only_with_can_fd():
    assert hal_config({"can": {"bitrate": 500_000, "data_bitrate": 100_000}}).can["bitrate"] == 500_000
    assert hal_config({"can": {"fd": True, "data_bitrate": 8_000_000}}).can["data_bitrate"] == 8_000_000
