"""Operator commands in the loop (start, stop, rearm, gains): carried out or refused between two
cycles, each recorded in the telemetry's operator_command column."""

import dataclasses
import threading

import numpy as np
import pytest

from beamctl.gains.defaults import paper_table_path
from beamctl.gains.table import load_table
from beamctl.hal.base import Sample
from beamctl.hal.sim import SimBackend
from beamctl.models.plant import Plant, plant_config
from beamctl.rt.allocation import geometry
from beamctl.rt.config import controller_config
from beamctl.rt.controller import COL, RECORD_COLUMNS, Controller
from beamctl.rt.loop import ControlLoop, OperatorCommand, operator_code, operator_labels
from beamctl.rt.safety import State
from beamctl.rt.telemetry import TelemetryWriter, read_telemetry
from tests.rt.fakes import ScriptedHal

RAMP_TIME = 0.05
BAD_STRAIN = ((np.nan, 0.0, 0.0, 0.0), 1500.0)
V = slice(COL["voltage_a1_V"], COL["voltage_a1_V"] + 6)


def oscillating(sequence: int):
    """A beam vibrating about straight at 20 Hz (the law drives the stacks without saturating)."""
    a = 3e-5 * np.sin(2 * np.pi * 20.0 * sequence / 2500.0)
    return (a, -a, 0.5 * a, 0.2 * a), 1500.0


@pytest.fixture(scope="module")
def table():
    return load_table(paper_table_path())


def twice_the_gain_with_two_more_states(table):
    """The paper's table with the law's gains doubled and two more (idle) compensator states: a
    table that drives the stacks differently and needs a record buffer of another size."""
    comp = table.compensator
    g, n = comp.a.shape[:2]
    m = n + 2

    def grow(x, rows, cols):
        out = np.zeros((g, rows, cols))
        out[:, :x.shape[1], :x.shape[2]] = x
        return out

    a = grow(comp.a, m, m)
    a[:, n:, n:] = 0.5 * np.eye(2)
    start = np.zeros((m, 4))
    start[:n] = comp.start
    bigger = dataclasses.replace(
        comp, a=a, b=grow(comp.b, m, 4), e=grow(comp.e, m, 4), c=grow(2.0 * comp.c, 4, m), d=2.0 * comp.d,
        ki=2.0 * comp.ki, start=start,
        plane_states={"y": [*comp.plane_states["y"], n, n + 1], "z": list(comp.plane_states["z"])})
    return dataclasses.replace(table, compensator=bigger)


def _config(**overrides):
    return controller_config({"start_ramp_time_s": 0.0, "pacing": "sample",
                              "safety": {"ramp_time_s": RAMP_TIME}, **overrides})


def _loop(table, tmp_path, script=(), default=oscillating, start=True, **overrides):
    controller = Controller(table, _config(**overrides))
    hal = ScriptedHal(table.design.sample_rate_hz, list(script), default=default)
    hal.open()
    telemetry = TelemetryWriter(tmp_path / "run.btl", RECORD_COLUMNS, capacity=1 << 16).start()
    return ControlLoop(controller, hal, telemetry=telemetry, stop_on_fault=False, start=start), hal


def _run(loop):
    return loop.run(acquire_rt=False)


def _recorded(tmp_path):
    """[(row, label, state)] of the rows where the telemetry records an operator command."""
    _, rows = read_telemetry(tmp_path / "run.btl")
    codes = rows[:, COL["operator_command"]]
    labels = operator_labels()
    return [(int(i), labels[int(codes[i])], State(int(rows[i, COL["state"]])).name)
            for i in np.flatnonzero(codes)], rows


def test_every_code_has_a_label_and_carried_out_differs_from_refused():
    labels = operator_labels()
    codes = {operator_code(name, done) for name in ("start", "stop", "rearm", "gains")
             for done in (True, False)}
    assert len(codes) == 8 and 0 not in codes and codes <= set(labels), labels
    assert labels[operator_code("gains", False)] == "gains refused" and labels[0] == "none"


@pytest.mark.parametrize(("name", "why"), [
    ("start", "already running"),
    ("rearm", "no fault to re-arm"),
    ("gains", "changes only at bias"),
])
def test_a_command_refused_while_running_changes_nothing(table, tmp_path, name, why):
    """Refused while the controller runs: the voltages written are exactly those of the same run
    without the command, and the refusal is in the telemetry at the sample it was decided at."""
    reference, ref_hal = _loop(table, tmp_path / "ref", default=oscillating)
    reference.max_cycles = 600
    _run(reference)
    loop, hal = _loop(table, tmp_path, default=oscillating)
    loop.max_cycles = 600
    command = OperatorCommand(name, loop.controller.prepare_table(table) if name == "gains" else None)
    loop.on_cycle = lambda lp: lp.post(command) if lp.cycles == 300 else None
    _run(loop)
    assert command.outcome == "refused" and why in command.refusal, command.refusal
    np.testing.assert_array_equal(np.array(hal.written), np.array(ref_hal.written),
                                  err_msg=f"a refused {name} changed the voltages")
    recorded, _ = _recorded(tmp_path)
    assert recorded == [(300, f"{name} refused", "RUNNING")], recorded
    assert loop.controller.table is table


def test_stop_ramps_to_bias_and_ends_the_run_as_sigterm_does(table, tmp_path):
    loop, hal = _loop(table, tmp_path, default=oscillating)
    command = OperatorCommand("stop")
    loop.on_cycle = lambda lp: lp.post(command) if lp.cycles == 400 else None
    result = _run(loop)
    assert command.outcome == "carried out" and command.transition == "RUNNING -> STOPPING"
    assert result.state == "STOPPED" and result.stop_requested_by == "operator"
    v = np.array(hal.written)
    assert np.abs(v[400] - 75.0).max() > 0.2, "the law was driving the stacks when the stop came"
    np.testing.assert_array_equal(v[-1], 75.0)
    assert len(v) - 1 - 400 <= RAMP_TIME * 2500 + 2, "the run ended once the ramp reached bias"
    recorded, _ = _recorded(tmp_path)
    assert recorded == [(400, "stop", "STOPPING")], recorded


def test_a_held_controller_waits_at_bias_until_start(table, tmp_path):
    """``beamctl run --hold``: armed, the stacks at bias, until the operator's start."""
    loop, hal = _loop(table, tmp_path, default=oscillating, start=False)
    start = OperatorCommand("start")

    def on_cycle(lp):
        if lp.cycles == 500:
            lp.post(start)
        if lp.cycles == 1000:
            lp.request_stop("test")

    loop.on_cycle = on_cycle
    _run(loop)
    assert start.outcome == "carried out" and start.transition == "ARMED -> RUNNING"
    v = np.array(hal.written)       # v[k + 1] answers cycle k
    np.testing.assert_array_equal(v[:501], 75.0, err_msg="the stacks left bias before the start")
    assert np.abs(v[501:900] - 75.0).max() > 0.2, "the law did not drive the stacks after the start"
    recorded, _ = _recorded(tmp_path)
    assert recorded == [(500, "start", "RUNNING")], recorded


def test_rearm_is_refused_while_the_stacks_ramp_and_carried_out_at_bias(table, tmp_path):
    """After a fault: a re-arm during the ramp to bias is refused saying so; at bias it clears the
    fault and the controller starts again from bias, without a jump."""
    loop, hal = _loop(table, tmp_path, script=[oscillating(k) for k in range(300)] + [BAD_STRAIN],
                      default=oscillating, start_ramp_time_s=0.05)
    early, late = OperatorCommand("rearm"), OperatorCommand("rearm")
    seen = []

    def on_cycle(lp):
        c = lp.controller
        seen.append(c.state)
        if c.state == State.FAULT and seen.count(State.FAULT) == 3:
            lp.post(early)
        elif c.state == State.FAULT and c.at_bias and early.outcome and not late.outcome:
            lp.post(late)
        if late.outcome and lp.cycles > 1500:
            lp.request_stop("test")

    loop.on_cycle = on_cycle
    result = _run(loop)
    assert early.outcome == "refused" and "still ramping to bias" in early.refusal, early.refusal
    assert late.outcome == "carried out" and late.transition == "FAULT -> RUNNING", late.transition
    assert result.state == "STOPPED" and result.fault == "NONE"
    recorded, rows = _recorded(tmp_path)
    assert [label for _, label, _ in recorded] == ["rearm refused", "rearm"], recorded
    (refused_row, _, refused_state), (rearm_row, _, rearm_state) = recorded
    assert refused_state == "FAULT" and rearm_state == "RUNNING"
    v = rows[:, V]
    assert np.all(v[rearm_row - 1] == 75.0), "re-armed before the stacks were at bias"
    assert np.abs(np.diff(v[refused_row:], axis=0)).max() < 2.0, "the restart jumped away from bias"


def test_a_gain_table_swapped_at_bias_is_the_one_the_controller_runs(table, tmp_path):
    """Faulted and at bias, the operator swaps in another table (twice the gains, a compensator
    of another size) and re-arms: from the restart on, the voltages are exactly those of a
    controller built on the new table, started on the same sample and fed the same samples."""
    other = twice_the_gain_with_two_more_states(table)
    loop, hal = _loop(table, tmp_path, script=[oscillating(k) for k in range(300)] + [BAD_STRAIN],
                      default=oscillating)
    swap = OperatorCommand("gains", loop.controller.prepare_table(other))
    rearm = OperatorCommand("rearm")

    def on_cycle(lp):
        c = lp.controller
        if c.state == State.FAULT and c.at_bias and not swap.outcome:
            lp.post(swap)
        elif swap.outcome and not rearm.outcome and lp._command is None:
            lp.post(rearm)
        if rearm.outcome and lp.cycles >= rearm.cycle + 400:
            lp.request_stop("test")

    loop.on_cycle = on_cycle
    _run(loop)
    assert swap.outcome == "carried out" and swap.transition == "FAULT -> FAULT", swap.refusal
    assert rearm.outcome == "carried out", rearm.refusal
    assert loop.controller.table is other and loop.controller.compensator_state.size == 6
    recorded, rows = _recorded(tmp_path)
    assert [label for _, label, _ in recorded] == ["gains", "rearm"], recorded

    # the same samples into a controller built on the other table, armed and started on the
    # sample the loop re-armed on (row k of the telemetry holds the sample stepped at cycle k)
    restart = rearm.cycle
    fresh = Controller(other, _config())
    samples = []
    for k in range(restart, restart + 300):
        sample = Sample()
        sample.timestamp, sample.sequence = rows[k, COL["time_s"]], int(rows[k, COL["sequence"]])
        sample.strains[:] = rows[k, COL["strain_y1"]:COL["strain_y1"] + 4]
        sample.axial_load = rows[k, COL["load_N"]]
        samples.append(sample)
    fresh.arm(samples[0])
    fresh.start()
    expected = np.array([fresh.step(sample).copy() for sample in samples])
    np.testing.assert_allclose(rows[restart:restart + 300, V], expected, rtol=0, atol=1e-9,
                               err_msg="after the swap the controller does not run the new table")
    moved = np.abs(expected - 75.0).max()
    assert moved > 0.2, f"the restarted law hardly moved the stacks ({moved:.3f} V): nothing was compared"


def test_a_table_refused_before_the_loop_is_recorded_and_the_running_one_kept(table, tmp_path):
    """A gain table that failed its checks reaches the loop as a refusal: recorded, the table
    in use untouched."""
    loop, hal = _loop(table, tmp_path, default=oscillating, start=False)
    command = OperatorCommand("gains", refusal="sha256: the file was changed after it was built")

    def on_cycle(lp):
        if lp.cycles == 100:
            lp.post(command)
        if lp.cycles == 300:
            lp.request_stop("test")

    loop.on_cycle = on_cycle
    _run(loop)
    assert command.outcome == "refused" and "changed after it was built" in command.refusal
    assert loop.controller.table is table
    recorded, _ = _recorded(tmp_path)
    assert recorded == [(100, "gains refused", "ARMED")], recorded


def test_a_command_from_another_thread_waits_for_its_outcome(table, tmp_path):
    """As the control socket does: post from another thread, wait; the loop decides between
    two of its cycles."""
    loop, hal = _loop(table, tmp_path, default=oscillating)
    command = OperatorCommand("start")
    outcome = []

    def operator():
        loop.post(command)
        outcome.append(command.wait(60.0))

    thread = threading.Thread(target=operator)

    def on_cycle(lp):
        if lp.cycles == 1:
            thread.start()
        if outcome:
            lp.request_stop("test")

    loop.on_cycle = on_cycle
    _run(loop)
    thread.join(60.0)
    assert outcome == [True] and command.outcome == "refused" and "already running" in command.refusal


def test_a_withdrawn_command_is_never_carried_out_and_a_later_one_is(table, tmp_path):
    loop, hal = _loop(table, tmp_path, default=oscillating)
    withdrawn, later = OperatorCommand("stop"), OperatorCommand("stop")
    loop.post(withdrawn)
    assert withdrawn.cancel(), "a command the loop has not taken can be withdrawn"
    loop.post(later)
    assert not later.outcome, "a withdrawn command does not block the next one"
    loop.max_cycles = 2000
    loop.on_cycle = None
    result = _run(loop)
    assert not withdrawn.wait(0) and withdrawn.outcome == ""
    assert later.outcome == "carried out" and result.stop_requested_by == "operator"
    recorded, _ = _recorded(tmp_path)
    assert [label for _, label, _ in recorded] == ["stop"], recorded


def test_a_command_the_loop_cannot_take_any_more_is_refused_at_once(table, tmp_path):
    loop, hal = _loop(table, tmp_path, default=oscillating)
    loop.max_cycles = 300
    pending = OperatorCommand("rearm")
    # posted on the last cycle: still pending when the run ends
    loop.on_cycle = lambda lp: lp.post(pending) if lp.controller.state == State.STOPPED else None
    result = _run(loop)
    assert result.state == "STOPPED"
    assert pending.outcome == "refused" and "ended" in pending.refusal, pending.refusal
    after = OperatorCommand("start")
    loop.post(after)
    assert after.wait(0) and after.outcome == "refused" and "has ended" in after.refusal


def test_gains_at_bias_on_the_simulated_beam_then_start_holds_it_straight(table, tmp_path):
    """With the simulated beam at 3000 N (near its 3194 N buckling load), held at bias: swap in
    another table, start, and the controller holds the beam near straight with the new gains."""
    plant = Plant(_paper_model(), plant_config({"sample_rate_hz": 2500.0, "load": {"start": 3000.0,
                                                                                    "end": 3000.0},
                                                "bow": {"amplitude": 5e-5, "angle_deg": 234.0}}))
    config = _config()
    controller = Controller(table, config)
    hal = SimBackend(plant, geometry(config.actuators), pace="simulated")
    telemetry = TelemetryWriter(tmp_path / "run.btl", RECORD_COLUMNS, capacity=1 << 16).start()
    loop = ControlLoop(controller, hal, telemetry=telemetry, stop_on_fault=False, start=False)
    other = twice_the_gain_with_two_more_states(table)
    swap = OperatorCommand("gains", controller.prepare_table(other))
    start = OperatorCommand("start")

    held = 2500             # 1 s at bias: the beam settles at its bowed shape

    def on_cycle(lp):
        if lp.cycles == 100:
            lp.post(swap)
        elif lp.cycles == held:
            lp.post(start)
        elif lp.cycles == held + 2 * 2500:
            lp.request_stop("test")

    loop.on_cycle = on_cycle
    try:
        result = _run(loop)
    finally:
        hal.close()
    assert swap.outcome == "carried out" and start.outcome == "carried out", (swap.refusal, start.refusal)
    assert result.fault == "NONE", result.reason
    assert loop.controller.table is other
    recorded, rows = _recorded(tmp_path)
    assert [label for _, label, _ in recorded] == ["gains", "start"], recorded
    q = np.hypot(rows[:, COL["q_1y"]], rows[:, COL["q_1z"]])
    before, after = q[held - 500:held].mean(), q[-500:].mean()
    assert after < 0.5 * before, (f"|q1| {before:.3g} at bias, {after:.3g} after 2 s of control with the "
                                  f"new table: the controller did not straighten the beam")


def _paper_model():
    from beamctl.models import build_model, load_parameters

    return build_model(load_parameters())
