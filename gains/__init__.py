"""Gain design, the one controller form (a scheduled state-space compensator), gain table
files and the gain schedule.

Turns a model (models/) into a gain table file offline and reads it back, validated, for the
real-time loop (rt/).
"""

from beamctl.gains.compensator import Compensator, CompensatorPoint
from beamctl.gains.discrete import LoopCheck, VelocityFilter, velocity_filter
from beamctl.gains.lqr import Weights, augmented_system, lqr_gain
from beamctl.gains.ridethrough import RideThrough
from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import (
    DesignSettings,
    GainTable,
    GainTableError,
    ScheduleSettings,
    load_table,
    write_table,
)

__all__ = [
    "Compensator",
    "CompensatorPoint",
    "DesignSettings",
    "GainSchedule",
    "GainTable",
    "GainTableError",
    "LoopCheck",
    "RideThrough",
    "ScheduleSettings",
    "VelocityFilter",
    "Weights",
    "augmented_system",
    "load_table",
    "lqr_gain",
    "velocity_filter",
    "write_table",
]
