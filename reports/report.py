"""A run's telemetry read for people: its series in physical units, its state changes and
faults, its figures of merit, and one self-contained HTML page (``beamctl report``); the
figures of ``beamctl log plot``.

A recording (``.btl``, from ``beamctl run`` or ``beamctl experiment --telemetry``) holds every
sample's record and, in its header, the settings it was recorded with (rt/telemetry.py,
``controller_meta``): the model whose mode shapes turn the modal displacements q into the
lateral deflection in mm (the gauges' reconstruction, as ``beamctl experiment`` measures it), the
voltage limits and the sample rate. A recording made before the header held the model is read
with the paper's Table 1 model, and says so.
"""

from __future__ import annotations

import base64
import html
import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from beamctl.common.outputs import replacing
from beamctl.config.schema import ConfigError
from beamctl.models import build_model, critical_load, load_parameters
from beamctl.models.modal import Deflection
from beamctl.models.params import parameters_from_dict
from beamctl.reports import plots
from beamctl.reports.plots import OFF_SCALE_M, RunCurves, png_bytes
from beamctl.reports.record import DEFAULT_VOLTAGE_LIMITS_V, FIGURE_POINTS, RunRecord
from beamctl.rt.controller import FLAG_NO_NEW_SAMPLE
from beamctl.rt.safety import DESCRIPTIONS, Fault, State
from beamctl.rt.telemetry import TelemetryError, read_telemetry
from beamctl.simulation.experiment import direction_at, first_crossing

FAILURE_DEFLECTION_M = 1.0e-3         # the paper's larger admissible deflection (section 4)
LOAD_VARIES_N = 100.0                 # a run whose load moved less has no deflection-versus-load figure
REPORT_DPI = 100
# a run this long whose stacks saturated or that faulted gets a second figure over time: the
# last moments, from EVENT_LEAD_S before the first saturation or fault to the end
LONG_RUN_S = 10.0
EVENT_LEAD_S = 2.0
EVENT_AFTER_S = 2.0
SATURATION_EVENT_S = 0.01           # a saturation this long is an event of the run


def _model(meta: dict):
    """(model, note): the recording's model, else the paper's Table 1 (noted)."""

    if isinstance(meta.get("model"), dict):
        try:
            return build_model(parameters_from_dict(meta["model"])), "the recording's model"
        except ConfigError as exc:
            raise TelemetryError(f"the model in the header is not valid: {exc}") from None
    return build_model(load_parameters()), "the paper's Table 1 model (the recording names no model)"


def load_run(path: str | Path) -> RunRecord:
    """Read a recording and turn it into physical units; a file that is not a recording, or
    holds no sample, is refused (``TelemetryError``, one line)."""

    path = Path(path)
    header, rows = read_telemetry(path)
    col = {name: i for i, name in enumerate(header["columns"])}
    missing = [c for c in ("time_s", "state", "q_1y", "voltage_a1_V", "load_N") if c not in col]
    if missing:
        raise TelemetryError(f"{path}: not a controller recording (no column {missing[0]!r})")
    recorded = len(rows)
    rows = rows[np.isfinite(rows[:, col["time_s"]])]
    if not len(rows):
        raise TelemetryError(f"{path}: the recording holds no sample")
    meta = header.get("meta") or {}
    model, note = _model(meta)
    q = rows[:, col["q_1y"]:col["q_1y"] + 4]
    mag, dy, dz = Deflection(model).series(q)
    time_s = rows[:, col["time_s"]] - rows[0, col["time_s"]]
    settings = meta.get("controller") or {}
    limits = (float(settings.get("actuators.min_voltage_v", DEFAULT_VOLTAGE_LIMITS_V[0])),
              float(settings.get("actuators.max_voltage_v", DEFAULT_VOLTAGE_LIMITS_V[1])))
    rate = meta.get("sample_rate_hz")
    if not rate:
        periods = np.diff(time_s)
        periods = periods[periods > 0]
        rate = 1.0 / float(np.median(periods)) if periods.size else math.nan

    def column(name: str) -> np.ndarray:
        return rows[:, col[name]] if name in col else np.full(len(rows), np.nan)

    return RunRecord(
        path=path, meta=meta, model_note=note, sample_rate_hz=float(rate), time_s=time_s,
        load_n=column("load_N"), load_filtered_n=column("load_filtered_N"),
        deflection_m=mag, deflection_y_m=dy, deflection_z_m=dz,
        voltages_v=rows[:, col["voltage_a1_V"]:col["voltage_a1_V"] + 6],
        state=column("state").astype(int), fault=column("fault").astype(int),
        flags=np.nan_to_num(column("flags")).astype(int), step_us=column("step_us"),
        answer_age_us=column("answer_age_us"), late_answers=column("late_answers"),
        recorded_rows=recorded, incomplete_row_bytes=int(header.get("incomplete_row_bytes", 0)),
        critical_load_n=float(critical_load(model)), voltage_limits_v=limits,
        bias_voltage_v=float(settings.get("actuators.bias_voltage_v", 0.5 * sum(limits))), settings=settings)


def warnings(run: RunRecord) -> list[str]:
    """What a reader of the run's figures should know: a recording cut off mid-row, a
    deflection computed with a model the recording does not name."""
    out = []
    if run.incomplete_row_bytes:
        out.append(f"{run.path} holds {run.recorded_rows} complete rows and ends in an incomplete row "
                   f"({run.incomplete_row_bytes} bytes ignored: the recording was cut off mid-write)")
    if not isinstance(run.meta.get("model"), dict):
        out.append(f"{run.path} names no model: the deflection in mm is computed with "
                   f"{run.model_note.split(' (')[0]}")
    return out


def state_name(code: int) -> str:
    try:
        return State(code).name
    except ValueError:
        return f"state {code}"


def fault_name(code: int) -> str:
    try:
        return Fault(code).name
    except ValueError:
        return f"fault {code}"


@dataclass(frozen=True)
class Event:
    """A change of the supervisor's state or fault."""

    time_s: float
    load_n: float
    state: str
    fault: str
    text: str


def events(run: RunRecord) -> list[Event]:
    """The first state and every change of state or fault, in order."""
    changed = np.flatnonzero((np.diff(run.state) != 0) | (np.diff(run.fault) != 0)) + 1
    out = []
    for i in (0, *changed.tolist()):
        state, fault = state_name(run.state[i]), fault_name(run.fault[i])
        if run.fault[i] != Fault.NONE:
            try:
                text = f"{fault}: {DESCRIPTIONS[Fault(run.fault[i])]}"
            except ValueError:
                text = fault
        else:
            text = "initial state" if i == 0 else "no fault"
        out.append(Event(time_s=float(run.time_s[i]), load_n=float(run.load_n[i]), state=state,
                         fault=fault, text=text))
    return out


def faults(run: RunRecord) -> list[str]:
    """The names of the faults the run latched, in order."""
    names: list[str] = []
    for e in events(run):
        if e.fault != Fault.NONE.name and e.fault not in names:
            names.append(e.fault)
    return names


def _longest(mask: np.ndarray) -> int:
    """The longest run of True in ``mask``, in samples."""
    if not mask.any():
        return 0
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return int((ends - starts).max())


def _max_mm(deflection_m: np.ndarray) -> float | None:
    """The largest finite deflection in mm (a recording of a beam that ran away before the
    simulated rig had end stops holds inf and nan)."""
    finite = deflection_m[np.isfinite(deflection_m)]
    return float(finite.max() * 1e3) if finite.size else None


def _lost(run: RunRecord, passed: np.ndarray) -> dict[str, Any] | None:
    """Where the beam was lost (its deflection first passed 1 mm): the load, the time, the
    supervisor's state then and the run's first fault (None: not lost)."""
    if not passed.size:
        return None
    i = int(passed[0])
    latched = np.flatnonzero(run.fault != Fault.NONE)
    return {"load_n": float(run.load_n[i]), "time_s": float(run.time_s[i]),
            "state": state_name(run.state[i]),
            "fault": fault_name(run.fault[latched[0]]) if latched.size else None,
            "fault_time_s": float(run.time_s[latched[0]]) if latched.size else None}


def figures_of_merit(run: RunRecord) -> dict[str, Any]:
    """What the run achieved and how the loop kept time, SI units except where named."""

    running = run.state == State.RUNNING
    rate = run.sample_rate_hz
    load = run.load_n          # the load cell: the beam's load without the schedule filter's lag
    passed = np.flatnonzero(run.deflection_m > FAILURE_DEFLECTION_M)
    before = np.arange(len(load)) < (passed[0] if passed.size else len(load))
    held = running & before & np.isfinite(load)
    saturated = run.saturated("A") | run.saturated("B")
    ages = run.answer_age_us[np.isfinite(run.answer_age_us)]
    steps = run.step_us[np.isfinite(run.step_us)]
    late = run.late_answers[np.isfinite(run.late_answers)]
    period_us = 1e6 / rate if rate == rate else math.nan
    return {
        "samples": len(run.time_s),
        "duration_s": float(run.time_s[-1]),
        "sample_rate_hz": rate,
        "max_deflection_mm": _max_mm(run.deflection_m),
        "max_deflection_running_mm": _max_mm(run.deflection_m[running]) if running.any() else None,
        "lost": _lost(run, passed),
        "load_range_n": [float(np.nanmin(run.load_n)), float(np.nanmax(run.load_n))],
        "load_held_n": float(load[held].max()) if held.any() else None,
        "load_at_0.5mm_n": first_crossing(load, run.deflection_m, 0.5e-3),
        "load_at_1.0mm_n": first_crossing(load, run.deflection_m, FAILURE_DEFLECTION_M),
        "direction_at_1.0mm_deg": (direction_at(run.deflection_m, run.deflection_y_m, run.deflection_z_m,
                                                FAILURE_DEFLECTION_M) if passed.size else None),
        "voltage_range_v": [float(run.voltages_v.min()), float(run.voltages_v.max())],
        "saturated_time_s": float(saturated.sum() / rate),
        "longest_saturation_s": float(_longest(saturated) / rate),
        "late_answers": int(late.max()) if late.size else 0,
        "answer_age_p99_us": float(np.percentile(ages, 99)) if ages.size else None,
        "steps_over_period": int((steps > period_us).sum()) if steps.size else 0,
        "step_max_us": float(steps.max()) if steps.size else None,
        "missing_samples": int(((run.flags & FLAG_NO_NEW_SAMPLE) != 0).sum()),
        "faults": faults(run),
        "end_state": state_name(run.state[-1]),
    }


def run_curves(run: RunRecord, color: str = "tab:blue"):
    """The run as figure 7's curves (plots.RunCurves) until its deflection went off the scale,
    thinned to ``FIGURE_POINTS``; held while controlled and the stacks had room."""

    lost = np.flatnonzero(run.deflection_m > OFF_SCALE_M)
    end = int(lost[0]) + 1 if lost.size else len(run.time_s)       # one sample off the scale, no more
    k = max(1, math.ceil(end / FIGURE_POINTS))
    part = slice(0, end, k)
    saturated = run.saturated("A")[part] | run.saturated("B")[part]
    running = run.state[part] == State.RUNNING
    held = np.flatnonzero(saturated | (~running & (np.cumsum(running) > 0)))
    load = run.load_n          # the load cell: the beam's load without the schedule filter's lag
    return RunCurves(label=run.label, color=color, controlled=run.controlled, load_n=load[part],
                     deflection_y_m=run.deflection_y_m[part], deflection_z_m=run.deflection_z_m[part],
                     held_samples=int(held[0]) if held.size else None)


def first_event_s(run: RunRecord) -> float | None:
    """The time of the run's first fault or first saturation lasting SATURATION_EVENT_S (a
    stack touching its limit for a sample or two as the controller starts is no event; None:
    neither happened)."""
    saturated = run.saturated("A") | run.saturated("B")
    rate = run.sample_rate_hz if math.isfinite(run.sample_rate_hz) else 0.0
    need = max(1, int(round(SATURATION_EVENT_S * rate)))
    lasting = np.convolve(saturated.astype(np.int32), np.ones(need, dtype=np.int32), "full")[:len(saturated)]
    starts = np.flatnonzero(lasting >= need) - (need - 1)       # where a saturation that lasted began
    hits = np.flatnonzero(run.fault != Fault.NONE)
    times = [float(run.time_s[i]) for i in (hits[:1].tolist() + starts[:1].tolist())]
    return min(times) if times else None


def run_figures(run: RunRecord) -> dict[str, Any]:
    """The run's figures by file name: over time (and, for a long run, its last moments from
    just before its first saturation or fault), figure 7a where the load moved, and 7b."""

    figures = {"run_over_time.png": plots.run_over_time(run)}
    event = first_event_s(run)
    if event is not None and run.time_s[-1] > LONG_RUN_S:
        start = max(0.0, event - EVENT_LEAD_S)
        # to EVENT_AFTER_S past the event, or past where the beam went off the scale: the event in
        # the middle of the window, not squeezed into its left edge by a long wait at bias after it
        lost = np.flatnonzero(run.deflection_m > OFF_SCALE_M)
        end = event + EVENT_AFTER_S
        if lost.size and run.time_s[lost[0]] >= event:
            end = max(end, float(run.time_s[lost[0]]) + 0.5)
        end = min(end, float(run.time_s[-1]))
        part = f"{start:.2f} to {end:.2f} s ({event - start:.2f} s before its first saturation or fault)"
        figures["run_end.png"] = plots.run_over_time(run.window(start, end), part)
    curves = [run_curves(run)]
    if np.nanmax(run.load_n) - np.nanmin(run.load_n) > LOAD_VARIES_N:
        figures["fig7a_run.png"] = plots.figure_7a(curves, run.critical_load_n, paper=False)
    figures["fig7b_run.png"] = plots.figure_7b(curves, paper=False)
    return figures


# -- the HTML page ----------------------------------------------------------------------------

_CSS = """body{font-family:sans-serif;max-width:1200px;margin:2em auto;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em}td,th{border:1px solid #ccc;padding:.25em .6em;
text-align:left;vertical-align:top}th{background:#f3f3f3}.fault{color:#b00;font-weight:bold}
img{max-width:100%;border:1px solid #ddd;margin:.5em 0}code{font-size:90%}"""


def _setting(value: Any) -> str:
    """A setting as a file would say it: 0.5, [-200, 1200] as -200, 1200, true."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, list):
        return ", ".join(_setting(v) for v in value)
    return str(value)


def _table(rows: list[tuple[str, ...]], head: tuple[str, ...] | None = None,
           fault_rows: set[int] = frozenset()) -> str:
    out = ["<table>"]
    if head:
        out.append("<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in head) + "</tr>")
    for i, row in enumerate(rows):
        cls = ' class="fault"' if i in fault_rows else ""
        out.append(f"<tr{cls}>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def _lost_text(lost: dict[str, Any] | None) -> str:
    if lost is None:
        return "no"
    text = f"at {lost['load_n']:.0f} N, {lost['time_s']:.2f} s, {lost['state']}"
    if lost["fault"]:
        dt = lost["time_s"] - lost["fault_time_s"]
        text += (f", {dt:.2f} s after {lost['fault']} (the stacks ramping to bias)" if dt >= 0
                 else f"; {lost['fault']} {-dt:.2f} s later")
    return text


def merit_rows(merit: dict[str, Any]) -> list[tuple[str, str]]:
    """The figures of merit as (name, value with unit) for a person."""
    def mm(v):
        return "-" if v is None else f"{v:.3f} mm"

    def n(v):
        return "-" if v is None else f"{v:.0f} N"

    return [
        ("samples", f"{merit['samples']} at {merit['sample_rate_hz']:.0f} Hz ({merit['duration_s']:.2f} s)"),
        ("end state", merit["end_state"]),
        ("faults", ", ".join(merit["faults"]) or "none"),
        ("max deflection (gauges)", mm(merit["max_deflection_mm"])),
        ("max deflection while controlled", mm(merit["max_deflection_running_mm"])),
        ("load range (load cell)", f"{merit['load_range_n'][0]:.0f} to {merit['load_range_n'][1]:.0f} N"),
        ("load held (controlled, deflection below 1.0 mm)", n(merit["load_held_n"])),
        ("beam lost (deflection past 1.0 mm)", _lost_text(merit.get("lost"))),
        ("load at 0.5 mm / 1.0 mm", f"{n(merit['load_at_0.5mm_n'])} / {n(merit['load_at_1.0mm_n'])}"
                                    if merit["load_at_0.5mm_n"] is not None else "not reached"),
        ("direction at 1.0 mm", "-" if merit["direction_at_1.0mm_deg"] is None
         else f"{merit['direction_at_1.0mm_deg']:.0f} deg from +y"),
        ("voltage range (six stacks)",
         f"{merit['voltage_range_v'][0]:.1f} to {merit['voltage_range_v'][1]:.1f} V"),
        ("saturated (either support)", f"{merit['saturated_time_s']:.3f} s in all, longest "
                                       f"{merit['longest_saturation_s']:.3f} s"),
        ("late answers", str(merit["late_answers"])
         + ("" if merit["answer_age_p99_us"] is None
            else f" (answer age p99 {merit['answer_age_p99_us']:.0f} us)")),
        ("control steps longer than the period (overruns of the step)", str(merit["steps_over_period"])
         + ("" if merit["step_max_us"] is None else f" (longest step {merit['step_max_us']:.0f} us)")),
        ("samples missing (no new sample in a period)", str(merit["missing_samples"])),
    ]


def setting_rows(run: RunRecord) -> list[tuple[str, str]]:
    """The recording's settings from its header, one row each (the model's parameters last)."""
    rows = []
    for key, value in run.meta.items():
        if key in ("controller", "model"):
            continue
        if key == "design" and isinstance(value, dict):
            loads = value.get("loads_n") or []
            value = ", ".join([str(value.get("kind", "?")), f"{value.get('sample_rate_hz', math.nan):g} Hz",
                               f"{value.get('schedule', '?')} schedule"]
                              + ([f"gains for {loads[0]:g}..{loads[-1]:g} N"] if loads else []))
        rows.append((key, json.dumps(value) if isinstance(value, dict | list) else _setting(value)))
    rows += [(f"controller.{k}", _setting(v)) for k, v in run.settings.items()]
    rows.append(("deflection computed with", run.model_note))
    if run.critical_load_n:
        rows.append(("critical load of that model", f"{run.critical_load_n:.0f} N"))
    rows += [("warning", text) for text in warnings(run)]
    return rows


def html_page(run: RunRecord, merit: dict[str, Any], images: dict[str, bytes]) -> str:
    """One self-contained page: figures as base64 PNG, no external resource."""
    evs = events(run)
    event_rows = [(f"{e.time_s:.4f}", f"{e.load_n:.0f}", e.state, e.text) for e in evs]
    fault_rows = {i for i, e in enumerate(evs) if e.fault != Fault.NONE.name}
    figures = "\n".join(
        f'<figure><img alt="{html.escape(name)}" src="data:image/png;base64,'
        f'{base64.b64encode(data).decode()}"><figcaption>{html.escape(name)}</figcaption></figure>'
        for name, data in images.items())
    model = html.escape(json.dumps(run.meta.get("model"), indent=1)) if run.meta.get("model") else ""
    faults = ", ".join(merit["faults"]) or "none"
    title = html.escape(f"beamctl run report: {run.label}")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title><style>{_CSS}</style></head>
<body>
<h1>{title}</h1>
<p>{html.escape(str(run.path))}: {merit['samples']} samples, {merit['duration_s']:.2f} s, ended
{html.escape(merit['end_state'])}; faults: <span class="fault">{html.escape(faults)}</span></p>
<h2>Figures of merit</h2>
{_table(merit_rows(merit))}
<h2>State changes and faults</h2>
{_table(event_rows, ("time s", "load N", "state", "fault"), fault_rows)}
<h2>Figures</h2>
{figures}
<h2>Settings</h2>
{_table(setting_rows(run), ("setting", "value"))}
{f"<details><summary>model parameters</summary><pre>{model}</pre></details>" if model else ""}
</body></html>
"""


def write_report(path: str | Path, out: str | Path,
                 warn: Callable[[str], None] | None = None) -> tuple[Path, dict[str, Any]]:
    """Read the recording ``path`` and write its page to ``out`` (whole or not at all); return
    the page's path and the figures of merit. ``warn`` is told what ``warnings`` finds (the
    page states it too)."""

    run = load_run(path)
    for text in warnings(run):
        if warn:
            warn(text)
    merit = figures_of_merit(run)
    images = {name: png_bytes(fig, REPORT_DPI) for name, fig in run_figures(run).items()}
    page = html_page(run, merit, images)
    out = Path(out)
    with replacing(out) as temp:
        Path(temp).write_text(page, encoding="utf-8")
    return out, merit
