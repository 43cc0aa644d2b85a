"""The solvers agree with each other, with exact enumeration, and with closed form in 3-D."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from tests.contact.boxes import box_problem
from tests.contact.spatial import spatial_box_problem
from torchcontact.contact import (
    ContactProblem,
    LemkeOutcome,
    is_consistent,
    lemke,
    project_capped_simplex,
    solve,
    solve_active_set,
    solve_mode,
)


def _enumerate_lcp(A: np.ndarray, q: np.ndarray) -> list[np.ndarray]:
    """Every solution of a small LCP by trying all 2^N complementary bases."""
    N = q.size
    solutions = []
    for basic in itertools.product([False, True], repeat=N):
        z_set = np.flatnonzero(basic)
        z = np.zeros(N)
        if z_set.size:
            try:
                z[z_set] = np.linalg.solve(A[np.ix_(z_set, z_set)], -q[z_set])
            except np.linalg.LinAlgError:
                continue
        w = A @ z + q
        if z.min() >= -1e-10 and w.min() >= -1e-10:
            solutions.append(z)
    return solutions


@pytest.mark.parametrize("seed", range(20))
def test_lemke_matches_enumeration_on_p_matrix_lcps(seed: int) -> None:
    rng = np.random.default_rng(seed)
    N = 6
    B, C = rng.normal(size=(N, N)), rng.normal(size=(N, N))
    A = B @ B.T + 0.5 * np.eye(N) + (C - C.T)  # positive definite, not symmetric: a P-matrix
    q = rng.normal(size=N)
    (expected,) = _enumerate_lcp(A, q)
    result = lemke(A, q)
    assert result.outcome is LemkeOutcome.SOLVED
    np.testing.assert_allclose(result.z, expected, atol=1e-10)
    assert abs(result.z @ result.w) < 1e-12


def test_lemke_degenerate_q_with_ties_terminates() -> None:
    """Every entry of q equal and A with repeated rows: a plain ratio test ties at each step."""
    A = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 2.0]]) + 1e-3 * np.eye(3)
    q = np.array([-1.0, -1.0, -1.0])
    result = lemke(A, q)
    assert result.outcome is LemkeOutcome.SOLVED
    assert result.z.min() >= 0
    assert result.w.min() >= -1e-12
    assert abs(result.z @ result.w) < 1e-12
    assert any(np.allclose(result.z, s) for s in _enumerate_lcp(A, q))


def test_lemke_reports_infeasible_lcp_as_ray() -> None:
    """w = −z − 1 ≥ 0 has no solution with z ≥ 0: Lemke must end on a ray, not 'solve'."""
    result = lemke(np.array([[-1.0]]), np.array([-1.0]))
    assert result.outcome is LemkeOutcome.RAY


def _random_frictionless(seed: int, batch: int = 8) -> ContactProblem:
    gen = torch.Generator().manual_seed(seed)
    n, K = 6, 4
    B = torch.randn(batch, n, n, generator=gen, dtype=torch.float64)
    M = B @ B.transpose(-1, -2) + n * torch.eye(n, dtype=torch.float64)
    Jn = torch.randn(batch, K, n, generator=gen, dtype=torch.float64)
    t = torch.randn(batch, K, 1, n, generator=gen, dtype=torch.float64)
    return ContactProblem(
        M=M,
        v=torch.randn(batch, n, generator=gen, dtype=torch.float64),
        f=torch.randn(batch, n, generator=gen, dtype=torch.float64),
        Jn=Jn,
        Jt=torch.cat([t, -t], dim=-2),
        phi=0.01 * torch.rand(batch, K, generator=gen, dtype=torch.float64),
        mu=torch.zeros(batch, K, dtype=torch.float64),
        h=0.01,
    )


@pytest.mark.parametrize("seed", range(3))
def test_all_solvers_agree_on_random_frictionless_problems(seed: int) -> None:
    problem = _random_frictionless(seed)
    reference = solve(problem, "lemke")
    assert bool(reference.status.converged.all())
    assert reference.status.residual.max().item() <= 1e-9
    for method, options in (("qp", {}), ("pgs", {"max_sweeps": 20000})):
        other = solve(problem, method, **options)
        assert bool(other.status.converged.all()), method
        torch.testing.assert_close(other.pn, reference.pn, atol=1e-6, rtol=0)
        torch.testing.assert_close(other.v_next, reference.v_next, atol=1e-6, rtol=0)


def _random_boxes(seed: int, batch: int = 40):
    """Boxes flat or tilted on a corner, still or moving, pushed or not: every mode occurs."""
    gen = torch.Generator().manual_seed(seed)

    def uniform(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=gen, dtype=torch.float64)

    tilted = uniform(batch) < 0.5
    theta = torch.where(
        tilted, 0.3 * (uniform(batch) - 0.5), torch.zeros(batch, dtype=torch.float64)
    )
    height = 0.25 * torch.cos(theta) + 0.5 * torch.sin(theta).abs() + 0.002 * uniform(batch)
    height = torch.where(tilted, height, torch.full_like(height, 0.25))
    q = torch.stack([torch.zeros_like(theta), height, theta], dim=-1)
    moving = (uniform(batch, 1) < 0.5).to(torch.float64)
    v = moving * (2 * uniform(batch, 3) - 1) * torch.tensor([1.0, 0.3, 1.0], dtype=torch.float64)
    force = 10 * (2 * uniform(batch, 2) - 1)
    mu = float(0.3 + 0.6 * uniform(()))
    return box_problem(q=q, v=v, mu=mu, force=force, force_point=(-0.5, 0.2), corners=(0, 1, 2, 3))


@pytest.mark.parametrize("seed", range(3))
def test_lemke_and_qp_agree_on_frictional_planar_problems(seed: int) -> None:
    problem = _random_boxes(seed)
    lemke_solution = solve(problem, "lemke")
    qp_solution = solve(problem, "qp")
    assert bool(lemke_solution.status.converged.all())
    assert bool(qp_solution.status.converged.all())
    assert lemke_solution.status.residual.max().item() <= 1e-9
    torch.testing.assert_close(qp_solution.v_next, lemke_solution.v_next, atol=1e-6, rtol=0)
    assert bool(is_consistent(problem, lemke_solution).all())
    modes = lemke_solution.mode
    assert {0, 1}.issubset(set(modes.unique().tolist()))
    assert int(modes.max()) >= 2


@pytest.mark.parametrize("seed", range(3))
def test_solve_mode_reproduces_lemke_from_its_mode(seed: int) -> None:
    problem = _random_boxes(seed)
    reference = solve(problem, "lemke")
    again = solve_mode(problem, reference.mode)
    torch.testing.assert_close(again.v_next, reference.v_next, atol=1e-9, rtol=0)
    assert again.status.residual.max().item() <= 1e-9
    assert bool(again.status.converged.all())
    assert bool(is_consistent(problem, again).all())


def test_spatial_box_sliding_decelerates_at_mu_g_and_resting_box_is_still() -> None:
    """Eight friction directions, four coplanar corners (redundant normal rows)."""
    v = torch.zeros(3, 6, dtype=torch.float64)
    v[0, 0] = 1.0  # slides along friction direction 0 (x)
    v[1, 1] = -0.5  # slides along direction 6 (−y)
    problem = spatial_box_problem(v=v, mu=0.4, directions=8)
    for method in ("lemke", "qp"):
        solution = solve(problem, method)
        assert bool(solution.status.converged.all()), method
        expected = v.clone()
        expected[0, 0] -= 0.4 * 9.81 * 0.01
        expected[1, 1] += 0.4 * 9.81 * 0.01
        torch.testing.assert_close(solution.v_next, expected, atol=1e-9, rtol=0)
        torch.testing.assert_close(
            solution.pn.sum(-1), torch.full((3,), 1.5 * 9.81 * 0.01, dtype=torch.float64)
        )
        again = solve_mode(problem, solution.mode)
        torch.testing.assert_close(again.v_next, solution.v_next, atol=1e-9, rtol=0)
        assert bool(is_consistent(problem, again).all())


def test_spatial_sticking_friction_is_written_on_bracketing_directions() -> None:
    """A lateral push below the friction limit: friction along (−1, −1)/√2 splits evenly."""
    force = torch.zeros(1, 6, dtype=torch.float64)
    force[0, 0] = force[0, 1] = 2.0
    problem = spatial_box_problem(v=torch.zeros(1, 6, dtype=torch.float64), force=force)
    mode = torch.ones(1, 4, dtype=torch.long)
    solution = solve_mode(problem, mode)
    torch.testing.assert_close(
        solution.v_next, torch.zeros(1, 6, dtype=torch.float64), atol=1e-12, rtol=0
    )
    total = solution.pt.sum(dim=-2)[0]  # (D,)
    angles = torch.arange(8, dtype=torch.float64) * (math.pi / 4)
    net = torch.stack([total @ torch.cos(angles), total @ torch.sin(angles)])
    torch.testing.assert_close(
        net, torch.full((2,), -2.0 * 0.01, dtype=torch.float64), atol=1e-12, rtol=0
    )
    # Directions at 45° steps: (−1, −1)/√2 is direction 5. Internal friction forces that
    # cancel between corners are free; they stay at round-off level.
    assert total[[0, 1, 2, 3, 4, 6, 7]].abs().max().item() < 1e-8 * total[5].item()
    assert bool(is_consistent(problem, solution).all())


def test_capped_simplex_projection_matches_brute_force() -> None:
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(200, 4, generator=gen, dtype=torch.float64)
    cap = torch.rand(200, generator=gen, dtype=torch.float64)
    projected = project_capped_simplex(x, cap)
    assert (projected >= 0).all()
    assert (projected.sum(-1) <= cap + 1e-12).all()
    # Optimality: no feasible random point is closer.
    candidates = torch.rand(200, 2000, 4, generator=gen, dtype=torch.float64)
    candidates = candidates / candidates.sum(-1, keepdim=True).clamp(min=1.0) * cap[:, None, None]
    best = (candidates - x[:, None]).norm(dim=-1).amin(dim=-1)
    assert ((projected - x).norm(dim=-1) <= best + 1e-12).all()


def test_solvers_report_non_convergence_instead_of_garbage() -> None:
    problem = _random_boxes(0)
    pgs = solve(problem, "pgs", max_sweeps=1)
    lemke_limited = solve(problem, "lemke", max_pivots=1)
    qp_limited = solve(problem, "qp", max_rounds=1)
    exact = solve(problem, "lemke")
    for limited in (pgs, lemke_limited, qp_limited):
        wrong = (limited.v_next - exact.v_next).abs().amax(dim=-1) > 1e-6
        assert bool(wrong.any())
        # Every entry that is wrong says so.
        assert not bool((wrong & limited.status.converged).any())


def test_active_set_from_a_wrong_guess_reaches_lemke() -> None:
    """Starting from 'all separated', a few batched mode corrections find Lemke's answer."""
    problem = _random_boxes(2)
    exact = solve(problem, "lemke")
    result = solve_active_set(problem, torch.zeros_like(exact.mode), max_iterations=8)
    converged = result.status.converged
    assert converged.double().mean().item() > 0.5  # a heuristic: most, not all (75% here)
    torch.testing.assert_close(result.v_next[converged], exact.v_next[converged], atol=1e-9, rtol=0)
    assert bool(is_consistent(problem, result)[converged].all())
    assert not bool(is_consistent(problem, result)[~converged].any())
