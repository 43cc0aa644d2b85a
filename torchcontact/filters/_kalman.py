"""Batched linear Kalman filter: predict and update with log-likelihood."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcontact._checks import (
    all_finite,
    all_finite_many,
    broadcast_batch,
    check_mask,
    check_symmetric_psd,
    check_tensor,
)
from torchcontact.filters import _linalg as la
from torchcontact.filters._gaussian import Gaussian, check_gaussian, unchecked_gaussian

_LOG_2PI = math.log(2.0 * math.pi)


def predict_core(
    mean: Tensor, cov: Tensor, F: Tensor, c: Tensor | None, Q: Tensor, *, symmetric: bool = True
) -> tuple[Tensor, Tensor]:
    """Kalman prediction in the batch-last layout (see ``_linalg``).

    Args:
        mean: ``(n, *B)``; cov: ``(n, n, *B)``; F: ``(n, n, *B)``; c: ``(n, *B)`` or None;
        Q: ``(n, n, *B)`` (all with the same number of batch dims, broadcastable).
        symmetric: symmetrize the covariance; skip only when it goes straight into
            :func:`update_core` with every component observed (which then reads its lower
            triangle only).

    Returns:
        ``(F m + c, sym(F P Fᵀ + Q))``.
    """
    mean = la.mv(F, mean)
    if c is not None:
        mean = mean + c
    cov = la.add_(la.mm_t(la.mm(F, cov), F), Q)
    return mean, (la.symmetrize(cov) if symmetric else cov)


def update_core(
    mean: Tensor,
    cov: Tensor,
    y: Tensor,
    H: Tensor,
    d: Tensor | None,
    R: Tensor,
    observed: Tensor | None,
    *,
    entrywise: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """Kalman update in the batch-last layout (see ``_linalg``), Joseph form.

    Args:
        mean: ``(n, *B)``; cov: ``(n, n, *B)``; y: ``(k, *B)`` (finite where observed);
        H: ``(k, n, *B)``; d: ``(k, *B)`` or None; R: ``(k, k, *B)``.
        observed: None (every component observed) or bool ``(k, *B)``: the components used.
            Unused components are removed exactly: their rows of ``H`` are zeroed, their
            residual is zero and their block of ``R`` is replaced by the identity, decoupled
            from the rest, so ``S`` is block diagonal with an identity block that contributes
            neither gain nor likelihood. An entry with no observed component is returned
            unchanged with log-likelihood 0.
        entrywise: factor ``cov`` matrix by matrix without host synchronization (compiled
            kernels; see :func:`~torchcontact.filters._linalg.psd_cholesky`).

    Returns:
        ``(mean⁺ (n, *B), cov⁺ (n, n, *B), log_likelihood (*B))``; the log-likelihood is
        non-finite where ``H P Hᵀ + R`` is not positive definite.
    """
    k, n = H.shape[0], H.shape[1]
    batch_ndim = mean.ndim - 1
    if observed is not None:
        H, y, d, R = _mask_unobserved(H, y, d, R, observed, batch_ndim)
    residual = y - la.mv(H, mean)
    if d is not None:
        residual = residual - d
    # Square-root (Gram) form: with P = C Cᵀ, S = (H C)(H C)ᵀ + R and the Joseph update
    # (I - K H) P (I - K H)ᵀ + K R Kᵀ = (C - K H C)(C - K H C)ᵀ + K R Kᵀ are sums of Gram
    # matrices, positive semi-definite to rounding even when P spans many orders of magnitude
    # (tiny R, huge P) in float32, where products of P itself would cancel catastrophically.
    root = la.psd_cholesky(cov, entrywise=entrywise)
    HC = la.mm(H, root)
    HP = la.mm_t(HC, root)
    low = la.Cholesky(la.add_(la.mm_t(HC, HC), R))  # S = L Lᵀ
    # One forward substitution for [H P | r]: W = L⁻¹ H P and the whitened residual z = L⁻¹ r.
    rhs = [HP, residual.unsqueeze(1)]
    if HP.shape[2:] != residual.shape[1:]:  # y with batch dims that P and H lack, or vice versa
        batch = [max(a, b) for a, b in zip(HP.shape[2:], residual.shape[1:], strict=True)]
        rhs = [HP.expand(k, n, *batch), residual.unsqueeze(1).expand(k, 1, *batch)]
    solved = low.solve(torch.cat(rhs, dim=1))
    z = solved[:, n]
    gain_t = low.solve_transpose(solved[:, :n])  # Kᵀ = S⁻¹ H P, (k, n, *B)
    num_obs: float | Tensor = float(k) if observed is None else observed.sum(0).to(mean.dtype)
    log_lik = -0.5 * ((z * z).sum(0) + low.log_det() + num_obs * _LOG_2PI)
    new_mean = mean + la.mtv(gain_t, residual)
    AC = la.add_(la.mtm(gain_t, HC).neg_(), root)  # (I - K H) C
    new_cov = la.symmetrize(la.add_(la.mm_t(AC, AC), la.mm(la.mtm(gain_t, R), gain_t)))
    if observed is not None:
        none = ~observed.any(0)
        new_mean = torch.where(none, mean, new_mean)
        new_cov = torch.where(none, cov, new_cov)
        log_lik = torch.where(none, 0.0, log_lik)
    return new_mean, new_cov, log_lik


def update_log_likelihood(
    mean: Tensor,
    cov: Tensor,
    y: Tensor,
    H: Tensor,
    d: Tensor | None,
    R: Tensor,
    observed: Tensor | None,
    *,
    entrywise: bool = False,
) -> Tensor:
    """The log-likelihood of :func:`update_core` alone, by the same operations (the same values).

    ``mean`` and ``cov`` may be the leading ``r`` components and ``(r, r)`` block when ``H``
    reads only the leading ``r`` state components (its other columns are zero): the first
    ``r`` rows of the Cholesky factor, and so ``S = H P Hᵀ + R``, depend on that block only.
    The products are computed as :func:`update_core` computes them at the full size ``n``, so
    the likelihood is the same, to the bit where ``H``'s entries are 0 and ±1 (otherwise
    ``H μ`` may round differently), except when a full covariance of the batch is not
    numerically positive definite (then :func:`update_core` factors every matrix in the
    semi-definite mode of :func:`~torchcontact.filters._linalg.psd_cholesky`, which rounds
    differently).

    Args:
        mean: ``(r, *B)``; cov: ``(r, r, *B)``, ``r <= n``; y, H, d, R, observed,
            entrywise: as in :func:`update_core` (``H`` is ``(k, n, *B)``).

    Returns:
        ``(*B)`` log-likelihoods.
    """
    k, n, r = H.shape[0], H.shape[1], cov.shape[0]
    batch_ndim = mean.ndim - 1
    if observed is not None:
        H, y, d, R = _mask_unobserved(H, y, d, R, observed, batch_ndim)
    residual = y - la.mv(H[:, :r], mean)
    if d is not None:
        residual = residual - d
    root = la.psd_cholesky(cov, entrywise=entrywise)
    batch = math.prod(torch.broadcast_shapes(mean.shape[1:], cov.shape[2:], H.shape[2:]))
    HC = la.mm(H[:, :r], root, size=k * n * n * batch)
    low = la.Cholesky(la.add_(la.mm_t(HC, HC, size=k * n * k * batch), R))
    z = low.solve(residual.unsqueeze(1))[:, 0]
    num_obs: float | Tensor = float(k) if observed is None else observed.sum(0).to(mean.dtype)
    log_lik = -0.5 * ((z * z).sum(0) + low.log_det() + num_obs * _LOG_2PI)
    if observed is not None:
        log_lik = torch.where(~observed.any(0), 0.0, log_lik)
    return log_lik


def observed_components(y: Tensor, mask: Tensor | None) -> Tensor | None:
    """The ``(*B, k)`` components of ``y`` an update uses, or None when it uses all of them.

    A measurement whose components are *all* NaN means "no measurement"; ``mask`` (``True`` =
    use) removes components. A NaN in a used component of a partial measurement is an error.
    """
    nan = torch.isnan(y)
    if mask is None and not bool(nan.any()):
        return None
    observed = (~nan.all(-1, keepdim=True)).expand(nan.shape)
    if mask is not None:
        observed = observed & mask
    if bool((nan & observed).any()):
        raise ValueError(
            "y: NaN in a used component of a partial measurement (a NaN measurement must be "
            "NaN in every component; mark missing components with mask instead)"
        )
    return observed


def kf_predict(g: Gaussian, *, F: Tensor, c: Tensor | None = None, Q: Tensor) -> Gaussian:
    r"""Kalman prediction through the linear model :math:`x^+ = F x + c + w,\ w \sim N(0, Q)`.

    .. math::

        \mu^+ = F \mu + c, \qquad P^+ = \tfrac12 (A + A^\top),\ A = F P F^\top + Q

    Model tensors broadcast against the batch of ``g`` (e.g. one ``(n, n)`` matrix for all).

    Args:
        g: belief ``(*B, n)``, Euclidean (``cov`` is ``(*B, n, n)``).
        F: ``(*B', n, n)`` state transition matrix.
        c: ``(*B', n)`` known offset (control input term); zero if None.
        Q: ``(*B', n, n)`` process noise covariance (symmetric PSD, to the tolerance of
            :func:`~torchcontact._checks.check_symmetric_psd`).

    Returns:
        The predicted Gaussian with the broadcast batch shape.

    Raises:
        ValueError: a bad argument (named first in the message): wrong type, dtype or shape,
            NaN or inf, batch shapes that do not broadcast, a ``Q`` that is not symmetric PSD,
            or finite inputs whose prediction overflows the dtype (``F``, ``c`` or ``Q``).
    """
    g = check_gaussian(g, "g", euclidean=True)
    n = g.dim
    F = check_tensor("F", F, event_shape=(n, n), like=g.mean)
    Q = check_tensor("Q", Q, event_shape=(n, n), like=g.mean)
    check_symmetric_psd("Q", Q)
    shapes = [("g", g.batch_shape), ("F", F.shape[:-2]), ("Q", Q.shape[:-2])]
    if c is not None:
        c = check_tensor("c", c, event_shape=(n,), like=g.mean)
        shapes.append(("c", c.shape[:-1]))
    batch = broadcast_batch(shapes)
    nb = len(batch)
    mean, cov = predict_core(
        la.to_batch_last(g.mean, 1, nb),
        la.to_batch_last(g.cov, 2, nb),
        la.to_batch_last(F, 2, nb),
        None if c is None else la.to_batch_last(c, 1, nb),
        la.to_batch_last(Q, 2, nb),
    )
    if not all_finite_many(mean, cov):
        raise _prediction_overflow(g, F, c, Q)
    return unchecked_gaussian(
        la.to_batch_first(mean.expand(n, *batch), 1),
        la.to_batch_first(cov.expand(n, n, *batch), 2),
    )


def kf_update(
    g: Gaussian,
    y: Tensor,
    *,
    H: Tensor,
    d: Tensor | None = None,
    R: Tensor,
    mask: Tensor | None = None,
) -> tuple[Gaussian, Tensor]:
    r"""Kalman update with the measurement :math:`y = H x + d + v,\ v \sim N(0, R)`.

    .. math::

        S = H P H^\top + R = L L^\top, \quad K = P H^\top S^{-1}, \quad
        \mu^+ = \mu + K (y - H \mu - d),

        P^+ = (I - K H) P (I - K H)^\top + K R K^\top \quad\text{(Joseph form, symmetrized)},

        \log p(y) = \log N(y;\ H \mu + d,\ S)

    ``S`` is factored by Cholesky; the gain comes from two triangular solves (no inverse).
    The Joseph form is evaluated in square-root form: with a (semi-definite) Cholesky factor
    :math:`P = C C^\top`, :math:`S = (HC)(HC)^\top + R` and
    :math:`P^+ = (C - KHC)(C - KHC)^\top + K R K^\top`, sums of Gram matrices that stay
    positive semi-definite to rounding even when ``P`` spans more orders of magnitude than
    float32 resolves (tiny ``R``, huge prior); ``P^+`` is then symmetrized exactly.

    Missing data: an entry of ``y`` that is NaN in *every* component means "no measurement":
    that entry is returned unchanged with log-likelihood 0. ``mask`` (``True`` = use the
    component) ignores components exactly as if their rows were deleted from ``y``, ``H``,
    ``d`` and ``R`` (masked components may be NaN). Any other NaN, and any inf, in ``y``
    raises ``ValueError``.

    Args:
        g: prior belief ``(*B, n)``, Euclidean.
        y: ``(*B', m)`` measurement.
        H: ``(*B', m, n)`` measurement matrix.
        d: ``(*B', m)`` known measurement offset; zero if None.
        R: ``(*B', m, m)`` measurement noise covariance: symmetric PSD (to the tolerance of
            :func:`~torchcontact._checks.check_symmetric_psd`), with ``H P Hᵀ + R`` positive
            definite on the used components (a singular ``R`` is fine where ``H P Hᵀ`` covers
            it).
        mask: ``(*B', m)`` bool, ``True`` where the component is used; all if None.

    Returns:
        ``(posterior, log_likelihood)`` with the broadcast batch shape ``*B``; the
        log-likelihood ``(*B,)`` is differentiable w.r.t. every input.

    Raises:
        ValueError: a bad argument (named first in the message): wrong type, dtype or shape,
            NaN (other than a missing measurement) or inf, batch shapes that do not
            broadcast, an ``R`` that is not symmetric PSD, ``H P Hᵀ + R`` not positive
            definite (``R``), or finite inputs whose update overflows the dtype (``H``, ``y``
            or ``g``).

    References:
        R. E. Kalman, "A new approach to linear filtering and prediction problems", J. Basic
        Eng. 82(1), 1960. R. S. Bucy and P. D. Joseph, "Filtering for Stochastic Processes
        with Applications to Guidance", 1968 (the Joseph form).
    """
    g = check_gaussian(g, "g", euclidean=True)
    n = g.dim
    if not isinstance(y, Tensor) or y.ndim < 1:
        raise ValueError(f"y: expected a (*B, m) tensor, got {getattr(y, 'shape', y)!r}")
    k = int(y.shape[-1])
    y = check_tensor("y", y, event_shape=(k,), like=g.mean, allow_nan=True)
    H = check_tensor("H", H, event_shape=(k, n), like=g.mean)
    R = check_tensor("R", R, event_shape=(k, k), like=g.mean)
    check_symmetric_psd("R", R)
    shapes = [("g", g.batch_shape), ("y", y.shape[:-1]), ("H", H.shape[:-2]), ("R", R.shape[:-2])]
    if d is not None:
        d = check_tensor("d", d, event_shape=(k,), like=g.mean)
        shapes.append(("d", d.shape[:-1]))
    if mask is not None:
        mask = check_mask("mask", mask, size=k)
        shapes.append(("mask", mask.shape[:-1]))
    batch = broadcast_batch(shapes)
    nb = len(batch)
    observed = observed_components(y, mask)
    mean, cov, log_lik = update_core(
        la.to_batch_last(g.mean, 1, nb),
        la.to_batch_last(g.cov, 2, nb),
        la.to_batch_last(y, 1, nb),
        la.to_batch_last(H, 2, nb),
        None if d is None else la.to_batch_last(d, 1, nb),
        la.to_batch_last(R, 2, nb),
        None if observed is None else la.to_batch_last(observed, 1, nb),
    )
    if not all_finite_many(log_lik, mean, cov):
        raise update_failure(g.mean, g.cov, H, R, finite_likelihood=all_finite(log_lik.detach()))
    posterior = unchecked_gaussian(
        la.to_batch_first(mean.expand(n, *batch), 1),
        la.to_batch_first(cov.expand(n, n, *batch), 2),
    )
    return posterior, log_lik.expand(batch)


def _mask_unobserved(
    H: Tensor, y: Tensor, d: Tensor | None, R: Tensor, observed: Tensor, batch_ndim: int
) -> tuple[Tensor, Tensor, Tensor | None, Tensor]:
    """Zero the rows of ``H``, ``y`` and ``d`` of unobserved components and replace their
    block of ``R`` by the identity (see :func:`update_core`)."""
    k = H.shape[0]
    H = H * observed.unsqueeze(1)
    y = torch.where(observed, y, 0.0)
    if d is not None:
        d = torch.where(observed, d, 0.0)
    both = observed.unsqueeze(1) & observed.unsqueeze(0)
    return H, y, d, torch.where(both, R, la.eye(k, batch_ndim, R))


def _prediction_overflow(g: Gaussian, F: Tensor, c: Tensor | None, Q: Tensor) -> ValueError:
    """The error of a prediction from finite inputs that overflowed, naming the input that
    made it overflow: ``F`` when ``F μ`` or ``F P Fᵀ`` does, else ``c`` or ``Q`` (failure path
    only; shapes as in :func:`kf_predict`)."""
    Fm = (F @ g.mean.unsqueeze(-1)).squeeze(-1)
    if not (all_finite(Fm) and all_finite(F @ g.cov @ F.mT)):
        name = "F"
    elif c is not None and not all_finite(Fm + c):
        name = "c"
    else:
        name = "Q"
    return ValueError(
        f"{name}: the prediction F μ + c, F P Fᵀ + Q overflows {g.dtype} (largest |F| = "
        f"{float(F.abs().max()):.3g}, |g.mean| = {float(g.mean.abs().max()):.3g}, |g.cov| = "
        f"{float(g.cov.abs().max()):.3g})"
    )


def update_failure(
    mean: Tensor,
    cov: Tensor,
    H: Tensor,
    R: Tensor,
    *,
    finite_likelihood: bool,
    measurement: str = "H",
) -> ValueError:
    """The error of a Kalman update from finite inputs whose result is not finite (failure
    path only): ``R`` when the innovation covariance ``S = H P Hᵀ + R`` is not positive
    definite, ``H`` (``measurement``) when it overflows, else ``y`` (the residual
    overflowed) or, with a finite likelihood, ``g`` (the posterior overflowed).

    Args:
        mean: ``(*B, n)`` prior mean; cov: ``(*B, n, n)`` prior covariance; H: ``(*B', k, n)``;
            R: ``(*B', k, k)``.
        finite_likelihood: whether the update's log-likelihood was finite.
        measurement: the name of the argument that gave ``H`` (``"h"`` for the EKF).
    """
    S = H @ cov @ H.mT + R
    if not all_finite(S):
        return ValueError(
            f"{measurement}: the innovation covariance H P Hᵀ + R overflows {mean.dtype} "
            f"(largest |H| = {float(H.abs().max()):.3g}, |g.cov| = {float(cov.abs().max()):.3g})"
        )
    if bool((torch.linalg.cholesky_ex(S).info != 0).any()):
        return ValueError(
            "R: the innovation covariance H P Hᵀ + R is not positive definite (check R and g.cov)"
        )
    if not finite_likelihood:
        return ValueError(
            f"y: the residual y - H μ - d or its likelihood overflows {mean.dtype} (largest "
            f"|g.mean| = {float(mean.abs().max()):.3g})"
        )
    return ValueError(
        f"g: the posterior overflows {mean.dtype} (largest |g.mean| = "
        f"{float(mean.abs().max()):.3g}, |g.cov| = {float(cov.abs().max()):.3g})"
    )
