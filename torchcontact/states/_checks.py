"""Input validation for the contact-state entry points (every error names the argument)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

_FLOAT_DTYPES = (torch.float32, torch.float64)


def check_float(name: str, value: object, *, trailing: tuple[int, ...], what: str) -> Tensor:
    """Check that ``value`` is a finite float32/float64 tensor with trailing shape ``trailing``.

    Args:
        name: the argument's name, used in the error message.
        value: the object to check.
        trailing: required trailing sizes; ``-1`` accepts any size.
        what: human description of the expected shape, e.g. ``"(*B, K, d)"``.

    Returns:
        ``value``, typed as a tensor.

    Raises:
        ValueError: ``value`` is not a float tensor, has the wrong shape, or holds NaN or inf.
    """
    if not isinstance(value, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if value.dtype not in _FLOAT_DTYPES:
        raise ValueError(f"{name} must be float32 or float64, got dtype {value.dtype}")
    check_trailing(name, value, trailing=trailing, what=what)
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name} contains NaN or inf")
    return value


def check_trailing(name: str, value: Tensor, *, trailing: tuple[int, ...], what: str) -> None:
    """Check the trailing sizes of ``value`` (``-1`` in ``trailing`` accepts any size).

    Raises:
        ValueError: ``value`` has too few dimensions or a trailing size differs.
    """
    k = len(trailing)
    tail = tuple(value.shape[value.ndim - k :]) if value.ndim >= k else None
    if tail is None or any(t not in (-1, s) for t, s in zip(trailing, tail, strict=True)):
        raise ValueError(f"{name} must have shape {what}, got {tuple(value.shape)}")


def check_dtype(name: str, value: object, dtype: torch.dtype, what: str) -> Tensor:
    """Check that ``value`` is a tensor of exactly ``dtype`` (``what`` describes its shape).

    Raises:
        ValueError: ``value`` is not a tensor of that dtype.
    """
    if not isinstance(value, Tensor) or value.dtype != dtype:
        got = value.dtype if isinstance(value, Tensor) else type(value).__name__
        raise ValueError(f"{name} must be a {dtype} tensor {what}, got {got}")
    return value


def check_positive(name: str, value: object) -> float:
    """Check that ``value`` is a finite real number ``> 0`` and return it as a float.

    Raises:
        ValueError: ``value`` is not a finite positive number.
    """
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or not math.isfinite(value)
        or value <= 0
    ):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return float(value)


def check_dim(name: str, value: object) -> int:
    """Check that ``value`` is the spatial dimension 2 (planar) or 3 (spatial).

    Raises:
        ValueError: ``value`` is neither 2 nor 3.
    """
    if isinstance(value, bool) or value not in (2, 3):
        raise ValueError(f"{name} must be 2 (planar) or 3 (spatial), got {value!r}")
    assert isinstance(value, int)
    return value
