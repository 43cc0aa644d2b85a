"""Manipulation states: relative poses, the pose grid, canonical states."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from tests.states.scenes import box_step, stack
from torchcontact.states import (
    ContactState,
    FeatureGrid,
    ManipulationState,
    PoseGrid,
    manipulation_states,
    relative_pose,
)

CONTACT_GRID = FeatureGrid(dim=2, radius=0.05, angle=math.radians(15))
POSE_GRID = PoseGrid(dim=2, position_step=0.05, angle_step=math.pi / 4)


def _homogeneous(pose: torch.Tensor) -> np.ndarray:
    x, y, theta = pose.tolist()
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])


def test_planar_relative_pose_matches_homogeneous_matrices() -> None:
    gen = torch.Generator().manual_seed(0)
    objects = 3 * torch.randn(20, 3, generator=gen)
    robots = 3 * torch.randn(20, 3, generator=gen)
    relative = relative_pose(objects, robots)
    for i in range(20):
        T = np.linalg.solve(_homogeneous(objects[i]), _homogeneous(robots[i]))
        assert np.allclose(relative[i, :2].numpy(), T[:2, 2], atol=1e-12)
        assert math.isclose(math.cos(relative[i, 2]), T[0, 0], abs_tol=1e-12)
        assert math.isclose(math.sin(relative[i, 2]), T[1, 0], abs_tol=1e-12)
        assert -math.pi <= float(relative[i, 2]) < math.pi


def test_spatial_relative_pose_matches_scipy() -> None:
    gen = torch.Generator().manual_seed(1)
    poses = torch.randn(2, 20, 7, generator=gen)
    poses[..., 3:] = poses[..., 3:] / poses[..., 3:].norm(dim=-1, keepdim=True)
    relative = relative_pose(poses[0], poses[1])
    for i in range(20):
        R_o = Rotation.from_quat(poses[0, i, 3:].numpy(), scalar_first=True)
        R_r = Rotation.from_quat(poses[1, i, 3:].numpy(), scalar_first=True)
        position = R_o.inv().apply(poses[1, i, :3].numpy() - poses[0, i, :3].numpy())
        assert np.allclose(relative[i, :3].numpy(), position, atol=1e-12)
        expected = (R_o.inv() * R_r).as_matrix()
        actual = Rotation.from_quat(relative[i, 3:].numpy(), scalar_first=True).as_matrix()
        assert np.allclose(actual, expected, atol=1e-12)
        assert float(relative[i, 3]) >= 0


def test_planar_pose_grid_rounds_and_wraps() -> None:
    # 8 angle bins of width π/4 centred on kπ/4; the bin of π straddles ±π.
    assert POSE_GRID.angle_bins == 8
    poses = torch.tensor(
        [
            [0.124, -0.126, 0.0],
            [0.126, -0.124, math.pi / 8 - 1e-9],
            [0.0, 0.0, math.pi / 8 + 1e-9],
            [0.0, 0.0, math.pi - 0.01],
            [0.0, 0.0, -math.pi + 0.01],
            [0.0, 0.0, -math.pi / 4],
        ]
    )
    keys = POSE_GRID.quantize(poses).tolist()
    assert keys == [[2, -3, 0], [3, -2, 0], [0, 0, 1], [0, 0, 4], [0, 0, 4], [0, 0, 7]]


def test_spatial_pose_grid_uses_the_rotation_vector() -> None:
    grid = PoseGrid(dim=3, position_step=0.1, angle_step=0.1)
    half = 0.5 * 0.32  # 0.32 rad about z, a rotation vector (0, 0, 0.32): key 3
    q = torch.tensor([math.cos(half), 0.0, 0.0, math.sin(half)])
    poses = torch.stack(
        [
            torch.cat([torch.tensor([0.26, 0.0, -0.04]), q]),
            torch.cat([torch.tensor([0.26, 0.0, -0.04]), -q]),  # the same rotation
            torch.tensor([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]),
        ]
    )
    assert grid.quantize(poses).tolist() == [[3, 0, 0, 0, 0, 3], [3, 0, 0, 0, 0, 3], [0] * 6]


def test_no_contact_states_differ_only_by_relative_pose() -> None:
    near, near_pose = box_step(x=0.0)  # finger 0.1 m left of the box, not touching
    far, far_pose = box_step(x=0.0)
    far_pose = far_pose - torch.tensor([0.3, 0.0, 0.0])
    (a,) = manipulation_states(
        near, robot_pose=near_pose, contact_grid=CONTACT_GRID, pose_grid=POSE_GRID
    )
    (b,) = manipulation_states(
        far, robot_pose=far_pose, contact_grid=CONTACT_GRID, pose_grid=POSE_GRID
    )
    assert not a.robot_contact
    assert a.contact == b.contact
    assert a.pose == (-12, 0, 0)  # -0.6 m / 0.05 m
    assert b.pose == (-18, 0, 0)
    assert a != b
    assert len({a, b, replace(a)}) == 2


@settings(max_examples=30, deadline=None)
@given(
    x=st.floats(-2.0, 2.0),
    y=st.floats(-2.0, 2.0),
    theta=st.floats(-math.pi, math.pi),
)
def test_manipulation_state_is_invariant_to_moving_the_whole_scene(
    x: float, y: float, theta: float
) -> None:
    contacts, finger_pose = box_step(x=0.0, finger=(-0.5, 0.06))
    (state,) = manipulation_states(
        contacts, robot_pose=finger_pose, contact_grid=CONTACT_GRID, pose_grid=POSE_GRID
    )
    assert state.robot_contact
    c, s = math.cos(theta), math.sin(theta)
    R = torch.tensor([[c, -s], [s, c]])
    t = torch.tensor([x, y])
    assert contacts.pose is not None
    moved = replace(
        contacts,
        points=contacts.points @ R.T + t,
        normals=contacts.normals @ R.T,
        pose=torch.cat([R @ contacts.pose[:2] + t, contacts.pose[2:] + theta]),
    )
    robot = torch.cat([R @ finger_pose[:2] + t, finger_pose[2:] + theta])
    (again,) = manipulation_states(
        moved, robot_pose=robot, contact_grid=CONTACT_GRID, pose_grid=POSE_GRID
    )
    assert again == state


def test_object_frame_contacts_take_an_object_frame_robot_pose() -> None:
    contacts, finger_pose = box_step(x=0.7, finger=(-0.5, 0.06))
    assert contacts.pose is not None
    points, normals = contacts.object_frame()
    local = replace(contacts, points=points, normals=normals, pose=None)
    relative = relative_pose(contacts.pose, finger_pose)
    (a,) = manipulation_states(
        contacts, robot_pose=finger_pose, contact_grid=CONTACT_GRID, pose_grid=POSE_GRID
    )
    (b,) = manipulation_states(
        local, robot_pose=relative, contact_grid=CONTACT_GRID, pose_grid=POSE_GRID
    )
    assert a == b
    assert a.pose == (-10, 1, 0)  # finger at (-0.5, 0.06) in the object frame


def test_json_round_trip_and_labels() -> None:
    contacts, finger_pose = box_step(x=0.0, finger=(-0.5, 0.06))
    (state,) = manipulation_states(
        contacts, robot_pose=finger_pose, contact_grid=CONTACT_GRID, pose_grid=POSE_GRID
    )
    text = json.dumps(state.to_json())
    assert ManipulationState.from_json(json.loads(text)) == state
    assert str(state) == "(-10, 1, 0) E2st R1st"
    assert str(ManipulationState((), ContactState())) == "() free"


def test_validation() -> None:
    contacts, finger_pose = box_step(x=0.0)
    with pytest.raises(ValueError, match=r"robot_pose must have shape \(\*B, 3\) planar"):
        manipulation_states(
            contacts,
            robot_pose=finger_pose[:2],
            contact_grid=CONTACT_GRID,
            pose_grid=POSE_GRID,
        )
    with pytest.raises(ValueError, match="robot_pose must have batch shape"):
        manipulation_states(
            contacts,
            robot_pose=finger_pose.expand(2, 3),
            contact_grid=CONTACT_GRID,
            pose_grid=POSE_GRID,
        )
    with pytest.raises(ValueError, match="position_step: expected a finite number > 0"):
        PoseGrid(dim=2, position_step=0.0, angle_step=0.1)
    with pytest.raises(ValueError, match="pose must hold ints"):
        ManipulationState((0.5,), ContactState())  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="robot_pose must match object_pose"):
        relative_pose(torch.zeros(3), torch.zeros(2, 3))
    with pytest.raises(ValueError, match="robot_pose holds a zero quaternion"):
        relative_pose(torch.tensor([0.0, 0, 0, 1, 0, 0, 0]), torch.zeros(7))


def test_planar_box_contacts_geometry() -> None:
    # Resting at x = 1: bottom corners at (0.5, 0) and (1.5, 0).
    contacts, finger = box_step(x=1.0, finger=(-0.5, 0.1))
    expected = [[0.5, 0.0], [1.5, 0.0], [1.5, 0.5], [0.5, 0.5], [0.5, 0.35]]
    torch.testing.assert_close(contacts.points, torch.tensor(expected), rtol=0, atol=1e-15)
    assert contacts.mode.tolist() == [1, 1, 0, 0, 1]
    assert contacts.normals[4].tolist() == [1.0, 0.0]
    assert finger.tolist() == [0.5, 0.35, 0.0]
    # Tipped by 30° about the bottom-right corner at x = 2: that corner stays at (2, 0), the
    # bottom-left one rises to height 1 · sin 30° = 0.5, the finger normal turns with the box.
    tipped, _ = box_step(x=2.0, tip=math.radians(30))
    torch.testing.assert_close(
        tipped.points[:2], torch.tensor([[2 - math.cos(math.pi / 6), 0.5], [2.0, 0.0]])
    )
    torch.testing.assert_close(tipped.normals[4], torch.tensor([math.cos(math.pi / 6), -0.5]))
    assert tipped.mode.tolist() == [0, 1, 0, 0, 0]


@pytest.mark.bitwise("indexing and stacking copy the entries")
def test_contact_set_indexing_picks_batch_elements() -> None:
    steps = [box_step(x=0.0)[0], box_step(x=0.3, finger=(-0.5, 0.0))[0]]
    batch = stack(steps)
    assert batch.batch_shape == (2,)
    for i, step in enumerate(steps):
        picked = batch[i]
        assert picked.batch_shape == ()
        for name in ("points", "normals", "pn", "mode", "mask", "pose"):
            assert torch.equal(getattr(picked, name), getattr(step, name))
