"""What a service configuration would run, checked without starting the service: the gain table
(its file, hash, design, closed-loop check, ride-through limits, robust result when the table
records one), the backend and its bus budget, the voltages, the control socket and the
telemetry file; and every reason ``beamctl run`` would refuse to start, each in one line.

The same set-up functions as the service (assembly/run.py) build what the service would build,
short of what changes the world: the HAL is built but not opened, the control socket is looked
at (a service answering there would make the run refuse) but not bound, the telemetry file's
folder is checked but nothing is written.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from beamctl.assembly.run import build_hal, check_voltage_range, load_gain_table, load_service_config
from beamctl.common.outputs import OutputPathError, check_new_file
from beamctl.config.schema import ConfigError
from beamctl.gains.robust import robust_text
from beamctl.hal.base import HalError
from beamctl.hal.can_backend import socketcan_problem
from beamctl.rt.controller import Controller
from beamctl.service.control import ControlError, default_socket_path, socket_place

TELEMETRY_DEFAULT = "beamctl-%Y%m%d-%H%M%S.btl"


@dataclass
class ConfigCheck:
    """``items``: (what, what the service would use) in the order a person reads them;
    ``refusals``: why the service would not start (empty: it would)."""

    config: str
    items: list[tuple[str, str]] = field(default_factory=list)
    refusals: list[str] = field(default_factory=list)
    data: dict[str, Any] = field(default_factory=dict)

    @property
    def would_start(self) -> bool:
        return not self.refusals

    def to_dict(self) -> dict[str, Any]:
        return {"config": self.config, "would_start": self.would_start, "refusals": self.refusals,
                **self.data}


def check_config(path: str | Path) -> ConfigCheck:
    """Everything ``beamctl run --config path`` would check before its loop starts, and what it
    would run (see the module docstring)."""
    out = ConfigCheck(config=str(path))
    try:
        cfg = load_service_config(path)
    except ConfigError as exc:
        out.refusals.append(str(exc))
        return out
    out.items.append(("config", f"{cfg.source}: {cfg.hal.backend} backend, {cfg.controller.pacing} pacing"))
    out.data.update(backend=cfg.hal.backend, pacing=cfg.controller.pacing,
                    model_sha256=cfg.model.digest())
    table = _table(cfg, out)
    if cfg.hal.backend == "can" and cfg.hal.can["interface"] == "socketcan":
        problem = socketcan_problem(cfg.hal.can["channel"])     # what opening the bus would meet
        if problem:
            out.refusals.append(f"{cfg.source}: hal.can.channel = {cfg.hal.can['channel']!r}: {problem}")
    if table is not None:
        _hal(cfg, table, out)
        try:
            Controller(table, cfg.controller)
        except (ConfigError, ValueError) as exc:
            out.refusals.append(f"controller: {exc}")
    a = cfg.controller.actuators
    out.items.append(("voltages", f"{a.min_voltage_v:g} to {a.max_voltage_v:g} V, bias "
                                  f"{a.bias_voltage_v:g} V, {a.force_constant_n_per_v:g} N/V a stack"))
    _socket(cfg, out)
    _telemetry(cfg, out)
    return out


def _table(cfg, out: ConfigCheck):
    path = Path(cfg.table_path)
    try:
        table = load_gain_table(cfg)
    except ConfigError as exc:
        out.refusals.append(str(exc))
        out.items.append(("gain table", f"{path}: refused"))
        return None
    sha = table.sha256              # the content hash `beamctl run` records and `ctl status` reports
    d = table.design
    loads = table.loads_n
    out.items.append(("gain table", f"{path.resolve()}"))
    out.items.append(("table sha256", f"{sha} (its content's, as `beamctl ctl status` reports it)"))
    out.items.append(("design", f"{d.kind} at {d.sample_rate_hz:g} Hz, {len(loads)} loads "
                                f"{loads[0]:g}..{loads[-1]:g} N, schedule {table.schedule.mode}; "
                                f"assumes {d.io.describe()}"))
    stable = table.all_stable
    out.items.append(("closed-loop check", "passed at every check point" if stable else "FAILED"))
    rt = table.ride_through
    if rt is not None:
        out.items.append(("ride-through", rt.describe(loads, d.sample_rate_hz)))
        out.items.append(("  per load", rt.reference_text(loads, d.sample_rate_hz)))
    else:
        out.items.append(("ride-through", "not analysed by this version (fixed limits: 5 samples, half a "
                                          "period); rebuild the table (`beamctl gains build`)"))
    robust = getattr(table, "robust", None)
    out.items.append(("robust check", robust_text(robust)))
    out.data.update(table={"path": str(path.resolve()), "sha256": sha, "design": d.kind,
                           "sample_rate_hz": d.sample_rate_hz, "loads_n": [float(loads[0]), float(loads[-1])],
                           "closed_loop_check_passed": bool(stable), "robust": robust})
    return table


def _hal(cfg, table, out: ConfigCheck) -> None:
    try:
        hal = build_hal(cfg, table)
    except (HalError, ConfigError, OSError) as exc:
        out.refusals.append(f"hal.{cfg.hal.backend}: {exc}")
        return
    try:
        check_voltage_range(cfg, hal)
    except ConfigError as exc:
        out.refusals.append(str(exc))
    budget = getattr(hal, "budget", None)
    if budget is not None:
        c = cfg.hal.can
        out.items.append(("bus", f"{c['interface']}:{c['channel']}, {budget.description}: "
                                 f"{100 * budget.load:.1f} % at {budget.sample_rate_hz:g} Hz "
                                 f"(at most {budget.max_sample_rate_hz:.0f} Hz within 80 %)"))
        out.data["bus_load"] = budget.load
    else:
        out.items.append(("bus", "none (the simulated rig in this process)"))
    close = getattr(hal, "close", None)
    if close is not None:
        try:
            close()
        except Exception:       # never opened: nothing to release
            pass


def _socket(cfg, out: ConfigCheck) -> None:
    path = Path(cfg.control_socket) if cfg.control_socket else default_socket_path()
    try:
        stale = socket_place(path, make_directory=False)       # the service's own checks, nothing made
    except ControlError as exc:
        out.refusals.append(str(exc))
        out.items.append(("control socket", f"{path} (refused)"))
        return
    state = "a socket left from an earlier run (the service replaces it)" if stale else "free"
    out.items.append(("control socket", f"{path} ({state})"))
    out.data["control_socket"] = str(path)


def _telemetry(cfg, out: ConfigCheck) -> None:
    name = cfg.telemetry or TELEMETRY_DEFAULT
    try:
        check_new_file(name, f"{cfg.source}: run.telemetry" if cfg.telemetry else "telemetry")
    except (ConfigError, OutputPathError) as exc:
        out.refusals.append(str(exc))
        return
    out.items.append(("telemetry", name if cfg.telemetry else f"{TELEMETRY_DEFAULT} here (no run.telemetry)"))
    out.data["telemetry"] = name
