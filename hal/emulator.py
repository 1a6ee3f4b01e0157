"""The CAN plant emulator: the simulated beam behind the DBC, playing the DAQ, duties included.

Each sample it sends ``DAQ_Strains`` (and every ``SampleDivisor`` samples ``DAQ_Load``, before
the strains), then applies the latest valid ``CTRL_Voltages`` it received and advances the
plant one sample. It keeps the DAQ's side of the contract (hal/beamctl.dbc), with the
controller's codecs (hal/dbc.py: the CRC over each message's Data ID): a voltage frame is
applied only if it is a standard data frame of the right length with a good CRC and a new
sequence, everything else is counted and dropped (a voltage frame's sequence names the sample it
answers: the DAQ knows which samples it sent, so "new" means an answer to a sample of the last
half counter span that is later than the one applied last); when no valid voltage frame has
arrived for ``silence_timeout_s`` (the DBC's ``SilenceTimeoutMs``) it ramps the stacks linearly to
bias within ``fallback_ramp_s`` (``FallbackRampMs``) by itself, and holds bias until valid frames
come again.

``wallclock`` pace sends at the sample rate of the wall clock, as the DAQ does; ``lockstep``
waits for the controller's answer to each sample before stepping (for tests and bench runs
that must not depend on the machine's load: however late the answer, the plant applies it to
the sample it answers). Run it in a thread (tests, over python-can's ``virtual`` interface) or
as its own process: ``beamctl plant --can socketcan:vcan0``. ``on_step(plant, voltages)`` is
called in the emulator's own thread after every plant step, with the voltages the stacks had
during that step: the one consistent place to observe the plant while it runs.

The controller's latency is measured per sample as the DAQ sees it: from the send of a
``DAQ_Strains`` frame to the bus time stamp of the ``CTRL_Voltages`` frame that answers it (the
same sequence), in ``latencies_s`` (NaN where a sample was not answered).

What the beam saw of the controller's stalls, in the DAQ's own clock: the plant steps in a row
during which no new answer was applied (the stacks held one voltage; 0 while every sample is
answered before the next), the longest of the run (``held_longest``) and of each minute of
plant time (``held_longest_per_minute``), counted while answers come (a controller that has
stopped answering is not a stall: the DAQ falls back to bias on its own); and every hold of at
least ``long_hold_s`` (5 ms) with its plant time, load and the samples of it this process did not
send itself (``long_holds``: a hold made of the emulator's own lateness is the simulated DAQ's
stall, not the controller's).
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable

import can
import numpy as np

from beamctl.hal import frames, localbus
from beamctl.hal.dbc import STRAIN_SIGNALS, VOLTAGE_SIGNALS, Contract
from beamctl.hal.e2e import _bytes
from beamctl.models.actuators import StackGeometry
from beamctl.models.plant import Plant

PACES = ("wallclock", "lockstep")
WAIT_SLICE_S = 0.05        # a lockstep wait looks at the stop request this often
NOTHING = -1               # ``_recv``: no frame came
_RAW_ID = struct.Struct("<I")
_RAW_TIME = struct.Struct("<d")


class CanPlantEmulator:
    def __init__(self, bus: can.BusABC, plant: Plant, geometry: StackGeometry,
                 contract: Contract | None = None, pace: str = "wallclock",
                 answer_timeout_s: float = 0.05, latency_samples: int = 0,
                 silence_timeout_s: float | None = None, fallback_ramp_s: float | None = None,
                 on_step: Callable[[Plant, np.ndarray], None] | None = None, skip_late: bool = False) -> None:
        if pace not in PACES:
            raise ValueError(f"emulator pace {pace!r}: expected one of {PACES}")
        self.bus = bus
        self.plant = plant
        self.contract = contract or Contract()
        c = self.contract
        self.pace = pace
        self.answer_timeout_s = answer_timeout_s
        self.silence_timeout_s = c.silence_timeout_s if silence_timeout_s is None else silence_timeout_s
        self.fallback_ramp_s = c.fallback_ramp_s if fallback_ramp_s is None else fallback_ramp_s
        if not self.silence_timeout_s > 0:
            raise ValueError(f"silence time-out {self.silence_timeout_s!r} s: the DAQ must fall back "
                             f"after a positive time without valid voltage frames")
        self.on_step = on_step
        self.period_s = plant.config.period_s
        self._force_matrix = geometry.force_matrix()
        self._voltages = np.full(6, geometry.bias_voltage_v)
        self._bias = np.full(6, geometry.bias_voltage_v)
        self._fallback_from = self._bias.copy()
        self._swing = np.zeros(6)           # the voltages less bias, and the forces they give
        self._forces = np.zeros(4)
        self._decoded = [0.0] * len(c.voltages.names)
        self._voltage_order = c.voltages.order(VOLTAGE_SIGNALS)
        self._voltage_sequence = c.voltages.index("sequence")
        self._modulus = c.strains.sequence_modulus
        self._last_applied = -1            # index of the sample whose answer was applied last
        self._strain_order = c.strains.order(STRAIN_SIGNALS)
        self._strain_values = [0.0] * len(c.strains.names)
        self._strain_limit = c.strains.signals[self._strain_order[0]].maximum
        self._load_values = [0.0] * len(c.load.names)
        self._status_values = [0] * len(c.status.names)
        self._sent_at = np.full(c.strains.sequence_modulus, np.nan)   # time.time() of each sequence
        self.samples = 0
        self.voltage_frames = 0
        self.rejected = {"extended_ids": 0, "remote_frames": 0, "wrong_length": 0, "crc_errors": 0,
                         "out_of_range": 0, "repeated": 0, "behind": 0}
        self.missed_answers = 0
        # wallclock: samples whose time passed while this process was held up are stepped and
        # not sent (a DAQ's clock; ``beamctl plant``), instead of sent late in a burst (a thread
        # beside the controller in one interpreter, where the lateness is the interpreter's)
        self.skip_late = skip_late
        self.skipped = 0                   # samples stepped but not sent
        self.status_frames = 0
        self.last_state = None
        self.fallbacks = 0                 # times the DAQ fell back to bias on its own
        self.falling_back = False
        self._last_valid = None            # time.monotonic() of the latest valid voltage frame
        self._fallback_start = 0.0
        self.latencies_s = np.full(latency_samples, np.nan)
        self._answered = False             # a new answer applied since the last plant step
        self._held_run = 0                 # plant steps in a row without a new answer
        self.held_longest = 0
        self.held_longest_per_minute: list[int] = []
        # every hold of at least ``long_hold_s``: (plant time at its end (s), load (N), samples held,
        # of them not sent by this process itself (its own lateness))
        self.long_hold_s = 0.005
        self.long_holds: list[tuple[float, float, int, int]] = []
        self._held_unsent = 0               # samples of the hold under way this process did not send
        self._counting = False              # holds count from the step after the first answer on
        self._sending = True                # the step under way follows a sample sent
        self._samples_per_minute = max(1, int(round(60.0 / plant.config.period_s)))
        self.stop_event = threading.Event()
        self._thread: threading.Thread | None = None
        # on the local bus the frames go as datagrams filled in place (localbus's fast path, as
        # the CAN backend's): a DAQ's clock has no time for a can.Message per frame
        self._raw = isinstance(bus, localbus.LocalBus)
        if self._raw:
            self._tx = {}
            for codec in (c.strains, c.load):
                frame = bus.raw_frame(codec.frame_id, codec.length)
                data = np.frombuffer(frame, dtype=np.uint8)[localbus.RAW_DATA:][:codec.length]
                self._tx[codec.frame_id] = (frame, data, np.zeros(len(codec.names)))
            self._rx = bytearray(localbus.RAW_BUFFER_SIZE)
            self._rx_data = np.frombuffer(self._rx, dtype=np.uint8)[localbus.RAW_DATA:]

    # -- one sample ----------------------------------------------------------------------------------
    def _send(self, codec, values: list) -> None:
        if not self._raw:
            self.bus.send(can.Message(arbitration_id=codec.frame_id, data=codec.encode(values),
                                      is_extended_id=False))
            return
        frame, data, array = self._tx[codec.frame_id]
        array[:] = values
        if frames.encode(codec.plan_int, codec.plan_float, array, data):
            codec.encode(values)        # says which value is out of the DBC's range
        self.bus.send_raw(frame)

    def _recv(self, timeout: float) -> int | None:
        """Take the next frame within ``timeout`` (``_take``); NOTHING when none came."""
        if not self._raw:
            msg = self.bus.recv(timeout)
            return NOTHING if msg is None else self._take(msg)
        rx = self._rx
        if not self.bus.recv_raw_into(rx, timeout):
            return NOTHING
        flags = rx[localbus.RAW_FLAGS]
        if flags & localbus.ERROR_FRAME:
            return None
        return self._take_data(_RAW_ID.unpack_from(rx, localbus.RAW_ID)[0],
                               flags & (frames.EXTENDED_ID | frames.REMOTE_FRAME), rx[localbus.RAW_DLC],
                               self._rx_data, rx[localbus.RAW_LENGTH],
                               _RAW_TIME.unpack_from(rx, localbus.RAW_TIME)[0])

    def warm(self) -> None:
        """Run the decoding of a voltage frame and the encoding of both frames once (their
        compiled code loaded) before the clock starts: a DAQ that stops for it on its first
        answer is a stall the controller has to ride through."""
        c = self.contract
        probe = np.zeros(max(c.voltages.length, 1), dtype=np.uint8)
        c.voltages.reject_data(0, c.voltages.length, probe, c.voltages.length, [0.0] * len(c.voltages.names))
        c.status.reject_data(0, c.status.length, probe, c.status.length, [0] * len(c.status.names))
        for codec, values in ((c.strains, self._strain_values), (c.load, self._load_values)):
            codec.encode(values)
            if self._raw:
                frame, data, array = self._tx[codec.frame_id]
                array[:] = values
                frames.encode(codec.plan_int, codec.plan_float, array, data)

    def _send_sample(self) -> None:
        c = self.contract
        strains, load = self.plant.measure()
        if self.samples % c.load.divisor == 0:   # the load first: the sample then carries it
            lv = self._load_values
            lv[c.load.index("axial_load")] = min(max(load, -500.0), 6000.0)
            lv[c.load.index("sequence")] = (self.samples // c.load.divisor) & 0xFF
            self._send(c.load, lv)
        v = self._strain_values
        limit = self._strain_limit          # a gauge beyond full scale is sent at full scale
        for k, i in enumerate(self._strain_order):
            e = float(strains[k])
            # a beam gone beyond every bound (the simulated plant diverged: NaN) reads full scale
            v[i] = min(max(e, -limit), limit) if e == e else limit
        seq = self.samples % c.strains.sequence_modulus
        v[c.strains.index("sequence")] = seq
        self._sent_at[seq] = time.time()
        self._send(c.strains, v)

    def _take(self, msg: can.Message) -> int | None:
        """Apply a received frame; for a valid voltage frame, return its sequence (the sample it
        answers), else None."""
        if msg.is_error_frame:
            return None
        flags = ((frames.EXTENDED_ID if msg.is_extended_id else 0)
                 | (frames.REMOTE_FRAME if msg.is_remote_frame else 0))
        data = _bytes(msg.data)
        return self._take_data(msg.arbitration_id, flags, msg.dlc, data, len(msg.data), msg.timestamp)

    def _take_data(self, frame_id: int, flags: int, dlc: int, data: np.ndarray, length: int,
                   timestamp: float) -> int | None:
        """``_take`` of a frame given as its fields (the data's first ``length`` bytes)."""
        c = self.contract
        if frame_id not in (c.voltages.frame_id, c.status.frame_id):
            return None
        codec = c.voltages if frame_id == c.voltages.frame_id else c.status
        values = self._decoded if codec is c.voltages else self._status_values
        rejected = self.rejected
        fault = codec.reject_data(flags, dlc, data, length, values)
        if fault is not None:
            rejected[fault] += 1
            return None
        if codec is c.status:
            self.status_frames += 1
            self.last_state = int(values[c.status.index("state")])
            return None
        seq = int(self._decoded[self._voltage_sequence])
        ago = (self.samples - seq) % self._modulus        # samples since the one it answers
        index = self.samples - ago
        if ago >= self._modulus // 2 or index < self._last_applied:
            rejected["behind"] += 1
            return None
        if index == self._last_applied:
            rejected["repeated"] += 1
            return None
        self._last_applied = index
        for k, i in enumerate(self._voltage_order):
            self._voltages[k] = self._decoded[i]
        self.voltage_frames += 1
        self._answered = True
        self._last_valid = time.monotonic()
        self.falling_back = False
        sent = self._sent_at[seq]
        if 0 <= index < len(self.latencies_s) and sent == sent:
            self.latencies_s[index] = timestamp - sent
        return seq

    def _fall_back(self) -> None:
        """The DAQ's duty: no valid voltage frame for the silence time-out, ramp to bias."""
        if self._last_valid is None:
            return
        now = time.monotonic()
        if not self.falling_back:
            if now - self._last_valid <= self.silence_timeout_s:
                return
            self.falling_back = True
            self.fallbacks += 1
            self._fallback_start = now
            self._fallback_from[:] = self._voltages
        elapsed = now - self._fallback_start
        remaining = max(0.0, 1.0 - elapsed / self.fallback_ramp_s) if self.fallback_ramp_s > 0 else 0.0
        np.subtract(self._fallback_from, self._bias, out=self._voltages)
        self._voltages *= remaining
        self._voltages += self._bias

    def _step_plant(self) -> None:
        self._fall_back()
        np.subtract(self._voltages, self._bias, out=self._swing)
        np.dot(self._force_matrix, self._swing, out=self._forces)
        self.plant.step(self._forces)
        self._count_hold()
        self.samples += 1
        if self.on_step is not None:
            self.on_step(self.plant, self._voltages)

    def _count_hold(self) -> None:
        """After a plant step: the run of steps without a new answer, and the longest per minute
        (a run is recorded when an answer ends it: a silence that never ends is the controller
        gone, which the fallback handles)."""
        if not self._answered:
            self._held_run += 1
            if not self._sending:
                self._held_unsent += 1
            return
        self._answered = False
        run, self._held_run = self._held_run, 0
        unsent, self._held_unsent = self._held_unsent, 0
        # the steps before the first answer are the controller's start-up, not a stall (its
        # first answers may come several to a step, as it works through what queued meanwhile)
        first, self._counting = not self._counting, True
        if run == 0 or first:
            return
        if run * self.period_s >= self.long_hold_s:
            self.long_holds.append((self.plant.time, self.plant.axial_load, run, unsent))
        minute = self.samples // self._samples_per_minute
        per = self.held_longest_per_minute
        while len(per) <= minute:
            per.append(0)
        per[minute] = max(per[minute], run)
        self.held_longest = max(self.held_longest, run)

    def _await_answer(self) -> bool:
        """Lockstep: take frames until the voltage frame answering the sample just sent (True),
        or until ``answer_timeout_s`` or a stop request (False). A late answer to an earlier
        sample is not applied: its sequence is behind the newest one applied, or, if nothing
        newer came, it is applied as the latest voltages but does not end the wait."""
        expected = self.samples % self.contract.strains.sequence_modulus
        deadline = time.monotonic() + self.answer_timeout_s
        while not self.stop_event.is_set():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                break
            if self._recv(min(remaining, WAIT_SLICE_S)) == expected:
                return True
        self.missed_answers += 1
        return False

    def run(self, max_samples: int | None = None) -> None:
        """Emulate until ``stop()`` (or ``max_samples``)."""
        self.warm()
        self.plant.reset()
        start = time.monotonic()
        while not self.stop_event.is_set() and (max_samples is None or self.samples < max_samples):
            self._send_sample()
            if self.pace == "lockstep":
                self._await_answer()
            else:
                next_time = start + (self.samples + 1) * self.period_s
                while True:
                    remaining = next_time - time.monotonic()
                    if remaining <= 0:
                        break
                    self._recv(remaining)
            self._step_plant()
            if self.pace == "wallclock" and self.skip_late:
                # a DAQ's clock does not wait: samples whose time passed while this process was
                # held up are stepped (the beam moves on, the stacks hold) and never sent, as
                # frames lost on the bus; a burst of late frames is not what a DAQ sends
                while (time.monotonic() - start > (self.samples + 1) * self.period_s
                       and not self.stop_event.is_set()
                       and (max_samples is None or self.samples < max_samples)):
                    self._sending = False
                    self._step_plant()
                    self._sending = True
                    self.skipped += 1

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
