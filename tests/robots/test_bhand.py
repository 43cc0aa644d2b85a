"""The BarrettHand against closed-form planar finger geometry from Barrett's published dimensions,
its coupling map, and the WAM + hand composition."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcontact.robots import load

# BarrettHand BH8-series User's Manual, finger kinematics (metres, radians).
AW, A1, A2, A3, DW, D3 = 0.025, 0.05, 0.07, 0.05, 0.084, 0.0095
PHI2, PHI3 = 0.0, math.radians(42.0)
R = {1: -1.0, 2: 1.0, 3: 0.0}
J = {1: 1.0, 2: 1.0, 3: -1.0}


def finger_geometry(k: int, spread: float, inner: float, outer: float) -> dict[str, np.ndarray]:
    """Closed-form planar finger: knuckle, outer-joint and fingertip positions and the tip rotation.

    The finger moves in the vertical plane through its knuckle spanned by the radial direction u
    (angle r*spread - j*pi/2 in the palm plane) and the palm normal: the inner link leaves the
    knuckle at height 0 and angle ``inner`` above u, the outer link continues at
    ``inner + outer + Phi3``, and the tip frame sits A3 along the outer link and D3 across it
    (towards the palm-normal side).
    """
    theta = R[k] * spread - J[k] * math.pi / 2
    u = np.array([math.cos(theta), math.sin(theta), 0.0])
    w = np.array([0.0, 0.0, 1.0])
    base = np.array([R[k] * AW, 0.0, DW])
    a2 = inner + PHI2
    phi = a2 + outer + PHI3
    knuckle = base + A1 * u
    outer_joint = knuckle + A2 * (math.cos(a2) * u + math.sin(a2) * w)
    along = math.cos(phi) * u + math.sin(phi) * w
    across = -math.sin(phi) * u + math.cos(phi) * w
    tip = outer_joint + A3 * along + D3 * across
    rotation = np.stack([along, np.cross(across, along), across], axis=1)
    return {"knuckle": knuckle, "outer_joint": outer_joint, "tip": tip, "tip_rotation": rotation}


def hand_configurations(n: int, rng: np.random.Generator) -> np.ndarray:
    """Actuated configurations (spread, F1 inner, F2 inner, F3 inner) within the limits."""
    spread = rng.uniform(0.0, math.pi, size=(n, 1))
    inner = rng.uniform(0.0, 2.44, size=(n, 3))
    return np.concatenate([spread, inner], axis=1)


def test_actuated_coordinates_and_limits() -> None:
    hand = load("bhand")
    assert hand.joint_names == (
        "bhand_f1_spread",
        "bhand_f1_inner",
        "bhand_f2_inner",
        "bhand_f3_inner",
    )
    np.testing.assert_allclose(hand.lower.numpy(), [0.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(hand.upper.numpy(), [math.pi, 2.44, 2.44, 2.44])
    full = load("bhand", coupled=False)
    assert full.dof == 8
    limits = dict(
        zip(
            full.joint_names,
            zip(full.lower.tolist(), full.upper.tolist(), strict=True),
            strict=True,
        )
    )
    for k in (1, 2, 3):
        assert limits[f"bhand_f{k}_inner"] == (0.0, 2.44)
        assert limits[f"bhand_f{k}_outer"] == (0.0, 0.84)
    assert limits["bhand_f1_spread"] == limits["bhand_f2_spread"] == (0.0, math.pi)


def test_coupling_map() -> None:
    hand = load("bhand")
    coupling = hand.coupling
    q = torch.tensor([0.3, 0.9, 1.5, 2.1], dtype=torch.float64)
    full = dict(zip(coupling.full_names, coupling.to_full(q).tolist(), strict=True))
    assert full == pytest.approx(
        {
            "bhand_f1_spread": 0.3,
            "bhand_f2_spread": 0.3,
            "bhand_f1_inner": 0.9,
            "bhand_f1_outer": 0.3,
            "bhand_f2_inner": 1.5,
            "bhand_f2_outer": 0.5,
            "bhand_f3_inner": 2.1,
            "bhand_f3_outer": 0.7,
        }
    )
    # Inner at its upper limit keeps the outer joint within its own limit.
    assert 2.44 / 3 <= 0.84


def test_fingertips_at_zero_match_closed_form() -> None:
    hand = load("bhand")
    frames = hand.forward_kinematics(torch.zeros(4, dtype=torch.float64))
    for k in (1, 2, 3):
        reference = finger_geometry(k, 0.0, 0.0, 0.0)
        np.testing.assert_allclose(
            frames[f"bhand_f{k}_tip"][:3, 3].numpy(), reference["tip"], atol=1e-12
        )
    # At zero spread F1 and F2 sit side by side, opposite F3.
    assert frames["bhand_f1_tip"][1, 3] < 0
    assert frames["bhand_f3_tip"][1, 3] > 0


def test_coupled_fingers_match_closed_form() -> None:
    rng = np.random.default_rng(11)
    hand = load("bhand")
    q = hand_configurations(100, rng)
    frames = hand.forward_kinematics(torch.from_numpy(q))
    for b in range(q.shape[0]):
        for k in (1, 2, 3):
            spread = q[b, 0] if k != 3 else 0.0
            inner = q[b, k]
            reference = finger_geometry(k, spread, inner, inner / 3.0)
            np.testing.assert_allclose(
                frames[f"bhand_f{k}_inner"][b, :3, 3].numpy(), reference["knuckle"], atol=1e-12
            )
            np.testing.assert_allclose(
                frames[f"bhand_f{k}_outer"][b, :3, 3].numpy(), reference["outer_joint"], atol=1e-12
            )
            np.testing.assert_allclose(
                frames[f"bhand_f{k}_tip"][b, :3, 3].numpy(), reference["tip"], atol=1e-12
            )
            np.testing.assert_allclose(
                frames[f"bhand_f{k}_tip"][b, :3, :3].numpy(), reference["tip_rotation"], atol=1e-12
            )


def test_uncoupled_fingers_match_closed_form() -> None:
    rng = np.random.default_rng(12)
    hand = load("bhand", coupled=False)
    names = hand.joint_names
    q = np.stack(
        [rng.uniform(*(0.0, 0.84) if n.endswith("outer") else (0.0, 2.44), size=50) for n in names],
        axis=1,
    )
    frames = hand.forward_kinematics(torch.from_numpy(q))
    value = {n: q[:, i] for i, n in enumerate(names)}
    for b in range(q.shape[0]):
        for k in (1, 2, 3):
            spread = value[f"bhand_f{k}_spread"][b] if k != 3 else 0.0
            reference = finger_geometry(
                k, spread, value[f"bhand_f{k}_inner"][b], value[f"bhand_f{k}_outer"][b]
            )
            np.testing.assert_allclose(
                frames[f"bhand_f{k}_tip"][b, :3, 3].numpy(), reference["tip"], atol=1e-12
            )


def test_spread_moves_f1_and_f2_symmetrically() -> None:
    rng = np.random.default_rng(13)
    hand = load("bhand")
    q = hand_configurations(20, rng)
    q[:, 2] = q[:, 1]  # same inner angle on F1 and F2
    frames = hand.forward_kinematics(torch.from_numpy(q))
    f1, f2 = frames["bhand_f1_tip"][:, :3, 3], frames["bhand_f2_tip"][:, :3, 3]
    mirror = torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(f1 * mirror, f2)


def test_actuated_jacobian_is_full_jacobian_times_coupling() -> None:
    rng = np.random.default_rng(14)
    hand = load("bhand")
    full = load("bhand", coupled=False)
    q = torch.from_numpy(hand_configurations(30, rng))
    q_full = hand.coupling.to_full(q)
    point = torch.from_numpy(rng.normal(scale=0.01, size=(30, 3)))
    for k in (1, 2, 3):
        link = f"bhand_f{k}_tip"
        actuated = hand.jacobian(q, link, point=point)
        expected = full.jacobian(q_full, link, point=point) @ hand.coupling.matrix
        torch.testing.assert_close(actuated, expected)
        torch.testing.assert_close(
            hand.forward_kinematics(q, link), full.forward_kinematics(q_full, link)
        )


def test_actuated_jacobian_matches_central_differences() -> None:
    rng = np.random.default_rng(15)
    hand = load("bhand")
    q = torch.from_numpy(hand_configurations(1, rng)[0])
    h = 1e-6
    steps = torch.eye(4, dtype=torch.float64) * h
    for k in (1, 2, 3):
        link = f"bhand_f{k}_tip"
        jac = hand.jacobian(q, link)
        dx = (
            hand.forward_kinematics(q + steps, link)[:, :3, 3]
            - hand.forward_kinematics(q - steps, link)[:, :3, 3]
        ) / (2 * h)
        torch.testing.assert_close(jac[:3], dx.T, atol=1e-8, rtol=0)
        # Only the spread (F1, F2) and the finger's own inner joint move the tip.
        moving = {0, k} if k != 3 else {k}
        for column in range(4):
            assert bool(jac[:, column].abs().max() > 0) == (column in moving)


def test_wam_with_hand_composes_tool_and_hand_transforms() -> None:
    rng = np.random.default_rng(16)
    arm, hand, both = load("wam7"), load("bhand"), load("wam7_bhand")
    assert both.joint_names == arm.joint_names + hand.joint_names
    assert set(both.link_names) == set(arm.link_names) | set(hand.link_names)
    q_arm = torch.from_numpy(rng.uniform(arm.lower.numpy(), arm.upper.numpy(), size=(40, 7)))
    q_hand = torch.from_numpy(hand_configurations(40, rng))
    q = torch.cat([q_arm, q_hand], dim=-1)
    frames = both.forward_kinematics(q)
    tool = arm.forward_kinematics(q_arm, "wam_tool")
    torch.testing.assert_close(frames["bhand_palm"], tool)
    for link, pose in hand.forward_kinematics(q_hand).items():
        torch.testing.assert_close(frames[link], tool @ pose)
    for link, pose in arm.forward_kinematics(q_arm).items():
        torch.testing.assert_close(frames[link], pose)
    # Jacobian of a fingertip: arm columns move it rigidly with the tool; hand columns are the
    # hand's Jacobian rotated into the world frame.
    tip = both.jacobian(q, "bhand_f3_tip")
    hand_tip = hand.jacobian(q_hand, "bhand_f3_tip")
    rotation = tool[:, :3, :3]
    torch.testing.assert_close(tip[:, :3, 7:], rotation @ hand_tip[:, :3])
    torch.testing.assert_close(tip[:, 3:, 7:], rotation @ hand_tip[:, 3:])
    tip_in_tool = torch.linalg.solve(tool, frames["bhand_f3_tip"])[:, :3, 3]
    torch.testing.assert_close(tip[:, :, :7], arm.jacobian(q_arm, "wam_tool", point=tip_in_tool))
