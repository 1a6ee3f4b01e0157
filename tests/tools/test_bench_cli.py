"""`beamctl bench --commands`: whole commands timed as a user starts them, in turn, medians; a
command that fails is named with its exit status and last line, in one line, no traceback."""

import argparse
import json
import subprocess
import sys

from beamctl.bench import measure
from beamctl.tools import bench_cmd

CLI = [sys.executable, "-c", measure.CLI]


def test_commands_are_timed_in_turn_each_as_a_process_of_its_own(monkeypatch):
    monkeypatch.setattr(measure, "COMMANDS", (("version", ("--version",)),
                                              ("a file", ("gains", "show", "--help"))))
    seen = []
    times = measure.command_times(rounds=2, progress=lambda done, total, label: seen.append(label))
    assert list(times) == ["version", "a file"]
    for name, t in times.items():
        assert len(t["runs_s"]) == 2, f"{name}: two rounds timed, the warm-up not: {t}"
        assert 0.0 < t["min_s"] <= t["median_s"] <= t["max_s"], f"{name}: {t}"
    assert seen[:2] == ["warm-up: version", "warm-up: a file"], f"progress in turn: {seen}"
    assert seen[-1] == "round 2/2: a file", seen


def test_a_command_that_fails_is_named_with_its_last_line_and_no_traceback(monkeypatch):
    missing = ("config", "check", "/nonexistent.yaml")
    monkeypatch.setattr(measure, "COMMANDS", (("a missing config", missing),))
    try:
        measure.command_times(rounds=1)
    except RuntimeError as exc:
        message = str(exc)
    else:
        raise AssertionError("a command that failed was timed as if it had run")
    assert "beamctl config check /nonexistent.yaml" in message and "exit status" in message, message
    assert "\n" not in message, f"one line: {message!r}"


def test_bench_commands_flag_is_refused_with_a_bad_repeat():
    done = subprocess.run([*CLI, "bench", "--commands", "--repeat", "0"], capture_output=True, text=True)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert "--repeat" in done.stderr, done.stderr


def test_json_of_the_commands_mode_is_one_object(monkeypatch, capsys):
    monkeypatch.setattr(measure, "COMMANDS", (("version", ("--version",)),))
    code = bench_cmd.run(argparse.Namespace(offline=False, live=False, commands=True, repeat=1, json=True))
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert out["commands"]["version"]["runs_s"], out
