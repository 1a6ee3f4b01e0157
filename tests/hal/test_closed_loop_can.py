"""Acceptance: the rt controller with the paper's gain table holds the simulated beam at 3000 N
over virtual CAN, and reaches its safe state when the DAQ falls silent; bad frames never reach
the law; answers later than the table allows fault.

Every controller here runs at the shipped safety settings (the gain table's ride-through
limits), on a CAN rig (tests/hal/rigs.py) whose emulator waits for each answer and whose clock
passes only while the DAQ is silent (or an answer is made late on purpose): what is asserted
does not depend on this machine's scheduling."""

import can
import numpy as np

from beamctl.hal.dbc import Contract
from beamctl.rt.config import controller_config
from beamctl.rt.controller import COL, FLAG_NO_NEW_SAMPLE, I_FLAGS, Controller
from beamctl.rt.safety import Fault, State
from beamctl.rt.telemetry import TelemetryWriter, read_telemetry
from tests.hal.rigs import LOCKSTEP_TIMEOUT_S, RATE_HZ, TABLE, CanRig, shipped_limits, wait_until

HOLD_S = 2.0
CONTRACT = Contract()
SHIPPED = controller_config({"pacing": "sample"})       # the safety as shipped: the table's limits


def test_beam_held_straight_at_3000_N_then_safe_when_the_daq_stops():
    """The DAQ falls silent after 2 s of plant time: the stale-input fault comes after exactly
    the table's gap limit + 1 periods without a sample (the samples due in that time are
    missing, one more than the loop rides through), measured as the loop measures it."""
    plant_log = {"time": [], "deflection": [], "voltages": []}
    rig = None

    def on_step(plant, voltages):
        """In the emulator's thread, after each plant step: a consistent view of the beam."""
        plant_log["time"].append(plant.time)
        plant_log["deflection"].append(plant.deflection()[0])
        plant_log["voltages"].append(voltages.copy())
        if plant.time >= HOLD_S:
            rig.emulator.stop_event.set()      # the DAQ falls silent

    rig = CanRig(load={"start": 3000.0, "end": 3000.0}, bow={"amplitude": 5e-5, "angle_deg": 234.0},
                 on_step=on_step, answer_timeout_s=LOCKSTEP_TIMEOUT_S)
    controller = Controller(TABLE, SHIPPED)
    last_sample, at_fault = [None], []

    def watch(loop):
        now = rig.clock()
        if not int(controller.record[I_FLAGS]) & FLAG_NO_NEW_SAMPLE:
            last_sample[0] = now
        elif controller.supervisor.fault != Fault.NONE and not at_fault:
            at_fault.append(((now - last_sample[0]) * RATE_HZ, controller.safety.gap_limit))

    rig.hal.open()
    try:
        result = rig.loop(controller, on_cycle=watch).run(acquire_rt=False)
    finally:
        rig.close()
    t = np.array(plant_log["time"])
    d = np.array(plant_log["deflection"])
    v = np.array(plant_log["voltages"])
    assert t[-1] >= HOLD_S, f"the emulator stopped at {t[-1]:.3f} s of plant time ({result.reason})"
    assert np.all(v >= 0.0) and np.all(v <= 150.0), "a stack voltage left [0, 150] V"
    assert d[0] > 0.5e-3, "starts from the uncontrolled equilibrium at 3000 N (0.77 mm)"
    held = d[t >= 1.0]
    # 0.03 mm: the integral action zeroes the gauge strains; what is left is noise and the
    # part of the bow-driven deflection the gauges cannot see (tens of micrometres)
    assert held.max() < 0.03e-3, f"deflection in the second second up to {held.max() * 1e3:.4f} mm"
    assert result.fault == Fault.STALE_INPUT.name, result.reason
    silent, gap = at_fault[0]
    cap = shipped_limits(3000.0)[:, 0].max()
    assert 1 <= gap <= cap, (
        f"live gap limit {gap} samples at the fault: the table's growth against the measured spreads "
        f"gives 1 to its cap {cap:g} (tests/rt/test_engine.py checks its value)")
    # the loop's read time-outs end at the deadline (and a tenth of a period past it, if the
    # sum of the time-outs falls short of it by a rounding)
    assert gap + 1 <= silent <= gap + 1.1 + 1e-9, (
        f"stale-input fault after {silent:.2f} periods without a sample; due after {gap + 1}")
    assert result.hal["sequence_gaps"] == 0 and result.hal["out_of_range"] == 0
    assert controller.safety.late_answers == 0, "on the rig's clock an answer takes no time"
    assert rig.emulator.missed_answers == 0, "every sample was answered (lockstep)"


class GarbageDaq:
    """Another node on the bus that copies each strain frame it sees into bad ones carrying 9e-4
    strains (ten times what the held beam shows): as an extended frame, as a remote frame, with
    a wrong CRC, with the same sequence (a repeat, CRC right), three samples behind (CRC right),
    and on an unknown identifier. It answers in the emulator's thread after each plant step
    (``after_step``), so its frames for a sample reach the controller after that sample and
    before the next one, whatever this machine's scheduling."""

    STRAIN = 9e-4
    KINDS = ("extended_ids", "remote_frames", "crc_errors", "sequence_repeated", "sequence_behind",
             "unknown_ids")

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.sent = dict.fromkeys(self.KINDS, 0)
        self._values = [0.0] * len(CONTRACT.strains.names)

    def _frame(self, seq: int, good_crc: bool = True) -> bytes:
        data = bytearray(CONTRACT.strains.encode([self.STRAIN] * 4 + [seq & 0xFF, 0]))
        if not good_crc:
            data[-1] ^= 0xA5
        return bytes(data)

    def after_step(self, plant, voltages) -> None:
        strains_id = CONTRACT.strains.frame_id
        while (msg := self.bus.recv(0.0)) is not None:
            if msg.arbitration_id != strains_id or msg.is_extended_id:
                continue
            CONTRACT.strains.decode_into(msg.data, self._values)
            seq = int(self._values[CONTRACT.strains.index("sequence")])
            kind = self.KINDS[seq % 6]
            if kind == "extended_ids":
                frame = can.Message(arbitration_id=strains_id, data=self._frame(seq + 1), is_extended_id=True)
            elif kind == "remote_frames":
                frame = can.Message(arbitration_id=strains_id, is_remote_frame=True, dlc=8,
                                    is_extended_id=False)
            elif kind == "crc_errors":
                frame = can.Message(arbitration_id=strains_id, data=self._frame(seq + 1, good_crc=False),
                                    is_extended_id=False)
            elif kind == "sequence_repeated":
                frame = can.Message(arbitration_id=strains_id, data=self._frame(seq), is_extended_id=False)
            elif kind == "sequence_behind":
                frame = can.Message(arbitration_id=strains_id, data=self._frame(seq - 3),
                                    is_extended_id=False)
            else:
                frame = can.Message(arbitration_id=0x1F0, data=bytes(8), is_extended_id=False)
            self.bus.send(frame)
            self.sent[kind] += 1

    def close(self) -> None:
        self.bus.shutdown()


def test_garbage_on_the_bus_never_reaches_the_law_and_does_not_stop_control(tmp_path):
    """Bad frames of every kind beside the DAQ's good ones: the controller runs on undisturbed,
    no bad frame's 9e-4 strain ever appears in the telemetry (what the law saw), each is counted
    as what it is (all but those sent after the last sample the loop read), and the DAQ's last
    word from the controller is STOPPED."""
    garbage = None
    rig = CanRig(load={"start": 2000.0, "end": 2000.0}, answer_timeout_s=LOCKSTEP_TIMEOUT_S,
                 on_step=lambda plant, v: garbage.after_step(plant, v))
    garbage = GarbageDaq(rig.hal.channel)
    controller = Controller(TABLE, SHIPPED)
    telemetry = TelemetryWriter.for_controller(tmp_path / "garbage.btl", controller).start()
    rig.hal.open()
    try:
        result = rig.loop(controller, telemetry=telemetry, max_cycles=3000).run(acquire_rt=False)
        # the emulator, waiting for the next answer, takes the status frame the loop ended with
        wait_until(lambda: rig.emulator.last_state == State.STOPPED, "the DAQ hearing STOPPED")
        missed = rig.emulator.missed_answers    # before the stop gives up on the next sample's
    finally:
        rig.close()
        garbage.close()
    assert result.state == "STOPPED" and result.stop_requested_by == "cycle limit", result.reason
    _, records = read_telemetry(tmp_path / "garbage.btl")
    strains = records[:, [COL[f"strain_{c}"] for c in ("y1", "z1", "y2", "z2")]]
    assert np.abs(strains).max() < 0.5 * GarbageDaq.STRAIN, (
        f"a strain of {np.abs(strains).max():.2e} reached the law: a bad frame got through")
    answered = (records[:, COL["flags"]].astype(int) & FLAG_NO_NEW_SAMPLE) == 0
    sequences = records[answered, COL["sequence"]]
    steps = np.diff(sequences) % 256
    assert np.all(steps == 1), f"the law saw sequence steps {sorted(set(steps.tolist()))}, not one each"
    h = result.hal
    assert sum(garbage.sent.values()) > 3000, f"only {sum(garbage.sent.values())} bad frames were sent"
    for kind, sent in garbage.sent.items():
        # the loop reads a sample's bad frames with the next sample: the last sample's go unread
        assert sent - 1 <= h[kind] <= sent, f"{kind}: {h[kind]} counted of {sent} sent"
    assert h["samples_missed"] == 0 and h["sequence_implausible"] == 0 and h["sequence_resyncs"] == 0
    assert controller.safety.late_answers == 0 and missed == 0


def test_samples_queued_before_the_first_read_are_discarded_and_counted(tmp_path):
    """The DAQ streams from the moment the bus is open (wallclock pace); what queued before the
    loop was ready (here at least 150 samples) is dropped unanswered: the loop arms on the
    newest of them, and the first sample it answers after that is the one that follows it,
    never one of the backlog; a sample skipped later (the newest after a stall) is counted."""
    backlog = 150
    rig = CanRig(pace="wallclock", load={"start": 1000.0, "end": 1000.0})
    controller = Controller(TABLE, SHIPPED)
    telemetry = TelemetryWriter.for_controller(tmp_path / "backlog.btl", controller).start()
    rig.hal.open()
    try:
        rig.wait_sent(backlog)
        result = rig.loop(controller, telemetry=telemetry, max_cycles=200).run(acquire_rt=False)
    finally:
        rig.close()
    assert result.state == "STOPPED", result.reason
    # every sample queued was complete (the load comes first, with sample 0): all but the newest
    # were dropped, and the newest armed the controller
    assert result.backlog_discarded >= backlog - 1, (
        f"{result.backlog_discarded} samples discarded with {backlog} or more queued")
    assert result.hal["backlog_discarded"] == result.backlog_discarded
    _, records = read_telemetry(tmp_path / "backlog.btl")
    answered = records[(records[:, COL["flags"]].astype(int) & FLAG_NO_NEW_SAMPLE) == 0]
    sequences = answered[:, COL["sequence"]]
    # the first sample answered after arming follows the newest queued; any that came while the
    # controller armed (wallclock pace) are skipped for the newest and counted as held
    first_skip = (sequences[0] - result.backlog_discarded - 1) % 256
    assert first_skip < 64 and answered[0, COL["held_samples"]] >= first_skip, (
        f"the first sample answered after arming is {sequences[0]:.0f}, the newest queued was "
        f"{result.backlog_discarded}: {first_skip} skipped, "
        f"{answered[0, COL['held_samples']]:.0f} counted as held")
    # after arming, a stall of this process (wallclock pace, a busy machine) lets samples queue:
    # the newest is answered and the ones skipped count as the time the stacks held their voltage
    # (the stall is measured while the law runs: before it starts the stacks are at bias)
    jump = np.diff(sequences) % 256 - 1
    held = answered[1:, COL["held_samples"]]
    running = answered[1:, COL["state"]] == State.RUNNING.value
    short = running & (held < jump)
    assert not short.any(), (
        f"samples skipped while running without being counted as held: jumps {jump[short][:5]}, "
        f"held {held[short][:5]}")
    assert running.sum() > 100, f"the law ran for only {running.sum()} of 200 samples"


def test_a_daq_waiting_for_its_first_answer_gets_it_though_the_backlog_is_discarded():
    """A lockstep DAQ sends one sample and waits for its answer: that sample, queued before the
    loop starts, is the newest of the backlog and is answered, not dropped (dropping it would
    leave both sides waiting until a time-out)."""
    rig = CanRig(load={"start": 1000.0, "end": 1000.0}, answer_timeout_s=LOCKSTEP_TIMEOUT_S)
    controller = Controller(TABLE, SHIPPED)
    rig.hal.open()
    try:
        rig.wait_sent(1)                        # sample 0 is queued, the emulator waits for its answer
        result = rig.loop(controller, max_cycles=50).run(acquire_rt=False)
        missed = rig.emulator.missed_answers    # before the stop gives up on the next sample's
    finally:
        rig.close()
    assert result.state == "STOPPED", result.reason
    assert result.backlog_discarded == 0 and missed == 0


def test_a_streak_of_late_answers_beyond_the_table_s_limit_faults():
    """Over CAN, answers that take longer than the delay the table's loop tolerates (its answer
    budget's margin over the design's delay, twice) from their sample's arrival to having been
    sent (made so on the rig's clock): a streak as long as the table's late-answer limit is ridden
    through, each late answer counted; the answer that makes the next streak one longer than the
    limit faults LATE_ANSWERS."""
    first = 1000                    # well after the fade-in
    plan = {}
    controller = None

    def delay(k: int) -> float:
        if k == first:              # the limits in use at the load reached
            limit = controller.safety.late_limit
            plan.update(limit=limit, budget_s=controller.safety.answer_budget_s,
                        late=set(range(first + 1, first + 1 + limit))
                        | set(range(first + limit + 2, first + 2 * limit + 3)))
        if k in plan.get("late", ()):
            design = TABLE.design.io.delay_samples / RATE_HZ
            tolerated = max(plan["budget_s"], design + 2.0 * (plan["budget_s"] - design))
            return tolerated + 0.5 / RATE_HZ
        return 0.0

    rig = CanRig(answer_timeout_s=LOCKSTEP_TIMEOUT_S, answer_delay_s=delay)
    controller = Controller(TABLE, SHIPPED)
    faulted = []

    def watch(loop):
        if controller.supervisor.fault != Fault.NONE and not faulted:
            faulted.append((rig.hal.samples_read - 1, controller.safety.late_answers))

    rig.hal.open()
    try:
        # bounded: a loop that does not fault ends and says so instead of running on
        result = rig.loop(controller, on_cycle=watch, max_cycles=first + 2000).run(acquire_rt=False)
    finally:
        rig.close()
    assert result.fault == Fault.LATE_ANSWERS.name, result.reason
    limit = plan["limit"]
    limits = shipped_limits(1500.0)
    assert any(1 <= limit <= row[1] and np.isclose(row[2], plan["budget_s"] * RATE_HZ, rtol=1e-12, atol=0)
               for row in limits), (
        f"late-answer limit {limit}, budget {plan['budget_s'] * RATE_HZ:g} periods: not the table's "
        f"at 1500 N")
    sample, late_answers = faulted[0]
    due = first + 2 * limit + 2
    assert sample == due, (
        f"the late answer to sample {sample} faulted; due at sample {due} ({limit} ridden through)")
    assert late_answers == 2 * limit + 1, f"{late_answers} late answers counted"
