"""The contract between two processes: the controller (``beamctl run``) and the DAQ (the plant
emulator) each fall back to a safe state when the other dies without a word (SIGKILL), over
the loopback-only local bus (hal/localbus.py; on the lab PC the same holds over socketcan)."""

import signal
import time

import can
import numpy as np
import pytest
import yaml

from beamctl.gains.defaults import paper_table_path
from beamctl.hal.can_backend import CanBackend
from beamctl.hal.emulator import CanPlantEmulator
from beamctl.rt.config import controller_config
from beamctl.rt.controller import FLAG_NO_NEW_SAMPLE, I_FLAGS, Controller
from beamctl.rt.loop import ControlLoop
from beamctl.rt.safety import Fault
from tests.hal.rigs import GEOMETRY, IN_PROCESS_SAFETY, TABLE, make_plant
from tests.tools.processes import beamctl

BIAS = 75.0
RATE = TABLE.design.sample_rate_hz
# what a busy two-core machine may add to a deadline before a thread or process gets to run
SCHEDULING_SLACK_S = 0.1


@pytest.fixture
def channel(tmp_path, monkeypatch, request):
    """A local-bus channel of the test's own, in a base directory the child processes share."""
    monkeypatch.setenv("BEAMCTL_LOCALBUS_DIR", str(tmp_path / "bus"))
    return f"c{abs(hash(request.node.name)) % 10**8}"


def _service_config(tmp_path, channel: str) -> str:
    config = {
        "gains": {"table": str(paper_table_path())},
        "hal": {"backend": "can", "can": {"interface": "beamctl_local", "channel": channel, "fd": False,
                                          "rate_tolerance": 0.0}},
        "controller": {"pacing": "sample", "safety": {**IN_PROCESS_SAFETY, "ramp_time_s": 0.1}},
        "plant": {"load": {"start": 1500.0, "end": 1500.0}, "bow": {"amplitude": 5e-5, "angle_deg": 234.0}},
        "run": {"telemetry": str(tmp_path / "run.btl")},
    }
    path = tmp_path / "service.yaml"
    path.write_text(yaml.safe_dump(config))
    return str(path)


def test_a_controller_killed_with_sigkill_leaves_the_daq_ramping_to_bias(tmp_path, channel):
    """The controller drives the stacks, then dies without a word: after the DBC's silence
    time-out (20 ms) the DAQ ramps to bias within its fallback ramp (here 0.2 s) by itself."""
    silence, ramp = 0.02, 0.2
    log = []
    bus = can.Bus(interface="beamctl_local", channel=channel)
    emulator = CanPlantEmulator(bus, make_plant(), GEOMETRY, pace="wallclock", fallback_ramp_s=ramp,
                                on_step=lambda plant, v: log.append((time.monotonic(), v.copy())))
    assert emulator.silence_timeout_s == silence, "the DBC's SilenceTimeoutMs"
    controller = beamctl("run", "--config", _service_config(tmp_path, channel), cwd=tmp_path)
    try:
        emulator.start()
        deadline = time.monotonic() + 60.0
        while emulator.voltage_frames < 1500 and time.monotonic() < deadline and controller.poll() is None:
            time.sleep(0.05)
        assert controller.poll() is None, controller.communicate()[1].decode()
        assert emulator.voltage_frames >= 1500, "the controller did not answer"
        driven = np.abs(log[-1][1] - BIAS).max()
        assert driven > 0.5, f"the controller was not driving the stacks ({driven:.2f} V from bias)"
        # a controller starved of the processor for the silence time-out before the kill is a
        # fallback too (the DAQ doing its job on a busy machine): count those after the kill
        fallbacks_before = emulator.fallbacks
        controller.send_signal(signal.SIGKILL)
        killed = time.monotonic()
        controller.wait(10.0)
        time.sleep(silence + ramp + 2 * SCHEDULING_SLACK_S)
    finally:
        if controller.poll() is None:
            controller.kill()
        controller.communicate()
        emulator.stop()
        bus.shutdown()
    t = np.array([e[0] for e in log]) - killed
    v = np.array([e[1] for e in log])
    after_kill = emulator.fallbacks - fallbacks_before
    assert after_kill == 1, f"{after_kill} fallbacks to bias after the kill (one is due)"
    at_bias = np.all(v == BIAS, axis=1)
    after = t > silence + ramp + SCHEDULING_SLACK_S
    assert after.any() and at_bias[after].all(), "not at bias within the silence time-out and the ramp"
    first_bias = t[np.argmax(at_bias & (t > 0))]
    assert first_bias >= ramp - SCHEDULING_SLACK_S / 2, (
        f"at bias {1e3 * first_bias:.0f} ms after the kill: a jump, not a {1e3 * ramp:.0f} ms ramp")


def test_a_daq_killed_with_sigkill_leaves_the_controller_ramping_to_bias(tmp_path, channel):
    """The DAQ (the emulator in its own process) dies mid-run: the controller faults on stale
    input after stale_periods periods of time and ramps to bias in its ramp's samples, one a
    period without samples. The ramp is counted in cycles: each waits a period for a sample
    that does not come, and on a busy machine a wait takes longer than asked (it never takes
    less, so the fault is never early)."""
    config = _service_config(tmp_path, channel)
    backend = CanBackend(RATE, "beamctl_local", channel, rate_tolerance=0.0).open()
    daq = beamctl("plant", "--can", f"beamctl_local:{channel}", "--config", config, cwd=tmp_path)
    settings = controller_config({"pacing": "sample", "safety": {**IN_PROCESS_SAFETY, "ramp_time_s": 0.1}})
    controller = Controller(TABLE, settings)
    events = []

    def watch(loop):
        has_sample = not int(controller.record[I_FLAGS]) & FLAG_NO_NEW_SAMPLE
        events.append((time.perf_counter(), has_sample, controller.at_bias,
                       controller.supervisor.fault != Fault.NONE))
        if loop.cycles == 2000:
            daq.send_signal(signal.SIGKILL)

    try:
        assert daq.stdout.readline(), f"the emulator did not start: {daq.stderr.read().decode()}"
        result = ControlLoop(controller, backend, on_cycle=watch).run(acquire_rt=False)
    finally:
        if daq.poll() is None:
            daq.kill()
        daq.communicate()
        backend.close()
    assert daq.returncode == -signal.SIGKILL
    assert result.fault == Fault.STALE_INPUT.name, result.reason
    t = np.array([e[0] for e in events])
    has_sample = np.array([e[1] for e in events])
    at_bias = np.array([e[2] for e in events])
    last_sample = t[np.flatnonzero(has_sample)[-1]]
    assert not at_bias[np.flatnonzero(has_sample)[-1]], "the controller was driving the stacks"
    faulted = np.array([e[3] for e in events])
    first_fault = int(np.argmax(faulted))
    stale_s = IN_PROCESS_SAFETY["stale_periods"] / RATE
    silent = t[first_fault] - last_sample
    assert stale_s <= silent <= stale_s + SCHEDULING_SLACK_S, (
        f"stale-input fault {1e3 * silent:.1f} ms after the last sample; due after {1e3 * stale_s:.0f} ms")
    ramp_cycles = int(np.argmax(at_bias[first_fault:]))
    ramp_samples = round(0.1 * RATE)
    assert abs(ramp_cycles - ramp_samples) <= 1, (
        f"at bias {ramp_cycles} cycles after the fault; the 100 ms ramp is {ramp_samples} samples")

