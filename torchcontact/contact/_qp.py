"""The QP-based fallback: OSQP through qpsolvers, with staggered projections for friction."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from numpy.typing import NDArray

from torchcontact._checks import check_int, check_positive
from torchcontact.contact._lcp import default_tolerance
from torchcontact.contact._per_problem import solve_one_by_one
from torchcontact.contact._problem import ContactProblem
from torchcontact.contact._solution import Solution

if TYPE_CHECKING:
    import scipy.sparse as sp

FloatArray = NDArray[np.float64]

#: OSQP settings tight enough for the staggered projections to match Lemke to 1e-6.
OSQP_SETTINGS: dict[str, Any] = {
    "eps_abs": 1e-12,
    "eps_rel": 1e-12,
    "eps_prim_inf": 1e-14,
    "eps_dual_inf": 1e-14,
    "max_iter": 200_000,
    "polishing": False,
    "raise_error": False,
}


def solve_qp(problem: ContactProblem, *, max_rounds: int = 500, tol: float = 1e-11) -> Solution:
    r"""Solve every problem of the batch with convex QPs (OSQP), one by one.

    Frictionless slots reduce the LCP to one convex QP in the normal impulses,

    .. math:: \min_{p_n \ge 0} \tfrac12 p_n^\top W_{nn} p_n + p_n^\top q_n,

    whose optimality conditions are exactly the complementarity conditions. With friction the
    LCP is not a convex QP, so the method of *staggered projections* alternates two convex
    QPs until the impulses stop changing: the normal QP above with the friction impulse held
    fixed (``q_n + W_{nt} p_t``), and the maximal-dissipation friction QP with the normal
    impulse held fixed,

    .. math:: \min_{p_t \ge 0,\ E^\top p_t \le \mu p_n} \tfrac12 p_t^\top W_{tt} p_t
              + p_t^\top (q_t + W_{tn} p_n),

    whose multiplier of the cone constraint is the sliding speed σ. A fixed point satisfies
    the full Stewart–Trinkle LCP; unlike Anitescu's convex relaxation it does not let a
    sliding body lift off.

    Args:
        problem: the contact problem, batch ``*B``.
        max_rounds: limit on normal/friction projection rounds per problem.
        tol: stop when the impulses change by less than ``tol × (1 + max|p|)`` in a round.

    Returns:
        The :class:`Solution`; ``status.converged`` is ``False`` where OSQP failed, the rounds
        did not settle, or the LCP residual exceeds the float64 tolerance.

    References:
        D. M. Kaufman, S. Sueda, D. L. James and D. K. Pai, "Staggered projections for
        frictional contact in multibody systems", ACM TOG 27(5), 2008.
        B. Stellato et al., "OSQP: an operator splitting solver for quadratic programs",
        Math. Prog. Comp. 12, 2020.
    """

    check_int("max_rounds", max_rounds, low=1)
    check_positive("tol", tol)

    def solve_one(
        W: FloatArray, q: FloatArray, mu: FloatArray, D: int
    ) -> tuple[FloatArray, bool, int]:
        pn, pt, ok, rounds = _staggered_projections(W, q, mu, D, max_rounds=max_rounds, tol=tol)
        return np.concatenate([pn, pt]), ok, rounds

    # OSQP meets its constraints to ~1e-12, so the residual test is looser than Lemke's.
    return solve_one_by_one(
        problem, solve_one, tolerance=1e3 * default_tolerance(torch.float64), mode_atol=1e-7
    )


def _staggered_projections(
    W: FloatArray, q: FloatArray, mu: FloatArray, D: int, *, max_rounds: int, tol: float
) -> tuple[FloatArray, FloatArray, bool, int]:
    """Alternate the normal and friction QPs of one problem until the impulses settle.

    Args:
        W: ``(K + K·D, K + K·D)`` Delassus matrix of the real slots.
        q: ``(K + K·D,)`` free constraint velocities.
        mu: ``(K,)`` friction coefficients.
        D: friction directions per contact.
        max_rounds: round limit.
        tol: relative change that ends the rounds.

    Returns:
        ``pn (K,)``, ``pt (K·D,)``, whether every QP succeeded and the rounds settled, rounds.
    """
    K = mu.shape[0]
    if K == 0:
        return np.zeros(0), np.zeros(0), True, 0
    Wnn, Wnt = W[:K, :K], W[:K, K:]
    Wtn, Wtt = W[K:, :K], W[K:, K:]
    qn, qt = q[:K], q[K:]
    pn, pt = np.zeros(K), np.zeros(K * D)
    frictional = bool(mu.max() > 0)
    import scipy.sparse as sp  # the QP fallback's own dependencies load when it is used

    cone = sp.csc_matrix(np.kron(np.eye(K), np.ones((1, D))))
    for round_index in range(1, max_rounds + 1):
        pn_new = _nonnegative_qp(Wnn, qn + Wnt @ pt, start=pn)
        if pn_new is None:
            return pn, pt, False, round_index
        if not frictional:
            return pn_new, pt, True, round_index
        pt_new = _nonnegative_qp(Wtt, qt + Wtn @ pn_new, start=pt, G=cone, h=mu * pn_new)
        if pt_new is None:
            return pn_new, pt, False, round_index
        change = max(np.abs(pn_new - pn).max(), np.abs(pt_new - pt).max())
        pn, pt = pn_new, pt_new
        size = 1.0 + max(np.abs(pn).max(), np.abs(pt).max())
        if change <= tol * size:
            return pn, pt, True, round_index
    return pn, pt, False, max_rounds


def _nonnegative_qp(
    P: FloatArray,
    c: FloatArray,
    *,
    start: FloatArray,
    G: sp.csc_matrix | None = None,
    h: FloatArray | None = None,
) -> FloatArray | None:
    """``argmin ½ xᵀPx + cᵀx`` s.t. ``x ≥ 0`` (and ``G x ≤ h``) with OSQP, warm-started at
    ``start``; ``None`` on failure."""
    import scipy.sparse as sp
    from qpsolvers import Problem, solve_problem

    size = c.shape[0]
    P_sym = sp.csc_matrix(0.5 * (P + P.T))
    qp = Problem(P_sym, c, G=G, h=h, lb=np.zeros(size), ub=np.full(size, np.inf))
    result = solve_problem(qp, solver="osqp", initvals=start, verbose=False, **OSQP_SETTINGS)
    if not result.found or result.x is None:
        return None
    # OSQP meets bounds only to its tolerance; impulses are projected onto them exactly.
    x: FloatArray = np.maximum(np.asarray(result.x, dtype=np.float64), 0.0)
    return x
