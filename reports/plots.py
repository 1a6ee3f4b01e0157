"""Figures (matplotlib, Agg backend: no screen needed)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from beamctl.common.outputs import replacing
from beamctl.config.schema import ConfigError
from beamctl.models import build_model, critical_load, eigenfrequencies, fe_frequency_response
from beamctl.models.fe import FEModel
from beamctl.models.fit import model_response
from beamctl.models.measured import FrfData, resonances
from beamctl.models.modal import ModalModel
from beamctl.models.params import ModelParameters
from beamctl.reports.record import RunRecord
from beamctl.rt.safety import Fault, State
from beamctl.simulation.experiment import direction_at
from beamctl.simulation.study import survival

# the figures of ``beamctl experiment``'s report
FIG7A, FIG7B, VOLTAGES = "fig7a_deflection_vs_load.png", "fig7b_path_yz.png", "voltages_vs_load.png"
EXPERIMENT_FIGURES = (FIG7A, FIG7B, VOLTAGES)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _finish(fig, ax, path: Path, *, xlabel: str, ylabel: str, title: str,
            legend: dict | None = None) -> Path:
    """Label, grid and save a single-axes figure."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    if legend is not None:
        ax.legend(**legend)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return save(fig, path)


def save(fig, path: Path, dpi: float = 120) -> Path:
    """Save the figure whole (never half a PNG, even when interrupted) and close it."""
    data = png_bytes(fig, dpi)
    with replacing(path) as temp:
        Path(temp).write_bytes(data)
    return Path(path)


# a figure's PNG in a palette of this many colours: the same to the eye (lines, text and a few
# shades of fill), a third of the bytes of matplotlib's own PNG (figure 7a: 52 kB against
# 164 kB) and written in less time (0.71 and 0.89 x, medians of 10 in two runs)
PNG_COLOURS = 128


def png_bytes(fig, dpi: float = 100) -> bytes:
    """The figure as PNG bytes (palette colours, ``PNG_COLOURS``); the figure is closed."""
    import io

    from PIL import Image

    try:
        fig.set_dpi(dpi)
        rgba, size = fig.canvas.print_to_buffer()       # the Agg canvas (_pyplot)
    finally:
        _pyplot().close(fig)
    palette = Image.frombuffer("RGBA", size, rgba, "raw", "RGBA", 0, 1).convert("RGB").quantize(
        colors=PNG_COLOURS, method=Image.Quantize.FASTOCTREE)
    out = io.BytesIO()
    palette.save(out, format="PNG")
    return out.getvalue()


def _finish_bode(fig, ax_m, ax_p, path: Path, title: str) -> Path:
    """Label, grid and save an amplitude/phase figure of Gy/z (figures 5a and 6)."""
    ax_m.set_ylabel("|Gy/z| in 1/N (strain per N)")
    ax_p.set_ylabel("arg Gy/z in deg")
    ax_p.set_xlabel("frequency f in Hz")
    ax_p.set_yticks([-180, -90, 0, 90, 180])
    ax_m.set_title(title)
    for ax in (ax_m, ax_p):
        ax.grid(True, alpha=0.3)
    ax_m.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    return save(fig, path)


def eigenfrequencies_vs_load(model: FEModel, reduced: ModalModel, path: Path,
                             measured: Sequence[FrfData] = ()) -> Path:
    """Figure 5b: the first three eigenfrequencies versus axial load up to the critical load; the
    resonances of ``measured`` frequency responses as points (y: triangles, z: circles)."""
    plt = _pyplot()
    fcr = critical_load(model)
    loads = np.linspace(0.0, fcr, 200)
    full = np.array([eigenfrequencies(model, f, 3) for f in loads])
    red = np.array([reduced.eigenfrequencies(f) for f in loads])
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for i in range(3):
        ax.plot(loads, full[:, i], color="k", label="full FE model" if i == 0 else None)
    for i in range(2):
        ax.plot(loads, red[:, i], "--", color="tab:red",
                label=f"reduced model (modes at {reduced.reference_load:.0f} N)" if i == 0 else None)
    for plane, marker in (("y", "v"), ("z", "o")):
        points = [(d.load_n, f) for d in measured for f in resonances(d)[plane]]
        if points:
            x, y = zip(*points, strict=True)
            ax.plot(x, y, marker, mfc="none", color="tab:blue", label=f"measured, {plane} direction")
    ax.axvline(fcr, color="0.5", lw=0.8)
    ax.text(fcr, ax.get_ylim()[1] * 0.95, f" Fx,cr = {fcr:.0f} N", ha="right", va="top")
    return _finish(fig, ax, path, xlabel="axial load Fx in N", ylabel="eigenfrequency f in Hz",
                   title="Eigenfrequencies f1/2/3 versus axial load (figure 5b)",
                   legend={"loc": "upper left", "bbox_to_anchor": (0.0, 0.88)})


def frequency_response_full_vs_reduced(model: FEModel, reduced: ModalModel, axial_load: float,
                                       freqs_hz: np.ndarray, path: Path) -> Path:
    """Figure 6: amplitude and phase of Gy (and Gz) from the full and the reduced model."""
    plt = _pyplot()
    g_full = fe_frequency_response(model, axial_load, freqs_hz)
    g_red = reduced.frequency_response(axial_load, freqs_hz)
    fig, (ax_m, ax_p) = plt.subplots(2, 1, sharex=True, figsize=(7, 6))
    curves = [(g_full[:, 0, 0], "k", "-", "full FE model, Gy"),
              (g_full[:, 1, 1], "tab:gray", ":", "full FE model, Gz"),
              (g_red[:, 0, 0], "tab:red", "--", "reduced modal model, Gy")]
    for g, color, style, label in curves:
        ax_m.semilogy(freqs_hz, np.abs(g), style, color=color, label=label)
        phase = np.degrees(np.angle(g))
        phase[phase <= -180.0 + 1e-6] += 360.0  # report the half-turn as +180 deg throughout
        ax_p.plot(freqs_hz, phase, style, color=color)
    return _finish_bode(fig, ax_m, ax_p, path, f"Frequency responses at Fx = {axial_load:g} N (figure 6)")


def frequency_response_measured(d: FrfData, models: Sequence[tuple[str, np.ndarray]], path: Path) -> Path:
    """Figure 5a: amplitude and phase of Gy = eps_y1 / Fay,A and Gz = eps_z1 / Faz,A measured
    (y dashed, z dotted) against each model's (label, [nf x 4 x 4] response) at the measurement's
    frequencies."""
    plt = _pyplot()
    f = d.frequencies_hz
    fig, (ax_m, ax_p) = plt.subplots(2, 1, sharex=True, figsize=(7, 6))

    def draw(g, style, color, label, width=1.2):
        ax_m.semilogy(f, np.abs(g), style, color=color, label=label, lw=width)
        ax_p.plot(f, np.degrees(np.angle(g)), style, color=color, lw=width)

    colors = ("0.55", "k", "tab:red")
    for (label, g), color in zip(models, colors, strict=False):
        draw(g[:, 0, 0], "-", color, f"{label}, Gy (= Gz)", 1.6 if color == "k" else 1.0)
    for (i, j), style, name in (((0, 0), "--", "Gy"), ((1, 1), ":", "Gz")):
        if np.all(np.isfinite(d.frf[:, i, j])):
            draw(d.frf[:, i, j], style, "tab:blue", f"measured, {name}")
    return _finish_bode(fig, ax_m, ax_p, path,
                        f"Frequency responses at Fx = {d.load_n:.0f} N, model and measurement (figure 5a)")


# a panel's gains span more than this factor: a log axis, else a linear one from zero
LOG_AXIS_RANGE = 20.0
# a gain whose spread over the loads is below this fraction of its size is constant: its
# spread is the design's rounding (1e-10 relative for the paper's integral gains), not a trend
CONSTANT_GAIN = 1e-6


def _gain_panel(ax, loads_n: np.ndarray, curves: Sequence[tuple[str, np.ndarray]], marker: str) -> None:
    """|gain| versus load, one curve per (label, values): on a log axis where the panel spans
    decades, else on a linear one from zero; a constant gain drawn as its value, named."""
    magnitudes = [np.abs(v) for _, v in curves]
    every = np.concatenate(magnitudes)
    positive = every[every > 0]
    log = positive.size > 0 and positive.max() > LOG_AXIS_RANGE * positive.min()
    for (label, signed), v, style in zip(curves, magnitudes, ("-", "--", ":"), strict=False):
        sign = _sign_note(loads_n, signed)
        shown = label if "|" in label else f"|{label}|"         # "sum |C|" is a magnitude already
        if np.ptp(v) <= CONSTANT_GAIN * v.max():
            v = np.full_like(v, v.mean())
            label = f"{shown} = {v[0]:.4g} (constant{', ' + sign if sign else ''})"
        else:
            label = shown + (f" ({sign})" if sign else "")
        ax.plot(loads_n, v, marker + style, ms=3, label=label)
    if log:
        ax.set_yscale("log")
    else:
        ax.set_ylim(0.0, 1.15 * every.max() if every.max() > 0 else 1.0)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="lower left")


def _sign_note(loads_n: np.ndarray, values: np.ndarray) -> str:
    """What the magnitude hides: "negative" throughout, or where the sign changes ("" when
    positive throughout)."""
    values = np.asarray(values, dtype=float)
    if np.all(values >= 0):
        return ""
    if np.all(values <= 0):
        return "negative"
    flips = np.flatnonzero(np.signbit(values[1:]) != np.signbit(values[:-1]))
    where = ", ".join(f"{0.5 * (loads_n[i] + loads_n[i + 1]):.0f}" for i in flips[:3])
    return f"changes sign near {where} N"


def gains_figure(table):
    """Gains versus axial load for support A, y direction: |K| per state of an integral-lqr
    table, else the compensator's |D| and |Ki| per gauge channel (the figure, not saved)."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(12, 4), sharex=True)
    if table.gains is not None:
        names = {0: "q1y", 2: "q2y", 4: "dq1y/dt", 6: "dq2y/dt", 8: "int q1y", 10: "int q2y"}
        rows = table.gains[:, 0, :]
        groups = [("displacement gains (N per modal unit)", (0, 2)),
                  ("velocity gains (N s per modal unit)", (4, 6)),
                  ("integral gains (N per modal unit s)", (8, 10))]
        ylabel, title = "|K| (row Fay,A; signs in the legend)", "Integral LQR gains K(Fx)"
    else:
        comp = table.compensator
        names = {0: "D y1", 1: "D y2", 2: "Ki y1", 3: "Ki y2", 4: "sum |C|"}
        rows = np.column_stack([comp.d[:, 0, 0], comp.d[:, 0, 2], comp.ki[:, 0, 0], comp.ki[:, 0, 2],
                                np.abs(comp.c[:, 0, :]).sum(axis=1)])
        groups = [("direct gains D (N per strain)", (0, 1)), ("integral gains Ki (N per unit of xi)", (2, 3)),
                  ("state gains, sum of |C| (N per state unit)", (4,))]
        ylabel = "magnitude (row Fay,A; signs in the legend)"
        title = f"Compensator gains ({table.design.kind})"
    marker = "o" if table.schedule.mode == "paper" else ""
    for ax, (group_title, cols) in zip(axes, groups, strict=True):
        _gain_panel(ax, table.loads_n, [(names[c], rows[:, c]) for c in cols], marker)
        ax.set_title(group_title, fontsize=9)
        ax.set_xlabel("axial load Fx in N")
    axes[0].set_ylabel(ylabel)
    fcr = None
    try:

        fcr = critical_load(build_model(table.model_parameters))
    except ConfigError:
        pass
    if fcr:
        for ax in axes:
            ax.axvline(fcr, color="0.5", lw=0.8, ls="--")
    fig.suptitle(f"{title}, {table.schedule.mode} schedule (dashed: critical load {fcr:.0f} N)"
                 if fcr else title)
    fig.tight_layout()
    return fig


def gains_vs_load(table, path: Path) -> Path:
    """``gains_figure`` saved as PNG."""
    return save(gains_figure(table), path)


# -- figure 7 ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class RunCurves:
    """One run's series for figure 7 (SI units), in sample order."""

    label: str
    color: str
    controlled: bool
    load_n: np.ndarray
    deflection_y_m: np.ndarray          # the deflection at its largest point, y and z components
    deflection_z_m: np.ndarray
    beam_deflection_m: np.ndarray | None = None   # the simulated beam's own, not seen by the gauges
    held_samples: int | None = None     # samples before the stacks first reached a limit (None: all)
    style: str = "-"
    width: float = 1.4

    @property
    def deflection_m(self) -> np.ndarray:
        return np.hypot(self.deflection_y_m, self.deflection_z_m)


@dataclass(frozen=True)
class Failure:
    """Where a run was let go: the direction of its deflection where it passed ``at_m``
    (``passed`` False: it never did, and the direction is the one at its end)."""

    angle_deg: float
    load_n: float
    at_m: float
    passed: bool


# the paper's measurements (section 4, figure 7)
PAPER_UNCONTROLLED_POINTS = ((2438.0, 0.5e-3), (2723.0, 1.0e-3))    # load N, deflection m
PAPER_CONTROLLED_MAX_LOAD_N = 3223.0
PAPER_DIRECTION_DEG = {False: 234.0, True: 128.0}                    # uncontrolled, controlled
FAILURE_DEFLECTION_M = 1.0e-3
# a beam this far out has failed (what a recording holds beyond it is a lost beam or a simulation
# diverging): a figure's scale stops here
OFF_SCALE_M = 5.0e-3
# a figure 7a whose runs start above this load is drawn from where they start, not from 0 N
ZOOM_FROM_N = 1000.0
# a controlled run whose deflection while held stays below this fraction of the figure's
# scale lies flat in it: figure 7a magnifies the controlled runs
FLAT_FRACTION = 0.1
# the magnified panel is scaled to what a held run's deflection stays below for all but its
# last samples (a run's rise in the moments before its stacks reach their limit runs off the top)
HELD_PERCENTILE = 98.0


def failure(run: RunCurves, at_m: float = FAILURE_DEFLECTION_M) -> Failure | None:
    """The direction and load where ``run``'s deflection first passed ``at_m``, else at its end."""

    d = run.deflection_m
    if not d.size:
        return None
    above = np.flatnonzero(d > at_m)
    i = int(above[0]) if above.size else len(d) - 1
    angle = direction_at(d, run.deflection_y_m, run.deflection_z_m, at_m)
    return Failure(angle_deg=float(angle), load_n=float(run.load_n[i]), at_m=at_m, passed=bool(above.size))


def _scale(runs: Sequence[RunCurves]) -> float:
    """The deflection figure 7 is scaled to: the largest of the runs', at most ``OFF_SCALE_M``."""
    top = max((float(np.nanmax(r.deflection_m)) for r in runs if r.deflection_m.size), default=1e-3)
    return min(top, OFF_SCALE_M) if top > 0 else 1e-3


def _held(run: RunCurves) -> np.ndarray:
    """Mask of the samples while the run was held: before its stacks first reached a limit."""
    held = np.ones(len(run.load_n), dtype=bool)
    if run.held_samples is not None:
        held[run.held_samples:] = False
    return held


def figure_7a(runs: Sequence[RunCurves], critical_load_n: float | None = None, paper: bool = True):
    """Figure 7a: the deflection's y and z components (absolute, as the paper plots q1,y and
    q1,z) and its magnitude versus load, in mm, every run; the paper's measured points as points
    (``paper``); and, when a controlled run lies flat at this scale, its held part magnified (µm)
    near the critical load, where the controlled runs part from the uncontrolled one."""
    plt = _pyplot()
    scale_m = _scale(runs)
    magnify = [r for r in runs if r.controlled and _held(r).any()]
    if not any(_held_top(r) < FLAT_FRACTION * scale_m for r in magnify):
        magnify = []
    loads = np.concatenate([r.load_n for r in runs]) if runs else np.zeros(1)
    finite = loads[np.isfinite(loads)]
    low = float(finite.min()) if finite.size else 0.0
    # a run that starts far up the load (a recording of the lab's 2800 to 3300 N) is drawn where it ran
    x_low = 0.0 if low < ZOOM_FROM_N else max(0.0, low - 100.0)
    x_high = max((float(finite.max()) if finite.size else 0.0) + 100.0, (critical_load_n or 0.0) + 300.0)
    mosaic = [["y", "z"], ["m", "h"]] if magnify else [["y", "z"], ["m", "m"]]
    fig, named = plt.subplot_mosaic(mosaic, figsize=(11, 7.8), layout="constrained")
    ax_y, ax_z, ax_m = named["y"], named["z"], named["m"]
    ax_h = named.get("h")
    top_mm = 1.08 * scale_m * 1e3
    panels = ((ax_y, "(a) y component |w_y|", lambda r: np.abs(r.deflection_y_m)),
              (ax_z, "(b) z component |w_z|", lambda r: np.abs(r.deflection_z_m)),
              (ax_m, "(c) magnitude |w|" + (", with the paper's measured points" if paper else ""),
               lambda r: r.deflection_m))
    for ax, title, of in panels:
        for r in runs:
            ax.plot(r.load_n, of(r) * 1e3, r.style, color=r.color, lw=r.width)
        ax.set_ylim(-0.03 * top_mm, top_mm)
        ax.set_xlim(x_low, x_high)
        ax.set_title(title, fontsize=10)
        ax.set_ylabel("deflection in mm")
    for level in (0.5, 1.0):
        ax_m.axhline(level, color="0.75", lw=0.6, zorder=0)
    if paper:
        points, values = zip(*PAPER_UNCONTROLLED_POINTS, strict=True)
        ax_m.plot(points, np.array(values) * 1e3, "o", ms=8, mfc="white", mec="k", mew=1.5, zorder=5,
                  label="paper, uncontrolled: 0.5 mm at 2438 N, 1.0 mm at 2723 N", gid="paper-uncontrolled")
        ax_m.plot([PAPER_CONTROLLED_MAX_LOAD_N], [0.0], "^", ms=9, mfc="white", mec="k", mew=1.5, zorder=5,
                  clip_on=False,
                  label=f"paper, controlled: straight until {PAPER_CONTROLLED_MAX_LOAD_N:.0f} N",
                  gid="paper-controlled")
    if critical_load_n:
        for ax in (ax_y, ax_z, ax_m, ax_h):
            if ax is not None:
                ax.axvline(critical_load_n, color="k", lw=0.8, ls="--",
                           label=f"critical load Fx,cr = {critical_load_n:.0f} N" if ax is ax_m else None)
    ax_m.legend(fontsize=7.5, loc="upper left")
    if magnify:
        held_top = max(_held_top(r) for r in magnify)
        held_loads = np.concatenate([r.load_n[_held(r)] for r in magnify])
        held_loads = held_loads[np.isfinite(held_loads)]
        handles = []
        for r in magnify:
            held = _held(r)
            for values, style, width, what in (
                    (np.abs(r.deflection_y_m[held]), "-", 1.0, "|w_y| (gauges)"),
                    (np.abs(r.deflection_z_m[held]), "--", 1.0, "|w_z| (gauges)"),
                    (r.beam_deflection_m[held] if r.beam_deflection_m is not None and r.beam_deflection_m.size
                     else None, ":", 1.4, "|w| of the simulated beam (not seen by the gauges)")):
                if values is None:
                    continue
                ax_h.plot(r.load_n[held], values * 1e6, style, color=r.color, lw=width)
                name = r.label.removeprefix("controlled, ").split(",")[0]
                handles.append(plt.Line2D([], [], color=r.color, ls=style, lw=width, label=f"{name}: {what}"))
        ax_h.set_ylim(0.0, 1.2 * held_top * 1e6)
        # where the story is: from a little below the critical load to where the stacks ran out
        if held_loads.size:
            top_held = float(held_loads.max())
            zoom_low = min(0.9 * critical_load_n, top_held - 200.0) if critical_load_n else x_low
            ax_h.set_xlim(max(x_low, zoom_low), top_held + 50.0)
        ax_h.legend(handles=handles, fontsize=6.5, loc="best")
        ax_h.set_title("(d) controlled runs magnified near Fx,cr, until their stacks reach a limit",
                       fontsize=10)
        ax_h.set_ylabel("deflection in µm")
    for ax in (ax_m, ax_h):
        if ax is not None:
            ax.set_xlabel("axial load Fx in N")
    for ax in named.values():
        ax.grid(True, alpha=0.3)
    fig.legend(handles=[plt.Line2D([], [], color=r.color, ls=r.style, lw=r.width, label=r.label)
                        for r in runs], loc="outside lower center", ncol=min(len(runs), 3), fontsize=8.5)
    fig.suptitle("Deflection versus axial load (figure 7a)")
    return fig


def _held_top(run: RunCurves) -> float:
    """The deflection (gauges or simulated beam) the run stayed below while it was held, for
    all but the last ``100 - HELD_PERCENTILE`` per cent of that time."""
    held = _held(run)
    top = np.percentile(run.deflection_m[held], HELD_PERCENTILE)
    if run.beam_deflection_m is not None and run.beam_deflection_m.size:
        top = max(top, np.percentile(run.beam_deflection_m[held], HELD_PERCENTILE))
    return float(top)


def figure_7b(runs: Sequence[RunCurves], paper: bool = True):
    """Figure 7b: each run's path in the y-z plane in a panel of its own (same scale), the
    direction it failed in marked (an arrow and its angle), the paper's direction dashed
    (``paper``); a controlled run's held part magnified in an inset."""
    plt = _pyplot()
    scale_m = _scale(runs)
    lim = 1.1 * scale_m * 1e3
    fig, axes = plt.subplots(1, len(runs), figsize=(4.3 * len(runs) + 0.4, 4.9), squeeze=False,
                             layout="constrained")
    for ax, r in zip(axes[0], runs, strict=True):
        ax.axhline(0, color="0.75", lw=0.6)
        ax.axvline(0, color="0.75", lw=0.6)
        ax.plot(r.deflection_y_m * 1e3, r.deflection_z_m * 1e3, "-", color=r.color, lw=r.width, zorder=3)
        f = failure(r)
        if paper:
            ref = math.radians(PAPER_DIRECTION_DEG[r.controlled])
            ax.plot([0, 0.92 * lim * math.cos(ref)], [0, 0.92 * lim * math.sin(ref)], "--", color="k", lw=0.9,
                    label=f"paper's direction, {PAPER_DIRECTION_DEG[r.controlled]:.0f} deg")
        if f is not None:
            a = math.radians(f.angle_deg)
            rim = (0.92 * lim * math.cos(a), 0.92 * lim * math.sin(a))
            ax.plot([0, rim[0]], [0, rim[1]], ":", color=r.color, lw=1.2, zorder=2)
            what = (f"failed at {f.angle_deg:.0f} deg ({f.load_n:.0f} N)" if f.passed
                    else f"at the end: {f.angle_deg:.0f} deg ({f.load_n:.0f} N)")
            ax.plot([rim[0]], [rim[1]], "o", ms=8, color=r.color, mec="k", zorder=4, gid="failure-direction",
                    label=what)
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        ax.grid(True, alpha=0.3)
        ax.set_title(r.label, fontsize=9, color=r.color)
        ax.set_xlabel("deflection in y in mm")
        ax.legend(fontsize=7.5, loc="upper left")
        if r.controlled:
            _held_inset(ax, r)
    axes[0][0].set_ylabel("deflection in z in mm")
    fig.suptitle("Path of the deflection in the y-z plane (figure 7b)")
    return fig


def _held_inset(ax, run: RunCurves) -> None:
    """An inset (µm) of the run's path while it was held, in the quadrant its failure leaves free."""
    held = _held(run)
    if not held.any():
        return
    y, z = run.deflection_y_m[held] * 1e6, run.deflection_z_m[held] * 1e6
    half = 1.2 * float(max(np.abs(y).max(), np.abs(z).max(), 1e-3))
    f = failure(run)
    # opposite the failure's quadrant, away from the arrow and the legend (upper left)
    right = f is None or math.cos(math.radians(f.angle_deg)) < 0
    inset = ax.inset_axes([0.58 if right else 0.05, 0.05, 0.38, 0.38])
    inset.plot(y, z, "-", color=run.color, lw=0.6)
    inset.plot([0], [0], "+", color="k", ms=6)
    inset.set_xlim(-half, half)
    inset.set_ylim(-half, half)
    inset.set_aspect("equal")
    inset.tick_params(labelsize=6)
    inset.set_title(f"held, in µm (until {run.load_n[held][-1]:.0f} N)", fontsize=6.5)


_RUN_STYLE = {"uncontrolled": ("0.35", "uncontrolled", "-", 1.6),
              "interpolate": ("tab:blue", "controlled, interpolated K(Fx), anti-windup", "-", 1.4),
              "paper": ("tab:orange", "controlled, paper's 500 N switching", "--", 2.0)}
_RUN_ORDER = {"uncontrolled": 0, "interpolate": 1, "paper": 2}


def experiment_runs(summary: dict, traces: dict) -> list[RunCurves]:
    """The experiment's runs (``run_experiment``) as figure 7's curves, uncontrolled first."""
    names = {"uncontrolled": "uncontrolled", "interpolate": "controlled", "paper": "paper_switching"}
    runs = []
    for mode, trace in sorted(traces.items(), key=lambda kv: _RUN_ORDER[kv[0]]):
        a = trace.arrays()
        color, label, style, width = _RUN_STYLE[mode]
        allocation = summary.get(names[mode], {}).get("allocation")
        if mode == "paper" and allocation == "clip":
            label += ", stacks clipped"
        runs.append(RunCurves(label=label, color=color, controlled=mode != "uncontrolled", load_n=a["load_n"],
                              deflection_y_m=a["deflection_y_m"], deflection_z_m=a["deflection_z_m"],
                              beam_deflection_m=a["true_deflection_m"] if mode != "uncontrolled" else None,
                              held_samples=_first(a["saturated"]) if mode != "uncontrolled" else None,
                              style=style, width=width))
    return runs


def _first(mask: np.ndarray) -> int | None:
    """Index of the first True in ``mask`` (None: there is none)."""
    hits = np.flatnonzero(mask)
    return int(hits[0]) if hits.size else None


def voltages_figure(summary: dict, traces: dict):
    """Per controlled run, one panel: each of the six stack voltages versus load (support A
    solid, B dashed) over the band between the lowest and the highest stack, with the limits
    (panels of their own: two translucent bands on one axis mixed into a colour no legend named)."""
    plt = _pyplot()
    modes = [m for m in traces if m != "uncontrolled"]
    fig, axes = plt.subplots(len(modes) or 1, 1, figsize=(8, 2.2 + 2.3 * max(len(modes), 1)), sharex=True,
                             squeeze=False, layout="constrained")
    for ax, mode in zip(axes[:, 0], modes, strict=False):
        a = traces[mode].arrays()
        color, label, _, _ = _RUN_STYLE[mode]
        ax.fill_between(a["load_n"], a["v_min"], a["v_max"], color=color, alpha=0.15, lw=0,
                        label="between the lowest and the highest stack")
        stacks = np.asarray(a.get("voltages", np.zeros((0, 7))), dtype=float)
        if stacks.ndim == 2 and stacks.shape[0] > 1 and stacks.shape[1] == 7:
            # each stack (sampled every 500 cycles): support A solid, B dashed, by stack colour
            for j in range(6):
                stack_color = _STACK_COLORS[j % 3]
                ax.plot(stacks[:, 0], stacks[:, 1 + j], color=stack_color, lw=0.9, ls="-" if j < 3 else "--",
                        label=f"{'ab'[j // 3]}{j % 3 + 1}")
        else:
            ax.plot(a["load_n"], a["v_max"], color=color, lw=0.9, label="highest stack")
            ax.plot(a["load_n"], a["v_min"], color=color, lw=0.9, ls="--", label="lowest stack")
        for limit in (0.0, 150.0):
            ax.axhline(limit, color="tab:red", lw=0.8, ls=":")
        ax.set_ylim(-5, 155)
        ax.set_ylabel("stack voltage in V")
        ax.set_title(label, fontsize=9)
        ax.legend(fontsize=7, loc="lower left", ncol=4)
        ax.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel("axial load Fx in N")
    fig.suptitle("Piezo stack voltages versus load (limits 0 and 150 V, dotted red)", fontsize=11)
    return fig


def experiment_figures(summary: dict, traces: dict, out_dir: Path) -> list[Path]:
    """Figure 7a (deflection versus load), 7b (path in the y-z plane) and the voltages."""
    runs = experiment_runs(summary, traces)
    out_dir = Path(out_dir)
    return [save(figure_7a(runs, summary["critical_load_N"]), out_dir / FIG7A),
            save(figure_7b(runs), out_dir / FIG7B),
            save(voltages_figure(summary, traces), out_dir / VOLTAGES)]


# -- a run over time (beamctl log plot, beamctl report) ---------------------------------------

SYMLOG_LINEAR_M = 10e-6      # the deflection axis over time is linear within 10 µm of zero
CRITICAL_LOAD_SHOWN = 0.8    # a run's load drawn against the critical load once it comes this close
# stacks 1, 2, 3 of a support: a colour and a line style each, the same at both supports
_STACK_COLORS = ("tab:green", "tab:purple", "tab:brown")      # stacks 1, 2, 3 of a support
_STACK_STYLE = (("tab:blue", "-"), ("tab:red", "--"), ("tab:green", "-."))


def _pooled(mask: np.ndarray, k: int) -> np.ndarray:
    """``mask`` thinned to every k-th sample, a point True where any sample of its block was."""
    n = len(mask) // k * k
    pooled = mask[:n].reshape(-1, k).any(axis=1) if n else np.zeros(0, dtype=bool)
    return np.concatenate([pooled, mask[n:].any(keepdims=True)]) if n < len(mask) else pooled


def run_over_time(run: RunRecord, part: str = ""):
    """A recording over time: the deflection in mm (y, z, magnitude), the axial load, the
    voltages of support A and of support B (three stacks each, told apart by colour and line
    style, the limits and the bias drawn, saturated stretches shaded) and the supervisor's state
    with its faults (the figure, not saved). ``part`` names a window of the run in the title."""

    plt = _pyplot()
    k = run.stride()
    t = run.time_s[::k]
    fig, axes = plt.subplots(5, 1, figsize=(11, 11), sharex=True, layout="constrained",
                             gridspec_kw={"height_ratios": [1.3, 0.9, 1.1, 1.1, 0.7]})
    ax_d, ax_l, ax_a, ax_b, ax_s = axes
    ax_d.plot(t, run.deflection_y_m[::k] * 1e3, color="tab:blue", lw=0.8, label="w_y")
    ax_d.plot(t, run.deflection_z_m[::k] * 1e3, color="tab:orange", lw=0.8, label="w_z")
    ax_d.plot(t, run.deflection_m[::k] * 1e3, color="k", lw=1.0, label="|w|")
    # a held beam's micrometres and a failing beam's millimetres on one axis: linear within
    # SYMLOG_LINEAR_M of zero, logarithmic beyond
    ax_d.set_yscale("symlog", linthresh=SYMLOG_LINEAR_M * 1e3, linscale=1.0)
    top = float(np.nanmax(run.deflection_m))
    if top > OFF_SCALE_M:
        lost = int(np.flatnonzero(run.deflection_m > OFF_SCALE_M)[0])
        right_half = run.time_s[lost] > 0.5 * (run.time_s[0] + run.time_s[-1])     # the side with room
        ax_d.annotate(f"off scale from {run.time_s[lost]:.2f} s (the beam is lost)", (run.time_s[lost], 0.72),
                      xycoords=("data", "axes fraction"), xytext=(-6 if right_half else 6, 0),
                      textcoords="offset points", ha="right" if right_half else "left", va="center",
                      fontsize=8, color="tab:red")
    top = 1.5 * max(min(top, OFF_SCALE_M), SYMLOG_LINEAR_M) * 1e3
    ax_d.set_ylim(-top, top)
    ax_d.set_ylabel("deflection in mm")
    ax_d.set_title("deflection at its largest point along the beam (strain gauges; linear within "
                   f"{SYMLOG_LINEAR_M * 1e6:g} µm of zero, logarithmic beyond)", fontsize=9)
    ax_d.legend(fontsize=8, loc="upper left", ncol=3)
    if np.isfinite(run.load_n).any():
        ax_l.plot(t, run.load_n[::k], color="0.6", lw=0.6, label="load cell")
    if np.isfinite(run.load_filtered_n).any():
        ax_l.plot(t, run.load_filtered_n[::k], color="k", lw=1.0, label="filtered (the schedule's)")
    if run.critical_load_n and np.nanmax(run.load_n) > CRITICAL_LOAD_SHOWN * run.critical_load_n:
        ax_l.axhline(run.critical_load_n, color="k", ls="--", lw=0.7,
                     label=f"critical load {run.critical_load_n:.0f} N")
    ax_l.set_ylabel("axial load in N")
    ax_l.legend(fontsize=8, loc="upper left", ncol=3)
    v_min, v_max = run.voltage_limits_v
    for ax, support, first in ((ax_a, "A", 0), (ax_b, "B", 3)):
        saturated = _pooled(run.saturated(support), k)
        if saturated.any():
            ax.fill_between(t, v_min, v_max, where=saturated[:len(t)], color="tab:red", alpha=0.12, lw=0,
                            step="mid", label="saturated")
        for i, (color, style) in enumerate(_STACK_STYLE):
            ax.plot(t, run.voltages_v[::k, first + i], style, color=color, lw=0.9,
                    label=f"{support.lower()}{i + 1}")
        for limit in (v_min, v_max):
            ax.axhline(limit, color="tab:red", lw=0.8, ls=":")
        ax.axhline(run.bias_voltage_v, color="0.5", lw=0.6, ls=":")
        span = v_max - v_min
        ax.set_ylim(v_min - 0.05 * span, v_max + 0.05 * span)
        ax.set_ylabel(f"support {support} in V")
        ax.legend(fontsize=8, loc="upper left", ncol=4)
    ax_a.set_title(f"stack voltages (limits {v_min:g} and {v_max:g} V dotted red, bias "
                   f"{run.bias_voltage_v:g} V dotted grey)", fontsize=9)
    # the state from its changes (never thinned away), the faults named where they latched
    changed = np.flatnonzero((np.diff(run.state) != 0) | (np.diff(run.fault) != 0)) + 1
    at = np.concatenate([[0], changed, [len(run.time_s) - 1]])
    ax_s.step(run.time_s[at], run.state[at], where="post", color="k", lw=1.2)
    ax_s.set_yticks([s.value for s in State], [s.name for s in State], fontsize=7)
    ax_s.set_ylim(-0.5, max(State).value + 0.5)
    for i in changed:
        if run.fault[i] != Fault.NONE and run.fault[i - 1] == Fault.NONE:
            try:
                name = Fault(run.fault[i]).name
            except ValueError:
                name = f"fault {run.fault[i]}"
            for ax in axes:
                ax.axvline(run.time_s[i], color="tab:red", lw=0.9)
            right_half = run.time_s[i] > 0.5 * (run.time_s[0] + run.time_s[-1])  # the side with room
            ax_s.annotate(name, (run.time_s[i], run.state[i]), xytext=(-4 if right_half else 4, -10),
                          textcoords="offset points", ha="right" if right_half else "left", fontsize=8,
                          color="tab:red")
    ax_s.set_ylabel("state")
    ax_s.set_xlabel("time in s from the first sample")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    fig.suptitle(f"{run.label} over time" + (f", {part}" if part else ""))
    return fig


_STUDY_FAILURE = {"linear": ("instability onset", "unstable"), "experiment": ("let-go load", "let go")}


def _survival_curve(ax, km, color: str, label: str) -> None:
    """A Kaplan-Meier estimate as the step curve it is, from the lowest value observed to the
    highest (``end``: flat after the last failure, nothing drawn beyond), censored values as '+'
    on it."""
    start = min(km.failure_at[:1].tolist() + km.censored_at[:1].tolist())
    x = np.concatenate([[start], km.failure_at, [km.end]])
    y = np.concatenate([[0.0], km.probability, km.probability[-1:] if km.failures else [0.0]])
    ax.step(x, y, where="post", color=color, label=label)
    if km.censored_at.size:
        ax.plot(km.censored_at, km.at(km.censored_at), "+", color=color, ms=9, mew=1.5)


def study_figures(rows: Sequence[dict], designs: Sequence[str], out_dir: Path,
                  kind: str = "linear") -> list[Path]:
    """An uncertainty study's report: the failures' onset / own critical load as a histogram and
    the Kaplan-Meier estimate of its distribution per design, and the Kaplan-Meier probability
    of failure versus axial load. A censored sample (it never failed: a lower bound) is never
    drawn as a failure: it is counted in the legends and marked '+' on the curves, which end at
    the largest value observed."""

    what, failed = _STUDY_FAILURE[kind]
    plt = _pyplot()
    fig, (ax_h, ax_c) = plt.subplots(1, 2, figsize=(11, 4.5))
    fig_p, ax_p = plt.subplots(figsize=(7.5, 4.8))
    valid = [r for r in rows if r["design"] in designs and math.isfinite(r["ratio"])]
    failures = [r["ratio"] for r in valid if not r["censored"]]
    bins = np.histogram_bin_edges(failures, bins=max(5, min(50, len(failures) // 5))) if failures else 10
    for i, design in enumerate(designs):
        mine = [r for r in valid if r["design"] == design]
        if not mine:
            continue
        color, name = f"C{i}", Path(design).name
        ratio, load = survival(mine, "ratio"), survival(mine, "onset_n")
        censored = len(ratio.censored_at)
        at = f" at {load.censored_at[0]:.0f} N" if censored and np.ptp(load.censored_at) == 0 else ""
        label = f"{name}: {ratio.failures} {failed}, {censored or 'none'} censored"
        ax_h.hist([r["ratio"] for r in mine if not r["censored"]], bins=bins, color=color, alpha=0.5,
                  ec="white", label=label + (" (not drawn)" if censored else ""))
        _survival_curve(ax_c, ratio, color, label + (" (+)" if censored else ""))
        _survival_curve(ax_p, load, color, label + (f"{at} (+)" if censored else ""))
    for ax in (ax_c, ax_p):
        ax.set_ylim(-0.02, 1.02)
    for ax in (ax_h, ax_c):
        ax.axvline(1.0, color="0.4", lw=0.8, ls="--")
        ax.set_xlabel(f"{what} / own Fx,cr")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="upper left")
    ax_h.set_ylabel("samples")
    ax_h.yaxis.get_major_locator().set_params(integer=True)
    ax_h.set_title("Failures over the study (censored samples not drawn)", fontsize=10)
    ax_c.set_ylabel("estimated fraction failed at or below")
    ax_c.set_title("Kaplan-Meier estimate (+ censored, a lower bound)", fontsize=10)
    fig.tight_layout()
    paths = [save(fig, Path(out_dir) / "study_ratio.png")]
    paths.append(_finish(fig_p, ax_p, Path(out_dir) / "study_failure_probability.png",
                         xlabel=f"axial load Fx in N ({what})",
                         ylabel=f"estimated probability {failed} at or below Fx",
                         title="Probability of failure versus axial load (Kaplan-Meier, + censored)",
                         legend={"fontsize": 8, "loc": "upper left"}))
    return paths


def figure_5a(measured: list[FrfData], before: ModelParameters,
              fitted: tuple[ModelParameters, float | None] | None, path: Path) -> Path:
    """Figure 5a for the first measurement: Gy and Gz measured, the model before and after."""
    d = measured[0]
    freqs = d.frequencies_hz
    curves = [("model before the fit", model_response(before, d, freqs))]
    if fitted is not None:
        curves.append(("model after the fit", model_response(fitted[0], d, freqs, fitted[1])))
    return frequency_response_measured(d, curves, path)


def stack_use_figure(stacks: dict, stack_use: Sequence | None, path: Path,
                     own_critical_n: float | None = None) -> Path:
    """The stacks' use against the load (``beamctl commission``): the prediction from the static
    strains (commission's stacks.json: ``loads_n``, ``fraction``, ``measured``, ``critical_load_n``),
    the fraction at the measured loads, and where given the controlled run's own use (``stack_use``:
    (load, fraction) pairs; dynamic, so above the static curve by the control's own motion)."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    fcr = stacks["critical_load_n"]
    if stack_use:
        run = np.asarray(stack_use, dtype=float)
        ax.plot(run[:, 0], 100 * run[:, 1], color="tab:orange", lw=0.9, zorder=3,
                label="the controlled run on the simulated rig")
    predicted = 100 * np.asarray(stacks["fraction"])
    rough = bool(stacks.get("one_load"))
    ax.plot(stacks["loads_n"], predicted, color="tab:blue", lw=2, ls="--" if rough else "-",
            label="predicted to hold the beam straight, at rest"
                  + (" (from one load: rough, either way)" if rough else ""))
    measured = np.asarray(stacks["measured"], dtype=float).reshape(-1, 2)
    ax.plot(measured[:, 0], 100 * measured[:, 1], "o", color="tab:blue", ms=7,
            label="from the static strains measured")
    ax.axhline(100, color="tab:red", lw=1.2, label="a stack at its limit")
    ax.axvline(fcr, color="k", ls="--", lw=1, label=f"fitted Fx,cr {fcr:.0f} N")
    if own_critical_n is not None:
        ax.axvline(own_critical_n, color="0.4", ls=":", lw=1,
                   label=f"the rig's own Fx,cr {own_critical_n:.0f} N")
    ax.set_xlim(0, max(stacks["loads_n"]))
    top = max(110.0, float(np.nanmax(predicted)) + 5)
    ax.set_ylim(0, min(top, 200.0))
    return _finish(fig, ax, path, xlabel="axial load Fx (N)", ylabel="stacks' swing used (%)",
                   title=f"Stack authority: {'roughly ' if rough else ''}"
                         f"{100 * stacks['at_critical']:.0f} % of the swing at the fitted Fx,cr",
                   legend={"loc": "upper left", "fontsize": 8})
