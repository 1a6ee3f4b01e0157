"""How a run is put together: the service configuration shared by ``beamctl run``, ``plant``,
``experiment``, identification, commissioning and the benchmarks, and the builders that turn it
into a model, gain table, controller, plant and HAL (the lab service, service/, is one of the
runs put together here).

One YAML file, every section optional, every key checked::

    model:      partial model parameters (the model the gains are designed for), or the path of
                a model file (model parameters, or a file with a model: section such as the
                output of `beamctl model fit`)
    gains:      {table: path}            (default: the shipped gains/default.yaml)
    controller: rt settings               (rt/config.py)
    hal:        backend and its settings  (hal/config.py)
    plant:      the simulated beam: plant settings (models/plant.py) and ``model:``, its own
                beam parameters when it should differ from the controller's model
    run:        {telemetry: path, duration_s: seconds to run (0: until stopped)}
    control:    {socket: path of the control socket (default: service/control.py
                default_socket_path)}
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from beamctl import hal
from beamctl.config.schema import ConfigError, merge, nonnegative, path, read_yaml, refuse_renamed, validate
from beamctl.gains.defaults import default_table_path
from beamctl.gains.table import GainTable, load_table
from beamctl.hal.base import HalBase
from beamctl.hal.config import HalConfig, hal_config
from beamctl.models import build_model
from beamctl.models.actuators import StackGeometry
from beamctl.models.params import ModelParameters, parameters_from_dict
from beamctl.models.plant import Plant, PlantConfig, plant_config
from beamctl.rt.allocation import geometry
from beamctl.rt.config import ControllerConfig, controller_config

SECTIONS = ("model", "gains", "controller", "hal", "plant", "run", "control")
# Keys renamed to carry their unit: a file that still sets an old one is refused, naming the new.
RENAMED_RUN_KEYS = {"duration": "duration_s"}


@dataclass(frozen=True)
class ServiceConfig:
    source: str
    model: ModelParameters
    table_path: Path
    controller: ControllerConfig
    hal: HalConfig
    plant: dict = field(default_factory=dict)          # plant settings (validated when built)
    plant_model: dict = field(default_factory=dict)    # the plant's own parameter overrides
    telemetry: str = ""
    duration_s: float = 0.0
    control_socket: str = ""                           # "": the default path


def _section(data: dict, name: str, source: str) -> dict:
    value = data.get(name) or {}
    if not isinstance(value, dict):
        raise ConfigError(name, value, "a mapping of keys to values", source)
    return value


def service_config(data: dict | None = None, source: str = "") -> ServiceConfig:
    data = data or {}
    unknown = sorted(set(data) - set(SECTIONS))
    if unknown:
        raise ConfigError(unknown[0], data[unknown[0]], f"one of the sections {list(SECTIONS)}", source)
    if isinstance(data.get("model"), str):
        model_overrides = model_file_overrides(data["model"], f"{source}: model" if source else "model")
    else:
        model_overrides = _section(data, "model", source)
    try:
        params = parameters_from_dict(model_overrides, source)
    except ConfigError as exc:
        raise ConfigError(f"model.{exc.key}", exc.value, exc.expected, source) from None
    gains = validate({"table": "", **_section(data, "gains", source)}, {"table": path()}, source, "gains.")
    table = Path(gains["table"]) if gains["table"] else default_table_path()
    run_section = _section(data, "run", source)
    refuse_renamed(run_section, RENAMED_RUN_KEYS, source, "run.")
    run = validate({"telemetry": "", "duration_s": 0.0, **run_section},
                   {"telemetry": path(), "duration_s": nonnegative("s")}, source, "run.")
    plant = dict(_section(data, "plant", source))
    plant_model = plant.pop("model", None) or {}
    if not isinstance(plant_model, dict):
        raise ConfigError("plant.model", plant_model, "a mapping of model parameters", source)
    control = validate({"socket": "", **_section(data, "control", source)}, {"socket": path()}, source,
                       "control.")
    controller = controller_config(_section(data, "controller", source), source, "controller.")
    hal = hal_config(_section(data, "hal", source), source)
    if hal.backend == "can" and controller.pacing == "timer":
        raise ConfigError("controller.pacing", "timer",
                          "'sample' with the can backend: the DAQ streams at its own clock, and a "
                          "timer of the PC's would let frames queue up and add delay", source)
    return ServiceConfig(
        source=source, model=params, table_path=table, controller=controller, hal=hal, plant=plant,
        plant_model=plant_model, telemetry=run["telemetry"], duration_s=run["duration_s"],
        control_socket=control["socket"])


def model_file_overrides(path: str | Path, what: str = "--config") -> dict:
    """The model parameters a file gives: a model parameter file (keys beam, supports, ...), or
    a configuration with a ``model:`` mapping (a rig's service config, the output of `beamctl
    model fit`), whose other sections are checked as a service config's."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(what, str(path), "an existing model or service configuration file")
    data = read_yaml(p)
    if isinstance(data, dict) and set(data) & set(SECTIONS):
        section = data.get("model")
        if not isinstance(section, dict):
            raise ConfigError("model", section, "a mapping of model parameters (this file has service "
                              "sections but no model section to take the model from)", str(p))
        service_config({k: v for k, v in data.items() if k != "model"}, str(p))
        return section
    return data or {}


def load_model_file(path: str | Path | None, what: str = "--config") -> ModelParameters:
    """Model parameters over the paper's Table 1 from either kind of file (``model_file_overrides``;
    ``what`` names the flag in messages); None: the paper's defaults."""
    if path is None:
        return parameters_from_dict({}, "paper defaults")
    return parameters_from_dict(model_file_overrides(path, what), str(path))


def load_service_config(path: str | Path | None) -> ServiceConfig:
    if path is None:
        return service_config({}, "defaults")
    return service_config(read_yaml(path), str(path))


def load_gain_table(cfg: ServiceConfig, path: str | Path | None = None) -> GainTable:
    """The configured table (or the one at ``path``, which an operator asks the running service
    to swap in), refused unless designed for exactly the configured model, its content matches
    its SHA-256, and its closed-loop check is there and passed."""
    table_path = cfg.table_path if path is None else Path(path)
    if not table_path.is_file():
        raise ConfigError("gains.table" if path is None else "table", str(table_path),
                          f"an existing gain table file (relative paths are taken from the current "
                          f"directory; build one with `beamctl gains build --out {table_path}`)",
                          cfg.source if path is None else "")
    return load_table(table_path, cfg.model)


def plant_geometry(cfg: ServiceConfig) -> StackGeometry:
    """The rig the plant has: the controller's belief, or the plant's own actuators."""
    if cfg.hal.sim["own_actuators"]:
        a = cfg.hal.sim["actuators"]
        return StackGeometry(a["force_constant_n_per_v"], a["bias_voltage_v"], tuple(a["orientation_deg"]))
    return geometry(cfg.controller.actuators)


def plant_parameters(cfg: ServiceConfig) -> ModelParameters:
    """The simulated beam's parameters: ``plant.model`` over the controller's model (or that
    model itself)."""
    if not cfg.plant_model:
        return cfg.model
    try:
        return parameters_from_dict(merge(cfg.model.to_dict(), cfg.plant_model), cfg.source)
    except ConfigError as exc:
        raise ConfigError(f"plant.model.{exc.key}", exc.value, exc.expected, cfg.source) from None


# the simulated DAQ's clock may be off the table's rate by this much (the robust check's box: 1 %)
PLANT_RATE_TOLERANCE = 0.05


def plant_settings(cfg: ServiceConfig, table: GainTable,
                   overrides: dict[str, Any] | None = None) -> PlantConfig:
    """The plant section (with ``overrides``) validated at the gain table's rate: by default the
    plant is sampled at that rate; ``plant.sample_rate_hz`` within PLANT_RATE_TOLERANCE of it is
    a rig whose DAQ clock is off (the plant advances by its own period a sample, the controller
    computes with the table's). The simulated rig has the I/O chain the table's design
    declares (its delay, its anti-alias filter) except where ``plant.io`` says otherwise."""
    sample_rate_hz = table.design.sample_rate_hz
    data = {"sample_rate_hz": sample_rate_hz, **cfg.plant, **(overrides or {})}
    io = data.get("io")
    data["io"] = {**table.design.io.to_dict(), **io} if isinstance(io, dict) else (
        table.design.io.to_dict() if io is None else io)
    pc = plant_config(data, cfg.source, "plant.")
    if abs(pc.sample_rate_hz / sample_rate_hz - 1.0) > PLANT_RATE_TOLERANCE:
        raise ConfigError("plant.sample_rate_hz", pc.sample_rate_hz,
                          f"the gain table's sample rate {sample_rate_hz:g} Hz, or within "
                          f"{PLANT_RATE_TOLERANCE:.0%} of it (a DAQ whose clock is off)", cfg.source)
    return pc


def build_plant(cfg: ServiceConfig, table: GainTable, overrides: dict[str, Any] | None = None) -> Plant:
    """The simulated beam: the plant section over the controller's model (or its own beam)."""
    pc = plant_settings(cfg, table, overrides)
    return Plant(build_model(plant_parameters(cfg)), pc)


def build_hal(cfg: ServiceConfig, table: GainTable, plant: Plant | None = None) -> HalBase:
    """The configured backend (not yet open), built by the HAL's factory (``hal.create``). The
    sim backend gets ``plant`` (or builds one)."""
    if cfg.hal.backend == "sim":
        return hal.create("sim", plant=plant or build_plant(cfg, table), geometry=plant_geometry(cfg),
                          pace=cfg.hal.sim["pace"])
    c = cfg.hal.can
    return hal.create("can", sample_rate_hz=table.design.sample_rate_hz, interface=c["interface"],
                      channel=c["channel"], bitrate_bit_s=c["bitrate_bit_s"], fd=c["fd"],
                      data_bitrate_bit_s=c["data_bitrate_bit_s"], dbc=c["dbc"] or None,
                      record=c["record"] or None, rate_tolerance=c["rate_tolerance"], spin_s=c["spin_s"])


def check_voltage_range(cfg: ServiceConfig, hal: HalBase) -> None:
    """The controller's voltage range must be one the HAL's DBC can carry (backends without a
    DBC: any)."""
    contract = getattr(hal, "contract", None)
    if contract is None:
        return
    signal_range = contract.voltages.signals[0]
    a = cfg.controller.actuators
    for key, value in (("min_voltage_v", a.min_voltage_v), ("max_voltage_v", a.max_voltage_v),
                       ("bias_voltage_v", a.bias_voltage_v)):
        if not signal_range.minimum <= value <= signal_range.maximum:
            raise ConfigError(f"controller.actuators.{key}", value,
                              f"a voltage the DBC's {contract.voltages.name} carries "
                              f"([{signal_range.minimum:g}, {signal_range.maximum:g}] V)", cfg.source)
