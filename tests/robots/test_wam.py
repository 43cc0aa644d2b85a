"""The WAM against an independent NumPy version of Barrett's DH table and finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcontact.robots import load

# Barrett WAM Arm User's Manual, 7-DOF DH table (Spong: T_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)).
DH_A = (0.0, 0.0, 0.045, -0.045, 0.0, 0.0, 0.0)
DH_ALPHA = (-math.pi / 2, math.pi / 2, -math.pi / 2, math.pi / 2, -math.pi / 2, math.pi / 2, 0.0)
DH_D = (0.0, 0.0, 0.55, 0.0, 0.3, 0.0, 0.06)
LOWER = np.array([-2.6, -2.0, -2.8, -0.9, -4.76, -1.6, -3.0])
UPPER = np.array([2.6, 2.0, 2.8, 3.1, 1.24, 1.6, 3.0])


def dh_frames(q: np.ndarray) -> list[np.ndarray]:
    """DH frames 0..7 (base, then after each joint) of one configuration ``q`` ``(7,)``."""
    frames = [np.eye(4)]
    for qi, a, alpha, d in zip(q, DH_A, DH_ALPHA, DH_D, strict=True):
        c, s = math.cos(qi), math.sin(qi)
        ca, sa = math.cos(alpha), math.sin(alpha)
        step = np.array(
            [
                [c, -s * ca, s * sa, a * c],
                [s, c * ca, -c * sa, a * s],
                [0.0, sa, ca, d],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )
        frames.append(frames[-1] @ step)
    return frames


def dh_jacobian(q: np.ndarray, point_world: np.ndarray) -> np.ndarray:
    """Spong's geometric Jacobian ``(6, 7)`` of a world point moving with link 7."""
    frames = dh_frames(q)
    columns = []
    for i in range(7):
        z, o = frames[i][:3, 2], frames[i][:3, 3]
        columns.append(np.concatenate([np.cross(z, point_world - o), z]))
    return np.stack(columns, axis=1)


def random_q(n: int, rng: np.random.Generator) -> np.ndarray:
    return rng.uniform(LOWER, UPPER, size=(n, 7))


def test_zero_configuration_puts_tool_at_091() -> None:
    robot = load("wam7")
    tool = robot.forward_kinematics(torch.zeros(7, dtype=torch.float64), "wam_tool")
    torch.testing.assert_close(tool[:3, 3], torch.tensor([0.0, 0.0, 0.91], dtype=torch.float64))
    torch.testing.assert_close(tool[:3, :3], torch.eye(3, dtype=torch.float64))


@pytest.mark.bitwise("limits are parsed from decimal strings, correctly rounded")
def test_joint_metadata_and_limits() -> None:
    robot = load("wam7")
    assert robot.dof == 7
    assert robot.joint_names == tuple(f"wam_j{i}" for i in range(1, 8))
    assert robot.link_names[0] == "wam_base"
    np.testing.assert_array_equal(robot.lower.numpy(), LOWER)
    np.testing.assert_array_equal(robot.upper.numpy(), UPPER)


def test_forward_kinematics_matches_dh_table() -> None:
    rng = np.random.default_rng(1)
    robot = load("wam7")
    q = random_q(300, rng)
    frames = robot.forward_kinematics(torch.from_numpy(q))
    for b in range(q.shape[0]):
        reference = dh_frames(q[b])
        np.testing.assert_allclose(frames["wam_tool"][b].numpy(), reference[7], atol=1e-12)
        for i in range(1, 8):
            # Link frame i = DH frame (i-1) rotated by q_i about its z axis.
            c, s = math.cos(q[b, i - 1]), math.sin(q[b, i - 1])
            rz = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
            np.testing.assert_allclose(
                frames[f"wam_link{i}"][b].numpy(), reference[i - 1] @ rz, atol=1e-12
            )


def test_float32_forward_kinematics_is_float64_rounded() -> None:
    rng = np.random.default_rng(2)
    robot = load("wam7")
    q = random_q(200, rng)
    tool32 = robot.forward_kinematics(torch.from_numpy(q).float(), "wam_tool")
    assert tool32.dtype == torch.float32
    reference = np.stack([dh_frames(qb)[7] for qb in q])
    np.testing.assert_allclose(tool32.double().numpy(), reference, atol=2e-6)


def test_jacobian_matches_dh_jacobian_at_a_point() -> None:
    rng = np.random.default_rng(3)
    robot = load("wam7")
    q = random_q(200, rng)
    point = rng.normal(scale=0.1, size=(200, 3))
    jac = robot.jacobian(torch.from_numpy(q), "wam_link7", point=torch.from_numpy(point))
    for b in range(q.shape[0]):
        frames = dh_frames(q[b])
        # wam_link7 = DH frame 6 . Rz(q7); the point is given in wam_link7's frame.
        c, s = math.cos(q[b, 6]), math.sin(q[b, 6])
        link7 = frames[6] @ np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
        world = link7[:3, :3] @ point[b] + link7[:3, 3]
        np.testing.assert_allclose(jac[b].numpy(), dh_jacobian(q[b], world), atol=1e-12)


def test_jacobian_of_intermediate_link_has_zero_columns_beyond_it() -> None:
    rng = np.random.default_rng(4)
    robot = load("wam7")
    q = torch.from_numpy(random_q(10, rng))
    jac = robot.jacobian(q, "wam_link3")
    assert torch.all(jac[..., 3:] == 0)
    assert torch.all(jac[..., :3].abs().sum(dim=-2) > 0)


def _rotation_vee(m: np.ndarray) -> np.ndarray:
    return np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]]) / 2.0


def test_jacobian_matches_central_differences_of_forward_kinematics() -> None:
    rng = np.random.default_rng(5)
    robot = load("wam7")
    h = 1e-6
    for _ in range(20):
        q = torch.from_numpy(random_q(1, rng)[0])
        point = torch.from_numpy(rng.normal(scale=0.1, size=3))
        jac = robot.jacobian(q, "wam_tool", point=point).numpy()
        steps = torch.eye(7, dtype=torch.float64) * h
        plus = robot.forward_kinematics(q + steps, "wam_tool").numpy()
        minus = robot.forward_kinematics(q - steps, "wam_tool").numpy()
        pose = robot.forward_kinematics(q, "wam_tool").numpy()
        p = point.numpy()
        for k in range(7):
            dx = ((plus[k, :3, :3] - minus[k, :3, :3]) @ p + plus[k, :3, 3] - minus[k, :3, 3]) / (
                2 * h
            )
            omega = _rotation_vee((plus[k, :3, :3] - minus[k, :3, :3]) / (2 * h) @ pose[:3, :3].T)
            np.testing.assert_allclose(jac[:3, k], dx, atol=1e-8)
            np.testing.assert_allclose(jac[3:, k], omega, atol=1e-8)


def test_autograd_through_forward_kinematics_agrees_with_jacobian() -> None:
    rng = np.random.default_rng(6)
    robot = load("wam7")
    q = torch.from_numpy(random_q(1, rng)[0]).requires_grad_(True)
    position = robot.forward_kinematics(q, "wam_tool")[:3, 3]
    rows = [torch.autograd.grad(position[i], q, retain_graph=True)[0] for i in range(3)]
    jac = robot.jacobian(q.detach(), "wam_tool")
    torch.testing.assert_close(torch.stack(rows), jac[:3])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_batch_of_ten_thousand(dtype: torch.dtype) -> None:
    rng = np.random.default_rng(7)
    robot = load("wam7")
    q = torch.from_numpy(random_q(10_000, rng)).to(dtype)
    tool = robot.forward_kinematics(q, "wam_tool")
    jac = robot.jacobian(q, "wam_tool")
    assert tool.shape == (10_000, 4, 4)
    assert tool.dtype == dtype
    assert jac.shape == (10_000, 6, 7)
    assert jac.dtype == dtype
    for b in (0, 4_321, 9_999):
        reference = dh_frames(q[b].double().numpy())
        tol = 1e-12 if dtype == torch.float64 else 2e-6
        np.testing.assert_allclose(tool[b].double().numpy(), reference[7], atol=tol)
        np.testing.assert_allclose(
            jac[b].double().numpy(),
            dh_jacobian(q[b].double().numpy(), reference[7][:3, 3]),
            atol=tol,
        )


def test_leading_batch_dimensions_are_kept() -> None:
    rng = np.random.default_rng(8)
    robot = load("wam7")
    q = torch.from_numpy(random_q(12, rng)).reshape(3, 4, 7)
    assert robot.forward_kinematics(q, "wam_link4").shape == (3, 4, 4, 4)
    assert robot.jacobian(q, "wam_link4").shape == (3, 4, 6, 7)
    point = torch.zeros(5, 1, 1, 3, dtype=torch.float64)
    assert robot.jacobian(q, "wam_link4", point=point).shape == (5, 3, 4, 6, 7)
