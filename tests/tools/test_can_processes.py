"""The contract between two processes: the controller (``beamctl run``) and the DAQ (the plant
emulator) each fall back to a safe state when the other dies without a word (SIGKILL), over
the loopback-only local bus (hal/localbus.py; on the lab PC the same holds over socketcan).

What is asserted holds whatever this machine's scheduling: each side's reaction is checked on
that side's own terms (the DAQ's fallback against the times it stepped at, the controller's
fault on a clock of the test's own), never against how soon the other process got to run."""

import signal
import time

import can
import numpy as np
import pytest
import yaml

from beamctl.gains.defaults import paper_table_path
from beamctl.hal.emulator import CanPlantEmulator
from beamctl.rt.config import controller_config
from beamctl.rt.controller import FLAG_NO_NEW_SAMPLE, I_FLAGS, Controller
from beamctl.rt.loop import ControlLoop
from beamctl.rt.safety import Fault
from tests.hal.rigs import GEOMETRY, TABLE, RigBackend, RigClock, make_plant, shipped_limits, wait_until
from tests.processes import beamctl

BIAS = 75.0
RATE = TABLE.design.sample_rate_hz
RAMP_S = 0.1                 # the controller's ramp to bias (a setting, not a ride-through limit)


@pytest.fixture
def channel(request):
    """A local-bus channel of the test's own, in the test's base directory that the child processes
    share ($BEAMCTL_LOCALBUS_DIR, set by tests/conftest.py)."""
    return f"c{abs(hash(request.node.name)) % 10**8}"


def _service_config(tmp_path, channel: str, **controller) -> str:
    """The service file of both processes; its safety is the shipped one (the gain table's
    ride-through limits) but for the ramp's time."""
    config = {
        "gains": {"table": str(paper_table_path())},
        "hal": {"backend": "can", "can": {"interface": "beamctl_local", "channel": channel, "fd": False,
                                          "rate_tolerance": 0.0}},
        "controller": {"pacing": "sample", "safety": {"ramp_time_s": RAMP_S}, **controller},
        "plant": {"load": {"start": 1500.0, "end": 1500.0}, "bow": {"amplitude": 5e-5, "angle_deg": 234.0}},
        "run": {"telemetry": str(tmp_path / "run.btl")},
    }
    path = tmp_path / "service.yaml"
    path.write_text(yaml.safe_dump(config))
    return str(path)


def test_a_controller_killed_with_sigkill_leaves_the_daq_ramping_to_bias(tmp_path, channel, compiled_engine):
    """The controller process answers the DAQ's samples, then dies without a word: the DAQ holds
    its last voltages for the DBC's silence time-out (20 ms) after the last valid voltage frame,
    then ramps linearly to bias within its fallback ramp (here 0.2 s), once, and stays there.

    The controller is armed and holds the stacks at its bias, 90 V (``--hold``; the DAQ's bias is
    75 V): so it sends the same voltages whatever this machine's scheduling does to it (at the
    shipped ride-through limits a controller running on this busy machine may fault on its own,
    and then ramps to bias: that is the controller's business, tested with a clock of its own in
    tests/hal). The DAQ's times are the ones it stepped at (``on_step``, after each step): the
    time each step computed its voltages at lies between the previous step's and its own."""
    silence, ramp, held_v = 0.02, 0.2, 90.0
    log = []                        # (time, voltages, valid voltage frames, fallbacks, falling back)
    bus = can.Bus(interface="beamctl_local", channel=channel)
    killed = []
    controller = None

    def on_step(plant, v):
        e = emulator
        log.append((time.monotonic(), v.copy(), e.voltage_frames, e.fallbacks, e.falling_back))
        if not killed and e.voltage_frames >= 200:
            controller.send_signal(signal.SIGKILL)
            killed.append(len(log) - 1)

    emulator = CanPlantEmulator(bus, make_plant(), GEOMETRY, pace="wallclock", fallback_ramp_s=ramp,
                                on_step=on_step)
    assert emulator.silence_timeout_s == silence, "the DBC's SilenceTimeoutMs"
    config = _service_config(tmp_path, channel, actuators={"bias_voltage_v": held_v})
    controller = beamctl("run", "--config", config, "--hold", cwd=tmp_path)
    try:
        emulator.start()
        wait_until(lambda: killed or controller.poll() is not None,
                   "200 valid voltage frames from the controller", timeout_s=300.0)
        controller.wait(60.0)
        # the DAQ at bias, and 100 more steps of it
        wait_until(lambda: emulator.falling_back and np.all(log[-1][1] == BIAS), "the DAQ at bias")
        at_bias = len(log)
        wait_until(lambda: len(log) >= at_bias + 100, "100 more steps of the DAQ")
    finally:
        if controller.poll() is None:
            controller.kill()
        err = controller.communicate()[1].decode()
        emulator.stop()
        bus.shutdown()
    assert killed and controller.returncode == -signal.SIGKILL, f"the controller ended by itself: {err}"
    t = np.array([e[0] for e in log])
    v = np.array([e[1] for e in log])
    frames = np.array([e[2] for e in log])
    fallbacks = np.array([e[3] for e in log])
    falling = np.array([e[4] for e in log])
    j = int(np.flatnonzero(np.diff(frames))[-1]) + 1      # the step after the last valid frame came
    assert j >= killed[0], "valid frames came until the kill"
    # the last valid frame was taken after step j - 1 had been logged: last_valid > t[j - 1]
    assert emulator.fallbacks - fallbacks[j - 1] == 1, (
        f"{emulator.fallbacks - fallbacks[j - 1]} fallbacks to bias after the last valid frame (one is due)")
    f = j + int(np.argmax(falling[j:]))                   # the step the fallback began at
    assert falling[f] and falling[f:].all(), "falling back from its start to the end"
    np.testing.assert_array_equal(v[j:f], held_v, err_msg="the last valid voltages held until the fallback")
    assert t[f] > t[j - 1] + silence, "the fallback began before the silence time-out had passed"
    # linear from 90 V at the fallback's start to bias a ramp later, in the DAQ's time: step i
    # computed its voltages at a time in [t[i-1], t[i]], the fallback began in [t[f-1], t[f]]
    for i in range(f, len(t)):
        early, late = max(t[i - 1] - t[f], 0.0), t[i] - t[f - 1]
        high = BIAS + (held_v - BIAS) * max(0.0, 1.0 - early / ramp)
        low = BIAS + (held_v - BIAS) * max(0.0, 1.0 - late / ramp)
        assert np.all((v[i] >= low - 1e-9) & (v[i] <= high + 1e-9)), (
            f"step {i - f} of the fallback at {v[i].min():.3f} V, off the ramp's [{low:.3f}, {high:.3f}] V")
    at_bias = np.all(v[f:] == BIAS, axis=1)
    first = int(np.argmax(at_bias))
    assert at_bias[first] and at_bias[first:].all(), "at bias, and there to stay"


def test_a_daq_killed_with_sigkill_leaves_the_controller_ramping_to_bias(tmp_path, channel):
    """The DAQ (the emulator in its own process, in lockstep) dies mid-run: the controller faults
    on stale input once the table's gap limit + 1 periods have passed without a sample, and
    ramps to bias in its ramp's samples, one a period without samples.

    The controller (in this process, at the shipped safety) runs on a clock of the test's own
    (tests/hal/rigs.py): its reads wait for the DAQ as long as the DAQ process lives, and once it
    is dead (and what it sent is read) each read time-out passes on that clock. The DAQ waits for
    each answer before its next sample (lockstep; after 50 ms it sends the next one anyway)."""
    config = _service_config(tmp_path, channel)
    daq = None
    clock = RigClock()
    backend = RigBackend(RATE, "beamctl_local", channel, rate_tolerance=0.0, clock=clock,
                         daq_running=lambda: daq.poll() is None).open()
    daq = beamctl("plant", "--can", f"beamctl_local:{channel}", "--config", config, "--pace", "lockstep",
                  cwd=tmp_path)
    controller = Controller(TABLE, controller_config({"pacing": "sample", "safety": {"ramp_time_s": RAMP_S}}))
    events = []

    def watch(loop):
        has_sample = not int(controller.record[I_FLAGS]) & FLAG_NO_NEW_SAMPLE
        events.append((clock(), has_sample, controller.at_bias, controller.supervisor.fault != Fault.NONE,
                       controller.safety.gap_limit))
        if loop.cycles == 2000:
            daq.send_signal(signal.SIGKILL)

    try:
        assert daq.stdout.readline(), f"the emulator did not start: {daq.stderr.read().decode()}"
        result = ControlLoop(controller, backend, clock=clock, on_cycle=watch).run(acquire_rt=False)
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
    faulted = np.array([e[3] for e in events])
    last = int(np.flatnonzero(has_sample)[-1])
    assert not at_bias[last], "the controller was driving the stacks"
    first_fault = int(np.argmax(faulted))
    assert first_fault >= 2000, f"the fault came in cycle {first_fault + 1}, before the kill (cycle 2000)"
    gap = events[first_fault][4]
    cap = shipped_limits(1500.0)[:, 0].max()
    assert 1 <= gap <= cap, f"live gap limit {gap} samples at the fault: expected 1 to the cap {cap:g}"
    silent = (t[first_fault] - t[last]) * RATE
    assert gap + 1 <= silent <= gap + 1.1 + 1e-9, (
        f"stale-input fault after {silent:.2f} periods without a sample; due after {gap + 1}")
    ramp_cycles = int(np.argmax(at_bias[first_fault:])) + 1        # the fault's cycle is the first
    ramp_samples = round(RAMP_S * RATE)
    assert ramp_cycles == ramp_samples, (
        f"at bias after {ramp_cycles} cycles from the fault's; the {1e3 * RAMP_S:.0f} ms ramp is "
        f"{ramp_samples} samples")
