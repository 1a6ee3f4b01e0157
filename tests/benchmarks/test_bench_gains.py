"""Benchmarks of the gain schedule (``pytest tests/benchmarks --benchmark-enable``)."""

import itertools

import numpy as np
import pytest

from beamctl.gains.defaults import paper_table_path
from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import load_table


@pytest.mark.parametrize("mode", ["interpolate", "paper"])
def test_schedule_follow_and_output(benchmark, mode):
    """The schedule's share of a step: follow the load, then the law's product."""
    from dataclasses import replace

    table = load_table(paper_table_path())
    s = GainSchedule.from_table(replace(table, schedule=replace(table.schedule, mode=mode)))
    loads = itertools.cycle(np.linspace(260.0, 3900.0, 1000).tolist())
    signals = np.full(12 + s.n_states, 1e-6)
    u = np.zeros(4)
    s.reset(260.0)

    def step():
        s.follow(next(loads))
        s.output(signals, u)

    benchmark(step)
    assert np.all(np.isfinite(u))
