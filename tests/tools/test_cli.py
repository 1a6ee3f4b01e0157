"""The command line under bad input and interruption: one line on stderr, the documented exit
status, never a traceback, never a half-written file."""

import fcntl
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from beamctl.tools import experiment_cmd, gains_cmd, log_cmd, model_cmd, run_cmd
from beamctl.tools.cli import main
from tests.processes import beamctl, interrupt_when

# the paper's design (integral LQR, 2500 Hz) builds in seconds; the robust check is left out
PAPER_BUILD = ("gains", "build", "--design", "integral-lqr", "--no-robust")

UNWRITABLE = Path("/sys")      # refuses new files even to root


def _no_work(*_args, **_kwargs):
    raise AssertionError("the work started before the output path was checked")


def _one_line_error(capsys, *needles) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for needle in needles:
        assert str(needle) in err, err
    return err


# -- output paths, checked before the work starts --------------------------------------------------

def _config(tmp_path, data) -> str:
    f = tmp_path / "service.yaml"
    f.write_text(yaml.safe_dump(data))
    return str(f)


# the command, its argv with the output path, what the message calls the path, the work that
# must not start
COMMANDS = {
    "experiment --out": ("experiment", lambda p, tmp: ["experiment", "--out", p], "--out",
                         (experiment_cmd, "run_experiment")),
    "gains build --out": ("gains build", lambda p, tmp: ["gains", "build", "--out", p], "--out",
                          (gains_cmd, "build_table")),
    "model --plot": ("model", lambda p, tmp: ["model", "--plot", p], "--plot", (model_cmd, "build_model")),
    "gains show --plot": ("gains show", lambda p, tmp: ["gains", "show", "--plot", p], "--plot",
                          (gains_cmd, "_load")),
    "log export --out": ("log export", lambda p, tmp: ["log", "export", str(tmp / "run.btl"), "--to", "csv",
                                                       "--out", p], "--out", (log_cmd, "read_telemetry")),
    "log plot --out": ("log plot", lambda p, tmp: ["log", "plot", str(tmp / "run.btl"), "--out", p], "--out",
                       (log_cmd, "read_telemetry")),
    "run --telemetry": ("run", lambda p, tmp: ["run", "--config", _config(tmp, {}), "--telemetry", p],
                        "--telemetry", (run_cmd, "Service")),
    "run.telemetry": ("run", lambda p, tmp: ["run", "--config", _config(tmp, {"run": {"telemetry": p}})],
                      "service.yaml: run.telemetry", (run_cmd, "Service")),
}
DIRECTORY_FLAGS = {"experiment --out", "model --plot", "gains show --plot", "log plot --out"}


def _bad_path(kind: str, command: str, tmp: Path) -> tuple[Path, str]:
    """A path of ``kind`` that ``command`` cannot write, and the reason its refusal gives."""
    (tmp / "a-file").write_text("")
    if kind == "wrong kind":
        if command in DIRECTORY_FLAGS:
            return tmp / "a-file", "it is a file, not a directory"
        return tmp, "it is a directory"
    if kind == "file as parent":
        return tmp / "a-file" / "out" / "x.png", f"{tmp / 'a-file'} is not a directory"
    return UNWRITABLE / "beamctl-report" / "x.out", ""       # permission denied, or a read-only /sys


@pytest.mark.parametrize("kind", ["wrong kind", "file as parent", "no permission"])
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_an_output_path_that_cannot_be_written_is_refused_before_the_work(command, kind, tmp_path,
                                                                          monkeypatch, capsys):
    name, argv, what, (module, work) = COMMANDS[command]
    monkeypatch.setattr(module, work, _no_work)
    monkeypatch.chdir(tmp_path)
    path, why = _bad_path(kind, command, tmp_path)
    args = argv(str(path), tmp_path)
    before = sorted(tmp_path.rglob("*"))
    assert main(args) == 2
    err = _one_line_error(capsys, f"{what} {path}: cannot write there ({why}")
    assert why or "(permission denied)" in err or "(read-only file system)" in err, err
    assert err.startswith(f"beamctl {name}: error: "), err
    assert sorted(tmp_path.rglob("*")) == before, "a refused command leaves nothing behind"


def test_a_refused_experiment_leaves_no_report_folder(tmp_path, capsys):
    config = tmp_path / "bad.yaml"
    config.write_text("plant: {load: {rate: -1}}\n")
    argv = ["experiment", "--config", str(config), "--out", str(tmp_path / "report"), "--telemetry"]
    assert main(argv) == 2
    _one_line_error(capsys, "plant.load.rate")
    assert not (tmp_path / "report").exists()


def test_export_s_default_output_is_checked_too(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(log_cmd, "read_telemetry", _no_work)
    (tmp_path / "run.csv").mkdir()
    assert main(["log", "export", str(tmp_path / "run.btl"), "--to", "csv"]) == 2
    _one_line_error(capsys, "--out (default)", tmp_path / "run.csv", "it is a directory")


def test_export_never_overwrites_the_recording_it_reads(tmp_path, capsys):
    recording = tmp_path / "run.csv"
    recording.write_bytes(b"recorded")
    assert main(["log", "export", str(recording), "--to", "csv"]) == 2
    _one_line_error(capsys, "it is the telemetry file being exported")
    assert recording.read_bytes() == b"recorded"


def test_a_service_whose_hal_cannot_open_leaves_no_empty_recording(tmp_path, capsys):
    telemetry = tmp_path / "logs" / "run.btl"
    config = _config(tmp_path, {"hal": {"backend": "can", "can": {"interface": "socketcan",
                                                                   "channel": "beamctl-none0"}},
                                "run": {"telemetry": str(telemetry)}})
    assert main(["run", "--config", config]) == 2
    assert "cannot open socketcan:beamctl-none0" in capsys.readouterr().err
    assert not (tmp_path / "logs").exists()


def test_a_can_recording_path_is_checked_with_the_telemetry(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(run_cmd, "Service", _no_work)
    config = _config(tmp_path, {"hal": {"backend": "can", "can": {"record": str(tmp_path)}}})
    assert main(["run", "--config", config]) == 2
    _one_line_error(capsys, "hal.can.record", "it is a directory")


# -- flags -----------------------------------------------------------------------------------------

@pytest.mark.parametrize(("argv", "needle"), [
    (["gains", "build", "--mode", "fast"], "--mode"),
    (["bus-budget", "--rate", "fast"], "--rate"),
    (["experiment", "--no-such-flag"], "--no-such-flag"),
    (["log", "export", "run.btl"], "--to"),
    (["gains"], "ACTION"),
])
def test_a_bad_flag_is_refused_in_one_line(argv, needle, capsys):
    assert main(argv) == 2
    _one_line_error(capsys, "error:", needle)


@pytest.mark.parametrize("argv", [
    ["model", "--config", "missing.yaml"],
    ["gains", "build", "--config", "missing.yaml"],
    ["gains", "check", "missing.yaml"],
    ["gains", "show", "missing.yaml"],
    ["experiment", "--config", "missing.yaml"],
    ["run", "--config", "missing.yaml"],
    ["log", "export", "missing.btl", "--to", "csv"],
    ["log", "plot", "missing.btl", "--out", "figs"],
    ["bus-budget", "--dbc", "missing.dbc"],
])
def test_a_missing_input_file_is_refused_in_one_line(argv, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    command = argv[:2] if argv[0] in ("gains", "log") else argv[:1]
    _one_line_error(capsys, f"beamctl {' '.join(command)}: error:", "missing.")
    assert list(tmp_path.iterdir()) == [], "nothing written"


# -- interruption ----------------------------------------------------------------------------------

def test_ctrl_c_anywhere_in_a_command_exits_130_in_one_line(monkeypatch, capsys):
    def interrupted(*_args, **_kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(model_cmd, "build_model", interrupted)
    assert main(["model"]) == 130
    assert capsys.readouterr().err == "beamctl model: interrupted (SIGINT)\n"


@pytest.mark.parametrize(("signum", "status", "said"), [
    (signal.SIGINT, 130, "interrupted (SIGINT)"),
    (signal.SIGTERM, 143, "interrupted (SIGTERM during the command)"),
])
def test_ctrl_c_or_sigterm_during_gains_build_leaves_no_table(tmp_path, signum, status, said):
    out = tmp_path / "gains" / "table.yaml"
    # 401 grid points: long enough that the signal lands while it computes, on any machine
    process = beamctl(*PAPER_BUILD, "--grid", "0:4000:10", "--out", str(out), cwd=tmp_path)
    code, err = interrupt_when(process, b"gains build:", signum=signum)
    assert code == status, err
    assert err.splitlines()[-1] == f"beamctl gains build: {said}", err
    assert "Traceback" not in err
    assert not out.exists() and not (tmp_path / "gains").exists(), "no table, no temporary file"


def test_a_reader_that_stops_early_ends_the_command_quietly(tmp_path):
    """``beamctl gains check | head``: exit 141 (the shell's status for SIGPIPE), no traceback."""
    from beamctl.gains.defaults import paper_table_path

    # a one-page pipe, made so before the command starts (shrunk after, a busy machine let the
    # command write all of it into the default 64 kB first): the check's ~7 kB table (the paper's:
    # every load and midpoint) cannot all be written before this reader leaves
    read_end, write_end = os.pipe()
    fcntl.fcntl(write_end, fcntl.F_SETPIPE_SZ, 4096)
    try:
        process = beamctl("gains", "check", str(paper_table_path()), cwd=tmp_path, stdout=write_end)
    finally:
        os.close(write_end)
    with open(read_end, "rb", buffering=0) as reader:
        assert reader.read(10) == b"gain table"
    err = process.communicate(timeout=300)[1].decode()
    assert process.returncode == 141, err
    assert "Traceback" not in err and "BrokenPipeError" not in err and "Exception ignored" not in err, err


def test_the_command_line_starts_without_the_heavy_libraries(tmp_path):
    """numpy, scipy and python-can take about a second to import: they are imported inside
    main(), so a Ctrl-C even then ends in one line rather than a traceback."""
    heavy = "('numpy', 'scipy', 'can', 'cantools', 'matplotlib')"
    code = f"import sys, beamctl.tools.cli; print(sorted(m for m in {heavy} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path,
                         check=True, timeout=120)
    assert out.stdout.strip() == "[]", out.stdout


def test_ctrl_c_before_the_command_is_known_is_one_line(monkeypatch, capsys):
    from beamctl.tools import cli

    def interrupted(command=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", interrupted)
    assert main(["model"]) == 130
    assert capsys.readouterr().err == "beamctl: interrupted (SIGINT)\n"


def test_a_model_fit_error_names_the_command_as_typed(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["model", "fit", "missing.npz", "--out", "fitted.yaml"]) == 2
    _one_line_error(capsys, "beamctl model fit: error:", "missing.npz")


def test_experiment_telemetry_takes_the_folder_it_records_into(tmp_path, capsys):
    """As `run --telemetry FILE` names where its recording goes, `experiment --telemetry DIR`
    does (alone, the report folder); a file there is refused before any run."""
    (tmp_path / "a-file").write_text("")
    argv = ["experiment", "--out", str(tmp_path / "report"), "--telemetry", str(tmp_path / "a-file")]
    assert main(argv) == 2
    _one_line_error(capsys, "beamctl experiment: error:", "--telemetry", "not a directory")
    assert not (tmp_path / "report").exists() or not any((tmp_path / "report").iterdir())


def test_every_help_page_shows_its_percent_signs_once():
    """argparse %-formats help strings but prints descriptions as written: a description that
    wrote %% showed "95 %%" to the reader."""
    import argparse

    from beamctl.tools.cli import build_parser

    def pages(parser, name):
        yield name, parser.format_help()
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub_name, sub in action.choices.items():
                    yield from pages(sub, f"{name} {sub_name}")

    shown = dict(pages(build_parser(), "beamctl"))
    assert len(shown) > 20, sorted(shown)
    doubled = [name for name, text in shown.items() if "%%" in text]
    assert not doubled, f"help pages that print '%%': {doubled}"


def test_a_command_imports_what_it_runs_and_not_the_others():
    """`beamctl model ...` builds its own parser: the benchmark's numba intrinsics and the study's
    modules are not imported for it (about 1.3 s of imports here); `beamctl --help` lists every
    command, each once."""
    code = ("import sys\nfrom beamctl.tools.cli import build_parser, COMMANDS\n"
            "build_parser('model')\n"
            "others = ('beamctl.bench.measure', 'beamctl.tools.study_cmd')\n"
            "print(sorted(m for m in others if m in sys.modules))\n"
            "sub = build_parser()._subparsers._group_actions[0]\n"
            "print(sorted(sub.choices) == sorted(COMMANDS))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         timeout=120)
    imported, listed = out.stdout.split("\n")[:2]
    assert imported == "[]", f"`beamctl model` imported other commands' modules: {imported}"
    assert listed == "True", "`beamctl --help` does not list exactly the commands of COMMANDS"
