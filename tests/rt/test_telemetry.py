"""Telemetry files: reading them whole or cut off mid-write, what their header says, and what a
decimated or triggered recording keeps."""

import time

import numpy as np
import pytest
import yaml

from beamctl.config.schema import ConfigError
from beamctl.gains.defaults import paper_table_path
from beamctl.gains.table import load_table
from beamctl.rt.config import controller_config
from beamctl.rt.controller import FLAG_NAMES, RECORD_COLUMNS, TRIGGER_FLAGS, Controller
from beamctl.rt.loop import ControlLoop
from beamctl.rt.safety import Fault, State
from beamctl.rt.telemetry import Recording, TelemetryError, TelemetryReader, TelemetryWriter, read_telemetry
from tests.rt.fakes import ScriptedHal
from tests.rt.test_loop import oscillating


def _recording(path, rows: int):
    with TelemetryWriter(path, ["t", "x"], capacity=1024) as writer:
        for i in range(rows):
            writer.push(np.array([i, 2.0 * i]))
    return path


def test_a_complete_file_has_no_incomplete_row(tmp_path):
    header, rows = read_telemetry(_recording(tmp_path / "t.btl", 10))
    assert len(rows) == 10 and header["incomplete_row_bytes"] == 0
    assert header["columns"] == ["t", "x"]


def test_a_file_cut_off_mid_row_gives_its_complete_rows_and_says_what_it_ignored(tmp_path):
    path = _recording(tmp_path / "t.btl", 10)
    path.write_bytes(path.read_bytes()[:-5])          # the last row (16 bytes) loses 5
    header, rows = read_telemetry(path)
    np.testing.assert_array_equal(rows[:, 0], np.arange(9))
    assert header["incomplete_row_bytes"] == 11


def test_chunks_give_the_rows_read_whole(tmp_path):
    path = _recording(tmp_path / "t.btl", 100)
    with TelemetryReader(path) as reader:
        whole = reader.read_all()
        chunked = np.vstack([chunk.copy() for chunk in reader.chunks(7)])   # 7 does not divide 100
    np.testing.assert_array_equal(chunked, whole)
    np.testing.assert_array_equal(whole[:, 1], 2.0 * np.arange(100))


def test_a_header_cut_off_is_refused_in_one_line(tmp_path):
    path = _recording(tmp_path / "t.btl", 10)
    path.write_bytes(path.read_bytes()[:40])          # magic, length and part of the header
    with pytest.raises(TelemetryError, match="damaged header") as err:
        read_telemetry(path)
    assert "\n" not in str(err.value)


# -- what the header says -------------------------------------------------------------------------

def _paper_loop(tmp_path, telemetry: dict | None = None, beam=oscillating, cycles: int = 2000):
    table = load_table(paper_table_path())
    controller = Controller(table, controller_config({"pacing": "sample", "telemetry": telemetry or {}}))
    hal = ScriptedHal(table.design.sample_rate_hz, default=beam).open()
    writer = TelemetryWriter.for_controller(tmp_path / "run.btl", controller, meta={"run": "test"}).start()
    ControlLoop(controller, hal, telemetry=writer, max_cycles=cycles).run(acquire_rt=False)
    return table, writer


def test_a_controllers_recording_says_its_rate_table_units_and_labels(tmp_path):
    table, writer = _paper_loop(tmp_path, cycles=50)
    header, _ = read_telemetry(writer.path)
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)   # libyaml where installed: the same data
    stored_hash = yaml.load(paper_table_path().read_text(), Loader=loader)["sha256"]
    assert header["meta"]["gain_table_sha256"] == stored_hash, \
        "the header must carry the sha256 the gain table file carries"
    assert header["meta"]["run"] == "test"
    assert header["sample_rate_hz"] == table.design.sample_rate_hz == 2500.0
    assert header["recording"] == {"mode": "full"}
    units = header["units"]
    assert [units[c] for c in ("time_s", "load_N", "voltage_a1_V", "step_us")] == ["s", "N", "V", "us"]
    assert units["strain_y1"] == "m/m" and units["q_1y"] == "m*sqrt(kg)" and units["state"] == ""
    assert set(units) == set(RECORD_COLUMNS)
    assert header["labels"]["state"] == {str(s.value): s.name for s in State}
    assert header["labels"]["fault"] == {str(f.value): f.name for f in Fault}
    assert header["bits"]["flags"] == {str(bit): name for bit, name in FLAG_NAMES.items()}


# -- decimated and triggered recordings -----------------------------------------------------------

COLUMNS = ["time_s", "state", "fault", "flags", "x"]
LABELS = {"state": {s.value: s.name for s in State}, "fault": {f.value: f.name for f in Fault}}
BITS = {"flags": dict(FLAG_NAMES)}
RATE_HZ = 1000.0


def _rows(n: int, events: list[tuple[int, str, float]] = ()) -> np.ndarray:
    """n samples at RATE_HZ, RUNNING, no fault, no flags; each of ``events`` (index, column,
    value) sets a column from that sample on."""
    rows = np.zeros((n, len(COLUMNS)))
    rows[:, 0] = np.arange(n) / RATE_HZ
    rows[:, 1] = State.RUNNING
    rows[:, 4] = np.sin(np.arange(n))
    for i, column, value in sorted(events):
        rows[i:, COLUMNS.index(column)] = value
    return rows


def _record(path, rows: np.ndarray, recording: Recording, *, chunk_ends=(), start=True):
    """Push ``rows`` through a writer; with ``start`` the writer thread takes them in chunks
    that end at ``chunk_ends`` (each pushed part is waited for before the next); without it,
    close() writes them all. The ring holds the largest part, so the ring wraps round and
    nothing is dropped. Return the header and the sample indices of the rows in the file."""
    ends = (*chunk_ends, len(rows))
    capacity = max(np.diff(ends, prepend=0)) if start else len(rows)
    writer = TelemetryWriter(path, COLUMNS, capacity, flush_interval_s=0.01, sample_rate_hz=RATE_HZ,
                             recording=recording, labels=LABELS, bits=BITS,
                             trigger_bits={"flags": TRIGGER_FLAGS})
    if start:
        writer.start()
    try:
        begin = 0
        for end in ends:
            for row in rows[begin:end]:
                writer.push(row)
            deadline = time.monotonic() + 60.0
            while start and writer.received + writer.dropped < end and time.monotonic() < deadline:
                time.sleep(0.002)
            begin = end
    finally:
        writer.close()
    assert writer.dropped == 0, "the test pushes no more than the ring holds between drains"
    header, kept = read_telemetry(path)
    assert writer.written == len(kept) and writer.received == len(rows)
    return header, np.rint(kept[:, 0] * RATE_HZ).astype(int)


def _events(rows: np.ndarray, columns: list[str]) -> np.ndarray:
    """Indices where one of ``columns`` differs from the sample before (the definition)."""
    idx = [COLUMNS.index(c) for c in columns]
    return 1 + np.flatnonzero(np.any(rows[1:, idx] != rows[:-1, idx], axis=1))


def test_a_decimated_recording_keeps_every_kth_sample_and_every_event(tmp_path):
    rows = _rows(1000, [(123, "state", State.FAULT), (123, "fault", Fault.STALE_INPUT), (457, "flags", 32),
                        (458, "flags", 0), (601, "state", State.ARMED), (602, "fault", Fault.NONE)])
    header, kept = _record(tmp_path / "d.btl", rows, Recording("decimated", decimation=10),
                           chunk_ends=(100, 124, 300, 457, 600, 850))
    assert header["recording"] == {"mode": "decimated", "decimation": 10}
    expected = sorted(set(range(0, 1000, 10)) | {123, 457, 458, 601, 602})
    assert kept.tolist() == expected, f"kept {sorted(set(kept) ^ set(expected))} differ from the definition"


def test_decimation_does_not_depend_on_how_the_writer_is_handed_the_samples(tmp_path):
    rng = np.random.default_rng(3)
    rows = _rows(3000)
    rows[:, 3] = rng.choice([0, 0, 0, 0, 1, 32], size=3000)         # flags: events everywhere
    expected = sorted(set(range(0, 3000, 7)) | set(_events(rows, ["state", "fault", "flags"]).tolist()))
    parts = (1, 2, 255, 256, 700, 1111, 1400, 1650, 1900, 2100, 2300, 2555, 2800)
    for i, chunk_ends in enumerate([(), parts]):
        _, kept = _record(tmp_path / f"d{i}.btl", rows, Recording("decimated", decimation=7),
                          chunk_ends=chunk_ends, start=bool(chunk_ends))
        assert kept.tolist() == expected


def test_a_trigger_keeps_exactly_its_pre_and_post_trigger_window(tmp_path):
    """pre_trigger_s 0.1 s and post_trigger_s 0.2 s at 1000 Hz: the 100 samples before the fault,
    the fault's sample and the 200 after it, nothing else."""
    rows = _rows(2000, [(1000, "state", State.FAULT)])
    recording = Recording("triggered", pre_trigger_s=0.1, post_trigger_s=0.2)
    header, kept = _record(tmp_path / "t.btl", rows, recording, chunk_ends=(250, 500, 750, 950, 1001, 1150))
    windows = header["recording"]
    assert (windows["pre_trigger_samples"], windows["post_trigger_samples"]) == (100, 200)
    assert kept.tolist() == list(range(900, 1201))


def test_a_saturation_triggers_and_keeps_the_window_open_while_it_lasts(tmp_path):
    rows = _rows(3000, [(1000, "flags", 1), (1400, "flags", 0), (2500, "flags", 4)])  # 4: held integrator
    recording = Recording("triggered", pre_trigger_s=0.05, post_trigger_s=0.1)
    _, kept = _record(tmp_path / "t.btl", rows, recording, chunk_ends=(200, 999, 1200, 1399, 1700))
    assert kept.tolist() == list(range(950, 1400 + 100)), \
        "saturated samples 1000..1399 trigger; the held-integrator flag alone does not"


def test_triggered_windows_match_the_definition_however_the_samples_arrive(tmp_path):
    rng = np.random.default_rng(5)
    n, pre, post = 4000, 30, 45
    rows = _rows(n)
    for i in rng.choice(n, size=25, replace=False):
        rows[i:, rng.choice([1, 2])] = rng.integers(0, 6)
    rows[:, 3] = np.where(rng.random(n) < 0.004, 2.0, 0.0)        # saturated support B, now and then
    triggers = set(_events(rows, ["state", "fault"]).tolist()) | set(np.flatnonzero(rows[:, 3]).tolist())
    expected = sorted({j for t in triggers for j in range(max(0, t - pre), min(n, t + post + 1))})
    for i, chunk_ends in enumerate([(), (10, 29, 31, 256, 500, 700, 900, 1100, 1300, 1500, 1700, 1900, 2100,
                                         2300, 2500, 2700, 2900, 3100, 3300, 3500, 3700, 3900)]):
        _, kept = _record(tmp_path / f"t{i}.btl", rows,
                          Recording("triggered", pre_trigger_s=pre / RATE_HZ, post_trigger_s=post / RATE_HZ),
                          chunk_ends=chunk_ends, start=bool(chunk_ends))
        assert kept.tolist() == expected


def test_nothing_recorded_before_the_history_fills_is_lost_at_close(tmp_path):
    """A trigger 30 samples into a recording with 100 samples of pre-trigger history keeps the 30
    before it; one at the very last sample, pushed just before close(), keeps its 100."""
    rows = _rows(500, [(30, "state", State.FAULT), (499, "state", State.STOPPED)])
    recording = Recording("triggered", pre_trigger_s=0.1, post_trigger_s=0.05)
    _, kept = _record(tmp_path / "t.btl", rows, recording, start=False)
    assert kept.tolist() == list(range(0, 81)) + list(range(399, 500))


def test_a_controllers_triggered_recording_keeps_the_fault_with_its_windows(tmp_path):
    """A strain beyond the limit at sample 1200 faults the paper's controller (2500 Hz): with
    pre_trigger_s 0.2 s and post_trigger_s 0.4 s the file holds the 500 samples before the fault
    and the 1000 after it, time stamps exact."""
    def beam(sequence):
        (strains, load) = oscillating(sequence)
        return ((1.0, 0.0, 0.0, 0.0), load) if sequence == 1201 else (strains, load)

    table, writer = _paper_loop(tmp_path, {"mode": "triggered", "pre_trigger_s": 0.2, "post_trigger_s": 0.4},
                                beam=beam, cycles=3000)
    header, rows = read_telemetry(writer.path)
    col = {name: i for i, name in enumerate(header["columns"])}
    fault_at = int(np.flatnonzero(rows[:, col["state"]] == State.FAULT)[0])
    assert rows[fault_at, col["fault"]] == Fault.STRAIN_OUT_OF_RANGE
    assert fault_at == 500 and len(rows) == 500 + 1 + 1000, (fault_at, len(rows))
    np.testing.assert_allclose(np.diff(rows[:, col["time_s"]]), 1 / 2500.0, rtol=1e-9,
                               err_msg="the kept samples are consecutive: one period apart")
    assert writer.received > len(rows)


@pytest.mark.parametrize("settings, key", [
    ({"mode": "sometimes"}, "controller.telemetry.mode"),
    ({"decimation": 0}, "controller.telemetry.decimation"),
    ({"decimation": 2.5}, "controller.telemetry.decimation"),
    ({"pre_trigger_s": 120.0}, "controller.telemetry.pre_trigger_s"),
    ({"post_trigger_s": -1.0}, "controller.telemetry.post_trigger_s"),
])
def test_recording_settings_are_checked(settings, key):
    with pytest.raises(ConfigError) as err:
        controller_config({"telemetry": settings}, "lab.yaml", "controller.")
    assert err.value.key == key and "\n" not in str(err.value)


def test_recording_settings_reach_the_writer():
    cfg = controller_config({"telemetry": {"mode": "triggered", "pre_trigger_s": 0.5, "post_trigger_s": 3}})
    assert cfg.telemetry.recording == Recording("triggered", decimation=10, pre_trigger_s=0.5,
                                                post_trigger_s=3.0)


def test_a_controller_s_recording_names_its_model_and_settings_under_the_caller_s_meta(tmp_path):
    """A reader turns q into millimetres with the model's mode shapes and draws the voltage
    limits the controller had: the header holds both, and what the caller adds."""
    from beamctl.gains.defaults import paper_table_path
    from beamctl.gains.table import load_table
    from beamctl.rt.config import controller_config
    from beamctl.rt.controller import Controller

    table = load_table(paper_table_path())
    controller = Controller(table, controller_config({"allocation": "clip",
                                                      "actuators": {"max_voltage_v": 140.0}}))
    with TelemetryWriter.for_controller(tmp_path / "run.btl", controller, meta={"mode": "paper"}):
        pass
    meta = read_telemetry(tmp_path / "run.btl")[0]["meta"]
    assert meta["mode"] == "paper" and meta["sample_rate_hz"] == 2500.0
    assert meta["controller"]["allocation"] == "clip"
    assert meta["controller"]["actuators.max_voltage_v"] == 140.0
    assert meta["model"] == table.model_parameters.to_dict(), "the gain table's model, whole"
    assert meta["design"]["kind"] == "integral-lqr"
