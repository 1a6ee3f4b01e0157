"""Model parameters: Table 1 defaults, key-by-key overrides, refusal of bad input."""

import math

import pytest

from beamctl.config.schema import ConfigError
from beamctl.models import build_model, load_parameters, parameters_from_dict, reduce
from beamctl.models.fe import buckling_eigen, structure


def test_defaults_are_table_1_of_the_paper(paper_params):
    p = paper_params
    assert (p.beam.length, p.beam.radius, p.beam.density) == (0.400, 4.0e-3, 2789.0)
    assert (p.beam.youngs_modulus, p.beam.proportional_limit) == (75.8e9, 485.0e6)
    assert (p.extension.length, p.extension.radius) == (7.5e-3, 6.0e-3)
    assert (p.extension.density, p.extension.youngs_modulus) == (7810.0, 210.0e9)
    assert (p.supports.rotational_stiffness, p.supports.lateral_stiffness,
            p.supports.actuator_stiffness) == (192.4, 30.0e6, 22.0e6)
    assert p.sensors.strain_gauge_positions == (0.148, 0.252)
    assert p.damping.ratios == (0.015, 0.0045)
    assert p.damping.identification_load == 2000.0
    assert p.fe.nodes == 35
    assert p.modal.reference_load_fraction == 0.78


def test_a_partial_file_overrides_only_its_keys(tmp_path, paper_params):
    f = tmp_path / "stiffer.yaml"
    f.write_text("supports:\n  rotational_stiffness: 250.0\nfe: {nodes: 21}\n")
    p = load_parameters(f)
    assert p.supports.rotational_stiffness == 250.0
    assert p.fe.nodes == 21
    assert p.supports.lateral_stiffness == paper_params.supports.lateral_stiffness
    assert p.beam == paper_params.beam


@pytest.mark.parametrize(
    ("overrides", "key", "expected_words"),
    [
        ({"beams": {"length": 0.4}}, "beams", "known keys"),
        ({"beam": {"lenght": 0.4}}, "beam.lenght", "known keys"),
        ({"supports": {"lateral_stiffness": -1.0}}, "supports.lateral_stiffness", "from 100 to 1e+11 N/m"),
        ({"supports": {"rotational_stiffness": 0.0}}, "supports.rotational_stiffness", "from 0.001 to"),
        ({"supports": {"actuator_stiffness": "stiff"}}, "supports.actuator_stiffness", "finite number"),
        ({"beam": {"radius": True}}, "beam.radius", "finite number"),
        ({"beam": {"density": float("nan")}}, "beam.density", "finite number"),
        ({"beam": {"length": None}}, "beam.length", "finite number"),
        ({"fe": {"nodes": 4}}, "fe.nodes", "integer >= 5"),
        ({"fe": {"nodes": 35.5}}, "fe.nodes", "integer"),
        ({"sensors": {"strain_gauge_positions": [0.148, 0.45]}},
         "sensors.strain_gauge_positions[1]", "inside the beam"),
        ({"sensors": {"strain_gauge_positions": [0.0, 0.252]}},
         "sensors.strain_gauge_positions[0]", "inside the beam"),
        ({"sensors": {"strain_gauge_positions": [0.148]}}, "sensors.strain_gauge_positions", "list of 2"),
        ({"sensors": {"strain_gauge_positions": [0.2, 0.2]}},
         "sensors.strain_gauge_positions", "different"),
        ({"damping": {"ratios": [0.015, 1.5]}}, "damping.ratios", "< 1"),
        ({"beam": 0.4}, "beam", "mapping"),
    ],
)
def test_bad_input_is_refused_naming_key_value_and_expectation(overrides, key, expected_words):
    with pytest.raises(ConfigError) as err:
        parameters_from_dict(overrides, source="test.yaml")
    message = str(err.value)
    assert err.value.key == key, message
    assert key in message and "test.yaml" in message, message
    assert expected_words in message, message
    assert "expected" in message, message


def test_damping_identified_on_the_unloaded_beam_is_refused_as_negative_damping():
    """The paper's ratios fitted at the unloaded eigenfrequencies need beta < 0."""
    params = parameters_from_dict({"damping": {"identification_load": 0.0}})
    with pytest.raises(ConfigError) as err:
        build_model(params)
    assert err.value.key == "damping.ratios"
    assert "negative damping" in str(err.value) and "beta = -" in str(err.value)


def test_identification_load_beyond_buckling_is_refused_naming_the_critical_load():
    params = parameters_from_dict({"damping": {"identification_load": 3300.0}})
    with pytest.raises(ConfigError, match=r"below this model's critical buckling load Fx,cr = 3193\.5 N"):
        build_model(params)


def test_a_model_buckling_below_the_identification_load_is_refused_and_fits_below_it():
    """The damping ratios hold at the load they were measured at: a beam that buckles below
    2000 N cannot have been identified there, and is fitted at a load it carries."""
    thin = {"beam": {"radius": 3.5e-3}}
    x, mass, elastic, geometric, b0, c0 = structure(parameters_from_dict(thin))
    critical, _ = buckling_eigen(elastic, geometric)
    assert critical < 2000.0, "the thin beam must buckle below the identification load"
    with pytest.raises(ConfigError) as err:
        build_model(parameters_from_dict(thin))
    assert err.value.key == "damping.identification_load", str(err.value)
    assert f"Fx,cr = {critical:.1f} N" in str(err.value), "the message gives the model's own Fx,cr"
    model = build_model(parameters_from_dict({**thin, "damping": {"identification_load": 1200.0}}))
    assert model.rayleigh_alpha > 0 and model.rayleigh_beta > 0


def test_the_soft_supports_model_fits_its_damping_at_2000_N():
    """Buckling at 2381 N, the model with soft supports is still identified at 2000 N."""
    params = parameters_from_dict({"supports": {"lateral_stiffness": 2.0e6, "actuator_stiffness": 5.0e6}})
    model = build_model(params)
    assert model.rayleigh_alpha > 0 and model.rayleigh_beta > 0


def test_the_old_absolute_reference_load_is_refused_naming_the_new_key(tmp_path):
    f = tmp_path / "old.yaml"
    f.write_text("modal: {reference_load: 2500.0}\n")
    with pytest.raises(ConfigError) as err:
        load_parameters(f)
    message = str(err.value)
    assert err.value.key == "modal.reference_load", message
    assert "modal.reference_load_fraction" in message and "old.yaml" in message, message


@pytest.mark.parametrize("fraction", [1.0, 1.2, -0.1])
def test_a_reference_load_fraction_outside_0_to_1_is_refused(fraction):
    with pytest.raises(ConfigError) as err:
        parameters_from_dict({"modal": {"reference_load_fraction": fraction}})
    assert err.value.key == "modal.reference_load_fraction" and "< 1" in str(err.value)


def test_gauges_that_cannot_tell_the_modes_apart_are_refused_with_the_condition_number():
    params = parameters_from_dict({"sensors": {"strain_gauge_positions": [0.148, 0.1481]}})
    with pytest.raises(ConfigError) as err:
        reduce(build_model(params))
    assert err.value.key == "sensors.strain_gauge_positions"
    assert "cond(C0 Phi) =" in str(err.value)


def test_digest_identifies_the_parameter_set(paper_params):
    same = load_parameters()
    other = parameters_from_dict({"beam": {"radius": 4.1e-3}})
    assert same.digest() == paper_params.digest()
    assert other.digest() != paper_params.digest()
    assert len(paper_params.digest()) == 64 and not math.isnan(int(paper_params.digest(), 16))


@pytest.mark.parametrize("section, key, value, unit", [
    ("beam", "length", 400.0, "m"),                     # mm for m
    ("beam", "youngs_modulus", 75.8, "N/m^2"),          # GPa for Pa
    ("beam", "radius", 4.0, "m"),
    ("supports", "lateral_stiffness", 30.0, "N/m"),     # MN/m for N/m
    ("extension", "length", 7.5, "m"),
])
def test_a_value_in_the_wrong_unit_is_refused_naming_its_key_and_unit(section, key, value, unit):
    """Before, beam.length: 400 passed the schema and was refused as a damping identification
    load above a critical load of 0 N."""
    with pytest.raises(ConfigError) as info:
        parameters_from_dict({section: {key: value}}, "rig.yaml")
    message = str(info.value)
    assert f"{section}.{key} = {value:g}" in message and f"(in {unit})" in message, message
    assert " from " in message and " to " in message, f"the plausible range is said: {message}"
