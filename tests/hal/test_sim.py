"""The sim backend on a rig with a transport delay (``plant.io.delay_samples``)."""

import numpy as np

from beamctl.hal.sim import SimBackend
from tests.hal.rigs import GEOMETRY, make_plant

# a straight beam without noise: its strains are exactly zero until a force reaches it
QUIET = {"noise": {"strain": 0.0, "load": 0.0, "seed": 0}, "bow": {"amplitude": 0.0, "angle_deg": 0.0}}


def _first_moved(hal: SimBackend, samples: int = 6) -> tuple[int, np.ndarray]:
    """Answer sample 0 with bias, every later sample with +30 V on stack a1; the index of the
    first sample whose strains are not zero, and all strains read."""
    volts = np.full(6, GEOMETRY.bias_voltage_v)
    strains = []
    for k in range(samples):
        strains.append(hal.read(timeout=1.0).strains.copy())
        volts[0] = GEOMETRY.bias_voltage_v + (30.0 if k >= 1 else 0.0)
        hal.write(volts)
    moved = [k for k, s in enumerate(strains) if np.any(s != 0.0)]
    return moved[0], np.array(strains)


def test_a_voltage_reaches_the_strains_one_sample_later_on_a_rig_delayed_by_one_sample():
    """The answer to sample 1 shows in sample 2 on the direct rig, in sample 3 on a rig with
    one sample of transport delay; reopening the backend starts with nothing in the delay."""
    direct = SimBackend(make_plant(**QUIET), GEOMETRY, pace="simulated")
    delayed = SimBackend(make_plant(io={"delay_samples": 1}, **QUIET), GEOMETRY, pace="simulated")
    assert delayed.sample_rate_hz == delayed.plant.config.sample_rate_hz
    with direct:
        first_direct, strains_direct = _first_moved(direct)
    with delayed:
        first_delayed, strains_delayed = _first_moved(delayed)
    assert (first_direct, first_delayed) == (2, 3), "the delay adds exactly one sample"
    np.testing.assert_allclose(strains_delayed[1:], strains_direct[:-1], rtol=1e-12, atol=0.0)
    with delayed:
        again, _ = _first_moved(delayed)
    assert again == 3, "forces left in the delay by the previous run must not reach the beam"
