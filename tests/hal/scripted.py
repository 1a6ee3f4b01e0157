"""A CAN backend on a scripted bus, on a clock of the test's own: frames with the time stamps the
test constructs, so that what depends on time (the alive counter's window, the answer's age) is
decided by the script, never by the machine's speed.

``ScriptedBus`` is a python-can bus (``ScriptedBackend`` opens one) whose ``recv`` returns the
frames put into it, in order, and whose ``send`` keeps the frames sent and calls ``on_send``.
``ScriptedDaq`` puts DAQ frames into it, stamped ``t0 + k * period`` for sample ``k``, and sets
the backend's clock to a little after the newest stamp.
"""

from __future__ import annotations

import collections
import time

import can
import pytest

from beamctl.hal.base import HalStaleData
from beamctl.hal.can_backend import CanBackend
from beamctl.hal.dbc import Contract

CONTRACT = Contract()
RATE_HZ = 2500.0
PERIOD_S = 1.0 / RATE_HZ


class ScriptedBus(can.BusABC):
    def __init__(self, channel, **kwargs) -> None:
        self.channel_info = f"scripted {channel}"
        self.queue: collections.deque[can.Message] = collections.deque()
        self.sent: list[can.Message] = []
        self.on_send = None
        super().__init__(channel=channel, **kwargs)

    def put(self, msg: can.Message) -> None:
        self.queue.append(msg)

    def _recv_internal(self, timeout):
        if self.queue:
            return self.queue.popleft(), False
        if timeout:
            time.sleep(min(timeout, 0.01))
        return None, False

    def send(self, msg: can.Message, timeout=None) -> None:
        self.sent.append(msg)
        if self.on_send is not None:
            self.on_send(msg)


class ScriptedBackend(CanBackend):
    """The CAN backend on a ``ScriptedBus`` (everything else as on any python-can bus)."""

    def _make_bus(self, options: dict) -> can.BusABC:
        return ScriptedBus(self.channel)


class Clock:
    """The backend's wall clock, set by the script."""

    def __init__(self, now: float) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


class ScriptedDaq:
    """DAQ frames into a scripted backend's bus, sample ``k`` stamped ``t0 + k * period``."""

    LATENCY_S = 50e-6          # the backend's clock runs this much after the newest frame's stamp

    def __init__(self, backend: CanBackend, t0: float = 1000.0) -> None:
        self.backend = backend
        self.bus: ScriptedBus = backend.bus
        self.t0 = t0
        self.clock = Clock(t0)
        backend.wall_clock = self.clock

    def stamp(self, k: float) -> float:
        return self.t0 + k * PERIOD_S

    def frame(self, frame_id: int, data: bytes, k: float, **fields) -> None:
        stamp = self.stamp(k)
        self.bus.put(can.Message(arbitration_id=frame_id, data=data, timestamp=stamp,
                                 **{"is_extended_id": False, **fields}))
        self.clock.now = max(self.clock.now, stamp + self.LATENCY_S)

    def strains(self, seq: int, k: float, values=(1e-5, -2e-5, 3e-6, 0.0), **fields) -> None:
        self.frame(CONTRACT.strains.frame_id, CONTRACT.strains.encode([*values, seq % 256, 0]), k, **fields)

    def load(self, seq: int, k: float, value: float = 1500.0) -> None:
        self.frame(CONTRACT.load.frame_id, CONTRACT.load.encode([value, seq % 256, 0]), k)

    def samples(self, timeout: float = 0.001) -> list[tuple[int, int]]:
        """(sequence, missed) of every sample the backend delivers from what is queued."""
        out = []
        while self.bus.queue:
            try:
                s = self.backend.read(timeout=timeout)
            except HalStaleData:
                break
            out.append((s.sequence, s.missed))
        return out


@pytest.fixture
def scripted():
    """Makes CAN backends (2500 Hz, rate check off, each frame read in turn: ``newest_only``
    False unless asked for) on scripted buses, each with its DAQ."""
    backends = []

    def make(**settings) -> ScriptedDaq:
        backends.append(ScriptedBackend(RATE_HZ, "scripted", f"scripted-{len(backends)}",
                                        **{"rate_tolerance": 0.0, "newest_only": False, **settings}).open())
        return ScriptedDaq(backends[-1])

    yield make
    for backend in backends:
        backend.close()
