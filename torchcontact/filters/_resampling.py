"""Batched particle resampling: multinomial, stratified, systematic, residual and optimal."""

from __future__ import annotations

from typing import Any, Literal, get_args

import torch
from torch import Tensor

from torchcontact._checks import FLOAT_DTYPES, describe

ResamplingMethod = Literal["multinomial", "systematic", "stratified", "residual"]
RESAMPLING_METHODS: tuple[str, ...] = get_args(ResamplingMethod)


_BELOW_ONE = 1.0 - 2.0**-53  # the largest float64 below 1


def normalized_cdf(weights: Tensor) -> Tensor:
    """float64 CDF ``(*B, N)`` of non-negative ``weights`` ``(*B, N)`` (each row with a positive
    entry), divided by its own last entry so that it ends at exactly 1."""
    cdf = weights.to(torch.float64).cumsum(-1)
    return cdf / cdf[..., -1:]


def search_cdf(cdf: Tensor, u: Tensor) -> Tensor:
    """Indices ``i`` with ``cdf[i-1] <= u < cdf[i]``: ``cdf (*B, N)``, ``u (*B, M)`` float64 in
    ``[0, 1)`` → ``(*B, M)`` long. An entry of weight zero is never selected."""
    return torch.searchsorted(cdf, u.clamp(0.0, _BELOW_ONE).contiguous(), right=True)


def inverse_cdf(weights: Tensor, u: Tensor) -> Tensor:
    """Inverse-CDF sampling: :func:`search_cdf` on :func:`normalized_cdf` of ``weights``."""
    return search_cdf(normalized_cdf(weights), u)


def _uniforms(
    method: str,
    batch: torch.Size,
    num: int,
    generator: torch.Generator | None,
    device: torch.device,
) -> Tensor:
    """``(*B, num)`` float64 points in ``[0, 1)`` for the given scheme (not residual)."""
    kw: dict[str, Any] = {"dtype": torch.float64, "device": device, "generator": generator}
    if method == "multinomial":
        return torch.rand((*batch, num), **kw)
    strata = torch.arange(num, dtype=torch.float64, device=device)
    if method == "stratified":
        return (strata + torch.rand((*batch, num), **kw)) / num
    return (strata + torch.rand((*batch, 1), **kw)) / num  # systematic


def resample_indices(
    log_weights: Tensor, num_samples: int, method: str, generator: torch.Generator | None
) -> Tensor:
    """Unvalidated core of :func:`resample` (every row must have a finite log-weight)."""
    lw = log_weights.detach().to(torch.float64)
    weights = torch.exp(lw - lw.amax(-1, keepdim=True))
    batch, device = lw.shape[:-1], lw.device
    if method != "residual":
        return inverse_cdf(weights, _uniforms(method, batch, num_samples, generator, device))
    scaled = weights / weights.sum(-1, keepdim=True) * num_samples
    copies = torch.floor(scaled)
    remainder = scaled - copies
    num_copies = copies.sum(-1, keepdim=True)
    slots = torch.arange(num_samples, dtype=torch.float64, device=device).expand(*batch, -1)
    deterministic = torch.searchsorted(copies.cumsum(-1), slots.contiguous(), right=True)
    remainder = torch.where(remainder.sum(-1, keepdim=True) > 0, remainder, weights)
    random = inverse_cdf(remainder, _uniforms("multinomial", batch, num_samples, generator, device))
    n = lw.shape[-1]
    return torch.where(slots < num_copies, deterministic.clamp(max=n - 1), random)


def _check_log_weights(log_weights: object, name: str, *, allow_dead: bool = False) -> Tensor:
    """Check ``(*B, N)`` float32/float64 log-weights without NaN or ``+inf``; unless
    ``allow_dead``, every row needs a finite entry."""
    if not isinstance(log_weights, Tensor) or log_weights.dtype not in FLOAT_DTYPES:
        raise ValueError(
            f"{name}: expected a float32 or float64 tensor, got {describe(log_weights)}"
        )
    if log_weights.ndim < 1 or log_weights.shape[-1] < 1:
        raise ValueError(f"{name}: expected shape (*B, N) with N >= 1, got {log_weights.shape}")
    if bool(torch.isnan(log_weights).any() | torch.isposinf(log_weights).any()):
        raise ValueError(f"{name}: contains NaN or +inf")
    if not allow_dead and bool(torch.isneginf(log_weights).all(-1).any()):
        raise ValueError(f"{name}: a row has every weight zero (all -inf)")
    return log_weights


def resample(
    log_weights: Tensor,
    *,
    method: ResamplingMethod = "systematic",
    num_samples: int | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    r"""Draw ancestor indices with probabilities proportional to ``exp(log_weights)``.

    Every scheme is unbiased (the expected number of copies of particle ``i`` is
    :math:`M w_i`) and runs batched, without loops over batch or particles:

    * ``"multinomial"``: :math:`M` i.i.d. draws from the weights;
    * ``"stratified"``: one uniform draw in each stratum :math:`[k/M, (k+1)/M)`;
    * ``"systematic"``: one uniform offset shared by all strata (lowest variance, but
      correlated across neighbours: do not use it on arrays laid out with a period);
    * ``"residual"``: :math:`\lfloor M w_i \rfloor` deterministic copies, the rest multinomial.

    Args:
        log_weights: ``(*B, N)`` unnormalized log-weights (``-inf`` = weight zero; every row
            needs a finite entry).
        method: the scheme.
        num_samples: ``M``; ``N`` if None.
        generator: random source (reproducible runs); torch's default if None.

    Returns:
        ``(*B, M)`` long indices into the last dim, grouped in ascending order of ancestor
        (multinomial and residual draws excepted). Particles of weight zero are never drawn.

    References:
        R. Douc, O. Cappé and E. Moulines, "Comparison of resampling schemes for particle
        filtering", ISPA 2005.
    """
    lw = _check_log_weights(log_weights, "log_weights")
    if method not in RESAMPLING_METHODS:
        raise ValueError(f"method: expected one of {RESAMPLING_METHODS}, got {method!r}")
    num = int(lw.shape[-1]) if num_samples is None else num_samples
    if not isinstance(num, int) or num < 1:
        raise ValueError(f"num_samples: expected a positive int, got {num_samples!r}")
    return resample_indices(lw, num, method, generator)


def effective_sample_size(log_weights: Tensor) -> Tensor:
    r"""Kish's effective sample size :math:`(\sum_i w_i)^2 / \sum_i w_i^2`, ``(*B, N)`` → ``(*B,)``.

    Computed in log space from unnormalized log-weights; 0 for a row with every weight zero.

    Raises:
        ValueError: ``log_weights`` is not a float32/float64 ``(*B, N)`` tensor, or holds NaN
            or ``+inf``.
    """
    lw = _check_log_weights(log_weights, "log_weights", allow_dead=True)
    dead = torch.isneginf(lw).all(-1, keepdim=True)
    safe = torch.where(dead, 0.0, lw)
    ess = torch.exp(2.0 * torch.logsumexp(safe, -1) - torch.logsumexp(2.0 * safe, -1))
    return torch.where(dead.squeeze(-1), 0.0, ess)


def optimal_resample_core(
    log_weights: Tensor, num_samples: int, generator: torch.Generator | None
) -> tuple[Tensor, Tensor]:
    """Unvalidated core of :func:`optimal_resample` (rows must have a finite entry)."""
    n_out = num_samples
    lw = log_weights - torch.logsumexp(log_weights, -1, keepdim=True)
    sorted_lw, order = torch.sort(lw, dim=-1, descending=True)
    sorted_w = torch.exp(sorted_lw)
    tail = sorted_w.flip(-1).cumsum(-1).flip(-1)  # tail[k] = weight outside the top k
    kept_candidates = torch.arange(n_out, device=lw.device)
    fits = (n_out - kept_candidates) * sorted_w[..., :n_out] < tail[..., :n_out]
    found = fits.any(-1, keepdim=True)
    kept = torch.where(found, fits.to(torch.int8).argmax(-1, keepdim=True), n_out)  # (*B, 1)
    drawn = n_out - kept  # L, the slots filled at random
    tail_mass = tail.gather(-1, kept.clamp(max=tail.shape[-1] - 1))  # S = weight not kept
    tail_mass = torch.where(found, tail_mass, 1.0)  # unused there; keeps gradients finite
    # Systematic draw of L children with probabilities c·w (< 1: at most one copy each) over
    # a random permutation of the remaining children, so that no layout period biases it. The
    # permutation orders the children by random keys tied to their own index (not to their
    # rank by weight), and the survivors leave in the order of their index: children of equal
    # weight (modes with the same prediction) whose rank swaps under a perturbation of the
    # weights by rounding are then drawn with the same random numbers, so that the filter's
    # result is a piecewise smooth function of the model's parameters for a fixed generator.
    position = torch.arange(lw.shape[-1], device=lw.device)
    left = torch.where(position >= kept, sorted_w, 0.0).detach()
    remaining = torch.zeros_like(left).scatter(-1, order, left)  # by child index
    batch = lw.shape[:-1]
    perm = torch.argsort(torch.rand(lw.shape, generator=generator, device=lw.device), dim=-1)
    remaining = remaining.gather(-1, perm)
    remaining = torch.where(found, remaining, 1.0)  # rows with nothing to draw: any valid CDF
    slot = torch.arange(n_out, device=lw.device)
    offset = torch.rand((*batch, 1), dtype=torch.float64, generator=generator, device=lw.device)
    u = ((slot - kept) + offset) / drawn.clamp(min=1)
    picked = perm.gather(-1, inverse_cdf(remaining, u))
    is_drawn = slot >= kept
    indices = torch.where(is_drawn, picked, order[..., :n_out])
    new_lw = torch.where(
        is_drawn,
        torch.log(tail_mass) - torch.log(drawn.clamp(min=1).to(lw.dtype)),
        sorted_lw[..., :n_out],
    )
    indices, by_index = torch.sort(indices, dim=-1)
    new_lw = new_lw.gather(-1, by_index)
    return indices, new_lw - torch.logsumexp(new_lw, -1, keepdim=True)


def optimal_resample(
    log_weights: Tensor, num_samples: int, *, generator: torch.Generator | None = None
) -> tuple[Tensor, Tensor]:
    r"""Fearnhead–Clifford optimal resampling of ``M`` weighted particles down to ``N <= M``.

    With normalized weights :math:`w_i`, the threshold :math:`c` solves
    :math:`\sum_i \min(c\, w_i, 1) = N`. Particles with :math:`c\, w_i \ge 1` are kept once
    with their own weight; the others are drawn with probability :math:`c\, w_i` (systematic
    sampling over a random permutation, so each is drawn at most once) and, when drawn,
    carry the weight :math:`1/c`. The result is unbiased — :math:`E[\tilde w_i] = w_i` — and
    minimizes the expected squared error among such schemes. If at most ``N`` particles have
    a positive weight, all of them are kept exactly (no randomness) and the remaining slots
    hold zero-weight particles.

    Args:
        log_weights: ``(*B, M)`` unnormalized log-weights, each row with a finite entry.
        num_samples: ``N`` (``1 <= N <= M``).
        generator: random source; torch's default if None.

    Returns:
        ``(indices (*B, N), log_weights (*B, N))``: the survivors and their normalized
        log-weights. Gradients flow to ``log_weights`` through the kept weights and through
        :math:`1/c`, not through the (discrete) selection.

    References:
        P. Fearnhead and P. Clifford, "On-line inference for hidden Markov models via particle
        filters", J. R. Statist. Soc. B 65(4), 2003.
    """
    lw = _check_log_weights(log_weights, "log_weights")
    if not isinstance(num_samples, int) or not 1 <= num_samples <= lw.shape[-1]:
        raise ValueError(
            f"num_samples: expected an int in [1, {lw.shape[-1]}], got {num_samples!r}"
        )
    return optimal_resample_core(lw, num_samples, generator)
