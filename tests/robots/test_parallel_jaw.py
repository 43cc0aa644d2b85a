"""The parallel-jaw gripper against its documented dimensions."""

from __future__ import annotations

import torch

from torchcontact.robots import load

FINGER_LENGTH = 0.06


def test_symmetric_gripper_has_one_coordinate() -> None:
    jaw = load("parallel_jaw")
    assert jaw.joint_names == ("jaw_left",)
    torch.testing.assert_close(jaw.lower, torch.tensor([0.0], dtype=torch.float64))
    torch.testing.assert_close(jaw.upper, torch.tensor([0.05], dtype=torch.float64))


def test_finger_frames_follow_the_opening() -> None:
    jaw = load("parallel_jaw")
    half = torch.tensor([[0.0], [0.013], [0.05]], dtype=torch.float64)
    frames = jaw.forward_kinematics(half)
    zeros = torch.zeros_like(half[:, 0])
    left = torch.stack([-half[:, 0], zeros, zeros], dim=-1)
    right = torch.stack([half[:, 0], zeros, zeros], dim=-1)
    along = torch.tensor([0.0, FINGER_LENGTH, 0.0], dtype=torch.float64)
    torch.testing.assert_close(frames["jaw_left_finger"][:, :3, 3], left)
    torch.testing.assert_close(frames["jaw_right_finger"][:, :3, 3], right)
    torch.testing.assert_close(frames["jaw_left_tip"][:, :3, 3], left + along)
    torch.testing.assert_close(frames["jaw_right_tip"][:, :3, 3], right + along)
    # Finger frames: x away from the centreline, y along the approach direction.
    for link, sign in (("jaw_left_finger", -1.0), ("jaw_right_finger", 1.0)):
        torch.testing.assert_close(
            frames[link][:, :3, 0], sign * torch.eye(3, dtype=torch.float64)[0].expand(3, 3)
        )
        torch.testing.assert_close(
            frames[link][:, :3, 1], torch.eye(3, dtype=torch.float64)[1].expand(3, 3)
        )


def test_jacobians_of_the_fingertips() -> None:
    q = torch.tensor([0.02], dtype=torch.float64)
    symmetric = load("parallel_jaw")
    torch.testing.assert_close(
        symmetric.jacobian(q, "jaw_left_tip")[:, 0],
        torch.tensor([-1.0, 0, 0, 0, 0, 0], dtype=torch.float64),
    )
    torch.testing.assert_close(
        symmetric.jacobian(q, "jaw_right_tip")[:, 0],
        torch.tensor([1.0, 0, 0, 0, 0, 0], dtype=torch.float64),
    )
    independent = load("parallel_jaw", coupled=False)
    assert independent.joint_names == ("jaw_left", "jaw_right")
    jac = independent.jacobian(torch.tensor([0.01, 0.03], dtype=torch.float64), "jaw_right_tip")
    torch.testing.assert_close(jac[:, 0], torch.zeros(6, dtype=torch.float64))
    torch.testing.assert_close(jac[:, 1], torch.tensor([1.0, 0, 0, 0, 0, 0], dtype=torch.float64))
