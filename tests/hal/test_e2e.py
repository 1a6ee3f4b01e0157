"""End-to-end protection (hal/e2e.py): the CRC over each message's Data ID, checked against an
independent bitwise implementation, the DBC's Data IDs, and the alive counter's window and
resynchronisation on arrival times the tests construct."""

from pathlib import Path

import can
import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from beamctl.hal.base import HalConfigurationError
from beamctl.hal.dbc import MESSAGES, Contract, default_dbc_path
from beamctl.hal.e2e import (
    BEHIND,
    IMPLAUSIBLE,
    JITTER_PERIODS,
    NEW,
    REPEATED,
    RESYNC,
    SYNC_FRAMES,
    AliveCounter,
    crc8_sae_j1850,
    frame_crc,
)
from tests.hal.reference import low_byte_crc, reference_crc8, reference_frame_crc

CONTRACT = Contract()


# -- CRC -----------------------------------------------------------------------------------------------------
def test_the_crc_is_the_catalogue_s_crc_8_sae_j1850():
    assert reference_crc8(b"123456789") == 0x4B, "the reference itself: the catalogue's check value"
    assert crc8_sae_j1850(b"123456789") == 0x4B
    assert crc8_sae_j1850(b"") == 0x00


@settings(max_examples=300)
@given(data=st.binary(max_size=64))
def test_the_compiled_crc_agrees_with_the_bitwise_reference(data):
    assert crc8_sae_j1850(data) == reference_crc8(data)


@settings(max_examples=300)
@given(data_id=st.integers(0, 0xFFFF), data=st.binary(min_size=1, max_size=64), position=st.integers(0, 63))
def test_a_frame_crc_covers_the_data_id_low_byte_then_high_byte_then_the_data(data_id, data, position):
    crc_byte = position % len(data)
    assert frame_crc(data_id, data, crc_byte) == reference_frame_crc(data_id, data, crc_byte)


def test_every_message_has_the_data_id_of_its_dbc_attribute_and_they_differ():
    db = cantools.database.load_file(str(default_dbc_path()))
    from_dbc = {name: db.get_message_by_name(name).dbc.attributes["DataID"].value
                for name, _ in MESSAGES.values()}
    assert {c.name: c.data_id for c in CONTRACT.codecs.values()} == from_dbc
    assert len(set(from_dbc.values())) == len(from_dbc)


@pytest.mark.parametrize("role", list(MESSAGES))
def test_encoded_frames_carry_the_reference_crc_and_a_changed_byte_fails_it(role):
    codec = CONTRACT.codecs[role]
    values = [max(s.minimum, 0.0) if s.name != "sequence" else 77 for s in codec.signals]
    data = codec.encode(values)
    assert data[codec.crc_byte] == reference_frame_crc(codec.data_id, data, codec.crc_byte)
    assert codec.crc_ok(data)
    for i in range(codec.length):                 # any single-bit error in any byte is caught
        changed = bytearray(data)
        changed[i] ^= 0x10
        assert not codec.crc_ok(changed), (role, i)


def test_a_frame_with_the_old_identifier_low_byte_crc_fails():
    """A frame whose CRC was computed the old way (over the identifier's low byte) is no longer
    valid under its identifier: the CRC names the message by its Data ID."""
    codec = CONTRACT.strains
    data = bytearray(codec.encode([1e-5, -2e-5, 3e-6, 0.0, 5, 0]))
    data[codec.crc_byte] = low_byte_crc(codec.frame_id, data, codec.crc_byte)
    assert data[codec.crc_byte] != reference_frame_crc(codec.data_id, data, codec.crc_byte), \
        "the two schemes happen to agree on this frame: choose other values"
    assert not codec.crc_ok(data)
    values = [0.0] * len(codec.names)
    assert codec.reject(_message(codec.frame_id, data), values) == "crc_errors"


def _message(frame_id, data):
    return can.Message(arbitration_id=frame_id, data=bytes(data), is_extended_id=False)


def _variant(tmp_path: Path, old: str, new: str) -> Path:
    text = default_dbc_path().read_text()
    assert old in text, old
    path = tmp_path / "variant.dbc"
    path.write_text(text.replace(old, new))
    return path


def test_two_identifiers_sharing_a_low_byte_are_told_apart(tmp_path):
    """CTRL_Voltages moved to 0x200, which shares its low byte 0x00 with DAQ_Strains' 0x100 (both
    8 bytes): under the old scheme a voltage frame carried the very CRC a strain frame of the same
    bytes must carry; with the Data IDs a voltage frame on 0x100 fails the strains' CRC."""
    path = _variant(tmp_path, "BO_ 288 CTRL_Voltages", "BO_ 512 CTRL_Voltages")
    text = path.read_text().replace("BO_ 288 ", "BO_ 512 ").replace("SG_ 288 ", "SG_ 512 ")
    path.write_text(text)
    contract = Contract(path)
    assert contract.voltages.frame_id & 0xFF == contract.strains.frame_id & 0xFF
    frame = contract.voltages.encode([30.0, 60.0, 90.0, 120.0, 150.0, 0.0, 9, 0])
    assert low_byte_crc(0x200, frame, 7) == low_byte_crc(0x100, frame, 7), "the old scheme: one CRC for both"
    assert contract.voltages.crc_ok(frame)
    assert not contract.strains.crc_ok(frame)
    assert contract.strains.reject(_message(contract.strains.frame_id, frame), [0.0] * 6) == "crc_errors"


@pytest.mark.parametrize(("old", "new", "names"), [
    ('BA_ "DataID" BO_ 257 45058;\n', "", ["DAQ_Load", "no DataID attribute"]),
    ('BA_ "DataID" BO_ 257 45058;', 'BA_ "DataID" BO_ 257 45057;', ["DAQ_Load", "DAQ_Strains", "0xB001"]),
    ('BA_ "DataID" BO_ 289 45060;', 'BA_ "DataID" BO_ 289 70000;', ["CTRL_Status", "70000", "16-bit"]),
], ids=["missing", "shared", "too-large"])
def test_a_dbc_without_a_data_id_of_its_own_per_message_is_refused_in_one_line(tmp_path, old, new, names):
    with pytest.raises(HalConfigurationError) as err:
        Contract(_variant(tmp_path, old, new))
    message = str(err.value)
    assert "\n" not in message and all(n in message for n in names), message


# -- the alive counter ---------------------------------------------------------------------------------------
# A period of 2**-11 s (2048 Hz): the arrival times below and their differences are exact binary
# fractions, so a jump exactly at the window's edge is decided by the rule, not by rounding.
P = 2.0 ** -11
T0 = 1000.0


def at(k: float) -> float:
    """The arrival time of sample ``k``."""
    return T0 + k * P


def fresh(first: int = 100) -> AliveCounter:
    c = AliveCounter(256, P)
    assert c.accept(first, at(0)) == NEW and c.last == first
    return c


def test_the_first_frame_is_taken_as_it_comes_and_frames_in_order_skip_nothing():
    c = AliveCounter(256, P)
    assert c.last is None
    verdicts = [c.accept(seq % 256, at(k)) for k, seq in enumerate(range(250, 262))]
    assert verdicts == [NEW] * 12 and c.skipped == 0 and c.last == 5
    assert (c.gaps, c.missed, c.repeated, c.behind, c.implausible, c.resyncs) == (0, 0, 0, 0, 0, 0)


@pytest.mark.parametrize("elapsed", [0, 1, 5, 40, 124, 125, 126, 400])
def test_a_forward_jump_is_accepted_up_to_the_elapsed_periods_plus_the_jitter_allowance(elapsed):
    """From counter 100, a frame ``elapsed`` periods later: new up to elapsed + 2 ahead (never
    beyond 127), implausible from there up to 127, behind from 128."""
    window = min(elapsed + JITTER_PERIODS, 127)
    for delta in range(1, 256):
        c = fresh(100)
        verdict = c.accept((100 + delta) % 256, at(elapsed))
        expected = NEW if delta <= window else IMPLAUSIBLE if delta < 128 else BEHIND
        assert verdict == expected, f"jump of {delta} after {elapsed} periods"
        if verdict == NEW:
            assert c.skipped == delta - 1 and c.missed == delta - 1 and c.gaps == (delta > 1)
        else:
            assert c.last == 100, "a refused frame moved the counter"


def test_a_jump_as_large_as_the_periods_elapsed_tells_the_samples_skipped():
    """Samples 11..14 lost: sample 15 arrives five periods after 10; four skipped."""
    c = fresh(10)
    assert c.accept(15, at(5)) == NEW and c.skipped == 4
    assert c.accept(16, at(6)) == NEW and c.skipped == 0
    assert (c.gaps, c.missed) == (1, 4)


def test_a_frame_replayed_200_samples_later_is_refused_and_counted():
    """The frame of sample 100 (counter 100) replayed just after sample 300's (counter 44): its
    counter looks 56 ahead, while under a period has passed."""
    c = AliveCounter(256, P)
    for k in range(301):
        assert c.accept(k % 256, at(k)) == NEW
    assert c.accept(100, at(300.5)) == IMPLAUSIBLE
    assert c.last == 300 % 256
    assert c.accept(301 % 256, at(301)) == NEW and c.skipped == 0, "the stream goes on as if nothing came"
    assert (c.implausible, c.gaps, c.missed, c.resyncs) == (1, 0, 0, 0)


@pytest.mark.parametrize("ahead", [128, 156, 200, 250, 60])
def test_a_new_stream_is_taken_after_sync_consecutive_frames(ahead):
    """The sender restarted (or its counter moved on while its frames were lost): a stream that
    starts ``ahead`` of the last accepted counter (128..255: looks behind; 60 one period later:
    implausible) is refused SYNC_FRAMES - 1 times, then followed, skipping nothing."""
    c = fresh(50)
    start = (50 + ahead) % 256
    refused = BEHIND if ahead >= 128 else IMPLAUSIBLE
    verdicts = [c.accept((start + i) % 256, at(1 + i)) for i in range(SYNC_FRAMES + 2)]
    assert verdicts == [refused] * (SYNC_FRAMES - 1) + [RESYNC, NEW, NEW]
    assert c.skipped == 0 and c.last == (start + SYNC_FRAMES + 1) % 256
    assert c.resyncs == 1 and (c.behind + c.implausible) == SYNC_FRAMES - 1 and c.missed == 0


def test_repeats_and_old_frames_are_dropped_and_do_not_resynchronise_by_themselves():
    c = fresh(20)
    verdicts = [c.accept(20, at(1)), c.accept(15, at(1)), c.accept(12, at(1)), c.accept(19, at(1)),
                c.accept(15, at(1)), c.accept(20, at(1))]
    assert verdicts == [REPEATED, BEHIND, BEHIND, BEHIND, BEHIND, REPEATED]
    assert c.last == 20 and (c.repeated, c.behind, c.resyncs) == (2, 4, 0)


def test_a_repeat_leaves_a_new_stream_s_run_as_it_is_and_an_accepted_frame_ends_it():
    c = fresh(50)
    # a new stream at 200, a repeat of the accepted 50 in between: still three in a row
    assert [c.accept(s, at(1)) for s in (200, 50, 201, 202)] == [BEHIND, REPEATED, BEHIND, RESYNC]
    c = fresh(50)
    # the old stream's next frame is accepted between: the new stream's run starts again
    verdicts = [c.accept(s, at(k)) for s, k in ((200, 1), (201, 1), (51, 1), (202, 2), (203, 2), (204, 2))]
    assert verdicts == [BEHIND, BEHIND, NEW, BEHIND, BEHIND, RESYNC]


def test_after_a_silence_of_half_the_span_a_jump_is_the_smallest_the_counter_allows():
    """1000 periods without a frame: the counter may have wrapped; a frame 127 ahead is taken as
    127 ahead (126 skipped, the least the counter allows), one 128 ahead looks behind."""
    c = fresh(0)
    assert c.accept(127, at(1000)) == NEW and c.skipped == 126
    c = fresh(0)
    assert c.accept(128, at(1000)) == BEHIND


def test_the_counts_of_a_scripted_stream():
    c = AliveCounter(256, P)
    script = [(0, 0), (1, 1), (1, 1.5), (4, 4), (3, 4.5), (9, 9), (9, 9), (100, 9.5),
              (200, 10), (201, 11), (202, 12), (203, 13)]
    verdicts = [c.accept(seq, at(k)) for seq, k in script]
    assert verdicts == [NEW, NEW, REPEATED, NEW, BEHIND, NEW, REPEATED, IMPLAUSIBLE,
                        BEHIND, BEHIND, RESYNC, NEW]
    assert (c.gaps, c.missed, c.repeated, c.behind, c.implausible, c.resyncs) == (2, 2 + 4, 2, 3, 1, 1)
    c.reset()
    assert c.last is None and (c.gaps, c.missed, c.repeated, c.behind, c.implausible, c.resyncs) == (0,) * 6
    assert c.accept(17, at(100)) == NEW


def test_a_counter_needs_a_power_of_two_and_a_period():
    with pytest.raises(ValueError, match="power of two"):
        AliveCounter(100, P)
    with pytest.raises(ValueError, match="positive"):
        AliveCounter(256, 0.0)
