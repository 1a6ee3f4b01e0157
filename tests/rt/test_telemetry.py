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
