"""argparse types for numeric flags: a bad value is refused by argparse (exit 2) with what
was expected, instead of a traceback further on."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def number(*, low: float, inclusive: bool = True, integer: bool = False) -> Callable[[str], float]:
    """A finite number above ``low`` (or at it, when ``inclusive``)."""
    expected = f"{'an integer' if integer else 'a finite number'} {'>=' if inclusive else '>'} {low:g}"

    def parse(text: str):
        try:
            value = int(text) if integer else float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and (value >= low if inclusive else value > low)):
            raise argparse.ArgumentTypeError(f"{text!r}: expected {expected}")
        return value

    return parse


def integer(*, low: int, high: int) -> Callable[[str], int]:
    """An integer from ``low`` to ``high``."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{text!r}: expected an integer from {low} to {high}")
        return value

    return parse


def number_list(*, low: float) -> Callable[[str], list[float]]:
    """Comma-separated finite numbers, each >= ``low``, at least one."""
    one = number(low=low)

    def parse(text: str) -> list[float]:
        parts = [p for p in text.split(",") if p.strip()]
        if not parts:
            raise argparse.ArgumentTypeError(f"{text!r}: expected numbers >= {low:g}, separated by commas")
        return [one(p.strip()) for p in parts]

    return parse


seconds = number(low=0.0)
positive = number(low=0.0, inclusive=False)
steps = number(low=1000, integer=True)


def band(text: str) -> tuple[float, float]:
    """``LO:HI`` in Hz, 0 <= LO < HI, both finite."""
    try:
        low, high = (float(x) for x in text.split(":"))
    except ValueError:
        low = high = math.nan
    if not (math.isfinite(low) and math.isfinite(high) and 0 <= low < high):
        raise argparse.ArgumentTypeError(f"{text!r}: expected LO:HI in Hz, 0 <= LO < HI, e.g. 10:1200")
    return low, high


def renamed(parser: argparse.ArgumentParser, old: str, new: str) -> None:
    """``old`` was this flag's name: refused in one line naming ``new`` (hidden from --help)."""

    class _Renamed(argparse.Action):
        def __call__(self, p, namespace, values, option_string=None):
            p.error(f"{old} is now {new} (one name for the control socket on every command)")

    parser.add_argument(old, action=_Renamed, nargs="?", help=argparse.SUPPRESS)
