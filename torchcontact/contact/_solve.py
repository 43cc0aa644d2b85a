"""One entry point for the contact solvers."""

from __future__ import annotations

from typing import Any, Literal

from torchcontact.contact._lemke import solve_lemke
from torchcontact.contact._pgs import solve_pgs
from torchcontact.contact._problem import ContactProblem
from torchcontact.contact._qp import solve_qp
from torchcontact.contact._solution import Solution

Method = Literal["lemke", "qp", "pgs"]

#: The keyword options of each method's solver.
_OPTIONS = {
    "lemke": ("max_pivots",),
    "qp": ("max_rounds", "tol"),
    "pgs": ("max_sweeps", "tol", "check_every"),
}


def solve(problem: ContactProblem, method: Method = "lemke", **options: Any) -> Solution:
    """Solve a batch of contact problems.

    Args:
        problem: the contact problem, batch ``*B``.
        method: ``"lemke"`` (exact pivoting, the reference; :func:`solve_lemke`), ``"qp"``
            (OSQP with staggered projections; :func:`solve_qp`) or ``"pgs"`` (batched
            projected Gauss–Seidel; :func:`solve_pgs`).
        **options: keyword options of the chosen solver.

    Returns:
        The :class:`Solution`, with a per-problem status: check ``status.converged``.

    Raises:
        ValueError: if ``method`` is not one of the three, or an option is not one of its
            solver's (or is out of range).
    """
    if not isinstance(problem, ContactProblem):
        raise ValueError(f"problem must be a ContactProblem, got {type(problem).__name__}")
    if not isinstance(method, str) or method not in _OPTIONS:
        raise ValueError(f"method must be 'lemke', 'qp' or 'pgs', got {method!r}")
    unknown = sorted(set(options) - set(_OPTIONS[method]))
    if unknown:
        raise ValueError(
            f"options: {method!r} takes {', '.join(_OPTIONS[method])}, got unknown {unknown}"
        )
    if method == "lemke":
        return solve_lemke(problem, **options)
    if method == "qp":
        return solve_qp(problem, **options)
    return solve_pgs(problem, **options)
