"""The figures as a reader sees them: figure 7a and 7b of the experiment, the gains versus load.
What can be read from the figure objects is asserted on them: the scale a curve is drawn at,
the paper's points, the marked directions, text that does not overlap."""

import itertools
import math

import numpy as np
import pytest

from beamctl.gains.defaults import default_table_path, paper_table_path
from beamctl.gains.table import load_table
from beamctl.reports import plots
from beamctl.simulation.experiment import experiment_config, experiment_tables, run_experiment


@pytest.fixture(scope="module")
def experiment():
    """The experiment's three runs on a load ramp four times faster than the paper's."""
    cfg, settings = experiment_config({"plant": {"load": {"start": 260.0, "end": 3400.0, "rate": 200.0,
                                                          "hold": 0.2}}})
    summary, traces = run_experiment(cfg, settings, experiment_tables(cfg, settings))
    return summary, traces, plots.experiment_runs(summary, traces)


@pytest.fixture
def close():
    figures = []
    yield figures.append
    for fig in figures:
        plots._pyplot().close(fig)


def _panel(fig, title_start: str):
    return next(ax for ax in fig.axes if ax.get_title().startswith(title_start))


def _texts_do_not_overlap(fig) -> None:
    """Titles, axis labels, legends and annotations: no two of them share a pixel."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    boxes = []
    if fig._suptitle is not None:
        boxes.append(("suptitle", fig._suptitle.get_window_extent(renderer)))
    boxes += [(f"figure legend {i}", leg.get_window_extent(renderer)) for i, leg in enumerate(fig.legends)]
    for ax in fig.axes:
        if not ax.get_visible():
            continue
        name = ax.get_title() or "inset"
        for what, artist in (("title", ax.title), ("x label", ax.xaxis.label), ("y label", ax.yaxis.label),
                             ("legend", ax.get_legend())):
            if artist is not None and artist.get_visible() and (what == "legend" or artist.get_text()):
                boxes.append((f"{name}: {what}", artist.get_window_extent(renderer)))
    for (a, box_a), (b, box_b) in itertools.combinations(boxes, 2):
        assert not box_a.overlaps(box_b), f"{a!r} overlaps {b!r}"


def test_figure_7a_draws_the_controlled_runs_at_a_scale_that_shows_them(experiment, close):
    """At the uncontrolled run's millimetres the controlled runs lie flat at zero; the magnified
    panel draws them, until their stacks reach a limit, on an axis within a factor 1.5 of what
    their deflection stays below (all but its last 2 %: the moments before the stacks reach
    their limit may run off the top)."""
    summary, _, runs = experiment
    fig = plots.figure_7a(runs, summary["critical_load_N"])
    close(fig)
    magnified = _panel(fig, "(d)")
    assert magnified.get_visible()
    controlled = [r for r in runs if r.controlled]
    drawn = [line for line in magnified.get_lines() if len(line.get_xdata()) > 2]
    assert {line.get_color() for line in drawn} == {r.color for r in controlled}, "every controlled run"
    tops = [float(np.percentile(line.get_ydata(), 98)) for line in drawn]
    top = magnified.get_ylim()[1]
    assert max(tops) < top <= 1.5 * max(tops), (tops, magnified.get_ylim())
    # most of the way, the controlled runs stay below a tenth of the uncontrolled run's deflection
    full = _panel(fig, "(c)").get_ylim()[1]
    assert min(tops) * 1e-3 < 0.1 * full, "the magnified panel shows what the full scale cannot"


def test_figure_7a_magnifies_the_controlled_runs_near_the_critical_load(experiment, close):
    """Where the story is: 3194 -> 3225 N was a 30 N sliver of a 0 to 3500 N axis. Panel (d)
    spans from 0.9 x Fx,cr to where the stacks ran out; its legend names each run by colour."""
    summary, _, runs = experiment
    fcr = summary["critical_load_N"]
    fig = plots.figure_7a(runs, fcr)
    close(fig)
    low, high = _panel(fig, "(d)").get_xlim()
    assert 0.85 * fcr <= low < fcr < high < fcr + 400.0, (low, high)
    colours = {h.get_color() for h in _panel(fig, "(d)").get_legend().legend_handles}
    assert colours == {r.color for r in runs if r.controlled}, colours
    assert _panel(fig, "(d)").get_ylabel() == "deflection in µm"


def test_figure_7a_of_a_run_high_up_the_load_is_drawn_where_it_ran_without_an_empty_panel(close):
    """A recording from 2800 to 3300 N kept a 0 to 3500 N axis and an empty fourth panel."""
    load = np.linspace(2800.0, 3300.0, 500)
    run = plots.RunCurves(label="run", color="tab:blue", controlled=True, load_n=load,
                          deflection_y_m=1e-4 + 0 * load, deflection_z_m=1e-4 + 0 * load, held_samples=None)
    fig = plots.figure_7a([run], 3194.0, paper=False)
    close(fig)
    low, high = _panel(fig, "(c)").get_xlim()
    assert 2600.0 <= low <= 2800.0 and 3300.0 < high <= 3600.0, (low, high)
    assert all(ax.get_visible() and ax.has_data() for ax in fig.axes), "no empty panel"


def test_figure_7a_plots_the_y_and_z_components_as_the_paper_plots_q1y_and_q1z(experiment, close):
    summary, _, runs = experiment
    fig = plots.figure_7a(runs, summary["critical_load_N"])
    close(fig)
    uncontrolled = runs[0]
    for title, component in (("(a)", uncontrolled.deflection_y_m), ("(b)", uncontrolled.deflection_z_m)):
        line = next(line for line in _panel(fig, title).get_lines() if line.get_color() == uncontrolled.color)
        np.testing.assert_allclose(line.get_ydata(), np.abs(component) * 1e3, err_msg=title)
    # the bow at 234 deg: |w_z| / |w_y| = tan(54 deg) on the uncontrolled run
    ratio = np.abs(uncontrolled.deflection_z_m[-1] / uncontrolled.deflection_y_m[-1])
    assert ratio == pytest.approx(math.tan(math.radians(54.0)), rel=0.02)


def test_figure_7a_marks_the_paper_s_measurements_as_points_not_lines(experiment, close):
    summary, _, runs = experiment
    fig = plots.figure_7a(runs, summary["critical_load_N"])
    close(fig)
    lines = {line.get_gid(): line for line in _panel(fig, "(c)").get_lines() if line.get_gid()}
    points = lines["paper-uncontrolled"]
    assert points.get_linestyle() == "None" and points.get_marker() == "o"
    np.testing.assert_array_equal(points.get_xdata(), [2438.0, 2723.0])
    np.testing.assert_array_equal(points.get_ydata(), [0.5, 1.0])
    held = lines["paper-controlled"]
    assert held.get_linestyle() == "None" and held.get_marker() == "^"
    assert (held.get_xdata()[0], held.get_ydata()[0]) == (3223.0, 0.0)
    for ax in fig.axes:
        for line in ax.get_lines():
            x = np.asarray(line.get_xdata(), dtype=float)
            assert not (x.size == 2 and x[0] == x[1] and x[0] in (2438.0, 2723.0, 3223.0)), (
                f"a vertical line at a paper load in {ax.get_title()!r}")


def test_figure_7a_has_no_overlapping_text(experiment, close):
    summary, _, runs = experiment
    fig = plots.figure_7a(runs, summary["critical_load_N"])
    close(fig)
    _texts_do_not_overlap(fig)


def test_figure_7b_gives_every_run_its_panel_and_marks_its_failure_direction(experiment, close):
    """Each run's path in its own panel, so that no run hides another; one failure marker per
    run, at the direction the summary reports (where the deflection passed 1.0 mm)."""
    summary, _, runs = experiment
    fig = plots.figure_7b(runs)
    close(fig)
    names = {"uncontrolled": "uncontrolled", "tab:blue": "controlled", "tab:orange": "paper_switching"}
    panels = [ax for ax in fig.axes if ax.get_title() in {r.label for r in runs}]
    assert [ax.get_title() for ax in panels] == [r.label for r in runs]
    for ax, run in zip(panels, runs, strict=True):
        path = [line for line in ax.get_lines() if len(line.get_xdata()) > 100]
        assert len(path) == 1, f"{run.label}: one path"
        np.testing.assert_allclose(path[0].get_xdata(), run.deflection_y_m * 1e3)
        markers = [line for line in ax.get_lines() if line.get_gid() == "failure-direction"]
        assert len(markers) == 1, f"{run.label}: {len(markers)} failure markers"
        (y,), (z,) = markers[0].get_xdata(), markers[0].get_ydata()
        key = names.get(run.color, "uncontrolled") if run.controlled else "uncontrolled"
        expected = summary[key]["buckling_angle_deg"]
        assert math.degrees(math.atan2(z, y)) % 360.0 == pytest.approx(expected, abs=0.01), run.label
        assert str(round(expected)) in markers[0].get_label(), markers[0].get_label()
        reference = [line for line in ax.get_lines() if line.get_label().startswith("paper's direction")]
        assert reference and f"{128 if run.controlled else 234} deg" in reference[0].get_label()
    _texts_do_not_overlap(fig)


def test_figure_7b_shows_a_controlled_run_held_at_the_origin_magnified(experiment, close):
    """The held part of a controlled run is micrometres: an inset draws it at a scale that fills
    a good part of it."""
    _, _, runs = experiment
    fig = plots.figure_7b(runs)
    close(fig)
    insets = [inset for ax in fig.axes for inset in ax.child_axes
              if inset.get_title().startswith("held, in µm")]
    assert len(insets) == sum(r.controlled for r in runs)
    for inset in insets:
        path = max(inset.get_lines(), key=lambda line: len(line.get_xdata()))
        reach = max(np.abs(path.get_xdata()).max(), np.abs(path.get_ydata()).max())
        half = inset.get_xlim()[1]
        assert reach < half <= 1.5 * reach, (reach, inset.get_xlim())


def test_the_experiment_figures_are_written(experiment, tmp_path):
    summary, traces, _ = experiment
    paths = plots.experiment_figures(summary, traces, tmp_path)
    assert [p.name for p in paths] == list(plots.EXPERIMENT_FIGURES)
    for p in paths:
        assert p.read_bytes().startswith(b"\x89PNG") and p.stat().st_size > 10_000, p


def test_a_constant_integral_gain_is_drawn_as_its_value_on_a_linear_axis(close):
    """The paper's integral gains are the same at every load (1.58e7, equal to 1e-10 relative):
    a linear axis from zero with the value named, not a log axis magnifying the rounding."""
    table = load_table(paper_table_path())
    fig = plots.gains_figure(table)
    close(fig)
    integral = _panel(fig, "integral gains")
    assert integral.get_yscale() == "linear"
    gains = np.abs(table.gains[:, 0, 8])
    assert np.ptp(gains) < 1e-6 * gains.max(), "the premise: a constant gain"
    for line in integral.get_lines()[:2]:
        y = np.asarray(line.get_ydata())
        assert np.ptp(y) == 0.0 and y[0] == pytest.approx(gains.mean(), rel=1e-9)
        assert "(constant" in line.get_label() and "1.581e+07" in line.get_label()
    low, high = integral.get_ylim()
    assert low == 0.0 and gains.max() < high < 1.3 * gains.max()
    assert _panel(fig, "displacement gains").get_yscale() == "log", "gains over decades stay on a log axis"
    _texts_do_not_overlap(fig)


def test_a_gain_that_varies_by_ten_percent_is_on_a_linear_axis_and_shows_its_trend(close):
    """The shipped design's integral gain falls from 5.0e6 to 4.5e6 beyond the critical load."""
    table = load_table(default_table_path())
    fig = plots.gains_figure(table)
    close(fig)
    integral = _panel(fig, "integral gains")
    assert integral.get_yscale() == "linear"
    y = np.asarray(integral.get_lines()[0].get_ydata())
    assert np.ptp(y) > 0.05 * y.max(), "the trend is drawn, not flattened"
    assert "(constant" not in integral.get_lines()[0].get_label()


def test_magnitudes_say_what_sign_they_hide(close):
    """The shipped design's D and Ki are negative at every load: drawn as magnitudes, the legend
    says so (before, -5e6 in the table was +5e6 on the plot, without a word)."""
    table = load_table(default_table_path())
    fig = plots.gains_figure(table)
    close(fig)
    assert np.all(table.compensator.ki[:, 0, 0] < 0), "the premise: a negative integral gain"
    labels = [line.get_label() for line in _panel(fig, "integral gains").get_lines()]
    assert labels[0] == "|Ki y1| (negative)", labels
    assert plots._sign_note(np.array([0.0, 100.0, 200.0]), np.array([-1.0, -0.5, 0.5])) == \
        "changes sign near 150 N"


def test_the_voltages_figure_draws_each_stack_in_a_panel_per_controlled_run(experiment, close):
    """Before: the highest and the lowest stack only, two runs' translucent bands on one axis
    mixed into a colour no legend named."""
    summary, traces, _ = experiment
    fig = plots.voltages_figure(summary, traces)
    close(fig)
    controlled = [m for m in traces if m != "uncontrolled"]
    assert len(fig.axes) == len(controlled)
    for ax in fig.axes:
        labels = [line.get_label() for line in ax.get_lines() if not line.get_label().startswith("_")]
        assert labels[:6] == ["a1", "a2", "a3", "b1", "b2", "b3"], labels


def test_figure_7a_draws_a_run_with_a_load_cell_gap(close):
    """A NaN load-cell reading inside the held part made the magnified panel's axis NaN (a
    ValueError from matplotlib, a traceback from `beamctl report`)."""
    load = np.linspace(2000.0, 3300.0, 400)
    load[100] = np.nan
    run = plots.RunCurves(label="controlled", color="tab:blue", controlled=True, load_n=load,
                          deflection_y_m=np.full(400, 2e-5), deflection_z_m=np.full(400, 1e-5),
                          held_samples=None)
    uncontrolled = plots.RunCurves(label="uncontrolled", color="0.3", controlled=False, load_n=load[:300],
                                   deflection_y_m=np.linspace(1e-4, 1.5e-3, 300),
                                   deflection_z_m=np.linspace(1e-4, 1.5e-3, 300))
    fig = plots.figure_7a([uncontrolled, run], 3194.0, paper=False)
    close(fig)
    assert _panel(fig, "(d)").get_visible(), "the magnified panel is drawn"
    assert all(np.isfinite(ax.get_xlim()).all() for ax in fig.axes)
