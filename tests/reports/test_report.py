"""``beamctl report`` and ``beamctl log plot`` on a recorded run of the simulated rig that ends in
a fault: the load passes the load cell's range while the controller holds the beam."""

import base64
import re
import struct

import numpy as np
import pytest

from beamctl.assembly.run import build_plant, load_gain_table, plant_geometry, service_config
from beamctl.gains.defaults import paper_table_path
from beamctl.hal.sim import SimBackend
from beamctl.models import build_model, load_parameters
from beamctl.models.modal import Deflection
from beamctl.reports import report
from beamctl.rt.controller import RECORD_COLUMNS, Controller
from beamctl.rt.loop import ControlLoop
from beamctl.rt.safety import Fault, State
from beamctl.rt.telemetry import MAGIC, TelemetryWriter, read_telemetry
from beamctl.tools.cli import main

SENSOR_HIGH_N = 1200.0
SCENARIO = {
    "gains": {"table": str(paper_table_path())},
    "hal": {"backend": "sim"},
    "controller": {"pacing": "sample", "safety": {"load_range_n": [-200.0, SENSOR_HIGH_N]}},
    "plant": {"load": {"start": 1000.0, "end": 1400.0, "rate": 400.0},
              "bow": {"amplitude": 5e-5, "angle_deg": 234.0},
              "noise": {"strain": 2e-7, "load": 2.0, "seed": 3}},
}


def _record(path, scenario: dict, label: str, seconds: float):
    """The scenario's simulated rig under its gain table for ``seconds``, recorded to ``path``
    (the loop goes on after a fault, as a service's recording does); returns the plant. The
    plant must not overflow (numpy raises)."""
    cfg = service_config(scenario, label)
    table = load_gain_table(cfg)
    plant = build_plant(cfg, table)
    hal = SimBackend(plant, plant_geometry(cfg), pace="simulated")
    controller = Controller(table, cfg.controller)
    writer = TelemetryWriter.for_controller(path, controller, meta={"config": label}).start()
    hal.open()
    try:
        with np.errstate(all="raise"):
            ControlLoop(controller, hal, telemetry=writer, stop_on_fault=False,
                        max_cycles=int(seconds * table.design.sample_rate_hz)).run(acquire_rt=False)
    finally:
        hal.close()
        writer.close()
    return plant


@pytest.fixture(scope="module")
def faulted(tmp_path_factory):
    """1.5 s of the paper's design holding the simulated beam while the load ramps from 1000 N
    at 400 N/s; the load cell's range ends at 1200 N: a fault after about 0.5 s."""
    path = tmp_path_factory.mktemp("report") / "faulted.btl"
    _record(path, SCENARIO, "test scenario", 1.5)
    return path


def test_the_run_is_read_in_millimetres_with_the_recording_s_own_model(faulted):
    """The deflection is the gauges' reconstruction through the recorded model's mode shapes,
    the same numbers ``beamctl experiment`` measures with."""
    run = report.load_run(faulted)
    header, rows = read_telemetry(faulted)
    q = rows[:, RECORD_COLUMNS.index("q_1y"):RECORD_COLUMNS.index("q_1y") + 4]
    deflection = Deflection(build_model(load_parameters()))
    for i in (0, len(rows) // 2, len(rows) - 1):
        mag, y, z = deflection(q[i])
        assert run.deflection_m[i] == pytest.approx(mag, rel=1e-12)
        assert (run.deflection_y_m[i], run.deflection_z_m[i]) == pytest.approx((y, z), rel=1e-12)
    # a bow of 0.05 mm held by the controller: tens of micrometres, not metres or modal units
    assert 1e-6 < np.median(run.deflection_m) < 1e-4, np.median(run.deflection_m)
    assert report.warnings(run) == [], "the recording names its model"


def test_the_fault_is_found_where_the_load_passed_the_sensor_range(faulted):
    run = report.load_run(faulted)
    events = report.events(run)
    assert [e.state for e in events][:2] == ["RUNNING", "FAULT"], events
    fault = events[1]
    assert fault.fault == "LOAD_OUT_OF_SENSOR_RANGE"
    # the load cell reads the ramp with 2 N of noise: the first reading past 1200 N is within a
    # few noise widths and one sample's ramp (0.16 N) of it
    assert fault.load_n == pytest.approx(SENSOR_HIGH_N, abs=10.0), fault
    assert fault.time_s == pytest.approx((SENSOR_HIGH_N - 1000.0) / 400.0, abs=0.05), fault
    merit = report.figures_of_merit(run)
    assert merit["faults"] == ["LOAD_OUT_OF_SENSOR_RANGE"] and merit["end_state"] == "FAULT"
    assert merit["load_held_n"] == pytest.approx(SENSOR_HIGH_N, abs=10.0), "held until the fault"
    assert 0.0 <= merit["voltage_range_v"][0] < 75.0 < merit["voltage_range_v"][1] <= 150.0, merit
    assert merit["late_answers"] == 0 and merit["missing_samples"] == 0, merit
    assert merit["samples"] == len(read_telemetry(faulted)[1]), "every sample recorded"
    assert merit["duration_s"] == pytest.approx(1.5, abs=2 / 2500), "1.5 s at 2500 Hz"


def test_report_writes_one_self_contained_page_with_figures_settings_faults_and_merit(faulted, tmp_path,
                                                                                     capsys):
    out = tmp_path / "page.html"
    assert main(["report", str(faulted), "--out", str(out)]) == 0
    said = capsys.readouterr()
    assert said.err == "", said.err
    assert f"wrote {out}" in said.out and "LOAD_OUT_OF_SENSOR_RANGE" in said.out, said.out
    page = out.read_text()
    images = re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', page)
    assert len(images) == 3, "over time, figure 7a (the load moved 400 N) and 7b"
    for data in images:
        png = base64.b64decode(data)
        assert png.startswith(b"\x89PNG\r\n\x1a\n")
        width, height = struct.unpack(">II", png[16:24])
        assert width >= 400 and height >= 400, (width, height)
    assert not re.search(r'(src|href)="(https?:)?//', page), "no resource outside the page"
    assert "LOAD_OUT_OF_SENSOR_RANGE: the load-cell reading is outside the sensor range" in page
    assert "controller.safety.load_range_n" in page and "-200, 1200" in page, "its settings"
    assert "test scenario" in page
    for merit in ("max deflection", "load held", "voltage range", "saturated", "late answers",
                  "longer than the period"):
        assert merit in page, merit


def test_report_defaults_to_the_recording_s_name_with_html(faulted, tmp_path):
    copy = tmp_path / "run.btl"
    copy.write_bytes(faulted.read_bytes())
    assert main(["report", str(copy)]) == 0
    assert (tmp_path / "run.html").stat().st_size > 50_000


def _one_line_refusal(capsys, what: str) -> None:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert err.startswith("beamctl report: error: ") and what in err, err


def test_a_file_that_is_not_a_recording_is_refused_in_one_line(tmp_path, capsys):
    bad = tmp_path / "notes.btl"
    bad.write_text("hello")
    assert main(["report", str(bad), "--out", str(tmp_path / "p.html")]) == 2
    _one_line_refusal(capsys, "not a beamctl telemetry file")
    assert not (tmp_path / "p.html").exists()


def test_a_missing_recording_is_refused_in_one_line(tmp_path, capsys):
    assert main(["report", str(tmp_path / "absent.btl"), "--out", str(tmp_path / "p.html")]) == 2
    _one_line_refusal(capsys, "cannot read")


def test_a_recording_without_a_sample_is_refused_in_one_line(tmp_path, capsys):
    empty = tmp_path / "empty.btl"
    with TelemetryWriter(empty, RECORD_COLUMNS, capacity=4):
        pass
    assert empty.read_bytes().startswith(MAGIC)
    assert main(["report", str(empty), "--out", str(tmp_path / "p.html")]) == 2
    _one_line_refusal(capsys, "holds no sample")


def test_the_page_may_not_overwrite_the_recording(faulted, tmp_path, capsys):
    copy = tmp_path / "run.btl"
    copy.write_bytes(faulted.read_bytes())
    assert main(["report", str(copy), "--out", str(copy)]) == 2
    _one_line_refusal(capsys, "it is the recording being reported")
    assert copy.read_bytes() == faulted.read_bytes()


def test_a_recording_that_names_no_model_is_read_with_table_1_and_says_so(faulted, tmp_path, capsys):
    """Recordings made before the header held the model: the paper's Table 1 (the model the
    shipped tables are built for), with a warning on stderr and on the page."""
    header, rows = read_telemetry(faulted)
    old = tmp_path / "old.btl"
    with TelemetryWriter(old, header["columns"], capacity=len(rows) + 1,
                         meta={"config": "lab.yaml"}) as writer:
        for row in rows:
            writer.push(row)
    assert main(["report", str(old), "--out", str(tmp_path / "old.html")]) == 0
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "names no model" in err and "Table 1" in err, err
    assert "names no model" in (tmp_path / "old.html").read_text()
    np.testing.assert_allclose(report.load_run(old).deflection_m, report.load_run(faulted).deflection_m,
                               rtol=1e-12, err_msg="the recording was made with Table 1's model")


def test_log_plot_draws_the_run_over_time_and_its_figure_7(faulted, tmp_path, capsys):
    assert main(["log", "plot", str(faulted), "--out", str(tmp_path)]) == 0
    for name in ("run_over_time.png", "fig7a_run.png", "fig7b_run.png"):
        assert (tmp_path / name).stat().st_size > 10_000, name   # drawn: a blank figure is under 5 kB


def test_the_figure_over_time_tells_the_six_voltages_apart_with_the_limits(faulted):
    """Support A and support B in panels of their own, the three stacks of a support each in
    its colour and line style, the 0 and 150 V limits drawn; the state panel names the fault;
    the deflection in mm."""
    from beamctl.reports import plots

    run = report.load_run(faulted)
    fig = plots.run_over_time(run)
    try:
        ax_d, _, ax_a, ax_b, ax_s = fig.axes
        for ax, support in ((ax_a, "a"), (ax_b, "b")):
            stacks = [line for line in ax.get_lines() if line.get_label().startswith(support)]
            assert [line.get_label() for line in stacks] == [f"{support}1", f"{support}2", f"{support}3"]
            looks = {(line.get_color(), line.get_linestyle()) for line in stacks}
            assert len({c for c, _ in looks}) == 3 and len({s for _, s in looks}) == 3, looks
            levels = {line.get_ydata()[0] for line in ax.get_lines() if line.get_linestyle() == ":"}
            assert {0.0, 150.0} <= levels, levels
        assert "LOAD_OUT_OF_SENSOR_RANGE" in [t.get_text() for t in ax_s.texts]
        assert ax_d.get_ylabel() == "deflection in mm"
        magnitude = next(line for line in ax_d.get_lines() if line.get_label() == "|w|")
        np.testing.assert_allclose(magnitude.get_ydata(), run.deflection_m[::run.stride()] * 1e3)
    finally:
        plots._pyplot().close(fig)


def _synthetic(n: int, fault_at: int) -> report.RunRecord:
    """A run at 2500 Hz held at 1000 N that faults (stale input) at sample ``fault_at``."""
    state = np.full(n, int(State.RUNNING))
    fault = np.zeros(n, dtype=int)
    state[fault_at:] = int(State.FAULT)
    fault[fault_at:] = int(Fault.STALE_INPUT)
    zeros = np.zeros(n)
    return report.RunRecord(path=report.Path("synthetic.btl"), meta={}, model_note="", sample_rate_hz=2500.0,
                            time_s=np.arange(n) / 2500.0, load_n=zeros + 1000.0,
                            load_filtered_n=zeros + 1000.0,
                            deflection_m=zeros, deflection_y_m=zeros, deflection_z_m=zeros,
                            voltages_v=np.full((n, 6), 75.0), state=state, fault=fault, flags=fault * 0,
                            step_us=zeros, answer_age_us=zeros, late_answers=zeros)


def test_a_long_run_s_last_moments_get_a_figure_of_their_own():
    """40 s of a run whose fault comes at 30 s: a second figure over time from 2 s before it to
    2 s after it, the fault in the middle (before, the window ran to the end of the recording and
    a long wait at bias squeezed the fault into its left edge)."""
    run = _synthetic(100_000, fault_at=75_000)
    figures = report.run_figures(run)
    from beamctl.reports import plots

    try:
        assert "run_end.png" in figures
        state = figures["run_end.png"].axes[-1].get_lines()[0].get_xdata()
        assert state[0] == pytest.approx(28.0) and state[-1] == pytest.approx(32.0, abs=1e-3), state
    finally:
        for fig in figures.values():
            plots._pyplot().close(fig)


def test_a_state_change_missed_by_the_thinning_is_still_drawn():
    """A fault that lasts fewer samples than a figure's point spacing: the state panel is drawn
    from the changes themselves."""
    from beamctl.reports import plots

    run = _synthetic(100_000, fault_at=50_001)
    assert run.stride() > 1
    fig = plots.run_over_time(run)
    try:
        step = fig.axes[-1].get_lines()[0]
        assert int(State.FAULT) in step.get_ydata()
        first_fault = list(step.get_ydata()).index(int(State.FAULT))
        assert step.get_xdata()[first_fault] == pytest.approx(50_001 / 2500.0)
    finally:
        plots._pyplot().close(fig)


@pytest.fixture(scope="module")
def lost(tmp_path_factory):
    """The paper's design while the load ramps from 2000 N at 500 N/s to 3600 N, past the beam's
    3194 N: the stacks run out, the supervisor faults, the stacks ramp to bias and the beam is
    lost; the recording goes on to 4 s."""
    path = tmp_path_factory.mktemp("report") / "lost.btl"
    scenario = {**SCENARIO, "controller": {"pacing": "sample"},
                "plant": {"load": {"start": 2000.0, "end": 3600.0, "rate": 500.0},
                          "bow": {"amplitude": 1.61e-4, "angle_deg": 234.0},
                          "noise": {"strain": 2e-7, "load": 2.0, "seed": 3}}}
    return path, _record(path, scenario, "lost beam", 4.0)


def test_a_lost_beam_is_reported_with_what_was_held_and_where_it_was_lost(lost):
    """Before, the simulated beam ran away after the fault: numpy overflowed, the report said
    'max deflection nan mm' and 'load held -'."""
    path, plant = lost
    assert plant.on_stops_since is not None, "the beam was lost and came to rest on its stops"
    run = report.load_run(path)
    merit = report.figures_of_merit(run)
    assert merit["max_deflection_mm"] is not None and 1.0 < merit["max_deflection_mm"] < 30.0, merit
    assert merit["load_held_n"] is not None and merit["load_held_n"] > 3100.0, merit
    lost_at = merit["lost"]
    assert lost_at is not None and lost_at["fault"] == merit["faults"][0], merit
    # lost after it was held: the load cell's 2 N of noise aside
    assert lost_at["load_n"] >= merit["load_held_n"] - 10.0, (lost_at, merit["load_held_n"])
    rows = dict(report.merit_rows(merit))
    assert "nan" not in " ".join(rows.values()), rows
    text = rows["beam lost (deflection past 1.0 mm)"]
    assert text.startswith(f"at {lost_at['load_n']:.0f} N") and lost_at["fault"] in text, text
