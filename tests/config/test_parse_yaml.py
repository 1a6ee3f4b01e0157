"""config.schema.parse_yaml: long flow sequences of numbers read by the JSON parser give exactly
the data PyYAML gives, and anything JSON and YAML might read differently is left to YAML."""

import math

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from beamctl.config.schema import ConfigError, _Loader, parse_yaml, read_yaml
from beamctl.gains.defaults import default_table_path, paper_table_path


def _yaml(text: str):
    return yaml.load(text, Loader=_Loader)  # noqa: S506 (safe loader subclass)


def _same(a, b) -> bool:
    """Equal, NaN equal to NaN, and of the same types (1 and 1.0 are not the same here)."""
    if isinstance(a, dict):
        return isinstance(b, dict) and list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list):
        return (isinstance(b, list) and len(a) == len(b)
                and all(_same(x, y) for x, y in zip(a, b, strict=True)))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a):
        return math.isnan(b)
    return type(a) is type(b) and a == b


@pytest.mark.parametrize("path", [default_table_path(), paper_table_path()], ids=["default", "paper"])
def test_the_shipped_tables_read_the_same_as_by_yaml(path):
    text = path.read_text()
    assert _same(parse_yaml(text), _yaml(text)), f"{path.name}: parse_yaml and PyYAML read different data"


def _long(row: str, rows: int = 40) -> str:
    return "[" + ", ".join([row] * rows) + "]"


# spellings that JSON and YAML read differently, or that JSON refuses: each one inside a long
# flow sequence must leave that sequence to YAML
TRICKY = ["NaN", "Infinity", "-Infinity", ".inf", "-.inf", ".nan", "yes", "no", "on", "off", "~",
          "017", "+1", "1_000", "0x1F", "'1.0'", '"2.0"', "1.0 # note", "&a 1.0", "*a", "{a: 1}",
          "2001-12-14", "1e5", "1E-5", "-0", "1.", ".5", "null", "true", "False", "12:30"]


@pytest.mark.parametrize("token", TRICKY)
def test_a_sequence_with_a_spelling_json_reads_otherwise_is_read_as_yaml_reads_it(token):
    row = f"[1.0, -2.5e-3, {token}, 4]"
    if token == "*a":
        row = "[1.0, -2.5e-3, &a 3.0, *a]"
    text = f"first: 1\nmatrix: {_long(row)}\nlast: [1, 2]\n"
    try:
        expected = _yaml(text)
    except yaml.YAMLError:
        with pytest.raises(yaml.YAMLError):
            parse_yaml(text)
        return
    assert _same(parse_yaml(text), expected), f"{token!r} in a long flow sequence read otherwise than by YAML"


def test_a_flow_sequence_inside_a_block_scalar_stays_text():
    body = "  key: " + _long("[1.0, 2.0, 3.0]")
    text = f"note: |\n{body}\n  more text\nvalue: {_long('[0.5, 1.5]')}\n"
    assert _same(parse_yaml(text), _yaml(text))
    assert parse_yaml(text)["note"].startswith("key: [[1.0"), "the block scalar's text was changed"


def test_a_flow_sequence_inside_a_quoted_string_stays_text():
    text = f'note: "start\n  key: {_long("[1.0, 2.0]")}\n  end"\nother: 1\n'
    assert _same(parse_yaml(text), _yaml(text))


def test_a_yaml_error_after_a_long_sequence_names_the_line_as_written(tmp_path):
    matrix = yaml.dump([[float(i) + 0.5 for i in range(8)] for _ in range(60)], default_flow_style=True,
                       width=80)
    assert matrix.count("\n") > 5, "the sequence spans several lines"
    f = tmp_path / "bad.yaml"
    f.write_text(f"m: {matrix}x: [1, 2\ny: 3\n")
    lines = 1 + matrix.count("\n")
    with pytest.raises(ConfigError) as err:
        read_yaml(f)
    assert f"line {lines + 1}," in str(err.value) or f"line {lines + 2}," in str(err.value), (
        f"the error names a line other than the unclosed sequence's ({lines + 1}) or the next: {err.value}")


numbers = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64),
                    st.integers(min_value=-10**20, max_value=10**20), st.booleans(), st.none())
nested = st.recursive(st.lists(numbers, min_size=1, max_size=12),
                      lambda inner: st.lists(inner, min_size=1, max_size=6), max_leaves=300)
documents = st.dictionaries(st.from_regex(r"[a-z_][a-z0-9_]{0,8}", fullmatch=True),
                            st.one_of(nested, numbers, st.text(max_size=20)), min_size=1, max_size=6)


@settings(max_examples=100, deadline=None)
@given(documents, st.sampled_from([True, None, False]), st.integers(min_value=40, max_value=200))
def test_any_document_reads_the_same_as_by_yaml(doc, flow, width):
    """Random documents of nested numbers (NaN, infinities, huge integers, booleans, nulls) and
    strings, written in flow, mixed or block style at any line width (a hundred of them, as many
    as hypothesis draws by default: the spellings that JSON and YAML read differently are each
    tested on their own above)."""
    text = yaml.safe_dump(doc, default_flow_style=flow, width=width, sort_keys=False)
    assert _same(parse_yaml(text), _yaml(text)), text[:400]
