"""A run's side of the live view: a publisher (rt/live.py) for a controller's records,
described for the page (labels of states, faults and flags, voltage limits, the table's load
range, the critical load) and extended by the deflection in metres, which the record does not
hold (the largest lateral deflection along the beam from q, as ``beamctl experiment``
measures it). The service, the simulated experiment and the benchmarks publish with it; where
the view's socket is by default is the service's (service/live.py ``default_live_path``)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from beamctl.models import build_model, critical_load
from beamctl.models.modal import Deflection
from beamctl.rt import controller as rec
from beamctl.rt.controller import Controller
from beamctl.rt.live import Derived, LivePublisher
from beamctl.rt.safety import DESCRIPTIONS, Fault, State

FLAGS = {"saturated_A": rec.FLAG_SATURATED_A, "saturated_B": rec.FLAG_SATURATED_B,
         "integrator_held": rec.FLAG_INTEGRATOR_HELD, "load_out_of_table": rec.FLAG_LOAD_OUT_OF_TABLE,
         "no_new_sample": rec.FLAG_NO_NEW_SAMPLE, "fading_in": rec.FLAG_FADING_IN,
         "ramping_to_bias": rec.FLAG_RAMPING_TO_BIAS}
DEFLECTION_COLUMNS = ("deflection_m", "deflection_y_m", "deflection_z_m")
def deflection_columns(controller: Controller) -> Derived:
    """The deflection of the controller's model from the records' q."""
    deflection = Deflection(build_model(controller.table.model_parameters))
    first = rec.COL["q_1y"]
    return Derived(DEFLECTION_COLUMNS, lambda rows: deflection.many(rows[:, first:first + 4]))


def live_publisher(path: str | Path, controller: Controller, label: str,
                   table_path: str | None = None) -> LivePublisher:
    """A publisher of ``controller``'s records to the viewer at ``path`` (``label``: what runs,
    and ``table_path``: the gain table it starts with, for the page's title). Close it after the
    run."""
    table = controller.table
    actuators = controller.config.actuators
    meta = {"label": label, "table": table_path, "schedule": table.schedule.mode,
            "table_loads_n": [float(table.loads_n[0]), float(table.loads_n[-1])],
            "critical_load_n": critical_load(build_model(table.model_parameters)),
            "voltage_limits_v": [actuators.min_voltage_v, actuators.max_voltage_v],
            "bias_voltage_v": actuators.bias_voltage_v,
            "states": {int(s): s.name for s in State},
            "faults": {int(f): f"{f.name}: {DESCRIPTIONS[f]}" for f in Fault}, "flags": FLAGS}
    return LivePublisher(path, rec.RECORD_COLUMNS, controller.sample_rate_hz, meta=meta,
                         derived=deflection_columns(controller))


def watch_loop(publisher: LivePublisher, loop, telemetry,
               table_path: Callable[[], str] | None = None) -> None:
    """Send the loop's counters with each datagram, and the gain table running now (its load
    range and schedule; its path from ``table_path`` if given): read in the writer's thread,
    plain values the loop updates, nothing the loop waits for. An operator's table swap shows on
    the page from the next datagram on."""
    timing = loop.timing
    controller = loop.controller

    def status() -> dict:
        table = controller.table        # one object: its loads and schedule belong together
        running = {"cycles": loop.cycles, "overruns": timing.overruns,
                   "missed_periods": timing.missed_periods, "telemetry_dropped": telemetry.dropped,
                   "schedule": table.schedule.mode,
                   "table_loads_n": [float(table.loads_n[0]), float(table.loads_n[-1])]}
        if table_path is not None:
            running["table"] = table_path()
        return running

    publisher.status = status


def summary(publisher: LivePublisher, telemetry) -> str:
    """One line for the run's report: what the view was sent, what it missed and why."""
    text = f"live view {publisher.path}: {publisher.sent} datagrams sent, {publisher.dropped} dropped"
    if publisher.dropped and publisher.last_error:
        text += f" (last: {publisher.last_error.lower()})"
    if telemetry.live_error:
        text += f"; switched off after an error: {telemetry.live_error}"
    return text

