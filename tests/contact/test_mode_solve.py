"""solve_mode: differentiability, batching, dtypes and its validation."""

from __future__ import annotations

import pytest
import torch

from tests.contact.boxes import box_problem, resting_state
from torchcontact.contact import (
    SLIDING,
    STICKING,
    ContactProblem,
    solve,
    solve_mode,
    solve_mode_unchecked,
)


def _pushed_box() -> ContactProblem:
    q, v = resting_state()
    v[0] = 0.3
    return box_problem(
        q=q,
        v=v,
        mu=0.5,
        force=torch.tensor([3.0, 0.0], dtype=torch.float64),
        force_point=(-0.5, 0.1),
    )


@pytest.mark.parametrize(
    ("mode", "unique_split"),
    [
        ([SLIDING + 1, SLIDING + 1], True),
        ([STICKING, STICKING], False),
        ([0, STICKING], True),
        ([SLIDING + 1, 0], True),
    ],
)
def test_gradcheck_with_respect_to_every_input(mode: list[int], unique_split: bool) -> None:
    """Gradients match finite differences; two sticking corners share identical friction rows,
    so their friction split is not a function of the inputs and only v⁺, pn are checked."""
    base = _pushed_box()
    mode_t = torch.tensor(mode)
    phi0 = torch.tensor([0.001, 0.002], dtype=torch.float64)

    def step(v, f, phi, mu, Jn, Jt_half):
        problem = ContactProblem(
            M=base.M,
            v=v,
            f=f,
            Jn=Jn,
            Jt=torch.cat([Jt_half, -Jt_half], dim=-2),
            phi=phi,
            mu=mu,
            h=base.h,
        )
        solution = solve_mode(problem, mode_t)
        if unique_split:
            return solution.v_next, solution.pn, solution.pt
        return solution.v_next, solution.pn

    inputs = (
        base.v.clone(),
        base.f.clone(),
        phi0,
        base.mu.clone(),
        base.Jn.clone(),
        base.Jt[..., :1, :].clone(),
    )
    inputs = tuple(t.requires_grad_(True) for t in inputs)
    assert torch.autograd.gradcheck(step, inputs, eps=1e-6, atol=1e-7)


def test_batched_equals_looped_and_float32_matches_float64() -> None:
    gen = torch.Generator().manual_seed(3)
    q, v = resting_state((16,))
    v = v + 0.5 * torch.randn(16, 3, generator=gen, dtype=torch.float64)
    v[:, 1] = 0.0
    problem = box_problem(
        q=q, v=v, mu=0.6, force=torch.randn(16, 2, generator=gen, dtype=torch.float64)
    )
    mode = solve(problem, "lemke").mode
    batched = solve_mode(problem, mode)
    # A batch and a single problem may take different LAPACK kernels. The velocity is unique
    # (to ~100 ulps here); the normal impulses of a resting box's redundant corners are split
    # by the regularised second pass, which converges to ~1e-10 relative, not to the ulp.
    for index in range(16):
        single = solve_mode(problem[index], mode[index])
        torch.testing.assert_close(single.v_next, batched.v_next[index], atol=1e-14, rtol=1e-13)
        torch.testing.assert_close(single.pn, batched.pn[index], atol=1e-12, rtol=1e-9)
    as_float = solve_mode(problem.to(torch.float32), mode)
    assert as_float.v_next.dtype == torch.float32
    torch.testing.assert_close(as_float.v_next.double(), batched.v_next, atol=1e-5, rtol=0)
    assert bool(as_float.status.converged.all())


def test_batch_shape_is_preserved_and_padding_slots_carry_nothing() -> None:
    q, v = resting_state((2, 3))
    problem = box_problem(q=q, v=v, corners=(0, 1, 2))
    masked = ContactProblem(
        M=problem.M,
        v=problem.v,
        f=problem.f,
        Jn=problem.Jn,
        Jt=problem.Jt,
        phi=problem.phi,
        mu=problem.mu,
        h=problem.h,
        mask=torch.tensor([True, True, False]),
    )
    mode = torch.tensor([STICKING, STICKING, STICKING])  # the padding slot's mode is ignored
    solution = solve_mode(masked, mode)
    assert solution.v_next.shape == (2, 3, 3)
    assert solution.mode[..., 2].eq(0).all()
    assert solution.pn[..., 2].eq(0).all()
    assert solution.pt[..., 2, :].eq(0).all()
    torch.testing.assert_close(
        solution.pn.sum(-1), torch.full((2, 3), 2.0 * 9.81 * 0.01, dtype=torch.float64)
    )


def test_wrong_mode_is_reported_by_the_residual_not_hidden() -> None:
    """Forcing a sliding box to stick solves the linear system but violates the friction cone."""
    problem = _pushed_box()
    right = solve(problem, "lemke")
    wrong = solve_mode(problem, torch.tensor([STICKING, STICKING]))
    assert right.status.residual.item() < 1e-12
    assert bool(wrong.status.converged)  # the linear system itself was solved
    assert wrong.status.residual.item() > 1e-3


@pytest.mark.parametrize(
    ("mode", "message"),
    [
        (torch.tensor([0.0, 1.0]), "integer"),
        (torch.tensor([0, 5]), r"\[0, 4\)"),
        (torch.tensor([0, 1, 1]), "shape"),
    ],
)
def test_bad_mode_raises(mode: torch.Tensor, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        solve_mode(_pushed_box(), mode)


def test_initial_impulses_keep_a_known_split_of_redundant_contacts() -> None:
    """Two sticking corners share identical friction rows: the split is free, v⁺ is not."""
    q, v = resting_state()
    problem = box_problem(q=q, v=v, force=torch.tensor([2.0, 0.0], dtype=torch.float64))
    exact = solve(problem, "lemke")
    assert exact.mode.tolist() == [STICKING, STICKING]
    own = solve_mode(problem, exact.mode)
    anchored = solve_mode(problem, exact.mode, initial_impulses=(exact.pn, exact.pt))
    torch.testing.assert_close(own.v_next, exact.v_next, atol=1e-12, rtol=0)
    torch.testing.assert_close(anchored.pt, exact.pt, atol=1e-10, rtol=0)
    torch.testing.assert_close(anchored.pn, exact.pn, atol=1e-10, rtol=0)
    # Without the anchor, friction is shared in proportion to the normal load.
    share = own.pt[:, 0] / own.pn
    torch.testing.assert_close(share[0], share[1], atol=1e-9, rtol=0)


@pytest.mark.parametrize("sync_free", [False, True])
def test_unchecked_solve_reproduces_lemke_at_its_modes(sync_free: bool) -> None:
    """``solve_mode_unchecked`` (either way of running the friction split) at Lemke's modes
    returns Lemke's end velocity: unique, so 1e-9 of the velocity scale whatever the split of
    redundant corners; the batch mixes sticking, sliding and separating boxes."""
    gen = torch.Generator().manual_seed(11)
    q, v = resting_state((24,))
    v = v + 0.8 * torch.randn(24, 3, generator=gen, dtype=torch.float64)
    v[:, 1] = v[:, 1].clamp(max=0.0)
    problem = box_problem(
        q=q, v=v, mu=0.4, force=3.0 * torch.randn(24, 2, generator=gen, dtype=torch.float64)
    )
    exact = solve(problem, "lemke")
    assert bool(exact.status.converged.all())
    modes = torch.bincount(exact.mode.flatten(), minlength=4)
    assert bool((modes > 0).all()), modes  # every mode occurs in the batch
    unchecked = solve_mode_unchecked(problem, exact.mode, sync_free=sync_free)
    scale = float(exact.v_next.abs().max())
    torch.testing.assert_close(unchecked.v_next, exact.v_next, atol=1e-9 * scale, rtol=0)
    assert bool(unchecked.status.converged.all())
