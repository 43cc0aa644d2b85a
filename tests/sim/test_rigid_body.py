"""Spatial rigid-body dynamics against closed forms and slow per-body constructions."""

from __future__ import annotations

import math

import pytest
import torch

from torchcontact.geometry import Box, HalfSpace, quat_exp, quat_mul, quat_to_matrix
from torchcontact.sim import (
    Body,
    Scene,
    Simulator,
    contact_problem,
    free_angular_velocity,
    integrate_poses,
    spatial_mass_matrix,
    tangent_basis,
    tangent_directions,
)


def random_quaternions(*shape: int) -> torch.Tensor:
    q = torch.randn(*shape, 4, dtype=torch.float64)
    return q / q.norm(dim=-1, keepdim=True)


def random_inertias(count: int) -> torch.Tensor:
    """Inertias of boxes with random half extents and random principal axes."""
    half = 0.1 + torch.rand(count, 3, dtype=torch.float64)
    mass = 1.0 + torch.rand(count, dtype=torch.float64)
    a2 = half**2
    principal = (
        mass[:, None]
        / 3.0
        * torch.stack([a2[:, 1] + a2[:, 2], a2[:, 0] + a2[:, 2], a2[:, 0] + a2[:, 1]], -1)
    )
    R = quat_to_matrix(random_quaternions(count))
    return R @ torch.diag_embed(principal) @ R.transpose(-1, -2)


def test_mass_matrix_is_the_block_diagonal_of_rotated_inertias() -> None:
    masses = torch.tensor([1.5, 0.3, 2.0], dtype=torch.float64)
    inertia = random_inertias(3)
    quaternion = random_quaternions(5, 3)
    M = spatial_mass_matrix(masses, inertia, quaternion)
    assert M.shape == (5, 18, 18)
    for b in range(5):
        blocks = []
        for i in range(3):
            R = quat_to_matrix(quaternion[b, i])
            blocks += [masses[i] * torch.eye(3, dtype=torch.float64), R @ inertia[i] @ R.T]
        torch.testing.assert_close(M[b], torch.block_diag(*blocks), rtol=1e-13, atol=1e-15)


def test_kinetic_energy_in_the_body_frame() -> None:
    """½ vᵀ M v = ½ m |v|² + ½ ω_bᵀ I_b ω_b with ω_b = Rᵀ ω: the same energy in either frame."""
    masses = torch.tensor([2.0], dtype=torch.float64)
    inertia = random_inertias(1)
    quaternion = random_quaternions(20, 1)
    twist = torch.randn(20, 6, dtype=torch.float64)
    M = spatial_mass_matrix(masses, inertia, quaternion)
    energy = 0.5 * (twist.unsqueeze(-2) @ M @ twist.unsqueeze(-1)).reshape(20)
    R = quat_to_matrix(quaternion[:, 0])
    w_body = (R.transpose(-1, -2) @ twist[:, 3:, None]).squeeze(-1)
    expected = 0.5 * 2.0 * (twist[:, :3] ** 2).sum(-1) + 0.5 * torch.einsum(
        "bi,ij,bj->b", w_body, inertia[0], w_body
    )
    torch.testing.assert_close(energy, expected, rtol=1e-12, atol=0.0)


def test_spin_about_a_principal_axis_is_unchanged() -> None:
    inertia = torch.diag(torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64))
    quaternion = random_quaternions(1)[0]
    R = quat_to_matrix(quaternion)
    omega = 7.0 * R[:, 1]  # the body's y axis, in the world frame
    after = free_angular_velocity(inertia, quaternion, omega, 0.01)
    torch.testing.assert_close(after, omega, rtol=1e-13, atol=1e-13)


def test_symmetric_top_precesses_at_the_closed_form_rate() -> None:
    """Torque-free axisymmetric body (I₁ = I₂): in the body frame ω₃ is constant and (ω₁, ω₂)
    turns at Ω = (I₃ − I₁)/I₁ ω₃ (Landau & Lifshitz, Mechanics, §33). The scheme is first order
    in h: at h = 1e-4 over 0.5 s the body-frame components match to 1e-3 of |ω|."""
    I1, I3 = 0.2, 0.5
    inertia = torch.diag(torch.tensor([I1, I1, I3], dtype=torch.float64))
    w_body0 = torch.tensor([1.0, 0.0, 4.0], dtype=torch.float64)
    q = torch.tensor([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    h, steps = 1e-4, 5000
    omega = w_body0.clone()  # world = body at the identity
    for _ in range(steps):
        omega = free_angular_velocity(inertia, q[0, 3:], omega, h)
        q = integrate_poses(q, torch.cat([torch.zeros(3, dtype=torch.float64), omega])[None], h)
    R = quat_to_matrix(q[0, 3:])
    w_body = R.T @ omega
    rate = (I3 - I1) / I1 * 4.0
    t = h * steps
    # Euler: ω̇₁ = −Ω ω₂, ω̇₂ = Ω ω₁, so (ω₁, ω₂) = (cos Ωt, sin Ωt) from (1, 0).
    expected = torch.tensor([math.cos(rate * t), math.sin(rate * t), 4.0], dtype=torch.float64)
    torch.testing.assert_close(w_body, expected, rtol=0.0, atol=1e-3 * w_body0.norm().item())


def test_tumbling_never_gains_energy() -> None:
    """A body spinning near its intermediate axis tumbles; the implicit step's rotational energy
    never increases, and its world angular momentum stays within 2 % over 2 s."""
    inertia = torch.diag(torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64))
    q = torch.tensor([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    omega = torch.tensor([0.01, 10.0, 0.01], dtype=torch.float64)
    h = 0.002

    def energy_and_momentum(q: torch.Tensor, omega: torch.Tensor) -> tuple[float, torch.Tensor]:
        R = quat_to_matrix(q[0, 3:])
        I_world = R @ inertia @ R.T
        return float(0.5 * omega @ I_world @ omega), I_world @ omega

    energy, start_momentum = energy_and_momentum(q, omega)
    for _ in range(1000):
        omega = free_angular_velocity(inertia, q[0, 3:], omega, h)
        q = integrate_poses(q, torch.cat([torch.zeros(3, dtype=torch.float64), omega])[None], h)
        next_energy, next_momentum = energy_and_momentum(q, omega)
        assert next_energy <= energy * (1 + 1e-12)
        energy = next_energy
    assert float((next_momentum - start_momentum).norm()) <= 0.02 * float(start_momentum.norm())


def test_integration_composes_to_the_exact_rotation() -> None:
    """Constant ω for N steps is the rotation exp(N h ω): composition of equal rotations."""
    q = torch.cat([torch.randn(4, 1, 3, dtype=torch.float64), random_quaternions(4, 1)], -1)
    v = torch.randn(4, 1, 6, dtype=torch.float64)
    h, steps = 0.01, 50
    pose = q
    for _ in range(steps):
        pose = integrate_poses(pose, v, h)
    torch.testing.assert_close(
        pose[..., :3], q[..., :3] + steps * h * v[..., :3], rtol=1e-12, atol=1e-12
    )
    expected = quat_mul(quat_exp(steps * h * v[..., 3:]), q[..., 3:])
    sign = torch.sign((pose[..., 3:] * expected).sum(-1, keepdim=True))
    torch.testing.assert_close(pose[..., 3:], sign * expected, rtol=0.0, atol=1e-12)
    torch.testing.assert_close(
        pose[..., 3:].norm(dim=-1), torch.ones(4, 1, dtype=torch.float64), rtol=0.0, atol=1e-14
    )


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_tangent_basis_is_a_right_handed_orthonormal_frame(dtype: torch.dtype) -> None:
    normal = torch.randn(200, 3, dtype=dtype)
    normal = torch.cat(
        [
            normal,
            torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, 1e-9, -1.0]], dtype=dtype),
        ]
    )
    normal = normal / normal.norm(dim=-1, keepdim=True)
    basis = tangent_basis(normal)
    frame = torch.cat([basis, normal.unsqueeze(-2)], dim=-2)  # rows t1, t2, n
    eps = torch.finfo(dtype).eps
    torch.testing.assert_close(
        frame @ frame.transpose(-1, -2),
        torch.eye(3, dtype=dtype).expand(len(normal), 3, 3),
        rtol=0.0,
        atol=20 * eps,
    )
    torch.testing.assert_close(
        torch.linalg.det(frame), torch.ones(len(normal), dtype=dtype), rtol=0.0, atol=20 * eps
    )


def test_tangent_directions_follow_the_problem_convention() -> None:
    normal = torch.randn(50, 3, dtype=torch.float64)
    normal = normal / normal.norm(dim=-1, keepdim=True)
    for D in (4, 6, 8):
        directions = tangent_directions(normal, D)
        assert directions.shape == (50, D, 3)
        assert ((directions[:, : D // 2] + directions[:, D // 2 :]) == 0).all()  # exact: negated
        torch.testing.assert_close(
            (directions * normal[:, None]).sum(-1),
            torch.zeros(50, D, dtype=torch.float64),
            rtol=0.0,
            atol=1e-14,
        )
        # consecutive directions are 2π/D apart, counter-clockwise about n
        nxt = directions.roll(-1, dims=1)
        cos = (directions * nxt).sum(-1)
        sin = (torch.linalg.cross(directions, nxt) * normal[:, None]).sum(-1)
        torch.testing.assert_close(
            torch.atan2(sin, cos),
            torch.full((50, D), 2 * math.pi / D, dtype=torch.float64),
            rtol=0.0,
            atol=1e-12,
        )
    with pytest.raises(ValueError, match="num_directions"):
        tangent_directions(normal, 3)


def test_mass_solves_of_an_assembled_spatial_problem_invert_its_mass_matrix() -> None:
    """The assembled problem of two boxes at random orientations solves ``M x = rhs``
    (``M`` block-diagonal of ``m 1₃`` and ``R I Rᵀ``) to rounding: by the closed-form inverse
    the assembler keeps on the problem when nothing requires grad, by Cholesky otherwise."""
    quaternion = random_quaternions(6, 2)
    position = torch.tensor([[0.0, 0.0, 0.3], [2.0, 0.0, 0.4]], dtype=torch.float64)
    q = torch.cat([position.expand(6, 2, 3), quaternion], -1)
    rhs = torch.randn(6, 12, 3, dtype=torch.float64)
    for mass in (2.0, torch.tensor(2.0, dtype=torch.float64, requires_grad=True)):
        scene = Scene(
            bodies=(
                Body("ground", HalfSpace.ground(), kind="static"),
                Body("long", Box([0.5, 0.25, 0.25]), mass=mass),
                Body("flat", Box([0.3, 0.3, 0.1]), mass=0.7),
            ),
            gravity=(0.0, 0.0, -9.81),
            h=0.01,
        )
        state = Simulator(scene).initial_state(q=q, v=torch.zeros(6, 2, 6, dtype=torch.float64))
        with torch.no_grad():
            problem, _ = contact_problem(scene, state)
            x = problem.mass_solve(rhs)
        torch.testing.assert_close(problem.M @ x, rhs, rtol=1e-12, atol=1e-12)
