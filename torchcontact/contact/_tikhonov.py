"""Iterated Tikhonov regularisation: the linear solve inside the mode-decoupled contact step."""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import torch
from torch import Tensor

#: Batch size from which :func:`iterated_tikhonov` stops at a relative rather than a bitwise
#: fixed point (below it, the cheaper bitwise test is reached and costs fewer operations).
SETTLED_MIN_BATCH = 64

#: Order from which :func:`tikhonov_system` factors a CPU batch one matrix at a time. torch
#: 2.13 factors a CPU batch concurrently over its matrices, and MKL's getrf, run concurrently
#: on matrices of about 150 rows or more, returns pivots outside ``[1, m]`` while reporting
#: success, or never returns (seen with two threads; right with one thread or one matrix a
#: call, where getrf may still thread inside itself). Set with a 2x margin below the
#: smallest failing order seen, as that order may differ between CPUs; at this order the loop
#: costs about 1.5x the batched factorization (one thread), and nothing below it.
LU_SEQUENTIAL_MIN_ORDER = 64


#: Largest order that :func:`tikhonov_by_elimination` is meant for: its code grows with the
#: cube of the order (every column's elimination is written out).
ELIMINATION_MAX_ORDER = 16


@dataclass(frozen=True, eq=False)
class TikhonovSystem:
    r"""A square system ``A x = b`` prepared for iterated Tikhonov regularisation.

    The iteration ``(A + S) x_{i+1} = b + S x_i`` with ``S = diag(s)``, ``s > 0``, converges
    to the solution when ``A`` is nonsingular and, when ``A`` is singular but the system
    consistent, to the solution of least ``(x − x_0)ᵀ S (x − x_0)`` (the error along the null
    space never moves from the start, and shrinks by ``s / (λ + s)`` per iteration along an
    eigenvalue ``λ``). ``A + S`` is LU-factored once; every iteration, for every right-hand
    side, is one pair of triangular solves with those factors (never an inverse). Where the
    calls cost more than the arithmetic (small batches, compiled code), the iteration matrix
    ``R = (A + S)⁻¹ S`` can be formed once by one more solve with ``S`` as the right-hand
    side, after which an iteration is the affine map ``x ↦ y + R x``, a matrix product;
    on large batches of small systems the triangular solves are cheaper than the products.

    References:
        A. N. Tikhonov and V. Y. Arsenin, "Solutions of Ill-Posed Problems", Winston, 1977
        (iterated regularisation: ch. 2); H. W. Engl, M. Hanke and A. Neubauer,
        "Regularization of Inverse Problems", Kluwer, 1996, sec. 5.1.

    Attributes:
        LU: ``(*B, m, m)`` LU factors of ``A + S`` (``torch.linalg.lu_factor``).
        pivots: ``(*B, m)`` their pivots.
        shift: ``(*B, m, 1)`` the diagonal ``s`` of ``S``, as a column.
        R: ``(*B, m, m)`` the iteration matrix, or ``None`` where the iterations solve.
    """

    LU: Tensor
    pivots: Tensor
    shift: Tensor
    R: Tensor | None


def tikhonov_system(A: Tensor, shift: Tensor, *, products: bool = False) -> TikhonovSystem:
    """Factor ``A + diag(shift)``.

    Args:
        A: ``(*B, m, m)`` system matrices.
        shift: ``(*B, m)`` positive diagonal ``s`` of the regularisation ``S``.
        products: also form the iteration matrix ``R``, so that iterations are products.

    Returns:
        The :class:`TikhonovSystem`.
    """
    regularised = _regularised(A, shift)
    LU, pivots = _lu_factor(regularised)
    R = torch.linalg.lu_solve(LU, pivots, torch.diag_embed(shift)) if products else None
    return TikhonovSystem(LU=LU, pivots=pivots, shift=shift.unsqueeze(-1), R=R)


def _regularised(A: Tensor, shift: Tensor) -> Tensor:
    """``A + diag(shift)`` for ``A (*B, m, m)`` and ``shift (*B', m)`` (batches broadcast),
    written on a copy's diagonal (no ``(m, m)`` temporary for ``diag(shift)``)."""
    m = A.shape[-1]
    batch = torch.broadcast_shapes(A.shape[:-2], shift.shape[:-1])
    regularised = A.expand(*batch, m, m).clone()
    regularised.diagonal(dim1=-2, dim2=-1).add_(shift)
    return regularised


def _lu_factor(matrices: Tensor) -> tuple[Tensor, Tensor]:
    """``torch.linalg.lu_factor`` of ``matrices (*B, m, m)``, right with any thread count.

    CPU batches of order at least :data:`LU_SEQUENTIAL_MIN_ORDER` are factored one matrix a
    call (the batched call runs MKL's getrf concurrently, which fails at large orders);
    differentiable like the batched call.

    Returns:
        ``(*B, m, m)`` LU factors and ``(*B, m)`` pivots.
    """
    m = matrices.shape[-1]
    batch = matrices.shape[:-2]
    if matrices.device.type != "cpu" or m < LU_SEQUENTIAL_MIN_ORDER or batch.numel() <= 1:
        LU, pivots = torch.linalg.lu_factor(matrices)
        return LU, pivots
    factors = [torch.linalg.lu_factor(matrix) for matrix in matrices.reshape(-1, m, m)]
    LU = torch.stack([factor for factor, _ in factors]).reshape(matrices.shape)
    pivots = torch.stack([pivot for _, pivot in factors]).reshape(*batch, m)
    return LU, pivots


def iterated_tikhonov(
    system: TikhonovSystem,
    b: Tensor,
    *,
    refinements: int,
    start: Tensor | None = None,
    stop_at_fixed_point: bool = False,
) -> Tensor:
    """Run ``refinements`` iterations of :class:`TikhonovSystem` from ``start``.

    A linear operator on ``b`` (for ``start = None``), differentiable in the system and
    ``b``.

    Args:
        system: the prepared system, batch ``*B``.
        b: ``(*B', m, r)`` right-hand sides as columns (``*B'`` broadcasts against ``*B``).
        refinements: number of iterations, ``>= 1``.
        start: ``(*B', m, r)`` starting point ``x_0`` (a constant: detached), default zeros.
        stop_at_fixed_point: stop as soon as an iteration returns its input exactly (every
            later one would too) or, in batches of at least :data:`SETTLED_MIN_BATCH`
            problems, which almost never reach bitwise equality all at once, as soon as it
            moves no entry by more than ``eps^(3/4)`` times the largest entry of its problem
            (the iterates then agree with the limit to rounding, up to the contraction of
            the slowest direction; later iterations only exchange rounding errors); at the
            price of one host synchronisation per iteration, and only where no gradient is
            recorded (the derivative's iterates converge on their own).

    Returns:
        ``(*B'', m, r)`` the iterate ``x_refinements``.
    """
    LU, pivots, shift, R = system.LU, system.pivots, system.shift, system.R
    if R is not None:
        y: Tensor = torch.linalg.lu_solve(LU, pivots, b)
        x = y if start is None else y + R @ start.detach()
        for _ in range(refinements - 1):
            x = y + R @ x
        return x
    x = cast(
        Tensor,
        torch.linalg.lu_solve(
            LU, pivots, b if start is None else torch.addcmul(b, shift, start.detach())
        ),
    )
    stop = stop_at_fixed_point and not (
        torch.is_grad_enabled() and (b.requires_grad or LU.requires_grad)
    )
    relative = x.shape[:-2].numel() >= SETTLED_MIN_BATCH and x.shape[-2:].numel() > 0
    for _ in range(refinements - 1):
        previous, x = x, torch.linalg.lu_solve(LU, pivots, torch.addcmul(b, shift, x))
        if stop and bool(_settled(x, previous) if relative else (x == previous).all()):
            break
    return x


def _settled(x: Tensor, previous: Tensor) -> Tensor:
    """No entry of ``x (*B, m, r)`` (non-empty) moved from ``previous`` by more than
    ``eps^(3/4)`` times the largest entry of its problem."""
    size = x.abs().amax(dim=(-2, -1), keepdim=True)
    resolution = torch.finfo(x.dtype).eps ** 0.75
    return torch.le((x - previous).abs(), resolution * size).all()


def solve_by_elimination(matrices: Tensor, rhs: Tensor) -> Tensor:
    """Solve ``matrices X = rhs`` by Gaussian elimination with partial pivoting, written out.

    The elimination runs column by column with every operation on the whole batch (a row
    exchange is a gather, an elimination step a broadcast update), then back substitution
    row by row: under :func:`torch.compile` it fuses into a few loops over the batch, where
    ``torch.linalg.lu_factor`` and ``lu_solve`` stay library calls (one per call). The
    arithmetic is LAPACK's ``getrf`` + ``getrs`` on the augmented matrix: backward stable.
    For small orders (up to :data:`ELIMINATION_MAX_ORDER`): the code grows with the cube of
    the order. A zero pivot (a singular matrix) gives non-finite entries.

    Args:
        matrices: ``(*B, m, m)`` nonsingular matrices.
        rhs: ``(*B', m, r)`` right-hand sides (``*B'`` broadcasts against ``*B``).

    Returns:
        ``(*B'', m, r)`` the solutions.
    """
    m, r = matrices.shape[-1], rhs.shape[-1]
    batch = torch.broadcast_shapes(matrices.shape[:-2], rhs.shape[:-2])
    augmented = torch.cat(
        [matrices.expand(*batch, m, m), rhs.expand(*batch, m, r)], dim=-1
    )  # (*B'', m, m + r)
    rows = torch.arange(m, device=matrices.device)
    for k in range(m):
        pivot = augmented[..., k:, k].abs().argmax(dim=-1, keepdim=True) + k  # (*B'', 1)
        exchange = torch.where(rows == k, pivot, torch.where(rows == pivot, k, rows))
        augmented = augmented.gather(-2, exchange.unsqueeze(-1).expand(augmented.shape))
        head = augmented[..., k : k + 1, :]
        factor = augmented[..., k : k + 1] / head[..., k : k + 1]  # (*B'', m, 1)
        factor = torch.where((rows > k).unsqueeze(-1), factor, torch.zeros_like(factor))
        augmented = augmented - factor * head
    solution: list[Tensor] = []  # rows m - 1, m - 2, ..., 0
    for k in reversed(range(m)):
        row = augmented[..., k, m:]
        for j, known in zip(range(m - 1, k, -1), solution, strict=True):
            row = row - augmented[..., k, j : j + 1] * known
        solution.append(row / augmented[..., k, k : k + 1])
    return torch.stack(solution[::-1], dim=-2)


def tikhonov_by_elimination(
    A: Tensor, shift: Tensor, b: Tensor, *, refinements: int, start: Tensor | None = None
) -> Tensor:
    """:func:`iterated_tikhonov` of ``A + diag(shift)`` in the product form, every solve by
    :func:`solve_by_elimination` (no library call: for compiled code on small systems).

    ``y = (A + S)⁻¹ b`` and ``R = (A + S)⁻¹ S`` come from one elimination with ``[b, S]`` as
    the right-hand side; each iteration is ``x ↦ y + R x``. All ``refinements`` run.

    Args:
        A: ``(*B, m, m)`` system matrices, ``m <= ELIMINATION_MAX_ORDER``.
        shift: ``(*B, m)`` positive diagonal ``s`` of the regularisation ``S``.
        b: ``(*B, m, 1)`` right-hand sides as a column.
        refinements: number of iterations, ``>= 1``.
        start: ``(*B, m, 1)`` starting point ``x_0`` (a constant: detached), default zeros.

    Returns:
        ``(*B, m, 1)`` the iterate ``x_refinements``.
    """
    regularised = _regularised(A, shift)
    m = regularised.shape[-1]
    batch = torch.broadcast_shapes(regularised.shape[:-2], b.shape[:-2])
    rhs = torch.cat([b.expand(*batch, m, 1), torch.diag_embed(shift).expand(*batch, m, m)], dim=-1)
    solved = solve_by_elimination(regularised, rhs)
    y, R = solved[..., :1], solved[..., 1:]

    def step(x: Tensor) -> Tensor:
        # R x as a broadcast product and a sum, which compiles into the surrounding loop.
        return y + (R * x.transpose(-1, -2)).sum(dim=-1, keepdim=True)

    x = y if start is None else step(start.detach())
    for _ in range(refinements - 1):
        x = step(x)
    return x
