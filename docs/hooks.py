"""The documentation's generated parts: a MkDocs hook (``hooks:`` in docs/mkdocs.yml) and a script.

Two kinds of marker in a page's Markdown are replaced as the site is built:

``<!-- beamctl-config: SECTION -->``
    the reference of every key of a configuration section, read from the code: the schema the
    section is validated with (a mapping of keys to validators of ``beamctl.config.schema``),
    the defaults it is merged over, and what each validator accepts, in the validator's own
    words (the text of its refusal). The meaning of each key comes from
    docs/configuration-meanings.yaml. ``<!-- beamctl-config: renamed -->`` lists the keys that
    are refused naming their new name.

``<!-- beamctl-bench -->``
    the figures of ``beamctl bench --json`` (docs/measured/bench.json) and ``beamctl bench
    --offline --json`` (docs/measured/bench-offline.json), with the date and machine in
    docs/measured/about.json.

A problem (a section whose schema is gone, a meaning for a key the schema does not hold, a
figure the JSON lacks) is a warning, which ``mkdocs build --strict`` turns into a failure.

As a script::

    python docs/hooks.py config      # the configuration reference, as Markdown
    python docs/hooks.py bench       # the measured figures, as Markdown
    python docs/hooks.py measure     # run the benchmarks and write docs/measured/*.json (minutes)
"""

from __future__ import annotations

import datetime
import importlib
import json
import logging
import os
import platform
import re
import subprocess
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import yaml

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
MEANINGS = DOCS / "configuration-meanings.yaml"
MEASURED = DOCS / "measured"
BENCH_FILES = {"bench": "bench.json", "offline": "bench-offline.json", "commands": "bench-commands.json",
               "about": "about.json"}

log = logging.getLogger("mkdocs.hooks.beamctl")
_problems: list[str] = []


def _problem(message: str) -> None:
    """A warning in a MkDocs build (a failure with --strict); collected when run as a script."""
    _problems.append(message)
    log.warning("beamctl docs: %s", message)


# ---------------------------------------------------------------------------------------------
# the configuration reference

class _Probe:
    """A value no validator accepts: what a validator refuses it with says what it accepts."""

    def __repr__(self) -> str:
        return "<probe>"


def _closure(validator: Callable) -> dict[str, Any]:
    """The variables a validator closes over (``low``, ``length``, ``element``, ...)."""
    code = getattr(validator, "__code__", None)
    cells = getattr(validator, "__closure__", None) or ()
    if code is None:
        return {}
    return {name: cell.cell_contents for name, cell in zip(code.co_freevars, cells, strict=False)}


def accepted(validator: Callable) -> str:
    """What ``validator`` accepts, in its own words: the expectation it refuses a probe with
    (a list of probes for a list validator, so that the text names what each element must be)."""
    length = _closure(validator).get("length")
    probe: Any = [_Probe()] * length if isinstance(length, int) else _Probe()
    try:
        validator(probe)
    except Exception as exc:  # noqa: BLE001 (the schema's _Invalid carries .expected)
        expected = getattr(exc, "expected", None)
        if isinstance(expected, str):
            return expected
        raise RuntimeError(f"{validator!r} refused a probe without saying what it expects: {exc!r}") from None
    raise RuntimeError(f"{validator!r} accepted a probe")


_UNIT = re.compile(r" \(in ([^()]+)\)")


def unit(expected: str) -> str:
    """The unit in a validator's expectation (``positive("N")`` says "a finite number > 0 (in N)")."""
    found = _UNIT.search(expected)
    return found.group(1) if found else ""


def yaml_value(value: Any) -> str:
    """A default as it is written in a YAML file."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if value.is_integer() and abs(value) < 1e6:
            return f"{value:.1f}"
        short = f"{value:.6g}"
        return short if float(short) == value else repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(yaml_value(v) for v in value) + "]"
    if isinstance(value, str):
        return json.dumps(value) if value == "" or value != value.strip() else value
    return str(value)


def _cell(text: str) -> str:
    """Text for a table cell: pipes escaped, except in code spans (where the table reads them as text)."""
    parts = text.replace("\n", " ").split("`")
    return "`".join(part if i % 2 else part.replace("|", "\\|") for i, part in enumerate(parts))


def _code(text: str) -> str:
    return f"`{text}`"


def _attr(module: str, name: str) -> Any:
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as exc:
        _problem(f"{module}.{name} is gone ({exc}): the reference cannot show this section")
        return None


def _model_defaults() -> dict:
    from beamctl.models.params import default_dict
    return default_dict()


def _scenario_experiment() -> dict:
    scenario = _attr("beamctl.simulation.experiment", "SCENARIO")
    return (scenario or {}).get("experiment", {})


# Sections validated with a schema of beamctl.config.schema: (module, schema, defaults: a name in
# the module or a function giving them, the function that validates the section).
SCHEMAS: dict[str, tuple[str, str, str | Callable[[], dict], str]] = {
    "model": ("beamctl.models.params", "_SCHEMA", _model_defaults, "parameters_from_dict"),
    "controller": ("beamctl.rt.config", "_SCHEMA", "CONTROLLER_DEFAULTS", "controller_config"),
    "hal": ("beamctl.hal.config", "_SCHEMA", "HAL_DEFAULTS", "hal_config"),
    "plant": ("beamctl.models.plant", "_SCHEMA", "PLANT_DEFAULTS", "plant_config"),
    "experiment": ("beamctl.simulation.experiment", "_EXPERIMENT_SCHEMA", _scenario_experiment,
                   "experiment_config"),
}
# Sections whose keys are checked by code, not by a schema: only their defaults can be read.
DEFAULTS_ONLY: dict[str, tuple[str, str, str]] = {
    "plant.io": ("beamctl.models.iochain", "IO_DEFAULTS", "io_chain"),
    "study.linear": ("beamctl.simulation.study", "LINEAR_DEFAULTS", "study_from_dict"),
}
# Sections checked by code with neither schema nor defaults to read: (the function, where the
# documentation gives the keys).
NOT_INTROSPECTABLE: dict[str, tuple[str, str]] = {
    "gains": ("beamctl.assembly.run.service_config", "the overview above"),
    "run": ("beamctl.assembly.run.service_config", "the overview above"),
    "control": ("beamctl.assembly.run.service_config", "the overview above"),
    "study": ("beamctl.simulation.study.study_from_dict", "[Uncertainty studies](studies.md)"),
}
# Keys refused with the name to use instead: (module, mapping of old to new dotted keys, prefix).
RENAMED = (("beamctl.rt.config", "RENAMED_KEYS", "controller."),
           ("beamctl.hal.config", "RENAMED_KEYS", "hal."),
           ("beamctl.assembly.run", "RENAMED_RUN_KEYS", "run."))


def _source_file(module: str) -> str:
    """The repository path of a module of beamctl (``beamctl.rt.config`` -> ``rt/config.py``)."""
    return module.removeprefix("beamctl.").replace(".", "/") + ".py"


def _meanings() -> dict[str, dict[str, str]]:
    data = yaml.safe_load(MEANINGS.read_text(encoding="utf-8")) or {}
    return {section: dict(keys or {}) for section, keys in data.items()}


def _rows(schema: Mapping, defaults: Mapping, meanings: dict[str, str], prefix: str = "") -> list[str]:
    rows = []
    for key, rule in schema.items():
        dotted = prefix + key
        default = defaults.get(key) if isinstance(defaults, Mapping) else None
        if isinstance(rule, Mapping):
            if dotted in meanings:
                rows.append(f"| {_code(dotted + '.*')} | | | | {_cell(meanings.pop(dotted))} |")
            rows += _rows(rule, default if isinstance(default, Mapping) else {}, meanings, dotted + ".")
            continue
        if not isinstance(defaults, Mapping) or key not in defaults:
            _problem(f"{dotted}: the schema holds it but the defaults do not")
        what = accepted(rule)
        in_unit = unit(what)
        what = what.replace(f" (in {in_unit})", "") if in_unit else what
        rows.append(f"| {_code(dotted)} | {_code(yaml_value(default))} | {_cell(in_unit)} | {_cell(what)} | "
                    f"{_cell(meanings.pop(dotted, ''))} |")
    return rows


def _header(columns: tuple[str, ...]) -> list[str]:
    return ["| " + " | ".join(columns) + " |", "|" + " --- |" * len(columns)]


def section_reference(section: str) -> str:
    """The Markdown reference of one section (a key of SCHEMAS, DEFAULTS_ONLY or NOT_INTROSPECTABLE)."""
    meanings = _meanings().get(section, {})
    if section in SCHEMAS:
        module, schema_name, defaults_from, function = SCHEMAS[section]
        schema = _attr(module, schema_name)
        defaults = defaults_from() if callable(defaults_from) else _attr(module, defaults_from)
        if schema is None or defaults is None:
            return f"*The schema of `{section}` could not be read from `{module}` (see the warnings).*"
        lines = _header(("key", "default", "unit", "accepted", "meaning"))
        lines += _rows(schema, defaults, meanings)
        source = (f"\n*Generated from `{schema_name}` and its defaults in `{_source_file(module)}`, "
                  f"the schema `{function}` validates this section with.*\n")
        text = "\n".join(lines) + "\n" + source
    elif section in DEFAULTS_ONLY:
        module, defaults_name, function = DEFAULTS_ONLY[section]
        defaults = _attr(module, defaults_name)
        if defaults is None:
            return f"*The defaults of `{section}` could not be read from `{module}`.*"
        lines = _header(("key", "default", "meaning"))
        for key, value in defaults.items():
            lines.append(f"| {_code(key)} | {_code(yaml_value(value))} | {_cell(meanings.pop(key, ''))} |")
        text = ("\n".join(lines) + "\n\n"
                f"*Keys and defaults generated from `{defaults_name}` in `{_source_file(module)}`. "
                f"What each key accepts is not introspectable: `{function}` checks these keys in "
                f"code, not with a schema of `beamctl.config.schema`.*\n")
    elif section in NOT_INTROSPECTABLE:
        function, where = NOT_INTROSPECTABLE[section]
        text = (f"*Not introspectable: `{function}` checks the `{section}` section with rules written "
                f"inside the function, not a schema the documentation can read; {where} gives its keys.*\n")
    else:
        _problem(f"no configuration section {section!r} is known to docs/hooks.py")
        return f"*Unknown section `{section}`.*\n"
    for key in meanings:
        _problem(f"docs/configuration-meanings.yaml: {section}.{key} is not a key of the section's schema")
    return text


def renamed_reference() -> str:
    lines = _header(("old key (refused)", "write instead", "declared in"))
    for module, name, prefix in RENAMED:
        renamed = _attr(module, name)
        for old, new in (renamed or {}).items():
            lines.append(f"| {_code(prefix + old)} | {_code(prefix + new)} | `{_source_file(module)}` |")
    return "\n".join(lines) + "\n"


def config_reference_all() -> str:
    """Every section, for the script."""
    parts = []
    for section in (*SCHEMAS, *DEFAULTS_ONLY, *NOT_INTROSPECTABLE):
        parts += [f"## `{section}`\n", section_reference(section)]
    parts += ["## renamed keys\n", renamed_reference()]
    return "\n".join(parts)


# ---------------------------------------------------------------------------------------------
# the measured figures

def _load(name: str) -> Any:
    path = MEASURED / BENCH_FILES[name]
    if not path.is_file():
        _problem(f"{path.relative_to(ROOT)} is missing: run `python docs/hooks.py measure`")
        return None
    return json.loads(path.read_text(encoding="utf-8"))


def _get(data: Any, path: str) -> Any:
    """The value at a dotted path of the bench's JSON (None, and a warning, when it is not there)."""
    for key in path.split("/"):
        if not isinstance(data, Mapping) or key not in data:
            _problem(f"the bench JSON has no {path}")
            return None
        data = data[key]
    return data


def _n(value: Any, digits: int = 1) -> str:
    """A number as the page prints it; ? for one the JSON lacks."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return "?"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def _bench_rows(bench: Mapping) -> list[tuple[str, str]]:
    def g(path: str, digits: int = 1) -> str:
        return _n(_get(bench, path), digits)

    transport = str(_get(bench, "can/transport") or "?").split(":")[0]
    return [
        ("the whole control step of the shipped table (estimator, schedule, law, allocation, safety): the "
         "compiled cycle, timed inside compiled code by the CPU's cycle counter",
         f"p50 {g('step_us/compiled/p50', 2)} us, p99 {g('step_us/compiled/p99', 2)} us"),
        ("the same: the controller's `step` called from Python as the loop does",
         f"p50 {g('step_us/call/p50', 2)} us, p99 {g('step_us/call/p99', 2)} us "
         f"(p50 x{g('step_us/call_over_compiled_p50', 2)} the compiled cycle's)"),
        (f"the controller's CAN latency: strain frame sent -> the voltage frame answering it sent, shipped "
         f"table at {g('can/sample_rate_hz', 0)} Hz, DAQ emulator in its own process ({transport}), "
         f"{g('can/samples')} answers",
         f"p50 {g('can/p50')} us, p99 {g('can/p99')} us, p99.9 {g('can/p99.9')} us, "
         f"max {g('can/max', 0)} us; "
         f"{g('can/over_half_period')} later than half a period ({g('can/half_period_us', 0)} us), "
         f"{g('can/late')} later than the answer budget ({g('can/budget_us', 0)} us); "
         f"{g('can/bridged_samples')} samples missing and bridged, the longest gap {g('can/longest_gap')}; "
         f"ended {_get(bench, 'can/ended')}"),
        (f"bus load of the frames at {g('can/sample_rate_hz', 0)} Hz / the highest rate on classic CAN "
         f"1 Mbit/s / on CAN FD 1+4 Mbit/s",
         f"{g('can/bus_load_percent')} % of {_get(bench, 'can/bus')} / "
         f"{g('can/max_rate_classic_1M_Hz', 0)} Hz / {g('can/max_rate_fd_1M_4M_Hz', 0)} Hz"),
        (f"timer pacing against the sim backend, cycle start to start ({g('timer_cycle_us/period_us')} us "
         f"period, {g('timer_cycle_us/cycles')} cycles)",
         f"p50 {g('timer_cycle_us/p50')} us, p99 {g('timer_cycle_us/p99')} us, "
         f"max {g('timer_cycle_us/max')} us, {g('timer_cycle_us/overruns')} overruns"),
        ("simulation speed of the experiment's controlled run (the sim backend through the loop)",
         f"{g('sim_realtime_factor')} x real time ({g('sim/plant_s')} s of plant time in "
         f"{g('sim/wall_s')} s)"),
        ("building the default gain table inside one process (`beamctl gains build`'s work)",
         f"{g('gains_build_s', 2)} s"),
    ]


def _table(columns: tuple[str, ...], rows: list[tuple[str, ...]]) -> list[str]:
    return _header(columns) + ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]


def bench_page() -> str:
    """The measured figures of docs/measured/ as Markdown."""
    bench, offline, about = _load("bench"), _load("offline"), _load("about")
    commands = _load("commands")
    out: list[str] = []
    if about:
        out += [f"Measured on {about.get('date', '?')}, on {_get(about, 'machine/description')}; beamctl "
                f"{about.get('beamctl', '?')}, commit {about.get('commit', '?')}.", ""]
        runs = [(f"`docs/measured/{r.get('file')}`", f"`{r.get('command')}`",
                 str(r.get("started", "?")) + (f", commit {r['commit']}" if r.get("commit") else ""),
                 f"{_n(r.get('wall_s'))} s", f"{r.get('load_before', '?')} / {r.get('load_after', '?')}")
                for r in about.get("runs", [])]
        out += _table(("file", "command", "started", "wall time", "load average before / after"), runs)
        out.append("")
    if bench:
        out += ["## `beamctl bench`", ""] + _table(("what", "figure"), _bench_rows(bench)) + [""]
        timing = _get(bench, "can/loop_timing") or {}
        out += ["The CAN measurement's loop, per cycle (the HAL's read, the control step, the write, and the "
                "answer's age):", ""]
        out += _table(("part", "p50", "p99", "p99.9", "max", "count"),
                      [(part, *(f"{_n(t.get(k))} us" for k in ("p50_us", "p99_us", "p99.9_us", "max_us")),
                        _n(t.get("count"))) for part, t in timing.items()])
        out.append("")
        live = _get(bench, "live_view") or {}
        out += [f"The loop with and without a live view (`beamctl bench --live` measures only this): "
                f"timer pacing at {_n(live.get('period_us'))} us, the sim backend, telemetry written, "
                f"real-time set-up {live.get('realtime', '?')}; {_n(live.get('cycles'))} cycles a case, "
                f"the cases taken in turn in {_n(live.get('rounds'))} rounds, medians; ratios to the "
                f"case without `--live`; datagrams over all rounds:", ""]
        rows = []
        for case, r in live.items():
            if isinstance(r, Mapping):
                q = r.get("ratio")
                keys = ("cycle_p50", "cycle_p99", "step_p50")
                ratio = ", ".join(_n(q.get(k), 3) for k in keys) if q else "1"
                rows.append((case, f"{_n(r.get('cycle_p50'))} us", f"{_n(r.get('cycle_p99'))} us",
                             f"{_n(r.get('step_p50'), 2)} us", _n(r.get("overruns"), 0), ratio,
                             f"{r.get('sent')}, {r.get('dropped')}" if q else "-"))
        out += _table(("case", "cycle p50", "cycle p99", "step p50", "overruns",
                       "ratio: cycle p50, p99, step p50", "datagrams sent, dropped"), rows) + [""]
    if offline:
        out += ["## `beamctl bench --offline`", "",
                "A simulated sample of the experiment's controlled run through the loop and through the "
                "compiled kernel (the plant's discretisations computed afresh: cold; shared from the run "
                "before: warm), both running the engine's compiled cycle, alternately in one process. "
                "numba's compilation or cache load before the rounds: "
                f"{_n(_get(offline, 'compile_or_cache_load_s'), 2)} s.", ""]
        rows = []
        for k, r in enumerate(_get(offline, "rounds") or [], 1):
            held = r.get("held_load_n") or [None, None]
            rows.append((str(k), f"{_n(r.get('loop_us'), 2)} us", f"{_n(r.get('kernel_cold_us'), 2)} us",
                         f"{_n(r.get('kernel_warm_us'), 2)} us",
                         f"x{_n(r.get('ratio_cold'))} / x{_n(r.get('ratio_warm'))}", _n(r.get("cycles")),
                         f"{_n(held[0])} / {_n(held[1])} N"))
        med = _get(offline, "median") or {}
        rows.append(("median", f"{_n(med.get('loop_us'), 2)} us", f"{_n(med.get('kernel_cold_us'), 2)} us",
                     f"{_n(med.get('kernel_warm_us'), 2)} us",
                     f"x{_n(med.get('ratio_cold'))} / x{_n(med.get('ratio_warm'))}", "", ""))
        out += _table(("round", "loop", "kernel, cold", "kernel, warm", "ratio cold / warm", "samples",
                       "held to 1 mm at (loop / kernel)"), rows) + [""]
    if commands:
        out += ["## `beamctl bench --commands`", "",
                "Whole commands as a user starts them, each a process of its own (imports, compiled code "
                "from its cache, the work, the files written), taken in turn after a warm-up round; wall "
                "time:", ""]
        rows = [(f"`beamctl {name}`", f"{_n(t.get('median_s'), 2)} s",
                 f"{_n(t.get('min_s'), 2)} to {_n(t.get('max_s'), 2)} s", str(len(t.get("runs_s", []))))
                for name, t in (_get(commands, "commands") or {}).items()]
        out += _table(("command", "median", "least to most", "rounds"), rows) + [""]
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------
# running the benchmarks

def _machine() -> dict:
    cpu = ""
    try:
        cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                    if line.startswith("model name")), "")
    except OSError:
        pass
    cores = os.cpu_count()
    return {"description": f"{cores} cores ({cpu or platform.processor() or 'unknown CPU'}), "
                           f"{platform.system()} {platform.release()}, Python {platform.python_version()}",
            "cores": cores, "cpu": cpu, "kernel": platform.release(), "python": platform.python_version()}


def _loadavg() -> str:
    try:
        return " ".join(Path("/proc/loadavg").read_text().split()[:3])
    except OSError:
        return "unknown"


def _git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True).stdout.strip()


def measure() -> None:
    """Run ``beamctl bench --json``, ``--offline --json`` and ``--commands --json`` one after another and
    write their output, and when and where they ran, to docs/measured/."""
    import time
    from importlib.metadata import version

    MEASURED.mkdir(exist_ok=True)
    commit = _git("rev-parse", "--short", "HEAD")
    if _git("status", "--porcelain", "--untracked-files=no"):
        commit += " (with uncommitted changes in the working tree)"
    about = {"date": datetime.date.today().isoformat(), "machine": _machine(), "beamctl": version("beamctl"),
             "commit": commit, "runs": []}
    for name, args in (("bench", []), ("offline", ["--offline"]), ("commands", ["--commands"])):
        command = ["beamctl", "bench", *args, "--json"]
        run = {"file": BENCH_FILES[name], "command": " ".join(command), "load_before": _loadavg(),
               "started": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")}
        start = time.monotonic()
        done = subprocess.run(command, capture_output=True, text=True, check=True)
        json.loads(done.stdout)
        (MEASURED / BENCH_FILES[name]).write_text(done.stdout)
        run.update(wall_s=round(time.monotonic() - start, 1), load_after=_loadavg())
        about["runs"].append(run)
    (MEASURED / BENCH_FILES["about"]).write_text(json.dumps(about, indent=1) + "\n")


# ---------------------------------------------------------------------------------------------
# the MkDocs hook

_MARKER = re.compile(r"<!-- beamctl-(config: *([\w.]+)|bench) -->")


def _replace(match: re.Match) -> str:
    if match.group(1) == "bench":
        return bench_page()
    section = match.group(2)
    return renamed_reference() if section == "renamed" else section_reference(section)


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """MkDocs event: the markers of a page replaced by what they stand for."""
    return _MARKER.sub(_replace, markdown)


def main(argv: list[str]) -> int:
    what = argv[0] if argv else ""
    if what == "config":
        print(config_reference_all())
    elif what == "bench":
        print(bench_page())
    elif what == "measure":
        measure()
    else:
        print(__doc__.split("As a script::", 1)[1], file=sys.stderr)
        return 2
    return 1 if _problems else 0


if __name__ == "__main__":
    logging.basicConfig(format="%(levelname)s: %(message)s")
    sys.exit(main(sys.argv[1:]))
