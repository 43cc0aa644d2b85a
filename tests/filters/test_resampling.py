"""Resampling schemes: unbiasedness over many replicas, structural properties, optimal
(Fearnhead–Clifford) resampling, and input validation."""

from __future__ import annotations

import math

import pytest
import torch

from torchcontact.filters import effective_sample_size, optimal_resample, resample

F64 = torch.float64
WEIGHTS = torch.tensor([0.0, 0.31, 0.02, 0.004, 0.25, 0.116, 0.3, 0.0], dtype=F64)
N = WEIGHTS.numel()


def _counts(indices: torch.Tensor, size: int) -> torch.Tensor:
    out = torch.zeros(*indices.shape[:-1], size, dtype=F64)
    return out.scatter_add(-1, indices, torch.ones_like(indices, dtype=F64))


@pytest.mark.parametrize("method", ["multinomial", "systematic", "stratified", "residual"])
def test_resampling_is_unbiased_and_never_draws_zero_weights(method: str) -> None:
    replicas = 20000
    log_w = torch.log(WEIGHTS).expand(replicas, N) + 3.0  # unnormalized is fine
    gen = torch.Generator().manual_seed(0)
    idx = resample(log_w, method=method, generator=gen)  # type: ignore[arg-type]
    assert idx.shape == (replicas, N)
    assert idx.dtype == torch.long
    counts = _counts(idx, N)
    assert counts[:, WEIGHTS == 0].sum().item() == 0
    expected = N * WEIGHTS
    se = torch.sqrt(N * WEIGHTS * (1 - WEIGHTS) / replicas)
    assert ((counts.mean(0) - expected).abs() <= 5 * se + 1e-12).all()
    if method in ("systematic", "residual"):
        assert (counts >= torch.floor(expected)).all()
    if method == "systematic":
        assert (counts <= torch.ceil(expected)).all()


def test_resampling_num_samples_and_reproducibility() -> None:
    log_w = torch.log(WEIGHTS)
    a = resample(
        log_w, method="stratified", num_samples=50, generator=torch.Generator().manual_seed(3)
    )
    b = resample(
        log_w, method="stratified", num_samples=50, generator=torch.Generator().manual_seed(3)
    )
    assert a.shape == (50,)
    assert torch.equal(a, b)


def test_effective_sample_size() -> None:
    log_w = torch.log(torch.tensor([[0.5, 0.5, 0.0], [1.0, 1.0, 1.0]], dtype=F64)) + 2.0
    torch.testing.assert_close(effective_sample_size(log_w), torch.tensor([2.0, 3.0], dtype=F64))
    assert effective_sample_size(torch.full((2,), -math.inf, dtype=F64)).item() == 0.0


def test_optimal_resampling_is_unbiased_and_draws_each_child_at_most_once() -> None:
    replicas, n_out = 20000, 4
    log_w = torch.log(WEIGHTS).expand(replicas, N)
    idx, new_lw = optimal_resample(log_w, n_out, generator=torch.Generator().manual_seed(1))
    assert idx.shape == (replicas, n_out)
    torch.testing.assert_close(torch.logsumexp(new_lw, -1), torch.zeros(replicas, dtype=F64))
    assert (_counts(idx, N) <= 1).all()
    assert (_counts(idx, N)[:, WEIGHTS == 0] == 0).all()
    # E[new weight carried by child i] = w_i
    carried = torch.zeros(replicas, N, dtype=F64).scatter_add(-1, idx, torch.exp(new_lw))
    se = carried.std(0) / math.sqrt(replicas)
    assert ((carried.mean(0) - WEIGHTS).abs() <= 5 * se + 1e-12).all()
    # the heavy children (c·w >= 1) survive in every replica with their own weights
    heavy = torch.tensor([1, 6])
    torch.testing.assert_close(carried[:, heavy], WEIGHTS[heavy].expand(replicas, 2))


def test_optimal_resampling_keeps_everything_when_it_fits() -> None:
    log_w = torch.log(WEIGHTS)
    idx, new_lw = optimal_resample(log_w, 6, generator=torch.Generator().manual_seed(2))
    kept = idx[new_lw > -math.inf]
    assert sorted(kept.tolist()) == [1, 2, 3, 4, 5, 6]
    torch.testing.assert_close(
        torch.exp(new_lw[new_lw > -math.inf]), WEIGHTS[kept], rtol=1e-14, atol=0
    )


def test_optimal_resampling_gradient_is_finite() -> None:
    log_w = torch.log(WEIGHTS).clone().requires_grad_()
    _, new_lw = optimal_resample(log_w, 3, generator=torch.Generator().manual_seed(4))
    (grad,) = torch.autograd.grad(torch.exp(new_lw).pow(2).sum(), log_w)
    assert torch.isfinite(grad).all()


@pytest.mark.parametrize(
    ("call", "argument"),
    [
        (lambda: resample(torch.tensor([math.nan, 0.0])), "log_weights"),
        (lambda: resample(torch.full((2, 3), -math.inf)), "log_weights"),
        (lambda: resample(torch.zeros(3), method="bogus"), "method"),  # type: ignore[arg-type]
        (lambda: resample(torch.zeros(3), num_samples=0), "num_samples"),
        (lambda: optimal_resample(torch.zeros(3), 4), "num_samples"),
        (lambda: optimal_resample([0.0, 1.0], 1), "log_weights"),  # type: ignore[arg-type]
    ],
)
def test_bad_input_raises_value_error_naming_argument(call, argument: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError, match=f"^{argument}:"):
        call()
