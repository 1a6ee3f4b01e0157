"""The shipped deployment files are valid for the service."""

import configparser
from pathlib import Path

from beamctl.assembly.run import load_service_config

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def test_lab_config_is_a_valid_service_config():
    cfg = load_service_config(DEPLOY / "lab.yaml")
    assert cfg.hal.backend == "can" and cfg.hal.can["interface"] == "socketcan"
    assert cfg.controller.pacing == "sample" and cfg.controller.actuators.max_voltage_v == 150.0


def test_systemd_unit_runs_the_service_with_watchdog_and_realtime_limits():
    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.read(DEPLOY / "beamctl.service")
    service = unit["Service"]
    assert service["Type"] == "notify" and service["WatchdogSec"]
    assert "beamctl run --config" in service["ExecStart"] and "--require-rt" in service["ExecStart"]
    assert service["LimitMEMLOCK"] == "infinity" and service["LimitRTPRIO"] == "99"
    assert service["Restart"] == "on-failure"


def test_the_unit_makes_the_directory_where_beamctl_ctl_looks_for_the_service():
    from beamctl.service import control

    unit = configparser.ConfigParser(strict=False, interpolation=None)
    unit.read(DEPLOY / "beamctl.service")
    runtime = Path("/run") / unit["Service"]["RuntimeDirectory"]
    assert runtime == control.RUN_DIR, f"the unit makes {runtime}, beamctl ctl looks in {control.RUN_DIR}"
    assert load_service_config(DEPLOY / "lab.yaml").control_socket == "", "the lab uses the default socket"
