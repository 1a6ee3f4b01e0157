"""Test rigs: the sim backend, and the CAN backend talking to the plant emulator over
python-can's virtual bus (each rig on its own channel)."""

from __future__ import annotations

import itertools

import can

from beamctl.gains.defaults import paper_table_path
from beamctl.gains.table import load_table
from beamctl.hal.can_backend import CanBackend
from beamctl.hal.emulator import CanPlantEmulator
from beamctl.hal.sim import SimBackend
from beamctl.models import build_model
from beamctl.models.plant import Plant, plant_config
from beamctl.rt.allocation import geometry
from beamctl.rt.config import controller_config

_channels = itertools.count()
# The safety settings of a controller whose DAQ is an emulator in the same interpreter or a
# process beside it on this shared 2-core machine. Its thread or process can be held up for tens
# to hundreds of milliseconds (a virtual machine whose hypervisor takes a quarter to a half of its
# CPU time at times: `vmstat`'s st), and the tests are about a DAQ that falls silent or a
# controller that answers late for good, not about the machine's scheduling. So:
# - 1000 periods of time without a valid sample before the stale-input fault (0.4 s at 2500 Hz;
#   the shipped default, 5, is for a DAQ on its own hardware);
# - a latency budget of 100 periods (the most the config takes) and a streak of 1000 late answers
#   before that fault (the samples queued during a hold-up are all answered late).
IN_PROCESS_STALE_PERIODS = 1000
IN_PROCESS_SAFETY = {"stale_periods": IN_PROCESS_STALE_PERIODS, "answer_budget_periods": 100.0,
                     "late_answer_streak": 1000}
TABLE = load_table(paper_table_path())
MODEL = build_model(TABLE.model_parameters)
GEOMETRY = geometry(controller_config().actuators)


def make_plant(**overrides) -> Plant:
    settings = {"sample_rate_hz": TABLE.design.sample_rate_hz, "load": {"start": 1500.0, "end": 1500.0},
                "bow": {"amplitude": 5e-5, "angle_deg": 234.0}, "noise": {"strain": 2e-7, "load": 1.0}}
    settings.update(overrides)
    return Plant(MODEL, plant_config(settings))


class SimRig:
    name = "sim"

    def __init__(self, **plant_overrides) -> None:
        self.plant = make_plant(**plant_overrides)
        self.hal = SimBackend(self.plant, GEOMETRY)

    def silence(self) -> None:
        self.hal.go_silent()

    def close(self) -> None:
        self.hal.close()


class _RigBackend(CanBackend):
    """The CAN backend of a rig: the first open starts the emulator, so that no sample is sent
    before the controller listens (the virtual bus drops frames nobody receives)."""

    def __init__(self, emulator: CanPlantEmulator, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._emulator = emulator

    def _open(self) -> None:
        super()._open()
        if not self._emulator.running:
            self._emulator.start()


class CanRig:
    name = "can"

    def __init__(self, pace: str = "lockstep", latency_samples: int = 0, on_step=None,
                 answer_timeout_s: float = 0.05, **plant_overrides) -> None:
        channel = f"beamctl-test-{next(_channels)}"
        self.plant = make_plant(**plant_overrides)
        self.emulator_bus = can.Bus(interface="virtual", channel=channel)
        self.emulator = CanPlantEmulator(self.emulator_bus, self.plant, GEOMETRY, pace=pace,
                                         answer_timeout_s=answer_timeout_s,
                                         latency_samples=latency_samples, on_step=on_step)
        # lockstep runs at the controller's pace, not the DAQ's 2500 Hz: no rate check
        self.hal = _RigBackend(self.emulator, TABLE.design.sample_rate_hz, "virtual", channel,
                               rate_tolerance=0.0 if pace == "lockstep" else 0.05)

    def silence(self) -> None:
        self.emulator.stop()

    def close(self) -> None:
        self.emulator.stop()
        self.hal.close()
        self.emulator_bus.shutdown()


RIGS = {"sim": SimRig, "can": CanRig}
