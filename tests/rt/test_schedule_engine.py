"""The gain schedule as the compiled engine runs it (rt/engine.py ``_follow``, ``_settle``,
``_output``, ``_update``, ``_small_product``), driven through ``Controller``: the products the step
runs are the matrices ``GainSchedule.matrices_at`` reports (what the closed-loop checks
analyse), edges held and flagged (a running controller faults), the load filter's time
constant, the paper mode's switching with hysteresis.

The engine's schedule state is read where it lives: the grid point in use ``iv[V_INDEX]``, the
offset above it ``fv[X_OFFSET]``, the filtered load ``fv[X_FILTERED]``, the out-of-range flag
``iv[V_OUT_OF_RANGE]``. A product is checked on its own by calling the compiled function on the
controller's arrays, as ``_control`` calls it."""

from dataclasses import replace

import numpy as np
import pytest

from beamctl.gains.build import build_table
from beamctl.gains.compensator import Compensator
from beamctl.gains.defaults import default_table_path
from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import ScheduleSettings, load_table
from beamctl.hal.base import Sample
from beamctl.rt import engine as e
from beamctl.rt.config import controller_config
from beamctl.rt.controller import Controller
from beamctl.rt.safety import Fault, State

ZERO = (0.0, 0.0, 0.0, 0.0)


@pytest.fixture(scope="module")
def table(paper_model):
    """A small integral-LQR table (4 states, the whole-matrix products: its planes' states are
    not contiguous). Built unchecked: no ride-through analysis, the controller's legacy limits."""
    return build_table(paper_model, [0.0, 500.0, 1000.0, 1500.0, 2000.0], check=False)


@pytest.fixture(scope="module")
def lqg():
    """The shipped LQG (52 states, 6000 Hz): the engine runs its products per bending plane."""
    return load_table(default_table_path())


def _with(table, **settings):
    return replace(table, schedule=replace(table.schedule, **settings))


class Feed:
    """Samples for a controller, in sequence at the table's rate."""

    def __init__(self, table):
        self.rate = table.design.sample_rate_hz
        self.sequence = 0
        self.sample = Sample()

    def __call__(self, load, strains=ZERO) -> Sample:
        s = self.sample
        self.sequence += 1
        s.sequence = self.sequence
        s.timestamp = self.sequence / self.rate
        s.missed = 0
        s.axial_load = load
        s.strains[:] = strains
        return s


def _running(table, load, overrides=None) -> tuple[Controller, Feed]:
    """A controller of ``table`` started on a sample at ``load`` (the schedule settled there)."""
    c = Controller(table, controller_config(overrides))
    feed = Feed(table)
    c.arm(feed(load))
    c.start()
    assert c.state == State.RUNNING
    return c, feed


def _index(c) -> int:
    return int(c.iv[e.V_INDEX])


def _offset(c) -> float:
    return float(c.fv[e.X_OFFSET])


def _filtered(c) -> float:
    return float(c.fv[e.X_FILTERED])


def _magnitudes(comp, i: int, offset: float):
    """Per matrix, the magnitudes the engine's product sums at grid point ``i`` and ``offset``:
    |M_i| at a grid point, |M_i| + |M_i+1| between two (offset |S_i| is at most |M_i+1 - M_i|)."""
    out = {m: np.abs(getattr(comp, m)[i]) for m in ("a", "b", "e", "c", "d", "ki")}
    if offset != 0.0:
        for m in out:
            out[m] = out[m] + np.abs(getattr(comp, m)[i + 1])
    return out


def _assert_product(actual, terms, what=""):
    """actual == sum of matrix @ vector to rounding: within 1e-12 of the sum of the magnitudes
    summed (the gains span ten decades, so the sums cancel). ``terms``: (matrix, its
    magnitudes, vector)."""
    expected = sum(m @ v for m, _, v in terms)
    scale = sum(mag @ np.abs(v) for _, mag, v in terms)
    assert np.all(np.abs(actual - expected) <= 1e-12 * scale), (what, actual, expected)


def _integral_effect(c, dxi) -> np.ndarray:
    """du = -Ki dxi at the engine's grid point and offset, by the engine's own call (``_control``'s
    anti-windup test)."""
    du = np.zeros(4)
    e._small_product(c._mats, c.iv[e.O_INT], 4, 4, c.iv[e.V_INDEX], c.fv[e.X_OFFSET],
                     np.asarray(dxi, dtype=float), 0, du, 0)
    return du


def _step_products(c, feed, load, point, rng, what=""):
    """One step at ``load`` from a random signal vector (random compensator state, integral and
    strains): the law's u and the compensator's next state equal the matrices ``point(c)`` gives
    after the step, applied to the signals the step used, and so does the integral effect."""
    n = c.table.compensator.n_states
    x_c = rng.standard_normal(n)
    c.compensator_state[:] = x_c
    c.xi[:] = rng.standard_normal(4)
    y = 1e-4 * rng.standard_normal(4)
    c.step(feed(load, y))
    assert c.state == State.RUNNING, c.supervisor.reason()
    point = point(c)
    mags = _magnitudes(c.table.compensator, _index(c), _offset(c))
    xi, applied = c.xi.copy(), c.applied_forces.copy()      # the integral the law used, the forces applied
    np.testing.assert_array_equal(c.strains, y)
    _assert_product(c.u, [(-point.c, mags["c"], x_c), (-point.d, mags["d"], y), (-point.ki, mags["ki"], xi)],
                    f"u {what}")
    _assert_product(c.compensator_state, [(point.a, mags["a"], x_c), (point.b, mags["b"], y),
                                          (point.e, mags["e"], applied)], f"x_c {what}")
    dxi = rng.standard_normal(4)
    _assert_product(_integral_effect(c, dxi), [(-point.ki, mags["ki"], dxi)], f"du {what}")


@pytest.mark.parametrize("mode", ["interpolate", "paper"])
@pytest.mark.parametrize("which", ["table", "lqg"])
def test_the_products_the_step_runs_are_the_matrices_the_schedule_reports(request, which, mode):
    """What the engine's step computes, (M_i + offset S_i) s without forming the matrices, equals
    matrices_at(filtered load) applied to the signals (in ``paper`` mode the matrices of the grid
    point in use): the check analyses what the step runs. A noisy load sweep across the grid,
    each step from a random signal vector; the small table runs the whole-matrix products, the
    LQG the per-plane ones."""
    table = _with(request.getfixturevalue(which), mode=mode)
    schedule = GainSchedule.from_table(table)
    comp = table.compensator
    loads = table.loads_n
    rng = np.random.default_rng(2)
    steps = 2000
    sweep = loads[0] + (loads[-1] - loads[0]) * np.linspace(0.05, 0.95, steps)
    sweep += 20.0 * rng.standard_normal(steps)
    # random signals saturate the stacks at every step: no saturation fault within the sweep
    saturation_s = 2 * steps / table.design.sample_rate_hz
    c, feed = _running(table, sweep[0], {"safety": {"saturation_time_s": saturation_s}})
    if mode == "paper":         # switched with hysteresis: the grid point in use, no offset
        def point(c):
            assert _offset(c) == 0.0
            return comp.point(_index(c))
    else:                       # the engine's grid point and offset are the rule's, exactly
        def point(c):
            assert (_index(c), _offset(c)) == schedule._settled(_filtered(c))
            return schedule.matrices_at(_filtered(c))
    visited = set()
    for k, load in enumerate(sweep):
        _step_products(c, feed, load, point, rng, f"step {k}, load {load:.1f} N")
        assert c.record[e.I_LOAD_FILTERED] == _filtered(c)
        assert not c.iv[e.V_OUT_OF_RANGE]
        visited.add(_index(c))
    assert max(visited) - min(visited) >= 3, f"the sweep should cross the grid: {sorted(visited)}"


@pytest.mark.parametrize("mode", ["interpolate", "paper"])
def test_outside_the_grid_the_engine_holds_the_edge_and_flags_it(table, mode):
    """Followed beyond either end of the grid, the engine's schedule holds the edge point (no
    offset, nothing extrapolated) and raises its out-of-range flag; its products are the edge
    matrices, which matrices_at reports there too."""
    table = _with(table, mode=mode)
    comp, schedule = table.compensator, GainSchedule.from_table(table)
    last = len(table.loads_n) - 1
    rng = np.random.default_rng(0)
    for start, load, edge in ((1900.0, 2600.0, last), (100.0, -50.0, 0)):
        c = Controller(table, controller_config())
        c.arm(Feed(table)(start))
        assert not c.iv[e.V_OUT_OF_RANGE]
        for _ in range(2000):       # 0.8 s, 25 time constants of the load filter
            e._follow(c.iv, c.fv, c._mats, load)
        assert _filtered(c) == pytest.approx(load, abs=1e-6)
        assert (_index(c), _offset(c), int(c.iv[e.V_OUT_OF_RANGE])) == (edge, 0.0, 1)
        # the law's product at the held edge, on the controller's own arrays
        x_c, y, xi = rng.standard_normal(comp.n_states), rng.standard_normal(4), rng.standard_normal(4)
        c.compensator_state[:], c.strains[:], c.xi[:] = x_c, y, xi
        e._output(c._buffer, c.iv, c.fv, c._mats)
        point, mags = comp.point(edge), _magnitudes(comp, edge, 0.0)
        _assert_product(c.u, [(-point.c, mags["c"], x_c), (-point.d, mags["d"], y),
                              (-point.ki, mags["ki"], xi)])
        reported = schedule.matrices_at(load)
        for m in ("a", "b", "e", "c", "d", "ki"):
            np.testing.assert_array_equal(getattr(reported, m), getattr(point, m), err_msg=m)


@pytest.mark.parametrize("mode", ["interpolate", "paper"])
@pytest.mark.parametrize(("start", "load"), [(1900.0, 2600.0), (100.0, -50.0)])
def test_a_running_controller_faults_once_the_filtered_load_leaves_the_table(table, mode, start, load):
    """A load step beyond the grid (within the load cell's range): the controller runs on while
    the filtered load is within the table and faults LOAD_OUT_OF_TABLE_RANGE at the first sample
    it leaves it, flagged LOAD_OUT_OF_TABLE, the edge held."""
    table = _with(table, mode=mode)
    first, last = float(table.loads_n[0]), float(table.loads_n[-1])
    c, feed = _running(table, start)
    alpha = GainSchedule.from_table(table).alpha
    expected, f = 0, start          # the sample the filter leaves the grid at, by its own recurrence
    while first <= f <= last:
        f += alpha * (load - f)
        expected += 1
    for k in range(1, 10 * expected):
        c.step(feed(load))
        filtered = c.record[e.I_LOAD_FILTERED]
        if first <= filtered <= last:
            assert c.state == State.RUNNING, f"faulted at sample {k}, the filtered load {filtered} N within"
            assert not int(c.record[e.I_FLAGS]) & e.FLAG_LOAD_OUT_OF_TABLE
            continue
        assert c.state == State.FAULT and c.supervisor.fault == Fault.LOAD_OUT_OF_TABLE_RANGE
        assert int(c.record[e.I_FLAGS]) & e.FLAG_LOAD_OUT_OF_TABLE
        assert int(c.record[e.I_FLAGS]) & e.FLAG_RAMPING_TO_BIAS
        assert k == expected
        assert c.fv[e.X_FAULT_VALUE] == filtered
        assert f"outside the table's [{first:g}, {last:g}] N" in c.supervisor.detail
        if load > last:
            held = len(table.loads_n) - 1
        else:   # the paper's band holds grid point 1 until the load falls below L_0 - h/2
            held = 1 if mode == "paper" else 0
        assert (_index(c), _offset(c)) == (held, 0.0)
        break
    else:
        pytest.fail("the controller never faulted")
    before = _filtered(c)
    c.step(feed(load))              # faulted: the schedule no longer follows
    assert _filtered(c) == before and c.supervisor.fault == Fault.LOAD_OUT_OF_TABLE_RANGE


def test_load_cell_value_is_low_pass_filtered(table):
    """First order at 5 Hz: after one time constant 63 % of a step."""
    c, feed = _running(table, 1000.0)
    rate = table.design.sample_rate_hz
    tau_samples = int(round(rate / (2 * np.pi * table.schedule.load_filter_hz)))
    for _ in range(tau_samples):
        c.step(feed(2000.0))
    assert c.state == State.RUNNING
    assert _filtered(c) == pytest.approx(1000.0 + 1000.0 * (1 - np.exp(-1)), abs=5.0)
    assert c.record[e.I_LOAD_FILTERED] == _filtered(c)
    assert c.record[e.I_LOAD] == 2000.0


@pytest.mark.parametrize(("hysteresis", "chatters"), [(50.0, False), (0.0, True)])
def test_paper_switching_does_not_chatter_on_a_noisy_load_cell(table, hysteresis, chatters):
    """A slow ramp through 1000 N with 30 N RMS load-cell noise: one switch with the 50 N
    band; without it the filtered noise flips between the gains."""
    table = _with(table, mode="paper", load_filter_hz=5.0, hysteresis_n=hysteresis)
    rng = np.random.default_rng(1)
    rate = table.design.sample_rate_hz
    ramp = np.linspace(900.0, 1100.0, int(10 * rate)) + 30.0 * rng.standard_normal(int(10 * rate))
    c, feed = _running(table, 900.0)
    indices = np.empty(len(ramp), dtype=int)
    for k, load in enumerate(ramp):
        c.step(feed(load))
        indices[k] = _index(c)
    assert c.state == State.RUNNING
    switches = int(np.count_nonzero(np.diff(indices)))
    if chatters:
        assert switches > 1, "without hysteresis the noise should make the gain chatter"
    else:
        assert switches == 1, f"{switches} switches through one threshold"
        c.step(feed(1100.0))
        assert _index(c) == 3


@pytest.mark.parametrize(("load", "point"), [(1400.0, 3), (1500.0, 3), (1501.0, 4)])
def test_paper_mode_runs_the_matrices_of_the_next_grid_point(table, load, point):
    """The operator switched on to the next gain as the load passed each grid point: settled at a
    load, the engine runs the matrices of the grid point at or above it, as matrices_at reports."""
    table = _with(table, mode="paper")
    comp = table.compensator
    c, feed = _running(table, load)
    assert _index(c) == point
    rng = np.random.default_rng(3)
    reported = GainSchedule.from_table(table).matrices_at(load)
    for m in ("a", "b", "e", "c", "d", "ki"):
        np.testing.assert_array_equal(getattr(reported, m), getattr(comp, m)[point], err_msg=m)
    _step_products(c, feed, load, lambda c: comp.point(_index(c)), rng)
    assert _index(c) == point


def test_non_finite_load_keeps_the_matrices_and_faults(table):
    """The schedule does not filter a non-finite reading: grid point, offset and filtered load
    are kept (the products unchanged) and it counts as out of range. A running controller faults
    LOAD_NOT_FINITE on it first (the input check comes before the schedule)."""
    c, feed = _running(table, 1234.0)
    c.step(feed(1234.0))
    state = (_index(c), _offset(c), _filtered(c))
    assert state == (2, 234.0, 1234.0)
    rng = np.random.default_rng(4)
    c.compensator_state[:] = rng.standard_normal(c.table.compensator.n_states)
    c.strains[:], c.xi[:] = rng.standard_normal(4), rng.standard_normal(4)
    e._output(c._buffer, c.iv, c.fv, c._mats)
    before = c.u.copy()
    for bad in (float("nan"), float("inf"), -float("inf")):
        e._follow(c.iv, c.fv, c._mats, bad)
        assert (_index(c), _offset(c), _filtered(c)) == state
        assert c.iv[e.V_OUT_OF_RANGE] == 1
        e._output(c._buffer, c.iv, c.fv, c._mats)
        np.testing.assert_array_equal(c.u, before)
    for bad in (float("nan"), float("inf"), -float("inf")):
        c, feed = _running(table, 1234.0)
        c.step(feed(1234.0))
        c.step(feed(bad))
        assert c.supervisor.fault == Fault.LOAD_NOT_FINITE
        assert (_index(c), _offset(c), _filtered(c)) == state


def test_paper_switching_loads_rising_and_falling(table):
    """Rising, the matrices of grid point i + 1 take over once the load passes L_i + h/2 (the
    operator switched on to the next gain as the load passed each point); falling, those of
    point i - 1 come back below L_(i-1) - h/2. Swept in 0.1 N steps through a running
    controller with the load filter made transparent, each switch lies within one step of its
    load."""
    loads = [0.0, 500.0, 1000.0, 1500.0, 2000.0]
    level = np.arange(len(loads), dtype=float)[:, None, None]
    comp = Compensator(a=level * np.ones((5, 2, 2)), b=level * np.ones((5, 2, 4)),
                       e=np.zeros((5, 2, 4)), c=level * np.ones((5, 4, 2)), d=level * np.ones((5, 4, 4)),
                       ki=level * np.ones((5, 4, 4)), h=np.eye(4), start=np.zeros((2, 4)),
                       period_s=1 / 2500.0, plane_states={"y": [0], "z": [1]})
    # a table of that compensator (a design of its own: no K)
    levels = replace(table, loads_n=np.array(loads), compensator=comp, gains=None,
                     design=replace(table.design, kind="lqg", velocity_cutoff_hz=None, weights=None),
                     schedule=ScheduleSettings(mode="paper", load_filter_hz=1e12, hysteresis_n=50.0))
    assert GainSchedule.from_table(levels).alpha == 1.0

    def switches(sweep):
        c, feed = _running(levels, sweep[0])
        found, index = [], _index(c)
        for load in sweep:
            c.step(feed(load))
            assert _filtered(c) == load
            if _index(c) != index:
                found.append((round(load, 1), index, _index(c)))
                index = _index(c)
        assert c.state == State.RUNNING
        return found, c

    up, _ = switches(np.clip(np.arange(0.0, 2000.05, 0.1), 0.0, 2000.0))
    assert [(a, b) for _, a, b in up] == [(0, 1), (1, 2), (2, 3), (3, 4)], up
    step = 0.1 + 1e-6
    for load, i, _ in up:
        assert loads[i] + 25.0 < load <= loads[i] + 25.0 + step, f"switched up from {loads[i]} N at {load} N"
    down, c = switches(np.clip(np.arange(2000.0, -0.05, -0.1), 0.0, 2000.0))
    assert [(a, b) for _, a, b in down] == [(4, 3), (3, 2), (2, 1)], down
    for load, i, _ in down:
        assert loads[i - 1] - 25.0 - step <= load < loads[i - 1] - 25.0, (
            f"switched down from {loads[i]} N at {load} N")
    # the engine's law at the grid point it settled on: point 1's matrices are all ones
    assert _index(c) == 1
    c._buffer[e.I_SIGNALS:e.I_SIGNALS + 12] = 1.0
    c.compensator_state[:] = 1.0
    e._output(c._buffer, c.iv, c.fv, c._mats)
    np.testing.assert_array_equal(c.u, np.full(4, -10.0))      # u = -(C 1 + D 1 + Ki 1) = -(2 + 4 + 4)
