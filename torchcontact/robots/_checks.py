"""Input validation shared by the robot kinematics: every failure names the argument at fault."""

from __future__ import annotations

import torch
from torch import Tensor

_FLOAT_DTYPES = (torch.float32, torch.float64)


def check_float_tensor(name: str, value: object) -> Tensor:
    """Check that ``value`` is a finite float32/float64 tensor.

    Args:
        name: The argument's name, used in the error message.
        value: The object to check.

    Returns:
        ``value``, typed as a tensor.

    Raises:
        TypeError: ``value`` is not a ``torch.Tensor``.
        ValueError: ``value`` is not float32/float64, or holds NaN or inf.
    """
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if value.dtype not in _FLOAT_DTYPES:
        raise ValueError(f"{name} must be float32 or float64, got dtype {value.dtype}")
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name} contains NaN or inf")
    return value


def check_like(name: str, value: Tensor, *, reference_name: str, reference: Tensor) -> None:
    """Check that ``value`` has the dtype and device of ``reference`` (nothing is cast silently).

    Args:
        name: The argument's name.
        value: The tensor to check.
        reference_name: The reference argument's name.
        reference: The tensor whose dtype and device ``value`` must share.

    Raises:
        ValueError: The dtypes or devices differ.
    """
    if value.dtype != reference.dtype or value.device != reference.device:
        raise ValueError(
            f"{name} must have the dtype and device of {reference_name} "
            f"({reference.dtype}, {reference.device}), got ({value.dtype}, {value.device})"
        )


def check_last_dims(name: str, value: Tensor, expected: tuple[int, ...], what: str) -> None:
    """Check the trailing dimensions of ``value``.

    Args:
        name: The argument's name.
        value: The tensor to check.
        expected: The required trailing sizes, e.g. ``(3,)`` or ``(7,)``.
        what: A human description of the expected shape, e.g. ``"(*B, 7)"``.

    Raises:
        ValueError: ``value`` has fewer dimensions or different trailing sizes.
    """
    k = len(expected)
    if value.ndim < k or tuple(value.shape[value.ndim - k :]) != expected:
        raise ValueError(f"{name} must have shape {what}, got {tuple(value.shape)}")


def check_unit_rows(name: str, value: Tensor) -> None:
    """Check that every vector along the last dimension of ``value`` has unit length.

    The tolerance is 1e-6 in float64 and 1e-3 in float32 (on the length).

    Args:
        name: The argument's name.
        value: Tensor ``(..., 3)``.

    Raises:
        ValueError: Some vector's length differs from 1 by more than the tolerance.
    """
    tol = 1e-6 if value.dtype == torch.float64 else 1e-3
    error = (torch.linalg.vector_norm(value, dim=-1) - 1.0).abs()
    if error.numel() > 0 and float(error.max()) > tol:
        raise ValueError(
            f"{name} must hold unit vectors along its last dimension "
            f"(largest length error {float(error.max()):.3g} > {tol:g})"
        )


def broadcast_batch(shapes: dict[str, tuple[int, ...]]) -> tuple[int, ...]:
    """Broadcast the batch shapes of several arguments (NumPy rules), naming them on failure.

    Args:
        shapes: Argument name -> its batch shape.

    Returns:
        The broadcast batch shape.

    Raises:
        ValueError: The batch shapes do not broadcast.
    """
    ndim = max((len(shape) for shape in shapes.values()), default=0)
    result = [1] * ndim
    for shape in shapes.values():
        for axis, size in enumerate(shape, start=ndim - len(shape)):
            if size != 1 and result[axis] not in (1, size):
                listing = ", ".join(f"{name} {shape}" for name, shape in shapes.items())
                raise ValueError(f"batch shapes do not broadcast: {listing}")
            if size != 1:
                result[axis] = size
    return tuple(result)
