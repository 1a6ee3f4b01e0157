"""``beamctl log export`` to MDF4, HDF5, MATLAB v7.3 and v5 and CSV: each opened with the
library a lab would use (asammdf, h5py, scipy, hdf5storage for MATLAB's conventions), the values
equal to the recording's, with units, sample rate, the gain table's hash and the labels of the
state, fault and flag codes."""

import errno
import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import scipy.io
import yaml

from beamctl.gains.defaults import paper_table_path
from beamctl.gains.table import load_table
from beamctl.reports import recordings
from beamctl.rt.config import controller_config
from beamctl.rt.controller import FLAG_NAMES, Controller
from beamctl.rt.loop import ControlLoop
from beamctl.rt.safety import Fault, State
from beamctl.rt.telemetry import TelemetryWriter, read_telemetry
from beamctl.tools.cli import main
from tests.rt.fakes import ScriptedHal

asammdf = pytest.importorskip("asammdf", reason="the recordings extra: pip install -e '.[test]'")
h5py = pytest.importorskip("h5py", reason="the recordings extra: pip install -e '.[test]'")
hdf5storage = pytest.importorskip("hdf5storage", reason="the test extra: pip install -e '.[test]'")

FORMATS = ("mdf", "h5", "mat73", "mat", "csv")


def _beam(sequence: int):
    """A beam vibrating at 20 Hz; from sample 600 a static strain that saturates support A (and
    holds the integrator); at sample 1200 a strain beyond the limit: a fault, and the ramp to
    bias."""
    a = 3e-5 * np.sin(2 * np.pi * 20.0 * sequence / 2500.0)
    if 600 <= sequence < 1200:
        a += 5e-4
    if sequence == 1200:
        a = 1.0
    return (a, -a, 0.5 * a, 0.2 * a), 1500.0


def _run(path, telemetry: dict | None = None):
    table = load_table(paper_table_path())
    controller = Controller(table, controller_config({"pacing": "sample", "telemetry": telemetry or {}}))
    hal = ScriptedHal(table.design.sample_rate_hz, default=_beam).open()
    writer = TelemetryWriter.for_controller(path, controller, meta={"config": "test"}).start()
    ControlLoop(controller, hal, telemetry=writer, max_cycles=3000).run(acquire_rt=False)
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """The paper's controller (2500 Hz) running, saturating, faulting and ramping to bias."""
    path = _run(tmp_path_factory.mktemp("rec") / "run.btl")
    header, rows = read_telemetry(path)
    col = {name: i for i, name in enumerate(header["columns"])}
    needed = {"state": {State.RUNNING, State.FAULT}, "fault": {Fault.NONE, Fault.STRAIN_OUT_OF_RANGE},
              "flags": {0, 1, 1 | 4, 32, 64}}
    for column, codes in needed.items():
        assert set(np.unique(rows[:, col[column]]).astype(int)) == codes, \
            f"the scripted run no longer gives the {column} codes these tests need"
    return path


def _opened(fmt: str, out):
    """What an export holds, as its format's own reader gives it: (values, units, labels, bits,
    properties); values {column: array}, labels and bits {column: {value: label}}."""
    if fmt == "mdf":
        mdf = asammdf.MDF(out)
        try:
            master, *channels = mdf.groups[0].channels
            values, units, labels, bits = {"time_s": mdf.get_master(0)}, {"time_s": master.unit}, {}, {}
            for channel in channels:
                name = channel.name
                raw = mdf.get(name, raw=True)
                values[name], units[name] = raw.samples.astype(float), raw.unit
                conversion = raw.conversion
                if conversion is not None and conversion.conversion_type == 7:        # value to text
                    refs = conversion.referenced_blocks
                    labels[name] = {int(getattr(conversion, f"val_{i}")): refs[f"text_{i}"].decode()
                                    for i in range(conversion.val_param_nr)}
                elif conversion is not None and conversion.conversion_type == 11:     # bit-field text
                    refs = conversion.referenced_blocks
                    bits[name] = {int(getattr(conversion, f"mask_{i}")):
                                  refs[f"text_{i}"].referenced_blocks["text_0"].decode()
                                  for i in range(conversion.val_param_nr)}
            comment = ET.fromstring(mdf.header.comment)
            properties = {e.get("name"): e.text or "" for e in comment.iter("e")}
        finally:
            mdf.close()
        return values, units, labels, bits, properties
    if fmt == "h5":
        with h5py.File(out, "r") as f:
            columns = list(f.attrs["columns"])
            values = {c: f[c][:] for c in columns}
            units = {c: f[c].attrs["unit"] for c in columns}
            labels = {c: dict(zip(f[c].attrs["codes"].tolist(), f[c].attrs["labels"], strict=True))
                      for c in columns if "codes" in f[c].attrs}
            bits = {c: dict(zip(f[c].attrs["bits"].tolist(), f[c].attrs["labels"], strict=True))
                    for c in columns if "bits" in f[c].attrs}
            properties = {k: v for k, v in f.attrs.items() if k not in ("columns",)}
        return values, units, labels, bits, properties
    if fmt in ("mat73", "mat"):
        m = hdf5storage.loadmat(str(out)) if fmt == "mat73" else scipy.io.loadmat(out)
        columns = _texts(m["columns"])
        values = {c: m[c] for c in columns}
        units = {c: "".join(_texts(_field(m["units"], c))) for c in columns}
        labels, bits = {}, {}
        for c in _unwrap(m["labels"]).dtype.names:
            values_ = _field(m["labels"], c, "values").ravel().astype(int).tolist()
            table = dict(zip(values_, _texts(_field(m["labels"], c, "names")), strict=True))
            ({"codes": labels, "bits": bits})[_texts(_field(m["labels"], c, "kind"))[0]][c] = table
        properties = {"sample_rate_hz": float(m["sample_rate_hz"].ravel()[0]),
                      "gain_table_sha256": _texts(m["gain_table_sha256"])[0],
                      "recording_mode": _texts(_field(m["recording"], "mode"))[0]}
        return values, units, labels, bits, properties
    lines = out.read_text().splitlines()
    comments = dict(line[2:].split(": ", 1) for line in lines if line.startswith("# "))
    columns = lines[len(comments)].split(",")
    rows = [line.split(",") for line in lines[len(comments) + 1:]]
    table = np.array(rows, dtype=float).reshape(-1, len(columns))
    values = {c: table[:, i] for i, c in enumerate(columns)}
    labels, bits = _int_codes(comments["labels"]), _int_codes(comments["bits"])
    return values, json.loads(comments["units"]), labels, bits, comments


def _unwrap(value):
    """A MATLAB struct or cell as scipy (a 1 x 1 object array) or hdf5storage (a 1 x 1
    structured array) loads it: the one element."""
    while (isinstance(value, np.ndarray) and value.shape == (1, 1)
           and (value.dtype == object or value.dtype.names)):
        value = value[0, 0]
    return value


def _field(struct, *names):
    """``struct.a.b`` of a loaded MATLAB struct."""
    for name in names:
        struct = _unwrap(_unwrap(struct)[name])
    return struct


def _texts(value) -> list[str]:
    """The rows of a MATLAB char matrix as loaded (trailing padding removed)."""
    return [str(t).rstrip() for t in np.asarray(value).ravel()]


def _int_codes(text: str) -> dict[str, dict[int, str]]:
    return {c: {int(k): v for k, v in codes.items()} for c, codes in json.loads(text).items()}


@pytest.fixture(scope="module")
def exported(recording, tmp_path_factory):
    """Each format exported once through the command line: {format: (path, what it holds)}."""
    out_dir = tmp_path_factory.mktemp("exports")
    done = {}
    for fmt in FORMATS:
        out = out_dir / f"{fmt}-run{recordings.FORMATS[fmt]}"
        assert main(["log", "export", str(recording), "--to", fmt, "--out", str(out)]) == 0
        done[fmt] = (out, _opened(fmt, out))
    return done


@pytest.mark.parametrize("fmt", FORMATS)
def test_every_column_comes_back_with_the_recorded_values(recording, exported, fmt):
    """MDF4, HDF5 and MATLAB store the recording's IEEE doubles as they are (state, fault and
    flags in MDF4 as the integers they are): equal bit for bit. CSV writes 10 significant
    digits: equal within half a unit of the 10th digit, 5e-10 relative."""
    header, rows = read_telemetry(recording)
    values = exported[fmt][1][0]
    assert sorted(values) == sorted(header["columns"]), f"{fmt}: columns differ"
    for i, column in enumerate(header["columns"]):
        got = np.asarray(values[column], dtype=float).ravel()
        if fmt == "csv":
            np.testing.assert_allclose(got, rows[:, i], rtol=5e-10, atol=0, err_msg=f"{fmt}: {column}")
        else:
            np.testing.assert_array_equal(got, rows[:, i], err_msg=f"{fmt}: {column}")


@pytest.mark.parametrize("fmt", FORMATS)
def test_units_are_those_of_the_quantities(exported, fmt):
    units = exported[fmt][1][1]
    expected = {"time_s": "s", "load_N": "N", "load_filtered_N": "N", "force_y_A_N": "N", "voltage_b3_V": "V",
                "step_us": "us", "answer_age_us": "us", "strain_y1": "m/m", "q_1y": "m*sqrt(kg)",
                "xi_2z": "m*sqrt(kg)*s", "applied_force_z_B_N": "N", "state": "", "fault": "", "flags": ""}
    assert {c: units[c] for c in expected} == expected, f"{fmt}: units"


@pytest.mark.parametrize("fmt", FORMATS)
def test_state_fault_and_flag_labels_name_the_codes(exported, fmt):
    _, _, labels, bits, _ = exported[fmt][1]
    assert labels["state"] == {s.value: s.name for s in State}, f"{fmt}: state labels"
    assert labels["fault"] == {f.value: f.name for f in Fault}, f"{fmt}: fault labels"
    assert bits["flags"] == FLAG_NAMES, f"{fmt}: flag bits"


@pytest.fixture(scope="module")
def paper_table_sha256() -> str:
    """The hash the paper's table file records (read once: PyYAML takes a third of a second)."""
    return yaml.safe_load(paper_table_path().read_text())["sha256"]


@pytest.mark.parametrize("fmt", FORMATS)
def test_sample_rate_table_hash_and_mode_are_carried(exported, paper_table_sha256, fmt):
    properties = exported[fmt][1][4]
    assert float(properties["sample_rate_hz"]) == 2500.0, "the paper table's rate"
    assert properties["gain_table_sha256"] == paper_table_sha256
    assert properties["recording_mode"] == "full"


def test_mdf_channels_show_the_labels_of_their_codes(recording, exported):
    """asammdf applies the conversions: a state sample reads as its state's name, a flags sample
    as the names of its set bits."""
    _, rows = read_telemetry(recording)
    mdf = asammdf.MDF(exported["mdf"][0])
    try:
        state = mdf.get("state").samples
        flags = mdf.get("flags").samples
        fault = mdf.get("fault").samples
    finally:
        mdf.close()
    header = read_telemetry(recording)[0]
    col = {name: i for i, name in enumerate(header["columns"])}
    assert [s.decode() for s in state] == [State(int(v)).name for v in rows[:, col["state"]]]
    assert [s.decode() for s in fault] == [Fault(int(v)).name for v in rows[:, col["fault"]]]
    for text, value in zip(flags, rows[:, col["flags"]].astype(int), strict=True):
        assert sorted(t for t in text.decode().split("|") if t) == sorted(
            name for bit, name in FLAG_NAMES.items() if value & bit), f"flags {value}: {text}"


def test_mat73_is_an_hdf5_file_with_matlabs_header_and_classes(recording, exported):
    path = exported["mat73"][0]
    head = path.read_bytes()[:128]
    assert head.startswith(b"MATLAB 7.3 MAT-file"), head
    assert head[124:128] == b"\x00\x02IM", "version 0x0200 and the endian indicator, as MATLAB writes them"
    with h5py.File(path, "r") as f:
        assert f.userblock_size == 512
        assert f["q_1y"].shape == (1, 2449) and f["q_1y"].attrs["MATLAB_class"] == b"double", \
            "a column is an n x 1 double: HDF5 holds MATLAB's column-major dimensions reversed"
        assert f["units"].attrs["MATLAB_class"] == b"struct"
        fields = [b"".join(name).decode() for name in f["units"].attrs["MATLAB_fields"]]
        assert fields == read_telemetry(recording)[0]["columns"], "MATLAB_fields name the struct's fields"
        assert f["gain_table_sha256"].attrs["MATLAB_class"] == b"char"


def test_a_mat73_file_loads_as_matlab_would_give_it(exported):
    """hdf5storage reads MATLAB's conventions: columns n x 1, char matrices, nested structs."""
    m = hdf5storage.loadmat(str(exported["mat73"][0]))
    assert m["q_1y"].shape == (2449, 1)
    assert _texts(_field(m["labels"], "state", "names"))[:3] == ["INIT", "ARMED", "RUNNING"]
    assert json.loads(str(np.asarray(m["meta_json"]).ravel()[0]))["config"] == "test"


def test_mat_v5_columns_are_column_vectors(exported):
    m = scipy.io.loadmat(exported["mat"][0])
    assert m["voltage_a1_V"].shape == (2449, 1)


@pytest.mark.parametrize("fmt", FORMATS)
def test_exports_do_not_depend_on_the_chunk_size(recording, exported, tmp_path, fmt):
    """7 rows a chunk (it divides nothing here) gives what 2 MB a chunk gave."""
    out = tmp_path / f"small-chunks{recordings.FORMATS[fmt]}"
    assert recordings.export(recording, out, fmt, chunk_rows=7) == 2449
    values = _opened(fmt, out)[0]
    for column, expected in exported[fmt][1][0].items():
        np.testing.assert_array_equal(np.asarray(values[column]).ravel(), np.asarray(expected).ravel(),
                                      err_msg=f"{fmt}: {column}")


PEAK_GROWTH = """
import sys
import asammdf, h5py, scipy.io
from beamctl.reports import recordings

def status_kb(key):
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith(key + ":"))

fmt, out, chunk_rows, *sources = sys.argv[1:]
for source in sources:
    with open("/proc/self/clear_refs", "w") as f:      # the peak resident size starts again from here
        f.write("5")
    before_kb = status_kb("VmRSS")
    recordings.export(source, out, fmt, chunk_rows=int(chunk_rows))
    print((status_kb("VmHWM") - before_kb) * 1024)
"""


def peak_growth(fmt: str, sources: list, out, chunk_rows: int) -> list[int]:
    """By how much exporting each of ``sources`` in turn raises the resident memory of one
    process, at its peak, in bytes (Linux: /proc/self/clear_refs resets the peak). Memory an
    export freed may serve the next: an export measured later can only seem to need less."""
    command = [sys.executable, "-c", PEAK_GROWTH, fmt, str(out), str(chunk_rows), *map(str, sources)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    return [int(line) for line in result.stdout.split()]


def _synthetic(path, rows: int) -> int:
    """A recording of ``rows`` rows of 20 noisy columns at 1000 Hz; its size in bytes."""
    rng = np.random.default_rng(1)
    with TelemetryWriter(path, [f"c{i}" for i in range(20)], capacity=rows, sample_rate_hz=1000.0) as writer:
        for i, row in enumerate(rng.normal(size=(rows, 20))):
            row[0] = i / 1000.0
            writer.push(row)
    return path.stat().st_size


@pytest.fixture(scope="module")
def small_and_big(tmp_path_factory):
    """Recordings of 4 MB and 16 MB."""
    directory = tmp_path_factory.mktemp("sizes")
    return [(directory / f"{name}.btl", _synthetic(directory / f"{name}.btl", rows))
            for name, rows in (("small", 25_000), ("big", 100_000))]


@pytest.mark.skipif(not os.access("/proc/self/clear_refs", os.W_OK), reason="needs Linux's peak-RSS reset")
@pytest.mark.parametrize("fmt", ("mdf", "h5", "mat73", "csv"))
def test_an_export_streams_the_recording(small_and_big, tmp_path, fmt):
    """Read 5000 rows (800 kB) at a time, a 16 MB recording needs less than half of the 12 MB
    more memory than a 4 MB one: what an export holds does not grow with the recording.
    (MATLAB v5 holds whole columns, up to 64 MB of them at a time.)"""
    (small, small_bytes), (big, big_bytes) = small_and_big
    # the large one first: the small one may reuse what it freed and seem to need less still
    big_peak, small_peak = peak_growth(fmt, [big, small], tmp_path / f"out{recordings.FORMATS[fmt]}", 5000)
    assert big_peak - small_peak < 0.5 * (big_bytes - small_bytes), \
        (f"{fmt}: {small_peak / 1e6:.1f} MB at peak for a {small_bytes / 1e6:.0f} MB recording, "
         f"{big_peak / 1e6:.1f} MB for {big_bytes / 1e6:.0f} MB")


def test_exports_of_a_triggered_recording_keep_the_time_of_each_sample(tmp_path):
    settings = {"mode": "triggered", "pre_trigger_s": 0.1, "post_trigger_s": 0.1}
    path = _run(tmp_path / "triggered.btl", settings)
    header, rows = read_telemetry(path)
    assert 0 < len(rows) < 2449
    out = tmp_path / "triggered.mf4"
    assert main(["log", "export", str(path), "--to", "mdf", "--out", str(out)]) == 0
    values, _, _, _, properties = _opened("mdf", out)
    assert properties["recording_mode"] == "triggered" and properties["pre_trigger_samples"] == "250"
    np.testing.assert_array_equal(values["time_s"], rows[:, header["columns"].index("time_s")])


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_recording_without_samples_exports_its_description(tmp_path, fmt):
    """A run refused at its first sample leaves a header alone: every format writes no rows and
    still the units, labels and sample rate."""
    source = tmp_path / "empty.btl"
    table = load_table(paper_table_path())
    TelemetryWriter.for_controller(source, Controller(table, controller_config({}))).close()
    out = tmp_path / f"empty{recordings.FORMATS[fmt]}"
    assert recordings.export(source, out, fmt) == 0
    values, units, labels, _, properties = _opened(fmt, out)
    assert all(np.asarray(v).size == 0 for v in values.values()), f"{fmt}: rows in an empty recording"
    assert units["voltage_a1_V"] == "V" and labels["fault"][int(Fault.STALE_INPUT)] == "STALE_INPUT"
    assert float(properties["sample_rate_hz"]) == 2500.0


def test_the_default_output_is_the_recording_with_the_formats_suffix(recording, tmp_path):
    source = tmp_path / "run.btl"
    source.write_bytes(recording.read_bytes())
    assert main(["log", "export", str(source), "--to", "mdf"]) == 0
    assert main(["log", "export", str(source), "--to", "h5"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.btl", "run.h5", "run.mf4"]


# -- refusals ---------------------------------------------------------------------------------------

def _one_line(err: str, *words: str) -> None:
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for word in words:
        assert word in err, err


def test_an_unknown_format_is_refused_in_one_line(recording, tmp_path, capsys):
    out = tmp_path / "run.xlsx"
    assert main(["log", "export", str(recording), "--to", "xlsx", "--out", str(out)]) == 2
    _one_line(capsys.readouterr().err, "--to", "xlsx", "mdf")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("damage", ["missing", "not telemetry", "header cut off"])
@pytest.mark.parametrize("fmt", ("mdf", "mat73"))
def test_an_unreadable_recording_is_refused_and_leaves_no_output(recording, tmp_path, capsys, damage, fmt):
    source = tmp_path / "run.btl"
    if damage == "not telemetry":
        source.write_text("time,load\n0,0\n")
    elif damage == "header cut off":
        source.write_bytes(recording.read_bytes()[:200])
    out = tmp_path / "out.file"
    assert main(["log", "export", str(source), "--to", fmt, "--out", str(out)]) == 2
    _one_line(capsys.readouterr().err, str(source))
    assert sorted(p.name for p in tmp_path.iterdir()) == ([] if damage == "missing" else ["run.btl"])


def test_an_output_path_that_cannot_be_written_is_refused(recording, tmp_path, capsys):
    (tmp_path / "a-file").write_text("")
    out = tmp_path / "a-file" / "run.mf4"
    assert main(["log", "export", str(recording), "--to", "mdf", "--out", str(out)]) == 2
    _one_line(capsys.readouterr().err, "--out", "not a directory")


def test_a_disk_that_fills_up_mid_export_leaves_no_partial_file(recording, tmp_path, capsys, monkeypatch):
    def full(reader, description, out, chunk_rows):
        out.write_bytes(b"half a file")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setitem(recordings.WRITERS, "h5", full)
    out = tmp_path / "run.h5"
    assert main(["log", "export", str(recording), "--to", "h5", "--out", str(out)]) == 2
    _one_line(capsys.readouterr().err, "--out", "no space left on device")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("fmt, package", [("mdf", "asammdf"), ("h5", "h5py"), ("mat73", "h5py")])
def test_a_missing_package_names_the_extra_to_install(recording, tmp_path, capsys, monkeypatch, fmt, package):
    monkeypatch.setitem(sys.modules, package, None)       # import fails as if not installed
    assert main(["log", "export", str(recording), "--to", fmt, "--out", str(tmp_path / "out")]) == 2
    _one_line(capsys.readouterr().err, package, "pip install 'beamctl[recordings]'")
    assert list(tmp_path.iterdir()) == []
