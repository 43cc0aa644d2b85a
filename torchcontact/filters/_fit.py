"""Maximum-likelihood physical parameters from a filter's evidence, with standard errors."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

#: Relative step of the central differences of the gradient that give the curvature.
_CURVATURE_STEP = 1e-4
#: Curvature eigenvalues at most this share of the largest are flat (not identified).
_FLAT = 1e-8


@dataclass(frozen=True, eq=False)
class FitResult:
    """Estimates of :func:`fit_parameters`.

    Attributes:
        values: every parameter's estimate, a float64 scalar tensor, by name.
        standard_errors: every parameter's standard error (the square root of the diagonal of
            the inverse observed information, ``(−∇² log p)⁻¹``), ``nan`` where the curvature
            is not positive definite (the parameter is not identified by the data).
        log_evidence: ``log p(y | values)`` at the estimates.
        evaluations: number of evaluations of the evidence and its gradient (curvature
            included).
        converged: the gradient of ``log p`` in the optimizer's coordinates is below
            ``tolerance`` times ``max(1, |log p|)`` at the estimates.
    """

    values: dict[str, Tensor]
    standard_errors: dict[str, Tensor]
    log_evidence: Tensor
    evaluations: int
    converged: bool


def fit_parameters(
    log_evidence: Callable[[dict[str, Tensor]], Tensor],
    initial: Mapping[str, float],
    *,
    lower: Mapping[str, float] | None = None,
    max_iterations: int = 30,
    tolerance: float = 1e-6,
) -> FitResult:
    r"""Maximize a differentiable log-evidence over named scalar parameters.

    The parameters ``θ`` (friction coefficients, masses, noise scales) enter ``log_evidence``
    (typically: build a :class:`~torchcontact.filters.PlanarContactModel` of a scene with
    these values, run the :class:`~torchcontact.filters.RBPF` over recorded measurements and
    return ``belief.log_evidence.sum()``). A parameter with a lower bound ``ℓ`` is optimized
    as ``θ = ℓ + exp(u)``, so the bound holds at every step. L-BFGS with a strong-Wolfe line
    search (:class:`torch.optim.LBFGS`) runs on the unconstrained coordinates ``u``.

    The standard errors come from the observed information at the estimate,
    :math:`I = -\nabla^2_\theta \log p(y \mid \theta)`, each column by central differences
    of the exact gradient (relative step 1e-4). They are those of a maximum-likelihood
    estimate: they say how sharply the data pin a parameter down given the model, not how
    wrong the model is.

    Identifiability is the caller's business: with no known applied forces only ratios are
    identified (a mass scales gravity, friction and inertia alike); fit those the data
    determine, and a ``nan`` standard error flags a flat direction.

    Args:
        log_evidence: maps ``{name: float64 scalar tensor}`` to a scalar log-evidence,
            differentiable in the parameters.
        initial: starting value of every parameter (above its bound).
        lower: lower bounds by name (e.g. 0 for friction, masses); parameters not named are
            unbounded.
        max_iterations: L-BFGS iterations.
        tolerance: gradient tolerance of convergence, relative to ``max(1, |log p|)``.

    Returns:
        The :class:`FitResult`.

    Raises:
        ValueError: naming ``initial`` (empty, not finite, or not above its bound), ``lower``
            (a bound for an unknown parameter), ``max_iterations`` or ``tolerance``.
        RuntimeError: the evidence is not finite at the starting values.
    """
    if not initial:
        raise ValueError("initial: expected at least one parameter")
    bounds = dict(lower or {})
    unknown = set(bounds) - set(initial)
    if unknown:
        raise ValueError(f"lower: bounds for unknown parameters {sorted(unknown)}")
    for name, value in initial.items():
        if not math.isfinite(value):
            raise ValueError(f"initial: {name} must be finite, got {value!r}")
        if name in bounds and not value > bounds[name]:
            raise ValueError(f"initial: {name} = {value} must lie above its bound {bounds[name]}")
    if not isinstance(max_iterations, int) or max_iterations < 1:
        raise ValueError(f"max_iterations: expected an int >= 1, got {max_iterations!r}")
    if not tolerance > 0:
        raise ValueError(f"tolerance: expected > 0, got {tolerance!r}")

    names = list(initial)
    f64 = torch.float64

    def to_values(coordinates: Tensor) -> dict[str, Tensor]:
        return {
            name: bounds[name] + coordinates[i].exp() if name in bounds else coordinates[i]
            for i, name in enumerate(names)
        }

    start = [
        math.log(initial[name] - bounds[name]) if name in bounds else initial[name]
        for name in names
    ]
    coordinates = torch.tensor(start, dtype=f64, requires_grad=True)
    evaluations = 0

    def objective() -> Tensor:
        nonlocal evaluations
        evaluations += 1
        optimizer.zero_grad()
        value = log_evidence(to_values(coordinates))
        if not bool(torch.isfinite(value)):
            at = _floats(to_values(coordinates))
            raise RuntimeError(f"log_evidence is not finite ({float(value)}) at {at}")
        loss = -value
        loss.backward()
        return loss.detach()

    optimizer = torch.optim.LBFGS(
        [coordinates],
        lr=1.0,
        max_iter=max_iterations,
        tolerance_grad=1e-12,
        tolerance_change=1e-14,
        line_search_fn="strong_wolfe",
    )
    optimizer.step(objective)
    with torch.no_grad():
        estimate = {name: value.detach() for name, value in to_values(coordinates).items()}

    # Converged: the gradient in the optimizer's coordinates is below tolerance times the
    # evidence's own scale (a sum over many measurements has large gradients everywhere).
    at_estimate = log_evidence(estimate)
    final = _gradient(log_evidence, estimate) * torch.stack(
        [
            estimate[name] - bounds[name] if name in bounds else torch.ones((), dtype=f64)
            for name in names
        ]
    )
    scale = max(1.0, abs(float(at_estimate)))
    converged = bool(final.abs().max() <= tolerance * scale)
    evaluations += 2
    information, curvature_evaluations = _observed_information(log_evidence, estimate)
    evaluations += curvature_evaluations
    errors = _standard_errors(information)
    return FitResult(
        values=estimate,
        standard_errors={name: errors[i] for i, name in enumerate(names)},
        log_evidence=at_estimate.detach(),
        evaluations=evaluations,
        converged=converged,
    )


def _gradient(
    log_evidence: Callable[[dict[str, Tensor]], Tensor], values: dict[str, Tensor]
) -> Tensor:
    """``∇_θ log p`` at ``values``, ``(P,)``."""
    leaves = {name: value.detach().clone().requires_grad_(True) for name, value in values.items()}
    grads = torch.autograd.grad(log_evidence(leaves), list(leaves.values()))
    return torch.stack(grads)


def _observed_information(
    log_evidence: Callable[[dict[str, Tensor]], Tensor], values: dict[str, Tensor]
) -> tuple[Tensor, int]:
    """``(P, P)`` symmetric ``−∇² log p`` by central differences of the gradient, and the
    number of evaluations."""
    names = list(values)
    columns = []
    for name in names:
        step = _CURVATURE_STEP * max(1.0, abs(float(values[name])))
        ahead = {**values, name: values[name] + step}
        behind = {**values, name: values[name] - step}
        columns.append(
            -(_gradient(log_evidence, ahead) - _gradient(log_evidence, behind)) / (2 * step)
        )
    information = torch.stack(columns, dim=-1)
    return 0.5 * (information + information.mT), 2 * len(names)


def _standard_errors(information: Tensor) -> Tensor:
    """Square roots of the diagonal of ``information⁻¹``; ``nan`` for parameters that move
    along a flat or downward direction (an eigenvalue at most ``_FLAT`` times the largest)."""
    eigenvalues, vectors = torch.linalg.eigh(information)
    largest = float(eigenvalues.abs().max())
    flat = eigenvalues <= _FLAT * largest
    if largest == 0.0:
        return torch.full((information.shape[0],), math.nan, dtype=information.dtype)
    safe = torch.where(flat, 1.0, eigenvalues)
    variance = (vectors.square() / safe).masked_fill(flat, 0.0).sum(-1)
    unidentified = (vectors.square().masked_fill(~flat, 0.0).sum(-1)) > _FLAT
    return torch.where(unidentified, math.nan, variance.sqrt())


def _floats(values: Mapping[str, Tensor]) -> dict[str, float]:
    return {name: float(value) for name, value in values.items()}
