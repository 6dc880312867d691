"""Numeric arguments of the Python API (the CLI's argparse types check its own flags): a
float, bool or string where a count belongs is refused by name, not met later as a TypeError
or a silent truncation."""

from __future__ import annotations

import math
import operator
from typing import Any

__all__ = ["check_count", "check_seconds"]


def check_count(name: str, value: Any, least: int, meaning: str = "") -> int:
    """`value` as an int >= `least`: any integer type but bool, else a ValueError naming it
    (`meaning`: what the number counts, added to the message)."""
    try:
        number = None if isinstance(value, bool) else operator.index(value)
    except TypeError:
        number = None
    if number is None or number < least:
        raise ValueError(f"{name}={value!r} is invalid; expected an integer >= {least}"
                         f"{f' ({meaning})' if meaning else ''}")
    return number


def check_seconds(name: str, value: Any) -> float:
    """`value` as finite seconds > 0, else a ValueError naming it."""
    try:
        seconds = float(value) if not isinstance(value, (bool, str)) else math.nan
    except (TypeError, ValueError):
        seconds = math.nan
    if not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"{name}={value!r} is invalid; expected a number of seconds > 0")
    return seconds
