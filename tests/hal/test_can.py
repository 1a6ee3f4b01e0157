"""The CAN backend: garbage never reaches the controller; codecs, budget, recording."""

import subprocess
import sys
from pathlib import Path

import can
import cantools
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from beamctl import hal
from beamctl.hal.base import HalConfigurationError, HalConnectionLost, HalStaleData
from beamctl.hal.budget import bus_budget, check_budget, classic_frame_bits, fd_frame_time
from beamctl.hal.can_backend import CanBackend
from beamctl.hal.dbc import Contract, default_dbc_path

CONTRACT = Contract()


class Daq:
    """A hand-driven DAQ on a virtual channel, to inject good and bad frames."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.seq = 0

    def strains(self, values=(1e-5, -2e-5, 3e-6, 0.0), seq=None, dlc=None, raw: bytes | None = None):
        seq = self.seq if seq is None else seq
        data = raw if raw is not None else CONTRACT.strains.encode([*values, seq & 0xFF])
        if dlc is not None:
            data = data[:dlc]
        self.bus.send(can.Message(arbitration_id=CONTRACT.strains.frame_id, data=data, is_extended_id=False))
        self.seq = (seq + 1) & 0xFF

    def load(self, value=1500.0, seq=0, raw: bytes | None = None):
        data = raw if raw is not None else CONTRACT.load.encode([value, seq])
        self.bus.send(can.Message(arbitration_id=CONTRACT.load.frame_id, data=data, is_extended_id=False))

    def send(self, **kwargs):
        self.bus.send(can.Message(**kwargs))


@pytest.fixture
def pair(request):
    channel = f"garbage-{request.node.name}"
    backend = CanBackend(2500.0, "virtual", channel).open()
    daq = Daq(channel)
    daq.load()
    yield backend, daq
    backend.close()
    daq.bus.shutdown()


def _read_all(backend, timeout=0.05):
    out = []
    while True:
        try:
            s = backend.read(timeout=timeout)
        except HalStaleData:
            return out
        out.append((s.sequence, s.strains.copy(), s.axial_load))


def test_good_frames_become_samples(pair):
    backend, daq = pair
    for _ in range(5):
        daq.strains()
    samples = _read_all(backend)
    assert [s[0] for s in samples] == [0, 1, 2, 3, 4]
    np.testing.assert_allclose(samples[0][1], [1e-5, -2e-5, 3e-6, 0.0], atol=2.6e-7)
    assert samples[0][2] == pytest.approx(1500.0, abs=0.05)


def test_unknown_ids_short_frames_and_out_of_range_values_are_counted_and_dropped(pair):
    backend, daq = pair
    daq.strains()
    daq.send(arbitration_id=0x7FF, data=b"\x01\x02", is_extended_id=False)
    daq.send(arbitration_id=0x1ABCDE, data=bytes(8), is_extended_id=True)
    daq.strains(dlc=5)                                          # short frame
    daq.strains(raw=(0x1FFF).to_bytes(8, "little"))              # strain_y1 = +8191 LSB > 0.004
    daq.load(raw=b"\xff\xff\x01")                                # load 6053.5 N > 6000 N
    daq.strains()
    samples = _read_all(backend)
    assert [s[0] for s in samples] == [0, 3], "only the two good strain frames arrive"
    c = backend.counters
    assert (c["unknown_ids"], c["wrong_length"], c["out_of_range"]) == (2, 1, 2), c
    assert c["sequence_gaps"] == 1, "the dropped frames show up as a gap"
    assert all(np.all(np.abs(s[1]) < 1e-4) for s in samples)
    assert all(s[2] == pytest.approx(1500.0, abs=0.05) for s in samples), "bad load never used"


def test_sequence_jumps_are_counted(pair):
    backend, daq = pair
    for seq in (0, 1, 2, 7, 8, 255, 0):
        daq.strains(seq=seq)
    samples = _read_all(backend)
    assert len(samples) == 7
    assert backend.counters["sequence_gaps"] == 2
    assert backend.counters["samples_missed"] == 4 + 246


def test_error_frames_are_counted_and_bus_off_is_a_lost_connection(pair):
    backend, daq = pair
    daq.send(arbitration_id=0x004, is_error_frame=True, data=bytes(8))   # controller problem
    daq.strains()
    assert len(_read_all(backend)) == 1
    assert backend.counters["error_frames"] == 1
    daq.send(arbitration_id=0x040, is_error_frame=True, data=bytes(8))   # bus-off
    with pytest.raises(HalConnectionLost, match="bus-off"):
        backend.read(timeout=0.1)


def test_no_sample_before_the_first_load_value(request):
    channel = f"noload-{request.node.name}"
    backend = CanBackend(2500.0, "virtual", channel).open()
    daq = Daq(channel)
    try:
        daq.strains()
        with pytest.raises(HalStaleData):
            backend.read(timeout=0.05)
        daq.load(1234.5)
        daq.strains()
        assert backend.read(timeout=0.05).axial_load == pytest.approx(1234.5, abs=0.05)
    finally:
        backend.close()
        daq.bus.shutdown()


def test_strain_frames_without_load_frames_become_a_protocol_error(pair):
    """The load cell comes every 10th sample; a sample whose load is more than five load
    periods old is not a sample of the rig as it is (the gain schedule would run on a stale
    load): the read raises, which the controller turns into a HAL fault and a ramp to bias."""
    backend, daq = pair                      # one load frame sent, then only strains
    for _ in range(60):
        daq.strains()
    delivered = 0
    with pytest.raises(hal.HalProtocolError, match="no DAQ_Load frame for 51 samples"):
        for _ in range(60):
            backend.read(timeout=0.5)
            delivered += 1
    assert delivered == 50, "five load periods (50 samples) of strains use the last load"


def test_voltage_and_heartbeat_frames_follow_the_dbc(pair):
    """Each voltage frame carries the low four bits of the sequence of the sample it answers;
    the heartbeat follows every 25th voltage frame."""
    backend, daq = pair
    backend.publish_status(2, 0, 5)
    for seq in range(30, 55):
        daq.strains(seq=seq)
        assert backend.read(timeout=0.5).sequence == seq
        backend.write(np.array([0.0, 30.15, 75.0, 90.0, 120.3, 150.0]))
    frames = []
    while (m := daq.bus.recv(0.05)) is not None:
        frames.append(m)
    db = cantools.database.load_file(str(default_dbc_path()))
    volts = [db.decode_message(m.arbitration_id, m.data) for m in frames if m.arbitration_id == 0x120]
    status = [db.decode_message(m.arbitration_id, m.data) for m in frames if m.arbitration_id == 0x121]
    assert len(volts) == 25 and len(status) == 1
    assert [v["sequence"] for v in volts] == [seq % 16 for seq in range(30, 55)]
    assert volts[0]["voltage_b3"] == pytest.approx(150.0) and volts[0]["voltage_a2"] == pytest.approx(30.15)
    assert status[0]["state"] == 2 and status[0]["flags"] == 5


def test_a_voltage_outside_the_dbc_range_is_refused(pair):
    backend, _ = pair
    with pytest.raises(hal.HalProtocolError, match="voltage_a1"):
        backend.write(np.array([-1.0, 75, 75, 75, 75, 75]))


@settings(max_examples=200)
@given(values=st.lists(st.floats(min_value=-0.004, max_value=0.004), min_size=4, max_size=4),
       seq=st.integers(0, 255))
def test_compiled_codec_agrees_with_cantools(values, seq):
    db = cantools.database.load_file(str(default_dbc_path()))
    msg = db.get_message_by_name("DAQ_Strains")
    names = ["strain_y1", "strain_z1", "strain_y2", "strain_z2"]
    ours = CONTRACT.strains.encode([*values, seq])
    theirs = msg.encode(dict(zip(names + ["sequence"], [*values, seq], strict=True)), strict=False)
    assert ours == theirs
    decoded = [0.0] * 5
    assert CONTRACT.strains.decode_into(ours, decoded)
    reference = msg.decode(ours)
    assert decoded == pytest.approx([reference[n] for n in names + ["sequence"]], abs=1e-12)


def test_classic_frame_length_with_worst_case_stuffing():
    assert classic_frame_bits(8) == 135 and classic_frame_bits(0) == 55
    assert classic_frame_bits(8, extended=True) == 160
    assert fd_frame_time(8, 1e6, 4e6) < classic_frame_bits(8) / 1e6


def test_default_frames_fit_classic_can_at_2500_hz_and_the_limit_is_said():
    """Per sample: two 8-byte frames (strains, voltages), a 3-byte load frame every 10th and a
    4-byte heartbeat every 25th sample, each with worst-case stuffing, at 1 Mbit/s."""
    bits_per_sample = 2 * classic_frame_bits(8) + classic_frame_bits(3) / 10 + classic_frame_bits(4) / 25
    b = check_budget(CONTRACT, 2500.0, 1e6)
    assert b.load == pytest.approx(2500.0 * bits_per_sample / 1e6, rel=1e-12)
    highest = int(0.8e6 / bits_per_sample)                  # whole hertz within 80 %
    assert b.max_sample_rate_hz == highest
    assert bus_budget(CONTRACT, highest, 1e6).load <= 0.8 < bus_budget(CONTRACT, highest + 1, 1e6).load
    with pytest.raises(HalConfigurationError) as err:
        check_budget(CONTRACT, 3000.0, 1e6)
    message = str(err.value)
    assert f"{100 * 3000.0 * bits_per_sample / 1e6:.1f} %" in message, message
    assert f"at most {highest} Hz" in message and "CAN FD" in message, message
    fd = check_budget(CONTRACT, 5000.0, 1e6, fd=True, data_bitrate_bit_s=4e6)
    assert fd.max_sample_rate_hz > 6000


def test_unknown_backend_is_refused_and_the_sim_never_loads_a_can_library(tmp_path):
    with pytest.raises(HalConfigurationError, match="unknown HAL backend 'daq'"):
        hal.create("daq")
    code = ("import sys; from beamctl import hal; hal.backend_class('sim'); "
            "print('can' in sys.modules, 'cantools' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=tmp_path)
    assert out.stdout.split() == ["False", "False"], out.stdout


@pytest.mark.parametrize("suffix", [".asc", ".blf"])
def test_traffic_is_recorded_for_standard_can_tools(tmp_path, suffix, request):
    channel = f"record-{suffix}"
    path = tmp_path / f"traffic{suffix}"
    backend = CanBackend(2500.0, "virtual", channel, record=path).open()
    daq = Daq(channel)
    daq.load()
    for _ in range(3):
        daq.strains()
        backend.read(timeout=0.1)
        backend.write(np.full(6, 75.0))
    backend.close()
    daq.bus.shutdown()
    ids = [m.arbitration_id for m in can.LogReader(str(path))]
    assert ids.count(0x100) == 3 and ids.count(0x120) == 3 and 0x101 in ids


def test_recording_needs_a_known_format():
    with pytest.raises(HalConfigurationError, match=".asc or .blf"):
        CanBackend(2500.0, "virtual", "x", record="traffic.txt")


@pytest.mark.skipif(not Path("/sys/class/net/vcan0").exists(), reason="no vcan0 on this machine")
def test_socketcan_vcan0_round_trip():
    backend = CanBackend(2500.0, "socketcan", "vcan0").open()
    daq = can.Bus(interface="socketcan", channel="vcan0")
    try:
        daq.send(can.Message(arbitration_id=0x101, data=CONTRACT.load.encode([1000.0, 0]),
                             is_extended_id=False))
        daq.send(can.Message(arbitration_id=0x100, data=CONTRACT.strains.encode([0, 0, 0, 0, 0]),
                             is_extended_id=False))
        assert backend.read(timeout=0.5).axial_load == pytest.approx(1000.0, abs=0.05)
    finally:
        backend.close()
        daq.shutdown()


def test_a_daq_sampling_at_another_rate_than_the_gains_is_refused(pair):
    """The gains, filters and integrator assume the table's 2500 Hz; a DAQ set to 2000 Hz
    (here: frames paced at 0.5 ms) is a protocol error, i.e. a fault."""
    import time as _time

    backend, daq = pair
    with pytest.raises(hal.HalProtocolError, match=r"arrive at \d+ Hz; the gains are designed for 2500 Hz"):
        next_send = _time.perf_counter()
        for k in range(1200):
            next_send += 0.0005
            while _time.perf_counter() < next_send:
                pass
            if k % 10 == 0:
                daq.load(seq=k // 10)
            daq.strains()
            backend.read(timeout=0.1)
    assert backend.measured_rate_hz < 2200
