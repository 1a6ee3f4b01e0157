"""The CAN plant emulator in lockstep: each plant step applies the answer to its own sample."""

import can
import numpy as np

from beamctl.hal.dbc import Contract
from tests.hal.rigs import GEOMETRY, make_plant

CONTRACT = Contract()


def _answer(bus, sequence: int, volts: float) -> None:
    values = [volts] * 6 + [sequence & 0xF]      # volts: a multiple of the 0.15 V resolution
    bus.send(can.Message(arbitration_id=CONTRACT.voltages.frame_id,
                         data=CONTRACT.voltages.encode(values), is_extended_id=False))


def _next_strain_sequence(bus) -> int:
    values = [0.0] * len(CONTRACT.strains.names)
    while True:
        msg = bus.recv(5.0)
        assert msg is not None, "the emulator sent no sample"
        if msg.arbitration_id == CONTRACT.strains.frame_id:
            CONTRACT.strains.decode_into(msg.data, values)
            return int(values[CONTRACT.strains.index("sequence")])


def test_a_late_answer_is_applied_but_never_taken_for_the_next_sample_s_answer():
    """Sample 1 is answered after the emulator gave up on it: the plant steps once with the
    voltages it had (a missed answer), and the late answer, arriving while the emulator waits
    for sample 2's, does not end that wait; sample 2's own answer is what its step applies."""
    from beamctl.hal.emulator import CanPlantEmulator

    steps = []
    emulator_bus = can.Bus(interface="virtual", channel="emulator-late")
    controller_bus = can.Bus(interface="virtual", channel="emulator-late")
    emulator = CanPlantEmulator(emulator_bus, make_plant(), GEOMETRY, pace="lockstep",
                                answer_timeout_s=2.0,
                                on_step=lambda plant, v: steps.append(v.copy()))
    try:
        emulator.start(max_samples=3)
        assert _next_strain_sequence(controller_bus) == 0
        _answer(controller_bus, 0, 90.0)
        assert _next_strain_sequence(controller_bus) == 1     # sample 1: no answer in time
        assert _next_strain_sequence(controller_bus) == 2
        _answer(controller_bus, 1, 105.0)                    # late, for sample 1
        _answer(controller_bus, 2, 60.0)
        emulator.join(timeout=5.0)
    finally:
        emulator.stop()
        emulator_bus.shutdown()
        controller_bus.shutdown()
    assert emulator.missed_answers == 1
    np.testing.assert_array_equal([s[0] for s in steps], [90.0, 90.0, 60.0])
