"""The model fit against a rig whose FE mesh is finer than the model's (models/fit.py): the
strains at the gauges depend on the mesh by about 0.1 %, and kr, kl and kp are so correlated
that this moves kr by percent; what the fit says about it."""

import numpy as np
import pytest

from beamctl.models import build_model, load_parameters, parameters_from_dict
from beamctl.models.analysis import fe_frequency_response
from beamctl.models.fit import FitSettings, fit
from beamctl.models.measured import FrfData

KR = "supports.rotational_stiffness"
SUPPORTS = ("E", "kr", "kl", "kp", "damping")
OWN = ("E", "kr", "damping")
# a rig off Table 1 in E and kr only, and one that is also off in kl and kp
RIG = {("beam", "youngs_modulus"): 1.01, ("supports", "rotational_stiffness"): 0.9}
RIG_KLP = {**RIG, ("supports", "lateral_stiffness"): 1.1, ("supports", "actuator_stiffness"): 0.9}


def _measured(factors: dict, nodes: int = 71):
    """The rig's exact response on ``nodes`` FE nodes (Table 1's model: 35), at 2000 N, no noise,
    as a measurement whose coherence (0.99 over 8 averages) predicts 1.8 % a point."""
    d = load_parameters().to_dict()
    for (section, name), f in factors.items():
        d[section][name] *= f
    d["fe"]["nodes"] = nodes
    rig = parameters_from_dict(d, "finer rig")
    freqs = np.arange(10.0, 1201.0, 2.0)
    g = fe_frequency_response(build_model(rig), 2000.0, freqs)
    return rig, FrfData(frequencies_hz=freqs, frf=g, coherence=np.full(g.shape, 0.99), load_n=2000.0,
                        settings={"identify": {"averages": 8}}, source="finer rig")


def _kr(result, rig):
    value, sd = result.values[KR], result.std_errors[KR]
    true = rig.supports.rotational_stiffness
    return value / true - 1.0, (value - true) / sd, sd / value


@pytest.fixture(scope="module")
def rig_klp():
    return _measured(RIG_KLP)


def test_without_the_mesh_s_account_kr_is_percent_off_and_said_to_be_undetermined(rig_klp):
    """The fact the mesh account and the supports' tie exist for: noise-free data, the model exact
    but for its mesh, and kr comes back percent off (its statistical interval alone, 0.3 %, missed
    it); tied to kl and kp it is said to be undetermined, with an interval that holds it."""
    rig, data = rig_klp
    result = fit(load_parameters(), [data], FitSettings(parameters=SUPPORTS, mesh_correction=False))
    error, z, _ = _kr(result, rig)
    assert abs(error) > 0.01, (
        f"kr {100 * error:.2f} % off: the mesh bias this test demonstrates is gone, and the fit's "
        "mesh account may no longer be needed")
    assert KR in result.undetermined and abs(z) < 1.96, (result.undetermined, z)


def test_with_kl_and_kp_free_the_interval_holds_kr_and_the_fit_says_it_is_loose(rig_klp):
    """The strains cannot tell kr from kp (they see one effective rotational stiffness of the
    support): the fit must say so and give an interval that holds the rig's kr."""
    rig, data = rig_klp
    result = fit(load_parameters(), [data], FitSettings(parameters=SUPPORTS))
    error, z, relative_sd = _kr(result, rig)
    assert abs(z) < 1.96, f"kr {100 * error:.2f} % off, outside its 95 % interval (z = {z:.2f})"
    assert KR in result.undetermined, f"kr +-{100 * relative_sd:.2f} %: not said to be undetermined"
    assert any(w.startswith((f"{KR} is not determined closely", f"{KR} is undetermined"))
               and "actuator_stiffness" in w for w in result.warnings), result.warnings
    # and what the data do determine of the supports: a product of powers far tighter than kr
    tied = [c for c in result.combinations if KR in c["names"]]
    assert tied and tied[0]["relative_std_error"] < 0.1 * relative_sd, result.combinations
    assert any(w.startswith("the data tie kr") for w in result.warnings), result.warnings
    assert result.mesh_correction and KR in result.mesh_correction, "the change the finer mesh made is said"
    assert result.parameters.fe.nodes == 35, "the fitted model keeps the start model's mesh"


def test_with_kl_and_kp_as_the_model_s_the_fit_recovers_kr_within_half_a_percent():
    rig, data = _measured(RIG, nodes=141)
    result = fit(load_parameters(), [data], FitSettings(parameters=OWN))
    error, z, _ = _kr(result, rig)
    # the acceptance's 1 % for kr with half of it spare; E to 0.05 %
    assert abs(error) < 0.005, f"kr {100 * error:.2f} % off (allowed 0.5 %)"
    assert abs(result.values["beam.youngs_modulus"] / rig.beam.youngs_modulus - 1) < 5e-4
    assert abs(z) < 1.96, f"kr's 95 % interval misses the rig: z = {z:.2f}"
    # E and kr tied from one load: kr's interval counts the mesh's uncertainty (a closeness
    # warning), but nothing says the model misses the data
    assert not [w for w in result.warnings if "residual" in w or "undetermined" in w], result.warnings
    assert result.misfit < 0.05, "noise-free data are explained far below the 1.8 % noise they claim"


def test_kl_and_kp_held_at_the_wrong_values_are_warned_of_by_the_misfit(rig_klp):
    """The rig's kl and kp are 10 % off and not freed: kr takes up the difference (tens of
    percent) and the residual stands above the data's noise; the fit says so."""
    rig, data = rig_klp
    result = fit(load_parameters(), [data], FitSettings(parameters=OWN))
    error, _, _ = _kr(result, rig)
    assert abs(error) > 0.1, f"kr only {100 * error:.1f} % off: this rig no longer shows the case"
    assert result.misfit > 2.0
    assert any(w.startswith("the residual is") and "kl, kp" in w for w in result.warnings), result.warnings


def test_the_misfit_is_one_for_measurements_noisy_as_their_coherence_says_whatever_their_averages():
    """Two files of the model's own response, with the noise an H1 estimate of coherence 0.99 has
    over 8 and over 64 averages (each part of the log error of variance (1 - g2) / (2 n g2)): the
    model explains them down to that noise, misfit 1 (the 0.1 allows the random draw: about 9000
    points). Before, the fewest averages stood for all, and this gave 0.56."""
    params = load_parameters()
    freqs = np.arange(10.0, 1201.0, 2.0)
    g = fe_frequency_response(build_model(params), 2000.0, freqs)
    rng = np.random.default_rng(5)
    data = []
    for n in (8, 64):
        sd = np.sqrt(0.01 / (2 * n * 0.99))
        noise = np.exp(rng.normal(0, sd, g.shape) + 1j * rng.normal(0, sd, g.shape))
        data.append(FrfData(frequencies_hz=freqs, frf=g * noise, coherence=np.full(g.shape, 0.99),
                            load_n=2000.0, settings={"identify": {"averages": n}}, source=f"{n} averages"))
    result = fit(params, data, FitSettings(parameters=("E",), mesh_correction=False))
    assert abs(result.misfit - 1.0) < 0.1, result.misfit


def test_a_file_that_does_not_say_its_averages_gives_no_misfit():
    _, data = _measured(RIG)
    odd = FrfData(frequencies_hz=data.frequencies_hz, frf=data.frf, coherence=data.coherence, load_n=2000.0,
                  settings={"identify": "8 averages"}, source="odd")
    result = fit(load_parameters(), [odd], FitSettings(parameters=("E", "kr"), mesh_correction=False))
    assert result.misfit is None


def test_a_rig_with_stiffer_supports_and_less_damping_is_found_from_table_1():
    """The rig of a lab that commissioned from Table 1 (kr, kl, kp 15 to 18 % stiffer, E +4 %,
    damping 0.57 x), noise-free on 71 nodes at 1000 and 2000 N: from Table 1 the fit once ended
    where the model refuses the damping (3 x the rig's, misfit 140); started from the measured
    resonances and the damping scale of least residual, it finds the rig."""
    d = load_parameters().to_dict()
    d["beam"]["youngs_modulus"] = 7.88e10
    d["supports"].update(rotational_stiffness=225.0, lateral_stiffness=34.5e6, actuator_stiffness=26.0e6)
    d["damping"]["ratios"] = [0.0085, 0.0025]
    d["fe"]["nodes"] = 71
    rig = parameters_from_dict(d, "stiffer rig")
    freqs = np.arange(10.0, 1201.0, 1.0)
    data = []
    for load in (1000.0, 2000.0):
        g = fe_frequency_response(build_model(rig), load, freqs)
        data.append(FrfData(frequencies_hz=freqs, frf=g, coherence=np.full(g.shape, 0.99), load_n=load,
                            settings={"identify": {"averages": 8}}, source=f"stiffer rig {load:g} N"))
    result = fit(load_parameters(), data, FitSettings(parameters=SUPPORTS))
    assert result.misfit < 1.0, f"misfit {result.misfit:.3g}: the fit did not find the rig"
    for key, tolerance in (("beam.youngs_modulus", 0.01), ("supports.rotational_stiffness", 0.05),
                           ("supports.lateral_stiffness", 0.05), ("supports.actuator_stiffness", 0.05),
                           ("damping.ratios", 0.10)):
        section, name = key.split(".")
        error = np.abs(np.asarray(result.values[key]) / np.asarray(d[section][name]) - 1)
        assert np.all(error < tolerance), f"{key}: {result.values[key]} against the rig's {d[section][name]}"
