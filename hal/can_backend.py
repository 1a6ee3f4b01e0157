"""The ``can`` backend: the lab's strain/load DAQ on a CAN bus (python-can, any interface:
socketcan, pcan, kvaser, vector, virtual, beamctl_local), speaking the DBC in hal/beamctl.dbc.

Receive: one ``DAQ_Strains`` frame per sample makes a sample, with the latest ``DAQ_Load``
value (a sample is only produced once a load value has arrived, and the load must keep
coming). Each frame is validated before it is decoded, and only a frame that passes every
check reaches the controller; each failure is counted by kind:
extended (29-bit) identifier, remote frame, unknown identifier, wrong length, wrong CRC, value
outside the DBC range, repeated or old sequence (hal/e2e.py). A forward jump of the sequence
counts the samples missed. A bus-off error frame is a lost connection.
Send: ``CTRL_Voltages`` answers each delivered sample once, its ``sequence`` the sequence of
that sample, so the DAQ can pair them; a write with no new sample to answer sends nothing (the
DAQ would drop it as a repeat). The age of the sample when its answer is sent (from its arrival
on the bus to the send call) is ``answer_age_s``. ``CTRL_Status`` (state, fault, flags) goes
every ``SampleDivisor`` voltage frames, and at once on ``announce``. Optionally all traffic is
recorded with python-can's loggers (``.asc`` or ``.blf``, by the file suffix).
"""

from __future__ import annotations

import time
from pathlib import Path

import can
import numpy as np

from beamctl.hal.base import HalBase, HalConfigurationError, HalConnectionLost, HalProtocolError, Sample
from beamctl.hal.budget import check_budget
from beamctl.hal.dbc import STRAIN_SIGNALS, VOLTAGE_SIGNALS, Contract
from beamctl.hal.e2e import NEW, AliveCounter

CAN_ERR_BUSOFF = 0x40          # SocketCAN error class bit in an error frame's identifier
LOAD_SILENCE_DIVISORS = 5      # load frames that may be missed before the load counts as stale
RATE_WINDOW_S = 0.2            # seconds of strain frames over which the DAQ's rate is measured
# Without an accepted sample for this many periods, the 8-bit counter's position is unknown
# (at the DAQ's rate it has wrapped, or the DAQ restarted): the next good frame is taken as is.
RESYNC_PERIODS = 100
# A frame's bus time stamp is its arrival time when it lies within this much before the
# receive time (socketcan's kernel stamps, the virtual and local buses' send times); interfaces
# that stamp with a device clock of their own get the receive time instead.
TIMESTAMP_WINDOW_S = 1.0


class CanBackend(HalBase):
    name = "can"

    def __init__(self, sample_rate_hz: float, interface: str, channel: str, bitrate_bit_s: float = 1_000_000,
                 fd: bool = False, data_bitrate_bit_s: float | None = None, dbc: str | Path | None = None,
                 record: str | Path | None = None, bus_options: dict | None = None,
                 rate_tolerance: float = 0.05) -> None:
        super().__init__(sample_rate_hz)
        self.contract = Contract(dbc)
        self.budget = check_budget(self.contract, sample_rate_hz, bitrate_bit_s, fd, data_bitrate_bit_s)
        self.interface, self.channel = interface, channel
        self.bitrate_bit_s, self.fd, self.data_bitrate_bit_s = bitrate_bit_s, fd, data_bitrate_bit_s
        self.record = Path(record) if record else None
        if self.record and self.record.suffix not in (".asc", ".blf"):
            raise HalConfigurationError(f"recording {self.record}: expected a .asc or .blf file name")
        self.bus_options = dict(bus_options or {})
        self.bus: can.BusABC | None = None
        self._recorder = None
        c = self.contract
        self._strains_id, self._load_id = c.strains.frame_id, c.load.frame_id
        self._own_ids = {c.voltages.frame_id, c.status.frame_id}
        self._strain_values = [0.0] * len(c.strains.names)
        self._load_values = [0.0] * len(c.load.names)
        self._strain_seq_index = c.strains.index("sequence")
        self._load_index, self._load_seq_index = c.load.index("axial_load"), c.load.index("sequence")
        self._strain_order = c.strains.order(STRAIN_SIGNALS)
        self._voltage_order = c.voltages.order(VOLTAGE_SIGNALS)
        self._voltage_values = [0.0] * len(c.voltages.names)
        self._voltage_seq_index = c.voltages.index("sequence")
        self._status_values = [0] * len(c.status.names)
        self._status_index = [c.status.index(n) for n in ("state", "fault", "flags", "sequence")]
        self._status_divisor = c.status.divisor
        self._load_silence = LOAD_SILENCE_DIVISORS * c.load.divisor
        strain_signals = [c.strains.signals[i] for i in self._strain_order]
        self.strain_full_scale = min(min(s.maximum, -s.minimum) for s in strain_signals)
        self.strain_lsb = max(s.scale for s in strain_signals)
        resync = RESYNC_PERIODS / sample_rate_hz
        self._sequence = AliveCounter(c.strains.sequence_modulus, resync)
        self._load_sequence = AliveCounter(c.load.sequence_modulus, resync * c.load.divisor)
        # the DAQ must sample at the rate the gains were designed for: measured over windows
        # of RATE_WINDOW strain frames, refused when off by more than rate_tolerance (0: off)
        self.rate_tolerance = float(rate_tolerance)
        self._rate_window = max(64, int(sample_rate_hz * RATE_WINDOW_S))
        self._reset_counters()

    COUNTERS = ("frames_in", "frames_out", "extended_ids", "remote_frames", "unknown_ids", "wrong_length",
                "crc_errors", "out_of_range", "error_frames", "bus_off")

    def _reset_counters(self) -> None:
        self.counters = dict.fromkeys(self.COUNTERS, 0)
        self.counters.update(backlog_discarded=0, unanswered_writes=0)
        self._sequence.reset()
        self._load_sequence.reset()
        self._load = None
        self._samples_since_load = 0
        self._answered_seq = 0      # sequence of the latest sample delivered by read()
        self._arrival = 0.0         # its arrival on the bus (time.time() clock)
        self._pending = False       # delivered by read() and not yet answered
        self._discarding = False
        self._held = False
        self._voltage_frames = 0
        self._window_count = 0
        self._window_start = None
        self.measured_rate_hz = None
        self.answer_age_s = float("nan")

    # -- lifecycle ---------------------------------------------------------------------------------
    def _open(self) -> None:
        self._reset_counters()
        options = dict(self.bus_options)
        if self.interface != "socketcan":   # socketcan takes its bit rate from `ip link`
            options.setdefault("bitrate", int(self.bitrate_bit_s))
        if self.fd:
            options["fd"] = True
            if self.data_bitrate_bit_s:
                options.setdefault("data_bitrate", int(self.data_bitrate_bit_s))
        try:
            self.bus = can.Bus(interface=self.interface, channel=self.channel, **options)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise HalConnectionLost(f"can: cannot open {self.interface}:{self.channel}: {exc}") from None
        if self.record:
            self._recorder = can.Logger(str(self.record))

    def _close(self) -> None:
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None
        if self._recorder is not None:
            self._recorder.stop()
            self._recorder = None

    # -- receive ---------------------------------------------------------------------------------------
    def _read(self, sample: Sample, timeout: float | None) -> bool:
        if self._held:          # the newest sample found at start (``_discard_backlog``)
            self._held = False
            if sample is not self._sample:
                raise HalProtocolError("can: a held sample read into another buffer")
            return True
        deadline = time.monotonic() + (timeout if timeout is not None else 1.0)
        while True:
            remaining = deadline - time.monotonic()
            try:
                msg = self.bus.recv(max(remaining, 0.0))
            except can.CanError as exc:
                raise HalConnectionLost(f"can: receive failed: {exc}") from None
            if msg is None:
                return False
            if self._take(msg, sample):
                return True

    def _discard_backlog(self) -> int:
        """Take every frame already queued (the load value and the counters follow them); keep
        the newest complete sample for the next read, the one the DAQ waits to have answered,
        and drop the older ones unanswered. Return the number dropped."""
        self._discarding = True
        complete = 0
        try:
            while True:
                try:
                    msg = self.bus.recv(0.0)
                except can.CanError as exc:
                    raise HalConnectionLost(f"can: receive failed: {exc}") from None
                if msg is None:
                    break
                if self._take(msg, self._sample):
                    complete += 1
        finally:
            self._discarding = False
        self._held = complete > 0
        discarded = max(complete - 1, 0)
        self.counters["backlog_discarded"] += discarded
        return discarded

    def _take(self, msg: can.Message, sample: Sample) -> bool:
        """Validate, count and apply one received frame; True when it completed ``sample``."""
        counters = self.counters
        counters["frames_in"] += 1
        if self._recorder is not None:
            self._recorder.on_message_received(msg)
        if msg.is_error_frame:
            counters["error_frames"] += 1
            if msg.arbitration_id & CAN_ERR_BUSOFF:
                counters["bus_off"] += 1
                raise HalConnectionLost("can: bus-off")
            return False
        if msg.is_extended_id:
            counters["extended_ids"] += 1
            return False
        if msg.is_remote_frame:
            counters["remote_frames"] += 1
            return False
        frame_id = msg.arbitration_id
        if frame_id == self._strains_id:
            return self._take_strains(msg, sample)
        if frame_id == self._load_id:
            self._take_load(msg)
        elif frame_id not in self._own_ids:
            counters["unknown_ids"] += 1
        return False

    def _valid(self, codec, msg: can.Message, values: list) -> bool:
        fault = codec.reject(msg, values)
        if fault is None:
            return True
        self.counters[fault] += 1
        return False

    def _take_strains(self, msg: can.Message, sample: Sample) -> bool:
        c = self.contract
        if not self._valid(c.strains, msg, self._strain_values):
            return False
        now = time.time()
        arrival = msg.timestamp if 0.0 <= now - msg.timestamp < TIMESTAMP_WINDOW_S else now
        seq = int(self._strain_values[self._strain_seq_index])
        if self._sequence.accept(seq, arrival) != NEW:
            return False
        if self.rate_tolerance and not self._discarding:
            self._check_rate(arrival)
        if self._load is None:
            return False          # no load value yet: not a complete sample
        self._samples_since_load += 1
        if self._samples_since_load > self._load_silence:
            raise HalProtocolError(f"can: no {c.load.name} frame for {self._samples_since_load} "
                                   f"samples (expected every {c.load.divisor})")
        v = self._strain_values
        o = self._strain_order
        sample.strains[0], sample.strains[1] = v[o[0]], v[o[1]]
        sample.strains[2], sample.strains[3] = v[o[2]], v[o[3]]
        sample.axial_load = self._load
        sample.sequence = seq
        sample.timestamp = arrival
        self._answered_seq = seq
        self._arrival = arrival
        self._pending = True
        return True

    def _take_load(self, msg: can.Message) -> None:
        c = self.contract
        if not self._valid(c.load, msg, self._load_values):
            return
        seq = int(self._load_values[self._load_seq_index])
        if self._load_sequence.accept(seq, time.time()) != NEW:
            return
        self._load = self._load_values[self._load_index]
        self._samples_since_load = 0

    def _check_rate(self, stamp: float) -> None:
        if self._window_start is None:
            self._window_start, self._window_count = stamp, 0
            return
        self._window_count += 1
        if self._window_count < self._rate_window:
            return
        elapsed = stamp - self._window_start
        self._window_start, self._window_count = stamp, 0
        if elapsed <= 0:
            return
        rate = self._rate_window / elapsed
        self.measured_rate_hz = rate
        if abs(rate / self.sample_rate_hz - 1.0) > self.rate_tolerance:
            raise HalProtocolError(f"can: {self.contract.strains.name} arrive at {rate:.0f} Hz; the gains "
                                   f"are designed for {self.sample_rate_hz:g} Hz (tolerance "
                                   f"{100 * self.rate_tolerance:g} %)")

    # -- send ------------------------------------------------------------------------------------------
    def _send(self, frame_id: int, data: bytes) -> None:
        msg = can.Message(arbitration_id=frame_id, data=data, is_extended_id=False, is_fd=self.fd,
                          is_rx=False)
        try:
            self.bus.send(msg)
        except can.CanError as exc:
            raise HalConnectionLost(f"can: send failed: {exc}") from None
        self.counters["frames_out"] += 1
        if self._recorder is not None:
            self._recorder.on_message_received(msg)

    def _write(self, voltages: np.ndarray) -> None:
        if not self._pending:       # nothing new to answer: the DAQ would drop a repeat
            self.counters["unanswered_writes"] += 1
            return
        c = self.contract
        values = self._voltage_values
        for k, i in enumerate(self._voltage_order):
            values[i] = float(voltages[k])
        values[self._voltage_seq_index] = self._answered_seq
        try:
            data = c.voltages.encode(values)
        except ValueError as exc:
            raise HalProtocolError(f"can: {exc}") from None
        self.answer_age_s = time.time() - self._arrival
        self._send(c.voltages.frame_id, data)
        self._pending = False
        self._voltage_frames += 1
        if self._voltage_frames % self._status_divisor == 0:
            self._send_status()

    def _send_status(self) -> None:
        c = self.contract
        s = self._status_values
        i_state, i_fault, i_flags, i_seq = self._status_index
        s[i_state], s[i_fault], s[i_flags] = self.state_code, self.fault_code, self.flags_code
        s[i_seq] = (s[i_seq] + 1) & 0xFF
        self._send(c.status.frame_id, c.status.encode(s))

    def _announce(self) -> None:
        self._send_status()

    def status(self) -> dict:
        out = super().status()
        out.update(self.counters)
        q, ql = self._sequence, self._load_sequence
        out.update(sequence_gaps=q.gaps, samples_missed=q.missed, sequence_repeated=q.repeated,
                   sequence_behind=q.behind, sequence_resyncs=q.resyncs, load_sequence_repeated=ql.repeated,
                   load_sequence_behind=ql.behind, load_frames_missed=ql.missed)
        out.update(interface=self.interface, channel=self.channel,
                   bus_load_percent=100 * self.budget.load, bus=self.budget.description)
        return out
