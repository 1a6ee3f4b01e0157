"""One backend factory: hal.create builds every backend, the built-in ones and those other
packages register under the entry-point group ``beamctl.hal``."""

import ast
import importlib.metadata
from pathlib import Path

import pytest

from beamctl import hal
from beamctl.hal.base import HalBase

ROOT = Path(__file__).resolve().parents[2]
PRODUCT = ("config", "models", "gains", "rt", "hal", "common", "simulation", "identification", "service",
           "reports", "bench", "tools")


class _Daq(HalBase):
    """A backend another package could ship."""

    name = "daq"

    def __init__(self, sample_rate_hz: float, port: str) -> None:
        super().__init__(sample_rate_hz)
        self.port = port

    def _open(self) -> None:
        pass

    def _close(self) -> None:
        pass

    def _read(self, sample, timeout) -> bool:
        return False

    def _write(self, voltages) -> None:
        pass


def _with_entry_points(monkeypatch, *points: importlib.metadata.EntryPoint) -> None:
    def entry_points(**selection):
        assert selection == {"group": hal.ENTRY_POINT_GROUP}, selection
        return importlib.metadata.EntryPoints(points)
    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)


def test_a_backend_registered_by_another_package_is_built_by_name(monkeypatch):
    _with_entry_points(monkeypatch, importlib.metadata.EntryPoint(
        "daq", f"{__name__}:_Daq", hal.ENTRY_POINT_GROUP))
    backend = hal.create("daq", sample_rate_hz=2500.0, port="/dev/ttyUSB0")
    assert isinstance(backend, _Daq) and backend.port == "/dev/ttyUSB0"
    assert sorted(hal.backends()) == ["can", "daq", "sim"]


def test_a_registered_backend_cannot_take_a_built_in_name(monkeypatch):
    _with_entry_points(monkeypatch, importlib.metadata.EntryPoint("sim", f"{__name__}:_Daq",
                                                                  hal.ENTRY_POINT_GROUP))
    assert hal.backend_class("sim").__name__ == "SimBackend", "a package replaced the simulated rig"


def test_an_unknown_backend_names_the_known_ones(monkeypatch):
    _with_entry_points(monkeypatch)
    expected = r"unknown HAL backend 'daq': expected one of \['can', 'sim'\]"
    with pytest.raises(hal.HalConfigurationError, match=expected):
        hal.create("daq")


def test_no_product_module_builds_a_backend_but_through_the_factory():
    """A backend class called anywhere in the product outside hal/ bypasses the factory (and
    whatever a registered backend or a configured setting would change)."""
    classes = {"SimBackend", "CanBackend"}
    calls = []
    for folder in PRODUCT:
        if folder == "hal":
            continue
        for path in sorted((ROOT / folder).glob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Call):
                    f = node.func
                    name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""
                    if name in classes:
                        calls.append(f"{path.relative_to(ROOT)}:{node.lineno} {name}(...)")
    assert not calls, f"backends built directly (use beamctl.hal.create): {calls}"
