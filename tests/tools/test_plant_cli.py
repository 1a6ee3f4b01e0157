"""``beamctl plant`` (the emulator as the DAQ) and ``beamctl bus-budget``."""

import threading

import numpy as np
import pytest

from beamctl.hal.can_backend import CanBackend
from beamctl.tools.cli import main


def test_plant_command_plays_the_daq_for_a_controller(capsys):
    channel = "plant-cli"
    backend = CanBackend(2500.0, "virtual", channel).open()
    result = {}
    thread = threading.Thread(target=lambda: result.setdefault(
        "rc", main(["plant", "--can", f"virtual:{channel}", "--duration", "0.4", "--pace", "wallclock"])))
    thread.start()
    try:
        samples = []
        for _ in range(200):
            s = backend.read(timeout=1.0)
            samples.append(s.sequence)
            backend.write(np.full(6, 75.0))
    finally:
        thread.join(timeout=10)
        backend.close()
    assert result["rc"] == 0
    assert len(samples) == 200 and np.all(np.diff(samples) % 256 == 1)
    out = capsys.readouterr().out
    assert "stopped after 1000 samples" in out and "voltage frames" in out


@pytest.mark.parametrize("spec", ["vcan0", "socketcan:", ":vcan0"])
def test_can_spec_must_name_interface_and_channel(spec, capsys):
    assert main(["plant", "--can", spec]) == 2
    assert "INTERFACE:CHANNEL" in capsys.readouterr().err


def test_bus_budget_says_what_fits(capsys):
    assert main(["bus-budget"]) == 0
    out = capsys.readouterr().out
    assert "70.6 %" in out and "2834 Hz" in out and "6105 Hz" in out
    assert main(["bus-budget", "--rate", "3000"]) == 1
