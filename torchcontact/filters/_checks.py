"""Input validation shared by the filter entry points (every error is a ``ValueError`` naming
the argument at fault)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


def check_tensor(
    x: object,
    name: str,
    *,
    event_shape: Sequence[int],
    like: Tensor,
    allow_nan: bool = False,
    allow_neginf: bool = False,
) -> Tensor:
    """Check that ``x`` is a finite ``(*B', *event_shape)`` tensor with ``like``'s dtype/device.

    Args:
        x: the value to check.
        name: argument name used in error messages.
        event_shape: required trailing shape.
        like: reference tensor giving dtype and device.
        allow_nan: let NaN through (the caller gives it a meaning).
        allow_neginf: let ``-inf`` through (a log-probability of zero); ``+inf`` is an error.

    Returns:
        ``x`` as a tensor.
    """
    if not isinstance(x, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.dtype != like.dtype or x.device != like.device:
        raise ValueError(
            f"{name}: expected dtype {like.dtype} on {like.device}, got {x.dtype} on {x.device}"
        )
    event = tuple(event_shape)
    if x.ndim < len(event) or tuple(x.shape[x.ndim - len(event) :]) != event:
        shape = ", ".join(["*B", *map(str, event)])
        raise ValueError(f"{name}: expected shape ({shape}), got {tuple(x.shape)}")
    if allow_nan:
        bad = torch.isposinf(x) if allow_neginf else torch.isinf(x)
    else:
        bad = torch.isposinf(x) | torch.isnan(x) if allow_neginf else ~torch.isfinite(x)
    if bool(bad.any()):
        allowed = " or ".join(["NaN"] * (not allow_nan) + ["-inf"] * (not allow_neginf) + ["+inf"])
        raise ValueError(f"{name}: contains {allowed}")
    return x


def check_mask(mask: object, name: str, *, size: int) -> Tensor:
    """Check that ``mask`` is a ``(*B', size)`` bool tensor."""
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        raise ValueError(f"{name}: expected a bool tensor, got {getattr(mask, 'dtype', mask)!r}")
    if mask.ndim < 1 or mask.shape[-1] != size:
        raise ValueError(f"{name}: expected shape (*B, {size}), got {tuple(mask.shape)}")
    return mask


def broadcast_batch(shapes: Sequence[tuple[str, Sequence[int]]]) -> torch.Size:
    """Broadcast named batch shapes, raising ``ValueError`` naming the first that does not fit.

    (Plain Python: ``torch.broadcast_shapes`` costs tens of microseconds per call.)
    """
    batch: list[int] = []
    for name, shape in shapes:
        dims = list(shape)
        if len(dims) > len(batch):
            batch = [1] * (len(dims) - len(batch)) + batch
        offset = len(batch) - len(dims)
        for i, size in enumerate(dims):
            current = batch[offset + i]
            if size != current and 1 not in (size, current):
                raise ValueError(
                    f"{name}: batch shape {tuple(dims)} does not broadcast with {tuple(batch)}"
                )
            batch[offset + i] = current if size == 1 else size
    return torch.Size(batch)


def describe(value: object) -> str:
    """A short description of a value for error messages: dtype and shape of a tensor."""
    if isinstance(value, Tensor):
        return f"a {value.dtype} tensor of shape {tuple(value.shape)}"
    return type(value).__name__
