"""The CAN plant emulator: the simulated beam behind the DBC, playing the DAQ.

Each sample it sends ``DAQ_Strains`` (and every ``SampleDivisor`` samples ``DAQ_Load``),
then applies the latest ``CTRL_Voltages`` it received and advances the plant one sample.
``wallclock`` pace sends at the sample rate of the wall clock, as the DAQ does; ``lockstep``
waits for the controller's answer to each sample before stepping (for tests and bench runs
that must not depend on the machine's load). Run it in a thread (tests, over python-can's
``virtual`` interface) or as its own process: ``beamctl plant --can socketcan:vcan0``.
"""

from __future__ import annotations

import threading
import time

import can
import numpy as np

from beamctl.hal.dbc import STRAIN_SIGNALS, VOLTAGE_SIGNALS, Contract
from beamctl.models.actuators import StackGeometry
from beamctl.models.plant import Plant

PACES = ("wallclock", "lockstep")


class CanPlantEmulator:
    def __init__(self, bus: can.BusABC, plant: Plant, geometry: StackGeometry,
                 contract: Contract | None = None, pace: str = "wallclock",
                 answer_timeout: float = 0.05, latency_samples: int = 0) -> None:
        if pace not in PACES:
            raise ValueError(f"emulator pace {pace!r}: expected one of {PACES}")
        self.bus = bus
        self.plant = plant
        self.geometry = geometry
        self.contract = contract or Contract()
        self.pace = pace
        self.answer_timeout = answer_timeout
        self.period = plant.config.sample_period
        self._force_matrix = geometry.force_matrix()
        self._voltages = np.full(6, geometry.bias_voltage)
        self._bias = np.full(6, geometry.bias_voltage)
        self._decoded = [0.0] * len(self.contract.voltages.names)
        c = self.contract
        self._voltage_order = c.voltages.order(VOLTAGE_SIGNALS)
        self._strain_order = c.strains.order(STRAIN_SIGNALS)
        self._strain_values = [0.0] * len(c.strains.names)
        self._load_values = [0.0] * len(c.load.names)
        self.samples = 0
        self.voltage_frames = 0
        self.missed_answers = 0
        self.status_frames = 0
        self.last_state = None
        # sensor frame sent -> voltage frame received, seconds (lockstep pace only)
        self.latencies = np.full(latency_samples, np.nan)
        self.stop_event = threading.Event()
        self._thread: threading.Thread | None = None

    # -- one sample ----------------------------------------------------------------------------------
    def _send_sample(self) -> None:
        c = self.contract
        strains, load = self.plant.measure()
        v = self._strain_values
        for k, i in enumerate(self._strain_order):
            v[i] = min(max(float(strains[k]), -0.004), 0.004)
        v[c.strains.index("sequence")] = self.samples & 0xFF
        self.bus.send(can.Message(arbitration_id=c.strains.frame_id, data=c.strains.encode(v),
                                  is_extended_id=False))
        if self.samples % c.load.divisor == 0:
            lv = self._load_values
            lv[c.load.index("axial_load")] = min(max(load, -500.0), 6000.0)
            lv[c.load.index("sequence")] = (self.samples // c.load.divisor) & 0xFF
            self.bus.send(can.Message(arbitration_id=c.load.frame_id, data=c.load.encode(lv),
                                      is_extended_id=False))

    def _take(self, msg: can.Message) -> bool:
        """Apply a received frame; True for a voltage frame."""
        c = self.contract
        if msg.is_error_frame:
            return False
        if msg.arbitration_id == c.voltages.frame_id and msg.dlc == c.voltages.length:
            if c.voltages.decode_into(msg.data, self._decoded):
                for k, i in enumerate(self._voltage_order):
                    self._voltages[k] = self._decoded[i]
                self.voltage_frames += 1
                return True
        elif msg.arbitration_id == c.status.frame_id:
            self.status_frames += 1
            values = [0] * len(c.status.names)
            c.status.decode_into(msg.data, values)
            self.last_state = int(values[c.status.index("state")])
        return False

    def _step_plant(self) -> None:
        self.plant.step(self._force_matrix @ (self._voltages - self._bias))
        self.samples += 1

    def run(self, max_samples: int | None = None) -> None:
        """Emulate until ``stop()`` (or ``max_samples``)."""
        self.plant.reset()
        start = time.monotonic()
        while not self.stop_event.is_set() and (max_samples is None or self.samples < max_samples):
            sent = time.perf_counter()
            self._send_sample()
            if self.pace == "lockstep":
                deadline = time.monotonic() + self.answer_timeout
                answered = False
                while not answered:
                    msg = self.bus.recv(max(deadline - time.monotonic(), 0.0))
                    if msg is None:
                        self.missed_answers += 1
                        break
                    answered = self._take(msg)
                if answered and self.samples < len(self.latencies):
                    self.latencies[self.samples] = time.perf_counter() - sent
            else:
                next_time = start + (self.samples + 1) * self.period
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

    def stop(self) -> None:
        self.stop_event.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
