"""Iterated Tikhonov regularisation: the linear solve inside the mode-decoupled contact step."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor


@dataclass(frozen=True, eq=False)
class TikhonovSystem:
    r"""A square system ``A x = b`` prepared for iterated Tikhonov regularisation.

    The iteration ``(A + S) x_{i+1} = b + S x_i`` with ``S = diag(s)``, ``s > 0``, converges
    to the solution when ``A`` is nonsingular and, when ``A`` is singular but the system
    consistent, to the solution of least ``(x − x_0)ᵀ S (x − x_0)`` (the error along the null
    space never moves from the start, and shrinks by ``s / (λ + s)`` per iteration along an
    eigenvalue ``λ``). Each iteration is the affine map ``x ↦ y + R x`` with
    ``y = (A + S)⁻¹ b`` and ``R = (A + S)⁻¹ S``; ``R`` comes from one LU solve of ``A + S``
    (with ``S`` as the right-hand side, never an inverse), after which every iteration and
    every further right-hand side is a matrix product.

    References:
        A. N. Tikhonov and V. Y. Arsenin, "Solutions of Ill-Posed Problems", Winston, 1977
        (iterated regularisation: ch. 2); H. W. Engl, M. Hanke and A. Neubauer,
        "Regularization of Inverse Problems", Kluwer, 1996, sec. 5.1.

    Attributes:
        LU: ``(*B, m, m)`` LU factors of ``A + S`` (``torch.linalg.lu_factor``).
        pivots: ``(*B, m)`` their pivots.
        R: ``(*B, m, m)`` the iteration matrix ``(A + S)⁻¹ S``.
    """

    LU: Tensor
    pivots: Tensor
    R: Tensor


def tikhonov_system(A: Tensor, shift: Tensor) -> TikhonovSystem:
    """Factor ``A + diag(shift)`` and form the iteration matrix.

    Args:
        A: ``(*B, m, m)`` system matrices.
        shift: ``(*B, m)`` positive diagonal ``s`` of the regularisation ``S``.

    Returns:
        The :class:`TikhonovSystem`.
    """
    regularised = A + torch.diag_embed(shift)
    LU, pivots = torch.linalg.lu_factor(regularised)
    R = torch.linalg.lu_solve(LU, pivots, torch.diag_embed(shift))
    return TikhonovSystem(LU=LU, pivots=pivots, R=R)


def iterated_tikhonov(
    system: TikhonovSystem, b: Tensor, *, refinements: int, start: Tensor | None = None
) -> Tensor:
    """Run ``refinements`` iterations of :class:`TikhonovSystem` from ``start``.

    A linear operator on ``b`` (for ``start = None``), differentiable in the system and
    ``b``.

    Args:
        system: the prepared system, batch ``*B``.
        b: ``(*B', m, r)`` right-hand sides as columns (``*B'`` broadcasts against ``*B``).
        refinements: number of iterations, ``>= 1``.
        start: ``(*B', m, r)`` starting point ``x_0`` (a constant: detached), default zeros.

    Returns:
        ``(*B'', m, r)`` the iterate ``x_refinements``.
    """
    y: Tensor = torch.linalg.lu_solve(system.LU, system.pivots, b)
    x = y if start is None else y + system.R @ start.detach()
    for _ in range(refinements - 1):
        x = y + system.R @ x
    return x
