"""Unit quaternions ``(w, x, y, z)`` for spatial rotations."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcontact._checks import check_float_shape


def quat_mul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product of quaternions ``(*B, 4)`` stored ``(w, x, y, z)``."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def quat_conj(q: Tensor) -> Tensor:
    """Conjugate (the inverse of a unit quaternion) ``(*B, 4)``."""
    return torch.cat([q[..., :1], -q[..., 1:]], dim=-1)


def _small(sq: Tensor) -> Tensor:
    """Where a squared norm is small enough for the Taylor branches below to be exact in dtype."""
    return sq < math.sqrt(torch.finfo(sq.dtype).eps)


def quat_exp(v: Tensor) -> Tensor:
    """Unit quaternion of the rotation vector ``v`` ``(*B, 3)`` (radians) → ``(*B, 4)``."""
    v = check_float_shape("v", v, trailing=(3,), what="(*B, 3)")
    sq = (v * v).sum(-1, keepdim=True)
    small = _small(sq)
    theta = torch.sqrt(torch.where(small, torch.ones_like(sq), sq))  # safe: finite gradients
    half = 0.5 * theta
    scale = torch.where(small, 0.5 - sq / 48.0, torch.sin(half) / theta)
    w = torch.where(small, 1.0 - sq / 8.0, torch.cos(half))
    return torch.cat([w, scale * v], dim=-1)


def quat_log(q: Tensor) -> Tensor:
    """Rotation vector ``(*B, 3)`` of the unit quaternion ``q`` ``(*B, 4)``, angle in ``[0, π]``."""
    q = check_float_shape("q", q, trailing=(4,), what="(*B, 4)")
    q = torch.where(q[..., :1] < 0, -q, q)  # shortest rotation of the double cover
    w, v = q[..., :1], q[..., 1:]
    sq = (v * v).sum(-1, keepdim=True)
    small = _small(sq)
    s = torch.sqrt(torch.where(small, torch.ones_like(sq), sq))
    w_safe = torch.where(small, w, torch.ones_like(w))
    scale = torch.where(
        small, 2.0 / w_safe * (1.0 - sq / (3.0 * w_safe * w_safe)), 2.0 * torch.atan2(s, w) / s
    )
    return scale * v


def quat_to_matrix(q: Tensor) -> Tensor:
    """Rotation matrices ``(*B, 3, 3)`` of quaternions ``(*B, 4)`` ``(w, x, y, z)`` (normalized
    here), mapping body-frame vectors to the world frame: ``x_world = R x_body``."""
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return torch.stack([torch.stack(row, -1) for row in rows], -2)
