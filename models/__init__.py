"""Physics of the beam-column: parameters, FE model, modal reduction and the simulation plant.

Knows nothing about time or I/O beyond the sampled plant of ``models.plant``.
"""

from beamctl.models.analysis import (
    buckling_mode,
    critical_load,
    eigenfrequencies,
    fe_frequency_response,
    state_space,
)
from beamctl.models.fe import FEModel, build_model
from beamctl.models.modal import ModalModel, reduce
from beamctl.models.params import ModelParameters, load_parameters, parameters_from_dict

__all__ = [
    "FEModel",
    "ModalModel",
    "ModelParameters",
    "buckling_mode",
    "build_model",
    "critical_load",
    "eigenfrequencies",
    "fe_frequency_response",
    "load_parameters",
    "parameters_from_dict",
    "reduce",
    "state_space",
]
