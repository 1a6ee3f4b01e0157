"""Configuration validation: YAML as users write it, and one kind of refusal (the dotted key,
the value found and what was expected) for every file of every room."""

import pytest

from beamctl.config.schema import (
    ConfigError,
    dotted_get,
    dotted_update,
    integer,
    merge,
    number,
    number_list,
    positive,
    read_yaml,
    refuse_renamed,
    validate,
)

SCHEMA = {"beam": {"length": positive("m"), "nodes": integer(low=5)},
          "gauges": number_list(number("m", low=0.0), 2, "gauge positions")}
VALID = {"beam": {"length": 0.4, "nodes": 35}, "gauges": [0.148, 0.252]}


def test_yaml_exponent_without_sign_is_a_number(tmp_path):
    """YAML 1.1 would read 80e9 as a string; users write it that way."""
    f = tmp_path / "e.yaml"
    f.write_text("beam: {youngs_modulus: 80e9, radius: 4e-3}\n")
    assert read_yaml(f) == {"beam": {"youngs_modulus": 80e9, "radius": 4e-3}}


def test_missing_file_and_non_mapping_file_are_refused(tmp_path):
    with pytest.raises(ConfigError, match="readable YAML file"):
        read_yaml(tmp_path / "absent.yaml")
    f = tmp_path / "list.yaml"
    f.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping at the top level"):
        read_yaml(f)
    g = tmp_path / "broken.yaml"
    g.write_text("beam: {length: [\n")
    with pytest.raises(ConfigError, match="valid YAML"):
        read_yaml(g)


def test_an_empty_file_is_an_empty_mapping(tmp_path):
    f = tmp_path / "empty.yaml"
    f.write_text("# nothing set\n")
    assert read_yaml(f) == {}


def test_a_yaml_syntax_error_is_one_line_naming_where(tmp_path):
    f = tmp_path / "broken.yaml"
    f.write_text("plant:\n  bow: {amplitude: [1}\n")
    with pytest.raises(ConfigError) as err:
        read_yaml(f)
    message = str(err.value)
    assert "\n" not in message and str(f) in message and "line 2" in message, message


def test_merge_overrides_key_by_key_and_leaves_the_defaults_alone():
    merged = merge(VALID, {"beam": {"nodes": 21}})
    assert merged == {"beam": {"length": 0.4, "nodes": 21}, "gauges": [0.148, 0.252]}
    assert VALID["beam"]["nodes"] == 35


def test_valid_data_comes_back_converted():
    assert validate(VALID, SCHEMA) == {"beam": {"length": 0.4, "nodes": 35}, "gauges": (0.148, 0.252)}


@pytest.mark.parametrize(
    ("data", "key", "expected_words"),
    [
        (merge(VALID, {"beam": {"lenght": 0.4}}), "beam.lenght", "one of the known keys"),
        ({"beam": {"length": 0.4}, "gauges": [0.1, 0.2]}, "beam.nodes", "the key is missing"),
        (merge(VALID, {"beam": {"length": 0.0}}), "beam.length", "> 0 (in m)"),
        (merge(VALID, {"beam": {"length": True}}), "beam.length", "a finite number"),
        (merge(VALID, {"beam": {"nodes": 35.5}}), "beam.nodes", "an integer >= 5"),
        (merge(VALID, {"gauges": [0.1]}), "gauges", "a list of 2 gauge positions"),
        (merge(VALID, {"gauges": [0.1, -0.2]}), "gauges", "each a finite number >= 0"),
        (merge(VALID, {"beam": 0.4}), "beam", "a mapping"),
    ],
)
def test_a_refusal_names_the_dotted_key_the_value_and_what_was_expected(data, key, expected_words):
    with pytest.raises(ConfigError) as err:
        validate(data, SCHEMA, source="scenario.yaml", prefix="plant.")
    message = str(err.value)
    assert err.value.key == f"plant.{key}", message
    assert message.startswith(f"scenario.yaml: plant.{key} = "), message
    assert expected_words in message and "\n" not in message, message


def test_a_renamed_key_is_refused_naming_the_new_one_wherever_it_is_nested():
    renamed = {"pace": "pace_s", "safety.ramp_time": "safety.ramp_time_s"}
    refuse_renamed({"safety": {"ramp_time_s": 0.5}, "pace_s": 1.0}, renamed)   # the new names pass
    for data, key in (({"pace": 1.0}, "controller.pace"),
                      ({"safety": {"ramp_time": 0.5}}, "controller.safety.ramp_time")):
        with pytest.raises(ConfigError) as err:
            refuse_renamed(data, renamed, "lab.yaml", "controller.")
        assert err.value.key == key and f"{key}_s in its place" in str(err.value), str(err.value)
    refuse_renamed({"safety": 0.5}, renamed)   # not a mapping: left to validate, which names it


def test_a_dotted_key_reads_and_changes_a_value_an_element_or_a_whole_list():
    data = {"beam": {"length": 0.4}, "damping": {"ratios": [0.015, 0.0045]}}
    assert dotted_get(data, "beam.length") == 0.4 and dotted_get(data, "damping.ratios[1]") == 0.0045
    dotted_update(data, "beam.length", lambda old: old + 0.1)
    dotted_update(data, "damping.ratios[0]", lambda old: 0.02)
    assert data == {"beam": {"length": 0.5}, "damping": {"ratios": [0.02, 0.0045]}}
    dotted_update(data, "damping.ratios", lambda old: 2 * old)
    assert data["damping"]["ratios"] == [0.04, 0.009], "a whole list: each element changed"


def test_a_refusal_pickles_as_itself():
    """A refusal raised in a worker process reaches the caller as the same refusal (the robust
    check's and the coverage study's pools carry it back)."""
    import pickle

    e = ConfigError("damping.ratios", [0.0193, 0.00528],
                    "ratios that give non-negative Rayleigh coefficients", "rig 3")
    again = pickle.loads(pickle.dumps(e))
    assert type(again) is ConfigError and str(again) == str(e)
    assert (again.key, again.value, again.expected, again.source) == (e.key, e.value, e.expected, e.source)

