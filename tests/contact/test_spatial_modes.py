"""Spatial contact modes: every LCP solution has a mode, including sliding on a cone face.

With a polyhedral cone in 3-D the sliding friction of an LCP solution lies on one friction
direction (an edge of the cone, mode ``2 + d``) or on the face between two adjacent ones
(mode ``2 + D + d``). References: Lemke's method on random spatial problems, the mode's
equalities written out in the Stewart–Trinkle variables and solved by NumPy here (a second,
independent statement of what each mode means), closed-form point-mass sliding, and
Richardson-extrapolated finite differences for the gradients.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from torch import Tensor

from tests.contact.spatial import friction_rows, random_spatial_problems
from tests.sim.test_step import _richardson
from torchcontact.contact import (
    SEPARATED,
    SLIDING,
    STICKING,
    ContactProblem,
    friction_direction,
    is_consistent,
    is_face_sliding,
    is_sliding,
    num_modes,
    solve,
    solve_active_set,
    solve_mode,
)

F64 = torch.float64
#: Problems whose mode equations have a larger condition number (after equilibration) are
#: skipped: there the end velocity is not a well-posed function of the data (redundant rows).
MAX_CONDITION = 1e6
#: Relative agreement with Lemke's velocity: its final basis solve and the mode solve each
#: lose at most cond · eps ≈ 1e-10 on the problems kept.
VELOCITY_RTOL = 1e-9
#: PGS stops at a relative LCP residual of 1e-9: its velocities are off the exact solution of
#: their mode by up to 1.5e-9 relative on these problems.
PGS_RTOL = 1e-7


def _mode_equations(problem: ContactProblem, mode: Tensor) -> tuple[np.ndarray, np.ndarray, int]:
    """The equalities that ``mode`` makes of the Stewart–Trinkle LCP of one problem (NumPy).

    Unknowns: ``v⁺``, then per active slot its normal impulse and, sticking, two signed
    friction impulses along directions 0 and 1; sliding on an edge ``d``, ``pt_d`` and the
    sliding speed ``σ``; on the face ``d, e = d + 1``, ``pt_d``, ``pt_e`` and ``σ``. Equations:
    Newton–Euler, zero gap rate, and per friction unknown its row ``Jt_j v⁺ + bt_j (+ σ) = 0``,
    per sliding slot the cone row ``μ pn = Σ pt``.

    Returns:
        ``(A, b, n)``: the square system ``A y = b`` and the number of velocities ``n``.
    """
    M, v, f = (problem.M.numpy(), problem.v.numpy(), problem.f.numpy())
    Jn, Jt, mu = problem.Jn.numpy(), problem.Jt.numpy(), problem.mu.numpy()
    bn, bt, phi, h = problem.bn.numpy(), problem.bt.numpy(), problem.phi.numpy(), problem.h
    n, D = M.shape[0], Jt.shape[1]
    columns: list[np.ndarray] = []  # generalized direction of each impulse unknown
    rows: list[tuple[np.ndarray, float]] = []  # constraint rows on v⁺ with their right side
    cone: list[tuple[int, int, list[int]]] = []  # (slot, pn column, pt columns)
    sigma_rows: list[tuple[int, int]] = []  # (row, σ column) pairs
    for k, m in enumerate(mode.tolist()):
        if m == SEPARATED:
            continue
        pn_column = len(columns)
        columns.append(Jn[k])
        rows.append((Jn[k], -bn[k] - phi[k] / h))
        if m == STICKING:
            for j in (0, 1):
                columns.append(Jt[k, j])
                rows.append((Jt[k, j], -bt[k, j]))
            continue
        first = (m - SLIDING) % D
        pair = [first, (first + 1) % D] if m >= SLIDING + D else [first]
        pt_columns = []
        for j in pair:
            pt_columns.append(len(columns))
            columns.append(Jt[k, j])
        sigma_column = len(columns)
        columns.append(np.zeros(n))  # σ carries no impulse
        for j in pair:
            sigma_rows.append((len(rows), sigma_column))
            rows.append((Jt[k, j], -bt[k, j]))
        cone.append((k, pn_column, pt_columns))
    unknowns = len(columns)
    size = n + unknowns
    A, b = np.zeros((size, size)), np.zeros(size)
    A[:n, :n] = M
    if unknowns:
        A[:n, n:] = -np.stack(columns, axis=1)
    b[:n] = M @ v + h * f
    for index, (row, rhs) in enumerate(rows):
        A[n + index, :n] = row
        b[n + index] = rhs
    for row, sigma_column in sigma_rows:
        A[n + row, n + sigma_column] = 1.0
    for index, (slot, pn_column, pt_columns) in enumerate(cone):
        row = n + len(rows) + index
        A[row, n + pn_column] = mu[slot]
        A[row, [n + c for c in pt_columns]] = -1.0
    assert len(rows) + len(cone) == unknowns
    return A, b, n


def _solve_equations(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float]:
    """Solve ``A y = b`` after equilibrating rows and columns; also return the condition."""
    row_scale = 1.0 / np.abs(A).max(axis=1)
    scaled = A * row_scale[:, None]
    column_scale = 1.0 / np.abs(scaled).max(axis=0)
    scaled = scaled * column_scale[None, :]
    condition = float(np.linalg.cond(scaled))
    if not np.isfinite(condition) or condition > 1e14:
        return np.full(A.shape[0], np.nan), np.inf
    y = np.linalg.solve(scaled, b * row_scale) * column_scale
    return y, condition


def _velocity_error(actual: Tensor, expected: Tensor, problem: ContactProblem) -> Tensor:
    """``(*B,)`` largest velocity difference relative to the problem's velocity size."""
    scale = torch.maximum(expected.abs().amax(-1), problem.v_free().abs().amax(-1))
    return (actual - expected).abs().amax(-1) / scale


@pytest.mark.parametrize("directions", [4, 8])
@pytest.mark.parametrize("method", ["lemke", "pgs"])
def test_every_converged_answer_has_a_mode_that_reproduces_it(method: str, directions: int) -> None:
    """The issue's experiment: 300 random spatial problems, 3 slots of 8 velocities each.

    Every converged answer's mode (from ``contact_mode``) is accepted by ``is_consistent``;
    on every problem whose mode equations are well posed, those equations (solved by NumPy)
    give Lemke's velocity, and so does ``solve_mode`` at the mode, to 1e-9 relative. Face
    modes are common: before they existed, ``is_consistent`` rejected 103 of the 300 Lemke
    answers with D = 4 and 97 with D = 8 (102 of 299 and 74 of 268 PGS answers).
    """
    problem = random_spatial_problems(7 + directions, count=300, directions=directions, slots=3)
    reference = solve(problem, "lemke")
    answer = reference if method == "lemke" else solve(problem, "pgs", max_sweeps=1000)
    converged = answer.status.converged & reference.status.converged
    # (PGS converges linearly: 1000 sweeps meet its tolerance on 94 % of the D = 4 problems
    # and 79 % of the D = 8 ones.)
    assert converged.double().mean().item() > (0.95 if method == "lemke" else 0.7)
    mode = answer.mode
    consistent = is_consistent(problem, answer)
    assert bool(consistent[converged].all()), torch.nonzero(converged & ~consistent)

    face = is_face_sliding(mode, num_directions=directions)
    edge = is_sliding(mode) & ~face
    assert int(face[converged].sum()) >= 50
    assert int(edge[converged].sum()) >= 50
    assert int((mode == STICKING)[converged].sum()) >= 30

    # The mode's equations, solved by NumPy where they are well posed (an isolated solution).
    kept = torch.zeros_like(converged)
    exact = torch.zeros_like(answer.v_next)
    for index in torch.nonzero(converged).squeeze(-1).tolist():
        A, b, n = _mode_equations(problem[index], mode[index])
        y, condition = _solve_equations(A, b)
        if condition <= MAX_CONDITION:
            kept[index] = True
            exact[index] = torch.from_numpy(y[:n])
    assert kept.double().sum().item() >= 0.9 * converged.double().sum().item()
    # They hold at the answer (contact_mode named the right equalities)...
    own_error = _velocity_error(answer.v_next, exact, problem)[kept]
    assert own_error.max().item() <= (VELOCITY_RTOL if method == "lemke" else PGS_RTOL)
    # ... and solve_mode solves them.
    again = solve_mode(problem, mode)
    assert _velocity_error(again.v_next, exact, problem)[kept].max().item() <= VELOCITY_RTOL
    assert bool(is_consistent(problem, again)[kept].all())
    assert bool(again.status.converged[kept].all())
    # Where the answer is Lemke's solution (all of Lemke's own; a frictional LCP can have
    # several, and PGS finds another one on one of the D = 4 problems), the mode solve
    # reproduces Lemke's velocity.
    same = kept & (mode == reference.mode).all(dim=-1)
    assert same.double().sum().item() >= 0.98 * kept.double().sum().item()
    error = _velocity_error(again.v_next, reference.v_next, problem)
    assert error[same].max().item() <= VELOCITY_RTOL
    if method == "lemke":
        # Started from Lemke's impulses, the solve keeps them (its split included).
        kept_split = solve_mode(problem, mode, initial_impulses=(reference.pn, reference.pt))
        momentum = (problem.M @ problem.v_free().unsqueeze(-1)).abs().amax((-1, -2))
        scale = torch.maximum(reference.pn.abs().amax(-1), momentum)
        pt_error = (kept_split.pt - reference.pt).abs().amax((-1, -2)) / scale
        assert pt_error[kept].max().item() <= VELOCITY_RTOL


def _point_mass(force: tuple[float, float], *, h: float = 0.01) -> ContactProblem:
    """A 2 kg point mass on the plane ``z = 0`` (μ = 0.5, D = 4: ±x, ±y), pushed by ``force``."""
    mass = 2.0
    tangents = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=F64)
    return ContactProblem(
        M=mass * torch.eye(3, dtype=F64),
        v=torch.zeros(3, dtype=F64),
        f=torch.tensor([force[0], force[1], -9.81 * mass], dtype=F64),
        Jn=torch.tensor([[0.0, 0.0, 1.0]], dtype=F64),
        Jt=friction_rows(tangents, 4).unsqueeze(0),
        phi=torch.zeros(1, dtype=F64),
        mu=torch.tensor([0.5], dtype=F64),
        h=h,
    )


@pytest.mark.parametrize("method", ["lemke", "pgs"])
def test_point_mass_pushed_between_two_directions_slides_on_their_face(method: str) -> None:
    """Pushed along (−1, −1) with 10 N per axis: the square cone allows at most μ m g / 2 =
    4.905 N per axis along the diagonal, so the mass slides, its friction split equally
    between directions 0 (+x) and 1 (+y): v⁺ = h (−F + μ m g / 2) / m per axis."""
    h, mass, g, mu, push = 0.01, 2.0, 9.81, 0.5, 10.0
    problem = _point_mass((-push, -push), h=h)
    answer = solve(problem, method)
    assert bool(answer.status.converged)
    face = SLIDING + 4 + 0
    assert answer.mode.tolist() == [face]
    speed = h * (-push + mu * mass * g / 2) / mass
    expected_v = torch.tensor([speed, speed, 0.0], dtype=F64)
    half = mu * mass * g * h / 2
    expected_pt = torch.tensor([[half, half, 0.0, 0.0]], dtype=F64)
    tolerance = 1e-12 if method == "lemke" else 1e-9
    torch.testing.assert_close(answer.v_next, expected_v, atol=tolerance, rtol=0)
    torch.testing.assert_close(answer.pt, expected_pt, atol=tolerance * mass, rtol=0)
    assert bool(is_consistent(problem, answer))

    at_mode = solve_mode(problem, answer.mode)
    torch.testing.assert_close(at_mode.v_next, expected_v, atol=1e-12, rtol=0)
    torch.testing.assert_close(at_mode.pt, expected_pt, atol=1e-12, rtol=0)
    assert bool(is_consistent(problem, at_mode))
    # Neither edge can say it: all friction along +x (or +y) pushes the mass off the diagonal.
    for edge in (SLIDING + 0, SLIDING + 1):
        assert not bool(is_consistent(problem, solve_mode(problem, torch.tensor([edge]))))


@pytest.mark.parametrize("method", ["lemke", "pgs"])
def test_point_mass_pushed_along_a_direction_slides_on_its_opposite_edge(method: str) -> None:
    """Pushed along direction 0 (+x) with 15 N > μ m g = 9.81 N: friction μ m g h along
    direction 2 (−x) alone, an edge mode, v⁺ = h (F − μ m g) / m along x."""
    h, mass, g, mu, push = 0.01, 2.0, 9.81, 0.5, 15.0
    problem = _point_mass((push, 0.0), h=h)
    answer = solve(problem, method)
    assert bool(answer.status.converged)
    assert answer.mode.tolist() == [SLIDING + 2]
    expected_v = torch.tensor([h * (push - mu * mass * g) / mass, 0.0, 0.0], dtype=F64)
    expected_pt = torch.tensor([[0.0, 0.0, mu * mass * g * h, 0.0]], dtype=F64)
    tolerance = 1e-12 if method == "lemke" else 1e-9
    torch.testing.assert_close(answer.v_next, expected_v, atol=tolerance, rtol=0)
    torch.testing.assert_close(answer.pt, expected_pt, atol=tolerance * mass, rtol=0)
    at_mode = solve_mode(problem, answer.mode)
    torch.testing.assert_close(at_mode.v_next, expected_v, atol=1e-12, rtol=0)
    torch.testing.assert_close(at_mode.pt, expected_pt, atol=1e-12, rtol=0)
    assert bool(is_consistent(problem, at_mode))
    # A face beside the edge holds the slip on a diagonal, which takes negative friction.
    for face in (SLIDING + 4 + 1, SLIDING + 4 + 2):
        assert not bool(is_consistent(problem, solve_mode(problem, torch.tensor([face]))))


def test_gradients_at_a_face_mode_equal_richardson_differences() -> None:
    """A random problem with face-sliding slots: derivatives of v⁺, pn and pt at its Lemke
    mode with respect to v, f, φ, μ, the normal and tangent rows and M, against central
    differences extrapolated from steps ε and ε/2 (the mode is held fixed)."""
    base = random_spatial_problems(3, count=40, directions=4, slots=2, dofs=8)
    reference = solve(base, "lemke")
    face = is_face_sliding(reference.mode, num_directions=4)
    chosen = next(
        i for i in range(40) if bool(face[i].any()) and bool(reference.status.converged[i])
    )
    one = base[chosen]
    mode = reference.mode[chosen]
    A, b, _ = _mode_equations(one, mode)
    assert _solve_equations(A, b)[1] < MAX_CONDITION
    gen = torch.Generator().manual_seed(0)
    # The friction rows come from two tangent rows per slot (``W`` has orthogonal columns of
    # squared norm D / 2), so perturb those.
    W = friction_rows(torch.eye(2, dtype=F64), 4)  # (D, 2)
    tangents = W.T @ one.Jt / 2.0  # (K, 2, n)
    torch.testing.assert_close(W @ tangents, one.Jt)
    weights = [torch.randn(s, generator=gen, dtype=F64) for s in ((8,), (2,), (2, 4))]

    def loss(
        v: Tensor, f: Tensor, phi: Tensor, mu: Tensor, Jn: Tensor, T: Tensor, L: Tensor
    ) -> Tensor:
        problem = ContactProblem(
            M=L @ L.T,
            v=v,
            f=f,
            Jn=Jn,
            Jt=W @ T,
            phi=phi,
            mu=mu,
            h=one.h,
        )
        solution = solve_mode(problem, mode)
        outputs = (solution.v_next, solution.pn, solution.pt)
        return sum((w * o).sum() for w, o in zip(weights, outputs, strict=True))

    inputs = [
        one.v,
        one.f,
        one.phi,
        one.mu,
        one.Jn,
        tangents,
        torch.linalg.cholesky(one.M),
    ]
    leaves = [t.clone().requires_grad_(True) for t in inputs]
    value = loss(*leaves)
    gradients = torch.autograd.grad(value, leaves)
    for position, (point, gradient) in enumerate(zip(inputs, gradients, strict=True)):
        direction = torch.randn(point.shape, generator=gen, dtype=F64)
        if position == 6:
            direction = direction.tril()

        def along(epsilon: float, p=position, d=direction) -> Tensor:
            moved = list(inputs)
            moved[p] = inputs[p] + epsilon * d
            return loss(*moved).detach()

        expected = _richardson(along, 1e-4)
        actual = (gradient * direction).sum()
        assert actual.item() == pytest.approx(expected.item(), rel=1e-6, abs=1e-9), position


def test_mode_codes_name_edges_and_faces() -> None:
    """The code table: planar 0–3, spatial 0 … 2 + 2D − 1, faces from 2 + D on."""
    assert num_modes(2) == 4
    assert num_modes(4) == 10
    assert num_modes(8) == 18
    modes = torch.tensor([SEPARATED, STICKING, 2, 5, 6, 9])
    assert is_sliding(modes).tolist() == [False, False, True, True, True, True]
    assert is_face_sliding(modes, num_directions=4).tolist() == [False] * 4 + [True, True]
    # Face 9 = 2 + 4 + 3 lies between directions 3 and 0 (mod D); it reports direction 3.
    assert friction_direction(modes, num_directions=4).tolist() == [-1, -1, 0, 3, 0, 3]
    planar = torch.tensor([0, 1, 2, 3])
    assert not bool(is_face_sliding(planar, num_directions=2).any())
    assert friction_direction(planar, num_directions=2).tolist() == [-1, -1, 0, 1]


@pytest.mark.parametrize(("directions", "bad"), [(4, 10), (4, -1), (8, 18), (2, 4)])
def test_mode_values_past_the_faces_are_named(directions: int, bad: int) -> None:
    problem = random_spatial_problems(0, count=2, directions=directions, slots=2)
    mode = torch.tensor([1, bad])
    with pytest.raises(
        ValueError, match=rf"^mode values must lie in \[0, {num_modes(directions)}\)"
    ):
        solve_mode(problem, mode)
    good = solve(problem, "lemke")
    with pytest.raises(ValueError, match=r"^solution.mode"):
        is_consistent(problem, replace(good, mode=mode.expand(2, 2)))
    largest = torch.full((2, 2), num_modes(directions) - 1)
    assert solve_mode(problem, largest).mode.shape == (2, 2)


@pytest.mark.parametrize("directions", [4, 8])
def test_active_set_reaches_face_modes_from_sticking(directions: int) -> None:
    """From sticking, ``update_mode``'s corrections (sticking → face or edge, edge → face,
    face → edge) find Lemke's velocity, face modes included, on most random one-slot
    problems. Like any active-set method on an LCP it can cycle: the 10 % that fail here
    alternate between sticking (with a pulling normal impulse) and separated (penetrating),
    as planar slots can; an exact solver takes those."""
    problem = random_spatial_problems(21, count=200, directions=directions, slots=1)
    reference = solve(problem, "lemke")
    result = solve_active_set(problem, torch.ones_like(reference.mode), max_iterations=10)
    converged = result.status.converged & reference.status.converged
    assert converged.double().mean().item() > 0.8  # 89 % (D = 4), 90 % (D = 8)
    error = _velocity_error(result.v_next, reference.v_next, problem)
    assert error[converged].max().item() <= VELOCITY_RTOL
    face = is_face_sliding(result.mode, num_directions=directions)
    assert int(face[converged].sum()) >= 40  # of 58 (D = 4) and 47 (D = 8) in Lemke's modes
