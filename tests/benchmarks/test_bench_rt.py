"""Benchmark of the whole control step (``pytest tests/benchmarks --benchmark-enable -n 0``)."""

import itertools

import numpy as np

from beamctl.gains.defaults import paper_table_path
from beamctl.gains.table import load_table
from beamctl.hal.base import Sample
from beamctl.rt.config import controller_config
from beamctl.rt.controller import Controller


def test_control_step(benchmark):
    table = load_table(paper_table_path())
    c = Controller(table, controller_config({"start_ramp_time_s": 0.0}))
    inputs = []
    for k in range(1000):
        s = Sample()
        s.strains[:] = 3e-6 * np.sin(2 * np.pi * 20 * k / 2500.0)
        s.axial_load = 300.0 + 3.4 * k
        inputs.append(s)
    c.arm(inputs[0])
    c.start()
    feed = itertools.cycle(inputs)
    benchmark(lambda: c.step(next(feed)))
    assert c.state.name == "RUNNING", c.supervisor.reason()
