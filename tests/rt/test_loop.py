"""The loop against a scripted HAL: every way a run ends is a safe state with its reason."""

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import numpy as np
import pytest

from beamctl.common.signals import stop_on_signals
from beamctl.gains.defaults import paper_table_path
from beamctl.gains.table import load_table
from beamctl.hal.base import HalConnectionLost
from beamctl.rt.config import controller_config
from beamctl.rt.controller import COL, FLAG_NO_NEW_SAMPLE, RECORD_COLUMNS, Controller
from beamctl.rt.loop import ControlLoop
from beamctl.rt.safety import Fault, State
from beamctl.rt.telemetry import TelemetryWriter, read_telemetry
from tests.rt.fakes import ScriptedHal

DEFLECTED = ((8e-5, -4e-5, 3e-5, 1e-5), 1500.0)
RAMP_TIME = 0.05


def oscillating(sequence: int):
    """A beam vibrating about straight at 20 Hz (the controller drives the stacks without
    winding its integrator into saturation)."""
    a = 3e-5 * np.sin(2 * np.pi * 20.0 * sequence / 2500.0)
    return (a, -a, 0.5 * a, 0.2 * a), 1500.0


@pytest.fixture(scope="module")
def table():
    return load_table(paper_table_path())


def _loop(table, script, pacing="sample", write_delay=0.0, fail_write_after=None,
          default=DEFLECTED, max_cycles=None, **cfg):
    config = controller_config({"start_ramp_time_s": 0.0, "pacing": pacing,
                                "safety": {"ramp_time_s": RAMP_TIME, **cfg.pop("safety", {})}, **cfg})
    controller = Controller(table, config)
    hal = ScriptedHal(table.design.sample_rate_hz, script, default=default,
                      write_delay=write_delay, fail_write_after=fail_write_after)
    hal.open()
    return ControlLoop(controller, hal, max_cycles=max_cycles), hal


def _assert_safe_ramp(hal, was_driving: bool = True):
    """Voltages always in range; the last RAMP_TIME before reaching bias is a linear ramp
    with no step larger than (start - bias) / ramp samples; the run ends at bias."""
    v = np.array(hal.written)
    assert np.all((v >= 0.0) & (v <= 150.0)), "a voltage left [0, 150] V"
    np.testing.assert_array_equal(v[-1], 75.0)
    at_bias = np.all(v == 75.0, axis=1)
    end = len(v) - 1
    while end > 0 and at_bias[end - 1]:
        end -= 1
    n = round(RAMP_TIME * 2500.0)
    ramp = v[max(end - n, 0):end + 1]
    step = np.abs(np.diff(ramp, axis=0)).max()
    bound = np.abs(ramp[0] - 75.0).max() / n
    assert step <= bound * (1 + 1e-9) + 1e-12, f"jump of {step:.4f} V during the ramp (bound {bound:.4f})"
    if was_driving:
        before = np.abs(v[:max(end - n, 1)] - 75.0).max()
        assert before > 0.2, f"the controller was driving the stacks before the stop ({before:.3f} V)"


def _run(loop, require_rt=False):
    return loop.run(require_rt=require_rt, acquire_rt=False)


@pytest.mark.parametrize(("event", "fault"), [
    # silence past the table's gap limit at the load (125 samples of the paper's table at 1500 N;
    # each read time-out lets 1.5 periods pass)
    ([None] * 400, Fault.STALE_INPUT),
    ([((np.nan, 0.0, 0.0, 0.0), 1500.0)], Fault.STRAIN_NOT_FINITE),
    ([HalConnectionLost("bus-off")], Fault.HAL_ERROR),
])
def test_fault_ends_in_the_safe_state_with_its_reason(table, event, fault):
    script = [DEFLECTED] * 400 + event
    loop, hal = _loop(table, script)
    result = _run(loop)
    assert result.state == "FAULT" and result.fault == fault.name, result.reason
    _assert_safe_ramp(hal)
    assert np.abs(np.array(hal.written[399]) - 75.0).max() > 1.0, "was controlling before the fault"


def test_load_beyond_the_table_faults(table):
    script = [DEFLECTED] * 300 + [((0.0, 0.0, 0.0, 0.0), 4600.0)] * 3000
    loop, hal = _loop(table, script)
    result = _run(loop)
    assert result.fault == Fault.LOAD_OUT_OF_TABLE_RANGE.name, result.reason
    _assert_safe_ramp(hal)


def test_overrun_streak_faults_in_timer_pacing(table):
    """Each write takes 1 ms against a 0.4 ms period: a streak of overruns, skipped ahead,
    never a burst of catch-up cycles."""
    loop, hal = _loop(table, [], pacing="timer", write_delay=1e-3, safety={"overrun_streak": 10})
    start = time.perf_counter()
    result = _run(loop)
    elapsed = time.perf_counter() - start
    assert result.fault == Fault.OVERRUN_STREAK.name, result.reason
    t = result.timing
    assert t["overruns"] >= 10 and t["max_overrun_streak"] >= 10
    assert t["missed_periods"] >= t["overruns"], "skipped periods are counted"
    assert loop.cycles < elapsed / 1e-3 + 5, "no catch-up burst: at most one cycle per write time"
    _assert_safe_ramp(hal, was_driving=False)


def test_sigterm_ramps_to_bias_and_stops(table):
    """SIGTERM through the handlers a command installs (common/signals.py), the loop's stop request."""
    loop, hal = _loop(table, [], pacing="timer", default=oscillating)
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGTERM))
    previous = signal.signal(signal.SIGTERM, lambda *_: None)  # never let it reach pytest
    try:
        with stop_on_signals(signal.SIGTERM) as stop:
            loop.stop = stop
            timer.start()
            result = _run(loop)
    finally:
        timer.cancel()
        signal.signal(signal.SIGTERM, previous)
    assert result.state == "STOPPED" and result.stop_requested_by == "SIGTERM"
    assert result.fault == "NONE"
    _assert_safe_ramp(hal)


def test_the_loop_installs_no_signal_handler(table):
    """Library code: the loop leaves the process's handlers as they are; Ctrl-C without a stop
    request of the caller's leaves it through the emergency ramp to bias."""
    # time passes only when the loop sleeps: the run does not depend on this machine's speed
    clock = FakeClock(tick=0.0)
    config = controller_config({"start_ramp_time_s": 0.0, "safety": {"ramp_time_s": RAMP_TIME}})
    hal = ScriptedHal(table.design.sample_rate_hz, [], default=oscillating, sleep=clock.sleep).open()
    loop = ControlLoop(Controller(table, config), hal, max_cycles=400, clock=clock)
    # Ctrl-C as at a terminal (a shell starts a background job with SIGINT ignored)
    outside = signal.signal(signal.SIGINT, signal.default_int_handler)
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    seen = []

    def ctrl_c(loop):
        seen.append((signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)))
        if loop.cycles == 200:
            signal.raise_signal(signal.SIGINT)

    loop.on_cycle = ctrl_c
    try:
        _run(loop)
    except KeyboardInterrupt:
        pass
    else:
        pytest.fail(f"no KeyboardInterrupt: the run ended at cycle {loop.cycles} "
                    f"({loop.controller.state.name}: {loop.controller.supervisor.reason()})")
    finally:
        signal.signal(signal.SIGINT, outside)
    assert set(seen) == {before}, "the handlers during the run are the caller's"
    np.testing.assert_allclose(hal.written[-1], 75.0, err_msg="the emergency ramp ended at bias")


def test_a_signal_during_the_ramp_of_another_stop_is_still_reported(table):
    """The caller learns of the operator's signal even when the run was already stopping."""
    loop, hal = _loop(table, [], default=oscillating, max_cycles=300)

    def signal_in_the_ramp(loop):
        if loop.cycles == 310:
            signal.raise_signal(signal.SIGINT)

    loop.on_cycle = signal_in_the_ramp
    with stop_on_signals() as stop:
        loop.stop = stop
        result = _run(loop)
    assert result.stop_requested_by == "cycle limit" and result.signal_received == "SIGINT"
    assert result.state == "STOPPED"
    _assert_safe_ramp(hal)


def test_write_failure_faults(table):
    loop, hal = _loop(table, [], fail_write_after=300, default=oscillating)
    result = _run(loop)
    assert result.fault == Fault.HAL_ERROR.name and "amplifier link lost" in result.reason


class FakeClock:
    """Time that passes only when asked: ``tick`` per reading (the spin-wait advances), and
    what a sleep or an injected stretch of work asks for."""

    def __init__(self, tick: float = 1e-7) -> None:
        self.now = 0.0
        self.tick = tick

    def __call__(self) -> float:
        self.now += self.tick
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += max(seconds, 0.0)


def test_timer_pacing_keeps_absolute_deadlines_and_skips_ahead_after_an_overrun(table):
    """Every cycle starts on the grid t0 + k T, however late a cycle finished: after work that
    took 1.7 periods the next cycle starts on the next deadline still ahead, the skipped one
    counted, never a burst to catch up and never a shift of the grid. On a clock of the test's
    own, so the check is exact and the machine's load does not enter it (the jitter on the
    real clock is measured by `beamctl bench`)."""
    clock = FakeClock()
    loop, hal = _loop(table, [], pacing="timer", max_cycles=1000, default=oscillating)
    loop.clock, loop.sleep = clock, clock.sleep
    period = loop.period_s
    ends = []

    def on_cycle(lp):
        ends.append((clock.now, lp.timing.missed_periods))
        if lp.cycles % 100 == 50:
            clock.now += 1.7 * period          # this cycle's work overran its deadline

    loop.on_cycle = on_cycle
    result = _run(loop)
    assert result.state == "STOPPED"
    first = ends[0][0]
    slots = np.array([(t - first) / period for t, _ in ends])
    assert np.abs(slots - np.round(slots)).max() < 1e-3, "a cycle started off the deadline grid"
    missed = np.array([m for _, m in ends])
    expected = np.arange(len(ends)) + (missed - missed[0])
    np.testing.assert_array_equal(np.round(slots), expected,
                                  err_msg="cycles and skipped deadlines do not add up to the time")
    assert result.timing["overruns"] == result.timing["missed_periods"] > 0
    for stage in ("read", "compute", "write", "cycle"):
        assert result.timing[stage]["count"] > 900 and result.timing[stage]["max_us"] > 0


def test_telemetry_records_every_cycle(tmp_path, table):
    loop, hal = _loop(table, [], max_cycles=500, default=oscillating)
    loop.telemetry = TelemetryWriter(tmp_path / "run.btl", RECORD_COLUMNS, capacity=4096,
                                     meta={"test": True}).start()
    result = _run(loop)
    header, rows = read_telemetry(tmp_path / "run.btl")
    assert header["columns"] == RECORD_COLUMNS and header["meta"] == {"test": True}
    assert len(rows) == loop.cycles == result.telemetry["written"] and result.telemetry["dropped"] == 0
    np.testing.assert_array_equal(rows[:, COL["sequence"]], np.arange(2, 2 + len(rows)))
    np.testing.assert_array_equal(rows[-1, COL["voltage_a1_V"]:COL["voltage_a1_V"] + 6], 75.0)
    assert rows[-1, COL["state"]] == State.STOPPED


def test_a_full_ring_drops_records_and_counts_them(tmp_path):
    w = TelemetryWriter(tmp_path / "t.btl", ["a", "b"], capacity=8)  # writer thread not started
    for i in range(20):
        w.push(np.array([i, -i], dtype=float))
    assert w.dropped == 12
    w.close()
    _, rows = read_telemetry(tmp_path / "t.btl")
    np.testing.assert_array_equal(rows[:, 0], np.arange(8))


def test_telemetry_survives_kill_9_up_to_the_last_flush(tmp_path):
    path = tmp_path / "killed.btl"
    script = textwrap.dedent(f"""
        import time, numpy as np
        from beamctl.rt.telemetry import TelemetryWriter
        w = TelemetryWriter({str(path)!r}, ["t", "x"], capacity=100000, flush_interval_s=0.25).start()
        start = time.monotonic()
        print("started", flush=True)
        while True:
            t = time.monotonic() - start
            w.push(np.array([t, 2 * t]))
            time.sleep(0.0004)
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True,
                            cwd=tmp_path)
    try:
        assert proc.stdout.readline().strip() == "started"
        time.sleep(1.5)
        killed_at = 1.5
    finally:
        proc.kill()
        proc.wait()
    _, rows = read_telemetry(path)
    assert len(rows) > 100
    assert rows[-1, 0] > killed_at - 0.5 - 0.2, f"last record {rows[-1, 0]:.2f} s, killed at ~{killed_at} s"
    np.testing.assert_array_equal(rows[:, 1], 2 * rows[:, 0])


def test_a_stop_request_ends_a_run_that_stays_in_fault(table):
    """With stop_on_fault off (experiments, a service waiting for re-arm) the loop keeps
    cycling at bias after a fault; a stop request must still end it."""
    loop, hal = _loop(table, [DEFLECTED] * 100 + [((np.nan, 0.0, 0.0, 0.0), 1500.0)], default=oscillating)
    loop.stop_on_fault = False
    loop.on_cycle = lambda lp: lp.request_stop("test") if lp.cycles == 2000 else None
    result = _run(loop)
    assert result.state == "FAULT" and result.fault == Fault.STRAIN_NOT_FINITE.name
    assert 2000 <= result.cycles < 2100, result.cycles
    _assert_safe_ramp(hal, was_driving=False)


def test_operator_rearm_restarts_after_a_latched_fault(table):
    """What SIGUSR1 does in ``beamctl run``: after a fault at bias, a re-arm request clears
    it and the controller starts again, bumpless, from bias."""
    loop, hal = _loop(table, [DEFLECTED] * 100 + [((np.nan, 0.0, 0.0, 0.0), 1500.0)],
                      default=oscillating, start_ramp_time_s=0.05)
    loop.stop_on_fault = False
    seen = []

    def on_cycle(lp):
        state = lp.controller.state
        if not seen or seen[-1] != state:
            seen.append(state)
        if state == State.FAULT and lp.controller.at_bias and State.RUNNING not in seen[2:]:
            lp.request_rearm()
        if len(seen) >= 3 and state == State.RUNNING and lp.cycles > 900:
            lp.request_stop("test")

    loop.on_cycle = on_cycle
    result = _run(loop)
    assert seen[:3] == [State.RUNNING, State.FAULT, State.RUNNING], seen
    assert result.state == "STOPPED" and result.fault == "NONE"
    v = np.array(hal.written)
    assert np.abs(np.diff(v, axis=0)).max() < 2.0, "re-arm starts from bias without a jump"


def test_an_unexpected_error_in_the_loop_ramps_the_stacks_to_bias_before_propagating(table):
    loop, hal = _loop(table, [], default=oscillating, max_cycles=None)

    def explode(lp):
        if lp.cycles == 600:
            raise RuntimeError("a bug in a callback")

    loop.on_cycle = explode
    with pytest.raises(RuntimeError, match="a bug"):
        _run(loop)
    _assert_safe_ramp(hal)


def test_a_signal_s_rearm_follows_the_rules_of_the_control_socket_s(table):
    """SIGUSR1 is ``ctl rearm``: right after a fault, while the stacks ramp, it is refused (the
    voltages never jump back to bias) and the refusal is told to the service; once at bias, a
    second one re-arms. Each is decided by the supervisor's rules, as the socket's command is."""
    loop, hal = _loop(table, [DEFLECTED] * 300 + [((np.nan, 0.0, 0.0, 0.0), 1500.0)],
                      default=oscillating, start_ramp_time_s=0.05)
    loop.stop_on_fault = False
    states, told = [], []
    loop.on_signal_command = told.append

    def on_cycle(lp):
        states.append(lp.controller.state)
        if states[-1] == State.FAULT and states.count(State.FAULT) == 2:
            lp.request_rearm()        # two samples into the 125-sample ramp
        if states[-1] == State.FAULT and lp.controller.at_bias and len(told) == 1:
            lp.request_rearm()
        if lp.cycles > 1000:
            lp.request_stop("test")

    loop.on_cycle = on_cycle
    _run(loop)
    assert [(c.name, c.outcome) for c in told] == [("rearm", "refused"), ("rearm", "carried out")], told
    assert "still ramping to bias" in told[0].refusal and told[1].transition == "FAULT -> RUNNING", told
    first_fault = states.index(State.FAULT)
    restarted = first_fault + states[first_fault:].index(State.RUNNING)
    assert restarted - first_fault >= RAMP_TIME * 2500, "re-armed only after the ramp"
    v = np.array(hal.written)     # v[0] answers the arming sample, v[k + 1] cycle k
    ramp = v[first_fault:restarted + 1]
    step = np.abs(np.diff(ramp, axis=0)).max()
    assert step <= np.abs(ramp[0] - 75.0).max() / (RAMP_TIME * 2500) * (1 + 1e-9) + 1e-12


def test_sample_pacing_answers_every_sample_once_and_holds_through_a_missing_one(table):
    """One write per sample (and one for the arming sample): a read time-out while running
    neither writes nor moves the voltages, so a DAQ pairing answers with samples never sees
    an answer twice."""
    script = [DEFLECTED] * 200 + [None, None] + [DEFLECTED] * 100
    # time passes only by the read time-outs (1.5 periods each): the two missing samples are 3
    # periods of silence, short of the stale-input fault (5), however slow the machine
    clock = FakeClock(tick=0.0)
    config = controller_config({"start_ramp_time_s": 0.0, "safety": {"ramp_time_s": RAMP_TIME}})
    hal = ScriptedHal(table.design.sample_rate_hz, script, default=DEFLECTED, sleep=clock.sleep).open()
    loop = ControlLoop(Controller(table, config), hal, max_cycles=302, clock=clock)
    result = _run(loop)    # the cycle limit stops the run: a ramp to bias, one write per sample
    assert result.fault == Fault.NONE.name, result.reason
    v = np.array(hal.written)
    assert loop.cycles == (hal.sequence - 1) + 2, "every cycle but the two time-outs read a sample"
    assert len(v) == hal.sequence, f"{len(v)} writes for {hal.sequence} samples"
    assert np.abs(v[200] - v[199]).max() > 0, "the controller was moving the stacks"


def test_the_stale_input_fault_comes_after_stale_periods_of_time_not_of_read_time_outs(table):
    """The DAQ falls silent while the controller runs: with five missing samples ridden through,
    the fault is due once six periods of time have passed without a sample (the sixth sample is
    missing), not after six read time-outs of 1.5 periods each (9 periods). The loop's clock
    moves only by the HAL's time-outs here."""
    clock = FakeClock(tick=0.0)
    config = controller_config({"start_ramp_time_s": 0.0, "safety": {"ramp_time_s": RAMP_TIME,
                                                                     "stale_periods": 5}})
    controller = Controller(table, config)
    hal = ScriptedHal(2500.0, [DEFLECTED] * 200 + [None] * 40, sleep=clock.sleep).open()
    silent_at_fault, last_sample = [], [clock()]

    def watch(loop):
        if not int(controller.record[COL["flags"]]) & FLAG_NO_NEW_SAMPLE:
            last_sample[0] = clock()
        elif controller.supervisor.fault != Fault.NONE and not silent_at_fault:
            silent_at_fault.append((clock() - last_sample[0]) * 2500.0)

    loop = ControlLoop(controller, hal, clock=clock, on_cycle=watch)
    result = _run(loop)
    assert result.fault == Fault.STALE_INPUT.name, result.reason
    assert 6.0 <= silent_at_fault[0] <= 6.1 + 1e-9, (
        f"fault after {silent_at_fault[0]:.2f} periods without a sample; due after 6")


def test_a_streak_of_late_answers_faults_and_every_late_answer_is_counted(tmp_path, table):
    """A budget of 0.5 periods with ten answers in a row ridden through that held the stacks
    stale: answers later than the budget are counted; those within the delay the loop tolerates
    (the design's delay plus twice the budget's margin over it) are a loop with more delay, not a
    stall, and no streak of them faults (thirty in a row here); the eleventh in a row of answers
    later than that faults."""
    design = table.design.io.delay_samples
    tolerated = max(0.5, design + 2.0 * (0.5 - design))
    within = {50, 80, 81} | set(range(200, 230))
    beyond = set(range(300, 311))

    def age(sequence):
        if sequence in within:
            periods = (0.5 + tolerated) / 2
        else:
            periods = tolerated + 0.2 if sequence in beyond else 0.1
        return periods / 2500.0

    config = controller_config({"start_ramp_time_s": 0.0,
                                "safety": {"ramp_time_s": RAMP_TIME, "late_answer_streak": 10,
                                           "answer_budget_periods": 0.5}})
    controller = Controller(table, config)
    # 2000 samples, then an error: a loop that never faults on late answers ends, and says so
    script = [oscillating(k) for k in range(1, 2001)] + [RuntimeError("no fault in 2000 samples")]
    hal = ScriptedHal(2500.0, script, answer_ages_s=age).open()
    telemetry = TelemetryWriter.for_controller(tmp_path / "late.btl", controller).start()
    result = _run(ControlLoop(controller, hal, telemetry=telemetry))
    assert result.fault == Fault.LATE_ANSWERS.name, result.reason
    _, records = read_telemetry(tmp_path / "late.btl")
    sequence = records[:, COL["sequence"]]
    ages = records[:, COL["answer_age_us"]]
    faulted_at = int(sequence[np.argmax(records[:, COL["fault"]] != 0)])
    assert faulted_at == 310, (
        f"the eleventh answer in a row past the tolerated delay (sample 310) faults, not {faulted_at}")
    np.testing.assert_allclose(ages[np.isin(sequence, sorted(within))], 1e6 * (0.5 + tolerated) / 2 / 2500.0,
                               rtol=1e-9, err_msg="late answers' ages (us)")
    assert records[sequence == 310, COL["late_answers"]][0] == len(within) + len(beyond)
    assert result.timing["answer_age"]["count"] == int(np.isfinite(ages).sum())


def test_real_time_set_up_comes_before_the_hal_opens(table, monkeypatch):
    """Locking memory and collecting garbage take tens of milliseconds: done after the bus is
    open, the DAQ's samples queue up meanwhile."""
    from beamctl.rt import realtime

    events = []
    monkeypatch.setattr(realtime, "acquire", lambda *a, **k: events.append("real-time") or {})
    monkeypatch.setattr(realtime, "release", lambda: None)
    config = controller_config({"start_ramp_time_s": 0.0})
    hal = ScriptedHal(2500.0, default=oscillating)
    hal.opened = events
    ControlLoop(Controller(table, config), hal, max_cycles=5).run(acquire_rt=True)
    assert events == ["real-time", "open"], events


def test_signals_while_a_signal_s_rearm_is_pending_are_that_rearm(table):
    """SIGUSR1 twice more while the first re-arm waits for a sample (the bus is silent for a few
    samples): one re-arm carried out and told, no second one refused afterwards."""
    # a fault at the 300th sample, the ramp done by about 430; the bus silent for the 597th to
    # the 602nd sample, just after the first SIGUSR1
    script = [DEFLECTED] * 300 + [((np.nan, 0.0, 0.0, 0.0), 1500.0)] + [DEFLECTED] * 296 + [None] * 6
    loop, _ = _loop(table, script, default=oscillating, start_ramp_time_s=0.05)
    loop.stop_on_fault = False
    told = []
    loop.on_signal_command = told.append

    def on_cycle(lp):
        if lp.cycles >= 596 and lp.controller.state == State.FAULT:
            lp.request_rearm()
        if lp.cycles > 700:
            lp.request_stop("test")

    loop.on_cycle = on_cycle
    result = _run(loop)
    assert [(c.name, c.outcome) for c in told] == [("rearm", "carried out")], [
        (c.outcome, c.refusal) for c in told]
    assert result.state == "STOPPED" and result.fault == "NONE", result
