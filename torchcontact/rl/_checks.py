"""Input validation for the reinforcement-learning entry points (every error is a
``ValueError`` naming the argument at fault)."""

from __future__ import annotations

import math
import numbers

import torch
from torch import Tensor

FLOAT_DTYPES = (torch.float16, torch.bfloat16, torch.float32, torch.float64)


def check_int(name: str, value: object, *, low: int, high: int | None = None) -> int:
    """Check that ``value`` is an integer (not a bool) in ``[low, high)`` and return it.

    ``numpy`` integers are accepted and converted to ``int``; ``high=None`` means no upper
    bound.

    Raises:
        ValueError: ``value`` is not an integer or lies outside the range.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an int, got {value!r}")
    result = int(value)
    if result < low or (high is not None and result >= high):
        bounds = f"[{low}, {high})" if high is not None else f">= {low}"
        raise ValueError(f"{name} must lie in {bounds}, got {result}")
    return result


def check_real(
    name: str,
    value: object,
    *,
    low: float = -math.inf,
    high: float = math.inf,
    low_open: bool = False,
    high_open: bool = False,
) -> float:
    """Check that ``value`` is a finite real number in the given interval and return it.

    Args:
        name: the argument's name, used in the error message.
        value: the object to check (a Python or numpy real number, not a bool).
        low: lower bound.
        high: upper bound.
        low_open: exclude ``low`` itself.
        high_open: exclude ``high`` itself.

    Raises:
        ValueError: ``value`` is not a finite real number in the interval.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a real number, got {value!r}")
    result = float(value)
    too_low = result <= low if low_open else result < low
    too_high = result >= high if high_open else result > high
    if not math.isfinite(result) or too_low or too_high:
        interval = f"{'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
        raise ValueError(f"{name} must be a finite number in {interval}, got {value!r}")
    return result


def check_float_tensor(name: str, value: object, *, min_ndim: int, what: str) -> Tensor:
    """Check that ``value`` is a finite floating tensor with at least ``min_ndim`` dimensions.

    Args:
        name: the argument's name, used in the error message.
        value: the object to check.
        min_ndim: the least number of dimensions.
        what: human description of the expected shape, e.g. ``"(*B, K, A)"``.

    Raises:
        ValueError: ``value`` is not a floating tensor, has too few dimensions, or holds NaN or
            inf.
    """
    if not isinstance(value, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if value.dtype not in FLOAT_DTYPES:
        raise ValueError(f"{name} must be a floating tensor, got dtype {value.dtype}")
    if value.ndim < min_ndim:
        raise ValueError(f"{name} must have shape {what}, got {tuple(value.shape)}")
    if not all_finite(value):
        raise ValueError(f"{name} contains NaN or inf")
    return value


def all_finite(value: Tensor) -> bool:
    """Whether every entry of a floating tensor is finite.

    A finite sum proves it (NaN and ±inf propagate through a sum) and costs far less than an
    elementwise test on large tensors; only a non-finite sum (a non-finite entry, or an
    overflow) falls back to the elementwise test.
    """
    if bool(torch.isfinite(value.sum())):
        return True
    return bool(torch.isfinite(value).all())
