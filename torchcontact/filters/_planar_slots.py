"""Slot rows of a planar scene with one tracked body, and their derivatives along its pose.

The tables (:class:`SlotLayout`) are built once per scene; :func:`slot_rows` computes every
slot's rows at once from the slot geometry (:func:`~torchcontact.geometry.planar_slots`), in a
fixed number of tensor operations whatever the batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact.geometry import (
    HalfPlane,
    PlanarSlotTable,
    dot2,
    planar_slot_table,
    planar_slots,
)
from torchcontact.sim import Scene

#: State size: pose and twist.
_STATE = 6


@dataclass(frozen=True, eq=False)
class SlotLayout:
    """Tables of a scene with one dynamic body (the tracked one), built once.

    Shapes are the polygons and half-planes of the scene, in the order ``[tracked body,
    kinematic bodies, static polygons, half-planes]`` (that of their poses); every slot group
    has the tracked body on one side.

    Attributes:
        slots: the slot geometry's tables of the shapes and the scene's slot groups.
        static_poses: ``(Nf, 3)`` poses of the static shapes (zero for half-planes).
        slot_kinematic: ``(S,)`` index of each slot's kinematic body (0 if its group has none).
        feature_sign: ``(S, 9)`` signs of the features of :func:`slot_rows` as
            :func:`slot_rows` first computes them (``φ``, ``n``, ``r · t``, ``t``, ``r · n``
            and the kinematic body's velocity along ``n`` and ``t``): the tracked body's
            columns of the rows are ``±(n, r × n = −r · t)`` and ``±(t, r × t = r · n)``, ``+``
            where it is the receiver (owns the vertex), and the known velocities count with
            ``+1`` where the kinematic body is the receiver, ``-1`` where it is the other
            body, 0 where the group has none.
        gravity_step: ``(3,)`` the contact-free velocity change of a step, ``h g``.
        h: time step, seconds.
        pose_tangents: ``(3, Ns, 3)`` the derivatives of every shape's pose along ``x``, ``y``
            and ``θ`` of the tracked body (the unit vectors on the tracked shape, else 0).
        pose_directions: ``(3, 3)`` the identity: the derivatives of the pose along itself.
        tangent_mask: ``(4, 1, 1, 1)`` ``(0, 1, 1, 1)``: the derivatives among the stacked rows
            of :func:`slot_rows` (value, then ``x``, ``y``, ``θ``).
        body_mask: ``(4, 1, 6)`` 1 on the value's row and on the angular velocity of the
            derivatives' rows: what of a kinematic body's pose and twist the stacked point
            velocities use.
        embed: ``(3, 6)`` ``[I₃ 0]``: the pose part of a step's Jacobian.
        twist_tangents: ``(3, 3, 1)`` the unit twists, the derivatives of ``v`` along ``v``.
        closing: ``(2, 1, 1)`` 0 at the linearization point, 1 at the consistency check's
            point (the same with the mode's gaps closed).
    """

    slots: PlanarSlotTable
    static_poses: Tensor
    slot_kinematic: Tensor
    feature_sign: Tensor
    gravity_step: Tensor
    h: float
    pose_tangents: Tensor
    pose_directions: Tensor
    tangent_mask: Tensor
    body_mask: Tensor
    embed: Tensor
    twist_tangents: Tensor
    closing: Tensor


def slot_layout(scene: Scene, device: torch.device) -> SlotLayout:
    """The :class:`SlotLayout` of a scene with exactly one dynamic body, on ``device`` (the
    geometry only: the physical parameters are the model's, see
    :class:`~torchcontact.filters.PlanarContactModel`)."""
    f64 = torch.float64
    (tracked,) = scene.dynamic
    static, planes = [], []
    for i, body in enumerate(scene.bodies):
        if isinstance(body.shape, HalfPlane):
            planes.append(i)
        elif body.kind == "static":
            static.append(i)
    shapes = [tracked, *scene.kinematic, *static, *planes]
    shape_index = {body: s for s, body in enumerate(shapes)}
    table = planar_slot_table(
        [scene.bodies[i].shape for i in shapes],
        [(shape_index[g.receiver], shape_index[g.other]) for g in scene.slot_groups],
        margin=scene.margin,
    )

    slot_kinematic: list[int] = []
    feature_sign: list[list[float]] = []
    for group in scene.slot_groups:
        partner = group.other if group.receiver == tracked else group.receiver
        moving = scene.bodies[partner].kind == "kinematic"
        dynamic = 1.0 if group.receiver == tracked else -1.0
        known = 0.0 if not moving else 1.0 if group.receiver == partner else -1.0
        signs = [1.0, dynamic, dynamic, -dynamic, dynamic, dynamic, dynamic, known, known]
        slot_kinematic.extend([scene.kinematic.index(partner) if moving else 0] * group.count)
        feature_sign.extend([signs] * group.count)

    assert scene.gravity is not None  # set by Scene.__post_init__
    gravity = torch.tensor([*scene.gravity, 0.0], dtype=f64)
    static_poses = torch.zeros(len(static) + len(planes), 3, dtype=f64)
    for s, body_index in enumerate(static):
        pose = scene.bodies[body_index].pose
        assert pose is not None
        static_poses[s] = pose.detach()
    eye = torch.eye(3, dtype=f64)
    pose_tangents = torch.zeros(3, len(shapes), 3, dtype=f64)
    pose_tangents[:, 0] = eye
    body_mask = torch.zeros(4, 1, 6, dtype=f64)
    body_mask[0], body_mask[1:, ..., 5] = 1.0, 1.0
    fields = {
        "static_poses": static_poses,
        "slot_kinematic": torch.tensor(slot_kinematic, dtype=torch.long),
        "feature_sign": torch.tensor(feature_sign, dtype=f64),
        "gravity_step": scene.h * gravity,
        "pose_tangents": pose_tangents,
        "pose_directions": eye,
        "tangent_mask": torch.tensor([0.0, 1.0, 1.0, 1.0], dtype=f64).view(4, 1, 1, 1),
        "body_mask": body_mask,
        "embed": torch.eye(3, _STATE, dtype=f64),
        "twist_tangents": eye.unsqueeze(-1),
        "closing": torch.tensor([0.0, 1.0], dtype=f64).view(2, 1, 1),
    }
    return SlotLayout(
        slots=table.to(dtype=f64, device=device),
        **{name: value.to(device) for name, value in fields.items()},
        h=float(scene.h),
    )


def slot_rows(
    layout: SlotLayout,
    q: Tensor,
    q_kinematic: Tensor,
    v_kinematic: Tensor,
    *,
    tangents: bool = False,
) -> tuple[Tensor, Tensor]:
    """Every slot's rows of the contact problem (the tracked body's columns of them), and with
    ``tangents`` their derivatives along the tracked body's pose.

    The slot geometry is :func:`~torchcontact.geometry.planar_slots`' (that of
    :func:`~torchcontact.sim.contact_problem`), with its exact forward tangents along the
    tracked pose; the rows are linear in the geometry's outputs and the arm ``r`` from the
    tracked body's position to the slot's point, so their derivatives follow by the product
    rule on the stacked values and derivatives.

    Args:
        layout: the scene's layout.
        q: ``(*P, 3)`` poses of the tracked body.
        q_kinematic: ``(*P, Nk, 3)`` poses of the kinematic bodies.
        v_kinematic: ``(*P, Nk, 3)`` their twists.
        tangents: also return the derivatives along ``x``, ``y`` and ``θ`` of the tracked body.

    Returns:
        ``(*P, S, 9)``: ``φ``, the normal row ``Jn`` (3), the row ``Jt`` of friction direction
        ``+t`` (3; direction ``−t`` is its negative), and the known velocities ``bn`` and
        ``bt`` (along ``+t``); with ``tangents`` ``(*P, 4, S, 9)``: those, then their
        derivatives along ``x``, ``y`` and ``θ``; and the ``(*P, S)`` bool candidates.
    """
    batch = q.shape[:-1]
    static = layout.static_poses.expand(*batch, -1, 3)
    poses = torch.cat([q.unsqueeze(-2), q_kinematic, static], dim=-2)  # (*P, Ns, 3)
    arm_origin = q[..., None, :2]
    if tangents:
        geometry = planar_slots(
            layout.slots, poses, layout.pose_tangents.expand(*batch, *layout.pose_tangents.shape)
        )
        stacked = torch.cat([q.unsqueeze(-2), layout.pose_directions.expand(*batch, 3, 3)], -2)
        arm_origin = stacked[..., None, :2]  # (*P, D, 1, 2)
    else:
        geometry = planar_slots(layout.slots, poses)
    points, normals = geometry.points, geometry.normals  # (*P, [D,] S, 2)
    turn = layout.slots.turn
    # The slot's normal and tangent (n turned +90°), stacked: (*P, [D,] S, 2, 2).
    frames = torch.stack([normals, normals.flip(-1) * turn], dim=-2)
    arm = (points - arm_origin).unsqueeze(-2)
    if tangents:
        frames_value = frames[..., :1, :, :, :]
        frames_tangent = frames * layout.tangent_mask
        arm_value = arm[..., :1, :, :, :]
        moments = dot2(frames_value, arm, frames_tangent, arm_value)
    else:
        moments = dot2(frames, arm)  # r · n, r · t
    if q_kinematic.shape[-2]:
        # Point velocities of the slots' kinematic bodies (a group without one has sign 0).
        body = torch.cat([q_kinematic, v_kinematic], dim=-1).index_select(
            -2, layout.slot_kinematic
        )  # (*P, S, 6)
        if tangents:
            # The tangents keep only the angular velocity: ω turns the arm's derivative.
            body = body.unsqueeze(-3) * layout.body_mask  # (*P, D, S, 6)
        spun = (points - body[..., :2]).flip(-1) * turn
        velocity = torch.addcmul(body[..., 3:5], body[..., 5:], spun).unsqueeze(-2)
        if tangents:
            known = dot2(frames_value, velocity, frames_tangent, velocity[..., :1, :, :, :])
        else:
            known = dot2(frames, velocity)  # (*P, S, 2): along n, t
    else:
        known = torch.zeros_like(moments)
    features = torch.cat(
        [
            geometry.phi.unsqueeze(-1),
            frames[..., 0, :],
            moments[..., 1:],
            frames[..., 1, :],
            moments[..., :1],
            known,
        ],
        dim=-1,
    )
    return features * layout.feature_sign, geometry.active
