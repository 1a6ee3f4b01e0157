"""``beamctl config check``: what a configuration would run, and every reason ``beamctl run``
would refuse it, found without starting the service (service/check.py)."""

import json
from dataclasses import replace

import yaml

from beamctl.assembly.run import service_config
from beamctl.gains.defaults import default_table_path
from beamctl.gains.table import load_table, write_table
from beamctl.service.check import check_config
from beamctl.service.run import Service
from beamctl.tools.cli import main

RECORD = {"worst_ratio": 1.1007, "onset_N": 3521.0, "critical_load_N": 3199.0, "censored": False,
          "worst_rig": {"beam.youngs_modulus": 0.97}, "evaluated": 1496, "box_name": "box B",
          "box": {"parameters": {"beam.youngs_modulus": {"factor": [0.95, 1.05]}}, "seed": 1},
          "checked": "2026-11-27T03:00:00+00:00"}


def _write(path, data) -> str:
    path.write_text(yaml.safe_dump(data))
    return str(path)


def test_a_runnable_configuration_names_its_table_hash_and_design_and_exits_0(tmp_path, capsys):
    config = _write(tmp_path / "sim.yaml", {"hal": {"backend": "sim"},
                                             "control": {"socket": str(tmp_path / "ctl.sock")}})
    assert main(["config", "check", config]) == 0
    out = capsys.readouterr().out
    sha = load_table(default_table_path()).sha256       # the content hash the service reports
    assert str(default_table_path().resolve()) in out and sha in out, out
    assert "lqg at 6000 Hz" in out and "would start" in out
    robust = load_table(default_table_path()).robust      # the shipped table records its robust check
    line = next((x for x in out.splitlines() if x.startswith("robust check")), "")
    assert "held" in line and f"{robust['worst_ratio']:.4f}" in line, (
        f"the robust check's line does not give the table's record (worst ratio "
        f"{robust['worst_ratio']:.4f}): {line!r}")
    assert "ride-through" in out and "3300 N" in out, "the ride-through per load is not printed"


def test_every_reason_the_service_would_refuse_is_given_and_exits_1(tmp_path, capsys):
    """A classic CAN bus too slow for 6000 Hz, and a telemetry file that is already there."""
    (tmp_path / "old.btl").write_bytes(b"")
    config = _write(tmp_path / "can.yaml", {
        "hal": {"backend": "can", "can": {"interface": "virtual", "channel": "check", "fd": False,
                                          "bitrate_bit_s": 500000}},
        "run": {"telemetry": str(tmp_path / "old.btl")}, "control": {"socket": str(tmp_path / "c.sock")}})
    assert main(["config", "check", config, "--json"]) == 1
    report = json.loads(capsys.readouterr().out)
    assert not report["would_start"]
    reasons = " | ".join(report["refusals"])
    assert "bus load" in reasons and "6000 Hz" in reasons, reasons
    assert "old.btl" in reasons and "never overwritten" in reasons, reasons


def test_a_service_answering_on_the_socket_makes_it_refuse(tmp_path):
    sock = tmp_path / "ctl.sock"
    data = {"hal": {"backend": "sim", "sim": {"pace": "simulated"}}, "controller": {"pacing": "sample"},
            "plant": {"load": {"start": 1000.0, "end": 1000.0}}, "control": {"socket": str(sock)}}
    service = Service(service_config(data), tmp_path / "run.btl", control_socket=sock, hold=True,
                      acquire_rt=False)
    try:
        service.start()
        result = check_config(_write(tmp_path / "again.yaml", data))
    finally:
        service.request_stop()
        service.join(30.0)
        service.close()
    assert not result.would_start
    assert any("another service is running there" in r for r in result.refusals), result.refusals


def test_a_recorded_robust_check_is_kept_in_the_table_and_reported(tmp_path, capsys):
    table = replace(load_table(default_table_path()), robust=RECORD)
    path = tmp_path / "gains.yaml"
    write_table(table, path)
    again = load_table(path)
    assert again.intact and again.robust["worst_ratio"] == 1.1007, "kept under the table's content hash"
    assert main(["gains", "show", str(path)]) == 0
    assert "robust check: held" in capsys.readouterr().out
    config = _write(tmp_path / "sim.yaml", {"hal": {"backend": "sim"}, "gains": {"table": str(path)},
                                             "control": {"socket": str(tmp_path / "ctl.sock")}})
    assert main(["config", "check", config]) == 0
    out = capsys.readouterr().out
    assert "held: the worst rig of box B goes unstable at 1.1007 x its own critical load" in out, out
    assert "1496 rigs" in out


def test_a_socketcan_interface_this_machine_cannot_open_is_a_reason_with_what_to_do(tmp_path):
    """No SocketCAN in the kernel, or no such interface: either way `beamctl run` could not open
    the bus, and the reason says how to get one (modprobe, ip link)."""
    config = _write(tmp_path / "lab.yaml", {"hal": {"backend": "can", "can": {"interface": "socketcan",
                                                                             "channel": "nosuchcan9"}},
                                            "control": {"socket": str(tmp_path / "c.sock")}})
    result = check_config(config)
    reasons = [r for r in result.refusals if "hal.can.channel = 'nosuchcan9'" in r]
    assert reasons and ("modprobe" in reasons[0] or "ip link" in reasons[0]), result.refusals



def test_a_control_socket_path_the_service_could_not_bind_is_a_reason(tmp_path):
    """A plain file where the socket goes, or a folder under a file: `beamctl run` refuses both."""
    (tmp_path / "plain").write_text("")
    for where in (tmp_path / "plain", tmp_path / "plain" / "x.sock"):
        config = _write(tmp_path / "c.yaml", {"hal": {"backend": "sim"}, "control": {"socket": str(where)}})
        result = check_config(config)
        reasons = result.refusals
        assert any(str(where) in r or "not a directory" in r for r in reasons), (where, reasons)
