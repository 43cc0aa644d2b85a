"""Extended Kalman filter for differentiable models, on Euclidean spaces or manifolds."""

from __future__ import annotations

from collections.abc import Callable

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
from torchcontact.filters._kalman import observed_components, update_core, update_failure
from torchcontact.filters._manifold import EUCLIDEAN, Manifold

Dynamics = Callable[..., Tensor]
"""``f(x)`` or ``f(x, u)`` on one unbatched state ``x (n,)`` and input ``u (p,)`` → ``(n,)``."""
Measurement = Callable[[Tensor], Tensor]
"""``h(x)`` on one unbatched state ``x (n,)`` → ``(m,)``."""


def _linearize(
    fun: Callable[..., Tensor],
    x: Tensor,
    args: tuple[Tensor, ...],
    *,
    source: Manifold,
    target: Manifold,
    tangent_dim: int,
) -> tuple[Tensor, Tensor]:
    """Value and tangent-space Jacobian of ``fun`` at each row of ``x``.

    For each row ``x_i (n,)`` (and the rows of ``args``), returns ``fun(x_i)`` and
    ``J_i = ∂/∂δ local_target(fun(x_i), fun(retract_source(x_i, δ)))`` at ``δ = 0`` by forward-mode
    autodiff, vectorized with ``vmap``: values ``(b, m)``, Jacobians ``(b, k, d)``.
    """

    def single(xi: Tensor, *ai: Tensor) -> tuple[Tensor, Tensor]:
        base = fun(xi, *ai)

        def along(delta: Tensor) -> Tensor:
            return target.local(base, fun(source.retract(xi, delta), *ai))

        zero = torch.zeros(tangent_dim, dtype=xi.dtype, device=xi.device)
        return base, torch.func.jacfwd(along)(zero)

    value, jac = torch.func.vmap(single)(x, *args)
    return value, jac


def _check_manifold(manifold: object, name: str) -> Manifold:
    if not isinstance(manifold, Manifold):
        raise ValueError(f"{name}: expected a Manifold, got {type(manifold).__name__}")
    return manifold


def ekf_predict(
    g: Gaussian,
    f: Dynamics,
    *,
    u: Tensor | None = None,
    Q: Tensor,
    manifold: Manifold = EUCLIDEAN,
) -> Gaussian:
    r"""EKF prediction through the nonlinear model :math:`x^+ = f(x, u) \oplus w,\ w \sim N(0, Q)`.

    .. math::

        \mu^+ = f(\mu, u), \qquad
        F = \frac{\partial}{\partial \delta}\, \mathrm{local}\big(\mu^+,
            f(\mathrm{retract}(\mu, \delta), u)\big)\Big|_{\delta=0}, \qquad
        P^+ = F P F^\top + Q \text{ (symmetrized)}

    ``f`` acts on **one unbatched state** and is vectorized over the batch with
    ``torch.func.vmap``; its Jacobian comes from ``torch.func.jacfwd``, so ``f`` must be
    written with composable torch ops (no in-place writes to its inputs, no ``.item()``).
    Gradients flow through the result to any tensor ``f`` closes over.

    Args:
        g: belief with mean ``(*B, n)`` on ``manifold`` and tangent covariance ``(*B, d, d)``.
        f: dynamics ``f(x)`` (if ``u`` is None) or ``f(x, u)``: ``x (n,)``, ``u (p,)`` →
            ``(n,)``, a point of the same manifold.
        u: ``(*B', p)`` inputs (controls), broadcast against the batch; None for ``f(x)``.
        Q: ``(*B', d, d)`` process noise covariance in the tangent space at the prediction.
        manifold: the state manifold (``EUCLIDEAN`` by default; ``SE2``, ``SE3`` for poses).

    Returns:
        The predicted Gaussian (batch: the broadcast of ``g``, ``u`` and ``Q``).
    """
    manifold = _check_manifold(manifold, "manifold")
    g, n, dim = _check_state(g, manifold)
    Q = check_tensor("Q", Q, event_shape=(dim, dim), like=g.mean)
    check_symmetric_psd("Q", Q)
    shapes = [("g", g.batch_shape), ("Q", Q.shape[:-2])]
    if u is not None:
        if not isinstance(u, Tensor) or u.ndim < 1:
            raise ValueError(f"u: expected a (*B, p) tensor, got {getattr(u, 'shape', u)!r}")
        u = check_tensor("u", u, event_shape=(u.shape[-1],), like=g.mean)
        shapes.append(("u", u.shape[:-1]))
    batch = broadcast_batch(shapes)
    x = g.mean.expand(*batch, n).reshape(-1, n)
    args = () if u is None else (u.expand(*batch, u.shape[-1]).reshape(-1, u.shape[-1]),)
    mean, F = _linearize(f, x, args, source=manifold, target=manifold, tangent_dim=dim)
    if mean.shape != x.shape:
        raise ValueError(f"f: must map a state ({n},) to ({n},), got {tuple(mean.shape[1:])}")
    if not all_finite_many(mean, F):
        raise ValueError("f: returned NaN or inf, or has a NaN or inf Jacobian, at g.mean")
    nb = len(batch)
    F = la.to_batch_last(F.reshape(*batch, dim, dim), 2, nb)
    P = la.to_batch_last(g.cov, 2, nb)
    cov = la.symmetrize(la.add_(la.mm_t(la.mm(F, P), F), la.to_batch_last(Q, 2, nb)))
    if not all_finite(cov.detach()):
        raise ValueError(
            f"f: the prediction F P Fᵀ + Q overflows {g.dtype} with f's Jacobian F (largest "
            f"|F| = {float(F.abs().max()):.3g}, |g.cov| = {float(g.cov.abs().max()):.3g})"
        )
    return unchecked_gaussian(
        mean.reshape(*batch, n), la.to_batch_first(cov.expand(dim, dim, *batch), 2)
    )


def ekf_update(
    g: Gaussian,
    y: Tensor,
    h: Measurement,
    *,
    R: Tensor,
    mask: Tensor | None = None,
    manifold: Manifold = EUCLIDEAN,
    measurement_manifold: Manifold = EUCLIDEAN,
) -> tuple[Gaussian, Tensor]:
    r"""EKF update with the measurement :math:`y = h(x) \oplus v,\ v \sim N(0, R)`.

    The update is a Kalman update of the tangent error :math:`\delta` (error-state form):

    .. math::

        r = \mathrm{local}_y\big(h(\mu), y\big), \quad
        H = \frac{\partial}{\partial \delta}\, \mathrm{local}_y\big(h(\mu),
            h(\mathrm{retract}(\mu, \delta))\big)\Big|_{\delta=0},

        \delta^+ = K r, \quad \mu^+ = \mathrm{retract}(\mu, \delta^+), \quad
        P^+ = (I - K H) P (I - K H)^\top + K R K^\top

    with :math:`S = H P H^\top + R`, :math:`K = P H^\top S^{-1}` (Cholesky solves) and the
    log-likelihood :math:`\log N(r; 0, S)`. The covariance is not transported by the Jacobian
    of the reset :math:`\mu \leftarrow \mathrm{retract}(\mu, \delta^+)` (identity
    approximation, standard in error-state filters; Solà 2017, §7.2).

    ``h`` acts on one unbatched state and is vectorized with ``torch.func.vmap``; its Jacobian
    comes from ``torch.func.jacfwd``. A measurement that is NaN in every component means "no
    measurement" (entry unchanged, log-likelihood 0); ``mask`` drops residual components
    exactly, as in :func:`~torchcontact.filters.kf_update`.

    Args:
        g: prior with mean ``(*B, n)`` on ``manifold``, tangent covariance ``(*B, d, d)``.
        y: ``(*B', m)`` measurement, a point of ``measurement_manifold``.
        h: measurement function ``h(x)``: ``(n,)`` → ``(m,)``.
        R: ``(*B', k, k)`` measurement noise covariance in the measurement tangent space
            (``k = m`` for a Euclidean measurement).
        mask: ``(*B', k)`` bool, ``True`` where a residual component is used; all if None.
        manifold: the state manifold.
        measurement_manifold: the measurement manifold (e.g. ``SE3`` for a camera pose).

    Returns:
        ``(posterior, log_likelihood (*B,))``.
    """
    manifold = _check_manifold(manifold, "manifold")
    measurement_manifold = _check_manifold(measurement_manifold, "measurement_manifold")
    g, n, dim = _check_state(g, manifold)
    if not isinstance(y, Tensor) or y.ndim < 1:
        raise ValueError(f"y: expected a (*B, m) tensor, got {getattr(y, 'shape', y)!r}")
    m = int(y.shape[-1])
    y = check_tensor("y", y, event_shape=(m,), like=g.mean, allow_nan=True)
    k = measurement_manifold.tangent_dim(m)
    R = check_tensor("R", R, event_shape=(k, k), like=g.mean)
    check_symmetric_psd("R", R)
    shapes = [("g", g.batch_shape), ("y", y.shape[:-1]), ("R", R.shape[:-2])]
    if mask is not None:
        mask = check_mask("mask", mask, size=k)
        shapes.append(("mask", mask.shape[:-1]))
    batch = broadcast_batch(shapes)
    nb = len(batch)
    x = g.mean.expand(*batch, n).reshape(-1, n)
    y_hat, H = _linearize(h, x, (), source=manifold, target=measurement_manifold, tangent_dim=dim)
    if y_hat.shape[1:] != (m,):
        raise ValueError(f"y: h(x) has shape {tuple(y_hat.shape[1:])}, y has ({m},)")
    if not all_finite_many(y_hat, H):
        # not "no measurement": that is a NaN y, never a NaN h(x)
        raise ValueError("h: returned NaN or inf, or has a NaN or inf Jacobian, at g.mean")
    y_flat = y.expand(*batch, m).reshape(-1, m)
    missing = torch.isnan(y_flat).all(-1, keepdim=True)
    residual = measurement_manifold.local(y_hat, torch.where(missing, y_hat, y_flat))
    residual = torch.where(missing, torch.nan, residual).reshape(*batch, k)
    observed = observed_components(residual, mask)
    delta, cov, log_lik = update_core(
        torch.zeros((dim, *batch), dtype=g.dtype, device=g.device),
        la.to_batch_last(g.cov, 2, nb),
        la.to_batch_last(residual, 1, nb),
        la.to_batch_last(H.reshape(*batch, k, dim), 2, nb),
        None,
        la.to_batch_last(R, 2, nb),
        None if observed is None else la.to_batch_last(observed, 1, nb),
    )
    if not all_finite_many(log_lik, delta, cov):
        raise update_failure(
            g.mean,
            g.cov,
            H.reshape(*batch, k, dim),
            R,
            finite_likelihood=all_finite(log_lik.detach()),
            measurement="h",
        )
    mean = manifold.retract(x, la.to_batch_first(delta, 1).reshape(-1, dim))
    if observed is not None:
        unchanged = ~observed.expand(*batch, k).reshape(-1, k).any(-1, keepdim=True)
        mean = torch.where(unchanged, x, mean)
    if not all_finite(mean.detach()):
        raise ValueError(f"g: the posterior mean overflows {g.dtype} (manifold.retract(μ, K r))")
    posterior = unchecked_gaussian(
        mean.reshape(*batch, n), la.to_batch_first(cov.expand(dim, dim, *batch), 2)
    )
    return posterior, log_lik.expand(batch)


def _check_state(g: Gaussian, manifold: Manifold) -> tuple[Gaussian, int, int]:
    """Validate ``g`` as a state on ``manifold``: returns it, its size ``n`` and tangent size."""
    g = check_gaussian(g, "g", euclidean=False)
    dim = manifold.tangent_dim(g.dim)
    if g.tangent_dim != dim:
        raise ValueError(
            f"g: cov must be ({dim}, {dim}) on this manifold, got {tuple(g.cov.shape)}"
        )
    return g, g.dim, dim
