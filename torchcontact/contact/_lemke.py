"""Lemke's complementary pivoting with lexicographic degeneracy resolution (the exact reference)."""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
import torch
from numpy.typing import NDArray

from torchcontact._checks import check_int
from torchcontact.contact._lcp import default_tolerance
from torchcontact.contact._per_problem import solve_one_by_one
from torchcontact.contact._problem import ContactProblem
from torchcontact.contact._solution import Solution

FloatArray = NDArray[np.float64]


class LemkeOutcome(Enum):
    """How a run of Lemke's algorithm ended."""

    SOLVED = "solved"
    RAY = "secondary ray"
    MAX_PIVOTS = "pivot limit"


@dataclass(frozen=True)
class LemkeResult:
    """Result of :func:`lemke` on one LCP ``w = A z + q, 0 ≤ z ⊥ w ≥ 0``.

    Attributes:
        z: ``(N,)`` solution (meaningful only when ``outcome`` is ``SOLVED``).
        w: ``(N,)`` ``A z + q``.
        outcome: how the pivoting ended.
        pivots: number of pivots taken.
    """

    z: FloatArray
    w: FloatArray
    outcome: LemkeOutcome
    pivots: int


def lemke(A: FloatArray, q: FloatArray, *, max_pivots: int | None = None) -> LemkeResult:
    """Solve the LCP ``w = A z + q, z ≥ 0, w ≥ 0, zᵀw = 0`` by Lemke's method.

    The covering vector is ``e = 1``. Ties in the ratio test are broken lexicographically,
    which is equivalent to perturbing ``q`` by ``(ε, ε², …)``: the basis never cycles and the
    method ends on a solution whenever ``A`` is copositive-plus and the LCP is feasible, even
    for degenerate problems (a box resting on two corners) where a plain ratio test can stop
    on a secondary ray. The final basis is re-solved against the original data, so the answer
    carries no accumulated pivoting error.

    Args:
        A: ``(N, N)`` LCP matrix.
        q: ``(N,)`` LCP vector.
        max_pivots: pivot limit; default ``50 N + 100``.

    Returns:
        The :class:`LemkeResult`.

    References:
        C. E. Lemke, "Bimatrix equilibrium points and mathematical programming",
        Management Science 11(7), 1965. K. G. Murty, *Linear Complementarity, Linear and
        Nonlinear Programming*, 1988, ch. 2 (lexico-minimum ratio rule).
    """
    N = q.shape[0]
    if q.size == 0 or q.min() >= 0.0:
        z = np.zeros(N)
        return LemkeResult(z=z, w=q.copy(), outcome=LemkeOutcome.SOLVED, pivots=0)
    limit = 50 * N + 100 if max_pivots is None else max_pivots
    # Tableau columns: w (N) | z (N) | z0 (1). The w-columns hold the basis inverse, which
    # supplies the lexicographic tie-breaking rows.
    original = np.hstack([np.eye(N), -A, -np.ones((N, 1))])
    tableau = original.copy()
    rhs = q.astype(np.float64).copy()
    basis = np.arange(N)
    z0 = 2 * N
    # Tolerances follow the entries that drive the pivoting: a large positive q (a slack that
    # never leaves the basis, e.g. a contact far away) must not loosen the ratio tests.
    scale = 1.0 + np.abs(A).max() + float(-q.min())
    pivot_tol = 1e-12 * scale

    entering = z0
    rows = np.arange(N)
    column = np.ones(N)  # first step: x_B = rhs + e z0, leave at the lexico-most-negative row
    pivots = 0
    while pivots < limit:
        if pivots > 0:
            column = tableau[:, entering]
            rows = np.flatnonzero(column > pivot_tol)
            if rows.size == 0:
                return _finish(original, q, A, basis, LemkeOutcome.RAY, pivots)
        ratios = np.column_stack([rhs[rows], tableau[rows, :N]]) / column[rows, None]
        row = _lexicographic_argmin(ratios, rows, basis, z0, scale)
        leaving = basis[row]
        _pivot(tableau, rhs, row, entering)
        basis[row] = entering
        pivots += 1
        if leaving == z0:
            return _finish(original, q, A, basis, LemkeOutcome.SOLVED, pivots)
        entering = leaving + N if leaving < N else leaving - N
    return _finish(original, q, A, basis, LemkeOutcome.MAX_PIVOTS, pivots)


def _lexicographic_argmin(
    ratios: FloatArray, rows: NDArray[np.int_], basis: NDArray[np.int_], z0: int, scale: float
) -> int:
    """Row of the lexicographically smallest ratio row, preferring ``z0`` on a first-column tie."""
    candidates = np.arange(rows.size)
    tol = 1e-11 * scale
    first = ratios[:, 0]
    candidates = candidates[first <= first.min() + tol]
    z0_rows = candidates[basis[rows[candidates]] == z0]
    if z0_rows.size:
        return int(rows[z0_rows[0]])
    for column in range(1, ratios.shape[1]):
        if candidates.size == 1:
            break
        values = ratios[candidates, column]
        candidates = candidates[values <= values.min() + tol]
    return int(rows[candidates[0]])


def _pivot(tableau: FloatArray, rhs: FloatArray, row: int, column: int) -> None:
    """Gauss–Jordan pivot of the tableau on ``(row, column)``, in place."""
    pivot = tableau[row, column]
    tableau[row] /= pivot
    rhs[row] /= pivot
    factors = tableau[:, column].copy()
    factors[row] = 0.0
    tableau -= np.outer(factors, tableau[row])
    rhs -= factors * rhs[row]


def _finish(
    original: FloatArray,
    q: FloatArray,
    A: FloatArray,
    basis: NDArray[np.int_],
    outcome: LemkeOutcome,
    pivots: int,
) -> LemkeResult:
    """Re-solve the final basis against the original tableau and read off ``z``."""
    N = q.shape[0]
    try:
        values = np.linalg.solve(original[:, basis], q)
    except np.linalg.LinAlgError:
        outcome = LemkeOutcome.RAY if outcome is LemkeOutcome.SOLVED else outcome
        values = np.zeros(N)
    z = np.zeros(N)
    is_z = (basis >= N) & (basis < 2 * N)
    z[basis[is_z] - N] = values[is_z]
    return LemkeResult(z=z, w=A @ z + q, outcome=outcome, pivots=pivots)


def solve_lemke(problem: ContactProblem, *, max_pivots: int | None = None) -> Solution:
    """Solve every problem of the batch exactly with :func:`lemke` (float64, one by one).

    The Stewart–Trinkle LCP in ``z = [pn; pt; σ]`` over the real (unmasked) slots is

        ``A = [[Wnn, Wnt, 0], [Wtn, Wtt, E], [diag μ, −Eᵀ, 0]]``,
        ``q = [Jn v_free + bn + φ/h; Jt v_free + bt; 0]``

    with ``W = J M⁻¹ Jᵀ``. Problems are converted to float64 for the pivoting and the answer
    is returned in the problem's dtype. Each LCP is pivoted in units that make its data of
    order one, so the pivot tolerances, and the answer, do not depend on the units of ``h``,
    ``M`` and ``v``.

    Args:
        problem: the contact problem, batch ``*B``.
        max_pivots: pivot limit per problem (default ``50 N + 100``).

    Returns:
        The :class:`Solution`; ``status.converged`` is ``False`` where Lemke stopped on a ray or
        the pivot limit, or where the result's scale-invariant residual
        (:func:`~torchcontact.contact.relative_residual`) exceeds the float64 tolerance.
    """

    if max_pivots is not None:
        check_int("max_pivots", max_pivots, low=1)

    def solve_one(
        W: FloatArray, q: FloatArray, mu: FloatArray, D: int
    ) -> tuple[FloatArray, bool, int]:
        result = lemke(*_stewart_trinkle(W, q, mu, D), max_pivots=max_pivots)
        return result.z[: q.size], result.outcome is LemkeOutcome.SOLVED, result.pivots

    return solve_one_by_one(
        problem,
        solve_one,
        tolerance=default_tolerance(torch.float64),
        mode_atol=None,
        normalize=True,
    )


def _stewart_trinkle(
    W: FloatArray, q_contact: FloatArray, mu: FloatArray, D: int
) -> tuple[FloatArray, FloatArray]:
    """Assemble the Stewart–Trinkle LCP ``(A, q)`` of size ``K + K·D + K`` from ``W`` and ``q``."""
    K = mu.shape[0]
    E = np.kron(np.eye(K), np.ones((D, 1)))
    size = K + K * D + K
    A = np.zeros((size, size))
    A[: K + K * D, : K + K * D] = W
    A[K : K + K * D, K + K * D :] = E
    A[K + K * D :, :K] = np.diag(mu)
    A[K + K * D :, K : K + K * D] = -E.T
    q = np.concatenate([q_contact, np.zeros(K)])
    return A, q
