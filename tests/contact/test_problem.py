"""ContactProblem validation: every bad field is named."""

from __future__ import annotations

import math

import pytest
import torch

from tests.contact.boxes import box_problem, resting_state
from torchcontact.contact import (
    ContactProblem,
    is_consistent,
    lcp_residual,
    planar_box_problem,
    solve,
)


def _fields() -> dict:
    q, v = resting_state()
    problem = box_problem(q=q, v=v)
    return {name: getattr(problem, name) for name in ("M", "v", "f", "Jn", "Jt", "phi", "mu", "h")}


def _replace(name: str, value) -> dict:
    fields = _fields()
    fields[name] = value
    return fields


@pytest.mark.parametrize(
    ("name", "make", "message"),
    [
        ("M", lambda f: f["M"][:2, :2], "Jn must have shape"),
        (
            "M",
            lambda f: torch.diag(torch.tensor([1.0, -1.0, 1.0], dtype=torch.float64)),
            "M must be positive definite",
        ),
        (
            "M",
            lambda f: f["M"] + torch.triu(torch.ones(3, 3, dtype=torch.float64), 1),
            "M must be symmetric",
        ),
        ("v", lambda f: f["v"][:2], "v must have shape"),
        ("f", lambda f: torch.tensor([0.0, math.nan, 0.0], dtype=torch.float64), "f contains NaN"),
        ("Jn", lambda f: f["Jn"].float(), "Jn has dtype"),
        ("Jt", lambda f: f["Jt"][..., :1, :], "even number"),
        ("Jt", lambda f: f["Jt"].abs(), "opposite"),
        (
            "phi",
            lambda f: torch.full((2,), math.inf, dtype=torch.float64),
            "phi contains NaN or inf",
        ),
        ("phi", lambda f: torch.zeros(3, dtype=torch.float64), "phi must have shape"),
        ("mu", lambda f: torch.tensor([0.5, -0.1], dtype=torch.float64), "mu must be >= 0"),
        ("mu", lambda f: [0.5, 0.5], "mu must be a torch.Tensor"),
        ("h", lambda f: 0.0, "h: expected a finite number > 0"),
        ("h", lambda f: math.nan, "h: expected a finite number > 0"),
    ],
)
def test_bad_field_raises_value_error_naming_it(name: str, make, message: str) -> None:
    fields = _fields()
    with pytest.raises(ValueError, match=message):
        ContactProblem(**_replace(name, make(fields)))


def test_bad_mask_and_batch_shapes_are_named() -> None:
    with pytest.raises(ValueError, match="mask must be a bool tensor"):
        ContactProblem(**_fields(), mask=torch.ones(2))
    fields = _fields()
    fields["v"] = torch.zeros(4, 3, dtype=torch.float64)
    fields["phi"] = torch.zeros(5, 2, dtype=torch.float64)
    with pytest.raises(ValueError, match="do not broadcast"):
        ContactProblem(**fields)


def test_fields_broadcast_to_a_common_batch() -> None:
    fields = _fields()
    fields["v"] = torch.zeros(4, 3, dtype=torch.float64)
    problem = ContactProblem(**fields)
    assert problem.batch_shape == (4,)
    assert problem.Jt.shape == (4, 2, 2, 3)
    assert problem.mask.shape == (4, 2)
    assert problem.flatten().batch_shape == (4,)
    assert problem[1:3].batch_shape == (2,)


def test_unknown_method_is_named() -> None:
    with pytest.raises(ValueError, match="method must be"):
        solve(ContactProblem(**_fields()), "simplex")  # type: ignore[arg-type]


def test_library_box_example_equals_the_hand_written_one() -> None:
    gen = torch.Generator().manual_seed(5)
    q = torch.randn(7, 3, generator=gen, dtype=torch.float64)
    v = torch.randn(7, 3, generator=gen, dtype=torch.float64)
    force = torch.randn(7, 2, generator=gen, dtype=torch.float64)
    options = {"force": force, "force_point": (-0.5, 0.1), "corners": (0, 1, 2, 3), "mu": 0.3}
    ours = planar_box_problem(q=q, v=v, **options)
    by_hand = box_problem(q=q, v=v, **options)
    for name in ("M", "v", "f", "Jn", "Jt", "phi", "mu"):
        torch.testing.assert_close(getattr(ours, name), getattr(by_hand, name), msg=name)


def test_unchecked_construction_broadcasts_like_the_checked_one() -> None:
    """``ContactProblem.unchecked`` gives the validated constructor's fields and batch shape."""
    generator = torch.Generator().manual_seed(3)
    fields = {
        "M": torch.eye(3, dtype=torch.float64) * 2.0,
        "v": torch.randn(5, 3, dtype=torch.float64, generator=generator),
        "f": torch.randn(3, dtype=torch.float64, generator=generator),
        "Jn": torch.randn(5, 2, 3, dtype=torch.float64, generator=generator),
        "Jt": torch.randn(2, 1, 3, dtype=torch.float64, generator=generator).repeat(1, 2, 1)
        * torch.tensor([1.0, -1.0], dtype=torch.float64)[:, None],
        "phi": torch.rand(2, dtype=torch.float64, generator=generator),
        "mu": torch.full((2,), 0.5, dtype=torch.float64),
        "mask": torch.tensor([True, False]),
        "bn": torch.zeros(2, dtype=torch.float64),
        "bt": torch.zeros(2, 2, dtype=torch.float64),
    }
    checked = ContactProblem(**fields, h=0.01)
    unchecked = ContactProblem.unchecked(**fields, h=0.01)
    assert unchecked.batch_shape == checked.batch_shape == (5,)
    for name in ("M", "v", "f", "Jn", "Jt", "phi", "mu", "mask", "bn", "bt"):
        assert getattr(unchecked, name).shape == getattr(checked, name).shape, name
    assert unchecked.h == checked.h


def test_quantities_kept_on_a_problem_follow_gradients_and_grad_mode() -> None:
    """``v_free`` (kept on the problem when no field requires grad) against its closed form
    ``v + h M⁻¹ f`` for a diagonal ``M``, with and without grad mode; with a field that
    requires grad it is recomputed on every call, so that two backward passes through it
    both work (a graph kept on the problem would be freed by the first) and both give
    ``∂ Σ v_free / ∂f = h / diag(M)``."""
    q = torch.tensor([[0.0, 0.25, 0.0], [0.1, 0.3, 0.2]], dtype=torch.float64)
    v = torch.tensor([[1.0, 0.0, 0.0], [0.0, -0.5, 0.1]], dtype=torch.float64)
    problem = box_problem(q=q, v=v)
    diagonal = problem.M.diagonal(dim1=-2, dim2=-1)
    expected = v + problem.h * problem.f / diagonal
    with torch.no_grad():
        torch.testing.assert_close(problem.v_free(), expected, rtol=1e-14, atol=0.0)
    torch.testing.assert_close(problem.v_free(), expected, rtol=1e-14, atol=0.0)

    f = problem.f.clone().requires_grad_(True)
    fields = {name: getattr(problem, name) for name in ("M", "v", "Jn", "Jt", "phi", "mu")}
    grad_problem = ContactProblem(**fields, f=f, h=problem.h)
    for _ in range(2):
        (grad,) = torch.autograd.grad(grad_problem.v_free().sum(), f)
        torch.testing.assert_close(grad, problem.h / diagonal, rtol=1e-14, atol=0.0)


def test_checks_of_a_solution_changed_in_place_see_the_change() -> None:
    """The constraint velocities and scales at a solution are kept on the problem for the
    next check of the same tensors; a solution written over in place is a new one. A resting
    box's exact (Lemke) step is consistent with its modes; its end velocity raised by 1 m/s
    upwards separates both loaded corners at 1 m/s while they carry impulse (inconsistent, an
    LCP residual of min(pn, 1 m/s) per corner), and restored it is consistent again."""
    q, v = resting_state()
    problem = box_problem(q=q, v=v)
    solution = solve(problem, "lemke")
    assert bool(is_consistent(problem, solution))
    with torch.no_grad():
        solution.v_next[..., 1] += 1.0
    assert not bool(is_consistent(problem, solution))
    expected = float(torch.minimum(solution.pn, torch.ones_like(solution.pn)).amax())
    assert float(lcp_residual(problem, v_next=solution.v_next, pn=solution.pn, pt=solution.pt)) == (
        pytest.approx(expected, rel=1e-9)
    )
    with torch.no_grad():
        solution.v_next[..., 1] -= 1.0
    assert bool(is_consistent(problem, solution))
