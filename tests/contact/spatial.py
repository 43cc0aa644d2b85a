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


def friction_rows(tangents: Tensor, directions: int, *, phase: float | Tensor = 0.0) -> Tensor:
    """Friction-direction rows ``(*, D, n)`` from two tangent rows ``tangents (*, 2, n)``.

    Direction ``d`` is ``cos θ_d t₁ + sin θ_d t₂`` with ``θ_d = phase + 2π d / D``: ordered by
    angle, ``d + D/2`` opposite ``d`` (the convention of ``ContactProblem``). ``phase`` is a
    number or a tensor of the batch shape ``*`` of ``tangents``.
    """
    steps = torch.arange(directions, dtype=tangents.dtype) * (2 * math.pi / directions)
    angles = torch.as_tensor(phase, dtype=tangents.dtype).unsqueeze(-1) + steps
    weights = torch.stack([torch.cos(angles), torch.sin(angles)], dim=-1)  # (*, D, 2)
    return weights @ tangents


def random_spatial_problems(
    seed: int, *, count: int, directions: int, slots: int = 2, dofs: int = 8
) -> ContactProblem:
    """Random spatial problems: a random SPD mass matrix, random normal and tangent rows.

    Each slot's friction rows come from two random tangent rows (:func:`friction_rows`, with a
    random phase); velocities, forces (pressing the slots on, on average), gaps (some
    penetrating) and friction coefficients are random, so separated, sticking, edge- and
    face-sliding slots all occur (seed 11, 300 problems of 3 slots, D = 4: 423, 134, 180 and
    163 of them).
    """
    gen = torch.Generator().manual_seed(seed)
    f64 = torch.float64

    def normal(*shape: int) -> Tensor:
        return torch.randn(*shape, generator=gen, dtype=f64)

    def uniform(*shape: int) -> Tensor:
        return torch.rand(*shape, generator=gen, dtype=f64)

    root = normal(count, dofs, dofs)
    M = root @ root.transpose(-1, -2) / dofs + 0.5 * torch.eye(dofs, dtype=f64)
    phase = 2 * math.pi * uniform(count, slots)
    Jt = friction_rows(2.0 * normal(count, slots, 2, dofs), directions, phase=phase)
    Jn = normal(count, slots, dofs)
    penetrating = uniform(count, slots) < 0.3
    phi = torch.where(penetrating, -0.002 * uniform(count, slots), 0.01 * uniform(count, slots))
    return ContactProblem(
        M=M,
        v=0.3 * normal(count, dofs),
        f=5.0 * normal(count, dofs) - 20.0 * Jn.sum(dim=-2) / slots,  # pressed on, mostly
        Jn=Jn,
        Jt=Jt,
        phi=phi,
        mu=0.1 + 1.1 * uniform(count, slots),
        h=0.01,
    )
