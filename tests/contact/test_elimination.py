"""The written-out elimination of the compiled simulator step against NumPy's LAPACK solve and
the closed-form limit of iterated Tikhonov regularisation."""

from __future__ import annotations

import numpy as np
import torch

from torchcontact.contact._tikhonov import solve_by_elimination, tikhonov_by_elimination

F64 = torch.float64


def test_elimination_solves_systems_that_need_row_exchanges() -> None:
    """Matrices with a zero (then a tiny) leading entry, so that every column's pivot is
    found by an exchange, against ``numpy.linalg.solve``; the right-hand sides broadcast
    over the batch. The matrices are permutations of diagonally dominant ones (cond < 10),
    so the two solves agree to rounding (1e-12)."""
    gen = torch.Generator().manual_seed(0)
    m = 7
    dominant = torch.randn(5, m, m, generator=gen, dtype=F64) / m + 2.0 * torch.eye(m, dtype=F64)
    reverse = torch.arange(m - 1, -1, -1)
    matrices = dominant[:, reverse]  # anti-diagonal dominant: the (0, 0) entry is small
    matrices[0, 0, 0] = 0.0
    matrices[1, 0, 0] = 1e-300
    rhs = torch.randn(m, 3, generator=gen, dtype=F64)
    solution = solve_by_elimination(matrices, rhs)
    reference = np.linalg.solve(matrices.numpy(), np.broadcast_to(rhs.numpy(), (5, m, 3)))
    torch.testing.assert_close(solution, torch.from_numpy(reference), rtol=0.0, atol=1e-12)


def test_singular_pivot_gives_non_finite_entries() -> None:
    """A singular matrix is not solved silently: its solution is not finite."""
    matrices = torch.tensor([[[1.0, 2.0], [2.0, 4.0]]], dtype=F64)
    solution = solve_by_elimination(matrices, torch.ones(1, 2, 1, dtype=F64))
    assert not bool(torch.isfinite(solution).all())


def test_tikhonov_by_elimination_reaches_the_weighted_least_norm_solution() -> None:
    """A consistent singular system (``A = B Bᵀ`` of rank 3, order 6, the redundant rows of a
    resting contact): iterated Tikhonov from zero converges to the solution of least
    ``xᵀ S x``, ``x = S^{-1/2} (A S^{-1/2})⁺ b`` (NumPy's pseudo-inverse). The shifts are
    1e-3 of the nonzero eigenvalues (at least 0.5 here), so each iteration shrinks the error
    by 1e-3 or more and 8 iterations leave rounding only (1e-10 of the solution's size, as the
    regularised matrix has condition ~1e4)."""
    gen = torch.Generator().manual_seed(1)
    basis = torch.linalg.qr(torch.randn(4, 6, 3, generator=gen, dtype=F64)).Q
    A = basis @ torch.diag_embed(0.5 + torch.rand(4, 3, generator=gen, dtype=F64)) @ basis.mT
    shift = 1e-3 * (0.5 + torch.rand(4, 6, generator=gen, dtype=F64))
    b = A @ torch.randn(4, 6, 1, generator=gen, dtype=F64)
    x = tikhonov_by_elimination(A, shift, b, refinements=8)
    root = shift.sqrt().numpy()[..., None, :]
    scaled_pinv = np.linalg.pinv(A.numpy() / root, rcond=1e-10)
    reference = torch.from_numpy(scaled_pinv @ b.numpy() / root.swapaxes(-1, -2))
    torch.testing.assert_close(x, reference, rtol=0.0, atol=1e-10 * float(reference.abs().max()))
