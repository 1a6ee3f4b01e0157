"""The CAN plant emulator: the simulated beam behind the DBC, playing the DAQ.

Each sample it sends ``DAQ_Strains`` (and every ``SampleDivisor`` samples ``DAQ_Load``),
then applies the latest ``CTRL_Voltages`` it received and advances the plant one sample.
``wallclock`` pace sends at the sample rate of the wall clock, as the DAQ does; ``lockstep``
waits for the controller's answer to each sample before stepping (for tests and bench runs
that must not depend on the machine's load: however late the answer, the plant applies it to
the sample it answers). Run it in a thread (tests, over python-can's ``virtual`` interface) or
as its own process: ``beamctl plant --can socketcan:vcan0``. ``on_step(plant, voltages)`` is
called in the emulator's own thread after every plant step, with the voltages the stacks had
during that step: the one consistent place to observe the plant while it runs.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import can
import numpy as np

from beamctl.hal.dbc import STRAIN_SIGNALS, VOLTAGE_SIGNALS, Contract
from beamctl.models.actuators import StackGeometry
from beamctl.models.plant import Plant

PACES = ("wallclock", "lockstep")
WAIT_SLICE_S = 0.05        # a lockstep wait looks at the stop request this often


class CanPlantEmulator:
    def __init__(self, bus: can.BusABC, plant: Plant, geometry: StackGeometry,
                 contract: Contract | None = None, pace: str = "wallclock",
                 answer_timeout_s: float = 0.05, latency_samples: int = 0,
                 on_step: Callable[[Plant, np.ndarray], None] | None = None) -> None:
        if pace not in PACES:
            raise ValueError(f"emulator pace {pace!r}: expected one of {PACES}")
        self.bus = bus
        self.plant = plant
        self.contract = contract or Contract()
        self.pace = pace
        self.answer_timeout_s = answer_timeout_s
        self.on_step = on_step
        self.period_s = plant.config.sample_period
        self._force_matrix = geometry.force_matrix()
        self._voltages = np.full(6, geometry.bias_voltage)
        self._bias = np.full(6, geometry.bias_voltage)
        self._decoded = [0.0] * len(self.contract.voltages.names)
        c = self.contract
        self._voltage_order = c.voltages.order(VOLTAGE_SIGNALS)
        self._voltage_sequence = c.voltages.index("sequence")
        self._strain_order = c.strains.order(STRAIN_SIGNALS)
        self._strain_values = [0.0] * len(c.strains.names)
        self._load_values = [0.0] * len(c.load.names)
        self.samples = 0
        self.voltage_frames = 0
        self.missed_answers = 0
        self.status_frames = 0
        self.last_state = None
        # sensor frame sent -> voltage frame received, seconds (lockstep pace only)
        self.latencies_s = np.full(latency_samples, np.nan)
        self.stop_event = threading.Event()
        self._thread: threading.Thread | None = None

    # -- one sample ----------------------------------------------------------------------------------
    def _send_sample(self) -> None:
        c = self.contract
        strains, load = self.plant.measure()
        if self.samples % c.load.divisor == 0:   # the load first: the sample then carries it
            lv = self._load_values
            lv[c.load.index("axial_load")] = min(max(load, -500.0), 6000.0)
            lv[c.load.index("sequence")] = (self.samples // c.load.divisor) & 0xFF
            self.bus.send(can.Message(arbitration_id=c.load.frame_id, data=c.load.encode(lv),
                                      is_extended_id=False))
        v = self._strain_values
        for k, i in enumerate(self._strain_order):
            v[i] = min(max(float(strains[k]), -0.004), 0.004)
        v[c.strains.index("sequence")] = self.samples & 0xFF
        self.bus.send(can.Message(arbitration_id=c.strains.frame_id, data=c.strains.encode(v),
                                  is_extended_id=False))

    def _take(self, msg: can.Message) -> int | None:
        """Apply a received frame; for a voltage frame, return its sequence (the low four bits
        of the sample it answers), else None."""
        c = self.contract
        if msg.is_error_frame:
            return None
        if msg.arbitration_id == c.voltages.frame_id and msg.dlc == c.voltages.length:
            if c.voltages.decode_into(msg.data, self._decoded):
                for k, i in enumerate(self._voltage_order):
                    self._voltages[k] = self._decoded[i]
                self.voltage_frames += 1
                return int(self._decoded[self._voltage_sequence])
        elif msg.arbitration_id == c.status.frame_id:
            self.status_frames += 1
            values = [0] * len(c.status.names)
            c.status.decode_into(msg.data, values)
            self.last_state = int(values[c.status.index("state")])
        return None

    def _step_plant(self) -> None:
        self.plant.step(self._force_matrix @ (self._voltages - self._bias))
        self.samples += 1
        if self.on_step is not None:
            self.on_step(self.plant, self._voltages)

    def _await_answer(self) -> bool:
        """Lockstep: take frames until the voltage frame answering the sample just sent (True),
        or until ``answer_timeout_s`` or a stop request (False). A late answer to an earlier
        sample is applied (the stacks take the latest voltages) but does not end the wait."""
        expected = self.samples & 0xF
        deadline = time.monotonic() + self.answer_timeout_s
        while not self.stop_event.is_set():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            msg = self.bus.recv(min(remaining, WAIT_SLICE_S))
            if msg is not None and self._take(msg) == expected:
                return True
        self.missed_answers += 1
        return False

    def run(self, max_samples: int | None = None) -> None:
        """Emulate until ``stop()`` (or ``max_samples``)."""
        self.plant.reset()
        start = time.monotonic()
        while not self.stop_event.is_set() and (max_samples is None or self.samples < max_samples):
            sent = time.perf_counter()
            self._send_sample()
            if self.pace == "lockstep":
                if self._await_answer() and self.samples < len(self.latencies_s):
                    self.latencies_s[self.samples] = time.perf_counter() - sent
            else:
                next_time = start + (self.samples + 1) * self.period_s
                while True:
                    remaining = next_time - time.monotonic()
                    if remaining <= 0:
                        break
                    msg = self.bus.recv(remaining)
                    if msg is not None:
                        self._take(msg)
            self._step_plant()

    def start(self, max_samples: int | None = None) -> CanPlantEmulator:
        self._thread = threading.Thread(target=self.run, args=(max_samples,), name="can-plant", daemon=True)
        self._thread.start()
        return self

    @property
    def running(self) -> bool:
        """Started in its own thread (``start``) and not yet finished."""
        return self._thread is not None and self._thread.is_alive()

    def join(self, timeout: float | None = None) -> None:
        """Wait for a started emulator to finish (``max_samples`` reached, or stopped)."""
        if self._thread is not None:
            self._thread.join(timeout)

    def stop(self) -> None:
        self.stop_event.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
