"""The ``sim`` backend: the beam of models/plant.py in-process.

Each read measures the plant (strains with noise, load cell); each write converts the six
voltages into the four lateral forces with the rig's stack geometry and advances the plant
one sample. In ``simulated`` pace the plant runs as fast as the loop (an experiment runs
faster than real time); in ``wallclock`` pace a read waits until the sample is due.
"""

from __future__ import annotations

import time

import numpy as np

from beamctl.hal.base import HalBase, HalConfigurationError, Sample
from beamctl.models.actuators import StackGeometry
from beamctl.models.plant import Plant

PACES = ("simulated", "wallclock")


class SimBackend(HalBase):
    name = "sim"

    def __init__(self, plant: Plant, geometry: StackGeometry, pace: str = "simulated") -> None:
        super().__init__(plant.config.sample_rate_hz)
        if pace not in PACES:
            raise HalConfigurationError(f"sim pace {pace!r}: expected one of {PACES}")
        self.plant = plant
        self.geometry = geometry
        self.pace = pace
        self._force_matrix = geometry.force_matrix()
        self._bias = np.full(6, geometry.bias_voltage_v)
        self._delta = np.zeros(6)
        self._forces = np.zeros(4)
        self._sequence = 0
        self._silent = False
        self._start = 0.0

    def _open(self) -> None:
        self.plant.reset()
        self._sequence = 0
        self._silent = False
        self._start = time.monotonic()

    def _close(self) -> None:
        pass

    def go_silent(self) -> None:
        """Stop producing samples (a DAQ outage): reads time out from now on."""
        self._silent = True

    def _read(self, sample: Sample, timeout: float | None) -> bool:
        if self._silent:
            if self.pace == "wallclock" and timeout:
                time.sleep(timeout)
            return False
        if self.pace == "wallclock":
            delay = self._start + self.plant.time - time.monotonic()
            if delay > 0:
                if timeout is not None and delay > timeout:
                    time.sleep(timeout)
                    return False
                time.sleep(delay)
        strains, load = self.plant.measure()
        self._sequence += 1
        sample.sequence = self._sequence
        sample.missed = 0
        sample.timestamp = self.plant.time
        sample.strains[:] = strains
        sample.axial_load = load
        return True

    def _write(self, voltages: np.ndarray) -> None:
        np.subtract(voltages, self._bias, out=self._delta)
        np.dot(self._force_matrix, self._delta, out=self._forces)
        self.plant.step(self._forces)

    def status(self) -> dict:
        out = super().status()
        deflection, angle = self.plant.deflection()
        out.update(plant_time_s=self.plant.time, axial_load_N=self.plant.axial_load,
                   deflection_mm=1e3 * deflection, deflection_angle_deg=angle)
        return out
