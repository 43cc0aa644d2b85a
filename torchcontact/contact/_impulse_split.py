"""Redundant contacts: another split of the same generalized impulse among the contacts.

Where a body is held by more contact rows than it has degrees of freedom (a box grasped by
three sticking fingers of a kinematic hand, a box on four coplanar corners), the rows fix the
step's velocity but not how the impulse is shared among them: every :math:`(p_n', p_t')`
with

.. math::

    J_n^\\top p_n' + J_t^\\top p_t' = J_n^\\top p_n + J_t^\\top p_t

moves the bodies alike. A mode solve returns one split (:func:`solve_mode` picks the one of
least norm), which may pull at a contact or leave a sticking contact's cone although another
split of the same impulse satisfies the mode. :func:`redistribute_impulses` looks for such a
split, a linear feasibility problem per problem (HiGHS through :func:`scipy.optimize.linprog`),
so that a consistency check judges the mode, not the solver's choice among equal steps.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from torchcontact._checks import check_positive
from torchcontact.contact._lcp import (
    SEPARATED,
    STICKING,
    _scales,
    check_solution,
    friction_pair,
    is_face_sliding,
    mode_conditions,
    velocity_terms,
)
from torchcontact.contact._problem import ContactProblem
from torchcontact.contact._solution import Solution


def redistribute_impulses(problem: ContactProblem, solution: Solution, *, atol: float) -> Solution:
    """``solution`` with its impulses replaced, where its velocities satisfy its modes but its
    impulses do not, by a split of the same generalized impulse that satisfies them, where one
    exists (see the module docstring).

    The velocity ``v_next``, the modes and the status are kept. The split sought has
    non-negative impulses, none at separated or padding slots, a sticking slot's friction
    inside its polyhedral cone (:math:`\\sum_d p_{t,d} \\le \\mu p_n`), a sliding slot's on
    the cone's boundary along its direction or directions (:math:`\\sum p_{t,d} = \\mu p_n`
    over those, zero along the others); the cone conditions with half of the check's
    tolerance ``atol`` relative to a lower bound of its impulse scale at any split (that of
    :func:`is_consistent` without the impulses: the momentum change and the problem's
    floor), the generalized impulse to HiGHS's feasibility tolerance in units of that
    scale. Problems whose velocities already violate their modes, or whose impulses satisfy
    them, are not touched.

    Args:
        problem: the contact problem, batch ``*B``.
        solution: a solution of it (``v_next``, ``pn``, ``pt``, ``mode``), e.g. from
            :func:`solve_mode_unchecked`.
        atol: the relative tolerance of the consistency check that will judge the result.

    Returns:
        The solution with ``pn (*B, K)`` and ``pt (*B, K, D)`` redistributed where a
        consistent split was found.

    Raises:
        ValueError: ``problem`` or ``solution`` is not one, their shapes or dtypes differ, or
            ``atol`` is not positive.
    """
    check_solution(problem, solution)
    check_positive("atol", atol)
    v_next, pn, pt, mode = solution.v_next, solution.pn, solution.pt, solution.mode
    velocity_ok, impulse_ok = mode_conditions(
        problem, v_next=v_next, pn=pn, pt=pt, mode=mode, atol=atol
    )
    wanted = velocity_ok.all(-1) & ~impulse_ok.all(-1)
    if not bool(wanted.any()):
        return solution
    # The check's impulse scale without the impulses' own magnitudes (the momentum change and
    # the problem's floor): a lower bound of the scale at any split of the same impulse.
    gap_rate, slip = velocity_terms(problem, v_next)
    _, impulse_scale = _scales(
        problem,
        v_next=v_next,
        pn=torch.zeros_like(pn),
        pt=torch.zeros_like(pt),
        gap_rate=gap_rate,
        slip=slip,
        v_free=None,
    )
    index = wanted.nonzero(as_tuple=True)
    mode = mode.expand(pn.shape)
    first, second = friction_pair(mode, num_directions=problem.num_directions)
    face = is_face_sliding(mode, num_directions=problem.num_directions)
    fields = [
        problem.Jn[index],
        problem.Jt[index],
        problem.mu.expand(pn.shape)[index],
        problem.slot_mask[index],
        pn[index],
        pt[index],
        mode[index],
        first[index],
        second[index],
        face[index],
        impulse_scale[index][..., 0],
    ]
    arrays = [field.detach().cpu().numpy() for field in fields]
    new_pn, new_pt = pn.clone(), pt.clone()
    for row, values in enumerate(zip(*arrays, strict=True)):
        split = _feasible_split(*values, tolerance=0.5 * atol)
        if split is None:
            continue
        at = tuple(i[row] for i in index)
        new_pn[at] = torch.as_tensor(split[0], dtype=pn.dtype, device=pn.device)
        new_pt[at] = torch.as_tensor(split[1], dtype=pt.dtype, device=pt.device)
    return dataclasses.replace(solution, pn=new_pn, pt=new_pt)


def _feasible_split(
    Jn: np.ndarray,
    Jt: np.ndarray,
    mu: np.ndarray,
    mask: np.ndarray,
    pn: np.ndarray,
    pt: np.ndarray,
    mode: np.ndarray,
    first: np.ndarray,
    second: np.ndarray,
    face: np.ndarray,
    scale: float,
    *,
    tolerance: float,
) -> tuple[np.ndarray, np.ndarray] | None:
    """One problem's split ``(pn (K,), pt (K, D))`` of the impulse of ``pn, pt`` that
    satisfies the modes, or None if there is none (see :func:`redistribute_impulses`).

    The unknowns are the impulses in units of ``scale``: ``K`` normal, then ``K·D``
    friction (slot-major).
    """
    # imported here: the contact solvers load without scipy (tests/test_imports.py)
    from scipy.optimize import linprog

    K, D, n = Jt.shape
    rows = np.concatenate([Jn, Jt.reshape(K * D, n)], axis=0)  # (K + K·D, n)
    target = (Jn.T @ pn + Jt.reshape(K * D, n).T @ pt.reshape(-1)) / scale
    upper: list[float | None] = [None] * (K + K * D)
    fixed = ~mask | (mode == SEPARATED)
    inequality = []
    for slot in range(K):
        friction = K + slot * D + np.arange(D)
        if fixed[slot]:
            upper[slot] = 0.0
            for column in friction:
                upper[column] = 0.0
            continue
        cone = np.zeros(K + K * D)
        if mode[slot] == STICKING:
            cone[friction] = 1.0
            cone[slot] = -mu[slot]
            inequality.append(cone)
            continue
        carried = {int(first[slot]), int(second[slot]) if face[slot] else int(first[slot])}
        for direction in range(D):
            if direction in carried:
                cone[K + slot * D + direction] = 1.0
            else:
                upper[K + slot * D + direction] = 0.0
        cone[slot] = -mu[slot]
        inequality.extend([cone, -cone])
    bounds = [(0.0, bound) for bound in upper]
    result = linprog(
        np.zeros(K + K * D),
        A_ub=np.stack(inequality) if inequality else None,
        b_ub=np.full(len(inequality), tolerance) if inequality else None,
        A_eq=rows.T,
        b_eq=target,
        bounds=bounds,
        method="highs",
    )
    if result.status != 0:
        return None
    split = result.x * scale
    return split[:K], split[K:].reshape(K, D)
