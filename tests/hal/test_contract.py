"""One contract, every backend (python-can's back-to-back pattern): the sim backend, and the
CAN backend talking to the plant emulator over the virtual bus."""

import time

import numpy as np
import pytest

from beamctl.hal.base import HalConnectionLost, HalStaleData
from tests.hal.rigs import GEOMETRY, RIGS

STRAIN_LSB = 5e-7      # DBC resolution of the strains
VOLTAGE_LSB = 0.15


@pytest.fixture(params=sorted(RIGS))
def rig(request):
    r = RIGS[request.param]()
    yield r
    r.close()


def test_samples_are_consecutive_and_carry_the_plant_s_outputs(rig):
    with rig.hal as hal:
        bias = np.full(6, 75.0)
        sequences = []
        for _ in range(50):
            s = hal.read(timeout=1.0)
            sequences.append(s.sequence)
            assert s.missed == 0, "a sample in order skipped none"
            assert s.strains.shape == (4,) and np.all(np.isfinite(s.strains))
            assert s.axial_load == pytest.approx(1500.0, abs=10.0)
            hal.write(bias)
        assert np.all(np.diff(sequences) % 256 == 1), sequences


def test_written_voltages_move_the_beam_as_the_stack_geometry_says(rig):
    """60 V on stack a1 (150 N along +z at support A): the strains settle at the full FE
    model's static response to that force, on every backend."""
    bias = np.full(6, 75.0)
    step = bias.copy()
    step[0] += 400 * VOLTAGE_LSB
    with rig.hal as hal:
        settle = []
        for _ in range(1500):
            settle.append(hal.read(timeout=1.0).strains.copy())
            hal.write(bias)
        samples = []
        for _ in range(2500):
            samples.append(hal.read(timeout=1.0).strains.copy())
            hal.write(step)
    change = np.mean(samples[-1000:], axis=0) - np.mean(settle[-1000:], axis=0)
    model = rig.plant.model
    forces = GEOMETRY.forces(step)
    expected = model.output_matrix @ np.linalg.solve(model.load_stiffness(1500.0),
                                                     model.input_matrix @ forces)
    assert abs(expected[1]) > 40 * STRAIN_LSB, "the test force must be well above resolution"
    np.testing.assert_allclose(change, expected, rtol=0.05, atol=2 * STRAIN_LSB,
                               err_msg=f"{rig.name}: strain change for 150 N at support A")


def test_silence_is_a_stale_data_time_out(rig):
    with rig.hal as hal:
        hal.read(timeout=1.0)
        hal.write(np.full(6, 75.0))
        rig.silence()
        start = time.monotonic()
        with pytest.raises(HalStaleData):
            for _ in range(10):       # frames already in flight may still arrive
                hal.read(timeout=0.02)
                hal.write(np.full(6, 75.0))
        assert time.monotonic() - start < 1.0


def test_close_and_reopen(rig):
    hal = rig.hal
    hal.open()
    hal.read(timeout=1.0)
    hal.write(np.full(6, 75.0))
    hal.close()
    with pytest.raises(HalConnectionLost):
        hal.read(timeout=0.01)
    with pytest.raises(HalConnectionLost):
        hal.write(np.full(6, 75.0))
    hal.open()
    s = hal.read(timeout=1.0)
    assert np.all(np.isfinite(s.strains))
    hal.write(np.full(6, 75.0))
