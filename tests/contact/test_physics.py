"""Closed-form rigid-body results for a planar box on the ground, for every exact solver.

Each expected number is derived on paper from Newton–Euler and Coulomb's law (see the
docstrings), not read off the solvers.
"""

from __future__ import annotations

import math

import pytest
import torch

from tests.contact.boxes import box_problem, incline_gravity, resting_state
from torchcontact.contact import (
    SEPARATED,
    SLIDING,
    STICKING,
    friction_direction,
    is_consistent,
    is_sliding,
    solve,
    solve_mode,
)

G = 9.81
MASS = 2.0
A_HALF, B_HALF = 0.5, 0.25
H = 0.01
EXACT = ["lemke", "qp"]


def _solve_checked(problem, method):
    solution = solve(problem, method)
    assert bool(solution.status.converged.all()), solution.status
    assert bool(is_consistent(problem, solution).all())
    # The mode the solver found, solved on its own, gives the same step.
    again = solve_mode(problem, solution.mode)
    torch.testing.assert_close(again.v_next, solution.v_next, atol=1e-9, rtol=0)
    return solution


@pytest.mark.parametrize("method", EXACT)
def test_sliding_block_decelerates_at_mu_g_and_stops_when_predicted(method: str) -> None:
    """v_k = max(v0 − k μ g h, 0): each step removes μ g h until less than that remains."""
    mu, v0 = 0.4, 0.5
    q, v = resting_state()
    v[0] = v0
    decrement = mu * G * H
    stop_step = math.ceil(v0 / decrement)  # the first step that ends at rest
    for step in range(1, stop_step + 3):
        solution = _solve_checked(box_problem(q=q, v=v, mu=mu, h=H), method)
        v = solution.v_next
        expected = max(v0 - step * decrement, 0.0)
        assert v[0].item() == pytest.approx(expected, abs=1e-9)
        assert v[1].item() == pytest.approx(0.0, abs=1e-9)
        assert v[2].item() == pytest.approx(0.0, abs=1e-9)
        if step < stop_step:
            assert solution.mode.tolist() == [SLIDING + 1, SLIDING + 1]
            # Normal impulses carry the weight, shifted to the leading corner by the
            # friction torque: a (pn_front − pn_back) = b μ (pn_front + pn_back).
            pn_back, pn_front = solution.pn.tolist()
            assert pn_back + pn_front == pytest.approx(MASS * G * H, abs=1e-12)
            assert pn_front - pn_back == pytest.approx(
                B_HALF * mu / A_HALF * MASS * G * H, abs=1e-12
            )
        else:
            assert solution.mode.tolist() == [STICKING, STICKING]


@pytest.mark.parametrize("method", EXACT)
@pytest.mark.parametrize("degrees", [10.0, 20.0, 25.0, 30.0, 40.0])
def test_incline_sticks_iff_tan_below_mu_else_accelerates(method: str, degrees: float) -> None:
    """On an incline a block sticks iff tan θ < μ, else accelerates at g (sin θ − μ cos θ)."""
    mu = 0.5
    angle = math.radians(degrees)
    q, v = resting_state(half_extents=(0.5, 0.1))
    problem = box_problem(q=q, v=v, mu=mu, gravity=incline_gravity(angle), half_extents=(0.5, 0.1))
    solution = _solve_checked(problem, method)
    if math.tan(angle) < mu:
        assert solution.mode.tolist() == [STICKING, STICKING]
        torch.testing.assert_close(solution.v_next, torch.zeros(3, dtype=torch.float64))
    else:
        expected = H * G * (math.sin(angle) - mu * math.cos(angle))
        assert solution.v_next[0].item() == pytest.approx(expected, abs=1e-10)
        assert solution.v_next[2].item() == pytest.approx(0.0, abs=1e-10)
        assert solution.mode.tolist() == [SLIDING + 1, SLIDING + 1]


@pytest.mark.parametrize("method", EXACT)
def test_resting_box_has_no_drift_and_corner_forces_sum_to_weight(method: str) -> None:
    """Two corners at rest (a degenerate LCP): v⁺ = 0 and each corner carries m g h / 2."""
    q, v = resting_state()
    solution = _solve_checked(box_problem(q=q, v=v), method)
    torch.testing.assert_close(
        solution.v_next, torch.zeros(3, dtype=torch.float64), atol=1e-12, rtol=0
    )
    torch.testing.assert_close(
        solution.pn, torch.full((2,), MASS * G * H / 2, dtype=torch.float64), atol=1e-12, rtol=0
    )
    assert solution.pt.abs().max().item() < 1e-12


def _push(height: float, force: float, method: str):
    """Push the box's left face horizontally at ``height`` above the ground for one step."""
    q, v = resting_state()
    problem = box_problem(
        q=q,
        v=v,
        mu=0.5,
        force=torch.tensor([force, 0.0], dtype=torch.float64),
        force_point=(-A_HALF, height - B_HALF),
    )
    return _solve_checked(problem, method)


@pytest.mark.parametrize("method", EXACT)
def test_push_low_slides_without_rotation(method: str) -> None:
    """F > μ m g applied low (F·height < m g a): pure sliding at (F − μ m g)/m."""
    force = 1.2 * 0.5 * MASS * G
    height = 0.5 * MASS * G * A_HALF / force
    solution = _push(height, force, method)
    assert solution.v_next[0].item() == pytest.approx(
        H * (force - 0.5 * MASS * G) / MASS, abs=1e-10
    )
    assert solution.v_next[2].item() == pytest.approx(0.0, abs=1e-10)


@pytest.mark.parametrize("method", EXACT)
@pytest.mark.parametrize("ratio", [0.98, 1.02])
def test_push_high_tips_exactly_past_the_statics_threshold(method: str, ratio: float) -> None:
    """F < μ m g at height y: tips about the front corner iff F y > m g a.

    Tipping from rest pivots about the front corner: ω⁺ = −h (F y − m g a) / I_pivot with
    I_pivot = I + m (a² + b²).
    """
    force = 0.8 * 0.5 * MASS * G
    height = ratio * MASS * G * A_HALF / force
    solution = _push(height, force, method)
    if ratio < 1:
        torch.testing.assert_close(
            solution.v_next, torch.zeros(3, dtype=torch.float64), atol=1e-10, rtol=0
        )
        assert solution.mode.tolist() == [STICKING, STICKING]
    else:
        inertia = MASS * (A_HALF**2 + B_HALF**2) / 3
        pivot_inertia = inertia + MASS * (A_HALF**2 + B_HALF**2)
        omega = -H * (force * height - MASS * G * A_HALF) / pivot_inertia
        assert solution.v_next[2].item() == pytest.approx(omega, abs=1e-10)
        assert solution.mode.tolist() == [SEPARATED, STICKING]


@pytest.mark.parametrize("method", EXACT)
def test_plastic_impact_leaves_zero_normal_velocity(method: str) -> None:
    """A box landing flat at 2 m/s stops dead in one step: Σ pn = m (2 + g h)."""
    q, v = resting_state()
    v[1] = -2.0
    solution = _solve_checked(box_problem(q=q, v=v), method)
    assert solution.v_next[1].item() == pytest.approx(0.0, abs=1e-12)
    assert solution.pn.sum().item() == pytest.approx(MASS * (2.0 + G * H), abs=1e-12)


def test_pgs_matches_closed_form_resting_and_sliding() -> None:
    """PGS reaches the same closed-form answers on the well-posed cases, to its tolerance."""
    q, v = resting_state((2,))
    v[1, 0] = 0.5
    solution = solve(box_problem(q=q, v=v, mu=0.4), "pgs", max_sweeps=2000)
    assert bool(solution.status.converged.all())
    assert solution.v_next[0].abs().max().item() < 1e-8
    assert solution.v_next[1, 0].item() == pytest.approx(0.5 - 0.4 * G * H, abs=1e-8)


def test_mode_helpers_name_the_friction_direction_against_the_slip() -> None:
    """``is_sliding`` covers every sliding direction, and ``friction_direction`` names the
    direction that carries friction: the slip along it is negative (the block slides +x, its
    friction acts along −x)."""
    modes = torch.tensor([SEPARATED, STICKING, SLIDING, SLIDING + 1])
    assert is_sliding(modes).tolist() == [False, False, True, True]
    assert friction_direction(modes, num_directions=2).tolist() == [-1, -1, 0, 1]
    q, v = resting_state()
    v[0] = 0.5
    problem = box_problem(q=q, v=v, mu=0.4, h=H)
    solution = _solve_checked(problem, "lemke")
    direction = friction_direction(solution.mode, num_directions=2)
    assert bool(is_sliding(solution.mode).all())
    rows = problem.Jt[torch.arange(2), direction]  # (2, n): each corner's friction row
    slip = rows @ solution.v_next
    assert bool((slip < -1e-3).all()), slip
