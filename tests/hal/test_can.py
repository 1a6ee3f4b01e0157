"""The CAN backend: garbage never reaches the controller; codecs, budget, recording."""

import subprocess
import sys
import time
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
from beamctl.hal.e2e import crc8_sae_j1850, frame_crc

CONTRACT = Contract()


class Daq:
    """A hand-driven DAQ on a virtual channel, to inject good and bad frames."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.seq = 0

    def strains(self, values=(1e-5, -2e-5, 3e-6, 0.0), seq=None, dlc=None, raw: bytes | None = None,
                **frame):
        seq = self.seq if seq is None else seq
        data = raw if raw is not None else CONTRACT.strains.encode([*values, seq & 0xFF, 0])
        if dlc is not None:
            data = data[:dlc]
        self.bus.send(can.Message(arbitration_id=CONTRACT.strains.frame_id, data=data,
                                  **{"is_extended_id": False, **frame}))
        self.seq = (seq + 1) & 0xFF

    def load(self, value=1500.0, seq=0, raw: bytes | None = None):
        data = raw if raw is not None else CONTRACT.load.encode([value, seq, 0])
        self.bus.send(can.Message(arbitration_id=CONTRACT.load.frame_id, data=data, is_extended_id=False))

    def send(self, **kwargs):
        self.bus.send(can.Message(**kwargs))


def with_crc(codec, data: bytes) -> bytes:
    """``data`` with its CRC byte made right (to build frames that are bad in another way)."""
    out = bytearray(data)
    out[codec.crc_byte] = frame_crc(codec.frame_id, out, codec.crc_byte)
    return bytes(out)


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
    np.testing.assert_allclose(samples[0][1], [1e-5, -2e-5, 3e-6, 0.0], atol=2.6e-7,
                               err_msg="strains within half the 5e-7 resolution")
    assert samples[0][2] == pytest.approx(1500.0, abs=0.05)


def test_unknown_ids_short_frames_and_out_of_range_values_are_counted_and_dropped(pair):
    backend, daq = pair
    daq.strains()
    daq.send(arbitration_id=0x7FF, data=b"\x01\x02", is_extended_id=False)
    daq.strains(dlc=5)                                          # short frame
    # strain_y1 raw -2048: -1.024e-3, one step beyond the DBC's full scale (CRC right)
    daq.strains(raw=with_crc(CONTRACT.strains, (0x800).to_bytes(6, "little") + bytes([2, 0])))
    daq.load(raw=with_crc(CONTRACT.load, b"\xff\xff\x01\x00"))   # load 6053.5 N > 6000 N
    daq.strains(seq=3)
    samples = _read_all(backend)
    assert [s[0] for s in samples] == [0, 3], "only the two good strain frames arrive"
    c = backend.status()
    assert (c["unknown_ids"], c["wrong_length"], c["out_of_range"]) == (1, 1, 2), c
    assert (c["sequence_gaps"], c["samples_missed"]) == (1, 2), "the dropped frames show up as a gap"
    assert all(np.all(np.abs(s[1]) < 1e-4) for s in samples)
    assert all(s[2] == pytest.approx(1500.0, abs=0.05) for s in samples), "bad load never used"


def test_an_extended_frame_on_the_strain_identifier_never_becomes_a_sample(pair):
    """A 29-bit frame whose identifier happens to be 0x100 is another frame altogether: counted
    as an extended identifier, never decoded as DAQ_Strains."""
    backend, daq = pair
    daq.strains(values=(9e-4, 9e-4, 9e-4, 9e-4), is_extended_id=True)
    daq.send(arbitration_id=0x1ABCDE, data=bytes(8), is_extended_id=True)
    daq.strains(seq=1)
    samples = _read_all(backend)
    assert [s[0] for s in samples] == [1], samples
    assert backend.status()["extended_ids"] == 2
    assert backend.status()["unknown_ids"] == 0, "an extended identifier is its own kind of garbage"


def test_a_remote_frame_never_becomes_a_sample(pair):
    """A remote request on 0x100 with DLC 8 carries no data: it must not become an all-zero
    strain sample."""
    backend, daq = pair
    daq.send(arbitration_id=CONTRACT.strains.frame_id, is_remote_frame=True, dlc=8, is_extended_id=False)
    daq.strains(seq=0)
    samples = _read_all(backend)
    assert [s[0] for s in samples] == [0] and samples[0][1][0] == pytest.approx(1e-5, abs=2.6e-7)
    assert backend.status()["remote_frames"] == 1


@settings(max_examples=300, deadline=None)
@given(payload=st.binary(min_size=7, max_size=7), sequence=st.integers(1, 127))
def test_a_payload_with_a_wrong_crc_never_reaches_the_law(payload, sequence):
    """Random bytes that decode inside the DBC ranges, with a sequence the receiver would take:
    only the CRC stands between them and the stacks."""
    channel = f"crc-{sequence}-{payload.hex()}"
    backend = CanBackend(2500.0, "virtual", channel).open()
    daq = Daq(channel)
    try:
        daq.load()
        daq.strains(seq=0)
        data = bytearray(payload[:6] + bytes([sequence]) + b"\x00")
        data[7] = frame_crc(CONTRACT.strains.frame_id, data, 7) ^ 0x5A     # any wrong CRC
        daq.strains(raw=bytes(data))
        assert [s[0] for s in _read_all(backend, 0.01)] == [0]
        assert backend.status()["crc_errors"] == 1
    finally:
        backend.close()
        daq.bus.shutdown()


def test_a_crc_over_another_identifier_is_wrong(pair):
    """The identifier's low byte is part of the CRC: a DAQ_Load payload moved onto 0x100 with its
    own CRC fails, even where its bytes would decode."""
    backend, daq = pair
    crc_as_load = frame_crc(CONTRACT.load.frame_id, bytes(8), 7)
    daq.strains(raw=bytes(7) + bytes([crc_as_load]))
    daq.strains(seq=1)
    assert [s[0] for s in _read_all(backend)] == [1]
    assert backend.status()["crc_errors"] == 1


def test_repeated_and_swapped_frames_never_reach_the_law(pair):
    """0, 1, 1 (a repeat), 3, 2 (overtaken), 4: the law sees 0, 1, 3, 4 once each, and one
    sample (2) is missing, not hundreds."""
    backend, daq = pair
    values = {0: 1e-5, 1: 2e-5, 2: 3e-5, 3: 4e-5, 4: 5e-5}
    for seq, value in [(0, 1e-5), (1, 2e-5), (1, 7e-4), (3, 4e-5), (2, 3e-5), (4, 5e-5)]:
        daq.strains(values=(value, 0.0, 0.0, 0.0), seq=seq)
    samples = _read_all(backend)
    assert [s[0] for s in samples] == [0, 1, 3, 4]
    assert [s[1][0] for s in samples] == pytest.approx([values[k] for k in (0, 1, 3, 4)], abs=2.6e-7), \
        "the repeated frame's 7e-4 must never be used"
    c = backend.status()
    assert (c["sequence_repeated"], c["sequence_behind"], c["samples_missed"]) == (1, 1, 1), c


def test_samples_missed_counts_the_samples_lost_across_the_wrap():
    """252 -> 255 loses two, 255 -> 0 none, 0 -> 3 two: four in two gaps."""
    channel = "missed-across-wrap"
    backend = CanBackend(2500.0, "virtual", channel).open()
    daq = Daq(channel)
    try:
        daq.load()
        for seq in (250, 251, 252, 255, 0, 3, 3, 3, 2, 1):
            daq.strains(seq=seq)
        assert [s[0] for s in _read_all(backend)] == [250, 251, 252, 255, 0, 3]
        c = backend.status()
        assert (c["sequence_gaps"], c["samples_missed"]) == (2, 4), c
        assert (c["sequence_repeated"], c["sequence_behind"]) == (2, 2), c
    finally:
        backend.close()
        daq.bus.shutdown()


def test_after_a_long_silence_the_counter_is_taken_as_it_comes(pair):
    """A DAQ that restarted (its counter back at 0) is followed again once the silence exceeds
    the resynchronisation time (100 periods), not rejected as old for ever."""
    backend, daq = pair
    daq.strains(seq=200)
    assert [s[0] for s in _read_all(backend)] == [200]
    time.sleep(150 / 2500.0)
    daq.load(seq=0)
    daq.strains(seq=0)
    daq.strains(seq=1)
    assert [s[0] for s in _read_all(backend)] == [0, 1]
    assert backend.status()["sequence_resyncs"] == 1


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
    """Each voltage frame carries the sequence of the sample it answers and a right CRC; the
    heartbeat follows every 25th voltage frame; a write with no new sample sends nothing."""
    backend, daq = pair
    backend.publish_status(2, 0, 5)
    for seq in range(30, 55):
        daq.strains(seq=seq)
        assert backend.read(timeout=0.5).sequence == seq
        backend.write(np.array([0.0, 30.0, 75.0, 90.0, 120.6, 150.0]))
    backend.write(np.full(6, 75.0))           # nothing new to answer
    frames = []
    while (m := daq.bus.recv(0.05)) is not None:
        frames.append(m)
    db = cantools.database.load_file(str(default_dbc_path()))
    volts = [db.decode_message(m.arbitration_id, m.data) for m in frames if m.arbitration_id == 0x120]
    status = [db.decode_message(m.arbitration_id, m.data) for m in frames if m.arbitration_id == 0x121]
    assert len(volts) == 25 and len(status) == 1
    assert backend.status()["unanswered_writes"] == 1
    assert [v["sequence"] for v in volts] == list(range(30, 55))
    assert volts[0]["voltage_b3"] == pytest.approx(150.0) and volts[0]["voltage_a2"] == pytest.approx(30.0)
    assert volts[0]["voltage_b2"] == pytest.approx(120.6)
    assert status[0]["state"] == 2 and status[0]["flags"] == 5
    for m in frames:
        crc_byte = len(m.data) - 1
        assert m.data[crc_byte] == crc8_sae_j1850(bytes(m.data[:crc_byte]), m.arbitration_id), m


def test_the_final_state_is_announced_at_once(pair):
    backend, daq = pair
    backend.announce(5, 0, 0)
    m = daq.bus.recv(0.5)
    assert m is not None and m.arbitration_id == CONTRACT.status.frame_id
    values = [0] * len(CONTRACT.status.names)
    assert CONTRACT.status.crc_ok(m.data) and CONTRACT.status.decode_into(m.data, values)
    assert values[CONTRACT.status.index("state")] == 5


def test_a_voltage_outside_the_dbc_range_is_refused(pair):
    backend, daq = pair
    daq.strains()
    backend.read(timeout=0.5)
    with pytest.raises(hal.HalProtocolError, match="voltage_a1"):
        backend.write(np.array([-1.0, 75, 75, 75, 75, 75]))


def test_crc8_is_sae_j1850():
    """The catalogue's check value of CRC-8/SAE-J1850: 0x4B over "123456789"."""
    assert crc8_sae_j1850(b"123456789") == 0x4B
    assert crc8_sae_j1850(b"") == 0x00


@settings(max_examples=200)
@given(values=st.lists(st.floats(min_value=-0.0010235, max_value=0.0010235), min_size=4, max_size=4),
       seq=st.integers(0, 255))
def test_compiled_codec_agrees_with_cantools(values, seq):
    db = cantools.database.load_file(str(default_dbc_path()))
    msg = db.get_message_by_name("DAQ_Strains")
    names = ["strain_y1", "strain_z1", "strain_y2", "strain_z2", "sequence"]
    ours = CONTRACT.strains.encode([*values, seq, 0])
    theirs = bytearray(msg.encode(dict(zip(names + ["crc"], [*values, seq, 0], strict=True)), strict=False))
    theirs[7] = crc8_sae_j1850(bytes(theirs[:7]), 0x100)
    assert ours == bytes(theirs)
    decoded = [0.0] * 6
    assert CONTRACT.strains.decode_into(ours, decoded) and CONTRACT.strains.crc_ok(ours)
    reference = msg.decode(ours)
    assert decoded == pytest.approx([reference[n] for n in names + ["crc"]], abs=1e-12)


def test_classic_frame_length_with_worst_case_stuffing():
    assert classic_frame_bits(8) == 135 and classic_frame_bits(0) == 55
    assert classic_frame_bits(8, extended=True) == 160
    assert fd_frame_time(8, 1e6, 4e6) < classic_frame_bits(8) / 1e6


def test_default_frames_fit_classic_can_at_2500_hz_and_the_limit_is_said():
    """Per sample: two 8-byte frames (strains, voltages), a 4-byte load frame every 10th and a
    5-byte heartbeat every 25th sample, each with worst-case stuffing, at 1 Mbit/s."""
    bits_per_sample = 2 * classic_frame_bits(8) + classic_frame_bits(4) / 10 + classic_frame_bits(5) / 25
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
        daq.send(can.Message(arbitration_id=0x101, data=CONTRACT.load.encode([1000.0, 0, 0]),
                             is_extended_id=False))
        daq.send(can.Message(arbitration_id=0x100, data=CONTRACT.strains.encode([0, 0, 0, 0, 0, 0]),
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
