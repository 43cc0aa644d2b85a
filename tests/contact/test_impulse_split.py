"""redistribute_impulses: another split of a redundant contact set's impulse.

References: Lemke's exact solutions (a consistent split exists: the one Lemke found), moved
along the null space of the contact rows' transpose (the same generalized impulse, hence the
same step) until they violate their modes; and single contacts, whose impulse is unique.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch
from torch import Tensor

from tests.contact.spatial import random_spatial_problems
from torchcontact.contact import (
    SEPARATED,
    ContactProblem,
    Solution,
    is_consistent,
    redistribute_impulses,
    solve_lemke,
    solve_mode_unchecked,
)

ATOL = 0.05


def _generalized_impulse(problem: ContactProblem, pn: Tensor, pt: Tensor) -> Tensor:
    """``(*B, n)``: Jnᵀ pn + Jtᵀ pt."""
    normal = (problem.Jn * pn[..., None]).sum(-2)
    return normal + (problem.Jt * pt[..., None]).sum((-3, -2))


def _pulling_split(problem: ContactProblem, solution: Solution) -> tuple[Tensor, Tensor, Tensor]:
    """Per problem, the exact solution's impulses moved along the null vector of the rows of
    its touching slots with the largest normal part, until some normal impulse is -1 (the same
    generalized impulse); and ``(B,)`` bool, the rows have such a vector (redundant normals)."""
    pn, pt = solution.pn.clone(), solution.pt.clone()
    K, D = problem.num_slots, problem.num_directions
    redundant = torch.zeros(pn.shape[0], dtype=torch.bool)
    for b in range(pn.shape[0]):
        touching = (solution.mode[b] != SEPARATED) & problem.slot_mask[b]
        rows = torch.cat([problem.Jn[b], problem.Jt[b].reshape(K * D, -1)])  # (K + K·D, n)
        keep = torch.cat([touching, touching.repeat_interleave(D)])
        transposed = rows[keep].T  # (n, r)
        null = torch.linalg.svd(transposed).Vh[torch.linalg.matrix_rank(transposed) :]
        normal_part = null[:, : int(touching.sum())]  # the touching slots' normal columns
        if null.shape[0] == 0 or torch.linalg.matrix_norm(normal_part, ord=2) < 1e-3:
            continue
        weights = torch.linalg.svd(normal_part).U[:, 0]
        direction = torch.zeros(K + K * D, dtype=pn.dtype)
        direction[keep] = weights @ null
        s = int(direction[:K].abs().argmax())
        step = (-1.0 - pn[b, s]) / direction[s]
        pn[b] += step * direction[:K]
        pt[b] += step * direction[K:].reshape(K, D)
        redundant[b] = True
    return pn, pt, redundant


def test_a_pulling_split_of_an_exact_solution_is_redistributed_to_a_consistent_one() -> None:
    problem = random_spatial_problems(5, count=300, directions=4, slots=4, dofs=3)
    exact = solve_lemke(problem)
    # Exact solutions with at least two touching slots: 3 DOFs, at least 2 + 2·4 rows.
    touching = ((exact.mode != SEPARATED) & problem.slot_mask).sum(-1)
    chosen = (exact.status.converged & (touching >= 2)).nonzero().squeeze(-1)
    problem, exact = problem[chosen], exact.map_tensors(lambda t: t[chosen])
    assert bool(is_consistent(problem, exact, atol=ATOL).all())
    pn, pt, redundant = _pulling_split(problem, exact)
    assert int(redundant.sum()) >= 20
    problem, exact = problem[redundant], exact.map_tensors(lambda t: t[redundant])
    pn, pt = pn[redundant], pt[redundant]
    moved = dataclasses.replace(exact, pn=pn, pt=pt)
    torch.testing.assert_close(
        _generalized_impulse(problem, pn, pt),
        _generalized_impulse(problem, exact.pn, exact.pt),
        rtol=0.0,
        atol=1e-9,
    )
    assert not bool(is_consistent(problem, moved, atol=ATOL).any())

    split = redistribute_impulses(problem, moved, atol=ATOL)

    assert bool(is_consistent(problem, split, atol=ATOL).all())
    # The same step: the generalized impulse kept to the LP's feasibility tolerance (1e-7
    # of the impulse scale, here impulses of order 1), the velocity and modes untouched.
    torch.testing.assert_close(
        _generalized_impulse(problem, split.pn, split.pt),
        _generalized_impulse(problem, exact.pn, exact.pt),
        rtol=0.0,
        atol=1e-6,
    )
    assert split.v_next is moved.v_next
    assert split.mode is moved.mode


def test_a_single_contact_that_pulls_keeps_its_unique_impulse() -> None:
    # One slot, eight DOFs: its normal row is independent of its friction rows, so the
    # generalized impulse fixes pn; a sticking contact that must pull has no consistent split.
    problem = random_spatial_problems(3, count=300, directions=4, slots=1, dofs=8)
    sticking = torch.ones((*problem.batch_shape, 1), dtype=torch.long)
    solution = solve_mode_unchecked(problem, sticking)
    pulling = (solution.pn[:, 0] < -0.1) & solution.status.converged
    assert int(pulling.sum()) >= 10
    problem = problem[pulling]
    solution = solution.map_tensors(lambda t: t[pulling])

    split = redistribute_impulses(problem, solution, atol=ATOL)

    assert not bool(is_consistent(problem, split, atol=ATOL).any())
    torch.testing.assert_close(split.pn, solution.pn, rtol=0.0, atol=1e-12)


def test_bad_tolerance_is_a_value_error() -> None:
    problem = random_spatial_problems(0, count=2, directions=4)
    solution = solve_lemke(problem)
    with pytest.raises(ValueError, match="atol"):
        redistribute_impulses(problem, solution, atol=0.0)
