"""The greedy action of a batch of action values, with one documented tie rule."""

from __future__ import annotations

import torch
from torch import Tensor

from torchcontact._checks import check_float


def greedy_action(values: Tensor, *, generator: torch.Generator | None = None) -> Tensor:
    r"""The action of highest value, ``argmax_a values[..., a]``, with a deterministic tie rule.

    Without ``generator`` ties go to the lowest action index. With one, ties are broken
    uniformly at random and reproducibly: one key ``u ~ U[0, 1)`` per entry of ``values`` is
    drawn from ``generator`` (float64, in ``values``' shape, always, so the generator advances
    by the same amount whether or not there is a tie) and the maximizing action of highest key
    wins. Only exactly equal values tie; no noise is added to the values.

    Args:
        values: ``(*B, A)`` action values, finite float32/float64, ``A >= 1``.
        generator: the random source of the tie-breaking keys; None for the lowest index.

    Returns:
        ``(*B,)`` long actions.

    Raises:
        ValueError: ``values`` is not a finite floating tensor with ``A >= 1``, or
            ``generator`` is not a :class:`torch.Generator`.
    """
    values = check_float("values", values, min_ndim=1, what="(*B, A)")
    if values.shape[-1] == 0:
        raise ValueError(f"values must have A >= 1 actions, got shape {tuple(values.shape)}")
    if generator is None:
        return values.argmax(dim=-1)
    if not isinstance(generator, torch.Generator):
        raise ValueError(f"generator must be a torch.Generator, got {type(generator).__name__}")
    keys = torch.rand(values.shape, generator=generator, dtype=torch.float64)
    best = values == values.amax(dim=-1, keepdim=True)
    return torch.where(best, keys, -1.0).argmax(dim=-1)
