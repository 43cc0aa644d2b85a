"""One entry point for the contact solvers."""

from __future__ import annotations

from typing import Any, Literal

from torchcontact.contact._lemke import solve_lemke
from torchcontact.contact._pgs import solve_pgs
from torchcontact.contact._problem import ContactProblem
from torchcontact.contact._qp import solve_qp
from torchcontact.contact._solution import Solution

Method = Literal["lemke", "qp", "pgs"]


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
        ValueError: if ``method`` is not one of the three.
    """
    if not isinstance(problem, ContactProblem):
        raise ValueError(f"problem must be a ContactProblem, got {type(problem).__name__}")
    if method == "lemke":
        return solve_lemke(problem, **options)
    if method == "qp":
        return solve_qp(problem, **options)
    if method == "pgs":
        return solve_pgs(problem, **options)
    raise ValueError(f"method must be 'lemke', 'qp' or 'pgs', got {method!r}")
