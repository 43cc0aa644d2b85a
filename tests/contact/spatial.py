"""A spatial box on the ground with polyhedral friction, written out by hand for tests.

Twist ``(v, ω)`` in the world frame; the velocity of a point at offset ``r`` from the centre is
``v + ω × r``, so along a unit direction ``u`` its row is ``[u, r × u]``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcontact.contact import ContactProblem


def spatial_box_problem(
    *,
    v: Tensor,
    half_extents: tuple[float, float, float] = (0.3, 0.2, 0.1),
    mass: float = 1.5,
    mu: float = 0.4,
    h: float = 0.01,
    directions: int = 8,
    force: Tensor | None = None,
) -> ContactProblem:
    """An axis-aligned box resting on ``z = 0`` on its four bottom corners, twist ``v (*B, 6)``."""
    a, b, c = half_extents
    batch = v.shape[:-1]
    dtype = v.dtype
    inertia = [mass * (b * b + c * c) / 3, mass * (a * a + c * c) / 3, mass * (a * a + b * b) / 3]
    M = torch.diag(torch.tensor([mass, mass, mass, *inertia], dtype=dtype)).expand(*batch, 6, 6)
    f = torch.zeros(*batch, 6, dtype=dtype)
    f[..., 2] = -9.81 * mass
    if force is not None:
        f = f + force
    angles = torch.arange(directions, dtype=dtype) * (2 * math.pi / directions)
    tangents = torch.stack([torch.cos(angles), torch.sin(angles), torch.zeros_like(angles)], -1)
    normal = torch.tensor([0.0, 0.0, 1.0], dtype=dtype)
    Jn, Jt = [], []
    for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        r = torch.tensor([sx * a, sy * b, -c], dtype=dtype)
        Jn.append(torch.cat([normal, torch.linalg.cross(r, normal)]))
        Jt.append(torch.cat([tangents, torch.linalg.cross(r.expand_as(tangents), tangents)], -1))
    K = 4
    return ContactProblem(
        M=M,
        v=v,
        f=f,
        Jn=torch.stack(Jn).expand(*batch, K, 6),
        Jt=torch.stack(Jt).expand(*batch, K, directions, 6),
        phi=torch.zeros(*batch, K, dtype=dtype),
        mu=torch.full((*batch, K), mu, dtype=dtype),
        h=h,
    )
