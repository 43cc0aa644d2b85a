"""Contact problems and their solvers.

The Stewart–Trinkle contact step (:class:`ContactProblem`) is solved exactly by Lemke's method,
by OSQP with staggered projections, by batched projected Gauss–Seidel, or, with the contact
mode known, by one differentiable linear solve (:func:`solve_mode`). That solve's kernel
(:func:`tikhonov_system`, :func:`iterated_tikhonov`), its friction-split weights
(:func:`friction_split_weights`) and the settings of its regularisation
(``SOLVE_MODE_REFINEMENTS``, ``SOLVE_MODE_WEIGHTED_REFINEMENTS``,
``SOLVE_MODE_FRICTION_COST``, ``SOLVE_MODE_MIN_LOAD_SHARE``) are exported for the code that
differentiates it in closed form, the filters' per-mode linearization.

The contact mode of a slot is an integer: ``SEPARATED`` (0), ``STICKING`` (1), ``SLIDING + d``
(sliding with the friction impulse along friction direction ``d``, an edge of the friction
cone) and, when spatial (``D >= 4``), ``SLIDING + D + d`` (sliding with it on the face between
directions ``d`` and ``(d + 1) mod D``), so that every solution of the LCP has a mode that
:func:`solve_mode` reproduces and :func:`is_consistent` accepts. Planar problems have the
codes 0–3 only (:func:`num_modes`).
"""

from torchcontact.contact._active_set import solve_active_set, update_mode
from torchcontact.contact._examples import BOX_CORNER_SIGNS, planar_box_problem
from torchcontact.contact._impulse_split import redistribute_impulses
from torchcontact.contact._lcp import (
    SEPARATED,
    SLIDING,
    STICKING,
    consistent_with_mode,
    contact_mode,
    default_tolerance,
    delassus,
    friction_direction,
    is_consistent,
    is_face_sliding,
    is_sliding,
    lcp_residual,
    num_modes,
    relative_residual,
)
from torchcontact.contact._lemke import LemkeOutcome, LemkeResult, lemke, solve_lemke
from torchcontact.contact._mode_solve import (
    SOLVE_MODE_FRICTION_COST,
    SOLVE_MODE_MIN_LOAD_SHARE,
    SOLVE_MODE_REFINEMENTS,
    SOLVE_MODE_WEIGHTED_REFINEMENTS,
    friction_split_weights,
    solve_mode,
    solve_mode_unchecked,
)
from torchcontact.contact._pgs import project_capped_simplex, solve_pgs
from torchcontact.contact._problem import ContactProblem
from torchcontact.contact._qp import solve_qp
from torchcontact.contact._solution import Solution, SolveStatus
from torchcontact.contact._solve import Method, solve
from torchcontact.contact._tikhonov import TikhonovSystem, iterated_tikhonov, tikhonov_system

__all__ = [
    "BOX_CORNER_SIGNS",
    "SEPARATED",
    "SLIDING",
    "SOLVE_MODE_FRICTION_COST",
    "SOLVE_MODE_MIN_LOAD_SHARE",
    "SOLVE_MODE_REFINEMENTS",
    "SOLVE_MODE_WEIGHTED_REFINEMENTS",
    "STICKING",
    "ContactProblem",
    "LemkeOutcome",
    "LemkeResult",
    "Method",
    "Solution",
    "SolveStatus",
    "TikhonovSystem",
    "consistent_with_mode",
    "contact_mode",
    "default_tolerance",
    "delassus",
    "friction_direction",
    "friction_split_weights",
    "is_consistent",
    "is_face_sliding",
    "is_sliding",
    "iterated_tikhonov",
    "lcp_residual",
    "lemke",
    "num_modes",
    "planar_box_problem",
    "project_capped_simplex",
    "redistribute_impulses",
    "relative_residual",
    "solve",
    "solve_active_set",
    "solve_lemke",
    "solve_mode",
    "solve_mode_unchecked",
    "solve_pgs",
    "solve_qp",
    "tikhonov_system",
    "update_mode",
]
