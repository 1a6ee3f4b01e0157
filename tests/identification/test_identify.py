"""Identification on the simulated rig and the model fit: the rig's own parameters come back,
the excitation stays within its voltages, and every way the run can end early leaves the
stacks at bias."""

import signal

import numpy as np
import pytest

from beamctl.assembly.run import load_gain_table, service_config
from beamctl.common.signals import Interrupted, stop_on_signals
from beamctl.config.schema import ConfigError
from beamctl.hal.sim import SimBackend
from beamctl.identification.identify import IdentificationError, IdentifySettings, identify, record
from beamctl.models import build_model, load_parameters, parameters_from_dict
from beamctl.models.fit import FitError, FitSettings, fit
from beamctl.models.measured import PLANE_PAIRS, resonances
from beamctl.models.plant import Plant, plant_config

# The rig of the acceptance: its own beam differs from Table 1 (kr x0.8, modal damping x1.5,
# E x1.02) and its stacks give 3.3 N/V where the controller believes 3.0 N/V; the strain noise of
# the shipped experiment scenario (0.2 ue RMS).
TRUTH = {"beam.youngs_modulus": 75.8e9 * 1.02, "supports.rotational_stiffness": 192.4 * 0.8,
         "damping.ratios": [0.015 * 1.5, 0.0045 * 1.5], "actuators.force_constant_n_per_v": 3.3}
RIG = {"hal": {"sim": {"pace": "simulated", "own_actuators": True,
                       "actuators": {"force_constant_n_per_v": 3.3}}},
       "plant": {"noise": {"strain": 2e-7, "load": 2.0, "seed": 1},
                 "model": {"beam": {"youngs_modulus": TRUTH["beam.youngs_modulus"]},
                           "supports": {"rotational_stiffness": TRUTH["supports.rotational_stiffness"]},
                           "damping": {"ratios": TRUTH["damping.ratios"]}}}}
# the issue's tolerances: E and kr 1 %, the damping ratios 10 %, the force constant 2 %
TOLERANCE = {"beam.youngs_modulus": 0.01, "supports.rotational_stiffness": 0.01, "damping.ratios": 0.10,
             "actuators.force_constant_n_per_v": 0.02}
# reduced length: 3 averaged periods of 1 s per input (the command's default is 8)
SHORT = IdentifySettings(load_n=2000.0, averages=3)


@pytest.fixture(scope="module")
def rig():
    cfg = service_config(RIG, "mismatched rig")
    return cfg, load_gain_table(cfg)


@pytest.fixture(scope="module")
def measured(rig):
    cfg, table = rig
    data, _ = identify(cfg, table, SHORT)
    return data


def _rig_response(cfg, table, freqs, load_n=2000.0):
    """The mismatched rig's own sampled response, as its forces are computed with 3.0 N/V."""
    params = parameters_from_dict(RIG["plant"]["model"])
    plant = Plant(build_model(params), plant_config({"sample_rate_hz": table.design.sample_rate_hz,
                                                     "io": table.design.io.to_dict()}))
    return plant.frequency_response(load_n, freqs) * (3.3 / cfg.controller.actuators.force_constant_n_per_v)


def _spy_on_writes(monkeypatch) -> list:
    """Every voltage vector the simulated rig's HAL is sent, in order."""
    written = []
    original = SimBackend._write

    def spy(self, voltages):
        written.append(np.array(voltages))
        original(self, voltages)

    monkeypatch.setattr(SimBackend, "_write", spy)
    return written


def test_the_h1_estimate_is_the_rig_s_own_response_where_it_is_coherent(rig, measured):
    cfg, table = rig
    g = _rig_response(cfg, table, measured.frequencies_hz)
    for plane, pairs in PLANE_PAIRS.items():
        for i, j in pairs:
            good = measured.coherence[:, i, j] > 0.99
            assert good.mean() > 0.5, f"most of the band is coherent in {plane} ({i}, {j})"
            error = np.log(measured.frf[good, i, j] / g[good, i, j])
            # unbiased: the noise (about 1.5 % a point over 3 averages) scatters both ways
            for part, name in ((error.real, "log magnitude"), (error.imag, "phase (rad)")):
                assert abs(np.median(part)) < 0.005, f"({i}, {j}): {name} biased by {np.median(part):.3g}"
            # where the response stands far above the noise (its largest tenth), within 1 %
            strong = np.abs(g[good, i, j]) >= np.quantile(np.abs(g[good, i, j]), 0.9)
            assert np.median(np.abs(error[strong])) < 0.01, f"({i}, {j}) near its resonances"


def test_the_forces_of_one_plane_do_not_move_the_other(measured):
    """y forces, z strains: nothing but noise (the planes are decoupled)."""
    for i, j in ((1, 0), (3, 0), (0, 1), (2, 3)):
        assert np.median(measured.coherence[:, i, j]) < 0.5, f"({i}, {j}) is not coherent"


def test_the_fit_recovers_the_rig_s_own_parameters_within_the_issue_s_tolerances(measured):
    result = fit(load_parameters(), [measured], FitSettings())
    for key, truth in TRUTH.items():
        fitted = np.asarray(result.values[key])
        error = np.abs(fitted / np.asarray(truth) - 1)
        assert np.all(error < TOLERANCE[key]), (
            f"{key}: fitted {fitted}, rig {truth}: {100 * error} % off (allowed {100 * TOLERANCE[key]:g} %)")
        # the standard error says how far off the value may be: within 4 of them
        allowed = 4 * np.asarray(result.std_errors[key]) + 1e-4 * np.abs(truth)
        assert np.all(np.abs(fitted - truth) < allowed), (
            f"{key}: {fitted} vs {truth} beyond 4 standard errors {result.std_errors[key]}")
    assert result.cost < 0.1 * result.start_cost, "the fit explains most of what the start model missed"
    # from one load the supports' stiffnesses are hard to separate: the fit names the group and
    # what the data determine of it, far better than any one of them
    tied = [c for c in result.combinations if "supports.rotational_stiffness" in c["names"]]
    assert tied, f"kr's ties are not reported: {result.combinations}"
    kr = result.std_errors["supports.rotational_stiffness"] / result.values["supports.rotational_stiffness"]
    assert tied[0]["relative_std_error"] < 0.2 * kr, (tied[0], kr)


def test_a_fit_stopped_before_it_converged_is_refused(measured):
    with pytest.raises(FitError, match="did not converge"):
        fit(load_parameters(), [measured], FitSettings(max_evaluations=3))


def test_a_parameter_the_data_do_not_determine_is_refused(measured):
    """The beam's proportional limit does not enter its dynamics."""
    with pytest.raises(FitError, match="do not depend on beam.proportional_limit"):
        fit(load_parameters(), [measured], FitSettings(parameters=("kr", "beam.proportional_limit")))


def test_the_excitation_never_leaves_bias_plus_minus_its_amplitude(rig, monkeypatch):
    cfg, table = rig
    written = _spy_on_writes(monkeypatch)
    record(cfg, table, IdentifySettings(load_n=1000.0, averages=3, resolution_hz=4.0, amplitude_v=7.5,
                                        signal="chirp"))
    v = np.array(written)
    assert np.max(np.abs(v - 75.0)) <= 7.5 + 1e-9
    assert np.max(np.abs(v - 75.0)) > 7.0, "the full swing was used"
    np.testing.assert_allclose(v[-1], 75.0, err_msg="the run ends with the stacks at bias")


@pytest.mark.parametrize("settings, flag", [
    (IdentifySettings(load_n=2000.0, amplitude_v=80.0), "--amplitude"),
    (IdentifySettings(load_n=2000.0, averages=2), "--averages"),
    (IdentifySettings(load_n=2000.0, averages=1000, resolution_hz=0.1), "--averages"),
    (IdentifySettings(load_n=2000.0, resolution_hz=1e-9), "--resolution"),
    (IdentifySettings(load_n=3100.0), "--load"),
    (IdentifySettings(load_n=3100.0, closed_loop=True, supports="A"), "--supports"),
    (IdentifySettings(load_n=2000.0, band_hz=(10.0, 4000.0)), "--band"),
])
def test_settings_that_cannot_run_safely_are_refused_before_the_stacks_move(rig, settings, flag, monkeypatch):
    cfg, table = rig
    monkeypatch.setattr(SimBackend, "_open", lambda self: pytest.fail("the HAL was opened"))
    with pytest.raises(ConfigError) as info:
        record(cfg, table, settings)
    assert info.value.key == flag


def test_a_strain_beyond_the_limit_stops_the_excitation_and_ramps_to_bias(rig, monkeypatch):
    cfg, table = rig
    written = _spy_on_writes(monkeypatch)
    with pytest.raises(IdentificationError, match="beyond --max-strain 1e-06"):
        record(cfg, table, IdentifySettings(load_n=2000.0, max_strain=1e-6))
    np.testing.assert_allclose(written[-1], 75.0, err_msg="the stacks end at bias")
    # the load settles for 0.5 s (3000 samples) before the excitation starts
    assert len(written) < 3000 + 6000, "stopped within the first second of a 36 s excitation"


def test_ctrl_c_ramps_the_stacks_to_bias_and_ends_in_interrupted(rig, monkeypatch):
    cfg, table = rig
    written = _spy_on_writes(monkeypatch)

    def ctrl_c(done, total, label):
        if done > 3000:
            signal.raise_signal(signal.SIGINT)

    with pytest.raises(Interrupted) as info, stop_on_signals() as stop:
        record(cfg, table, SHORT, progress=ctrl_c, stop=stop)
    assert info.value.exit_status == 130
    assert np.max(np.abs(written[-200] - 75.0)) > 0.1, "the stacks were moving when Ctrl-C came"
    np.testing.assert_allclose(written[-1], 75.0, err_msg="the stacks end at bias")


def test_closed_loop_identification_above_the_critical_load_gives_the_open_loop_plant(rig):
    """At 3300 N (past the rig's own 3225 N) the beam only stands under control; the excitation
    rides on the law and the reference estimate gives the unstable plant's response."""
    cfg, table = rig
    # the loop feeds the strain noise back to the forces: 6 V of excitation (on the stacks' 75 V
    # bias) keeps most of the band coherent above it (at 3 V only about half of the band of the
    # pair (0, 2) had a coherence above 0.99)
    s = IdentifySettings(load_n=3300.0, closed_loop=True, averages=3, band_hz=(40.0, 800.0), amplitude_v=6.0)
    data, _ = identify(cfg, table, s)
    g = _rig_response(cfg, table, data.frequencies_hz, 3300.0)
    for i, j in PLANE_PAIRS["y"]:
        good = data.coherence[:, i, j] > 0.99
        assert good.mean() > 0.5, f"most of the band is coherent in ({i}, {j})"
        error = np.log(data.frf[good, i, j] / g[good, i, j])
        # unbiased, although the controller feeds the measurement noise back to the forces
        for part, name in ((error.real, "log magnitude"), (error.imag, "phase (rad)")):
            assert abs(np.median(part)) < 0.01, f"({i}, {j}): {name} biased by {np.median(part):.3g}"


def test_over_can_the_same_identification_finds_the_same_beam(tmp_path, monkeypatch):
    """Nothing but the HAL changes: the DAQ emulator (the paper's beam at 1500 N, 2500 Hz) over
    python-can's virtual bus, its voltages quantised to the DBC's 0.6 V. The controller has the
    shipped safety (the gain table's ride-through limits); the emulator runs in lockstep and the
    CAN backend is the rig's (tests/hal/rigs.py: on a clock of the test's own, waiting for each
    sample while the emulator runs), so this machine's scheduling changes nothing."""
    import can

    from beamctl.gains.defaults import paper_table_path
    from beamctl.hal.emulator import CanPlantEmulator
    from beamctl.models import eigenfrequencies
    from tests.hal.rigs import GEOMETRY, MODEL, make_plant, service_backends

    channel = "identify-can"
    bus = can.Bus(interface="virtual", channel=channel)
    emulator = CanPlantEmulator(bus, make_plant(), GEOMETRY, pace="lockstep")
    service_backends(monkeypatch, emulator)
    emulator.start()
    cfg = service_config({"gains": {"table": str(paper_table_path())},
                          "hal": {"backend": "can", "can": {"interface": "virtual", "channel": channel,
                                                            "rate_tolerance": 0.0}}}, "can rig")
    try:
        data, report = identify(cfg, load_gain_table(cfg), IdentifySettings(
            load_n=1500.0, averages=3, resolution_hz=2.0, band_hz=(20.0, 800.0), supports="A"))
    finally:
        emulator.stop()
        bus.shutdown()
    expected = eigenfrequencies(MODEL, 1500.0, 2)
    found = resonances(data)["y"][:2]
    # the emulated DAQ samples at 2500 Hz; 2 Hz lines and a parabola place a peak within 1 Hz
    assert np.all(np.abs(np.array(found) - expected) < 1.0), f"found {found}, the beam has {expected}"


def test_a_closed_loop_run_that_ends_early_holds_the_beam_until_the_load_is_safe(rig, monkeypatch):
    """The strain limit trips at 3300 N, past the rig's own 3225 N: the law keeps the beam
    straight while the (simulated) operator lowers the load, and only below 0.95 x Fx,cr of the
    model do the stacks ramp to bias."""
    cfg, table = rig
    loads = []
    original = SimBackend._write

    def spy(self, voltages):
        loads.append((self.plant.axial_load, np.array(voltages)))
        original(self, voltages)

    monkeypatch.setattr(SimBackend, "_write", spy)
    with pytest.raises(IdentificationError, match="beyond --max-strain"):
        record(cfg, table, IdentifySettings(load_n=3300.0, closed_loop=True, averages=3, max_strain=2e-6,
                                            amplitude_v=3.0, band_hz=(40.0, 800.0)))
    safe = 0.95 * 3193.5
    np.testing.assert_allclose(loads[-1][1], 75.0, err_msg="the run ends at bias")
    last_off_bias = max(i for i, (_, v) in enumerate(loads) if np.max(np.abs(v - 75.0)) > 1e-9)
    assert loads[last_off_bias][0] < safe, (
        f"the stacks were still working at {loads[last_off_bias][0]:.0f} N, and at bias only below it")
    assert max(load for load, _ in loads) > 3290.0, "the excitation ran at 3300 N"


def test_the_transient_of_a_beam_near_its_critical_load_is_left_out(rig):
    """At 3000 N the first mode rings at 50 Hz for about a second: with a 0.1 s period, dropping
    one period would leave the ring in the averages. Without noise, the estimate is the rig's
    own response."""
    cfg, table = rig
    quiet = service_config({**RIG, "plant": {**RIG["plant"], "noise": {"strain": 0.0, "load": 0.0}}}, "quiet")
    data, report = identify(quiet, table, IdentifySettings(load_n=3000.0, averages=3, resolution_hz=10.0,
                                                           supports="A", band_hz=(20.0, 800.0)))
    assert report["transient_periods"] > 1
    g = _rig_response(cfg, table, data.frequencies_hz, 3000.0)
    error = np.abs(np.log(data.frf[:, 0, 0] / g[:, 0, 0]))
    worst = data.frequencies_hz[error.argmax()]
    assert error.max() < 1e-3, f"largest log error {error.max():.3g} at {worst} Hz"
