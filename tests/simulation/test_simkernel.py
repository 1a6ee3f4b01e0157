"""The compiled kernel of offline runs (simulation/simkernel.py) runs the same run as the loop.

Each test runs one scenario twice, every cycle through ``ControlLoop`` and with the kernel
taking the uneventful cycles, and compares the runs sample by sample. The kernel's arithmetic
is the loop's in another summation order, so the two agree to rounding: 1e-9 of the quantity's
scale leaves ample room for the few ulps a sum of 50 products changes by while the beam is held,
and the comparison stops where the beam is let go and diverges (there a difference of one ulp
doubles every few samples; the load at which it happens is compared instead).
"""

from __future__ import annotations

import numpy as np
import pytest

from beamctl.config.schema import ConfigError
from beamctl.rt.loop import StopRequest
from beamctl.simulation.experiment import (
    check_engine,
    experiment_config,
    experiment_tables,
    run_mode,
    summarise,
)

# the load ramps fast from below the critical load, so a run crosses it within 3 s of plant time:
# control, saturation at 150 V, the saturation fault, the ramp to bias, the beam let go
FAST_RAMP = {"plant": {"load": {"start": 2000.0, "rate": 600.0, "hold": 0.05}}}


@pytest.fixture(scope="module")
def scenario():
    cfg, settings = experiment_config(FAST_RAMP, "fast ramp")
    return cfg, settings, experiment_tables(cfg, settings)


@pytest.fixture(scope="module")
def short_saturation():
    """The fast ramp with a saturation fault after 5 ms at 150 V: the fault comes before the
    beam is let go, so the run hands over to the loop at the fault and back for nothing."""
    cfg, settings = experiment_config({**FAST_RAMP, "controller": {"safety": {"saturation_time_s": 0.005}}},
                                      "fast ramp, short saturation")
    return cfg, settings, experiment_tables(cfg, settings)


def _both(scenario, mode, **kwargs):
    cfg, settings, tables = scenario
    loop = run_mode(mode, cfg, settings, tables[mode], engine="loop", **kwargs)
    kernel = run_mode(mode, cfg, settings, tables[mode], engine="kernel", **kwargs)
    return loop, kernel


def _assert_same_run(loop, kernel):
    a, b = loop.arrays(), kernel.arrays()
    assert kernel.cycles == loop.cycles, (
        f"the kernel's run took {kernel.cycles} cycles, the loop's {loop.cycles}: an event was missed "
        "or a cycle run twice")
    np.testing.assert_array_equal(b["load_n"], a["load_n"], err_msg="the monitor's samples differ in load")
    np.testing.assert_array_equal(b["state"], a["state"], err_msg="the lifecycle differs")
    np.testing.assert_array_equal(b["saturated"], a["saturated"], err_msg="saturation differs")
    assert kernel.end == loop.end and kernel.fault == loop.fault
    d = a["deflection_m"]
    failing = np.flatnonzero(d > 1.0e-3)
    held = np.arange(len(d)) < (failing[0] if failing.size else len(d))     # before the beam is let go
    assert held.sum() > 100, "too short a run to compare"
    for key in ("deflection_m", "deflection_y_m", "deflection_z_m", "true_deflection_m"):
        scale = np.max(np.abs(a[key][held]))
        np.testing.assert_allclose(b[key][held], a[key][held], rtol=0, atol=1e-9 * scale,
                                   err_msg=f"{key} differs beyond rounding while the beam is held")
    for key in ("v_min", "v_max"):
        np.testing.assert_allclose(b[key][held], a[key][held], rtol=0, atol=1e-9 * 150.0,
                                   err_msg=f"{key} differs beyond rounding")
    for threshold in ("load_at_0.5mm_N", "load_at_1.0mm_N"):
        x, y = summarise(loop, "", "")[threshold], summarise(kernel, "", "")[threshold]
        assert y == pytest.approx(x, abs=0.5), f"{threshold}: loop {x} N, kernel {y} N"


def test_the_controlled_run_through_saturation_fault_and_failure_is_the_loops(short_saturation):
    loop, kernel = _both(short_saturation, "interpolate")
    assert "PERSISTENT_SATURATION" in loop.fault, f"the scenario should saturate the stacks: {loop.fault!r}"
    _assert_same_run(loop, kernel)
    assert kernel.engine == "kernel" and loop.kernel_cycles == 0
    assert kernel.kernel_cycles > 0.5 * kernel.cycles, (
        f"only {kernel.kernel_cycles} of {kernel.cycles} cycles ran in the kernel: it hands over too often")


def test_the_paper_switching_run_is_the_loops(scenario):
    _assert_same_run(*_both(scenario, "paper"))


def test_the_uncontrolled_run_is_the_loops(scenario):
    loop, kernel = _both(scenario, "uncontrolled")
    _assert_same_run(loop, kernel)
    cfg = scenario[0]
    stop_ramp = round(cfg.controller.safety.ramp_time_s * 6000.0)
    assert kernel.kernel_cycles >= kernel.cycles - stop_ramp - 2, (
        f"{kernel.kernel_cycles} of {kernel.cycles} cycles in the kernel: all but the arming cycle and the "
        f"stop's ramp to bias ({stop_ramp} samples) should be")


def test_a_stop_request_ends_both_runs_at_the_same_cycle(scenario):
    """A stop set while the kernel runs is seen within its next hand-over, and the ramp to bias
    is the loop's: here the stop is set before the run, so both stop at once."""
    stop = StopRequest()
    stop.set("operator")
    loop, kernel = _both(scenario, "interpolate", stop=stop)
    assert kernel.cycles == loop.cycles and kernel.kernel_cycles == 0


def test_engine_choices_are_checked():
    assert check_engine("loop") == "loop"
    assert check_engine("auto", telemetry=True) == "loop", "telemetry is recorded by the loop only"
    assert check_engine("auto") == "kernel"
    with pytest.raises(ConfigError, match="telemetry"):
        check_engine("kernel", telemetry=True)
    with pytest.raises(ConfigError, match="one of auto, loop, kernel"):
        check_engine("gpu")


def test_the_controlled_run_held_at_150_v_is_the_loops(scenario):
    loop, kernel = _both(scenario, "interpolate")
    assert max(loop.v_max) == 150.0, "the scenario should drive a stack to its limit"
    _assert_same_run(loop, kernel)
