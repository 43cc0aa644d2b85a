"""Planar rigid transforms on batched poses ``(x, y, θ)``."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcontact._checks import check_float_shape


def rotation_matrix(theta: Tensor) -> Tensor:
    """``(*B, 2, 2)`` rotation matrices of angles ``theta (*B,)`` (rad, counter-clockwise)."""
    cos, sin = torch.cos(theta), torch.sin(theta)
    return torch.stack([torch.stack([cos, -sin], -1), torch.stack([sin, cos], -1)], -2)


def wrap_angle(angle: Tensor) -> Tensor:
    """Wrap angles (radians) into ``[-π, π)``: ``θ - 2π ⌊(θ + π) / 2π⌋``.

    Exact for angles already in range; slope 1 everywhere but at the cut.

    Args:
        angle: ``(*B,)`` float32 or float64 angles.
    """
    angle = check_float_shape("angle", angle, trailing=(), what="(*B)")
    return angle - 2 * math.pi * torch.floor((angle + math.pi) / (2 * math.pi))


def transform_points(pose: Tensor, points: Tensor) -> Tensor:
    """Map body-frame points to the world frame.

    Args:
        pose: ``(*B, 3)`` body poses ``(x, y, θ)`` in the world frame.
        points: ``(*B, P, 2)`` or ``(P, 2)`` points in the body frame.

    Returns:
        ``(*B, P, 2)`` points in the world frame, ``R(θ) p + (x, y)``.
    """
    rotation = rotation_matrix(pose[..., 2])
    return points @ rotation.transpose(-1, -2) + pose[..., None, :2]


def cross2(a: Tensor, b: Tensor) -> Tensor:
    """Planar cross product ``a_x b_y − a_y b_x`` over the last dimension (size 2)."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def dot2(a: Tensor, b: Tensor, c: Tensor | None = None, d: Tensor | None = None) -> Tensor:
    """Planar dot products over the last dimension (size 2): ``a · b``, or ``a · b + c · d``.

    Component by component (``a_x b_x + a_y b_y``): on the CPU, faster than a reduction over a
    last dimension of two, or than a product of the broadcast pairs.
    """
    total = torch.addcmul(a[..., 0] * b[..., 0], a[..., 1], b[..., 1])
    if c is None or d is None:
        return total
    return torch.addcmul(torch.addcmul(total, c[..., 0], d[..., 0]), c[..., 1], d[..., 1])


def perpendicular(u: Tensor) -> Tensor:
    """``u`` rotated by +90°: ``(−u_y, u_x)``."""
    return torch.stack([-u[..., 1], u[..., 0]], dim=-1)


def point_velocity(twist: Tensor, offset: Tensor) -> Tensor:
    """Velocity of body points: ``v + ω × r``.

    Args:
        twist: ``(*B, 3)`` body twists ``(vx, vy, ω)`` in the world frame.
        offset: ``(*B, P, 2)`` world-frame offsets ``r`` of the points from the body origin.

    Returns:
        ``(*B, P, 2)`` world-frame point velocities.
    """
    omega = twist[..., None, 2:3]
    return twist[..., None, :2] + omega * perpendicular(offset)


def wrench_row(direction: Tensor, offset: Tensor) -> Tensor:
    """Row mapping a body twist to a point's velocity along a direction: ``[u, r × u]``.

    Args:
        direction: ``(*B, P, 2)`` unit directions ``u``, world frame.
        offset: ``(*B, P, 2)`` world offsets ``r`` of the points from the body origin.

    Returns:
        ``(*B, P, 3)`` rows with ``row · (vx, vy, ω) = u · (v + ω × r)``.
    """
    return torch.cat([direction, cross2(offset, direction).unsqueeze(-1)], dim=-1)
