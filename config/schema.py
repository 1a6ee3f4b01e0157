"""Validation of nested YAML/dict configuration against a declared schema.

Every configuration file of the project (model parameters, plant scenario, controller and
HAL settings) is checked here on load, so that a wrong value is refused with one kind of
message: the dotted key, the value found and what was expected.
"""

from __future__ import annotations

import json
import math
import re
import secrets
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import yaml

Validator = Callable[[Any], Any]


class _Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):  # libyaml's parser where built
    """Safe YAML loader that reads YAML 1.2 floats: ``75.8e9`` and ``1e-3`` are numbers, not
    the strings PyYAML's YAML 1.1 rules would make of them."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                    |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                    |\.[0-9_]+(?:[eE][-+]?[0-9]+)?
                    |[-+]?\.(?:inf|Inf|INF)
                    |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."),
)


class ConfigError(ValueError):
    """A configuration value (or file) was refused.

    Attributes
    ----------
    key : str
        Dotted path of the offending key (``"beam.radius"``), empty for file-level errors.
    value : Any
        The value that was found.
    expected : str
        What would have been accepted.
    """

    def __init__(self, key: str, value: Any, expected: str, source: str = "") -> None:
        self.key = key
        self.value = value
        self.expected = expected
        self.source = source
        where = f"{source}: " if source else ""
        what = f"{key} = {value!r}" if key else repr(value)
        super().__init__(f"{where}{what}: expected {expected}")

    def __reduce__(self):
        # pickled with its own fields: a refusal raised in a worker process (the robust check's,
        # a study's) reaches the caller as itself; the default would call the constructor with
        # the message alone and break the pool that carries it
        return type(self), (self.key, self.value, self.expected, self.source)


class _Invalid(Exception):
    """Raised by a validator with the expectation text; turned into ConfigError by the caller."""

    def __init__(self, expected: str) -> None:
        super().__init__(expected)
        self.expected = expected


def _as_float(value: Any, expected: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _Invalid(expected)
    number = float(value)
    if not math.isfinite(number):
        raise _Invalid(expected)
    return number


def number(
    unit: str = "",
    *,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
    high_open: bool = False,
) -> Validator:
    """A finite real number, optionally bounded; ``low_open`` excludes the bound itself."""
    parts = ["a finite number"]
    if low is not None:
        parts.append(f"{'>' if low_open else '>='} {low:g}")
    if high is not None:
        parts.append(f"{'<' if high_open else '<='} {high:g}")
    expected = " ".join(parts[:1]) + (" " + " and ".join(parts[1:]) if parts[1:] else "")
    if unit:
        expected += f" (in {unit})"

    def check(value: Any) -> float:
        x = _as_float(value, expected)
        if low is not None and (x < low or (low_open and x == low)):
            raise _Invalid(expected)
        if high is not None and (x > high or (high_open and x == high)):
            raise _Invalid(expected)
        return x

    return check


def positive(unit: str = "") -> Validator:
    """A finite number > 0."""
    return number(unit, low=0.0, low_open=True)


def plausible(low: float, high: float, unit: str, zero: bool = False) -> Validator:
    """A finite number from ``low`` to ``high`` in ``unit`` (or 0 with ``zero``): the range a
    physical quantity of this rig can have, so that a value in the wrong unit (mm for m, GPa for
    Pa) is refused naming its key and the unit it must be in."""
    expected = f"a finite number {'0 or ' if zero else ''}from {low:g} to {high:g} {unit} (in {unit})"
    inner = number(low=low, high=high)

    def check(value: Any) -> float:
        x = _as_float(value, expected)
        if zero and x == 0.0:
            return x
        try:
            return inner(x)
        except _Invalid:
            raise _Invalid(expected) from None

    return check


def nonnegative(unit: str = "") -> Validator:
    """A finite number >= 0."""
    return number(unit, low=0.0)


def integer(*, low: int | None = None, high: int | None = None) -> Validator:
    """An integer (not a bool, not a float with a fraction) within bounds."""
    expected = "an integer"
    if low is not None:
        expected += f" >= {low}"
    if high is not None:
        expected += f" and <= {high}" if low is not None else f" <= {high}"

    def check(value: Any) -> int:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _Invalid(expected)
        if isinstance(value, float) and not value.is_integer():
            raise _Invalid(expected)
        n = int(value)
        if (low is not None and n < low) or (high is not None and n > high):
            raise _Invalid(expected)
        return n

    return check


def optional(validator: Validator, meaning: str) -> Validator:
    """``null`` (None, with ``meaning``: what no value stands for) or a value ``validator`` accepts."""

    def check(value: Any) -> Any:
        if value is None:
            return None
        try:
            return validator(value)
        except _Invalid as exc:
            raise _Invalid(f"{exc.expected}, or null ({meaning})") from None

    return check


def number_list(element: Validator, length: int, description: str) -> Validator:
    """A list of exactly ``length`` numbers, each passing ``element``."""
    expected = f"a list of {length} {description}"

    def check(value: Any) -> tuple[float, ...]:
        if not isinstance(value, (list, tuple)) or len(value) != length:
            raise _Invalid(expected)
        try:
            return tuple(element(v) for v in value)
        except _Invalid as exc:
            raise _Invalid(f"{expected}, each {exc.expected}") from None

    return check


def choice(*options: str) -> Validator:
    """One of a fixed set of strings."""
    expected = "one of " + ", ".join(repr(o) for o in options)

    def check(value: Any) -> str:
        if not isinstance(value, str) or value not in options:
            raise _Invalid(expected)
        return value

    return check


def boolean() -> Validator:
    """``true`` or ``false``."""

    def check(value: Any) -> bool:
        if not isinstance(value, bool):
            raise _Invalid("true or false")
        return value

    return check


def path() -> Validator:
    """A file path as a string; the empty string means none."""

    def check(value: Any) -> str:
        if not isinstance(value, str):
            raise _Invalid("a file path (or an empty string for none)")
        return value

    return check


def text() -> Validator:
    """A non-empty string."""

    def check(value: Any) -> str:
        if not isinstance(value, str) or not value:
            raise _Invalid("a non-empty string")
        return value

    return check


Schema = Mapping[str, "Validator | Schema"]


def merge(defaults: Mapping[str, Any], overrides: Mapping[str, Any]) -> dict[str, Any]:
    """Return ``defaults`` with ``overrides`` applied key by key (nested mappings merged)."""
    merged: dict[str, Any] = dict(defaults)
    for key, value in overrides.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), Mapping):
            merged[key] = merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def nested(key: str, value: Any) -> dict[str, Any]:
    """The mapping a dotted key sets: ``nested("beam.radius", 4e-3)`` is ``{"beam": {"radius": 4e-3}}``
    (to ``merge`` over a configuration)."""
    out: Any = value
    for part in reversed(key.split(".")):
        out = {part: out}
    return out


def dotted_get(root: Mapping[str, Any], key: str) -> Any:
    """The value at a dotted key of a nested mapping, ``a.b`` or an element ``a.b[i]``."""
    base, _, index = key.partition("[")
    node: Any = root
    for part in base.split("."):
        node = node[part]
    return node[int(index[:-1])] if index else node


def dotted_update(root: dict[str, Any], key: str, change: Callable[[Any], Any]) -> None:
    """Replace the value at a dotted key (as ``dotted_get``) by ``change(old)``; a whole list
    element by element."""
    base, _, index = key.partition("[")
    *parents, leaf = base.split(".")
    node: Any = root
    for part in parents:
        node = node[part]
    if index:
        i = int(index[:-1])
        node[leaf][i] = change(node[leaf][i])
    elif isinstance(node[leaf], list):
        node[leaf] = [change(x) for x in node[leaf]]
    else:
        node[leaf] = change(node[leaf])


def validate(data: Any, schema: Schema, source: str = "", prefix: str = "") -> dict[str, Any]:
    """Check ``data`` against ``schema`` and return the converted values.

    Unknown keys, missing keys, wrong types and out-of-range values raise ConfigError naming
    the dotted key. ``data`` must contain every key of the schema (merge with defaults first).
    """
    if not isinstance(data, Mapping):
        raise ConfigError(prefix.rstrip("."), data, "a mapping of keys to values", source)
    unknown = sorted(set(data) - set(schema))
    if unknown:
        key = prefix + str(unknown[0])
        raise ConfigError(key, data[unknown[0]], f"one of the known keys {sorted(schema)}", source)
    out: dict[str, Any] = {}
    for key, rule in schema.items():
        dotted = prefix + key
        if key not in data:
            raise ConfigError(dotted, None, "a value (the key is missing)", source)
        if isinstance(rule, Mapping):
            out[key] = validate(data[key], rule, source, dotted + ".")
            continue
        try:
            out[key] = rule(data[key])
        except _Invalid as exc:
            raise ConfigError(dotted, data[key], exc.expected, source) from None
    return out


def refuse_renamed(data: Any, renamed: Mapping[str, str], source: str = "", prefix: str = "") -> None:
    """Refuse a key that was renamed, in one line naming the key to use in its place.

    ``renamed`` maps old dotted keys to their new names (``{"safety.ramp_time":
    "safety.ramp_time_s"}``); ``prefix`` names the section in the message, as for ``validate``.
    Call it on the user's data before merging it with the defaults.
    """
    for old, new in renamed.items():
        *parents, leaf = old.split(".")
        node = data
        for part in parents:
            node = node.get(part) if isinstance(node, Mapping) else None
        if isinstance(node, Mapping) and leaf in node:
            raise ConfigError(prefix + old, node[leaf],
                              f"{prefix}{new} in its place (the key was renamed to carry its unit)", source)


# a mapping key at the start of a line whose value is a flow sequence: ``key: [...]``
_FLOW_VALUE = re.compile(r"^ *[A-Za-z_][A-Za-z0-9_.]*: (\[)", re.M)
# characters that end the scan early: a sequence holding them is left to YAML (strings, comments,
# anchors, flow mappings: JSON refuses them or reads them otherwise)
_NOT_PLAIN = frozenset("'\"#&*!{}|>%@`")
# flow sequences shorter than this are left to the YAML parser (nothing to gain)
_FLOW_MIN_CHARS = 512


def _reject_constant(name: str) -> Any:
    raise ValueError(name)       # NaN, Infinity: JSON's, not YAML's spelling (YAML reads a string)


def _plain_flows(text: str) -> tuple[str, dict[str, Any]]:
    """Cut the long flow sequences of plain numbers (``key: [[1.0, -2e-3], ...]``, how a gain
    table stores its matrices) out of ``text``, each read by the JSON parser where JSON and
    YAML read it alike, and leave a placeholder scalar in its place. JSON reads 146 000 numbers
    in a tenth of the time PyYAML takes (which builds a Python node for each). A sequence with
    anything JSON and YAML might read differently (quotes, anchors, comments, flow mappings,
    .inf, NaN, yes/no, 017, +1, 1_000) is left to YAML: JSON refuses those spellings."""
    nonce = secrets.token_hex(8)
    pieces: list[str] = []
    values: dict[str, Any] = {}
    pos = 0
    for m in _FLOW_VALUE.finditer(text):
        start = m.start(1)
        if start < pos:
            continue
        depth, j, n = 0, start, len(text)
        while j < n:
            ch = text[j]
            if ch == "[":
                depth += 1
            elif ch == "]":
                depth -= 1
                if depth == 0:
                    break
            elif ch in _NOT_PLAIN:
                break
            j += 1
        if depth != 0 or j - start < _FLOW_MIN_CHARS:
            continue
        line_end = text.find("\n", j)
        if text[j + 1:len(text) if line_end < 0 else line_end].strip():
            continue                  # something after the sequence on its line: YAML's to read
        try:
            value = json.loads(text[start:j + 1], parse_constant=_reject_constant)
        except ValueError:
            continue
        token = f"__beamctl_flow_{nonce}_{len(values)}__"
        values[token] = value
        pieces += [text[pos:start], token]
        pos = j + 1
    pieces.append(text[pos:])
    return "".join(pieces), values


def _put_back(node: Any, values: dict[str, Any], used: list[str], prefix: str) -> Any:
    """``node`` with each placeholder scalar replaced by its value (recorded in ``used``); a
    placeholder found anywhere else (inside a longer string, as a key) is recorded as None."""
    if isinstance(node, dict):
        if any(isinstance(k, str) and prefix in k for k in node):
            used.append(None)
        return {k: _put_back(v, values, used, prefix) for k, v in node.items()}
    if isinstance(node, list):
        return [_put_back(v, values, used, prefix) for v in node]
    if isinstance(node, str) and prefix in node:
        used.append(node if node in values else None)
        return values.get(node, node)
    return node


def parse_yaml(text_: str) -> Any:
    """``text_`` read as YAML (safe, YAML 1.2 floats), its long flow sequences of numbers by
    the JSON parser (``_plain_flows``): the same data as PyYAML gives, in a fraction of the
    time for a gain table. Where the cut text does not read back to exactly the placeholders'
    places (a placeholder inside a block scalar, say), the whole text is read by YAML."""
    cut, values = _plain_flows(text_) if len(text_) > _FLOW_MIN_CHARS else (text_, {})
    if values:
        try:
            data = yaml.load(cut, Loader=_Loader)  # noqa: S506 (safe loader subclass)
        except yaml.YAMLError:
            data = None               # the error is reported from the whole text, lines as written
        else:
            used: list[str | None] = []
            data = _put_back(data, values, used, next(iter(values))[:32])
            if None not in used and sorted(used) == sorted(values):
                return data
    return yaml.load(text_, Loader=_Loader)  # noqa: S506 (safe loader subclass)


def read_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping from ``path``; a missing, unreadable or non-mapping file is refused."""
    p = Path(path)
    try:
        text_ = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError("", str(p), f"a readable YAML file ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise ConfigError("", str(p), f"a UTF-8 text file (byte {exc.start} is not UTF-8)") from None
    try:
        data = parse_yaml(text_)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        what = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError("", str(p), f"valid YAML ({where}{what})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError("", str(p), f"a YAML mapping at the top level, found {type(data).__name__}")
    return data
