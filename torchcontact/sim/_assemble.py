"""From a scene and its state to the contact problem of one time step."""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact.contact import ContactProblem
from torchcontact.geometry import (
    HalfPlane,
    HalfSpace,
    PlanarSlotTable,
    SlotGeometry,
    SpatialSlotTable,
    cross2,
    planar_slot_table,
    planar_slots,
    spatial_slot_table,
    spatial_slots,
)
from torchcontact.sim._rigid_body import (
    free_angular_velocity,
    spatial_mass_matrix,
    tangent_directions,
)
from torchcontact.sim._robot_member import RobotStep, robot_step
from torchcontact.sim._scene import Scene
from torchcontact.sim._state import SceneState


@dataclass(frozen=True, eq=False)
class SceneLayout:
    """Index tables of a scene, in one dtype and on one device, built once.

    The scene's shapes are ordered ``[dynamic bodies, kinematic bodies, static bodies with a
    pose, half-planes or half-spaces, robots' collision primitives]``, so that their poses are
    ``[q, q_kinematic, static_poses, RobotStep.shape_poses]``.

    Attributes:
        dimension: 2 (planar) or 3 (spatial).
        slots: the slot geometry's tables of the shapes and the scene's slot groups (slot
            order: the scene's).
        static_poses: ``(Nf, 3)`` or ``(Nf, 7)`` world poses of the static bodies, then the
            zero pose for the half-planes (half-spaces).
        receiver_column: ``(K,)`` long: the dynamic-body index of each slot's receiver, ``Nd``
            if it is not dynamic.
        other_column: ``(K,)`` long: the same for each slot's other body.
        receiver_driver: ``(K,)`` long: the kinematic-body index of each slot's receiver,
            ``Nk`` if it is not kinematic.
        other_driver: ``(K,)`` long: the same for each slot's other body.
        num_dynamic: ``Nd``.
        mutual: some slot has a dynamic other body.
        driven_receiver: some slot's receiver is kinematic.
        driven_other: some slot's other body is kinematic.
        friction_sources: the distinct friction coefficients of the scene's pairs (numbers,
            or tensors broadcastable to the batch).
        slot_friction: ``(K,)`` long: each slot's index into ``friction_sources``.
        mu: ``(K,)`` the slots' friction coefficients, or ``None`` when a coefficient is a
            tensor that requires grad or varies over the batch (then gathered every step).
        mass_matrix: ``(n, n)`` the mass matrix of a planar scene, or ``None`` when a mass or
            inertia requires grad (then recomputed every step) or the scene is spatial.
        gravity_force: ``(Nd, 3)`` or ``(Nd, 6)`` the bodies' weights ``(m g, 0)``, or
            ``None`` when a mass requires grad.
        masses: ``(Nd,)`` the dynamic bodies' masses (spatial scenes; ``None`` when one
            requires grad).
        inertias: ``(Nd, 3, 3)`` their body-frame inertias (spatial scenes; ``None`` when one
            requires grad).
        slot_robot: ``(K,)`` long: the robot (index into ``Scene.robots``) whose primitive is
            each slot's receiver, ``R`` for the bodies' slots.
        slot_link: ``(K,)`` long: that primitive's link (index into the robot's
            ``link_names``), 0 for the bodies' slots.
        servo_columns: per robot, the index of its first joint among the problem's servo
            joints (``None`` for a kinematic robot).
    """

    dimension: int
    slots: PlanarSlotTable | SpatialSlotTable
    static_poses: Tensor
    receiver_column: Tensor
    other_column: Tensor
    receiver_driver: Tensor
    other_driver: Tensor
    num_dynamic: int
    mutual: bool
    driven_receiver: bool
    driven_other: bool
    friction_sources: tuple[float | Tensor, ...]
    slot_friction: Tensor
    mu: Tensor | None
    mass_matrix: Tensor | None
    gravity_force: Tensor | None
    masses: Tensor | None
    inertias: Tensor | None
    slot_robot: Tensor
    slot_link: Tensor
    servo_columns: tuple[int | None, ...]


# By the scene's id, each entry dropped when its scene is collected (a plain dict, which
# torch.compile traces: a weak-keyed one splits the compiled graph at every lookup).
_LAYOUTS: dict[int, dict[tuple[torch.dtype, torch.device], SceneLayout]] = {}


def scene_layout(scene: Scene, dtype: torch.dtype, device: torch.device) -> SceneLayout:
    """The :class:`SceneLayout` of a scene in ``dtype`` on ``device`` (cached per scene).

    A scene is immutable: its bodies, shapes and friction are read once. Masses, inertias and
    friction coefficients given as tensors that require grad are not cached but read at every
    step, so that gradients reach them.
    """
    layouts = _LAYOUTS.get(id(scene))
    if layouts is None:
        layouts = _LAYOUTS[id(scene)] = {}
        weakref.finalize(scene, _LAYOUTS.pop, id(scene), None)
    key = (dtype, device)
    if key not in layouts:
        layouts[key] = _build_layout(scene, dtype, device)
    return layouts[key]


def _build_layout(scene: Scene, dtype: torch.dtype, device: torch.device) -> SceneLayout:
    static = [i for i, b in enumerate(scene.bodies) if b.kind == "static"]
    unbounded = (HalfPlane, HalfSpace)
    posed = [i for i in static if not isinstance(scene.bodies[i].shape, unbounded)]
    planes = [i for i in static if isinstance(scene.bodies[i].shape, unbounded)]
    order = [*scene.dynamic, *scene.kinematic, *posed, *planes]
    shape_index = {body: s for s, body in enumerate(order)}
    shapes: list[object] = [scene.bodies[i].shape for i in order]
    groups = [(shape_index[g.receiver], shape_index[g.other]) for g in scene.slot_groups]
    robot_shape_start = []
    for robot_member in scene.robots:
        robot_shape_start.append(len(shapes))
        shapes.extend(link_shape.shape for link_shape in robot_member.robot.collision_shapes)
    groups.extend(
        (robot_shape_start[g.robot] + g.shape, shape_index[g.other])
        for g in scene.robot_slot_groups
    )
    table: PlanarSlotTable | SpatialSlotTable
    if scene.dimension == 2:
        table = planar_slot_table(shapes, groups, margin=scene.margin)  # type: ignore[arg-type]
    else:
        table = spatial_slot_table(shapes, groups, margin=scene.margin)  # type: ignore[arg-type]
    static_poses = torch.zeros(len(posed) + len(planes), scene.pose_size, dtype=torch.float64)
    if scene.dimension == 3:
        static_poses[:, 3] = 1.0  # identity quaternions
    for s, body in enumerate(posed):
        pose = scene.bodies[body].pose
        assert pose is not None
        static_poses[s] = pose.detach()

    K, Nd, Nk = scene.num_slots, len(scene.dynamic), len(scene.kinematic)
    columns = {name: torch.full((K,), size, dtype=torch.long) for name, size in
               (("rd", Nd), ("od", Nd), ("rk", Nk), ("ok", Nk))}  # fmt: skip
    sources: list[float | Tensor] = []
    slot_friction: list[int] = []
    for group in scene.slot_groups:
        span = slice(group.start, group.start + group.count)
        for member, dynamic, kinematic in ((group.receiver, "rd", "rk"), (group.other, "od", "ok")):
            if member in scene.dynamic:
                columns[dynamic][span] = scene.dynamic.index(member)
            elif member in scene.kinematic:
                columns[kinematic][span] = scene.kinematic.index(member)
        friction = scene.pair_mu(group.receiver, group.other)
        found = [k for k, source in enumerate(sources) if source is friction]
        if not found:
            sources.append(friction)
        slot_friction.extend([found[0] if found else len(sources) - 1] * group.count)
    slot_robot = torch.full((K,), len(scene.robots), dtype=torch.long)
    slot_link = torch.zeros(K, dtype=torch.long)
    for rgroup in scene.robot_slot_groups:
        span = slice(rgroup.start, rgroup.start + rgroup.count)
        columns["od"][span] = scene.dynamic.index(rgroup.other)
        robot = scene.robots[rgroup.robot].robot
        slot_robot[span] = rgroup.robot
        slot_link[span] = robot.link_names.index(robot.collision_shapes[rgroup.shape].link)
        friction = scene.pair_mu(rgroup.robot, rgroup.other, robot=True)
        found = [k for k, source in enumerate(sources) if source is friction]
        if not found:
            sources.append(friction)
        slot_friction.extend([found[0] if found else len(sources) - 1] * rgroup.count)
    servo_columns: list[int | None] = []
    servo_start = 0
    for robot_member in scene.robots:
        count = len(robot_member.servo_joints)
        servo_columns.append(servo_start if count else None)
        servo_start += count

    def constant(value: float | Tensor) -> bool:
        return not isinstance(value, Tensor) or (value.numel() == 1 and not value.requires_grad)

    mu = None
    if all(constant(source) for source in sources):
        values = torch.tensor([float(source) for source in sources], dtype=torch.float64)
        mu = values[torch.tensor(slot_friction, dtype=torch.long)].to(dtype=dtype, device=device)
    parameters = [
        value
        for i in scene.dynamic
        for value in (scene.bodies[i].mass, scene.bodies[i].inertia)
        if isinstance(value, Tensor)
    ]
    mass_matrix = gravity_force = masses = inertias = None
    if not any(value.requires_grad for value in parameters):
        gravity_force = _gravity_force(scene, dtype, device).detach()
        if scene.dimension == 2:
            mass_matrix = scene.mass_matrix().detach().to(dtype=dtype, device=device)
        else:
            masses = scene.masses().detach().to(dtype=dtype, device=device)
            inertias = scene.inertias().detach().to(dtype=dtype, device=device)

    def move(value: Tensor) -> Tensor:
        return value.to(device=device, dtype=dtype if value.is_floating_point() else value.dtype)

    return SceneLayout(
        dimension=scene.dimension,
        slots=table.to(dtype=dtype, device=device),
        static_poses=move(static_poses),
        receiver_column=move(columns["rd"]),
        other_column=move(columns["od"]),
        receiver_driver=move(columns["rk"]),
        other_driver=move(columns["ok"]),
        num_dynamic=Nd,
        mutual=bool((columns["od"] < Nd).any()),
        driven_receiver=bool((columns["rk"] < Nk).any()),
        driven_other=bool((columns["ok"] < Nk).any()),
        friction_sources=tuple(sources),
        slot_friction=torch.tensor(slot_friction, dtype=torch.long, device=device),
        mu=mu,
        mass_matrix=mass_matrix,
        gravity_force=gravity_force,
        masses=masses,
        inertias=inertias,
        slot_robot=slot_robot.to(device),
        slot_link=slot_link.to(device),
        servo_columns=tuple(servo_columns),
    )


def slot_friction(scene: Scene, *, dtype: torch.dtype, device: torch.device) -> Tensor:
    """The friction coefficient of every slot, from the scene's pair frictions.

    Tensors that require grad keep their graph; constant coefficients come from the scene's
    cached layout.

    Args:
        scene: the scene.
        dtype: floating dtype of the result.
        device: its device.

    Returns:
        ``(*F, K)``, ``*F`` the broadcast batch shape of the friction tensors (``()`` when every
        coefficient is a number or a scalar tensor).
    """
    layout = scene_layout(scene, dtype, device)
    if layout.mu is not None:
        return layout.mu
    values = [
        torch.as_tensor(source, dtype=dtype, device=device) for source in layout.friction_sources
    ]
    return torch.stack(torch.broadcast_tensors(*values), dim=-1)[..., layout.slot_friction]


def _gravity_force(scene: Scene, dtype: torch.dtype, device: torch.device) -> Tensor:
    """``(Nd, 3)`` or ``(Nd, 6)`` the dynamic bodies' weights ``(m g, 0)`` (keeps a tensor
    mass's graph)."""
    assert scene.gravity is not None
    torque = [0.0] * (scene.twist_size - scene.dimension)
    gravity = torch.tensor([*scene.gravity, *torque], dtype=dtype, device=device)
    return scene.masses().to(dtype=dtype, device=device)[:, None] * gravity


def body_poses(scene: Scene, state: SceneState) -> list[Tensor | None]:
    """World pose ``(*B, 3)`` (planar) or ``(*B, 7)`` (spatial) of every body (``None`` for
    half-planes and half-spaces)."""
    poses: list[Tensor | None] = []
    batch = state.batch_shape
    for i, body in enumerate(scene.bodies):
        if body.kind == "dynamic":
            poses.append(state.q[..., scene.dynamic.index(i), :])
        elif body.kind == "kinematic":
            poses.append(state.q_kinematic[..., scene.kinematic.index(i), :])
        elif body.pose is not None:
            poses.append(body.pose.to(state.q).expand(*batch, scene.pose_size))
        else:
            poses.append(None)
    return poses


def shape_poses(
    layout: SceneLayout, q: Tensor, q_kinematic: Tensor, robots: RobotStep | None = None
) -> Tensor:
    """``(*B, Ns, 3)`` or ``(*B, Ns, 7)`` world poses of the layout's shapes, from the
    dynamic ``(*B, Nd, ·)`` and kinematic ``(*B, Nk, ·)`` poses (and the robots'
    primitives)."""
    static = layout.static_poses.expand(*q.shape[:-2], -1, q.shape[-1])
    parts = [q, q_kinematic, static]
    if robots is not None:
        parts.append(robots.shape_poses)
    return torch.cat(parts, dim=-2)


def _pick(table: Tensor, index: Tensor) -> Tensor:
    """``(P, W, C)``: the rows ``index (P, W)`` of ``table (P, R, C)``."""
    return table.gather(1, index.unsqueeze(-1).expand(*index.shape, table.shape[-1]))


def moment_rows(arm: Tensor, directions: Tensor) -> Tensor:
    """``[u, r × u]``: the wrench of a unit force ``u`` at offset ``r`` from a centroid, which is
    also the row mapping the body's twist to its point velocity along ``u``.

    Args:
        arm: ``(..., d)`` offsets ``r``, world frame (broadcast against ``directions``).
        directions: ``(..., d)`` directions ``u``, world frame.

    Returns:
        ``(..., 3)`` rows ``(ux, uy, r × u)`` (``d = 2``) or ``(..., 6)`` rows
        ``(u, r × u)`` (``d = 3``).
    """
    if directions.shape[-1] == 2:
        return torch.cat([directions, cross2(arm, directions).unsqueeze(-1)], dim=-1)
    moment = torch.linalg.cross(arm.expand_as(directions), directions)
    return torch.cat([directions, moment], dim=-1)


def point_velocities(twist: Tensor, arm: Tensor) -> Tensor:
    """``v + ω × r``: velocities of points at offsets ``arm`` from centroids moving with
    ``twist`` (``(..., 3)`` planar ``(vx, vy, ω)`` with ``(..., 2)`` offsets, or ``(..., 6)``
    spatial ``(v, ω)`` with ``(..., 3)`` offsets), world frame."""
    if arm.shape[-1] == 2:
        spun = torch.stack([-arm[..., 1], arm[..., 0]], dim=-1)
        return torch.addcmul(twist[..., :2], twist[..., 2:], spun)
    velocity: Tensor = twist[..., :3] + torch.linalg.cross(twist[..., 3:], arm)
    return velocity


def dynamic_rows(
    layout: SceneLayout,
    poses: Tensor,
    points: Tensor,
    directions: Tensor,
    slots: Tensor,
    robots: RobotStep | None = None,
) -> Tensor:
    """Rows mapping the dynamic bodies' twists (and the servo robots' joint velocities) to
    slots' relative velocities along directions.

    A dynamic receiver contributes ``+[u, r × u]`` (``r`` from its centroid to the slot's
    point, :func:`moment_rows`), a dynamic other body ``−[u, r × u]``, in its columns. A servo
    robot's primitive (always a receiver) contributes ``+[u, r × u] · J_link`` in its joints'
    columns, ``r`` from the link frame's origin and ``J_link`` that origin's world-frame
    Jacobian: the rows of :meth:`~torchcontact.robots.Robot.contact_jacobian`.

    Args:
        layout: the scene's layout.
        poses: ``(P, Ns, 3)`` or ``(P, Ns, 7)`` world poses of the layout's shapes.
        points: ``(P, W, d)`` the slots' points, world frame.
        directions: ``(P, W, F, d)`` unit directions ``u`` per slot, world frame.
        slots: ``(P, W)`` long: the slots' indices among the scene's ``K``.
        robots: the robots' :class:`~torchcontact.sim.RobotStep` (scenes with robots).

    Returns:
        ``(P, W, F, n)`` rows, ``n = 3 Nd`` (planar) or ``6 Nd`` plus the servo joints
        (spatial).
    """
    d = points.shape[-1]
    members = [(layout.slots.slot_receiver, layout.receiver_column, 1)]
    if layout.mutual:
        members.append((layout.slots.slot_other, layout.other_column, -1))
    wrenches, columns = [], []
    for shape, column, sign in members:
        arm = (points - _pick(poses, shape[slots])[..., :d]).unsqueeze(-2)  # (P, W, 1, d)
        wrench = moment_rows(arm, directions)
        wrenches.append(wrench if sign > 0 else -wrench)
        columns.append(column[slots][..., None, None])  # (P, W, 1, 1)
    # One block of columns per dynamic body: the wrenches of the slots' members that are
    # that body.
    blocks = []
    for body in range(layout.num_dynamic):
        block = torch.where(columns[0] == body, wrenches[0], 0.0)
        for wrench, column in zip(wrenches[1:], columns[1:], strict=True):
            block = block + torch.where(column == body, wrench, 0.0)
        blocks.append(block)
    if robots is not None:
        blocks.extend(_robot_rows(layout, robots, points, directions, slots))
    return blocks[0] if len(blocks) == 1 else torch.cat(blocks, dim=-1)


def _robot_rows(
    layout: SceneLayout, robots: RobotStep, points: Tensor, directions: Tensor, slots: Tensor
) -> list[Tensor]:
    """The servo robots' column blocks ``(P, W, F, dof)`` of :func:`dynamic_rows`."""
    blocks = []
    owner, link = layout.slot_robot[slots], layout.slot_link[slots]  # (P, W)
    for r, start in enumerate(layout.servo_columns):
        if start is None:
            continue
        jacobian = robots.jacobians[r]  # (P, L, 6, dof)
        P, W = slots.shape
        dof = jacobian.shape[-1]
        index = link.clamp(max=jacobian.shape[1] - 1)
        picked = jacobian.gather(1, index[..., None, None].expand(P, W, 6, dof))
        origin = _pick(robots.origins[r], index)  # (P, W, 3)
        wrench = moment_rows((points - origin).unsqueeze(-2), directions)  # (P, W, F, 6)
        rows = wrench @ picked
        blocks.append(torch.where((owner == r)[..., None, None], rows, 0.0))
    return blocks


def known_velocities(
    layout: SceneLayout,
    poses: Tensor,
    points: Tensor,
    frames: Tensor,
    control: Tensor | None,
    robots: RobotStep | None = None,
) -> Tensor:
    """``(P, K, F)`` the kinematic bodies' contribution to every slot's relative velocity along
    its directions: ``±u · (v + ω × r)`` of a kinematic receiver (``+``) or other body (``−``).

    Args:
        layout: the scene's layout.
        poses: ``(P, Ns, 3)`` or ``(P, Ns, 7)`` world poses of the layout's shapes.
        points: ``(P, K, d)`` every slot's point, world frame.
        frames: ``(P, K, F, d)`` unit directions per slot, world frame.
        control: ``(P, Nk, 3)`` or ``(P, Nk, 6)`` twists of the kinematic bodies, or ``None``
            (at rest).
        robots: the robots' :class:`~torchcontact.sim.RobotStep`: a robot primitive (a
            receiver) adds ``u · (v + ω × r)`` of its link's known twist.
    """
    known = frames.new_zeros(frames.shape[:-1])
    if robots is not None:
        for r, twists in enumerate(robots.known_twists):
            index = layout.slot_link.clamp(max=twists.shape[1] - 1).expand(points.shape[0], -1)
            twist = _pick(twists, index)  # (P, K, 6)
            arm = points - _pick(robots.origins[r], index)
            velocity = point_velocities(twist, arm)
            along = (frames * velocity.unsqueeze(-2)).sum(-1)
            known = known + torch.where((layout.slot_robot == r)[:, None], along, 0.0)
    if control is None:
        return known
    d = points.shape[-1]
    # Twists of the slots' members, zero where a member is not kinematic.
    twists = torch.cat([control, control.new_zeros(control.shape[0], 1, control.shape[-1])], -2)
    slots = layout.slots
    for driven, shape, driver, sign in (
        (layout.driven_receiver, slots.slot_receiver, layout.receiver_driver, 1.0),
        (layout.driven_other, slots.slot_other, layout.other_driver, -1.0),
    ):
        if driven:
            twist = twists.index_select(-2, driver)  # (P, K, ·)
            arm = points - poses.index_select(-2, shape)[..., :d]
            velocity = point_velocities(twist, arm)
            known = known + sign * (frames * velocity.unsqueeze(-2)).sum(-1)
    return known


@dataclass(frozen=True, eq=False)
class SlotState:
    """The slots of a flat batch of scene states, before any problem is assembled.

    Attributes:
        layout: the scene's layout.
        poses: ``(P, Ns, 3)`` or ``(P, Ns, 7)`` world poses of the layout's shapes.
        geometry: the ``K`` slots' geometry, batch ``(P,)``.
        frames: ``(P, K, 1 + D/2, d)`` each slot's normal ``n`` and the first half of its
            friction directions (the other half are their opposites), world frame: planar,
            the tangent ``t`` (``n`` turned by +90°); spatial,
            :func:`~torchcontact.sim.tangent_directions`.
        known: ``(P, K, 1 + D/2)`` the known velocity terms ``bn`` and the first half of
            ``bt``.
        robots: the robots' :class:`~torchcontact.sim.RobotStep`, ``None`` without robots.
    """

    layout: SceneLayout
    poses: Tensor
    geometry: SlotGeometry
    frames: Tensor
    known: Tensor
    robots: RobotStep | None = None


def slot_state(
    scene: Scene,
    q: Tensor,
    q_kinematic: Tensor,
    control: Tensor | None,
    robots: RobotStep | None = None,
) -> SlotState:
    """The :class:`SlotState` of a flat batch: dynamic poses ``q (P, Nd, ·)``, kinematic poses
    ``q_kinematic (P, Nk, ·)`` and twists ``control (P, Nk, ·)`` (or ``None``), and the
    robots (:func:`~torchcontact.sim.robot_step`, scenes with robots)."""
    layout = scene_layout(scene, q.dtype, q.device)
    poses = shape_poses(layout, q, q_kinematic, robots)
    if isinstance(layout.slots, PlanarSlotTable):
        geometry = planar_slots(layout.slots, poses)
        normal = geometry.normals
        frames = torch.stack([normal, normal.flip(-1) * layout.slots.turn], dim=-2)
    else:
        geometry = spatial_slots(layout.slots, poses)
        half = scene.friction_directions // 2
        directions = tangent_directions(geometry.normals, scene.friction_directions)
        frames = torch.cat([geometry.normals.unsqueeze(-2), directions[..., :half, :]], dim=-2)
    known = known_velocities(layout, poses, geometry.points, frames, control, robots)
    return SlotState(layout, poses, geometry, frames, known, robots)


def assemble(
    scene: Scene,
    slots: SlotState,
    v: Tensor,
    keep: Tensor,
    *,
    force: Tensor | None,
    friction: Tensor | None,
) -> ContactProblem:
    """The contact problem of a flat batch on the slots ``keep``.

    A spatial scene's mass matrix is the world-frame one at the poses
    (:func:`~torchcontact.sim.spatial_mass_matrix`), and its non-contact force includes the
    implicit gyroscopic step (:func:`~torchcontact.sim.free_angular_velocity`) as the torque
    ``I_w (ω_free − ω) / h``, so that the problem's ``v_free`` is that step's.

    Args:
        scene: the scene.
        slots: the batch's :class:`SlotState`, batch ``(P,)``.
        v: ``(P, Nd, 3)`` or ``(P, Nd, 6)`` twists of the dynamic bodies.
        keep: ``(P, W)`` long: the slots of each entry's problem, among the ``K``.
        force: ``(P, Nd, 3)`` or ``(P, Nd, 6)`` applied generalized forces, or ``None``.
        friction: ``(P, K)`` per-slot friction overriding the scene's, or ``None``.

    Returns:
        The problem, batch ``(P,)``, ``W`` slots.
    """
    layout, geometry = slots.layout, slots.geometry
    P, dtype, device = v.shape[0], v.dtype, v.device

    K, W = slots.geometry.phi.shape[-1], keep.shape[-1]
    rows_of = (keep + K * torch.arange(P, device=device)[:, None]).flatten()

    def gather(t: Tensor) -> Tensor:  # (P, K, ...) -> (P, W, ...)
        return t.reshape(P * K, *t.shape[2:]).index_select(0, rows_of).view(P, W, *t.shape[2:])

    frames = gather(slots.frames)
    rows = dynamic_rows(layout, slots.poses, gather(geometry.points), frames, keep, slots.robots)
    Jt_half = rows[..., 1:, :]
    known = gather(slots.known)
    twist = v.shape[-1]
    f = layout.gravity_force
    if f is None:
        f = _gravity_force(scene, dtype, device)
    f = f.expand(P, -1, twist) if force is None else f + force
    M_inverse = None
    if layout.dimension == 2:
        M = layout.mass_matrix
        if M is None:
            M = scene.mass_matrix().to(dtype=dtype, device=device)
    else:
        M, gyroscopic, M_inverse = _spatial_inertia(scene, layout, slots.poses, v)
        f = f + gyroscopic
    v_flat, f_flat = v.flatten(-2), f.flatten(-2)
    if slots.robots is not None and slots.robots.velocity.shape[-1]:
        robots = slots.robots
        M, M_inverse = _block_diagonal(M.expand(P, -1, -1), robots.mass), None
        v_flat = torch.cat([v_flat, robots.velocity], dim=-1)
        f_flat = torch.cat([f_flat, robots.force], dim=-1)
    if friction is not None:
        mu = gather(friction)
    elif layout.mu is not None:
        mu = layout.mu[keep]
    else:
        mu = slot_friction(scene, dtype=dtype, device=device).expand(P, -1).gather(1, keep)
    phi = gather(geometry.phi)
    assert scene.recovery_speed is not None
    if math.isfinite(scene.recovery_speed):
        phi = phi.clamp(min=-scene.h * scene.recovery_speed)
    problem = ContactProblem.unchecked(
        M=M,
        v=v_flat,
        f=f_flat,
        Jn=rows[..., 0, :],
        Jt=torch.cat([Jt_half, -Jt_half], dim=-2),
        phi=phi,
        mu=mu,
        h=scene.h,
        mask=gather(geometry.active),
        bn=known[..., 0],
        bt=torch.cat([known[..., 1:], -known[..., 1:]], dim=-1),
    )
    if M_inverse is not None:
        # Kept for the problem's mass solves (where it keeps anything: no field requires grad).
        problem.cached("mass_inverse", lambda: M_inverse)
    return problem


def _block_diagonal(top: Tensor, bottom: Tensor) -> Tensor:
    """``(P, a + b, a + b)`` from the blocks ``(P, a, a)`` and ``(P, b, b)``."""
    a, b = top.shape[-1], bottom.shape[-1]
    return torch.cat(
        [
            torch.cat([top, top.new_zeros(*top.shape[:-1], b)], dim=-1),
            torch.cat([bottom.new_zeros(*bottom.shape[:-1], a), bottom], dim=-1),
        ],
        dim=-2,
    )


def _spatial_inertia(
    scene: Scene, layout: SceneLayout, poses: Tensor, v: Tensor
) -> tuple[Tensor, Tensor, Tensor | None]:
    """The mass matrix ``(P, 6 Nd, 6 Nd)`` of a spatial batch at its poses, the gyroscopic
    torques ``(P, Nd, 6)`` ``(0, I_w (ω_free − ω) / h)`` of the implicit free step, and the
    inverse mass matrix ``diag(1/m, R I⁻¹ Rᵀ)`` (``(R I Rᵀ)⁻¹ = R I⁻¹ Rᵀ``), or ``None``
    where a mass or an inertia requires grad."""
    masses, inertias = layout.masses, layout.inertias
    if masses is None or inertias is None:
        masses = scene.masses().to(dtype=v.dtype, device=v.device)
        inertias = scene.inertias().to(dtype=v.dtype, device=v.device)
    quaternion = poses[:, : layout.num_dynamic, 3:]
    M = spatial_mass_matrix(masses, inertias, quaternion)
    omega = v[..., 3:]
    omega_free = free_angular_velocity(inertias, quaternion, omega, scene.h)
    # M (0, ω_free − ω) / h: the angular blocks of M are the world inertias (its linear rows
    # meet only the zeros).
    change = torch.cat([torch.zeros_like(omega), omega_free - omega], dim=-1).flatten(-2)
    wrench = (M @ change.unsqueeze(-1)).squeeze(-1) / scene.h
    inverse = None
    if layout.masses is not None and layout.inertias is not None:
        inverse = spatial_mass_matrix(
            layout.masses.reciprocal(), torch.linalg.inv(layout.inertias), quaternion
        )
    return M, wrench.unflatten(-1, (layout.num_dynamic, 6)), inverse


def robot_inputs(
    scene: Scene, state: SceneState, joint_command: Tensor | None, base_twist: Tensor | None
) -> RobotStep | None:
    """The :class:`~torchcontact.sim.RobotStep` of a state's flattened batch ``(P,)``
    (``None`` when the scene has no robots); commands already flat ``(P, ·)``."""
    if not scene.robots:
        return None
    assert state.q_robot is not None
    assert state.v_robot is not None
    assert state.robot_base is not None
    assert scene.gravity is not None
    P = math.prod(state.batch_shape)
    return robot_step(
        scene.robots,
        q_robot=state.q_robot.reshape(P, -1),
        v_robot=state.v_robot.reshape(P, -1),
        robot_base=state.robot_base.reshape(P, len(scene.robots), 7),
        joint_command=joint_command,
        base_twist=base_twist,
        gravity=scene.gravity,
        h=scene.h,
    )


def contact_problem(
    scene: Scene,
    state: SceneState,
    *,
    control: Tensor | None = None,
    force: Tensor | None = None,
    friction: Tensor | None = None,
    joint_command: Tensor | None = None,
    base_twist: Tensor | None = None,
) -> tuple[ContactProblem, SlotGeometry]:
    """Assemble the Stewart–Trinkle step of a batch of scenes.

    For a slot at world point ``p`` with normal ``n`` (from ``other`` into ``receiver``), the
    gap rate is ``n · (v_p,receiver − v_p,other)``: a dynamic body contributes the row
    ``±[n, r × n]`` (``r`` from its centroid to ``p``) to ``Jn``, a kinematic body its known
    point velocity to ``bn``, a static body nothing; friction directions the same way. Planar
    scenes have the directions ``+t`` and ``−t`` (``t = n`` rotated by +90°), spatial scenes
    the scene's ``friction_directions`` (:func:`~torchcontact.sim.tangent_directions`). Every
    slot group is computed at once (:func:`~torchcontact.geometry.planar_slots` or
    :func:`~torchcontact.geometry.spatial_slots` on the scene's cached tables). The inputs
    are not validated (:meth:`Simulator.step` validates them).

    Args:
        scene: the scene.
        state: the batched state ``*B``.
        control: ``(*B, Nk, 3)`` (planar) or ``(*B, Nk, 6)`` (spatial) twists of the
            kinematic bodies (world frame), or ``None`` when the scene has none (or they
            rest).
        force: ``(*B, Nd, 3)`` or ``(*B, Nd, 6)`` applied generalized forces
            (``(fx, fy, τ)``, or force and torque) on the dynamic bodies, besides gravity.
        friction: ``(*B, K)`` per-slot friction overriding the scene's pair friction.
        joint_command: ``(*B, Nj)`` the robots' joint commands (servo targets, kinematic
            joint velocities; :meth:`Simulator.step`), or ``None``.
        base_twist: ``(*B, R, 6)`` the robots' base twists, or ``None``.

    Returns:
        The contact problem (``n = 3 Nd`` and ``D = 2``, or ``n = 6 Nd`` plus the servo
        robots' joints and the scene's ``D``; ``K`` slots) and the slot geometry (points,
        normals from each slot's ``other`` body into its receiver, gaps, candidates).
    """
    batch, K = state.batch_shape, scene.num_slots
    P, Nd, Nk = math.prod(batch), len(scene.dynamic), len(scene.kinematic)
    pose, twist, d = scene.pose_size, scene.twist_size, scene.dimension

    def flat(t: Tensor | None) -> Tensor | None:
        return None if t is None else t.reshape(P, *t.shape[len(batch) :])

    q, q_kinematic = state.q.reshape(P, Nd, pose), state.q_kinematic.reshape(P, Nk, pose)
    robots = robot_inputs(scene, state, flat(joint_command), flat(base_twist))
    slots = slot_state(scene, q, q_kinematic, flat(control), robots)
    keep = torch.arange(K, device=q.device).expand(P, K)
    problem = assemble(
        scene,
        slots,
        state.v.reshape(P, Nd, twist),
        keep,
        force=flat(force),
        friction=flat(friction),
    )
    geometry = slots.geometry
    return problem.reshape(*batch), SlotGeometry(
        points=geometry.points.reshape(*batch, K, d),
        normals=geometry.normals.reshape(*batch, K, d),
        phi=geometry.phi.reshape(*batch, K),
        active=geometry.active.reshape(*batch, K),
    )
