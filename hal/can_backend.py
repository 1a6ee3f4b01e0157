"""The ``can`` backend: the lab's strain/load DAQ on a CAN bus (python-can, any interface:
socketcan, pcan, kvaser, vector, virtual), speaking the DBC in hal/beamctl.dbc.

Receive: one ``DAQ_Strains`` frame per sample makes a sample, with the latest ``DAQ_Load``
value (a sample is only produced once a load value has arrived, and the load must keep
coming). A frame with an unknown identifier, the wrong length, a value outside the DBC
range, or an error frame never reaches the controller; each is counted, as are sequence
gaps. A bus-off error frame is a lost connection.
Send: ``CTRL_Voltages`` on every write, its ``sequence`` the low four bits of the sequence of
the latest sample delivered (the sample these voltages answer, so the DAQ can pair them);
``CTRL_Status`` (state, fault, flags) every ``SampleDivisor`` writes. Optionally all traffic
is recorded with python-can's loggers (``.asc`` or ``.blf``, by the file suffix).
"""

from __future__ import annotations

import time
from pathlib import Path

import can
import numpy as np

from beamctl.hal.base import HalBase, HalConfigurationError, HalConnectionLost, HalProtocolError, Sample
from beamctl.hal.budget import check_budget
from beamctl.hal.dbc import STRAIN_SIGNALS, VOLTAGE_SIGNALS, Contract

CAN_ERR_BUSOFF = 0x40          # SocketCAN error class bit in an error frame's identifier
LOAD_SILENCE_DIVISORS = 5      # load frames that may be missed before the load counts as stale
RATE_WINDOW_S = 0.2            # seconds of strain frames over which the DAQ's rate is measured


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
        # the DAQ must sample at the rate the gains were designed for: measured over windows
        # of RATE_WINDOW strain frames, refused when off by more than rate_tolerance (0: off)
        self.rate_tolerance = float(rate_tolerance)
        self._rate_window = max(64, int(sample_rate_hz * RATE_WINDOW_S))
        self._reset_counters()

    def _reset_counters(self) -> None:
        self.counters = {"frames_in": 0, "frames_out": 0, "sequence_gaps": 0, "samples_missed": 0,
                         "unknown_ids": 0, "wrong_length": 0, "out_of_range": 0, "error_frames": 0,
                         "bus_off": 0, "load_sequence_gaps": 0}
        self._last_seq = None
        self._last_load_seq = None
        self._load = None
        self._samples_since_load = 0
        self._answered_seq = 0      # sequence of the latest sample delivered by read()
        self._writes = 0
        self._window_count = 0
        self._window_start = None
        self.measured_rate_hz = None

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
        deadline = time.monotonic() + (timeout if timeout is not None else 1.0)
        c, counters = self.contract, self.counters
        while True:
            remaining = deadline - time.monotonic()
            try:
                msg = self.bus.recv(max(remaining, 0.0))
            except can.CanError as exc:
                raise HalConnectionLost(f"can: receive failed: {exc}") from None
            if msg is None:
                return False
            counters["frames_in"] += 1
            if self._recorder is not None:
                self._recorder.on_message_received(msg)
            if msg.is_error_frame:
                counters["error_frames"] += 1
                if msg.arbitration_id & CAN_ERR_BUSOFF:
                    counters["bus_off"] += 1
                    raise HalConnectionLost("can: bus-off")
                continue
            frame_id = msg.arbitration_id
            if frame_id == self._strains_id:
                if msg.dlc != c.strains.length:
                    counters["wrong_length"] += 1
                    continue
                if not c.strains.decode_into(msg.data, self._strain_values):
                    counters["out_of_range"] += 1
                    continue
                seq = int(self._strain_values[self._strain_seq_index])
                if self._last_seq is not None and seq != (self._last_seq + 1) & 0xFF:
                    counters["sequence_gaps"] += 1
                    counters["samples_missed"] += (seq - self._last_seq - 1) & 0xFF
                self._last_seq = seq
                if self.rate_tolerance:
                    self._check_rate(msg.timestamp)
                if self._load is None:
                    continue          # no load value yet: not a complete sample
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
                sample.timestamp = msg.timestamp
                self._answered_seq = seq
                return True
            if frame_id == self._load_id:
                if msg.dlc != c.load.length:
                    counters["wrong_length"] += 1
                elif not c.load.decode_into(msg.data, self._load_values):
                    counters["out_of_range"] += 1
                else:
                    seq = int(self._load_values[self._load_seq_index])
                    if self._last_load_seq is not None and seq != (self._last_load_seq + 1) & 0xFF:
                        counters["load_sequence_gaps"] += 1
                    self._last_load_seq = seq
                    self._load = self._load_values[self._load_index]
                    self._samples_since_load = 0
                continue
            if frame_id not in self._own_ids:
                counters["unknown_ids"] += 1

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
        c = self.contract
        values = self._voltage_values
        for k, i in enumerate(self._voltage_order):
            values[i] = float(voltages[k])
        values[self._voltage_seq_index] = self._answered_seq & 0xF
        try:
            data = c.voltages.encode(values)
        except ValueError as exc:
            raise HalProtocolError(f"can: {exc}") from None
        self._send(c.voltages.frame_id, data)
        self._writes += 1
        if self._writes % self._status_divisor == 0:
            s = self._status_values
            i_state, i_fault, i_flags, i_seq = self._status_index
            s[i_state], s[i_fault], s[i_flags] = self.state_code, self.fault_code, self.flags_code
            s[i_seq] = (self._writes // self._status_divisor) & 0xFF
            self._send(c.status.frame_id, c.status.encode(s))

    def status(self) -> dict:
        out = super().status()
        out.update(self.counters)
        out.update(interface=self.interface, channel=self.channel,
                   bus_load_percent=100 * self.budget.load, bus=self.budget.description)
        return out
