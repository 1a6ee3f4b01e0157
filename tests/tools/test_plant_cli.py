"""``beamctl plant`` (the emulator as the DAQ) and ``beamctl bus-budget``."""

import json
import re
import threading

import numpy as np
import pytest

from beamctl.gains.defaults import paper_table_path
from beamctl.hal.can_backend import CanBackend
from beamctl.tools.cli import main


def test_plant_command_plays_the_daq_for_a_controller(capsys, tmp_path):
    """The first sample may take the command's start-up (imports, the model and the plant: up to
    seconds on a busy machine); from then on the samples come at the table's rate and 200 of
    them in order, each answered, are well within the run's 1 s. A DAQ's clock does not wait:
    where the emulator's thread was held up (a busy machine) the samples it could not send on
    time are skipped, never sent late in a burst, and the command counts them. The controller's
    side reads every frame in order here (``newest_only=False``): reading only the newest after a
    stall, as the loop does, would drop the queued ones on this side and hide what the emulator
    sent."""
    channel = "plant-cli"
    config = tmp_path / "paper.yaml"      # the paper's design: 2500 Hz
    config.write_text(f"gains: {{table: {paper_table_path()}}}\n")
    backend = CanBackend(2500.0, "virtual", channel, newest_only=False).open()
    result = {}
    thread = threading.Thread(target=lambda: result.setdefault(
        "rc", main(["plant", "--can", f"virtual:{channel}", "--config", str(config), "--duration", "1.0",
                     "--pace", "wallclock", "--stats", str(tmp_path / "daq.json")])))
    thread.start()
    try:
        samples = []
        for i in range(200):
            s = backend.read(timeout=60.0 if i == 0 else 1.0)
            samples.append(s.sequence)
            backend.write(np.full(6, 75.0))
    finally:
        thread.join(timeout=10)
        backend.close()
    assert result["rc"] == 0
    out = capsys.readouterr().out
    assert "stopped after 2500 samples" in out and "voltage frames" in out
    skipped = int(re.search(r"(\d+) not sent", out).group(1))
    steps = np.diff(samples) % 256
    assert len(samples) == 200 and np.all(steps >= 1), f"samples out of order: {samples}"
    # after the first sample: the emulator's first steps may be late on a busy machine (start-up),
    # and a frame sent late among them may be refused by the sequence's plausibility window
    assert np.sum(steps[1:] - 1) <= skipped, (
        f"{np.sum(steps[1:] - 1)} samples missing between those read, the emulator skipped {skipped}")
    # the controller here answers 200 samples and stops: after its last answer the stacks hold
    # (no stall: nothing ends it). A jump of J between two samples it read is J samples the stacks
    # held voltages through, in at most three holds (the answers to the first of the two and to
    # the one before may reach the DAQ within the jump, when this thread answers late on a busy
    # machine): the longest hold is at least (J - 1) / 3. The DAQ counts holds from its step after
    # the controller's first answer on (before, its start-up), so the jumps after the first two
    # samples read, within which that first answer may come, are not among them
    stats = json.loads((tmp_path / "daq.json").read_text())
    assert stats["samples"] == 2500 and stats["voltage_frames"] >= 190, stats
    answered = steps[2:]
    assert stats["held_longest_samples"] >= (answered.max() - 1) / 3, (
        f"the DAQ recorded a longest hold of {stats['held_longest_samples']} samples, the controller "
        f"saw a jump of {answered.max()} after sample {np.argmax(answered) + 2} of those it read")
    assert stats["held_longest_ms"] == pytest.approx(stats["held_longest_samples"] / 2.5), stats


@pytest.mark.parametrize("spec", ["vcan0", "socketcan:", ":vcan0"])
def test_can_spec_must_name_interface_and_channel(spec, capsys):
    assert main(["plant", "--can", spec]) == 2
    assert "INTERFACE:CHANNEL" in capsys.readouterr().err


def test_bus_budget_says_what_fits(capsys):
    """Without flags: the shipped table's 6000 Hz on the HAL's default CAN FD bus. The highest
    rate it names fits (exit 0) and one hertz more does not (exit 1)."""
    assert main(["bus-budget"]) == 0
    out = capsys.readouterr().out
    assert "at 6000 Hz (the rate of" in out and "CAN FD 1000/4000 kbit/s" in out, out
    highest = int(re.search(r"highest sample rate within 80 %: (\d+) Hz", out).group(1))
    assert 6000 < highest, "the shipped 6000 Hz fits on CAN FD"
    assert main(["bus-budget", "--rate", str(highest)]) == 0
    assert main(["bus-budget", "--rate", str(highest + 1)]) == 1
    assert "exceeds the 80 % limit" in capsys.readouterr().out


def test_bus_budget_reads_a_configuration_s_bus_and_table_and_answers_in_json(tmp_path, capsys):
    config = tmp_path / "classic.yaml"
    config.write_text("hal:\n  backend: can\n  can: {fd: false, bitrate_bit_s: 1000000}\n")
    assert main(["bus-budget", "--config", str(config), "--json"]) == 1, "6000 Hz does not fit classic CAN"
    report = json.loads(capsys.readouterr().out)
    assert report["bus"] == "classic CAN 1000 kbit/s" and report["sample_rate_hz"] == 6000.0, report
    assert not report["fits"] and report["can_fd_load"] < 0.8, report
    assert main(["bus-budget", "--config", str(config), "--rate", "2500", "--json"]) == 0


@pytest.mark.parametrize(("argv", "flag", "value", "expected"), [
    (["--bitrate", "1"], "--bitrate", "1.0", "from 10 kbit/s to 1 Mbit/s"),
    (["--bitrate", "2e6"], "--bitrate", "2000000.0", "from 10 kbit/s to 1 Mbit/s"),
    (["--fd", "--data-bitrate", "16e6"], "--data-bitrate", "16000000.0", "to 8 Mbit/s"),
    (["--fd", "--bitrate", "500e3", "--data-bitrate", "250e3"], "--data-bitrate", "250000.0",
     "from the arbitration rate (500 kbit/s)"),
])
def test_a_bit_rate_no_can_bus_has_is_refused(argv, flag, value, expected, capsys):
    assert main(["bus-budget", *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith(f"beamctl bus-budget: error: {flag} = {value}: expected") and expected in err, err


def test_the_slowest_and_fastest_can_rates_are_accepted(capsys):
    assert main(["bus-budget", "--bitrate", "10e3", "--rate", "10"]) == 0
    assert main(["bus-budget", "--fd", "--bitrate", "1e6", "--data-bitrate", "8e6"]) == 0


def test_a_socketcan_bus_that_cannot_be_opened_says_what_to_do(capsys):
    assert main(["plant", "--can", "socketcan:nosuchcan9", "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert "cannot open socketcan:nosuchcan9" in err and ("modprobe" in err or "ip link" in err), err
    assert len(err.strip().splitlines()) == 1, err


def test_bus_budget_names_the_table_key_when_the_configuration_s_table_is_missing(tmp_path, capsys):
    config = tmp_path / "lab.yaml"
    config.write_text(f"gains: {{table: {tmp_path / 'none.yaml'}}}\nhal: {{backend: can}}\n")
    assert main(["bus-budget", "--config", str(config)]) == 2
    err = capsys.readouterr().err
    assert "gains.table" in err and "--rate" in err and len(err.strip().splitlines()) == 1, err
    assert main(["bus-budget", "--config", str(config), "--rate", "6000"]) == 0


@pytest.mark.parametrize("cpu", ["4096", "-2"])
def test_plant_refuses_a_cpu_it_may_not_run_on(capsys, cpu):
    """A CPU the process may not run on is refused in one line naming the flag and the CPUs it
    may run on, before anything is opened."""
    assert main(["plant", "--can", "virtual:plant-cpu", "--cpu", cpu]) == 2
    err = capsys.readouterr().err.strip()
    assert f"--cpu {cpu}" in err and "-1 for any" in err and len(err.splitlines()) == 1, err
