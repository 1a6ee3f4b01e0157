"""The telemetry record: one row per sample, written by the engine's compiled cycle (its layout,
``RECORD_COLUMNS`` and the ``I_*`` indices, is the engine's: rt/engine.py), and what a reader
needs to understand it: each column's unit, the labels of the coded columns (state, fault, the
operator's commands) and of the flag bits, the flags that trigger a recording's window, and the
settings a recording is read with (``controller_meta``). The layout's names (``COL``, ``I_*``,
``FLAG_*``) are imported from rt/engine.py (rt/controller.py re-exports them for readers). The
law's input vector is not read from these columns by name: the engine keeps its own indices
(``SIGNAL_COLUMNS``).
"""

from __future__ import annotations

from beamctl.rt.config import settings_by_key
from beamctl.rt.engine import FLAG_NAMES, FLAG_SATURATED_A, FLAG_SATURATED_B, RECORD_COLUMNS  # noqa: F401
from beamctl.rt.safety import OPERATOR_COMMANDS, Fault, State

# the flags that start a triggered recording's window (with any change of a coded column)
TRIGGER_FLAGS = FLAG_SATURATED_A | FLAG_SATURATED_B


# in the telemetry's operator_command column the i-th of the operator's commands
# (rt/safety.py's OPERATOR_COMMANDS) is 2 i + 1 when carried out and 2 i + 2 when refused (0: no
# command at that sample)


def operator_code(command: str, carried_out: bool) -> int:
    """The ``operator_command`` code of ``command`` carried out or refused."""
    return 2 * OPERATOR_COMMANDS.index(command) + (1 if carried_out else 2)


def operator_labels() -> dict[int, str]:
    """{code: label} of the telemetry's ``operator_command`` column: 0 "none", 1 "start",
    2 "start refused", 3 "stop", ..."""
    labels = {0: "none"}
    for name in OPERATOR_COMMANDS:
        labels[operator_code(name, True)] = name
        labels[operator_code(name, False)] = f"{name} refused"
    return labels


# Units of the columns whose names do not end in one (``load_N``, ``voltage_a1_V``, ``step_us``,
# ``time_s`` do): strains are m/m, the modal coordinates of the mass-normalised modes (eq. 15)
# m sqrt(kg), their integrals m sqrt(kg) s. Codes, counts and fractions have none.
_UNIT_SUFFIXES = {"_N": "N", "_V": "V", "_us": "us", "_s": "s"}
_UNIT_PREFIXES = {"strain_": "m/m", "q_": "m*sqrt(kg)", "xi_": "m*sqrt(kg)*s"}


def code_labels() -> dict[str, dict[int, str]]:
    """The record's coded columns and the label of each code: {column: {code: label}}."""
    return {"state": {int(s): s.name for s in State}, "fault": {int(f): f.name for f in Fault},
            "operator_command": operator_labels()}


def flag_labels() -> dict[str, dict[int, str]]:
    """The record's bit-field columns and the label of each bit: {column: {bit: label}}."""
    return {"flags": dict(FLAG_NAMES)}


def column_unit(column: str) -> str:
    """The unit of a record column ("" for codes, counts and fractions)."""
    for prefix, unit in _UNIT_PREFIXES.items():
        if column.startswith(prefix):
            return unit
    for suffix, unit in _UNIT_SUFFIXES.items():
        if column.endswith(suffix):
            return unit
    return ""


def controller_meta(controller) -> dict:
    """The settings a recording is read with: the sample rate, the controller's settings
    (allocation, actuators, safety limits), the gain table's design and its model's parameters
    (a reader turns modal displacements into millimetres with them)."""
    table = controller.table
    design = table.design
    return {"sample_rate_hz": controller.sample_rate_hz,
            "controller": settings_by_key(controller.config),
            "design": {"kind": design.kind, "sample_rate_hz": design.sample_rate_hz,
                       "schedule": table.schedule.mode, "loads_n": [float(table.loads_n[0]),
                                                                     float(table.loads_n[-1])]},
            "model": table.model_parameters.to_dict()}
