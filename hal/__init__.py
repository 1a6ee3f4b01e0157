"""Hardware abstraction: the interface (hal.base) and its backends, chosen by name.

Backends are imported only when asked for, so the simulated plant never loads a CAN
library; an unknown name is an error, and nothing falls back from one backend to another.
"""

from __future__ import annotations

import importlib

from beamctl.hal.base import (
    HalBase,
    HalConfigurationError,
    HalConnectionLost,
    HalError,
    HalProtocolError,
    HalStaleData,
    Sample,
)

BACKENDS = {
    "sim": ("beamctl.hal.sim", "SimBackend"),
    "can": ("beamctl.hal.can_backend", "CanBackend"),
}


def backend_class(name: str) -> type[HalBase]:
    """The backend class registered as ``name`` (imported now)."""
    try:
        module_name, class_name = BACKENDS[name]
    except KeyError:
        raise HalConfigurationError(
            f"unknown HAL backend {name!r}: expected one of {sorted(BACKENDS)}") from None
    return getattr(importlib.import_module(module_name), class_name)


def create(name: str, **settings) -> HalBase:
    """A backend instance (not yet open)."""
    return backend_class(name)(**settings)


__all__ = ["BACKENDS", "HalBase", "HalConfigurationError", "HalConnectionLost", "HalError",
           "HalProtocolError", "HalStaleData", "Sample", "backend_class", "create"]
