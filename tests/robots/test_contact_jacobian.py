"""Contact Jacobians against finite differences of the contact point's projected position."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcontact.robots import load


def contact_frame(normal: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit normal and D unit tangents spaced evenly around it."""
    n = normal / np.linalg.norm(normal)
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    angles = 2 * math.pi * np.arange(d) / d
    return n, np.stack([math.cos(a) * t1 + math.sin(a) * t2 for a in angles])


@pytest.mark.parametrize(
    ("name", "link"),
    [("wam7", "wam_link5"), ("wam7_bhand", "bhand_f2_outer"), ("bhand", "bhand_f1_tip")],
)
def test_contact_jacobian_matches_finite_differences(name: str, link: str) -> None:
    rng = np.random.default_rng(21)
    robot = load(name)
    h = 1e-6
    for _ in range(5):
        q = torch.from_numpy(rng.uniform(robot.lower.numpy(), robot.upper.numpy()))
        point = torch.from_numpy(rng.normal(scale=0.02, size=3))
        n, t = contact_frame(rng.normal(size=3), 4)
        normal, tangents = torch.from_numpy(n), torch.from_numpy(t)
        jn, jt = robot.contact_jacobian(q, link, point=point, normal=normal, tangents=tangents)
        assert jn.shape == (robot.dof,)
        assert jt.shape == (4, robot.dof)
        for k in range(robot.dof):
            step = torch.zeros(robot.dof, dtype=torch.float64)
            step[k] = h
            plus = robot.forward_kinematics(q + step, link)
            minus = robot.forward_kinematics(q - step, link)
            velocity = ((plus[:3, :3] - minus[:3, :3]) @ point + plus[:3, 3] - minus[:3, 3]) / (
                2 * h
            )
            torch.testing.assert_close(jn[k], normal @ velocity, atol=1e-8, rtol=0)
            torch.testing.assert_close(jt[:, k], tangents @ velocity, atol=1e-8, rtol=0)


def test_gap_rate_of_a_fingertip_against_a_plane() -> None:
    # A plane through the origin with normal n pointing toward the robot: gap = n . x_tip. A joint
    # velocity qdot changes it at Jn qdot (the known term bn of a kinematically driven robot).
    rng = np.random.default_rng(22)
    hand = load("bhand")
    q = torch.tensor([0.4, 1.0, 1.2, 0.8], dtype=torch.float64)
    qdot = torch.from_numpy(rng.normal(size=4))
    n = torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64)
    t = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]], dtype=torch.float64)
    tip = torch.zeros(3, dtype=torch.float64)
    jn, jt = hand.contact_jacobian(q, "bhand_f3_tip", point=tip, normal=n, tangents=t)
    dt = 1e-6
    gap = [n @ hand.forward_kinematics(q + s * dt * qdot, "bhand_f3_tip")[:3, 3] for s in (-1, 1)]
    torch.testing.assert_close(jn @ qdot, (gap[1] - gap[0]) / (2 * dt), atol=1e-8, rtol=0)
    torch.testing.assert_close(jt[0], -jt[1])


def test_many_contacts_on_one_configuration_broadcast() -> None:
    rng = np.random.default_rng(23)
    robot = load("wam7")
    q = torch.from_numpy(rng.uniform(robot.lower.numpy(), robot.upper.numpy()))
    frames = [contact_frame(rng.normal(size=3), 2) for _ in range(6)]
    normal = torch.from_numpy(np.stack([f[0] for f in frames]))
    tangents = torch.from_numpy(np.stack([f[1] for f in frames]))
    point = torch.from_numpy(rng.normal(scale=0.05, size=(6, 3)))
    jn, jt = robot.contact_jacobian(q, "wam_tool", point=point, normal=normal, tangents=tangents)
    assert jn.shape == (6, 7)
    assert jt.shape == (6, 2, 7)
    for k in range(6):
        single_n, single_t = robot.contact_jacobian(
            q, "wam_tool", point=point[k], normal=normal[k], tangents=tangents[k]
        )
        torch.testing.assert_close(jn[k], single_n)
        torch.testing.assert_close(jt[k], single_t)


def test_float32_contact_jacobian_agrees_with_float64() -> None:
    rng = np.random.default_rng(24)
    robot = load("wam7_bhand")
    q = torch.from_numpy(
        rng.uniform(robot.lower.numpy(), robot.upper.numpy(), size=(64, robot.dof))
    )
    n, t = contact_frame(np.array([0.2, -0.3, 0.9]), 4)
    args = {
        "point": torch.zeros(3, dtype=torch.float64),
        "normal": torch.from_numpy(n),
        "tangents": torch.from_numpy(t),
    }
    jn64, jt64 = robot.contact_jacobian(q, "bhand_f1_tip", **args)
    jn32, jt32 = robot.contact_jacobian(
        q.float(), "bhand_f1_tip", **{k: v.float() for k, v in args.items()}
    )
    assert jn32.dtype == torch.float32
    torch.testing.assert_close(jn32.double(), jn64, atol=1e-5, rtol=0)
    torch.testing.assert_close(jt32.double(), jt64, atol=1e-5, rtol=0)


def test_contact_jacobian_is_differentiable_in_q() -> None:
    # d(Jn q̇)/dq by autograd (pytorch-kinematics' analytical FK backward) vs central differences.
    rng = np.random.default_rng(25)
    robot = load("wam7")
    q0 = torch.from_numpy(rng.uniform(robot.lower.numpy(), robot.upper.numpy()))
    qdot = torch.from_numpy(rng.normal(size=7))
    n, t = contact_frame(rng.normal(size=3), 2)
    args = {
        "point": torch.tensor([0.01, -0.02, 0.03], dtype=torch.float64),
        "normal": torch.from_numpy(n),
        "tangents": torch.from_numpy(t),
    }

    def rate(q: torch.Tensor) -> torch.Tensor:
        return robot.contact_jacobian(q, "wam_link6", **args)[0] @ qdot

    q = q0.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(rate(q), q)
    h = 1e-6
    steps = torch.eye(7, dtype=torch.float64) * h
    fd = torch.stack([(rate(q0 + s) - rate(q0 - s)) / (2 * h) for s in steps])
    torch.testing.assert_close(grad, fd, atol=1e-7, rtol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu() -> None:
    rng = np.random.default_rng(26)
    robot = load("wam7_bhand")
    q = torch.from_numpy(
        rng.uniform(robot.lower.numpy(), robot.upper.numpy(), size=(32, robot.dof))
    )
    point = torch.from_numpy(rng.normal(scale=0.01, size=(32, 3)))
    for dtype in (torch.float32, torch.float64):
        cpu = robot.jacobian(q.to(dtype), "bhand_f2_tip", point=point.to(dtype))
        gpu = robot.jacobian(q.to("cuda", dtype), "bhand_f2_tip", point=point.to("cuda", dtype))
        assert gpu.device.type == "cuda"
        torch.testing.assert_close(gpu.cpu(), cpu, atol=1e-5, rtol=1e-5)
