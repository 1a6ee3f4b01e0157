"""Figures (matplotlib, Agg backend: no screen needed)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from beamctl.config.schema import ConfigError
from beamctl.models import critical_load, eigenfrequencies, fe_frequency_response
from beamctl.models.fe import FEModel
from beamctl.models.measured import FrfData, resonances
from beamctl.models.modal import ModalModel
from beamctl.tools.outputs import replacing

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
    return _save(fig, path)


def _save(fig, path: Path) -> Path:
    """Save the figure whole (never half a PNG, even when interrupted) and close it."""
    try:
        with replacing(path) as temp:
            fig.savefig(temp, dpi=120)
    finally:
        _pyplot().close(fig)
    return Path(path)


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
    return _save(fig, path)


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


def gains_vs_load(table, path: Path) -> Path:
    """Gains versus axial load for support A, y direction: |K| per state of an integral-lqr
    table, else the compensator's |D| and |Ki| per gauge channel."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(12, 4), sharex=True)
    if table.gains is not None:
        names = {0: "q1y", 2: "q2y", 4: "dq1y/dt", 6: "dq2y/dt", 8: "int q1y", 10: "int q2y"}
        rows = table.gains[:, 0, :]
        groups = [("displacement gains (N per modal unit)", (0, 2)),
                  ("velocity gains (N s per modal unit)", (4, 6)),
                  ("integral gains (N per modal unit s)", (8, 10))]
        ylabel, title = "|K| (row Fay,A)", "Integral LQR gains K(Fx)"
    else:
        comp = table.compensator
        names = {0: "D y1", 1: "D y2", 2: "Ki y1", 3: "Ki y2", 4: "sum |C|"}
        rows = np.column_stack([comp.d[:, 0, 0], comp.d[:, 0, 2], comp.ki[:, 0, 0], comp.ki[:, 0, 2],
                                np.abs(comp.c[:, 0, :]).sum(axis=1)])
        groups = [("direct gains D (N per strain)", (0, 1)), ("integral gains Ki (N per unit of xi)", (2, 3)),
                  ("state gains, sum of |C| (N per state unit)", (4,))]
        ylabel, title = "row Fay,A", f"Compensator gains ({table.design.kind})"
    for ax, (group_title, cols) in zip(axes, groups, strict=True):
        for c in cols:
            style = "o-" if table.schedule.mode == "paper" else "-"
            ax.semilogy(table.loads_n, np.abs(rows[:, c]), style, ms=3, label=names[c])
        ax.set_title(group_title, fontsize=9)
        ax.set_xlabel("axial load Fx in N")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].set_ylabel(ylabel)
    fcr = None
    try:
        from beamctl.models import build_model, critical_load

        fcr = critical_load(build_model(table.model_parameters))
    except ConfigError:
        pass
    if fcr:
        for ax in axes:
            ax.axvline(fcr, color="0.5", lw=0.8, ls="--")
    fig.suptitle(f"{title}, {table.schedule.mode} schedule (dashed: critical load {fcr:.0f} N)"
                 if fcr else title)
    fig.tight_layout()
    return _save(fig, path)


def telemetry_figures(header: dict, rows: np.ndarray, out_dir: Path) -> list[Path]:
    """From a controller telemetry file: figure 7a (modal displacement of the first modes
    versus load), 7b (their path in the y-z plane) and the stack voltages versus load."""
    plt = _pyplot()
    col = {name: i for i, name in enumerate(header["columns"])}
    load = rows[:, col["load_filtered_N"]]
    running = rows[:, col["state"]] == 2
    q1y, q1z = rows[:, col["q_1y"]], rows[:, col["q_1z"]]
    paths = []

    fig, (ax_a, ax_b) = plt.subplots(1, 2, figsize=(11, 4.5))
    ax_a.plot(load[running], np.hypot(q1y, q1z)[running] * 1e6, lw=0.8)
    ax_a.set_xlabel("axial load Fx in N (filtered load cell)")
    ax_a.set_ylabel("|q1| in 1e-6 (modal units)")
    ax_a.set_title("(a) first-mode modal displacement versus load")
    ax_a.grid(True, alpha=0.3)
    ax_b.plot(q1y[running] * 1e6, q1z[running] * 1e6, lw=0.8)
    ax_b.set_xlabel("q1,y in 1e-6")
    ax_b.set_ylabel("q1,z in 1e-6")
    ax_b.set_title("(b) first-mode path in the y-z plane")
    ax_b.set_aspect("equal", adjustable="datalim")
    ax_b.grid(True, alpha=0.3)
    fig.tight_layout()
    paths.append(_save(fig, Path(out_dir) / "fig7_modal_displacement.png"))

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name in ("a1", "a2", "a3", "b1", "b2", "b3"):
        ax.plot(load, rows[:, col[f"voltage_{name}_V"]], lw=0.7, label=name)
    paths.append(_finish(fig, ax, Path(out_dir) / "voltages.png",
                         xlabel="axial load Fx in N (filtered load cell)", ylabel="stack voltage in V",
                         title="Piezo stack voltages", legend={"ncol": 6, "fontsize": 8}))
    return paths


_RUN_STYLE = {"uncontrolled": ("tab:gray", "uncontrolled"),
              "interpolate": ("tab:blue", "controlled, interpolated K(Fx), anti-windup"),
              "paper": ("tab:orange", "controlled, paper's 500 N switching")}
_RUN_ORDER = {"paper": 1, "uncontrolled": 2, "interpolate": 3}       # drawing order, top last
_RUN_LINE = {"paper": (2.4, "--"), "uncontrolled": (1.2, "-"), "interpolate": (1.2, "-")}


def experiment_figures(summary: dict, traces: dict, out_dir: Path) -> list[Path]:
    """Figure 7a (deflection versus load), 7b (path in the y-z plane) and the voltages."""
    plt = _pyplot()
    paths = []
    fig, ax = plt.subplots(figsize=(8, 5))
    for mode, trace in sorted(traces.items(), key=lambda kv: _RUN_ORDER[kv[0]]):
        a = trace.arrays()
        color, label = _RUN_STYLE[mode]
        lw, ls = _RUN_LINE[mode]
        ax.plot(a["load_n"], a["deflection_m"] * 1e3, color=color, lw=lw, ls=ls, label=label + " (gauges)")
        if mode != "uncontrolled":
            ax.plot(a["load_n"], a["true_deflection_m"] * 1e3, color=color, lw=0.8, ls=":",
                    label=label.split(",")[1].strip() + ": simulated beam (not seen by the gauges)")
    fcr = summary["critical_load_N"]
    ax.axvline(fcr, color="k", lw=0.8, ls="--")
    ax.text(fcr, 1.2, f"Fx,cr = {fcr:.0f} N ", fontsize=8, va="top", ha="right")
    for load, text in ((2438, "paper 0.5 mm"), (2723, "paper 1.0 mm"), (3223, "paper max")):
        ax.axvline(load, color="tab:red", lw=0.6, alpha=0.5)
        ax.text(load, 1.55, text, rotation=90, fontsize=7, color="tab:red", va="top", ha="right")
    ax.axhline(0.5, color="0.7", lw=0.6)
    ax.axhline(1.0, color="0.7", lw=0.6)
    ax.set_xlim(0, max(3600, max(max(t.load_n) for t in traces.values()) + 100))
    ax.set_ylim(0, 1.6)
    paths.append(_finish(fig, ax, Path(out_dir) / FIG7A,
                         xlabel="axial load Fx in N", ylabel="largest lateral deflection in mm",
                         title="(a) deflection versus axial load (figure 7a)",
                         legend={"fontsize": 7, "loc": "upper left"}))

    fig, ax = plt.subplots(figsize=(5.5, 5.5))
    for mode, trace in traces.items():
        a = trace.arrays()
        color, label = _RUN_STYLE[mode]
        ax.plot(a["deflection_y_m"] * 1e3, a["deflection_z_m"] * 1e3, color=color, lw=1.0, label=label)
        if a["deflection_y_m"].size:
            ax.plot(a["deflection_y_m"][-1] * 1e3, a["deflection_z_m"][-1] * 1e3, "o", color=color, ms=4)
    ax.set_xlim(-1.6, 1.6)
    ax.set_ylim(-1.6, 1.6)
    ax.set_aspect("equal")
    ax.axhline(0, color="0.7", lw=0.6)
    ax.axvline(0, color="0.7", lw=0.6)
    paths.append(_finish(fig, ax, Path(out_dir) / FIG7B, xlabel="deflection in y in mm",
                         ylabel="deflection in z in mm", title="(b) path in the y-z plane (figure 7b)",
                         legend={"fontsize": 7, "loc": "upper left"}))

    fig, ax = plt.subplots(figsize=(8, 4.5))
    for mode, trace in traces.items():
        if mode == "uncontrolled":
            continue
        a = trace.arrays()
        color, label = _RUN_STYLE[mode]
        ax.fill_between(a["load_n"], a["v_min"], a["v_max"], color=color, alpha=0.25, lw=0)
        ax.plot(a["load_n"], a["v_max"], color=color, lw=0.8, label=f"{label}: highest and lowest stack")
        ax.plot(a["load_n"], a["v_min"], color=color, lw=0.8)
    for limit in (0.0, 150.0):
        ax.axhline(limit, color="tab:red", lw=0.8, ls="--")
    ax.set_ylim(-5, 155)
    paths.append(_finish(fig, ax, Path(out_dir) / VOLTAGES, xlabel="axial load Fx in N",
                         ylabel="stack voltage in V",
                         title="Piezo stack voltages versus load (limits 0 and 150 V)",
                         legend={"fontsize": 7, "loc": "lower left"}))
    return paths


def study_figures(rows: Sequence[dict], designs: Sequence[str], out_dir: Path) -> list[Path]:
    """An uncertainty study's report: held load / own critical load as a histogram and an
    empirical CDF per design, and the probability of failure versus axial load."""
    plt = _pyplot()
    fig, (ax_h, ax_c) = plt.subplots(1, 2, figsize=(10, 4))
    fig_p, ax_p = plt.subplots(figsize=(7, 4.5))
    for design in designs:
        mine = [r for r in rows if r["design"] == design]
        ratio = np.array([r["ratio"] for r in mine], dtype=float)
        ratio = ratio[np.isfinite(ratio)]
        held = np.sort(np.array([r["held_load_n"] for r in mine], dtype=float))
        held = held[np.isfinite(held)]
        label = Path(design).name
        if len(ratio):
            ax_h.hist(ratio, bins=max(5, min(50, len(ratio) // 5)), alpha=0.5, label=label)
            x = np.sort(ratio)
            ax_c.step(x, np.arange(1, len(x) + 1) / len(x), where="post", label=label)
        if len(held):
            ax_p.step(held, np.arange(1, len(held) + 1) / len(mine), where="post", label=label)
    ax_h.set_xlabel("held load / own Fx,cr")
    ax_h.set_ylabel("samples")
    ax_h.set_title("Held load over the study")
    ax_c.set_xlabel("held load / own Fx,cr")
    ax_c.set_ylabel("fraction of samples at or below")
    ax_c.set_title("Empirical CDF")
    for ax in (ax_h, ax_c):
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    paths = [_save(fig, Path(out_dir) / "study_ratio.png")]
    paths.append(_finish(fig_p, ax_p, Path(out_dir) / "study_failure_probability.png",
                         xlabel="axial load Fx in N", ylabel="probability the beam is let go below Fx",
                         title="Probability of failure versus axial load", legend={"fontsize": 8}))
    return paths
