"""Benchmarks of the gain schedule (``pytest tests/benchmarks --benchmark-enable -n 0``)."""

import itertools
from dataclasses import replace

import numpy as np
import pytest

from beamctl.gains.defaults import paper_table_path
from beamctl.gains.table import load_table
from beamctl.hal.base import Sample
from beamctl.rt import engine as e
from beamctl.rt.config import controller_config
from beamctl.rt.controller import Controller


@pytest.mark.parametrize("mode", ["interpolate", "paper"])
def test_schedule_follow_and_output(benchmark, mode):
    """The schedule's share of a step, as the engine runs it: follow the load, then the law's
    product (the compiled functions called on a controller's arrays, each call's dispatch from
    Python included)."""
    table = load_table(paper_table_path())
    c = Controller(replace(table, schedule=replace(table.schedule, mode=mode)), controller_config())
    first = Sample()
    first.axial_load = 260.0
    c.arm(first)
    loads = itertools.cycle(np.linspace(260.0, 3900.0, 1000).tolist())
    buf, iv, fv, mats = c._buffer, c.iv, c.fv, c._mats
    buf[e.I_SIGNALS:e.I_SIGNALS + 12] = 1e-6
    c.compensator_state[:] = 1e-6

    def step():
        e._follow(iv, fv, mats, next(loads))
        e._output(buf, iv, fv, mats)

    benchmark(step)
    assert np.all(np.isfinite(c.u))
