"""``beamctl log export|plot`` on a recorded run."""

import json

import numpy as np
import pytest
import scipy.io

from beamctl.gains.defaults import paper_table_path
from beamctl.gains.table import load_table
from beamctl.rt.config import controller_config
from beamctl.rt.controller import RECORD_COLUMNS, Controller
from beamctl.rt.loop import ControlLoop
from beamctl.rt.telemetry import TelemetryWriter, read_telemetry
from beamctl.tools.cli import main
from tests.rt.fakes import ScriptedHal
from tests.rt.test_loop import oscillating


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("log") / "run.btl"
    table = load_table(paper_table_path())
    controller = Controller(table, controller_config({"pacing": "sample"}))
    hal = ScriptedHal(table.design.sample_rate_hz, default=oscillating).open()
    writer = TelemetryWriter(path, RECORD_COLUMNS, capacity=8192).start()
    ControlLoop(controller, hal, telemetry=writer, max_cycles=2000).run(acquire_rt=False)
    return path


def test_export_mat_holds_every_column(recording, tmp_path, capsys):
    out = tmp_path / "run.mat"
    assert main(["log", "export", str(recording), "--to", "mat", "--out", str(out)]) == 0
    _, rows = read_telemetry(recording)
    mat = scipy.io.loadmat(out)
    np.testing.assert_array_equal(mat["q_1y"].ravel(), rows[:, RECORD_COLUMNS.index("q_1y")])
    assert "voltage_b3_V" in mat and "columns" in mat


def _table_lines(path) -> list[str]:
    """The CSV table: the lines below the ``#`` lines that describe the recording."""
    return [line for line in path.read_text().splitlines() if not line.startswith("#")]


def test_export_csv_has_a_header_row(recording, tmp_path):
    out = tmp_path / "run.csv"
    assert main(["log", "export", str(recording), "--to", "csv", "--out", str(out)]) == 0
    lines = _table_lines(out)
    assert lines[0].split(",") == RECORD_COLUMNS
    assert len(lines) == 1 + len(read_telemetry(recording)[1])


def test_plot_draws_the_run_over_time_and_its_path(recording, tmp_path, capsys):
    """The recording's load stays at 1500 N: no deflection-versus-load figure. It was written
    without the header's model: the deflection in mm comes from Table 1, and the plot says so."""
    assert main(["log", "plot", str(recording), "--out", str(tmp_path)]) == 0
    for name in ("run_over_time.png", "fig7b_run.png"):
        assert (tmp_path / name).stat().st_size > 10_000
    assert not (tmp_path / "fig7a_run.png").exists()
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "names no model" in err and "Table 1" in err, err


def test_a_file_that_is_not_telemetry_is_refused(tmp_path, capsys):
    bad = tmp_path / "bad.btl"
    bad.write_text("hello")
    assert main(["log", "export", str(bad), "--to", "csv"]) == 2
    assert "not a beamctl telemetry file" in capsys.readouterr().err


@pytest.fixture
def cut_off(recording, tmp_path):
    """The recording as a process killed mid-write leaves it: the last row lacks 100 bytes."""
    path = tmp_path / "cut.btl"
    path.write_bytes(recording.read_bytes()[:-100])
    return path


def _warning(err: str, rows: int, ignored: int) -> None:
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert "warning" in err and f"holds {rows} complete rows" in err, err
    assert f"ends in an incomplete row ({ignored} bytes ignored" in err, err


def test_export_of_a_file_cut_off_mid_row_keeps_the_complete_rows_and_warns(recording, cut_off, tmp_path,
                                                                            capsys):
    _, rows = read_telemetry(recording)
    out = tmp_path / "cut.csv"
    assert main(["log", "export", str(cut_off), "--to", "csv", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    _warning(captured.err, len(rows) - 1, 8 * len(RECORD_COLUMNS) - 100)
    assert len(_table_lines(out)) == 1 + len(rows) - 1
    assert f"wrote {out} ({len(rows) - 1} samples" in captured.out


def test_plot_of_a_file_cut_off_mid_row_warns_too(recording, cut_off, tmp_path, capsys):
    _, rows = read_telemetry(recording)
    assert main(["log", "plot", str(cut_off), "--out", str(tmp_path / "figs")]) == 0
    cut, model = capsys.readouterr().err.splitlines(keepends=True)
    _warning(cut, len(rows) - 1, 8 * len(RECORD_COLUMNS) - 100)
    assert "names no model" in model
    assert (tmp_path / "figs" / "run_over_time.png").exists()


def test_a_complete_file_exports_without_a_warning(recording, tmp_path, capsys):
    assert main(["log", "export", str(recording), "--to", "mat", "--out", str(tmp_path / "run.mat")]) == 0
    assert capsys.readouterr().err == ""


def test_export_writes_the_file_it_names(recording, tmp_path):
    """scipy would add .mat to a name without it; the file is where --out says."""
    out = tmp_path / "run.matlab"
    assert main(["log", "export", str(recording), "--to", "mat", "--out", str(out)]) == 0
    assert "q_1y" in scipy.io.loadmat(out) and not (tmp_path / "run.matlab.mat").exists()


def test_an_earlier_export_is_not_replaced_without_force(recording, tmp_path, capsys):
    """Before, a CSV export over an earlier .mat of the same name replaced it without a word."""
    out = tmp_path / "run.mat"
    assert main(["log", "export", str(recording), "--to", "mat", "--out", str(out)]) == 0
    before = out.read_bytes()
    capsys.readouterr()
    assert main(["log", "export", str(recording), "--to", "csv", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--force" in err and "already" in err and len(err.strip().splitlines()) == 1, err
    assert out.read_bytes() == before, "the earlier export is untouched"
    assert main(["log", "export", str(recording), "--to", "csv", "--out", str(out), "--force", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["format"] == "csv"


def test_csv_time_stamps_keep_every_sample_apart(tmp_path):
    """10 significant digits left 2 to 3 distinct times in 1.5 s of a CAN recording that had run
    for hours; the time column keeps nanoseconds. A recording 10 hours in, at 6000 Hz."""
    late = tmp_path / "late.btl"
    with TelemetryWriter(late, RECORD_COLUMNS, capacity=4096) as writer:
        for k in range(600):
            row = np.zeros(len(RECORD_COLUMNS))
            row[0] = 36_000.0 + k / 6000.0
            writer.push(row)
    out = tmp_path / "late.csv"
    assert main(["log", "export", str(late), "--to", "csv", "--out", str(out)]) == 0
    times = np.array([float(line.split(",")[0]) for line in _table_lines(out)[1:]])
    recorded = read_telemetry(late)[1][:, 0]
    np.testing.assert_allclose(times, recorded, rtol=0, atol=1e-9)
    assert len(np.unique(times)) == len(times)


def test_plot_takes_its_folder_as_out_and_names_the_flag_for_a_positional_one(recording, tmp_path, capsys):
    assert main(["log", "plot", str(recording), str(tmp_path / "figs")]) == 2
    assert "--out DIR" in capsys.readouterr().err
