"""A canonical contact problem: a planar box on flat ground (demos, tutorials, benchmarks)."""

from __future__ import annotations

import torch
from torch import Tensor

from torchcontact._checks import check_float, check_int, check_like, check_positive, check_real
from torchcontact.contact._problem import ContactProblem

#: Corner signs of a box in its body frame, counter-clockwise from bottom-left.
BOX_CORNER_SIGNS = ((-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0))


def planar_box_problem(
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
    """The contact step of planar boxes on the ground ``y = 0``, one slot per chosen corner.

    The box has uniform density (inertia ``m (a² + b²) / 3`` for half extents ``a, b``). A
    corner at world offset ``r`` from the centre moves at ``v + ω × r``, so along a unit world
    direction ``u`` its row is ``[u_x, u_y, r_x u_y − r_y u_x]``; the normal is ``+y`` and the
    friction directions are ``+x`` and ``−x``.

    Args:
        q: ``(*B, 3)`` poses ``(x, y, θ)`` in the world frame.
        v: ``(*B, 3)`` twists ``(vx, vy, ω)`` in the world frame.
        half_extents: ``(a, b)`` half width and half height in metres.
        mass: mass in kg.
        mu: friction coefficient with the ground.
        h: time step in seconds.
        gravity: gravitational acceleration ``(gx, gy)`` in m/s² (tilt it to model an incline).
        force: ``(*B, 2)`` world-frame force in N applied at ``force_point``, or ``None``.
        force_point: application point in the body frame, metres.
        corners: indices into :data:`BOX_CORNER_SIGNS` of the corners that become slots.

    Returns:
        The :class:`ContactProblem` with ``n = 3``, ``K = len(corners)``, ``D = 2``.

    Raises:
        ValueError: naming the argument that is not of the documented type, shape or range.
    """
    q = check_float("q", q, trailing=(3,), min_ndim=1, what="(*B, 3)")
    v = check_float("v", v, trailing=(3,), min_ndim=1, what="(*B, 3)")
    check_like("v", v, reference_name="q", reference=q)
    if v.shape != q.shape:
        raise ValueError(f"v must have the shape of q {tuple(q.shape)}, got {tuple(v.shape)}")
    if force is not None:
        check_float("force", force, trailing=(2,), min_ndim=1, what="(*B, 2)")
        check_like("force", force, reference_name="q", reference=q)
        if force.shape[:-1] != q.shape[:-1]:
            raise ValueError(
                f"force must have shape {(*q.shape[:-1], 2)}, got {tuple(force.shape)}"
            )
    if len(half_extents) != 2:
        raise ValueError(f"half_extents must be a pair (a, b), got {half_extents!r}")
    for index, extent in enumerate(half_extents):
        check_positive(f"half_extents[{index}]", extent)
    check_positive("mass", mass)
    check_real("mu", mu, low=0.0)
    check_positive("h", h)
    for name, pair in (("gravity", gravity), ("force_point", force_point)):
        if len(pair) != 2:
            raise ValueError(f"{name} must be a pair, got {pair!r}")
        for index, value in enumerate(pair):
            check_real(f"{name}[{index}]", value)
    for index, corner in enumerate(corners):
        check_int(f"corners[{index}]", corner, low=0, high=len(BOX_CORNER_SIGNS))
    dtype, device = q.dtype, q.device
    batch = q.shape[:-1]
    a, b = half_extents
    inertia = mass * (a * a + b * b) / 3.0
    M = torch.diag(torch.tensor([mass, mass, inertia], dtype=dtype, device=device))
    cos, sin = torch.cos(q[..., 2]), torch.sin(q[..., 2])
    rotation = torch.stack([torch.stack([cos, -sin], -1), torch.stack([sin, cos], -1)], -2)

    f = torch.tensor([mass * gravity[0], mass * gravity[1], 0.0], dtype=dtype, device=device)
    f = f.expand(*batch, 3)
    if force is not None:
        point = torch.tensor(force_point, dtype=dtype, device=device)
        r = rotation @ point
        torque = r[..., 0] * force[..., 1] - r[..., 1] * force[..., 0]
        f = f + torch.cat([force, torque.unsqueeze(-1)], dim=-1)

    signs = torch.tensor([BOX_CORNER_SIGNS[i] for i in corners], dtype=dtype, device=device)
    offsets = signs * torch.tensor([a, b], dtype=dtype, device=device)  # (K, 2) body frame
    r = (rotation.unsqueeze(-3) @ offsets.unsqueeze(-1)).squeeze(-1)  # (*B, K, 2) world frame
    one, zero = torch.ones_like(r[..., 0]), torch.zeros_like(r[..., 0])
    Jn = torch.stack([zero, one, r[..., 0]], dim=-1)
    tangent = torch.stack([one, zero, -r[..., 1]], dim=-1)
    return ContactProblem(
        M=M,
        v=v,
        f=f,
        Jn=Jn,
        Jt=torch.stack([tangent, -tangent], dim=-2),
        phi=q[..., 1:2] + r[..., 1],
        mu=torch.full(r.shape[:-1], mu, dtype=dtype, device=device),
        h=h,
    )
