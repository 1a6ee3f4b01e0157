"""Benchmarks of the gain schedule (``pytest tests/benchmarks --benchmark-enable``)."""

import itertools

import numpy as np
import pytest

from beamctl.gains.defaults import default_table_path
from beamctl.gains.schedule import GainSchedule
from beamctl.gains.table import load_table


@pytest.mark.parametrize("mode", ["interpolate", "paper"])
def test_schedule_update(benchmark, mode):
    from dataclasses import replace

    table = load_table(default_table_path())
    s = GainSchedule(replace(table, schedule=replace(table.schedule, mode=mode)))
    loads = itertools.cycle(np.linspace(260.0, 3900.0, 1000).tolist())
    s.reset(260.0)
    k = benchmark(lambda: s.update(next(loads)))
    assert k.shape == (4, 12)
