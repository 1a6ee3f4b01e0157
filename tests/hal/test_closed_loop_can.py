"""Acceptance: the rt controller with the default gain table holds the simulated beam at
3000 N over virtual CAN, and reaches its safe state when the DAQ falls silent."""

import time

import numpy as np

from beamctl.rt.config import controller_config
from beamctl.rt.controller import Controller
from beamctl.rt.loop import ControlLoop
from beamctl.rt.safety import Fault, State
from tests.hal.rigs import TABLE, CanRig


def test_beam_held_straight_at_3000_N_then_safe_when_the_daq_stops():
    rig = CanRig(load={"start": 3000.0, "end": 3000.0}, bow={"amplitude": 5e-5, "angle_deg": 234.0})
    # 25 periods (15 ms with the 1.5-period read time-out): the emulator shares this process's
    # interpreter, so a shorter budget would fault on a thread hand-off rather than a silent DAQ
    config = controller_config({"pacing": "sample", "safety": {"stale_periods": 25}})
    controller = Controller(TABLE, config)
    plant = rig.plant
    log = {"deflection": [], "voltages": [], "stopped_at": None, "fault_at": None}

    def watch(loop):
        if log["stopped_at"] is None:
            log["deflection"].append((plant.time, plant.deflection()[0]))
            log["voltages"].append(controller.voltages.copy())
            if plant.time >= 2.0:
                rig.silence()
                log["stopped_at"] = time.monotonic()
        elif log["fault_at"] is None and controller.state == State.FAULT:
            log["fault_at"] = time.monotonic()

    rig.hal.open()
    try:
        result = ControlLoop(controller, rig.hal, on_cycle=watch).run(acquire_rt=False)
    finally:
        rig.close()
    t, d = np.array(log["deflection"]).T
    v = np.array(log["voltages"])
    assert t[-1] >= 2.0 and np.all(v >= 0.0) and np.all(v <= 150.0)
    assert d[0] > 0.5e-3, "starts from the uncontrolled equilibrium at 3000 N (0.77 mm)"
    held = d[t >= 1.0]
    assert held.max() < 0.03e-3, f"deflection in the second second up to {held.max() * 1e3:.4f} mm"
    assert result.fault == Fault.STALE_INPUT.name, result.reason
    stale_time = config.safety.stale_periods * 1.5 * controller.period   # read time-out 1.5 T
    assert log["fault_at"] - log["stopped_at"] < stale_time + 0.05, (
        f"safe state {1e3 * (log['fault_at'] - log['stopped_at']):.1f} ms after the DAQ stopped")
    assert result.hal["sequence_gaps"] == 0 and result.hal["out_of_range"] == 0
