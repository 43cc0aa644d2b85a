"""Slot rows of a planar scene with one tracked body, and their derivatives along its pose.

The tables (:class:`SlotLayout`) are built once per scene; :func:`slot_rows` computes every
slot group's rows at once from them, in a fixed number of tensor operations whatever the batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact.geometry import TIE_TOLERANCE, HalfPlane, Polygon
from torchcontact.sim import Scene

#: Offset of padding edges (signed distance about ``-_FAR``: never the closest edge).
_FAR = 1e30
#: State size: pose and twist.
_STATE = 6


@dataclass(frozen=True, eq=False)
class SlotLayout:
    """Tables of a scene with one dynamic body (the tracked one), built once.

    Shapes are the polygons and half-planes of the scene, in the order ``[tracked body,
    kinematic bodies, static polygons, half-planes]`` (that of their poses), padded to ``V``
    edges: a polygon's padding vertices repeat its first vertex and its padding edges have zero
    normal and direction and lie far away; a half-plane is a single edge of unbounded length
    at the zero pose, whose direction (its tangent) lies within reach everywhere. Slot groups
    (``G``) pair a receiver's vertices with the other shape's edges; every group has the
    tracked body on one side.

    Attributes:
        frame: ``(Ns, 3V + 1, 2)`` body-frame rows of every shape: vertices, outward edge
            normals, edge directions (the normals turned by +90°; edge ``e`` runs from vertex
            ``e`` to ``e + 1``) and the origin (zero).
        frame_turned: ``(Ns, 3V + 1, 2)`` the same rows turned by +90°, so that a shape at
            angle ``θ`` has the rows ``cos θ · frame + sin θ · frame_turned``.
        translated: ``(3V + 1, 1)`` 1 on the rows that move with the shape's position (the
            vertices and the origin), 0 on the normals and directions.
        static_poses: ``(Nf, 3)`` poses of the static shapes.
        group_shapes: ``(2G,)`` shape of each group's vertices, then of its edges.
        group_kinematic: ``(G,)`` index of each group's kinematic body (0 if it has none).
        edge_offset: ``(G, 1, 2V)`` ``a_e · n_e`` and ``a_e · d_e`` of the other shape's edges
            in its body frame (``a_e`` the edge's first vertex).
        facing_offset: ``(G, 1, V)`` ``(a_e − c) · n_e``, ``c`` the other shape's vertex mean.
        edge_reach: ``(G, 1, V)`` the other shape's edge lengths plus the margin.
        tie_tolerance: ``(G, 1, 1)`` absolute tolerance of equally close edges.
        feature_sign: ``(G, V, 9)`` signs of the features of :func:`slot_rows` as
            :func:`slot_rows` first computes them (``φ``, ``n``, ``r · t``, ``t``, ``r · n``
            and the kinematic body's velocity along ``n`` and ``t``): the tracked body's
            columns of the rows are ``±(n, r × n = −r · t)`` and ``±(t, r × t = r · n)``, ``+``
            where it is the receiver (owns the vertex), and the known velocities count with
            ``+1`` where the kinematic body is the receiver, ``-1`` where it is the other
            body, 0 where the group has none.
        slot_source: ``(S,)`` each slot's index among the groups' ``G·V`` vertex slots, or
            None where they are the same (every receiver has ``V`` vertices).
        mu: ``(S,)`` friction coefficients.
        inverse_mass: ``(3,)`` diagonal of the tracked body's inverse mass matrix.
        gravity_step: ``(3,)`` the contact-free velocity change of a step, ``h M⁻¹ f``.
        turn: ``(2,)`` ``(−1, 1)``: ``u.flip(-1) * turn`` turns ``u`` by +90°.
        h: time step, seconds.
        margin: candidate margin, metres.
        pose_tangent: ``(2, 3V + 1, 2)`` the derivatives of a shape's rows along ``x`` and
            ``y`` of its pose (``translated`` times the unit vectors).
        tracked: ``(2G, 1, 1)`` 1 where ``group_shapes`` is the tracked body, else 0.
        pose_directions: ``(3, 3)`` the identity: the derivatives of the pose along itself.
        tangent_mask: ``(4, 1, 1, 1)`` ``(0, 1, 1, 1)``: the derivatives among the stacked rows
            of :func:`slot_rows` (value, then ``x``, ``y``, ``θ``).
        body_mask: ``(4, 1, 1, 6)`` 1 on the value's row and on the angular velocity of the
            derivatives' rows: what of a kinematic body's pose and twist the stacked point
            velocities use.
        stacked_offset: ``(4, G, 1, 2V)`` ``edge_offset`` on the value's row, 0 on the
            derivatives' rows.
        embed: ``(3, 6)`` ``[I₃ 0]``: the pose part of a step's Jacobian.
        twist_tangents: ``(3, 3, 1)`` the unit twists, the derivatives of ``v`` along ``v``.
        closing: ``(2, 1, 1)`` 0 at the linearization point, 1 at the consistency check's
            point (the same with the mode's gaps closed).
    """

    frame: Tensor
    frame_turned: Tensor
    translated: Tensor
    static_poses: Tensor
    group_shapes: Tensor
    group_kinematic: Tensor
    edge_offset: Tensor
    facing_offset: Tensor
    edge_reach: Tensor
    tie_tolerance: Tensor
    feature_sign: Tensor
    slot_source: Tensor | None
    mu: Tensor
    inverse_mass: Tensor
    gravity_step: Tensor
    turn: Tensor
    h: float
    margin: float
    pose_tangent: Tensor
    tracked: Tensor
    pose_directions: Tensor
    tangent_mask: Tensor
    body_mask: Tensor
    stacked_offset: Tensor
    embed: Tensor
    twist_tangents: Tensor
    closing: Tensor


def slot_layout(scene: Scene, device: torch.device) -> SlotLayout:
    """The :class:`SlotLayout` of a scene with exactly one dynamic body, on ``device``.

    Raises:
        ValueError: naming ``scene`` if a pair's friction is not a scalar (one scene serves
            every batch entry).
    """
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
    V = max(body.shape.num_vertices for body in scene.bodies if isinstance(body.shape, Polygon))
    frame = torch.zeros(len(shapes), 3 * V + 1, 2, dtype=f64)
    edge_offset = torch.full((len(shapes), 2 * V), _FAR, dtype=f64)
    facing_offset = torch.zeros(len(shapes), V, dtype=f64)
    edge_length = torch.zeros(len(shapes), V, dtype=f64)
    turn = torch.tensor([-1.0, 1.0], dtype=f64)
    for s, body_index in enumerate(shapes):
        shape = scene.bodies[body_index].shape
        if isinstance(shape, HalfPlane):  # one edge, everywhere within reach
            frame[s, V], frame[s, 2 * V] = shape.normal, shape.normal.flip(-1) * turn
            edge_offset[s, 0], edge_offset[s, V] = shape.point @ shape.normal, -_FAR
            edge_length[s, 0] = torch.inf
            continue
        local = shape.vertices.to(f64)
        n = len(local)
        edge = local.roll(-1, dims=0) - local
        length = edge.norm(dim=-1)
        direction = edge / length.unsqueeze(-1)
        outward = torch.stack([direction[:, 1], -direction[:, 0]], dim=-1)
        frame[s, :n], frame[s, n:V] = local, local[0]
        frame[s, V : V + n], frame[s, 2 * V : 2 * V + n] = outward, direction
        edge_offset[s, :n] = (local * outward).sum(-1)
        edge_offset[s, V : V + n] = (local * direction).sum(-1)
        facing_offset[s, :n] = ((local - local.mean(dim=0)) * outward).sum(-1)
        edge_length[s, :n] = length
    translated = torch.zeros(3 * V + 1, 1, dtype=f64)
    translated[:V] = translated[-1] = 1.0

    receiver, other, group_kinematic = [], [], []
    feature_sign = torch.zeros(len(scene.slot_groups), V, 9, dtype=f64)
    slot_source: list[int] = []
    mu: list[float] = []
    for g, group in enumerate(scene.slot_groups):
        receiver.append(shape_index[group.receiver])
        other.append(shape_index[group.other])
        friction = torch.as_tensor(scene.pair_mu(group.receiver, group.other), dtype=f64).detach()
        if friction.numel() != 1:
            raise ValueError(
                "scene: the linearization needs scalar friction coefficients, got a tensor of "
                f"shape {tuple(friction.shape)}"
            )
        partner = group.other if group.receiver == tracked else group.receiver
        moving = scene.bodies[partner].kind == "kinematic"
        group_kinematic.append(scene.kinematic.index(partner) if moving else 0)
        dynamic = 1.0 if group.receiver == tracked else -1.0
        known = 0.0 if not moving else 1.0 if group.receiver == partner else -1.0
        feature_sign[g] = torch.tensor(
            [1.0, dynamic, dynamic, -dynamic, dynamic, dynamic, dynamic, known, known]
        )
        slot_source.extend(g * V + j for j in range(group.count))
        mu.extend([float(friction)] * group.count)

    body = scene.bodies[tracked]
    mass, inertia = float(body.mass_value().detach()), float(body.inertia_value().detach())
    gravity = torch.tensor([*scene.gravity, 0.0], dtype=f64)
    groups = torch.tensor(other, dtype=torch.long)
    static_poses = torch.zeros(len(static) + len(planes), 3, dtype=f64)
    for s, body_index in enumerate(static):
        pose = scene.bodies[body_index].pose
        assert pose is not None
        static_poses[s] = pose.detach()
    eye = torch.eye(3, dtype=f64)
    tangent_mask = torch.tensor([0.0, 1.0, 1.0, 1.0], dtype=f64).view(4, 1, 1, 1)
    body_mask = torch.zeros(4, 1, 1, 6, dtype=f64)
    body_mask[0], body_mask[1:, ..., 5] = 1.0, 1.0
    edge_offsets = edge_offset[groups].unsqueeze(-2)
    fields = {
        "frame": frame,
        "frame_turned": frame.flip(-1) * turn,
        "translated": translated,
        "static_poses": static_poses,
        "group_shapes": torch.tensor(receiver + other, dtype=torch.long),
        "group_kinematic": torch.tensor(group_kinematic, dtype=torch.long),
        "edge_offset": edge_offsets,
        "facing_offset": facing_offset[groups].unsqueeze(-2),
        "edge_reach": edge_length[groups].unsqueeze(-2) + scene.margin,
        "tie_tolerance": TIE_TOLERANCE  # of a half-plane: 0, it has a single edge
        * edge_length[groups].nan_to_num(posinf=0.0).amax(-1)[:, None, None],
        "feature_sign": feature_sign,
        "mu": torch.tensor(mu, dtype=f64),
        "inverse_mass": torch.tensor([1.0 / mass, 1.0 / mass, 1.0 / inertia], dtype=f64),
        "gravity_step": scene.h * gravity,
        "turn": turn,
        "pose_tangent": translated * eye[:2, None, :2],
        "tracked": (torch.tensor(receiver + other) == 0).to(f64)[:, None, None],
        "pose_directions": eye,
        "tangent_mask": tangent_mask,
        "body_mask": body_mask,
        "stacked_offset": edge_offsets * (1.0 - tangent_mask),
        "embed": torch.eye(3, _STATE, dtype=f64),
        "twist_tangents": eye.unsqueeze(-1),
        "closing": torch.tensor([0.0, 1.0], dtype=f64).view(2, 1, 1),
    }
    source = None
    if slot_source != list(range(len(scene.slot_groups) * V)):
        source = torch.tensor(slot_source, dtype=torch.long, device=device)
    return SlotLayout(
        **{name: value.to(device) for name, value in fields.items()},
        slot_source=source,
        h=float(scene.h),
        margin=float(scene.margin),
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

    The slot geometry is that of :func:`~torchcontact.sim.contact_problem`: for a vertex
    against a polygon the closest edge is the one of largest signed distance, ties going to
    the edge that faces the vertex from the polygon's vertex mean, as in
    :func:`~torchcontact.geometry.polygon_slots`.

    The derivatives are exact, propagated by hand through the same operations (plain tensor
    operations, as :func:`torch.compile` wants them): a rotated row's derivative along ``θ``
    is the row turned by +90°, the signed distance ``φ`` (the largest over the edges) takes
    that of its arg-max edge (at a tie, the closest edge, whose normal the slot takes: a
    one-sided derivative), and the discrete decisions (closest edge, candidates) are held
    fixed. They are stacked behind the rows, so that the linear operations (gathers, slices,
    signs) run once on both.

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
    G, V = layout.facing_offset.shape[0], layout.facing_offset.shape[-1]
    static = layout.static_poses.expand(*q.shape[:-1], -1, 3)
    poses = torch.cat([q.unsqueeze(-2), q_kinematic, static], dim=-2)  # (*P, Ns, 3)
    angle = poses[..., 2, None, None]
    rotated = layout.frame * torch.cos(angle) + layout.frame_turned * torch.sin(angle)
    world = torch.addcmul(rotated, layout.translated, poses[..., None, :2])  # (*P, Ns, 3V+1, 2)
    shapes = world.index_select(-3, layout.group_shapes)
    arm_origin = q[..., None, None, :2]
    if tangents:
        # D = 4 stacked rows: the values, then the derivatives along x, y and θ of the tracked
        # body's rows (translated rows move along x and y; rotated rows turn by +90° along θ);
        # the other shapes do not move.
        turned = rotated[..., :1, :, :].flip(-1) * layout.turn  # (*P, 1, 3V+1, 2)
        moving = torch.cat([layout.pose_tangent.expand(*q.shape[:-1], 2, -1, 2), turned], -3)
        shapes = torch.cat([shapes.unsqueeze(-4), moving.unsqueeze(-3) * layout.tracked], -4)
        stacked = torch.cat(
            [q.unsqueeze(-2), layout.pose_directions.expand(*q.shape[:-1], 3, 3)], -2
        )
        arm_origin = stacked[..., None, None, :2]  # (*P, D, 1, 1, 2)
    points, other = shapes[..., :G, :V, :], shapes[..., G:, :, :]  # (*P, [D,] G, V or 3V+1, 2)
    edges = other[..., V : 3 * V, :]  # (*P, G, 2V, 2): outward normals, then directions
    relative = points - other[..., 3 * V :, :]
    if tangents:
        # Products of rows: value · derivative + derivative · value (the value's only once).
        edges_value, relative_value = edges[..., :1, :, :, :], relative[..., :1, :, :, :]
        projection = (
            relative @ edges_value.mT
            + relative_value @ (edges * layout.tangent_mask).mT
            - layout.stacked_offset
        )
        moved = projection[..., 1:, :, :, :V]  # (*P, 3, G, V, V): the distances' derivatives
        distance, along = projection[..., 0, :, :, :V], projection[..., 0, :, :, V:]
    else:
        projection = relative @ edges.mT - layout.edge_offset
        distance, along = projection[..., :V], projection[..., V:]  # (*P, G, V, V) each
    phi = distance.amax(dim=-1, keepdim=True)
    tie = distance >= phi - layout.tie_tolerance
    closest = torch.where(tie, distance + layout.facing_offset, -_FAR).argmax(-1, keepdim=True)
    phis = phi
    if tangents:
        # φ's derivative: that of the closest edge (the arg-max, ties going as the normal's).
        turning = moved.gather(-1, closest.unsqueeze(-4).expand(*moved.shape[:-1], 1))
        phis = torch.cat([phi.unsqueeze(-4), turning], dim=-4)  # (*P, D, G, V, 1)
    in_reach = (along >= -layout.margin) & (along <= layout.edge_reach)
    candidate = in_reach.gather(-1, closest) & (phi <= layout.margin)  # (*P, G, V, 1)
    # The closest edge's normal and direction: the slot's normal and tangent (n turned +90°).
    index = closest.unsqueeze(-3)
    if tangents:
        index = index.unsqueeze(-5)
    index = index.expand(*edges.shape[:-3], G, 2, V, 2)
    frames = edges.unflatten(-2, (2, V)).gather(-2, index)  # (*P, [D,] G, 2, V, 2)
    arm = (points - arm_origin).unsqueeze(-3)
    if tangents:
        frames_value = frames[..., :1, :, :, :, :]
        frames_tangent = frames * layout.tangent_mask.unsqueeze(-1)
        arm_value = arm[..., :1, :, :, :, :]
        moments = torch.addcmul(frames_value * arm, frames_tangent, arm_value).sum(-1)
    else:
        moments = (frames * arm).sum(-1)  # r · n, r · t
    if q_kinematic.shape[-2]:
        # Point velocities of the groups' kinematic bodies (a group without one has sign 0).
        body = torch.cat([q_kinematic, v_kinematic], dim=-1).index_select(
            -2, layout.group_kinematic
        )
        body = body.unsqueeze(-2)  # (*P, G, 1, 6)
        if tangents:
            # The tangents keep only the angular velocity: ω turns the arm's derivative.
            body = body.unsqueeze(-4) * layout.body_mask  # (*P, D, G, 1, 6)
        spun = (points - body[..., :2]).flip(-1) * layout.turn
        velocity = torch.addcmul(body[..., 3:5], body[..., 5:], spun).unsqueeze(-3)
        if tangents:
            known = torch.addcmul(
                frames_value * velocity, frames_tangent, velocity[..., :1, :, :, :, :]
            ).sum(-1)
        else:
            known = (frames * velocity).sum(-1)  # (*P, G, 2, V): along n, t
    else:
        known = torch.zeros_like(moments)
    features = torch.cat(
        [
            phis,
            frames[..., 0, :, :],
            moments[..., 1, :, None],
            frames[..., 1, :, :],
            moments[..., 0, :, None],
            known.mT,
        ],
        dim=-1,
    )
    features = (features * layout.feature_sign).flatten(-3, -2)  # (*P, [D,] G·V, 9)
    candidate = candidate.flatten(-3)
    if layout.slot_source is None:
        return features, candidate
    source = layout.slot_source
    return features.index_select(-2, source), candidate.index_select(-1, source)
