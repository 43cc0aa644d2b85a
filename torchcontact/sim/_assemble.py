"""From a scene and its state to the contact problem of one time step."""

from __future__ import annotations

import torch
from torch import Tensor

from torchcontact.contact import ContactProblem
from torchcontact.geometry import (
    HalfPlane,
    Polygon,
    SlotGeometry,
    concat_slots,
    halfplane_slots,
    perpendicular,
    point_velocity,
    polygon_slots,
    transform_points,
    wrench_row,
)
from torchcontact.sim._scene import Scene
from torchcontact.sim._state import SceneState


def body_poses(scene: Scene, state: SceneState) -> list[Tensor | None]:
    """World pose ``(*B, 3)`` of every body (``None`` for half-planes)."""
    return poses_of(scene, q=state.q, q_kinematic=state.q_kinematic)


def poses_of(scene: Scene, *, q: Tensor, q_kinematic: Tensor) -> list[Tensor | None]:
    """:func:`body_poses` from the poses of the dynamic ``(*B, Nd, 3)`` and kinematic
    ``(*B, Nk, 3)`` bodies alone."""
    poses: list[Tensor | None] = []
    batch = q.shape[:-2]
    for i, body in enumerate(scene.bodies):
        if body.kind == "dynamic":
            poses.append(q[..., scene.dynamic.index(i), :])
        elif body.kind == "kinematic":
            poses.append(q_kinematic[..., scene.kinematic.index(i), :])
        elif isinstance(body.shape, Polygon):
            assert body.pose is not None
            poses.append(body.pose.to(q).expand(*batch, 3))
        else:
            poses.append(None)
    return poses


def polygon_vertices(
    scene: Scene, poses: list[Tensor | None], dtype: torch.dtype
) -> dict[int, Tensor]:
    """World vertices ``(*B, V, 2)`` of every posed polygon, by body index."""
    return {
        i: transform_points(pose, body.shape.vertices.to(dtype))
        for i, (body, pose) in enumerate(zip(scene.bodies, poses, strict=True))
        if isinstance(body.shape, Polygon) and pose is not None
    }


def contact_problem(
    scene: Scene,
    state: SceneState,
    *,
    control: Tensor | None = None,
    force: Tensor | None = None,
    friction: Tensor | None = None,
) -> tuple[ContactProblem, SlotGeometry]:
    """Assemble the Stewart–Trinkle step of a batch of scenes.

    For a slot at world point ``p`` with normal ``n`` (from ``other`` into ``receiver``) and
    tangent ``t = n`` rotated by +90°, the gap rate is ``n · (v_p,receiver − v_p,other)``: a
    dynamic body contributes the row ``±[n, r × n]`` (``r`` from its centroid to ``p``) to
    ``Jn``, a kinematic body its known point velocity to ``bn``, a static body nothing.
    Friction directions are ``+t`` and ``−t``.

    Args:
        scene: the scene.
        state: the batched state ``*B``.
        control: ``(*B, Nk, 3)`` twists of the kinematic bodies (world frame), or ``None``
            when the scene has none (or they rest).
        force: ``(*B, Nd, 3)`` applied generalized forces ``(fx, fy, τ)`` on the dynamic
            bodies, besides gravity.
        friction: ``(*B, K)`` per-slot friction overriding the scene's pair friction.

    Returns:
        The contact problem (``n = 3 Nd``, ``K`` slots, ``D = 2``) and the slot geometry
        (points, normals from each slot's ``other`` body into its receiver, gaps, candidates).
    """
    dtype, batch = state.q.dtype, state.batch_shape
    num_dynamic = len(scene.dynamic)
    if control is None:
        control = torch.zeros(*batch, len(scene.kinematic), 3, dtype=dtype)
    poses = body_poses(scene, state)
    twists: list[Tensor | None] = []
    for i, body in enumerate(scene.bodies):
        if body.kind == "dynamic":
            twists.append(None)
        elif body.kind == "kinematic":
            twists.append(control[..., scene.kinematic.index(i), :])
        else:
            twists.append(torch.zeros(*batch, 3, dtype=dtype))
    world_vertices = polygon_vertices(scene, poses, dtype)

    geometries: list[SlotGeometry] = []
    Jn_parts, Jt_parts, bn_parts, bt_parts, mu_parts = [], [], [], [], []
    zero_block = torch.zeros((), dtype=dtype)
    for group in scene.slot_groups:
        other_shape = scene.bodies[group.other].shape
        vertices = world_vertices[group.receiver]
        if isinstance(other_shape, HalfPlane):
            geometry = halfplane_slots(vertices, other_shape, margin=scene.margin)
        else:
            geometry = polygon_slots(vertices, world_vertices[group.other], margin=scene.margin)
        geometries.append(geometry)
        normal = geometry.normals
        tangent = perpendicular(normal)
        blocks_n = [zero_block.expand(*normal.shape[:-1], 3)] * num_dynamic
        blocks_t = list(blocks_n)
        known_n = torch.zeros(normal.shape[:-1], dtype=dtype)
        known_t = torch.zeros(normal.shape[:-1], dtype=dtype)
        for member, sign in ((group.receiver, 1.0), (group.other, -1.0)):
            pose = poses[member]
            if pose is None:
                continue
            offset = geometry.points - pose[..., None, :2]
            twist = twists[member]
            if twist is None:
                column = scene.dynamic.index(member)
                blocks_n[column] = blocks_n[column] + sign * wrench_row(normal, offset)
                blocks_t[column] = blocks_t[column] + sign * wrench_row(tangent, offset)
            else:
                velocity = point_velocity(twist, offset)
                known_n = known_n + sign * (velocity * normal).sum(-1)
                known_t = known_t + sign * (velocity * tangent).sum(-1)
        Jn_parts.append(torch.stack(blocks_n, dim=-2).flatten(-2))
        Jt_row = torch.stack(blocks_t, dim=-2).flatten(-2)
        Jt_parts.append(torch.stack([Jt_row, -Jt_row], dim=-2))
        bn_parts.append(known_n)
        bt_parts.append(torch.stack([known_t, -known_t], dim=-1))
        mu = torch.as_tensor(scene.pair_mu(group.receiver, group.other), dtype=dtype)
        mu_parts.append(mu.unsqueeze(-1).expand(*batch, group.count))

    slots = concat_slots(geometries)
    masses = scene.masses().to(dtype)
    gravity = torch.tensor([scene.gravity[0], scene.gravity[1], 0.0], dtype=dtype)
    f = (masses[:, None] * gravity).expand(*batch, num_dynamic, 3)
    if force is not None:
        f = f + force
    problem = ContactProblem(
        M=scene.mass_matrix().to(dtype),
        v=state.v.flatten(-2),
        f=f.flatten(-2),
        Jn=torch.cat(Jn_parts, dim=-2),
        Jt=torch.cat(Jt_parts, dim=-3),
        phi=slots.phi,
        mu=torch.cat(mu_parts, dim=-1) if friction is None else friction,
        h=scene.h,
        mask=slots.active,
        bn=torch.cat(bn_parts, dim=-1),
        bt=torch.cat(bt_parts, dim=-2),
    )
    return problem, slots
