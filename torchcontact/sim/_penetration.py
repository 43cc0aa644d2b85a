"""The penetrating contact slots of many states, without assembling the rest of the problem."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcontact._checks import check_batched, check_float
from torchcontact.geometry import HalfPlane, Polygon, halfplane_slots, polygon_slots, wrench_row
from torchcontact.sim._assemble import polygon_vertices, poses_of
from torchcontact.sim._scene import Scene

#: Widening of the bounding boxes of the cull (metres): rounding in the vertex transforms.
_BOX_TOLERANCE = 1e-9


def penetration(scene: Scene, *, q: Tensor, q_kinematic: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Which contact slots of a batch of states penetrate, with their gaps and normal rows.

    A slot penetrates when it is a candidate (:class:`~torchcontact.geometry.SlotGeometry`'s
    ``active``) with a negative gap. Where it does, its gap and its row of ``Jn`` are those of
    :func:`~torchcontact.sim.contact_problem` at the state, to the bit (the same functions on
    the same numbers), less everything the problem also holds (velocities, tangents, known
    terms, friction). A vertex can only penetrate a polygon from inside the polygon's bounding
    box, so the slots of a polygon against another polygon are evaluated only for the states
    where some vertex lies in that box. This is the cheap query of a filter that projects many
    particles out of the bodies (thousands of poses per step), where most particles touch
    nothing but the ground.

    Args:
        scene: the scene.
        q: ``(*B, Nd, 3)`` poses of the dynamic bodies (world frame).
        q_kinematic: ``(*B, Nk, 3)`` poses of the kinematic bodies (world frame).

    Returns:
        ``phi (*B, K)`` gaps, ``Jn (*B, K, 3 Nd)`` normal rows and the bool ``(*B, K)``
        penetrating slots; ``phi`` and ``Jn`` are zero at the slots that do not penetrate.

    Raises:
        ValueError: ``q`` or ``q_kinematic`` is not a finite float32/float64 tensor of the
            documented shape, or their dtypes differ.
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a Scene, got {type(scene).__name__}")
    num_dynamic, num_kinematic = len(scene.dynamic), len(scene.kinematic)
    q = check_float("q", q, trailing=(num_dynamic, 3), min_ndim=2, what=f"(*B, {num_dynamic}, 3)")
    batch = q.shape[:-2]
    check_batched(
        "q_kinematic", q_kinematic, shape=(*batch, num_kinematic, 3), like=q, like_name="q"
    )
    P, K, dtype = math.prod(batch), scene.num_slots, q.dtype
    poses = poses_of(
        scene,
        q=q.reshape(P, num_dynamic, 3),
        q_kinematic=q_kinematic.reshape(P, num_kinematic, 3),
    )
    vertices = polygon_vertices(scene, poses, dtype)
    low = {i: v.amin(-2) - _BOX_TOLERANCE for i, v in vertices.items()}
    high = {i: v.amax(-2) + _BOX_TOLERANCE for i, v in vertices.items()}
    phi = q.new_zeros(P, K)
    Jn = q.new_zeros(P, K, 3 * num_dynamic)
    penetrating = torch.zeros(P, K, dtype=torch.bool, device=q.device)
    zero_block = torch.zeros((), dtype=dtype)
    for group in scene.slot_groups:
        other_shape = scene.bodies[group.other].shape
        rows: Tensor | None = None  # every state
        if isinstance(other_shape, Polygon):
            point = vertices[group.receiver]  # (P, V, 2)
            boxed = (point >= low[group.other][:, None]) & (point <= high[group.other][:, None])
            near = boxed.all(-1).any(-1)
            if not bool(near.all()):
                rows = near.nonzero().squeeze(-1)
                if rows.numel() == 0:
                    continue

        def pick(x: Tensor, rows: Tensor | None = rows) -> Tensor:
            return x if rows is None else x[rows]

        if isinstance(other_shape, HalfPlane):
            geometry = halfplane_slots(vertices[group.receiver], other_shape, margin=scene.margin)
        else:
            geometry = polygon_slots(
                pick(vertices[group.receiver]), pick(vertices[group.other]), margin=scene.margin
            )
        blocks = [zero_block.expand(*geometry.normals.shape[:-1], 3)] * num_dynamic
        for member, sign in ((group.receiver, 1.0), (group.other, -1.0)):
            if scene.bodies[member].kind == "dynamic":
                column = scene.dynamic.index(member)
                pose = poses[member]
                assert pose is not None
                offset = geometry.points - pick(pose)[..., None, :2]
                blocks[column] = blocks[column] + sign * wrench_row(geometry.normals, offset)
        block = torch.stack(blocks, dim=-2).flatten(-2)
        span = slice(group.start, group.start + group.count)
        inside = geometry.active & (geometry.phi < 0)
        if rows is None:
            phi[:, span], Jn[:, span], penetrating[:, span] = geometry.phi, block, inside
        else:
            phi[rows, span], Jn[rows, span], penetrating[rows, span] = (
                geometry.phi,
                block,
                inside,
            )
    phi = torch.where(penetrating, phi, 0.0)
    Jn = Jn * penetrating[..., None]
    return phi.view(*batch, K), Jn.view(*batch, K, 3 * num_dynamic), penetrating.view(*batch, K)
