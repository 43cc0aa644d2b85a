"""Rauch–Tung–Striebel fixed-interval smoother for linear-Gaussian models."""

from __future__ import annotations

from collections.abc import Sequence
from typing import overload

import torch
from torch import Tensor

from torchcontact._checks import all_finite, broadcast_batch, check_symmetric_psd, check_tensor
from torchcontact.filters import _linalg as la
from torchcontact.filters._gaussian import Gaussian, check_gaussian, unchecked_gaussian


def _as_list(x: Gaussian | Sequence[Gaussian], name: str) -> list[Gaussian]:
    if isinstance(x, Gaussian):
        check_gaussian(x, name, euclidean=True)
        if len(x.batch_shape) < 1:
            raise ValueError(f"{name}: a stacked Gaussian needs a leading time dim (T, *B, n)")
        return [x[t] for t in range(x.batch_shape[0])]
    if isinstance(x, Sequence):
        return [check_gaussian(g, f"{name}[{t}]", euclidean=True) for t, g in enumerate(x)]
    raise ValueError(f"{name}: expected a Gaussian or a sequence of Gaussians, got {type(x)}")


@overload
def rts_smooth(
    filtered: Gaussian, predicted: Gaussian, *, F: Tensor | Sequence[Tensor]
) -> Gaussian: ...


@overload
def rts_smooth(
    filtered: Sequence[Gaussian], predicted: Sequence[Gaussian], *, F: Tensor | Sequence[Tensor]
) -> list[Gaussian]: ...


def rts_smooth(
    filtered: Gaussian | Sequence[Gaussian],
    predicted: Gaussian | Sequence[Gaussian],
    *,
    F: Tensor | Sequence[Tensor],
) -> Gaussian | list[Gaussian]:
    r"""Rauch–Tung–Striebel smoother: :math:`p(x_t \mid y_{0:T-1})` from a Kalman filter's output.

    For the linear model :math:`x_{t+1} = F_t x_t + c_t + w_t`, with filtered beliefs
    :math:`N(\mu_t, P_t) = p(x_t \mid y_{0:t})` and one-step predictions
    :math:`N(\mu^-_{t+1}, P^-_{t+1}) = p(x_{t+1} \mid y_{0:t})`, the backward pass is

    .. math::

        G_t = P_t F_t^\top (P^-_{t+1})^{-1}, \quad
        \mu^s_t = \mu_t + G_t (\mu^s_{t+1} - \mu^-_{t+1}), \quad
        P^s_t = P_t + G_t (P^s_{t+1} - P^-_{t+1}) G_t^\top

    starting from :math:`\mu^s_{T-1} = \mu_{T-1}`; :math:`G_t` comes from a Cholesky solve
    with :math:`P^-_{t+1}` (no inverse) and every :math:`P^s_t` is symmetrized.

    Args:
        filtered: ``T`` filtered beliefs, each ``(*B, n)``: a sequence of Gaussians, or one
            Gaussian stacked over a leading time dim ``(T, *B, n)``.
        predicted: the ``T - 1`` predictions, in the same form: ``predicted[t]`` is
            ``kf_predict(filtered[t], F=F_t, ...)``, the prior of step ``t + 1`` (the filter's
            prior for step 0 is not an input).
        F: ``(*B', n, n)`` time-invariant transition matrix, or a sequence of ``T - 1``
            matrices ``F_t`` (``F_t`` maps ``x_t`` to ``x_{t+1}``).

    Returns:
        The ``T`` smoothed beliefs, in the form of ``filtered`` (a list, or a stacked Gaussian).

    References:
        H. E. Rauch, F. Tung and C. T. Striebel, "Maximum likelihood estimates of linear
        dynamic systems", AIAA Journal 3(8), 1965.
    """
    stacked = isinstance(filtered, Gaussian)
    filt = _as_list(filtered, "filtered")
    pred = _as_list(predicted, "predicted")
    T = len(filt)
    if T < 1:
        raise ValueError("filtered: needs at least one belief")
    if len(pred) != T - 1:
        raise ValueError(f"predicted: expected T - 1 = {T - 1} predictions, got {len(pred)}")
    like = filt[0].mean
    n = filt[0].dim
    batch = broadcast_batch([("filtered", g.batch_shape) for g in filt])
    for t, g in enumerate(filt + pred):
        name = f"filtered[{t}]" if t < T else f"predicted[{t - T}]"
        if g.dim != n or g.dtype != like.dtype or g.batch_shape != batch:
            raise ValueError(f"{name}: expected batch {tuple(batch)}, n = {n}, {like.dtype}")
    if isinstance(F, Tensor):
        Fs = [check_tensor("F", F, event_shape=(n, n), like=like)] * (T - 1)
    elif isinstance(F, Sequence) and len(F) == T - 1:
        Fs = [check_tensor(f"F[{t}]", Ft, event_shape=(n, n), like=like) for t, Ft in enumerate(F)]
    else:
        raise ValueError(f"F: expected a tensor or a sequence of T - 1 = {T - 1} tensors")
    broadcast_batch([("filtered", batch)] + [(f"F[{t}]", Ft.shape[:-2]) for t, Ft in enumerate(Fs)])
    nb = len(batch)
    mean = la.to_batch_last(filt[-1].mean, 1, nb)
    cov = la.to_batch_last(filt[-1].cov, 2, nb)
    out = [unchecked_gaussian(filt[-1].mean, filt[-1].cov)]
    for t in reversed(range(T - 1)):
        m_f, P_f = la.to_batch_last(filt[t].mean, 1, nb), la.to_batch_last(filt[t].cov, 2, nb)
        m_p, P_p = la.to_batch_last(pred[t].mean, 1, nb), la.to_batch_last(pred[t].cov, 2, nb)
        Ft = la.to_batch_last(Fs[t], 2, nb)
        low = la.Cholesky(P_p)
        gain_t = low.solve_transpose(low.solve(la.mm(Ft, P_f)))  # Gᵀ = P_p⁻¹ F P_f
        mean = m_f + la.mtv(gain_t, mean - m_p)
        cov = la.symmetrize(P_f + la.mm(la.mtm(gain_t, cov - P_p), gain_t))
        if not (all_finite(mean.detach()) and all_finite(cov.detach())):
            if bool((torch.linalg.cholesky_ex(pred[t].cov).info != 0).any()):
                raise ValueError(f"predicted[{t}]: covariance is not positive definite")
            name = "F" if isinstance(F, Tensor) else f"F[{t}]"
            raise ValueError(f"{name}: the smoothed belief overflows {like.dtype}")
        try:
            check_symmetric_psd("smoothed cov", la.to_batch_first(cov, 2))
        except ValueError as err:
            raise ValueError(
                f"predicted[{t}]: the smoothed covariance at t = {t} is not PSD: predicted[{t}] "
                f"must be filtered[{t}] predicted through F (P⁻ = F P Fᵀ + Q, Q PSD) ({err})"
            ) from err
        out.append(unchecked_gaussian(la.to_batch_first(mean, 1), la.to_batch_first(cov, 2)))
    out.reverse()
    if stacked:
        return unchecked_gaussian(
            torch.stack([g.mean for g in out]), torch.stack([g.cov for g in out])
        )
    return out
