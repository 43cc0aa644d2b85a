"""Link inertials and collision primitives read from the URDFs, and the joint-space dynamics
built on them, against finite differences of forward kinematics and the files' geometry."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from torchcontact.geometry import Box, Capsule, Sphere, quat_to_matrix
from torchcontact.robots import Robot, load

PRIMITIVES = """<?xml version="1.0"?>
<robot name="primitives">
  <link name="base">
    <collision>
      <origin xyz="0.1 0 0" rpy="0 0 0"/>
      <geometry><box size="0.2 0.4 0.6"/></geometry>
    </collision>
    <collision><geometry><sphere radius="0.05"/></geometry></collision>
    <collision>
      <origin xyz="0 0 0.3" rpy="0 1.5707963267948966 0"/>
      <geometry><cylinder radius="0.02" length="0.1"/></geometry>
    </collision>
    <collision><geometry><capsule radius="0.03" length="0.2"/></geometry></collision>
  </link>
</robot>
"""


def test_primitives_are_read_with_cylinders_as_capsules(tmp_path: Path) -> None:
    path = tmp_path / "primitives.urdf"
    path.write_text(PRIMITIVES)
    box, sphere, cylinder, capsule = Robot.from_urdf(path).collision_shapes
    assert isinstance(box.shape, Box)
    torch.testing.assert_close(
        box.shape.half_extents, torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    )
    assert isinstance(sphere.shape, Sphere)
    assert sphere.shape.radius == pytest.approx(0.05, rel=1e-15)
    for link_shape, radius, half in ((cylinder, 0.02, 0.05), (capsule, 0.03, 0.1)):
        assert isinstance(link_shape.shape, Capsule)
        assert link_shape.shape.radius == pytest.approx(radius, rel=1e-15)
        assert link_shape.shape.half_length == pytest.approx(half, rel=1e-15)
    # rpy (0, π/2, 0) turns the capsule's axis z onto the link's x axis.
    axis = quat_to_matrix(cylinder.pose[3:]) @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(
        axis, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), rtol=0, atol=1e-15
    )
    torch.testing.assert_close(
        cylinder.pose[:3], torch.tensor([0.0, 0.0, 0.3], dtype=torch.float64)
    )


@pytest.mark.parametrize(
    ("geometry", "message"),
    [
        ('<mesh filename="x.stl"/>', "unsupported primitive <mesh>"),
        ('<sphere radius="-1"/>', "radius must be a finite number > 0"),
        ('<box size="0.1 0.1"/>', "expected 3 finite numbers"),
        ('<cylinder radius="0.1"/>', "length must be a finite number"),
    ],
)
def test_bad_primitives_are_rejected(tmp_path: Path, geometry: str, message: str) -> None:
    path = tmp_path / "bad.urdf"
    path.write_text(
        f'<robot name="r"><link name="a"><collision><geometry>{geometry}</geometry></collision>'
        "</link></robot>"
    )
    with pytest.raises(ValueError, match=message):
        Robot.from_urdf(path)


@pytest.mark.parametrize("finger", [1, 2, 3])
def test_barretthand_fingertip_lies_on_the_outer_capsule(finger: int) -> None:
    """The fingertip frame (D3 = 9.5 mm off the outer link's DH axis) is on the surface of
    the outer link's capsule: its distance to the capsule's axis segment is the radius."""
    hand = load("bhand")
    q = torch.tensor([0.3, 0.7, 0.9, 1.1], dtype=torch.float64)
    frames = hand.forward_kinematics(q)
    outer, tip = frames[f"bhand_f{finger}_outer"], frames[f"bhand_f{finger}_tip"]
    tip_local = outer[:3, :3].T @ (tip[:3, 3] - outer[:3, 3])
    (link_shape,) = [s for s in hand.collision_shapes if s.link == f"bhand_f{finger}_outer"]
    capsule = link_shape.shape
    assert isinstance(capsule, Capsule)
    axis = quat_to_matrix(link_shape.pose[3:])[:, 2]
    along = float((tip_local - link_shape.pose[:3]) @ axis)
    assert abs(along) <= capsule.half_length + 1e-12
    nearest = link_shape.pose[:3] + along * axis
    assert float(torch.linalg.vector_norm(tip_local - nearest)) == pytest.approx(0.0095, abs=1e-12)


def test_wam7_bhand_carries_the_primitives_of_wam7_and_bhand() -> None:
    """wam7_bhand.urdf is wam7.urdf and bhand.urdf verbatim: same primitives, same poses."""
    combined = load("wam7_bhand").collision_shapes
    parts = load("wam7").collision_shapes + load("bhand").collision_shapes
    assert [s.link for s in combined] == [s.link for s in parts]
    for a, b in zip(combined, parts, strict=True):
        assert type(a.shape) is type(b.shape)
        assert repr(a.shape) == repr(b.shape)
        torch.testing.assert_close(a.pose, b.pose, rtol=0, atol=0.0 + 1e-15)


@pytest.mark.parametrize("name", ["wam7", "bhand", "parallel_jaw"])
def test_gravity_force_is_the_gradient_of_the_potential(name: str) -> None:
    """Σ m Jcᵀ g = ∂/∂q Σ m g · c(q): central differences of the links' centres of mass."""
    robot = load(name)
    generator = torch.Generator().manual_seed(5)
    low, high = robot.lower.clamp(min=-2.0), robot.upper.clamp(max=2.0)
    q = low + (high - low) * torch.rand(robot.dof, generator=generator, dtype=torch.float64)
    g = torch.tensor([0.5, -1.0, -9.81], dtype=torch.float64)

    def work(qq: torch.Tensor) -> float:
        frames = robot.forward_kinematics(qq)
        total = 0.0
        for inertial in robot.inertials:
            frame = frames[inertial.link]
            centre = frame[:3, :3] @ inertial.com + frame[:3, 3]
            total += inertial.mass * float(g @ centre)
        return total

    eps = 1e-6
    eye = torch.eye(robot.dof, dtype=torch.float64)
    expected = torch.tensor(
        [(work(q + eps * e) - work(q - eps * e)) / (2 * eps) for e in eye], dtype=torch.float64
    )
    torch.testing.assert_close(robot.gravity_force(q, g), expected, rtol=1e-7, atol=1e-8)


def test_link_jacobians_are_finite_differences_of_the_link_frames() -> None:
    """Each link origin's velocity and angular velocity per unit joint velocity, batched."""
    robot = load("wam7_bhand")
    q = torch.linspace(0.1, 0.9, robot.dof, dtype=torch.float64).unsqueeze(0).expand(2, -1)
    _transforms, jacobians = robot.link_jacobians(q)
    assert jacobians.shape == (2, len(robot.link_names), 6, robot.dof)
    eps = 1e-6
    for j in range(robot.dof):
        step = torch.zeros(robot.dof, dtype=torch.float64)
        step[j] = eps
        plus, minus = robot.link_jacobians(q + step)[0], robot.link_jacobians(q - step)[0]
        linear = (plus[..., :3, 3] - minus[..., :3, 3]) / (2 * eps)
        relative = plus[..., :3, :3] @ minus[..., :3, :3].transpose(-1, -2)
        skew = (relative - relative.transpose(-1, -2)) / 2
        angular = torch.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], -1) / (2 * eps)
        torch.testing.assert_close(jacobians[..., :3, j], linear, rtol=0, atol=1e-8)
        torch.testing.assert_close(jacobians[..., 3:, j], angular, rtol=0, atol=1e-8)
