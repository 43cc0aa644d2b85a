"""The per-mode linearization of :class:`~torchcontact.filters.PlanarContactModel`, fast.

It computes what the model's definition asks for: the exact Jacobian of the mode-fixed step
(:func:`~torchcontact.sim.contact_problem`, :func:`~torchcontact.contact.solve_mode`,
semi-implicit Euler) at the linearization point, and
:func:`~torchcontact.contact.is_consistent` there with the mode's gaps closed. The tensors
are small (a few modes, a dozen slots), so the time goes into the number of tensor
operations (a few microseconds each), not their size; this module uses a fixed number of
them per call, whatever the batch:

* the slot rows of every slot group at once (:func:`slot_rows`), from body-frame tables built
  once per scene: each shape's vertices, edge normals and edge directions (its contact
  tangents) rotate together, and a half-plane is a polygon of one unbounded edge; with them
  their derivatives along the tracked body's pose (``x``, ``y``, ``θ``), in closed form by
  the same operations (a rotated row's derivative along ``θ`` is the row turned by +90°, the
  gap ``φ`` takes that of its closest edge), stacked behind the rows;
* each mode's system holds only the slots that the mode activates and that are candidates at
  the point (sorted from a table of each mode's slots built once per model);
  ``solve_mode``'s system is the identity on every other row. The mode fixes the constraint
  rows ``C`` (active normals, sticking tangents), the impulse rows ``G`` (``C`` with
  ``μ Jt_d`` added to the normals of sliding slots), ``U = M⁻¹ Gᵀ``, ``A = C U`` and
  ``b = −(C v_free + target)``, ``target = (bn + φ/h, bt)``; all linear in the slot rows, so
  their derivatives along the pose follow from the rows' by the same operations;
* ``solve_mode``'s two iterated Tikhonov passes for the impulses ``x`` (``A x = b``), at the
  point and at the point with the mode's gaps closed (the consistency check's); the second
  pass (the friction split among redundant sticking contacts) runs on every mode and is kept
  for those with sticking slots, as ``solve_mode`` on one mode: it leaves the step unchanged
  where the mode's system is solvable, and decides the regularised answer where it is not.
  Each pass inverts its matrices once and iterates with products;
* the derivative along each of the six coordinates at once: ``dx = P(db − dA x)`` with
  ``dA = dC U + C dU`` and ``P`` the iterated Tikhonov solve of the pass kept (its inverse
  and weights held), ``dv⁺ = dU x + U dx + dv_free`` (``dv_free`` the unit twists along
  ``v``, zero along the pose), so that ``F = [[I + h ∂v⁺/∂q, h ∂v⁺/∂v], [∂v⁺/∂q, ∂v⁺/∂v]]``;
* ``is_consistent``'s tests on every slot, knowing which carry impulses;
* one host synchronisation (the size of the systems) and no validation: the model checks its
  inputs at its public methods.

With ``for_compile`` (the model's ``compiled=True``) the systems are sized by the mode table
instead: no host synchronisation, shapes that do not depend on the data, as
:func:`torch.compile` wants them.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact.contact import (
    SOLVE_MODE_FRICTION_COST,
    SOLVE_MODE_MIN_LOAD_SHARE,
    SOLVE_MODE_REFINEMENTS,
    SOLVE_MODE_WEIGHTED_REFINEMENTS,
)
from torchcontact.geometry import TIE_TOLERANCE, HalfPlane, Polygon
from torchcontact.sim import Scene

#: Offset of padding edges (signed distance about ``-_FAR``: never the closest edge).
_FAR = 1e30
#: State size: pose and twist.
_STATE = 6
#: Tikhonov shift of ``solve_mode`` relative to the largest diagonal entry of the system.
_SQRT_EPS = torch.finfo(torch.float64).eps ** 0.5


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


@dataclass(frozen=True, eq=False)
class ModeTable:
    """A model's per-slot modes as the linearization uses them, built once.

    Each mode's constraint system is laid out over ``W`` slots (``W`` the most slots any mode
    activates among the candidates of the call): the slots it activates that are candidates,
    in slot order, then others, whose rows are unused (the identity): ``W`` normal rows, then
    ``W`` tangent rows. The table keeps each mode's first ``W_max`` slots in that order
    without the candidates (those it activates, then the others), so a call only sorts them.

    Attributes:
        modes: ``(K, S)`` long per-slot modes.
        slots: ``(K, W_max)`` long, the slots each mode activates in slot order, then the
            first slots it does not (``W_max`` the most slots any mode activates).
        activates: ``(K, W_max)`` bool, the mode activates the slot (mode ≥ 1).
        sticks: ``(K, W_max)`` bool, the slot sticks in the mode (mode 1).
        slide: ``(K, W_max)`` float64 ``±μ`` of slots sliding with friction along ``±t``,
            else 0.
        eyes: the ``(2w, 2w)`` float64 identities, ``w = 1 … W_max``.
        acting: ``(K, S)`` bool, the slot carries an impulse in the mode (mode ≥ 1).
        separated: ``(K, S)`` bool, mode 0.
        sticking: ``(K, S)`` bool, mode 1.
        slip_sign: ``(K, S)`` float64 ``-1`` where friction acts along ``−t`` (mode 3), else 1.
    """

    modes: Tensor
    slots: Tensor
    activates: Tensor
    sticks: Tensor
    slide: Tensor
    eyes: tuple[Tensor, ...]
    acting: Tensor
    separated: Tensor
    sticking: Tensor
    slip_sign: Tensor


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


def mode_table(layout: SlotLayout, modes: Tensor) -> ModeTable:
    """The :class:`ModeTable` of ``(K, S)`` long per-slot modes."""
    f64 = torch.float64
    modes = modes.to(layout.mu.device)
    acting = modes >= 1
    W = max(1, int(acting.sum(-1).max()))
    slots = torch.argsort(acting.to(torch.uint8), dim=-1, descending=True, stable=True)[:, :W]
    sign = (modes == 2).to(f64) - (modes == 3).to(f64)
    return ModeTable(
        modes=modes,
        slots=slots,
        activates=acting.gather(-1, slots),
        sticks=(modes == 1).gather(-1, slots),
        slide=(sign * layout.mu).gather(-1, slots),
        eyes=tuple(torch.eye(2 * w, dtype=f64, device=modes.device) for w in range(1, W + 1)),
        acting=acting,
        separated=modes == 0,
        sticking=modes == 1,
        slip_sign=1.0 - 2.0 * (modes == 3).to(f64),
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


def _tikhonov(
    system: Tensor,
    diagonal: Tensor,
    b: Tensor,
    shift: Tensor,
    eye: Tensor,
    refinements: int,
) -> tuple[Tensor, Tensor]:
    """``solve_mode``'s iterated Tikhonov solve of ``A x = b``.

    Iterates ``(A + S) x_{i+1} = b + S x_i`` from ``x_0 = 0``, where ``A + S`` is ``system``
    plus ``diag(diagonal)`` and ``S = diag(shift)``: the solution when ``A`` is nonsingular,
    the one of least ``xᵀ S x`` when it is singular and consistent. It inverts ``A + S`` once
    (one LAPACK call) and iterates with products (``solve_mode`` solves with LU factors at
    every iteration: the same iterates to rounding).

    Args:
        system: ``(*B, m, m)`` system matrices less their diagonal additions.
        diagonal: ``(*B, m)`` the additions to their diagonals (identity rows and shift).
        b: ``(*B, m, r)`` right-hand sides.
        shift: ``(*B, m, 1)`` or ``(*B, 1, 1)`` the diagonal of ``S``.
        eye: ``(m, m)`` identity.
        refinements: number of iterations.

    Returns:
        ``(*B, m, r)``, and the inverse of ``A + S`` (for :func:`_iterate`).
    """
    inverse = torch.linalg.inv_ex(torch.addcmul(system, eye, diagonal.unsqueeze(-2)))[0]
    return _iterate(inverse, b, shift, refinements), inverse


def _iterate(inverse: Tensor, b: Tensor, shift: Tensor, refinements: int) -> Tensor:
    """The iterations of :func:`_tikhonov` with the inverse of ``A + S`` (which broadcasts
    against ``b``): a linear operator on ``b``."""
    x = inverse @ b
    for _ in range(refinements - 1):
        x = inverse @ torch.addcmul(b, shift, x)
    return x


def linearize_modes(
    layout: SlotLayout,
    table: ModeTable,
    x: Tensor,
    q_kinematic: Tensor,
    v_kinematic: Tensor,
    *,
    consistency_gap: float,
    consistency_tolerance: float,
    for_compile: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """Every mode's step linearized at ``x`` (its exact Jacobian), and its consistency.

    Args:
        layout: the scene's layout.
        table: the ``K`` modes.
        x: ``(B, 6)`` float64 linearization points.
        q_kinematic: ``(B, Nk, 3)`` float64 kinematic poses.
        v_kinematic: ``(B, Nk, 3)`` float64 kinematic twists.
        consistency_gap: gaps of a mode's slots within ``±consistency_gap`` are taken as
            closed by the check: a mean a millimetre off a contact (whose ``φ/h`` correction
            would turn its impulse around) does not count against the mode, while a contact
            held across a wider gap (a box "stuck" to a finger it has left) does.
        consistency_tolerance: relative tolerance of the check.
        for_compile: lay every system out over ``W_max`` slots (the most any mode of the
            table activates) instead of the most the modes activate among this call's
            candidates (the extra rows are the identity, decoupled): larger systems, the same
            results to rounding, no host synchronisation and shapes that do not depend on the
            data, as :func:`torch.compile` wants them.

    Returns:
        ``F (B, K, 6, 6)``, ``c (B, K, 6)`` and ``(B, K)`` bool: the mode is consistent.
    """
    B, (K, S), h, gap = x.shape[0], table.modes.shape, layout.h, consistency_gap
    features, candidate = slot_rows(layout, x[:, :3], q_kinematic, v_kinematic, tangents=True)
    centre = features[:, 0]  # (B, S, 9); features (B, 4, S, 9): value, d/dx, d/dy, d/dθ

    # Each mode's slots: those it activates among the candidates, in slot order, then others.
    slots = table.slots.expand(B, K, -1)
    acting = candidate.gather(-1, slots.flatten(1)).view_as(slots) & table.activates
    W = table.slots.shape[-1] if for_compile else max(1, int(acting.sum(-1).max()))
    order = torch.argsort(acting.to(torch.uint8), dim=-1, descending=True, stable=True)[..., :W]
    keep = slots.gather(-1, order)  # (B, K, W)
    acting = acting.gather(-1, order)
    sticks = acting & table.sticks.expand(B, K, -1).gather(-1, order)
    slide = table.slide.expand(B, K, -1).gather(-1, order)[:, :, None, :, None]

    # solve_mode on those slots: constraint rows C (normals, then tangents) and impulse rows
    # G (the same with μ Jt_d added to the normals of sliding slots); the rows of acting
    # normals and sticking tangents make the Schur system A = C U, U = M⁻¹ Gᵀ, for the
    # impulses; the other rows are the identity, with a zero right side. All of it is linear
    # in the slot rows, so their derivatives along the pose (stacked behind them) give dC,
    # dU and the derivative of the target (bn + φ/h, bt) by the same operations.
    index = (torch.arange(4, device=x.device)[:, None] * S + keep.unsqueeze(2)).view(B, -1, 1)
    rows = features.flatten(1, 2).gather(1, index.expand(-1, -1, 9)).view(B, K, 4, W, 9)
    phi, Jn, Jt, bn, bt = rows.split([1, 3, 3, 1, 1], dim=-1)
    on = torch.cat([acting, sticks, acting, sticks], dim=-1).to(torch.float64)  # (B, K, 4W)
    rows_on = on[:, :, None, :, None]
    on_c = rows_on[..., : 2 * W, :]
    CG = torch.cat([Jn, Jt, Jn + slide * Jt, Jt], dim=-2) * rows_on
    C, U = CG[..., : 2 * W, :], (CG[..., 2 * W :, :] * layout.inverse_mass).mT  # (B, K, 4, ·, ·)
    target = torch.cat([bn + phi / h, bt], dim=-2)  # (B, K, 4, 2W, 1)
    C0, U0 = C[:, :, :1], U[:, :, :1]
    system = C0 @ U0  # (B, K, 1, 2W, 2W)
    v_free = (x[:, 3:] + layout.gravity_step)[:, None, None, :, None]  # (B, 1, 1, 3, 1)
    # Two points: x, and x with the mode's gaps closed up to the dead zone (the consistency
    # check's).
    closed = torch.nn.functional.pad(phi[:, :, :1].clamp(-gap, gap), (0, 0, 0, W))
    target_points = torch.addcmul(target[:, :, :1], closed, layout.closing, value=-1.0 / h)
    b = torch.addcmul(C0 @ v_free, target_points, on_c).neg()  # (B, K, 2, 2W, 1)
    off = 1.0 - on[:, :, None, : 2 * W]  # (B, K, 1, 2W): the identity rows
    scale = system.diagonal(dim1=-2, dim2=-1).abs().amax(dim=-1, keepdim=True).clamp_min(1.0)
    shift = (_SQRT_EPS * scale).unsqueeze(-1)  # (B, K, 1, 1, 1)
    eye = table.eyes[W - 1]
    impulses, inverse = _tikhonov(
        system, off + shift[..., 0], b, shift, eye, SOLVE_MODE_REFINEMENTS
    )
    # Redundant sticking rows leave the impulse split free: solve_mode prefers normal support
    # and shares friction in proportion to the normal loads (kept for modes that stick).
    load = impulses[..., :W, :].clamp(min=0.0)
    share = load.amax(dim=-2, keepdim=True).clamp_min(torch.finfo(torch.float64).eps)
    friction = SOLVE_MODE_FRICTION_COST * share / (load + SOLVE_MODE_MIN_LOAD_SHARE * share)
    weighted = torch.cat([shift.expand_as(load), shift * friction], dim=-2)  # (..., 2W, 1)
    split, split_inverse = _tikhonov(
        system, off + weighted[..., 0], b, weighted, eye, SOLVE_MODE_WEIGHTED_REFINEMENTS
    )
    sticky = sticks.any(dim=-1)[:, :, None, None, None]
    impulses = torch.where(sticky, split, impulses)
    v_next = v_free + U0 @ impulses  # (B, K, 2, 3, 1)

    # The exact derivative of the step at x along the six coordinates j (the discrete choices
    # held): with w_j = dv_free + dU x (dv_free = e_j along the twist, dU along the pose),
    # dx = P(db − dA x) = −P(dC v⁺ + C w_j + dtarget), P the solve above (its weights held),
    # and dv⁺ = w_j + U dx.
    v_plus = v_next[:, :, :1]
    w = torch.cat(
        [U[:, :, 1:] @ impulses[:, :, :1], layout.twist_tangents.expand(B, K, 3, 3, 1)], 2
    )
    moving = torch.addcmul(C[:, :, 1:] @ v_plus, target[:, :, 1:], on_c)  # (B, K, 3, 2W, 1)
    rhs = (C0 @ w + torch.nn.functional.pad(moving, (0, 0, 0, 0, 0, 3))).neg()  # (B, K, 6, ·)
    held = torch.where(sticky, split_inverse[:, :, :1], inverse)
    weights = torch.where(sticky, weighted[:, :, :1], shift)
    derivative = _iterate(held, rhs, weights, SOLVE_MODE_WEIGHTED_REFINEMENTS)
    dv = (w + U0 @ derivative).squeeze(-1).mT  # (B, K, 3, 6): ∂v⁺/∂x
    F = torch.cat([torch.add(layout.embed, dv, alpha=h), dv], dim=-2)  # (B, K, 6, 6)
    v_step = v_plus[:, :, 0, :, 0]  # (B, K, 3)
    f = torch.cat([x[:, None, :3] + h * v_step, v_step], dim=-1)  # (B, K, 6)
    c = f - (F @ x[:, None, :, None]).squeeze(-1)

    # is_consistent at the last point, on every slot (impulses placed back on their slots).
    v_touch = v_next[:, :, -1, None]  # (B, K, 1, 3, 1)
    impulse = impulses[:, :, -1, :, 0].unflatten(-1, (2, W))  # (B, K, 2, W): normal, tangent
    placed = impulse.new_zeros(B, K, 2, S).scatter(
        -1, keep.unsqueeze(2).expand_as(impulse), impulse
    )
    pn, tangential = placed.unbind(2)
    phi_all = centre[:, None, :, 0]  # (B, 1, S)
    phi_all = torch.where(table.acting, phi_all - phi_all.clamp(-gap, gap), phi_all)
    rows_centre = centre[:, None, :, 1:7].unflatten(-1, (2, 3))  # (B, 1, S, 2, 3)
    velocity = rows_centre @ v_touch  # (B, K, S, 2, 1)
    gap_rate = velocity[..., 0, 0] + centre[:, None, :, 7] + phi_all / h  # (B, K, S)
    slip = velocity[..., 1, 0] + centre[:, None, :, 8]
    # The scales of problem_scales (is_consistent's): velocities the step starts from or the
    # impulses cause at the candidate slots, the known terms, penetration recovery; momenta.
    free = v_free[:, :, 0]  # (B, 1, 3, 1)
    caused = v_touch[:, :, 0] - free  # (B, K, 3, 1): v⁺ − v_free
    rates = torch.cat(
        [
            (rows_centre @ free.unsqueeze(2)).abs().expand(-1, K, -1, -1, -1),
            (rows_centre @ caused.unsqueeze(2)).abs(),
        ],
        dim=-1,
    ).amax(dim=(-2, -1))  # (B, K, S)
    known = centre[:, None, :, 7:9].abs().amax(dim=-1)  # (B, 1, S)
    per_slot = torch.maximum(torch.maximum(rates, known), (-phi_all / h).clamp(min=0.0))
    per_slot = torch.where(candidate.unsqueeze(1), per_slot, 0.0)
    tiny = torch.finfo(torch.float64).tiny
    v_scale = per_slot.amax(dim=-1, keepdim=True).clamp(min=tiny)  # (B, K, 1)
    mass = layout.inverse_mass.reciprocal()
    momenta = torch.cat(
        [
            (mass * x[:, 3:]).abs().amax(dim=-1)[:, None].expand(-1, K),
            (mass * layout.gravity_step).abs().amax().expand(B, K),
            (mass * caused[..., 0]).abs().amax(dim=-1),
        ]
    ).view(3, B, K)
    p_scale = torch.maximum(momenta.amax(dim=0), placed.abs().flatten(-2).amax(dim=-1))
    p_scale = p_scale.clamp(min=tiny).unsqueeze(-1)  # (B, K, 1)
    v_tol = consistency_tolerance * v_scale
    p_tol = consistency_tolerance * p_scale
    mu_pn = layout.mu * pn
    speed = slip.abs()
    stuck = (speed <= v_tol) & (tangential.abs() <= mu_pn + p_tol)
    slides = (slip * table.slip_sign + speed <= v_tol) & (mu_pn >= -p_tol)
    pressed = (
        (gap_rate.abs() <= v_tol) & (pn >= -p_tol) & torch.where(table.sticking, stuck, slides)
    )
    consistent = torch.where(table.separated, gap_rate >= -v_tol, pressed)
    return F, c, (consistent | ~candidate.unsqueeze(1)).all(dim=-1)
