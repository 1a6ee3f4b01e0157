"""Safety in one place: the one ramp to bias, and the counts that end in a fault."""

import numpy as np
import pytest

from beamctl.gains.defaults import paper_table_path
from beamctl.gains.table import load_table
from beamctl.hal.base import Sample
from beamctl.rt.config import controller_config
from beamctl.rt.controller import Controller
from beamctl.rt.loop import ControlLoop
from beamctl.rt.safety import Fault, State
from tests.rt.fakes import ScriptedHal


@pytest.fixture(scope="module")
def table():
    return load_table(paper_table_path())


def test_the_ramp_reaches_bias_linearly_in_its_samples_and_then_holds_it(table):
    """A fault ramps from the voltages it met to bias in ramp_time x rate samples, linearly,
    then holds bias (the engine's one ramp)."""
    c = _driving(table)
    start = c.voltages.copy()
    c.fault(Fault.OPERATOR, "test")
    steps = []
    while not c.at_bias:
        steps.append(c.step(None).copy())
    n = round(0.02 * c.sample_rate_hz)
    assert len(steps) == n, f"{n} ramp samples, then at bias"
    np.testing.assert_allclose(steps, [75.0 + (start - 75.0) * (1 - k / n) for k in range(1, n + 1)],
                               rtol=1e-12)
    np.testing.assert_array_equal(steps[-1], 75.0)
    assert np.all(c.step(None) == 75.0), "after the ramp, bias is held"


def _driving(table):
    c = Controller(table, controller_config({"start_ramp_time_s": 0.0, "safety": {"ramp_time_s": 0.02}}))
    s = Sample()
    s.strains[:] = (1e-4, -5e-5, 5e-5, 2e-5)
    s.axial_load = 1500.0
    c.arm(s)
    c.start()
    for _ in range(200):
        c.step(s)
    assert np.abs(c.voltages - 75.0).max() > 1.0, "the controller drives the stacks"
    return c


def test_the_loop_s_emergency_exit_writes_the_ramp_a_fault_runs(table):
    """One ramp: from the same voltages, the emergency path of the loop (an error inside it)
    writes to the HAL exactly the voltages the controller's fault ramp steps through."""
    faulted = _driving(table)
    faulted.fault(Fault.OPERATOR, "test")
    fault_ramp = []
    while not faulted.at_bias:
        fault_ramp.append(faulted.step(None).copy())

    c = _driving(table)
    hal = ScriptedHal(c.sample_rate_hz)
    hal.open()
    ControlLoop(c, hal)._emergency_ramp()
    np.testing.assert_array_equal(np.array(hal.written), np.array(fault_ramp))
    assert len(hal.written) == round(0.02 * c.sample_rate_hz)


def test_a_streak_of_overruns_faults_and_a_cycle_on_time_ends_the_streak(table):
    c = _driving(table)
    limit = c.config.safety.overrun_streak
    for _ in range(limit - 1):
        c.safety.cycle_overran()
    c.safety.cycle_on_time()
    for _ in range(limit - 1):
        c.safety.cycle_overran()
    assert c.state == State.RUNNING and c.safety.max_overrun_streak == limit - 1
    c.safety.cycle_overran()
    assert c.supervisor.fault == Fault.OVERRUN_STREAK, c.supervisor.reason()


def _in(table, situation: str) -> Controller:
    """A controller in one of the lifecycle's situations (driving the stacks where it runs)."""
    config = controller_config({"start_ramp_time_s": 0.0, "safety": {"ramp_time_s": 0.02}})
    if situation == "INIT":
        return Controller(table, config)
    c = _driving(table)
    if situation == "ARMED":
        c = Controller(table, config)
        s = Sample()
        s.axial_load = 1500.0
        c.arm(s)
    elif situation.startswith("FAULT"):
        c.fault(Fault.OPERATOR, "test")
    elif situation.startswith("STOP"):
        c.request_stop()
    if situation in ("FAULT at bias", "STOPPED"):
        while not c.at_bias or c.state == State.STOPPING:
            c.step(None)
    return c


SITUATIONS = ("INIT", "ARMED", "RUNNING", "FAULT ramping", "FAULT at bias", "STOPPING", "STOPPED")
# the rules as the lab documentation states them: the commands carried out in each situation
ALLOWED = {"INIT": {"stop"}, "ARMED": {"stop", "start", "gains"}, "RUNNING": {"stop"},
           "FAULT ramping": {"stop"}, "FAULT at bias": {"stop", "rearm", "gains"}, "STOPPING": {"stop"},
           "STOPPED": {"stop"}}


@pytest.mark.parametrize("situation", SITUATIONS)
def test_the_supervisor_s_rules_are_the_documented_ones_and_the_engine_carries_out_what_they_allow(
        table, situation):
    """One set of rules (Supervisor.refusal) for the control socket, SIGUSR1 and a gain table's
    swap: in each situation exactly the documented commands are allowed, every refusal says why,
    and each allowed one the engine (or the controller's swap) carries out without refusing."""
    c = _in(table, situation)
    expected_state = situation.split()[0]
    assert c.state.name == expected_state, (situation, c.state.name)
    assert c.at_bias == (situation != "RUNNING" and situation != "FAULT ramping" and situation != "STOPPING")
    refusals = {name: c.supervisor.refusal(name) for name in ("start", "stop", "rearm", "gains")}
    allowed = {name for name, why in refusals.items() if not why}
    assert allowed == ALLOWED[situation], (situation, refusals)
    assert all(len(why) > 10 for why in refusals.values() if why), refusals
    stopping = c.supervisor.refusal("start", stopping=True), c.supervisor.refusal("stop", stopping=True)
    assert stopping[0] != "" and stopping[1] == "", stopping
    sample = Sample()
    sample.axial_load = 1500.0
    for name in allowed:
        fresh = _in(table, situation)
        if name == "start":
            fresh.start()
        elif name == "stop":
            fresh.request_stop()
        elif name == "rearm":
            fresh.rearm(sample)
        else:
            fresh.use_table(fresh.prepare_table(table))
    with pytest.raises(ValueError, match="explode"):
        c.supervisor.refusal("explode")
