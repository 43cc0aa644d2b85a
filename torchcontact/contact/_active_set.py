"""A batched active-set iteration on contact modes, built on the mode-decoupled solve."""

from __future__ import annotations

import torch
from torch import Tensor

from torchcontact.contact._lcp import (
    SEPARATED,
    SLIDING,
    STICKING,
    consistent_with_mode,
    default_tolerance,
    friction_pair,
    is_face_sliding,
    is_sliding,
    velocity_terms,
)
from torchcontact.contact._mode_solve import solve_mode_unchecked, validate_mode
from torchcontact.contact._problem import ContactProblem
from torchcontact.contact._solution import Solution, SolveStatus

#: Share of the largest slip above which a sticking slot of an unsolved system starts sliding.
STRAINED_SHARE = 0.01


def update_mode(problem: ContactProblem, solution: Solution) -> Tensor:
    """One active-set correction of the modes of a mode-decoupled solution.

    Each slot whose solution violates its own mode switches to the mode that removes the
    violation: a separated slot that penetrates (gap rate < 0) starts sticking (a planar one
    that slips there: sliding against its slip); an active slot
    that pulls (``pn < 0``) separates; a sticking slot whose friction leaves the cone slides
    with its friction where it was (on the face of the two directions that carried it, or
    along the one direction); a sliding slot whose slip turned along its friction starts
    sticking. Where the linear solve did not converge (contradicting equalities, as a rigid
    finger with fewer joints than rows sticking to a held box), the sticking slots that
    slip most (at least 1 % of the largest slip among them) slide against that slip. When
    spatial, a slot sliding along an edge ``d`` whose slip is more opposed to
    a neighbouring direction moves to the face between the two, and a slot sliding on a face
    whose friction turned negative along one of its directions slides along the other.

    Args:
        problem: the contact problem.
        solution: a solution of ``problem`` at ``solution.mode`` (from :func:`solve_mode`).

    Returns:
        ``(*B, K)`` long corrected modes.
    """
    tol = 10 * default_tolerance(problem.dtype)
    D = problem.num_directions
    gap_rate, slip = velocity_terms(problem, solution.v_next)
    mode, pn, pt = solution.mode, solution.pn, solution.pt
    scale_v = 1.0 + gap_rate.abs().amax(dim=-1, keepdim=True)
    scale_p = 1.0 + pn.abs().amax(dim=-1, keepdim=True)
    first, second = friction_pair(mode, num_directions=D)
    slip_first = slip.gather(-1, first.unsqueeze(-1)).squeeze(-1)
    largest = pt.argmax(dim=-1)

    penetrates = (mode == SEPARATED) & (gap_rate < -tol * scale_v)
    pulls = (mode >= STICKING) & (pn < -tol * scale_p)
    outside_cone = (mode == STICKING) & (pt.sum(-1) > problem.mu * pn + tol * scale_p)
    reverses = is_sliding(mode) & (slip_first > tol * scale_v)
    leaving = SLIDING + largest
    closing = torch.full_like(mode, STICKING)
    if D == 2:
        # A planar slot that closes while it slips starts sliding against its slip (a box
        # landing or starting to slide on two corners; from sticking its active set cycled).
        # Spatial slots keep sticking: four coplanar corners sliding make the mode solve's
        # system singular, where the derivative of its split is not yet the limit's.
        slips = slip.abs().amax(dim=-1) > tol * scale_v
        closing = torch.where(slips, SLIDING + slip.argmin(dim=-1), closing)
    updated = torch.where(penetrates, closing, mode)
    if D > 2:
        # Sticking friction is written on two adjacent directions: keep it on their face.
        beside = torch.stack([(largest - 1) % D, (largest + 1) % D], dim=-1)
        pt_beside = pt.gather(-1, beside)
        neighbour = pt_beside.argmax(dim=-1)
        carried = pt_beside.amax(dim=-1) > tol * scale_p
        face_start = torch.where(neighbour == 0, beside[..., 0], largest)
        leaving = torch.where(carried, SLIDING + D + face_start, leaving)
        # An edge whose slip opposes a neighbour more: the face towards that neighbour.
        edge = is_sliding(mode) & ~is_face_sliding(mode, num_directions=D)
        slip_beside = slip.gather(-1, torch.stack([(first - 1) % D, (first + 1) % D], dim=-1))
        towards = slip_beside.argmin(dim=-1)
        turned = edge & (slip_beside.amin(dim=-1) < slip_first - tol * scale_v)
        face_start = torch.where(towards == 0, (first - 1) % D, first)
        updated = torch.where(turned, SLIDING + D + face_start, updated)
        # A face whose friction is negative along one direction: the edge of the other.
        face = is_face_sliding(mode, num_directions=D)
        pt_pair = pt.gather(-1, torch.stack([first, second], dim=-1))
        negative = face & (pt_pair.amin(dim=-1) < -tol * scale_p)
        other = torch.where(pt_pair[..., 0] < pt_pair[..., 1], second, first)
        updated = torch.where(negative, SLIDING + other, updated)
    updated = torch.where(outside_cone, leaving, updated)
    stuck = (mode == STICKING) & ~solution.status.converged.unsqueeze(-1)
    slip_size = slip.abs().amax(dim=-1)
    largest_slip = torch.where(stuck, slip_size, 0.0).amax(dim=-1, keepdim=True)
    strained = stuck & (slip_size > tol * scale_v) & (slip_size >= STRAINED_SHARE * largest_slip)
    updated = torch.where(strained, SLIDING + slip.argmin(dim=-1), updated)
    updated = torch.where(reverses, STICKING, updated)
    updated = torch.where(pulls, SEPARATED, updated)
    return torch.where(problem.slot_mask, updated, SEPARATED)


def solve_active_set(problem: ContactProblem, mode: Tensor, *, max_iterations: int = 4) -> Solution:
    """Solve from a mode guess by alternating :func:`solve_mode` and :func:`update_mode`.

    Each iteration is one batched linear solve of the whole batch; a problem stops changing as
    soon as its solution is consistent with its modes. Like any active-set method on an LCP it
    can cycle, so it is a fast path, not a reference: ``status.converged`` is ``True`` only for
    consistent solutions, and the rest should go to an exact solver.

    Args:
        problem: the contact problem, batch ``*B``.
        mode: ``(*B, K)`` initial mode guess (e.g. the previous time step's modes).
        max_iterations: limit on mode corrections.

    Returns:
        The last :class:`Solution` of each problem, differentiable through its final modes.
    """
    mode = validate_mode(problem, mode)
    batch = problem.batch_shape
    flat = problem.flatten()
    tolerance = 10 * default_tolerance(problem.dtype)

    def consistent(problem: ContactProblem, solution: Solution) -> Tensor:
        return consistent_with_mode(
            problem,
            v_next=solution.v_next,
            pn=solution.pn,
            pt=solution.pt,
            mode=solution.mode,
            atol=tolerance,
        )

    solution = solve_mode_unchecked(flat, mode.reshape(flat.slot_mask.shape))
    done = consistent(flat, solution) & solution.status.converged
    iterations = torch.ones(done.shape, dtype=torch.long, device=problem.device)
    for _ in range(max_iterations):
        pending = torch.nonzero(~done).squeeze(-1)
        if pending.numel() == 0:
            break
        subset = flat[pending]
        previous = solution.map_tensors(lambda t, index=pending: t[index])
        candidate = solve_mode_unchecked(subset, update_mode(subset, previous))
        solved = consistent(subset, candidate) & candidate.status.converged
        solution = solution.scatter(pending, candidate)
        done = done.index_put((pending,), solved)
        iterations = iterations.index_add(0, pending, torch.ones_like(pending))
    status = SolveStatus(converged=done, residual=solution.status.residual, iterations=iterations)
    result = Solution(
        v_next=solution.v_next, pn=solution.pn, pt=solution.pt, mode=solution.mode, status=status
    )
    return result.map_tensors(lambda t: t.reshape((*batch, *t.shape[1:])))
