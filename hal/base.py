"""The hardware abstraction: one interface, one backend per kind of hardware.

In the style of python-can's ``BusABC``: the shared behaviour (open/close as a context
manager, time-outs, staleness, the typed errors) is written once here; a backend supplies a
narrow set of hooks (``_open``, ``_read``, ``_write``, ``_close``). Backends are chosen by
name and imported lazily (``hal.create``), so the simulated plant never needs a CAN
library, and nothing ever falls back from the DAQ to the plant.

One ``read()`` returns one sample: time stamp, sequence number, the samples of the source
skipped since the previous one, the four strains (eps_y1, eps_z1, eps_y2, eps_z2) and the axial
load. ``write()`` takes the six stack voltages (a1, a2, a3 at support A, b1, b2, b3 at
support B).
"""

from __future__ import annotations

import abc

import numpy as np


class HalError(Exception):
    """Base of all HAL errors; the safety supervisor faults on any of them."""


class HalConfigurationError(HalError):
    """The backend was configured wrongly (unknown name, bad setting)."""


class HalConnectionLost(HalError):
    """The hardware went away (bus-off, process gone, device unplugged)."""


class HalStaleData(HalError):
    """No new sample arrived within the time-out."""


class HalProtocolError(HalError):
    """Data arrived but does not follow the contract (wrong frame, bad value)."""


class Sample:
    """One sensor sample. Backends fill one instance in place on each read: it is valid until
    the next ``read()`` (copy what must outlive it).

    ``missed`` is the number of samples of the source skipped between the previous sample
    delivered and this one: sampled by the source but never delivered (lost on the way, or
    dropped as invalid), which the controller bridges by catching its compensator up. It is 0
    for samples in order and for the first sample after ``open``; the ``sim`` backend never skips
    one; the ``can`` backend counts the counter values a forward jump of the DAQ_Strains
    ``sequence`` skipped (the jump minus one), and 0 after a resynchronisation to a new stream,
    where the counter cannot tell (hal/e2e.py; the time stamp tells the gap)."""

    __slots__ = ("timestamp", "sequence", "missed", "strains", "axial_load")

    def __init__(self) -> None:
        self.timestamp = 0.0          # s, backend clock (plant time or receive time)
        self.sequence = -1            # rolling counter of the source
        self.missed = 0               # samples of the source skipped since the previous one (0: in order)
        self.strains = np.zeros(4)    # eps_y1, eps_z1, eps_y2, eps_z2
        self.axial_load = 0.0         # N, load cell


class HalBase(abc.ABC):
    """Shared behaviour of every backend. Use as a context manager::

        with create(name, **settings) as hal:
            sample = hal.read(timeout=0.01)
            hal.write(voltages)
    """

    name = "base"

    def __init__(self, sample_rate_hz: float) -> None:
        if not sample_rate_hz > 0:
            raise HalConfigurationError(f"sample rate must be positive, got {sample_rate_hz!r}")
        self.sample_rate_hz = float(sample_rate_hz)
        self.period_s = 1.0 / self.sample_rate_hz
        self.is_open = False
        self.reads = 0
        self.writes = 0
        self._sample = Sample()
        self.state_code = self.fault_code = self.flags_code = 0
        # seconds from the arrival of the sample the last write answered to that write's frame
        # having been sent (the send returned), for backends that can measure it (NaN: not
        # measured)
        self.answer_age_s = float("nan")
        # the largest strain the hardware can report (a reading there may be clipped); None: no
        # such limit
        self.strain_full_scale: float | None = None
        # how long the hardware holds the last voltages without an answer before it falls back
        # to bias by itself (a DAQ's silence time-out); None: it holds them
        self.daq_silence_timeout_s: float | None = None

    # -- hooks for backends --------------------------------------------------------------------
    @abc.abstractmethod
    def _open(self) -> None:
        """Acquire the hardware (or start the plant)."""

    @abc.abstractmethod
    def _read(self, sample: Sample, timeout: float | None) -> bool:
        """Fill ``sample`` with the next sample; False if none arrived within ``timeout``."""

    @abc.abstractmethod
    def _write(self, voltages: np.ndarray) -> None:
        """Send six voltages."""

    @abc.abstractmethod
    def _close(self) -> None:
        """Release the hardware. Must be safe to call after a failed ``_open``."""

    # -- shared behaviour --------------------------------------------------------------------------
    def open(self) -> HalBase:
        if not self.is_open:
            self._open()
            self.is_open = True
        return self

    def close(self) -> None:
        if self.is_open:
            self.is_open = False
            self._close()

    def __enter__(self) -> HalBase:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def read(self, timeout: float | None = None) -> Sample:
        """The next sample (the same object each time, refilled). Raises HalStaleData when
        nothing arrives within ``timeout`` seconds (None: ten sample periods)."""
        if not self.is_open:
            raise HalConnectionLost(f"{self.name}: read on a closed backend")
        wait = 10 * self.period_s if timeout is None else timeout
        if not self._read(self._sample, wait):
            raise HalStaleData(f"{self.name}: no sample within {wait * 1e3:.1f} ms")
        self.reads += 1
        return self._sample

    def write(self, voltages: np.ndarray) -> None:
        """Send the six stack voltages (V)."""
        if not self.is_open:
            raise HalConnectionLost(f"{self.name}: write on a closed backend")
        self._write(voltages)
        self.writes += 1

    def discard_backlog(self) -> int:
        """Drop the samples already queued before the controller was ready to answer them, all
        but the newest, which the next read returns; return how many were dropped. Called once
        before the first read."""
        if not self.is_open:
            raise HalConnectionLost(f"{self.name}: discard on a closed backend")
        return self._discard_backlog()

    def _discard_backlog(self) -> int:
        return 0

    def announce(self, state: int, fault: int, flags: int = 0) -> None:
        """Publish the status and report it to the hardware now (the last word before the
        controller exits: STOPPED or FAULT), not at the next heartbeat."""
        self.publish_status(state, fault, flags)
        if self.is_open:
            self._announce()

    def _announce(self) -> None:  # noqa: B027 (a hook: backends without a status channel keep it empty)
        """Send the published status to the hardware now (backends that report it)."""

    def publish_status(self, state: int, fault: int, flags: int = 0) -> None:
        """The controller's safety state, latched fault and flags, for backends that report
        them to the hardware (the CAN heartbeat); the base only keeps them for ``status()``."""
        self.state_code, self.fault_code, self.flags_code = int(state), int(fault), int(flags) & 0xFF

    def status(self) -> dict:
        """Counters for reports (backends add their own)."""
        return {"backend": self.name, "reads": self.reads, "writes": self.writes}
