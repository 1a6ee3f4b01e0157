"""A scripted HAL for driving the loop in tests."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from beamctl.hal.base import HalBase, HalConnectionLost, Sample

# what a script step can be: a (strains, load) pair, None (no sample within the time-out),
# an exception instance (raised from read), or a callable run before producing a sample
Step = tuple | None | Exception | Callable[[], None]


class ScriptedHal(HalBase):
    """Plays ``script`` one entry per read, then ``default``: a (strains, load) pair, or a
    function of the sequence number returning one."""

    name = "scripted"

    def __init__(self, sample_rate_hz: float, script: list[Step] | None = None,
                 default: tuple = ((0.0, 0.0, 0.0, 0.0), 1000.0), write_delay: float = 0.0,
                 fail_write_after: int | None = None, sleep: Callable[[float], None] = time.sleep,
                 answer_ages_s: Callable[[int], float] | None = None) -> None:
        super().__init__(sample_rate_hz)
        self.sleep = sleep                      # how a read time-out lets its time pass
        self.answer_ages_s = answer_ages_s      # the age each answer reports, by sequence
        self.opened: list[str] = []             # what happened, in order (for start-up tests)
        self.script = list(script or [])
        self.default = default
        self.write_delay = write_delay
        self.fail_write_after = fail_write_after
        self.written: list[np.ndarray] = []
        self.sequence = 0

    def _open(self) -> None:
        self.opened.append("open")

    def _close(self) -> None:
        pass

    def _read(self, sample: Sample, timeout) -> bool:
        step = self.script.pop(0) if self.script else self._default()
        while callable(step):
            step()
            step = self.script.pop(0) if self.script else self._default()
        if step is None:            # nothing within the time-out: as a real bus, the time passes
            if timeout:
                self.sleep(timeout)
            return False
        if isinstance(step, Exception):
            raise step
        strains, load = step
        self.sequence += 1
        sample.sequence = self.sequence
        sample.timestamp = self.sequence / self.sample_rate_hz
        sample.strains[:] = strains
        sample.axial_load = load
        return True

    def _default(self):
        return self.default(self.sequence) if callable(self.default) else self.default

    def _write(self, voltages: np.ndarray) -> None:
        if self.fail_write_after is not None and len(self.written) >= self.fail_write_after:
            raise HalConnectionLost("scripted: amplifier link lost")
        if self.write_delay:
            time.sleep(self.write_delay)
        self.written.append(np.array(voltages))
        if self.answer_ages_s is not None:
            self.answer_age_s = self.answer_ages_s(self.sequence)

