"""The ``can`` backend: the lab's strain/load DAQ on a CAN bus (python-can, any interface:
socketcan, pcan, kvaser, vector, virtual, beamctl_local), speaking the DBC in hal/beamctl.dbc.

Receive: one ``DAQ_Strains`` frame per sample makes a sample, with the latest ``DAQ_Load``
value (a sample is only produced once a load value has arrived, and the load must keep
coming). Each frame is validated before it is decoded, and only a frame that passes every
check reaches the controller; each failure is counted by kind:
extended (29-bit) identifier, remote frame, unknown identifier, wrong length, wrong CRC, value
outside the DBC range, a sequence that is not new (repeated, behind, or further ahead than the
time since the last accepted frame allows; hal/e2e.py). A forward jump of the sequence counts the
samples missed, and the sample tells the controller how many it skipped (``Sample.missed``).
A bus-off error frame is a lost connection.
Send: ``CTRL_Voltages`` answers each delivered sample once, its ``sequence`` the sequence of
that sample, so the DAQ can pair them; a write with no new sample to answer sends nothing (the
DAQ would drop it as a repeat). The age of the sample when its answer has been sent (from its
arrival on the bus until the send returned) is ``answer_age_s``. ``CTRL_Status`` (state, fault,
flags) goes every ``SampleDivisor`` voltage frames, and at once on ``announce``. Optionally all
traffic is recorded with python-can's loggers (``.asc`` or ``.blf``, by the file suffix).

The work per frame is compiled (hal/frames.py, numba): validation, decoding, the alive
counters, the counters of refused frames, the load value, the rate measurement and the encoding
of the voltage frame run on arrays allocated once here (``_ks``, ``_fs``: configuration, state
and counters; the contract's plans). Two ways to the bus:

- python-can's ``Message`` API, for every interface (socketcan on the lab PC): ``bus.recv``
  returns a ``can.Message`` (socketcan: python-can's ``SocketcanBus`` reads the kernel's
  ``can_frame``/``canfd_frame`` with its receive time stamp, SO_TIMESTAMP), whose fields and
  data go to the compiled ``take_frame``; the voltage frame is encoded into a byte buffer and
  sent as a ``can.Message`` with ``bus.send`` (socketcan: one ``send`` of the frame on the
  raw CAN socket). Recording always takes this way (the loggers take messages).
- the local bus's raw datagrams (hal/localbus.py, ``beamctl_local``), without a ``Message`` per
  frame: ``recv_raw_into`` fills a buffer the compiled ``take_record`` reads the frame from, and
  the voltage frame is encoded into a datagram made once (``raw_frame``) and sent with
  ``send_raw``.
"""

from __future__ import annotations

import socket
import time
from pathlib import Path

import can
import numpy as np

from beamctl.hal import frames, localbus
from beamctl.hal.base import HalBase, HalConfigurationError, HalConnectionLost, HalProtocolError, Sample
from beamctl.hal.budget import check_budget
from beamctl.hal.dbc import STRAIN_SIGNALS, VOLTAGE_SIGNALS, Contract
from beamctl.hal.e2e import AliveCounter, _bytes
from beamctl.hal.frames import (
    C_BACKLOG,
    C_FRAMES_OUT,
    K_DISCARDING,
    K_PENDING,
    K_SINCE_LOAD,
    K_VOLTAGE_FRAMES,
    T_BUS_OFF,
    T_LOAD_STALE,
    T_RATE,
    T_SAMPLE,
    W_NOTHING,
    W_SENT,
    W_SHAPE,
)

CAN_ERR_BUSOFF = 0x40          # SocketCAN error class bit in an error frame's identifier
# A load value is used for this long (samples of the DAQ's clock, those lost on the way included)
# before the load counts as stale: the rig loads quasi-statically (50 N/s moves it 5 N in that
# time) and the ride-through takes a DAQ this silent for stopped (gains/ridethrough.py,
# GAP_HORIZON_S); lost load frames alone (a short receive queue, a stall) are not a fault.
LOAD_SILENCE_S = 0.1
# The read polls the bus for at most this share of a period: a loop that never sleeps uses all of
# its CPU, and Linux holds a real-time thread above 95 % of one for 50 ms a second
# (kernel.sched_rt_runtime_us); the loop's own work takes a further 20 to 30 % here at 6000 Hz.
SPIN_SHARE_MAX = 0.5
RATE_WINDOW_S = 0.2            # seconds of strain frames over which the DAQ's rate is measured
# A frame's bus time stamp is its arrival time when it lies within this much before the
# receive time (socketcan's kernel stamps, the virtual and local buses' send times); interfaces
# that stamp with a device clock of their own get the receive time instead.
TIMESTAMP_WINDOW_S = 1.0


class CanBackend(HalBase):
    name = "can"
    COUNTERS = frames.COUNTER_NAMES
    # the clock of the bus time stamps (``time.time``; tests construct time with their own)
    wall_clock = staticmethod(time.time)

    def __init__(self, sample_rate_hz: float, interface: str, channel: str, bitrate_bit_s: float = 1_000_000,
                 fd: bool = False, data_bitrate_bit_s: float | None = None, dbc: str | Path | None = None,
                 record: str | Path | None = None, bus_options: dict | None = None,
                 rate_tolerance: float = 0.05, spin_s: float = 0.0, newest_only: bool = True) -> None:
        """``spin_s``: how long before the next sample is due a read stops sleeping and polls
        the bus without yielding the CPU (0: never). A process asleep in the kernel takes
        from a few to tens of microseconds to wake when a frame arrives (far more on a virtual
        machine whose idle CPU the hypervisor has parked); polling for the last ``spin_s`` of
        each period trades that CPU time for the answer's latency. ``newest_only``: a read
        takes every frame queued and returns the newest sample, the older ones counted as
        missed (the wire contract, hal/beamctl.dbc: after a stall the DAQ gets the answer to its
        newest sample; False reads them one by one, for tests of the decoding)."""
        super().__init__(sample_rate_hz)
        if not spin_s >= 0.0:
            raise HalConfigurationError(f"spin time {spin_s!r} s: expected a time >= 0")
        if spin_s > SPIN_SHARE_MAX / sample_rate_hz:
            raise HalConfigurationError(
                f"spin time {spin_s * 1e6:g} us: expected at most {100 * SPIN_SHARE_MAX:g} % of the period "
                f"({SPIN_SHARE_MAX / sample_rate_hz * 1e6:.0f} us at {sample_rate_hz:g} Hz): a loop polling "
                f"longer takes nearly all of its CPU, and Linux then holds a real-time thread for 50 ms a "
                f"second (kernel.sched_rt_runtime_us)")
        self.spin_s = float(spin_s)
        self.newest_only = bool(newest_only)
        self._due = 0.0             # time.monotonic() when the next sample is due
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
        self._status_values = [0] * len(c.status.names)
        self._status_index = [c.status.index(n) for n in ("state", "fault", "flags", "sequence")]
        strain_signals = [c.strains.signals[i] for i in c.strains.order(STRAIN_SIGNALS)]
        self.strain_full_scale = min(min(s.maximum, -s.minimum) for s in strain_signals)
        # the DAQ falls back to bias by itself after this long without an answer (the DBC's)
        self.daq_silence_timeout_s = c.silence_timeout_s or None
        self.strain_lsb = max(s.scale for s in strain_signals)
        # the DAQ must sample at the rate the gains were designed for: measured over windows
        # of RATE_WINDOW of its samples (the frames received and those their counter says were
        # lost: a lost frame does not slow the DAQ's clock), refused when off by more than
        # rate_tolerance (0: off)
        self.rate_tolerance = float(rate_tolerance)
        self._rate_window = max(64, int(sample_rate_hz * RATE_WINDOW_S))
        self._configure()
        # the raw path's buffers, made per bus in _open; the Message path's voltage frame
        self._raw = False
        self._rx = self._rx_array = self._status_frame = None
        self._tx_frame = None
        self._tx_array = np.zeros(max(c.voltages.length, 1), dtype=np.uint8)
        self._raw_read = None
        self._reset_counters()

    def _configure(self) -> None:
        """The compiled path's configuration and state (layout: hal/frames.py, ``K_*``, ``F_*``)."""
        c, f = self.contract, frames
        rows = Contract.ROWS
        rows_int, rows_float = c.plan_int.shape, c.plan_float.shape
        ks = np.zeros(f.K_PLANS + rows_int[0] * rows_int[1], dtype=np.int64)
        fs = np.zeros(f.F_VALUES + c.max_signals + rows_float[0] * rows_float[1])
        ks[f.K_PLAN_WIDTH], ks[f.K_FPLAN_WIDTH] = rows_int[1], rows_float[1]
        ks[f.K_FPLANS] = f.F_VALUES + c.max_signals
        ks[f.K_PLANS:] = c.plan_int.ravel()
        fs[f.F_VALUES + c.max_signals:] = c.plan_float.ravel()
        if len(STRAIN_SIGNALS) > f.F_MAX_STRAINS:
            raise HalConfigurationError(f"can: {len(STRAIN_SIGNALS)} strains; the compiled path holds "
                                        f"{f.F_MAX_STRAINS}")
        ks[f.K_STRAINS], ks[f.K_LOAD] = rows["strains"], rows["load"]
        ks[f.K_VOLTAGES], ks[f.K_STATUS] = rows["voltages"], rows["status"]
        ks[f.K_LOAD_INDEX] = c.load.index("axial_load")
        ks[f.K_N_STRAINS] = len(STRAIN_SIGNALS)
        ks[f.K_STRAIN_ORDER:f.K_STRAIN_ORDER + len(STRAIN_SIGNALS)] = c.strains.order(STRAIN_SIGNALS)
        ks[f.K_N_VOLTAGES] = len(VOLTAGE_SIGNALS)
        ks[f.K_VOLTAGE_ORDER:f.K_VOLTAGE_ORDER + len(VOLTAGE_SIGNALS)] = c.voltages.order(VOLTAGE_SIGNALS)
        ks[f.K_BUSOFF_MASK] = CAN_ERR_BUSOFF
        ks[f.K_LOAD_SILENCE] = max(c.load.divisor, int(round(LOAD_SILENCE_S * self.sample_rate_hz)))
        ks[f.K_RATE_WINDOW] = self._rate_window
        ks[f.K_STATUS_DIVISOR] = c.status.divisor
        ks[f.K_RAW_FLAGS], ks[f.K_RAW_DLC] = localbus.RAW_FLAGS, localbus.RAW_DLC
        ks[f.K_RAW_LENGTH], ks[f.K_RAW_ID] = localbus.RAW_LENGTH, localbus.RAW_ID
        ks[f.K_RAW_TIME], ks[f.K_RAW_DATA] = localbus.RAW_TIME, localbus.RAW_DATA
        ks[f.K_RAW_EXTENDED], ks[f.K_RAW_REMOTE] = localbus.EXTENDED_ID, localbus.REMOTE_FRAME
        ks[f.K_RAW_ERROR] = localbus.ERROR_FRAME
        fs[f.F_RATE_TOLERANCE] = self.rate_tolerance
        fs[f.F_SAMPLE_RATE] = self.sample_rate_hz
        fs[f.F_STAMP_WINDOW] = TIMESTAMP_WINDOW_S
        self._ks, self._fs = ks, fs
        # the compiled path writes each sample's strains into the state: the sample shows them
        self._sample.strains = fs[f.F_STRAINS:f.F_STRAINS + len(STRAIN_SIGNALS)]
        try:
            self._sequence = AliveCounter(
                c.strains.sequence_modulus, self.period_s,
                state=(ks[f.K_SEQUENCE:f.K_SEQUENCE + f.A_INTS], fs[f.F_SEQUENCE:f.F_SEQUENCE + f.A_FLOATS]))
            self._load_sequence = AliveCounter(
                c.load.sequence_modulus, c.load.divisor * self.period_s,
                state=(ks[f.K_LOAD_SEQUENCE:f.K_LOAD_SEQUENCE + f.A_INTS],
                       fs[f.F_LOAD_SEQUENCE:f.F_LOAD_SEQUENCE + f.A_FLOATS]))
        except ValueError as exc:
            raise HalConfigurationError(f"DBC {c.path}: sequence: {exc}") from None

    def _reset_counters(self) -> None:
        f, ks, fs = frames, self._ks, self._fs
        ks[:len(self.COUNTERS)] = 0
        for k in (f.K_PENDING, f.K_ANSWER_SEQ, f.K_HAVE_LOAD, f.K_SINCE_LOAD, f.K_DISCARDING, f.K_RATE_COUNT,
                  f.K_VOLTAGE_FRAMES, f.K_DELIVERED):
            ks[k] = 0
        fs[f.F_ARRIVAL] = fs[f.F_LOAD] = 0.0
        fs[f.F_RATE_START] = fs[f.F_RATE] = float("nan")
        self._sequence.reset()
        self._load_sequence.reset()
        self._held = False
        self.answer_age_s = float("nan")

    @property
    def counters(self) -> dict:
        """Frames in and out, and the frames refused, by kind (a copy)."""
        return dict(zip(self.COUNTERS, self._ks[:len(self.COUNTERS)].tolist(), strict=True))

    @property
    def measured_rate_hz(self) -> float | None:
        """The DAQ's rate over the last complete window of strain frames (None: none yet)."""
        rate = float(self._fs[frames.F_RATE])
        return None if rate != rate else rate

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
            self.bus = self._make_bus(options)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise HalConnectionLost(f"can: cannot open {self.interface}:{self.channel}: {exc}"
                                    f"{open_hint(self.interface, self.channel)}") from None
        if self.record:
            self._recorder = can.Logger(str(self.record))
        c = self.contract
        self._raw = isinstance(self.bus, localbus.LocalBus) and self._recorder is None
        if self._raw:
            self._rx = bytearray(localbus.RAW_BUFFER_SIZE)
            self._rx_array = np.frombuffer(self._rx, dtype=np.uint8)
            self._tx_frame = self.bus.raw_frame(c.voltages.frame_id, c.voltages.length, is_fd=self.fd)
            self._tx_array = np.frombuffer(self._tx_frame, dtype=np.uint8)
            self._status_frame = self.bus.raw_frame(c.status.frame_id, c.status.length, is_fd=self.fd)
            self._ks[frames.K_TX_OFFSET] = localbus.RAW_DATA
            self._raw_read = (self.bus.recv_raw_into, self._rx, self._rx_array, self._ks, self._fs,
                              frames.take_record)
        else:
            self._tx_frame = None
            self._tx_array = np.zeros(max(c.voltages.length, 1), dtype=np.uint8)
            self._ks[frames.K_TX_OFFSET] = 0

    def _make_bus(self, options: dict) -> can.BusABC:
        """The python-can bus of ``interface`` and ``channel`` (tests put a scripted one here)."""
        return can.Bus(interface=self.interface, channel=self.channel, **options)

    def _close(self) -> None:
        self._raw = False
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
        if timeout is None:
            timeout = 1.0
        now = time.monotonic()
        deadline = now + timeout
        spin_from = self._due - self.spin_s if self.spin_s else deadline
        if self._raw:
            recv, rx, record, ks, fs, take = self._raw_read
            clock = self.wall_clock
            while True:
                now = time.monotonic()
                # sleep until the spin window, then poll without sleeping until the deadline
                wait = max(min(spin_from, deadline) - now, 0.0)
                try:
                    got = recv(rx, wait)
                except can.CanError as exc:
                    raise HalConnectionLost(f"can: receive failed: {exc}") from None
                if not got:
                    if time.monotonic() >= deadline:
                        return False
                    continue
                code, seq, missed, arrival, load = take(record, clock(), ks, fs)
                if code == T_SAMPLE:
                    # after a stall only the newest sample matters to the beam: whatever queued
                    # meanwhile is taken now, the older samples counted as missed (the
                    # controller bridges them) and the newest answered
                    try:
                        while self.newest_only and recv(rx, 0.0):
                            code, seq2, missed2, arrival2, load2 = take(record, clock(), ks, fs)
                            if code == T_SAMPLE:
                                missed += missed2 + 1
                                seq, arrival, load = seq2, arrival2, load2
                            elif code:
                                self._refuse(code)
                    except can.CanError as exc:
                        raise HalConnectionLost(f"can: receive failed: {exc}") from None
                    sample.sequence, sample.missed, sample.timestamp = seq, missed, arrival
                    sample.axial_load = load
                    if sample is not self._sample:
                        sample.strains[:] = self._sample.strains
                    self._due = time.monotonic() + self.period_s
                    return True
                if code:
                    self._refuse(code)
        while True:
            now = time.monotonic()
            wait = max(min(spin_from, deadline) - now, 0.0)
            try:
                msg = self.bus.recv(wait)
            except can.CanError as exc:
                raise HalConnectionLost(f"can: receive failed: {exc}") from None
            if msg is None:
                if time.monotonic() >= deadline:
                    return False
                continue
            if self._take(msg, sample):
                # the newest sample after a stall (as on the raw path)
                missed = sample.missed
                try:
                    while self.newest_only and (msg := self.bus.recv(0.0)) is not None:
                        if self._take(msg, sample):
                            missed += sample.missed + 1
                except can.CanError as exc:
                    raise HalConnectionLost(f"can: receive failed: {exc}") from None
                sample.missed = missed
                self._due = time.monotonic() + self.period_s
                return True

    def _discard_backlog(self) -> int:
        """Take every frame already queued (the load value and the counters follow them); keep
        the newest complete sample for the next read, the one the DAQ waits to have answered,
        and drop the older ones unanswered. Return the number dropped."""
        self._ks[K_DISCARDING] = 1
        complete = 0
        sample = self._sample
        try:
            if self._raw:
                while self.bus.recv_raw_into(self._rx, 0.0):
                    code, seq, missed, arrival, load = frames.take_record(self._rx_array, self.wall_clock(),
                                                                          self._ks, self._fs)
                    if code == T_SAMPLE:
                        sample.sequence, sample.timestamp, sample.axial_load = seq, arrival, load
                        complete += 1
                    elif code:
                        self._refuse(code)
            else:
                while (msg := self.bus.recv(0.0)) is not None:
                    if self._take(msg, sample):
                        complete += 1
        except can.CanError as exc:
            raise HalConnectionLost(f"can: receive failed: {exc}") from None
        finally:
            self._ks[K_DISCARDING] = 0
        self._held = complete > 0
        sample.missed = 0             # the first sample the controller sees
        discarded = max(complete - 1, 0)
        self._ks[C_BACKLOG] += discarded
        return discarded

    def _take(self, msg: can.Message, sample: Sample) -> bool:
        """Validate, count and apply one received python-can message; True when it completed
        ``sample``."""
        if self._recorder is not None:
            self._recorder.on_message_received(msg)
        flags = ((frames.EXTENDED_ID if msg.is_extended_id else 0)
                 | (frames.REMOTE_FRAME if msg.is_remote_frame else 0)
                 | (frames.ERROR_FRAME if msg.is_error_frame else 0))
        data = msg.data if msg.data is not None else b""
        stamp = msg.timestamp if msg.timestamp is not None else float("nan")
        code, seq, missed, arrival, load = frames.take_frame(
            flags, msg.arbitration_id, msg.dlc, _bytes(data), len(data), float(stamp), self.wall_clock(),
            self._ks, self._fs)
        if code == T_SAMPLE:
            sample.sequence, sample.missed, sample.timestamp, sample.axial_load = seq, missed, arrival, load
            if sample is not self._sample:
                sample.strains[:] = self._sample.strains
            return True
        if code:
            self._refuse(code)
        return False

    def _refuse(self, code: int) -> None:
        """Raise what the compiled path found (T_BUS_OFF, T_LOAD_STALE, T_RATE)."""
        c = self.contract
        if code == T_BUS_OFF:
            raise HalConnectionLost("can: bus-off")
        if code == T_LOAD_STALE:
            raise HalProtocolError(f"can: no {c.load.name} frame for {int(self._ks[K_SINCE_LOAD])} "
                                   f"samples (expected every {c.load.divisor}; a load value is used for "
                                   f"{1e3 * LOAD_SILENCE_S:g} ms at most)")
        if code == T_RATE:
            raise HalProtocolError(f"can: {c.strains.name} arrive at {self.measured_rate_hz:.0f} Hz; the "
                                   f"gains are designed for {self.sample_rate_hz:g} Hz (tolerance "
                                   f"{100 * self.rate_tolerance:g} %)")
        raise HalProtocolError(f"can: unknown outcome {code} of a received frame")

    # -- send ------------------------------------------------------------------------------------------
    def _send_message(self, frame_id: int, data: bytes) -> None:
        msg = can.Message(arbitration_id=frame_id, data=data, is_extended_id=False, is_fd=self.fd,
                          is_rx=False)
        self.bus.send(msg)
        if self._recorder is not None:
            self._recorder.on_message_received(msg)

    def _write(self, voltages: np.ndarray) -> None:
        ks = self._ks
        try:
            code, arrival, status_due = frames.answer(voltages, ks, self._fs, self._tx_array)
        except TypeError:           # not a vector of floats: made one
            voltages = np.asarray(voltages, dtype=np.float64)
            if voltages.ndim != 1:
                raise HalProtocolError(f"can: voltages of shape {voltages.shape}; expected six") from None
            code, arrival, status_due = frames.answer(voltages, ks, self._fs, self._tx_array)
        if code != W_SENT:
            if code == W_NOTHING:   # nothing new to answer: the DAQ would drop a repeat (counted)
                return
            if code == W_SHAPE:
                raise HalProtocolError(f"can: {len(voltages)} voltages; expected {len(VOLTAGE_SIGNALS)}")
            c = self.contract
            s = c.voltages.signals[code - 1]
            value = float(voltages[c.voltages.order(VOLTAGE_SIGNALS).index(code - 1)])
            raise HalProtocolError(f"can: {c.voltages.name}.{s.name} = {value!r} outside the DBC range "
                                   f"[{s.minimum}, {s.maximum}]")
        try:
            if self._raw:
                self.bus.send_raw(self._tx_frame)
            else:
                self._send_message(self.contract.voltages.frame_id,
                                   self._tx_array[:self.contract.voltages.length].tobytes())
        except can.CanError as exc:
            ks[K_PENDING] = 1       # not answered after all
            ks[C_FRAMES_OUT] -= 1
            ks[K_VOLTAGE_FRAMES] -= 1
            raise HalConnectionLost(f"can: send failed: {exc}") from None
        self.answer_age_s = self.wall_clock() - arrival
        if status_due:
            self._send_status()

    def _send_status(self) -> None:
        c = self.contract
        s = self._status_values
        i_state, i_fault, i_flags, i_seq = self._status_index
        s[i_state], s[i_fault], s[i_flags] = self.state_code, self.fault_code, self.flags_code
        s[i_seq] = (s[i_seq] + 1) & 0xFF
        data = c.status.encode(s)
        try:
            if self._raw:
                frame = self._status_frame
                frame[localbus.RAW_DATA:localbus.RAW_DATA + len(data)] = data
                self.bus.send_raw(frame)
            else:
                self._send_message(c.status.frame_id, data)
        except can.CanError as exc:
            raise HalConnectionLost(f"can: send failed: {exc}") from None
        self._ks[C_FRAMES_OUT] += 1

    def _announce(self) -> None:
        self._send_status()

    def status(self) -> dict:
        out = super().status()
        out.update(self.counters)
        q, ql = self._sequence, self._load_sequence
        out.update(sequence_gaps=q.gaps, samples_missed=q.missed, sequence_repeated=q.repeated,
                   sequence_behind=q.behind, sequence_implausible=q.implausible, sequence_resyncs=q.resyncs,
                   load_sequence_repeated=ql.repeated, load_sequence_behind=ql.behind,
                   load_sequence_implausible=ql.implausible, load_sequence_resyncs=ql.resyncs,
                   load_frames_missed=ql.missed)
        out.update(interface=self.interface, channel=self.channel,
                   bus_load_percent=100 * self.budget.load, bus=self.budget.description)
        return out


VCAN_COMMANDS = "sudo modprobe vcan && sudo ip link add dev vcan0 type vcan && sudo ip link set vcan0 up"


def socketcan_problem(channel: str) -> str | None:
    """Why a SocketCAN ``channel`` cannot be opened on this machine, with what to do (None: the
    kernel has SocketCAN and the interface exists)."""
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except (AttributeError, OSError):
        return ("this kernel has no SocketCAN (on the lab PC: `sudo modprobe can_raw`; a virtual bus: "
                f"`{VCAN_COMMANDS}`; without SocketCAN, python-can's virtual or the local bus: "
                "interface virtual or beamctl_local)")
    if not Path("/sys/class/net", channel).exists():
        return (f"no network interface {channel} (`ip link show` lists them; a virtual bus: "
                f"`{VCAN_COMMANDS}`)")
    return None


def open_hint(interface: str, channel: str) -> str:
    """What to do when opening a bus failed, for the message (empty: nothing to add)."""
    if interface != "socketcan":
        return ""
    problem = socketcan_problem(channel)
    return f": {problem}" if problem else ""
