"""QMDP: act on a belief over discrete states with the Q values of the fully observed MDP."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcontact._checks import all_finite, check_float
from torchcontact.rl._greedy import greedy_action


def qmdp_values(q_values: Tensor, probabilities: Tensor) -> Tensor:
    r"""Belief-weighted action values ``Q_b(a) = Σ_i p_i Q(m_i, a)``.

    QMDP assumes the state becomes fully observed after one step, so the value of an action
    under a belief is the expectation of the MDP's Q values; it never pays to gather
    information under this approximation.

    Args:
        q_values: ``(*Bq, K, A)`` Q values of the ``K`` discrete states (a shared ``(K, A)``
            table is the usual case).
        probabilities: ``(*Bp, K)`` belief, each row nonnegative and summing to 1 (within
            ``sqrt(eps)`` of its dtype). ``*Bq`` and ``*Bp`` broadcast to ``*B``.

    Returns:
        ``(*B, A)`` values, in the promoted dtype of the inputs.

    Raises:
        ValueError: an input is not a finite floating tensor, ``K`` differs, the batch shapes
            do not broadcast, a row of ``probabilities`` is negative or does not sum to 1, or
            the weighted sum overflows the dtype.

    References:
        M. L. Littman, A. R. Cassandra and L. P. Kaelbling, "Learning policies for partially
        observable environments: scaling up", ICML 1995 (the QMDP approximation).
    """
    q_values = check_float("q_values", q_values, min_ndim=2, what="(*B, K, A)")
    probabilities = check_float("probabilities", probabilities, min_ndim=1, what="(*B, K)")
    K, A = q_values.shape[-2:]
    if K == 0 or A == 0:
        raise ValueError(f"q_values must have K >= 1 and A >= 1, got {tuple(q_values.shape)}")
    if probabilities.shape[-1] != K:
        raise ValueError(
            f"probabilities must have shape (*B, {K}) to match q_values "
            f"{tuple(q_values.shape)}, got {tuple(probabilities.shape)}"
        )
    try:
        torch.broadcast_shapes(q_values.shape[:-2], probabilities.shape[:-1])
    except RuntimeError:
        raise ValueError(
            f"the batch shapes of q_values {tuple(q_values.shape)} and probabilities "
            f"{tuple(probabilities.shape)} do not broadcast"
        ) from None
    if bool((probabilities < 0).any()):
        raise ValueError("probabilities must be >= 0")
    tolerance = math.sqrt(torch.finfo(probabilities.dtype).eps)
    error = (probabilities.sum(-1) - 1).abs()
    if error.numel() and float(error.max()) > tolerance:
        raise ValueError(f"probabilities must sum to 1 over the last dim (within {tolerance:.1e})")
    dtype = torch.promote_types(q_values.dtype, probabilities.dtype)
    weights = probabilities.to(dtype).unsqueeze(-2)
    values = torch.matmul(weights, q_values.to(dtype)).squeeze(-2)
    if values.numel() and not all_finite(values):
        raise ValueError(f"q_values are too large: the weighted sum overflows {dtype}")
    return values


def qmdp_action(
    q_values: Tensor, probabilities: Tensor, *, generator: torch.Generator | None = None
) -> Tensor:
    r"""The QMDP action ``a* = argmax_a Σ_i p_i Q(m_i, a)``.

    :func:`greedy_action` of :func:`qmdp_values`: ties go to the lowest index, or, with
    ``generator``, to a uniformly random one of the tied actions (reproducible keys drawn from
    ``generator``).

    Args:
        q_values: ``(*Bq, K, A)`` Q values of the ``K`` discrete states.
        probabilities: ``(*Bp, K)`` belief over the states; ``*Bq`` and ``*Bp`` broadcast to
            ``*B``.
        generator: the random source of the tie-breaking keys; None for the lowest index.

    Returns:
        ``(*B,)`` long actions.

    Raises:
        ValueError: see :func:`qmdp_values` and :func:`greedy_action`.
    """
    return greedy_action(qmdp_values(q_values, probabilities), generator=generator)
