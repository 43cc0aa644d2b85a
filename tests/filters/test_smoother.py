"""RTS smoother against a NumPy RTS and against the exact batch (joint Gaussian) posterior."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.filters import reference as ref
from torchcontact.filters import Gaussian, kf_predict, kf_update, rts_smooth

F64 = torch.float64


def _filter(
    m0: torch.Tensor,
    P0: torch.Tensor,
    Fs: list[torch.Tensor],
    Q: torch.Tensor,
    H: torch.Tensor,
    R: torch.Tensor,
    ys: torch.Tensor,
) -> tuple[list[Gaussian], list[Gaussian]]:
    filtered, predicted = [], []
    g = Gaussian(m0, P0)
    for t, y in enumerate(ys):
        if t > 0:
            g = kf_predict(g, F=Fs[t - 1], Q=Q)
            predicted.append(g)
        g, _ = kf_update(g, y, H=H, R=R)
        filtered.append(g)
    return filtered, predicted


def test_rts_matches_numpy_rts() -> None:
    gen = torch.Generator().manual_seed(0)
    B, T, n = 3, 12, 3
    F = torch.eye(n, dtype=F64) + 0.2 * torch.randn(n, n, dtype=F64, generator=gen)
    Q = 0.05 * torch.eye(n, dtype=F64)
    H = torch.randn(1, n, dtype=F64, generator=gen)
    R = torch.tensor([[0.3]], dtype=F64)
    m0 = torch.randn(B, n, dtype=F64, generator=gen)
    P0 = torch.eye(n, dtype=F64).expand(B, n, n) * 2.0
    ys = torch.randn(T, B, 1, dtype=F64, generator=gen)
    filtered, predicted = _filter(m0, P0, [F] * (T - 1), Q, H, R, ys)
    smoothed = rts_smooth(filtered, predicted, F=F)
    stacked = rts_smooth(
        Gaussian(torch.stack([g.mean for g in filtered]), torch.stack([g.cov for g in filtered])),
        Gaussian(torch.stack([g.mean for g in predicted]), torch.stack([g.cov for g in predicted])),
        F=F,
    )
    assert len(smoothed) == T
    for b in range(B):
        ms, Ps = ref.rts(
            [g.mean[b].numpy() for g in filtered],
            [g.cov[b].numpy() for g in filtered],
            F.numpy(),
            Q.numpy(),
        )
        for t in range(T):
            np.testing.assert_allclose(smoothed[t].mean[b].numpy(), ms[t], atol=1e-10)
            np.testing.assert_allclose(smoothed[t].cov[b].numpy(), Ps[t], atol=1e-10)
            np.testing.assert_allclose(stacked.mean[t, b].numpy(), ms[t], atol=1e-10)
            np.testing.assert_allclose(stacked.cov[t, b].numpy(), Ps[t], atol=1e-10)


def test_rts_equals_batch_posterior_with_time_varying_dynamics() -> None:
    """Smoothed marginals = marginals of p(x_0..x_{T-1} | y_0..y_{T-1}) by dense conditioning."""
    gen = torch.Generator().manual_seed(1)
    T, n = 6, 2
    Fs = [
        torch.eye(n, dtype=F64) + 0.3 * torch.randn(n, n, dtype=F64, generator=gen)
        for _ in range(T - 1)
    ]
    Q = torch.tensor([[0.1, 0.02], [0.02, 0.05]], dtype=F64)
    H = torch.tensor([[1.0, 0.5]], dtype=F64)
    R = torch.tensor([[0.2]], dtype=F64)
    m0 = torch.tensor([0.5, -1.0], dtype=F64)
    P0 = torch.tensor([[1.0, 0.3], [0.3, 2.0]], dtype=F64)
    ys = torch.randn(T, 1, dtype=F64, generator=gen)
    filtered, predicted = _filter(m0, P0, Fs, Q, H, R, ys)
    smoothed = rts_smooth(filtered, predicted, F=Fs)

    # joint prior of X = (x_0, ..., x_{T-1}): x_t = A_t x_0 + sum_s A_{t,s} w_s
    Fn = [F.numpy() for F in Fs]
    mean = [m0.numpy()]
    for t in range(T - 1):
        mean.append(Fn[t] @ mean[-1])
    trans = [[np.eye(n) if s == t else None for s in range(T)] for t in range(T)]
    for t in range(T):
        for s in range(t - 1, -1, -1):
            trans[t][s] = trans[t][s + 1] @ Fn[s]  # maps x_s to x_t
    noise_cov = [P0.numpy()] + [Q.numpy()] * (T - 1)  # x_0 and w_0..w_{T-2} (w_s enters x_{s+1})
    joint = np.zeros((T * n, T * n))
    for t in range(T):
        for u in range(T):
            block = np.zeros((n, n))
            for s in range(min(t, u) + 1):  # source s: x_0 (s = 0) or w_{s-1} entering x_s
                block += trans[t][s] @ noise_cov[s] @ trans[u][s].T
            joint[t * n : (t + 1) * n, u * n : (u + 1) * n] = block
    mu = np.concatenate(mean)
    Hb = np.kron(np.eye(T), H.numpy())
    S = Hb @ joint @ Hb.T + np.kron(np.eye(T), R.numpy())
    gain = joint @ Hb.T @ np.linalg.inv(S)
    post_mean = mu + gain @ (ys.numpy().ravel() - Hb @ mu)
    post_cov = joint - gain @ Hb @ joint
    for t in range(T):
        sl = slice(t * n, (t + 1) * n)
        np.testing.assert_allclose(smoothed[t].mean.numpy(), post_mean[sl], atol=1e-10)
        np.testing.assert_allclose(smoothed[t].cov.numpy(), post_cov[sl, sl], atol=1e-10)


def test_rts_bad_input_raises_value_error() -> None:
    g = Gaussian(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))
    F = torch.eye(2, dtype=F64)
    with pytest.raises(ValueError, match=r"^predicted:"):
        rts_smooth([g, g, g], [g], F=F)
    with pytest.raises(ValueError, match=r"^F:"):
        rts_smooth([g, g, g], [g, g], F=[F])
    with pytest.raises(ValueError, match=r"^F:"):
        rts_smooth([g, g], [g], F=torch.eye(3, dtype=F64))
    with pytest.raises(ValueError, match=r"^filtered"):
        rts_smooth([g, "g"], [g], F=F)  # type: ignore[list-item]
