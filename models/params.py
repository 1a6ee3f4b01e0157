"""Parameters of the beam-column with piezo-elastic supports (Table 1 of the paper).

The shipped default is ``models/paper.yaml``. A user file overrides it key by key; every
value is checked and a wrong one is refused with the dotted key, the value and what was
expected. SI units throughout.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from beamctl.config.schema import (
    ConfigError,
    integer,
    merge,
    number,
    number_list,
    plausible,
    read_yaml,
    validate,
)

PAPER_YAML = "paper.yaml"

# The strain-gauge rule depends on the beam length, so it is checked after the schema.
_SCHEMA = {
    "beam": {
        "length": plausible(0.05, 5.0, "m"),
        "radius": plausible(0.5e-3, 0.1, "m"),
        "density": plausible(500.0, 25000.0, "kg/m^3"),
        "youngs_modulus": plausible(1e9, 1e12, "N/m^2"),
        "proportional_limit": plausible(1e6, 1e10, "N/m^2"),
    },
    "extension": {
        "length": plausible(0.5e-3, 0.5, "m"),
        "radius": plausible(0.5e-3, 0.1, "m"),
        "density": plausible(500.0, 25000.0, "kg/m^3"),
        "youngs_modulus": plausible(1e9, 1e12, "N/m^2"),
    },
    "supports": {
        "rotational_stiffness": plausible(1e-3, 1e9, "N m/rad"),      # up to a clamped end
        "lateral_stiffness": plausible(1e2, 1e11, "N/m"),
        "actuator_stiffness": plausible(1e2, 1e11, "N/m"),
    },
"sensors": {
        "strain_gauge_positions": number_list(number("m"), 2, "gauge positions"),
        "max_condition_number": number(low=1.0, low_open=True),
    },
    "damping": {
        "ratios": number_list(number(low=0.0, high=1.0, low_open=True, high_open=True), 2,
                              "modal damping ratios"),
        "identification_load": plausible(0.0, 1e6, "N"),
    },
    "fe": {"nodes": integer(low=5, high=401)},
    "modal": {"reference_load_fraction": number(low=0.0, high=1.0, high_open=True)},
}


@dataclass(frozen=True)
class Beam:
    length: float
    radius: float
    density: float
    youngs_modulus: float
    proportional_limit: float


@dataclass(frozen=True)
class Extension:
    length: float
    radius: float
    density: float
    youngs_modulus: float


@dataclass(frozen=True)
class Supports:
    rotational_stiffness: float
    lateral_stiffness: float
    actuator_stiffness: float


@dataclass(frozen=True)
class Sensors:
    strain_gauge_positions: tuple[float, float]
    max_condition_number: float


@dataclass(frozen=True)
class Damping:
    ratios: tuple[float, float]
    identification_load: float


@dataclass(frozen=True)
class FE:
    nodes: int


@dataclass(frozen=True)
class Modal:
    reference_load_fraction: float   # of the model's own critical load, 0 <= f < 1


@dataclass(frozen=True)
class ModelParameters:
    """All parameters of the beam-column model, validated."""

    beam: Beam
    extension: Extension
    supports: Supports
    sensors: Sensors
    damping: Damping
    fe: FE
    modal: Modal

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (lists instead of tuples), suitable for YAML or JSON."""
        return json.loads(json.dumps(asdict(self)))

    def digest(self) -> str:
        """SHA-256 of the canonical JSON of all parameters: identifies the model a gain table
        was designed for."""
        canonical = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canonical.encode()).hexdigest()


def default_dict() -> dict[str, Any]:
    """The shipped defaults (``models/paper.yaml``) as a plain dict."""
    with resources.as_file(resources.files("beamctl.models") / PAPER_YAML) as path:
        return read_yaml(path)


def parameters_from_dict(overrides: dict[str, Any] | None = None, source: str = "") -> ModelParameters:
    """Validate ``overrides`` applied over the paper defaults and return the parameters."""
    modal = (overrides or {}).get("modal")
    if isinstance(modal, dict) and "reference_load" in modal:
        raise ConfigError("modal.reference_load", modal["reference_load"],
                          "modal.reference_load_fraction in its place: the reduced model's "
                          "reference load is now a fraction of the model's own critical load, "
                          "0 <= f < 1 (the paper's beam: 0.78, i.e. 2491 N of 3194 N)", source)
    data = merge(default_dict(), overrides or {})
    v = validate(data, _SCHEMA, source)
    beam_length = v["beam"]["length"]
    gauges = v["sensors"]["strain_gauge_positions"]
    for i, x in enumerate(gauges):
        if not 0.0 < x < beam_length:
            raise ConfigError(
                f"sensors.strain_gauge_positions[{i}]",
                x,
                f"a position strictly inside the beam, 0 < x < beam.length = {beam_length:g} m",
                source,
            )
    if gauges[0] == gauges[1]:
        raise ConfigError("sensors.strain_gauge_positions", list(gauges),
                          "two different positions", source)
    return ModelParameters(
        beam=Beam(**v["beam"]),
        extension=Extension(**v["extension"]),
        supports=Supports(**v["supports"]),
        sensors=Sensors(**v["sensors"]),
        damping=Damping(**v["damping"]),
        fe=FE(**v["fe"]),
        modal=Modal(**v["modal"]),
    )


def load_parameters(path: str | Path | None = None) -> ModelParameters:
    """Parameters from a YAML file over the paper defaults (``None``: the defaults alone)."""
    if path is None:
        return parameters_from_dict({}, source=PAPER_YAML)
    return parameters_from_dict(read_yaml(path), source=str(path))
