"""Hardware abstraction: the interface (hal.base) and its backends, chosen by name.

Backends are imported only when asked for, so the simulated plant never loads a CAN
library; an unknown name is an error, and nothing falls back from one backend to another.
"""

from __future__ import annotations

import importlib
import importlib.metadata

from beamctl.hal.base import (
    HalBase,
    HalConfigurationError,
    HalConnectionLost,
    HalError,
    HalProtocolError,
    HalStaleData,
    Sample,
)

# the backends that come with beamctl; others register under the entry-point group
# ``beamctl.hal`` (name = "module:Class", as python-can's ``can.interface`` group does)
BACKENDS = {
    "sim": "beamctl.hal.sim:SimBackend",
    "can": "beamctl.hal.can_backend:CanBackend",
}
ENTRY_POINT_GROUP = "beamctl.hal"


def backends() -> dict[str, str]:
    """Every backend by name: the built-in ones and those other packages register (a name
    that is built in keeps its built-in backend)."""
    found = {ep.name: ep.value for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}
    return {**found, **BACKENDS}


def backend_class(name: str) -> type[HalBase]:
    """The backend class registered as ``name`` (imported now)."""
    known = backends()
    if name not in known:
        raise HalConfigurationError(f"unknown HAL backend {name!r}: expected one of {sorted(known)}")
    module_name, _, class_name = known[name].partition(":")
    return getattr(importlib.import_module(module_name), class_name)


def create(name: str, **settings) -> HalBase:
    """A backend instance (not yet open): the one way beamctl builds a backend, from its name
    and the backend's own settings (SimBackend: plant, geometry, pace; CanBackend:
    sample_rate_hz, interface, channel, ...)."""
    return backend_class(name)(**settings)


__all__ = ["BACKENDS", "ENTRY_POINT_GROUP", "HalBase", "HalConfigurationError", "HalConnectionLost",
           "HalError", "HalProtocolError", "HalStaleData", "Sample", "backend_class", "backends", "create"]
