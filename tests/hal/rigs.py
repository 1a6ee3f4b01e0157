"""Test rigs: the sim backend, and the CAN backend talking to the plant emulator over
python-can's virtual bus (each rig on its own channel).

The CAN rigs run the controller at the shipped safety settings (rt.config's defaults: the gain
table's ride-through limits) and their pass or fail does not depend on this machine's
scheduling (a shared 2-core virtual machine that holds a thread up for tens to hundreds of
milliseconds at times). Two things make them so:

- the emulator runs in ``lockstep`` pace by default: it waits for the answer to each sample
  before it steps the plant, so a controller held up misses no sample and the plant applies
  every answer to the sample it answers;
- the loop and the backend run on the rig's clock (``RigClock``, the same one for both: pass
  ``clock=rig.clock`` to the loop, or build it with ``CanRig.loop``), on which time passes
  only while the DAQ is silent, never while this machine is merely slow: a read waits for as
  long as the DAQ runs (``RigBackend``), and once the DAQ has stopped, each read time-out lets
  its time pass on the clock. The loop then counts a silence in periods exactly as the engine
  is specified to (more than the gap limit missing: STALE_INPUT), and an answer takes no time
  (none is late) unless the test makes it take some (``answer_delay_s``). As no time passes
  between samples, the backend's alive-counter window admits a jump of the sequence by at most
  its jitter of two samples: a DAQ that lost samples on the way shows as refused frames and a
  resynchronisation, not as samples missed (those are tested with constructed time stamps,
  tests/hal/test_can.py); the virtual bus loses none.

What this machine's timing does to the real clock (answer ages, jitter, the loop's cycle) is
measured by `beamctl bench` and tests/hal/can_path_bench.py, not asserted here.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable

import can
import numpy as np

from beamctl.gains.defaults import paper_table_path
from beamctl.gains.table import load_table
from beamctl.hal import can_backend
from beamctl.hal.base import HalConnectionLost, Sample
from beamctl.hal.can_backend import CanBackend
from beamctl.hal.dbc import Contract
from beamctl.hal.emulator import CanPlantEmulator
from beamctl.hal.sim import SimBackend
from beamctl.models import build_model
from beamctl.models.plant import Plant, plant_config
from beamctl.rt.allocation import geometry
from beamctl.rt.config import controller_config
from beamctl.rt.controller import Controller, ride_through_limits
from beamctl.rt.loop import ControlLoop

_channels = itertools.count()
TABLE = load_table(paper_table_path())
MODEL = build_model(TABLE.model_parameters)
GEOMETRY = geometry(controller_config().actuators)
RATE_HZ = TABLE.design.sample_rate_hz
STRAINS_ID = Contract().strains.frame_id
# A lockstep emulator that waits this long for an answer never gives up on a live controller,
# however long this machine holds it up (it still stops at once when asked to).
LOCKSTEP_TIMEOUT_S = 30.0
# A DAQ that runs but sends nothing for this long is a broken test, not a slow machine.
HUNG_DAQ_S = 60.0
WAIT_SLICE_S = 0.05


def make_plant(**overrides) -> Plant:
    settings = {"sample_rate_hz": RATE_HZ, "load": {"start": 1500.0, "end": 1500.0},
                "bow": {"amplitude": 5e-5, "angle_deg": 234.0}, "noise": {"strain": 2e-7, "load": 1.0}}
    settings.update(overrides)
    return Plant(MODEL, plant_config(settings))


def shipped_limits(load_n: float, table=TABLE) -> np.ndarray:
    """The ride-through limits a controller with the shipped settings applies at ``load_n``
    below the critical load, where a gap's growth stays near 1 and the live limit is its cap
    (rt.controller.ride_through_limits, the configuration's defaults): rows of (samples missing
    in a row, late answers in a row, answer budget in periods), one per grid interval of
    ``table`` whose range holds the load (two at a grid point: the schedule's hysteresis decides
    which is in use); the budget per interval the lesser of its two ends, as the engine takes
    them."""
    limits = ride_through_limits(table, controller_config())
    loads = np.asarray(table.loads_n, dtype=float)
    rows = [(limits.gap_cap, limits.late_cap, min(limits.budgets[i], limits.budgets[i + 1]))
            for i in range(len(loads) - 1) if loads[i] <= load_n <= loads[i + 1]]
    return np.array(rows)


class RigClock:
    """A rig's time: it passes only when asked (``sleep``: a read time-out while the DAQ is
    silent, an answer the test makes late), never with this machine's own delays. Starts at 0,
    far from ``time.time()``, so that the backend takes a frame's arrival at the clock's now
    (a bus time stamp is used only within a second before it)."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += max(seconds, 0.0)


class RigBackend(CanBackend):
    """The CAN backend on a rig's clock (its ``wall_clock``, for arrivals and answer ages).

    A read waits, however long this machine takes, while ``daq_running()``: a running DAQ sends
    the next sample (in lockstep once the previous one is answered), so waiting longer than the
    read's time-out is this machine's delay, not silence, and no time passes on the clock. Once
    the DAQ has stopped, what it sent before is read, then the read times out and its time-out
    passes on the clock. ``answer_delay_s(k)``, if given: how long the answer to the k-th sample
    read (0: the first) takes on the clock, from the sample's arrival until it has been sent."""

    def __init__(self, *args, daq_running: Callable[[], bool], clock: RigClock,
                 answer_delay_s: Callable[[int], float] | None = None, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.clock = clock
        self.wall_clock = clock
        self.daq_running = daq_running
        self.answer_delay_s = answer_delay_s
        self.samples_read = 0           # samples delivered since the backend was made
        self._unanswered = False

    def _read(self, sample: Sample, timeout: float | None) -> bool:
        if self._wait_for_sample(sample):
            self.samples_read += 1
            self._unanswered = True
            return True
        self.clock.sleep(1.0 if timeout is None else timeout)
        return False

    def _wait_for_sample(self, sample: Sample) -> bool:
        since = time.monotonic()
        while self.daq_running():
            if super()._read(sample, WAIT_SLICE_S):
                return True
            if time.monotonic() - since > HUNG_DAQ_S:
                raise HalConnectionLost(f"rig: the DAQ runs but sent no sample for {HUNG_DAQ_S:g} s")
        return super()._read(sample, 0.0)           # what it sent before it stopped

    def _write(self, voltages: np.ndarray) -> None:
        if self._unanswered and self.answer_delay_s is not None:
            self.clock.sleep(self.answer_delay_s(self.samples_read - 1))
        self._unanswered = False
        super()._write(voltages)


class SimRig:
    name = "sim"

    def __init__(self, **plant_overrides) -> None:
        self.plant = make_plant(**plant_overrides)
        self.hal = SimBackend(self.plant, GEOMETRY)

    def silence(self) -> None:
        self.hal.go_silent()

    def close(self) -> None:
        self.hal.close()


class _RigBackend(RigBackend):
    """The CAN backend of a rig: the first open starts the emulator, so that no sample is sent
    before the controller listens (the virtual bus drops frames nobody receives)."""

    def __init__(self, emulator: CanPlantEmulator, *args, **kwargs) -> None:
        super().__init__(*args, daq_running=lambda: emulator.running, **kwargs)
        self._emulator = emulator

    def _open(self) -> None:
        super()._open()
        if not self._emulator.running:
            self._emulator.start()


class CanRig:
    """The CAN backend (``hal``) and the plant emulator (``emulator``) on a virtual bus of their
    own, on the rig's clock (``clock``). ``samples_sent``: the DAQ_Strains frames the emulator
    has sent (each is in the backend's queue once counted). The emulator's DAQ_Strains rate is
    not checked (``rate_tolerance`` 0): in lockstep it runs at the controller's pace, and on
    the rig's clock no time passes between samples; the check is tested on frames with
    constructed time stamps (tests/hal/test_can.py). ``answer_timeout_s``: how long the
    emulator waits for an answer before it sends the next sample anyway; 0.05 s by default, for
    the backend tests that close and reopen the bus mid-stream (an answer lost with the old bus
    must not hold the emulator up); a closed loop passes ``LOCKSTEP_TIMEOUT_S``."""

    name = "can"

    def __init__(self, pace: str = "lockstep", latency_samples: int = 0, on_step=None,
                 answer_timeout_s: float = 0.05, answer_delay_s: Callable[[int], float] | None = None,
                 **plant_overrides) -> None:
        channel = f"beamctl-test-{next(_channels)}"
        self.plant = make_plant(**plant_overrides)
        self.clock = RigClock()
        self.samples_sent = 0
        self.emulator_bus = can.Bus(interface="virtual", channel=channel)
        send = self.emulator_bus.send

        def counted(msg: can.Message, timeout: float | None = None) -> None:
            send(msg, timeout)
            if msg.arbitration_id == STRAINS_ID:
                self.samples_sent += 1

        self.emulator_bus.send = counted
        self.emulator = CanPlantEmulator(self.emulator_bus, self.plant, GEOMETRY, pace=pace,
                                         answer_timeout_s=answer_timeout_s,
                                         latency_samples=latency_samples, on_step=on_step)
        self.hal = _RigBackend(self.emulator, RATE_HZ, "virtual", channel, rate_tolerance=0.0,
                               clock=self.clock, answer_delay_s=answer_delay_s)

    def loop(self, controller: Controller, **kwargs) -> ControlLoop:
        """The control loop of ``controller`` on this rig's backend and clock."""
        return ControlLoop(controller, self.hal, clock=self.clock, **kwargs)

    def wait_sent(self, samples: int) -> None:
        """Until the emulator has sent ``samples`` samples (however long this machine takes)."""
        wait_until(lambda: self.samples_sent >= samples, f"the emulator sending {samples} samples")

    def silence(self) -> None:
        self.emulator.stop()

    def close(self) -> None:
        self.emulator.stop()
        self.hal.close()
        self.emulator_bus.shutdown()


def service_backends(monkeypatch, emulator: CanPlantEmulator) -> RigClock:
    """Make the CAN backends a command builds (assembly/run.py ``build_hal``, which takes
    ``CanBackend`` from hal/can_backend.py when it runs) rig backends of ``emulator`` on a
    ``RigClock`` of their own, which is returned: they wait for its samples while it runs, and an
    answer takes no time. The command's loop keeps its own clock: it only ever reads it for a
    silence, and its reads time out only once the emulator has stopped."""
    clock = RigClock()

    def backend(*args, **kwargs) -> RigBackend:
        return RigBackend(*args, daq_running=lambda: emulator.running, clock=clock, **kwargs)

    monkeypatch.setattr(can_backend, "CanBackend", backend)
    return clock


def wait_until(condition: Callable[[], bool], what: str, timeout_s: float = HUNG_DAQ_S) -> None:
    """Until ``condition()`` holds: a guard against a hang, not a time the test depends on."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"not within {timeout_s:g} s: {what}"
        time.sleep(0.005)


RIGS = {"sim": SimRig, "can": CanRig}
