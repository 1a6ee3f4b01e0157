"""Files of measured frequency responses: .npz and .mat written and read back, .mat files made
in MATLAB and CSV files from other tools read, and every malformed file refused in one line
that names the file and the field."""

import math
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from beamctl.config.schema import ConfigError
from beamctl.identification.frf_files import read_frf, write_frf
from beamctl.models.measured import INPUTS, OUTPUTS, FrfData, nan_matrix

NF = 6
# the y bending plane measured (inputs yA and yB excited), the z plane not
MEASURED = ((0, 0), (0, 2), (2, 0), (2, 2))


def measurement(**fields) -> FrfData:
    """A y-plane measurement at 2000 N: six frequencies, four measured entries."""
    f = np.linspace(20.0, 145.0, NF)
    frf, coherence = nan_matrix(NF)
    rng = np.random.default_rng(7)
    for out, inp in MEASURED:
        frf[:, out, inp] = (rng.normal(size=NF) + 1j * rng.normal(size=NF)) * 1e-7
        coherence[:, out, inp] = rng.uniform(0.5, 1.0, size=NF)
    base = dict(frequencies_hz=f, frf=frf, coherence=coherence, load_n=2000.0)
    return FrfData(**{**base, **fields})


FULL = dict(sample_rate_hz=6000.0, force_constant_n_per_v=3.0,
            io={"delay_samples": 1.0, "anti_alias": {"type": "butterworth", "order": 2, "cutoff_hz": 1250.0}},
            settings={"signal": "chirp", "band_hz": [20, 145], "averages": 8, "rig": {"name": "A"}})


def hand_written(path, **variables):
    """A file holding just ``variables`` (None: left out), as another program would write it;
    by default the three required ones of a valid measurement."""
    data = measurement()
    base = {"frequencies_hz": data.frequencies_hz, "frf": data.frf, "load_n": 2000.0}
    values = {k: v for k, v in {**base, **variables}.items() if v is not None}
    if path.suffix == ".npz":
        np.savez(path, **values)
    else:
        scipy.io.savemat(path, values, oned_as="column")
    return path


def csv_text(data: FrfData, pairs=MEASURED, coherence=True, comments=None) -> str:
    """``data`` as the documented CSV, numbers in full precision."""
    lines = [f"# {k}: {v!r}" for k, v in (comments or {"load_n": data.load_n}).items()]
    header = ["frequency_hz"]
    for out, inp in pairs:
        name = f"{OUTPUTS[out]}_{INPUTS[inp]}"
        header += [f"re_{name}", f"im_{name}"] + ([f"coh_{name}"] if coherence else [])
    lines.append(",".join(header))
    for k, f in enumerate(data.frequencies_hz):
        cells = [repr(float(f))]
        for out, inp in pairs:
            h = data.frf[k, out, inp]
            cells += [repr(float(h.real)), repr(float(h.imag))]
            cells += [repr(float(data.coherence[k, out, inp]))] if coherence else []
        lines.append(",".join(cells))
    return "\n".join(lines) + "\n"


def refusal(path) -> ConfigError:
    """The ConfigError read_frf raises for ``path``; checked to be one line naming the file."""
    with pytest.raises(ConfigError) as info:
        read_frf(path)
    error = info.value
    assert error.source == str(path), f"the refusal must name the file {path}, not {error.source!r}"
    assert str(error).startswith(f"{path}: "), f"the message must start with the file: {error}"
    assert "\n" not in str(error), f"the refusal must be one line: {error!r}"
    return error


def assert_same(read: FrfData, written: FrfData, exact: bool) -> None:
    """Every field of ``read`` equals ``written`` (exactly, or to float precision)."""
    compare = np.testing.assert_array_equal if exact else (
        lambda a, b, err_msg: np.testing.assert_allclose(a, b, rtol=1e-15, atol=0, err_msg=err_msg))
    compare(read.frequencies_hz, written.frequencies_hz, err_msg="frequencies_hz changed on the way")
    compare(read.frf, written.frf, err_msg="frf changed on the way (NaN must stay NaN where not measured)")
    compare(read.coherence, written.coherence, err_msg="coherence changed on the way")
    for name in ("load_n", "sample_rate_hz", "force_constant_n_per_v", "io", "settings"):
        assert getattr(read, name) == getattr(written, name), f"{name} changed on the way"


# --- round trips -----------------------------------------------------------------------------------


@pytest.mark.parametrize("fields", [FULL, {}], ids=["every-field", "unknowns-left-none"])
def test_npz_reads_back_exactly(tmp_path, fields):
    data = measurement(**fields)
    npz, mat = write_frf(data, tmp_path / "frf.npz")
    assert (npz.name, mat.name) == ("frf.npz", "frf.mat"), "write_frf writes <stem>.npz and <stem>.mat"
    read = read_frf(npz)
    assert_same(read, data, exact=True)
    assert read.source == str(npz), "the measurement names the file it came from"


@pytest.mark.parametrize("fields", [FULL, {}], ids=["every-field", "unknowns-left-none"])
def test_mat_reads_back_to_float_precision(tmp_path, fields):
    data = measurement(**fields)
    _, mat = write_frf(data, tmp_path / "frf.mat")
    assert_same(read_frf(mat), data, exact=False)


def test_the_npz_file_needs_no_pickle(tmp_path):
    npz, _ = write_frf(measurement(**FULL), tmp_path / "frf")
    with np.load(npz, allow_pickle=False) as archive:
        names = {name: archive[name] for name in archive.files}
    assert str(names["format"]) == "beamctl-frf" and int(names["format_version"]) == 1
    assert tuple(names["outputs"]) == OUTPUTS and tuple(names["inputs"]) == INPUTS
    assert math.isclose(float(names["sample_rate_hz"]), 6000.0)


def test_matlab_sees_frf_as_nf_by_4_by_4_complex(tmp_path):
    _, mat = write_frf(measurement(), tmp_path / "frf")
    variables = scipy.io.loadmat(mat)
    assert variables["frf"].shape == (NF, 4, 4) and np.iscomplexobj(variables["frf"]), (
        "a MATLAB user must get frf(f, output, input), as tfestimate(..., 'mimo') gives it")
    assert variables["frequencies_hz"].shape == (NF, 1), "vectors are columns in MATLAB"
    assert np.isnan(variables["sample_rate_hz"]).all(), "an unknown sample rate is NaN in the file"
    assert str(variables["settings_json"][0]) == "{}" and str(variables["io_json"][0]) == "null"


@pytest.mark.parametrize("name", ["frf", "frf.npz", "frf.mat", "frf.NPZ"])
def test_both_files_are_written_whatever_suffix_is_given(tmp_path, name):
    paths = write_frf(measurement(), tmp_path / name)
    assert paths == [tmp_path / "frf.npz", tmp_path / "frf.mat"]
    assert all(p.is_file() for p in paths), "both files must be there"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frf.mat", "frf.npz"], "no temporary file is left"


def test_a_csv_reads_back_to_float_precision(tmp_path):
    data = measurement(sample_rate_hz=6000.0, force_constant_n_per_v=3.0)
    path = tmp_path / "frf.csv"
    path.write_text(csv_text(data, comments={"load_n": 2000.0, "sample_rate_hz": 6000.0,
                                             "force_constant_n_per_v": 3.0}))
    assert_same(read_frf(path), data, exact=False)


def test_a_csv_with_two_pairs_and_no_coherence(tmp_path):
    data = measurement()
    path = tmp_path / "two.CSV"
    path.write_text("# exported from the analyser\n"
                    + csv_text(data, pairs=((0, 0), (2, 2)), coherence=False))
    read = read_frf(path)
    expected = np.zeros((4, 4), bool)
    expected[0, 0] = expected[2, 2] = True
    np.testing.assert_array_equal(read.measured, expected, err_msg="only y1/yA and y2/yB were in the file")
    np.testing.assert_allclose(read.frf[:, 0, 0], data.frf[:, 0, 0], rtol=1e-15)
    assert (read.coherence[:, [0, 2], [0, 2]] == 1).all(), "a pair without coh_ columns is fully coherent"
    assert np.isnan(read.coherence[:, 0, 2]).all(), "a pair not in the file is NaN (not measured)"
    assert read.sample_rate_hz is None and read.force_constant_n_per_v is None and read.settings == {}


@pytest.mark.parametrize("load_n", [np.array([[2000.0]]), 2000.0, np.array([2000.0])],
                         ids=["matlab-1x1", "plain-scalar", "1-element"])
@pytest.mark.parametrize("suffix", [".mat", ".npz"])
def test_a_file_with_only_the_three_required_variables(tmp_path, suffix, load_n):
    data = measurement()
    path = hand_written(tmp_path / f"by-hand{suffix}", frequencies_hz=data.frequencies_hz[None, :],
                        load_n=load_n)
    read = read_frf(path)
    np.testing.assert_array_equal(read.frf, data.frf, err_msg="frf must read as written")
    np.testing.assert_array_equal(read.frequencies_hz, data.frequencies_hz,
                                  err_msg="a row vector of frequencies is a vector")
    assert read.load_n == 2000.0
    assert (read.coherence[:, read.measured] == 1).all(), "without coherence: taken as fully coherent"
    assert np.isnan(read.coherence[:, ~read.measured]).all(), "coherence stays NaN where not measured"
    unknowns = (read.sample_rate_hz, read.force_constant_n_per_v, read.io, read.settings)
    assert unknowns == (None, None, None, {}), "what the file does not give is unknown"


def test_nan_for_unknown_sample_rate_and_force_constant_is_none(tmp_path):
    path = hand_written(tmp_path / "m.mat", sample_rate_hz=math.nan, force_constant_n_per_v=np.zeros((0, 0)))
    read = read_frf(path)
    assert read.sample_rate_hz is None, "NaN means unknown"
    assert read.force_constant_n_per_v is None, "an empty MATLAB array ([]) means unknown"


def test_one_frequency_keeps_its_shape_through_matlab(tmp_path):
    data = measurement()
    path = hand_written(tmp_path / "one.mat", frequencies_hz=data.frequencies_hz[:1], frf=data.frf[:1])
    assert read_frf(path).frf.shape == (1, 4, 4)


def test_coherence_a_rounding_error_above_one_is_accepted_as_one(tmp_path):
    data = measurement()
    coherence = data.coherence.copy()
    coherence[:, 0, 0] = 1 + 2e-16
    read = read_frf(hand_written(tmp_path / "m.npz", coherence=coherence))
    assert (read.coherence[:, 0, 0] == 1.0).all(), "1 + 2e-16 is 1 computed in floating point"


# --- refusals --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["frf.txt", "frf.json", "frf"])
def test_a_file_of_another_suffix_is_refused(tmp_path, name):
    error = refusal(tmp_path / name)
    assert ".npz, .mat or .csv" in error.expected, f"the refusal must list the formats: {error}"


def test_writing_to_another_suffix_is_refused(tmp_path):
    with pytest.raises(ConfigError) as info:
        write_frf(measurement(), tmp_path / "frf.csv")
    assert info.value.key == "--out" and "both are written" in info.value.expected, str(info.value)
    assert list(tmp_path.iterdir()) == [], "nothing is written"


def test_writing_data_the_reader_would_refuse_is_refused(tmp_path):
    data = measurement()
    with pytest.raises(ConfigError) as info:
        write_frf(FrfData(data.frequencies_hz, data.frf[:, :, :2], data.coherence, 2000.0, source="sweep 3"),
                  tmp_path / "frf")
    assert info.value.key == "frf" and "sweep 3" in info.value.source, str(info.value)
    assert list(tmp_path.iterdir()) == [], "nothing is written"


@pytest.mark.parametrize("suffix", [".npz", ".mat", ".csv"])
def test_a_missing_file_is_refused(tmp_path, suffix):
    assert "no such file" in str(refusal(tmp_path / f"absent{suffix}"))


def test_a_directory_is_refused(tmp_path):
    (tmp_path / "d.npz").mkdir()
    assert "is a directory" in str(refusal(tmp_path / "d.npz"))


@pytest.mark.parametrize("suffix", [".npz", ".mat"])
@pytest.mark.parametrize("content", [b"", b"not a measurement at all\n" * 20], ids=["empty", "text"])
def test_a_file_that_is_not_the_format_is_refused(tmp_path, suffix, content):
    path = tmp_path / f"junk{suffix}"
    path.write_bytes(content)
    error = refusal(path)
    assert ("NumPy .npz" if suffix == ".npz" else "MATLAB .mat") in error.expected, str(error)


@pytest.mark.parametrize("suffix", [".npz", ".mat"])
def test_a_truncated_file_is_refused(tmp_path, suffix):
    written = write_frf(measurement(**FULL), tmp_path / "whole")[0 if suffix == ".npz" else 1]
    path = tmp_path / f"cut{suffix}"
    path.write_bytes(written.read_bytes()[: written.stat().st_size // 2])
    refusal(path)


def test_a_matlab_v73_file_is_refused_with_how_to_save_it(tmp_path):
    _, mat = write_frf(measurement(), tmp_path / "frf")
    raw = bytearray(mat.read_bytes())
    raw[124:126] = b"\x00\x02"          # the header's version field of an HDF5-based v7.3 file
    mat.write_bytes(bytes(raw))
    error = refusal(mat)
    assert "v7.3" in str(error.value) and "-v7" in error.expected, str(error)


@pytest.mark.parametrize("content", ["", "\n\n", "# load_n: 2000\n# only comments\n"],
                         ids=["empty", "blank", "comments-only"])
def test_a_csv_without_a_header_row_is_refused(tmp_path, content):
    path = tmp_path / "empty.csv"
    path.write_text(content)
    assert "header row" in refusal(path).expected


def test_a_csv_that_is_not_text_is_refused(tmp_path):
    path = tmp_path / "binary.csv"
    path.write_bytes(b"frequency_hz,re_y1_yA,im_y1_yA\n\xff\xfe\x00")
    assert "UTF-8" in refusal(path).expected


@pytest.mark.parametrize("suffix", [".npz", ".mat"])
@pytest.mark.parametrize("name", ["frequencies_hz", "frf", "load_n"])
def test_a_missing_required_variable_is_refused(tmp_path, suffix, name):
    error = refusal(hand_written(tmp_path / f"m{suffix}", **{name: None}))
    assert error.key == name and str(error.value) == "missing", str(error)


def test_a_csv_without_load_is_refused(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text(csv_text(measurement(), comments={"sample_rate_hz": 6000.0}))
    assert refusal(path).key == "load_n"


def _frequencies(*changes):
    f = measurement().frequencies_hz.copy()
    for index, value in changes:
        f[index] = value
    return f


@pytest.mark.parametrize(("frequencies", "key", "expected"), [
    (np.ones((NF, 2)), "frequencies_hz", "a vector"),
    (_frequencies((2, math.nan)), "frequencies_hz[2]", "finite"),
    (_frequencies((0, 0.0)), "frequencies_hz[0]", "> 0 Hz"),
    (_frequencies((0, -20.0)), "frequencies_hz[0]", "> 0 Hz"),
    (_frequencies((3, 45.0)), "frequencies_hz[3]", "strictly increasing"),
    (_frequencies((3, 120.0)), "frequencies_hz[4]", "strictly increasing"),
], ids=["2-d", "nan", "zero", "negative", "falling", "repeated"])
def test_bad_frequencies_are_refused(tmp_path, frequencies, key, expected):
    error = refusal(hand_written(tmp_path / "m.npz", frequencies_hz=frequencies))
    assert error.key == key and expected in error.expected, str(error)


def test_frf_of_another_shape_is_refused(tmp_path):
    error = refusal(hand_written(tmp_path / "m.npz", frf=measurement().frf[:, :, :2]))
    assert error.key == "frf" and str(error.value) == f"shape ({NF}, 4, 2)", str(error)
    assert f"({NF}, 4, 4)" in error.expected


def test_a_transposed_frf_is_refused_with_the_layout_expected(tmp_path):
    error = refusal(hand_written(tmp_path / "m.mat", frf=np.transpose(measurement().frf, (1, 2, 0))))
    assert str(error.value) == f"shape (4, 4, {NF})", str(error)
    assert "frequency x output" in error.expected and "permute(frf, [3 1 2])" in error.expected, (
        f"the refusal must say which layout is expected and how to get it: {error}")


def test_a_non_finite_value_inside_a_measured_entry_is_refused(tmp_path):
    frf = measurement().frf.copy()
    frf[4, 2, 0] = complex(math.nan, 1.0)
    error = refusal(hand_written(tmp_path / "m.npz", frf=frf))
    assert str(error).split(": ")[1] == "frf[4, 2, 0] = nan+1j", str(error)
    assert "output y2, input yA" in error.expected, f"the refusal must name the channels: {error}"


def test_a_file_without_a_measured_entry_is_refused(tmp_path):
    error = refusal(hand_written(tmp_path / "m.mat", frf=nan_matrix(NF)[0]))
    assert error.key == "frf" and "at least one measured entry" in error.expected, str(error)


@pytest.mark.parametrize(("value", "expected_value"), [(1.2, 1.2), (-0.1, -0.1), (math.nan, math.nan)])
def test_coherence_outside_zero_to_one_where_measured_is_refused(tmp_path, value, expected_value):
    coherence = measurement().coherence.copy()
    coherence[3, 0, 2] = value
    error = refusal(hand_written(tmp_path / "m.npz", coherence=coherence))
    assert error.key == "coherence[3, 0, 2]" and "from 0 to 1" in error.expected, str(error)
    assert repr(error.value) == repr(expected_value)


def test_coherence_of_another_shape_is_refused(tmp_path):
    error = refusal(hand_written(tmp_path / "m.mat", coherence=np.ones((NF, 4))))
    assert error.key == "coherence" and "(6, 4, 4)" in error.expected, str(error)


@pytest.mark.parametrize("load_n", [math.nan, math.inf, -5.0])
def test_a_load_that_is_not_finite_or_negative_is_refused(tmp_path, load_n):
    error = refusal(hand_written(tmp_path / "m.mat", load_n=load_n))
    assert error.key == "load_n" and ">= 0" in error.expected, str(error)


def test_a_load_given_as_text_is_refused(tmp_path):
    error = refusal(hand_written(tmp_path / "m.mat", load_n="2000"))
    assert error.key == "load_n" and str(error.value) == "text '2000'", str(error)


@pytest.mark.parametrize("name", ["sample_rate_hz", "force_constant_n_per_v"])
@pytest.mark.parametrize("value", [0.0, -6000.0, math.inf])
def test_a_rate_or_force_constant_not_above_zero_is_refused(tmp_path, name, value):
    error = refusal(hand_written(tmp_path / "m.npz", **{name: value}))
    assert error.key == name and "> 0" in error.expected, str(error)


def test_a_csv_value_not_above_zero_is_refused(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text(csv_text(measurement(), comments={"load_n": 2000.0, "sample_rate_hz": -1.0}))
    assert refusal(path).key == "sample_rate_hz"


def test_a_csv_comment_value_that_is_not_a_number_is_refused(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("# load_n: 2 kN\n" + csv_text(measurement(), comments={}))
    error = refusal(path)
    assert error.key == "load_n" and error.value == "2 kN", str(error)


def test_a_csv_comment_value_given_twice_is_refused(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("# load_n: 2000\n" + csv_text(measurement(), comments={"load_n": 2500.0}))
    error = refusal(path)
    assert error.key == "load_n" and "line 1 and line 2" in error.expected, str(error)


def test_settings_that_are_not_json_are_not_written(tmp_path):
    with pytest.raises(ConfigError) as info:
        write_frf(measurement(settings={"band_hz": (20, math.inf)}), tmp_path / "frf")
    assert info.value.key == "settings" and "JSON-ready" in info.value.expected, str(info.value)
    assert list(tmp_path.iterdir()) == [], "nothing is written"


def test_an_unknown_csv_column_is_refused_with_what_names_look_like(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text(csv_text(measurement()).replace("im_y2_yA", "im_y2_ya"))
    error = refusal(path)
    assert error.value == "im_y2_ya" and error.key.startswith("header column"), str(error)
    assert "re_<out>_<in>" in error.expected and "y1, z1, y2, z2" in error.expected, str(error)


def test_a_csv_whose_first_column_is_not_frequency_is_refused(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text(csv_text(measurement()).replace("frequency_hz", "f_hz"))
    error = refusal(path)
    assert error.key == "header column 1" and "frequency_hz" in error.expected, str(error)


def test_a_csv_column_given_twice_is_refused(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text(csv_text(measurement()).replace("coh_y1_yB", "coh_y1_yA"))
    assert "each column once" in refusal(path).expected


def test_a_csv_pair_with_re_but_no_im_is_refused(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("# load_n: 2000\nfrequency_hz,re_y1_yA,re_z1_zA,im_z1_zA\n10,1e-7,2e-7,0\n")
    error = refusal(path)
    assert error.key == "im_y1_yA" and "re_y1_yA and im_y1_yA" in error.expected, str(error)


def test_a_non_numeric_csv_cell_is_refused_with_its_line_and_column(tmp_path):
    path = tmp_path / "m.csv"
    lines = csv_text(measurement()).splitlines()
    cells = lines[4].split(",")
    cells[5] = "1.2e-7i"
    lines[4] = ",".join(cells)
    path.write_text("\n".join(lines))
    error = refusal(path)
    assert error.key == "line 5, column im_y1_yB" and error.value == "1.2e-7i", str(error)


def test_a_csv_row_of_another_length_is_refused(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text(csv_text(measurement()) + "200.0,1e-7\n")
    error = refusal(path)
    assert error.key == f"line {NF + 3}" and "one per header column" in error.expected, str(error)


def test_a_file_of_another_format_is_refused(tmp_path):
    error = refusal(hand_written(tmp_path / "m.npz", format="beamctl-gain-table"))
    assert error.key == "format" and "'beamctl-frf'" in error.expected, str(error)


@pytest.mark.parametrize("suffix", [".npz", ".mat"])
def test_a_newer_format_version_is_refused(tmp_path, suffix):
    error = refusal(hand_written(tmp_path / f"m{suffix}", format="beamctl-frf", format_version=2))
    assert error.key == "format_version" and error.value == 2, str(error)
    assert "written by a newer beamctl" in error.expected, str(error)


def test_channels_in_another_order_are_refused(tmp_path):
    swapped = np.array(("y1", "y2", "z1", "z2"), dtype=object)
    error = refusal(hand_written(tmp_path / "m.mat", outputs=swapped))
    assert error.key == "outputs" and "y1, z1, y2, z2 in this order" in error.expected, str(error)


@pytest.mark.parametrize(("variable", "text", "key"), [
    ("settings_json", "{'rig': 'A'}", "settings_json"),
    ("settings_json", "[1, 2]", "settings"),
    ("io_json", "{\"delay_samples\": -1}", "io.delay_samples"),
    ("io_json", "{\"delay\": 1}", "io.delay"),
])
def test_bad_json_variables_are_refused(tmp_path, variable, text, key):
    error = refusal(hand_written(tmp_path / "m.mat", **{variable: text}))
    assert error.key == key, str(error)


def test_the_readme_csv_example_reads(tmp_path):
    """The CSV example of the documentation's page on identification (docs/pages/identification.md,
    once the README's) reads as it says."""
    page = (Path(__file__).resolve().parents[2] / "docs" / "pages" / "identification.md").read_text()
    section = page.split("## Measured frequency responses: file formats", 1)[1]
    example = section.split("```text\n", 1)[1].split("```", 1)[0]
    path = tmp_path / "example.csv"
    path.write_text(example)
    read = read_frf(path)
    assert (read.load_n, read.sample_rate_hz, read.frequencies_hz.tolist()) == (2000.0, 6000.0, [10.0, 12.5])
    assert read.measured.sum() == 2 and read.measured[0, 0] and read.measured[1, 1], (
        "the documentation's example holds y1/yA and z1/zA")
