"""Reading telemetry files, complete or cut off mid-write."""

import numpy as np

from beamctl.rt.telemetry import TelemetryWriter, read_telemetry


def _recording(path, rows: int):
    with TelemetryWriter(path, ["t", "x"], capacity=64) as writer:
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
