"""Planar box-on-ground contact problems written out by hand, for tests and benchmarks.

A box of half-width ``a`` and half-height ``b`` (mass ``m``, inertia ``m (a² + b²) / 3``) with
state ``q = (x, y, θ)``, twist ``(vx, vy, ω)``, on the ground ``y = 0``. The contact slots are
its corners; the velocity of a corner at offset ``r`` from the centre is
``(vx − ω r_y, vy + ω r_x)``, so along a unit direction ``u`` its row is ``[u_x, u_y, r × u]``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcontact.contact import ContactProblem

CORNERS = ((-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0))


def box_problem(
    *,
    q: Tensor,
    v: Tensor,
    half_extents: tuple[float, float] = (0.5, 0.25),
    mass: float = 2.0,
    mu: float = 0.5,
    h: float = 0.01,
    gravity: tuple[float, float] = (0.0, -9.81),
    force: Tensor | None = None,
    force_point: tuple[float, float] = (0.0, 0.0),
    corners: tuple[int, ...] = (0, 1),
) -> ContactProblem:
    """The contact step of a batch of boxes ``q (*B, 3)``, ``v (*B, 3)`` (float64).

    ``force (*B, 2)`` is applied at ``force_point`` (body frame); ``corners`` picks the slots.
    """
    a, b = half_extents
    batch = q.shape[:-1]
    dtype = q.dtype
    inertia = mass * (a * a + b * b) / 3.0
    M = torch.diag(torch.tensor([mass, mass, inertia], dtype=dtype)).expand(*batch, 3, 3)
    cos, sin = torch.cos(q[..., 2]), torch.sin(q[..., 2])

    def world_offset(point: tuple[float, float]) -> tuple[Tensor, Tensor]:
        px, py = point
        return cos * px - sin * py, sin * px + cos * py

    f = torch.zeros(*batch, 3, dtype=dtype)
    f[..., 0] = mass * gravity[0]
    f[..., 1] = mass * gravity[1]
    if force is not None:
        rx, ry = world_offset(force_point)
        f[..., 0] += force[..., 0]
        f[..., 1] += force[..., 1]
        f[..., 2] += rx * force[..., 1] - ry * force[..., 0]
    Jn, Jt, phi = [], [], []
    for index in corners:
        sx, sy = CORNERS[index]
        rx, ry = world_offset((sx * a, sy * b))
        one, zero = torch.ones_like(rx), torch.zeros_like(rx)
        normal = torch.stack([zero, one, rx], dim=-1)
        tangent = torch.stack([one, zero, -ry], dim=-1)
        Jn.append(normal)
        Jt.append(torch.stack([tangent, -tangent], dim=-2))
        phi.append(q[..., 1] + ry)
    return ContactProblem(
        M=M,
        v=v,
        f=f,
        Jn=torch.stack(Jn, dim=-2),
        Jt=torch.stack(Jt, dim=-3),
        phi=torch.stack(phi, dim=-1),
        mu=torch.full((*batch, len(corners)), mu, dtype=dtype),
        h=h,
    )


def resting_state(
    batch: tuple[int, ...] = (), half_extents: tuple[float, float] = (0.5, 0.25)
) -> tuple[Tensor, Tensor]:
    """``q, v`` of boxes resting flat on the ground."""
    q = torch.zeros(*batch, 3, dtype=torch.float64)
    q[..., 1] = half_extents[1]
    return q, torch.zeros(*batch, 3, dtype=torch.float64)


def incline_gravity(angle: float, g: float = 9.81) -> tuple[float, float]:
    """Gravity in the frame of an incline of ``angle`` rad whose down-slope direction is +x."""
    return g * math.sin(angle), -g * math.cos(angle)
