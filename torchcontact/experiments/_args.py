"""Validation of the experiment scripts' arguments, before any work.

Each check raises a ``ValueError`` that names the argument, the allowed values and the value
given, e.g. ``"particles: expected an int >= 24 (the model's number of modes K), got 16"``.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable


def check_int(name: str, value: object, *, low: int, why: str = "") -> int:
    """Check that ``value`` is an int (not a bool) ``>= low`` and return it.

    Args:
        name: the argument's name.
        value: the value given.
        low: the least allowed value.
        why: where the bound comes from, shown in parentheses (empty: nothing).

    Raises:
        ValueError: ``value`` is not an int ``>= low``.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
        reason = f" ({why})" if why else ""
        raise ValueError(f"{name}: expected an int >= {low}{reason}, got {value!r}")
    return int(value)


def check_float(
    name: str,
    value: object,
    *,
    low: float = -math.inf,
    high: float = math.inf,
    low_open: bool = False,
    high_open: bool = False,
) -> float:
    """Check that ``value`` is a finite real number in the interval and return it.

    Args:
        name: the argument's name.
        value: the value given.
        low: lower bound.
        high: upper bound.
        low_open: exclude ``low``.
        high_open: exclude ``high``.

    Raises:
        ValueError: ``value`` is not a finite number in the interval.
    """
    if not isinstance(value, bool) and isinstance(value, numbers.Real):
        x = float(value)
        above = x > low if low_open else x >= low
        below = x < high if high_open else x <= high
        if math.isfinite(x) and above and below:
            return x
    interval = f"{'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
    raise ValueError(f"{name}: expected a finite number in {interval}, got {value!r}")


def check_choice(name: str, value: object, choices: Iterable[str]) -> str:
    """Check that ``value`` is one of ``choices`` and return it.

    Raises:
        ValueError: ``value`` is not one of ``choices``.
    """
    allowed = tuple(choices)
    if value not in allowed:
        raise ValueError(f"{name}: expected one of {allowed}, got {value!r}")
    return str(value)


def check_name(name: str, value: object) -> str:
    """Check that ``value`` is a non-empty folder name (no path separator) and return it.

    Raises:
        ValueError: ``value`` is empty or holds ``/`` or ``\\``.
    """
    if not isinstance(value, str) or not value or "/" in value or "\\" in value:
        raise ValueError(f"{name}: expected a non-empty name without '/' or '\\', got {value!r}")
    return value
