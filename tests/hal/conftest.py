"""Fixtures of the HAL tests: ``scripted`` (tests/hal/scripted.py), CAN backends on scripted
buses whose time stamps and clock the test constructs."""

from tests.hal.scripted import scripted  # noqa: F401 (a fixture)
