"""Object poses and the object frame: planar ``(x, y, θ)`` and spatial ``(p, q_wxyz)`` poses."""

from __future__ import annotations

import torch
from torch import Tensor

from torchcontact._checks import check_float
from torchcontact.geometry import quat_mul, quat_to_matrix, wrap_angle
from torchcontact.geometry import rotation_matrix as planar_rotation


def pose_size(dim: int) -> int:
    """Number of pose coordinates: 3 for planar ``(x, y, θ)``, 7 for spatial ``(p, q_wxyz)``."""
    return 3 if dim == 2 else 7


def check_pose(name: str, pose: object, dim: int) -> Tensor:
    """Check that ``pose`` is a finite ``(*B, 3)`` planar or ``(*B, 7)`` spatial pose.

    Raises:
        ValueError: wrong type, shape or values; a spatial quaternion of zero length.
    """
    size = pose_size(dim)
    what = "(*B, 3) planar (x, y, θ)" if dim == 2 else "(*B, 7) spatial (p, q_wxyz)"
    pose = check_float(name, pose, trailing=(size,), what=what)
    if dim == 3 and bool((torch.linalg.vector_norm(pose[..., 3:], dim=-1) == 0).any()):
        raise ValueError(f"{name} holds a zero quaternion")
    return pose


def rotation_matrix(pose: Tensor, dim: int) -> Tensor:
    """Rotation of the body frame in the world frame.

    Args:
        pose: ``(*B, 3)`` planar ``(x, y, θ)`` or ``(*B, 7)`` spatial ``(p, q_wxyz)`` pose of the
            body in the world frame; the quaternion is normalized here.
        dim: 2 or 3.

    Returns:
        ``R (*B, d, d)`` with ``x_world = R x_body + t``.
    """
    if dim == 2:
        return planar_rotation(pose[..., 2])
    return quat_to_matrix(pose[..., 3:])


def to_body_frame(points: Tensor, normals: Tensor, pose: Tensor) -> tuple[Tensor, Tensor]:
    """Express world-frame contact points and normals in a body's frame.

    Args:
        points: ``(*B, K, d)`` points in the world frame.
        normals: ``(*B, K, d)`` directions in the world frame.
        pose: ``(*B, 3)`` or ``(*B, 7)`` pose of the body in the world frame.

    Returns:
        ``R^T (p - t)`` and ``R^T n``, both ``(*B, K, d)`` in the body frame.
    """
    dim = points.shape[-1]
    R = rotation_matrix(pose, dim)
    t = pose[..., :dim].unsqueeze(-2)
    # Row vectors: (R^T x)^T = x^T R.
    return (points - t) @ R, normals @ R


def relative_pose(object_pose: Tensor, robot_pose: Tensor) -> Tensor:
    """Pose of the robot in the object's frame, ``T_object⁻¹ T_robot``.

    Args:
        object_pose: ``(*B, 3)`` planar ``(x, y, θ)`` or ``(*B, 7)`` spatial ``(p, q_wxyz)`` pose
            of the object in the world frame.
        robot_pose: pose of the robot (e.g. its end effector) in the world frame, same shape.

    Returns:
        ``(*B, 3)`` planar pose with its angle wrapped into ``[-π, π)``, or ``(*B, 7)`` spatial
        pose with a unit quaternion of non-negative ``w``, in the object frame.

    Raises:
        ValueError: the poses are malformed or their shapes differ.
    """
    if not isinstance(object_pose, Tensor) or object_pose.shape[-1:] not in ((3,), (7,)):
        shape = tuple(object_pose.shape) if isinstance(object_pose, Tensor) else object_pose
        raise ValueError(f"object_pose must have shape (*B, 3) or (*B, 7), got {shape}")
    dim = 2 if object_pose.shape[-1] == 3 else 3
    object_pose = check_pose("object_pose", object_pose, dim)
    robot_pose = check_pose("robot_pose", robot_pose, dim)
    if robot_pose.shape != object_pose.shape or robot_pose.dtype != object_pose.dtype:
        raise ValueError(
            f"robot_pose must match object_pose ({tuple(object_pose.shape)}, "
            f"{object_pose.dtype}), got ({tuple(robot_pose.shape)}, {robot_pose.dtype})"
        )
    R = rotation_matrix(object_pose, dim)
    offset = robot_pose[..., :dim] - object_pose[..., :dim]
    position = (offset.unsqueeze(-2) @ R).squeeze(-2)
    if dim == 2:
        angle = wrap_angle(robot_pose[..., 2] - object_pose[..., 2])
        return torch.cat([position, angle.unsqueeze(-1)], -1)
    q_object = object_pose[..., 3:] / torch.linalg.vector_norm(
        object_pose[..., 3:], dim=-1, keepdim=True
    )
    q_robot = robot_pose[..., 3:] / torch.linalg.vector_norm(
        robot_pose[..., 3:], dim=-1, keepdim=True
    )
    conjugate = q_object * q_object.new_tensor([1.0, -1.0, -1.0, -1.0])
    q = quat_mul(conjugate, q_robot)
    q = torch.where(q[..., :1] < 0, -q, q)
    return torch.cat([position, q], -1)
