"""From a scene and its state to the contact problem of one time step."""

from __future__ import annotations

import weakref
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact.contact import ContactProblem
from torchcontact.geometry import (
    HalfPlane,
    PlanarSlotTable,
    Polygon,
    SlotGeometry,
    cross2,
    planar_slot_table,
    planar_slots,
)
from torchcontact.sim._scene import Scene
from torchcontact.sim._state import SceneState


@dataclass(frozen=True, eq=False)
class SceneLayout:
    """Index tables of a scene, in one dtype and on one device, built once.

    The scene's shapes are ordered ``[dynamic bodies, kinematic bodies, static polygons,
    half-planes]``, so that their poses are ``[q, q_kinematic, static_poses]``.

    Attributes:
        slots: the slot geometry's tables of the shapes and the scene's slot groups (slot
            order: the scene's).
        static_poses: ``(Nf, 3)`` world poses of the static polygons, then zeros for the
            half-planes.
        receiver_dynamic: ``(K, Nd)`` 1 at the dynamic column of each slot's receiver, if it
            is dynamic.
        other_dynamic: ``(K, Nd)`` the same for each slot's other body.
        receiver_kinematic: ``(K, Nk)`` 1 at the kinematic index of each slot's receiver, if
            it is kinematic.
        other_kinematic: ``(K, Nk)`` the same for each slot's other body.
        mutual: some slot has a dynamic other body.
        driven_receiver: some slot's receiver is kinematic.
        driven_other: some slot's other body is kinematic.
        friction_sources: the distinct friction coefficients of the scene's pairs (numbers,
            or tensors broadcastable to the batch).
        slot_friction: ``(K,)`` long: each slot's index into ``friction_sources``.
        mu: ``(K,)`` the slots' friction coefficients, or ``None`` when a coefficient is a
            tensor that requires grad or varies over the batch (then gathered every step).
        mass_matrix: ``(n, n)`` the mass matrix, or ``None`` when a mass or inertia requires
            grad (then recomputed every step).
        gravity_force: ``(Nd, 3)`` the bodies' weights ``(m gx, m gy, 0)``, or ``None`` with
            ``mass_matrix``.
    """

    slots: PlanarSlotTable
    static_poses: Tensor
    receiver_dynamic: Tensor
    other_dynamic: Tensor
    receiver_kinematic: Tensor
    other_kinematic: Tensor
    mutual: bool
    driven_receiver: bool
    driven_other: bool
    friction_sources: tuple[float | Tensor, ...]
    slot_friction: Tensor
    mu: Tensor | None
    mass_matrix: Tensor | None
    gravity_force: Tensor | None


_LAYOUTS: weakref.WeakKeyDictionary[Scene, dict[tuple[torch.dtype, torch.device], SceneLayout]]
_LAYOUTS = weakref.WeakKeyDictionary()


def scene_layout(scene: Scene, dtype: torch.dtype, device: torch.device) -> SceneLayout:
    """The :class:`SceneLayout` of a scene in ``dtype`` on ``device`` (cached per scene).

    A scene is immutable: its bodies, shapes and friction are read once. Masses, inertias and
    friction coefficients given as tensors that require grad are not cached but read at every
    step, so that gradients reach them.
    """
    layouts = _LAYOUTS.setdefault(scene, {})
    key = (dtype, device)
    if key not in layouts:
        layouts[key] = _build_layout(scene, dtype, device)
    return layouts[key]


def _build_layout(scene: Scene, dtype: torch.dtype, device: torch.device) -> SceneLayout:
    static = [i for i, b in enumerate(scene.bodies) if b.kind == "static"]
    polygons = [i for i in static if isinstance(scene.bodies[i].shape, Polygon)]
    planes = [i for i in static if isinstance(scene.bodies[i].shape, HalfPlane)]
    order = [*scene.dynamic, *scene.kinematic, *polygons, *planes]
    shape_index = {body: s for s, body in enumerate(order)}
    table = planar_slot_table(
        [scene.bodies[i].shape for i in order],
        [(shape_index[g.receiver], shape_index[g.other]) for g in scene.slot_groups],
        margin=scene.margin,
    )
    static_poses = torch.zeros(len(polygons) + len(planes), 3, dtype=torch.float64)
    for s, body in enumerate(polygons):
        pose = scene.bodies[body].pose
        assert pose is not None
        static_poses[s] = pose.detach()

    K, Nd, Nk = scene.num_slots, len(scene.dynamic), len(scene.kinematic)
    one_hot = {
        name: torch.zeros(K, size, dtype=torch.float64)
        for name, size in (("rd", Nd), ("od", Nd), ("rk", Nk), ("ok", Nk))
    }
    sources: list[float | Tensor] = []
    slot_friction: list[int] = []
    for group in scene.slot_groups:
        span = slice(group.start, group.start + group.count)
        for member, dynamic, kinematic in ((group.receiver, "rd", "rk"), (group.other, "od", "ok")):
            if member in scene.dynamic:
                one_hot[dynamic][span, scene.dynamic.index(member)] = 1.0
            elif member in scene.kinematic:
                one_hot[kinematic][span, scene.kinematic.index(member)] = 1.0
        friction = scene.pair_mu(group.receiver, group.other)
        found = [k for k, source in enumerate(sources) if source is friction]
        if not found:
            sources.append(friction)
        slot_friction.extend([found[0] if found else len(sources) - 1] * group.count)

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
    mass_matrix = gravity_force = None
    if not any(value.requires_grad for value in parameters):
        mass_matrix = scene.mass_matrix().detach().to(dtype=dtype, device=device)
        gravity_force = _gravity_force(scene, dtype, device).detach()

    def move(value: Tensor) -> Tensor:
        return value.to(device=device, dtype=dtype if value.is_floating_point() else value.dtype)

    return SceneLayout(
        slots=table.to(dtype=dtype, device=device),
        static_poses=move(static_poses),
        receiver_dynamic=move(one_hot["rd"]),
        other_dynamic=move(one_hot["od"]),
        receiver_kinematic=move(one_hot["rk"]),
        other_kinematic=move(one_hot["ok"]),
        mutual=bool(one_hot["od"].any()),
        driven_receiver=bool(one_hot["rk"].any()),
        driven_other=bool(one_hot["ok"].any()),
        friction_sources=tuple(sources),
        slot_friction=torch.tensor(slot_friction, dtype=torch.long, device=device),
        mu=mu,
        mass_matrix=mass_matrix,
        gravity_force=gravity_force,
    )


def _gravity_force(scene: Scene, dtype: torch.dtype, device: torch.device) -> Tensor:
    """``(Nd, 3)`` the dynamic bodies' weights ``(m gx, m gy, 0)`` (keeps a tensor mass's
    graph)."""
    gravity = torch.tensor([*scene.gravity, 0.0], dtype=dtype, device=device)
    return scene.masses().to(dtype=dtype, device=device)[:, None] * gravity


def body_poses(scene: Scene, state: SceneState) -> list[Tensor | None]:
    """World pose ``(*B, 3)`` of every body (``None`` for half-planes)."""
    poses: list[Tensor | None] = []
    batch = state.batch_shape
    for i, body in enumerate(scene.bodies):
        if body.kind == "dynamic":
            poses.append(state.q[..., scene.dynamic.index(i), :])
        elif body.kind == "kinematic":
            poses.append(state.q_kinematic[..., scene.kinematic.index(i), :])
        elif isinstance(body.shape, Polygon):
            assert body.pose is not None
            poses.append(body.pose.to(state.q).expand(*batch, 3))
        else:
            poses.append(None)
    return poses


def shape_poses(layout: SceneLayout, q: Tensor, q_kinematic: Tensor) -> Tensor:
    """``(*B, Ns, 3)`` world poses of the layout's shapes, from the dynamic ``(*B, Nd, 3)``
    and kinematic ``(*B, Nk, 3)`` poses."""
    static = layout.static_poses.expand(*q.shape[:-2], -1, 3)
    return torch.cat([q, q_kinematic, static], dim=-2)


def dynamic_rows(layout: SceneLayout, poses: Tensor, points: Tensor, directions: Tensor) -> Tensor:
    """Rows mapping the dynamic bodies' twists to the slots' relative velocities along
    directions.

    A dynamic receiver contributes ``+[u, r × u]`` (``r`` from its centroid to the slot's
    point), a dynamic other body ``−[u, r × u]``, in its three columns.

    Args:
        layout: the scene's layout.
        poses: ``(*B, Ns, 3)`` world poses of the layout's shapes.
        points: ``(*B, K, 2)`` the slots' points, world frame.
        directions: ``(*B, K, F, 2)`` unit directions ``u`` per slot, world frame.

    Returns:
        ``(*B, K, F, 3 Nd)`` rows.
    """

    def rows(shape: Tensor, columns: Tensor) -> Tensor:
        arm = (points - poses.index_select(-2, shape)[..., :2]).unsqueeze(-2)  # (*B, K, 1, 2)
        wrench = torch.cat([directions, cross2(arm, directions).unsqueeze(-1)], dim=-1)
        return columns[:, None, :, None] * wrench.unsqueeze(-2)  # (*B, K, F, Nd, 3)

    blocks = rows(layout.slots.slot_receiver, layout.receiver_dynamic)
    if layout.mutual:
        blocks = blocks - rows(layout.slots.slot_other, layout.other_dynamic)
    return blocks.flatten(-2)


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
    Friction directions are ``+t`` and ``−t``. Every slot group is computed at once
    (:func:`~torchcontact.geometry.planar_slots` on the scene's cached tables). The inputs are
    not validated (:meth:`Simulator.step` validates them).

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
    q = state.q
    dtype, batch = q.dtype, state.batch_shape
    layout = scene_layout(scene, dtype, q.device)
    poses = shape_poses(layout, q, state.q_kinematic)
    geometry = planar_slots(layout.slots, poses)
    normal = geometry.normals
    frames = torch.stack([normal, normal.flip(-1) * layout.slots.turn], dim=-2)  # n, t
    rows = dynamic_rows(layout, poses, geometry.points, frames)  # (*B, K, 2, n)
    Jt_row = rows[..., 1, :]

    known = torch.zeros((), dtype=dtype, device=q.device).expand(*geometry.phi.shape, 2)
    if control is not None:
        for driven, shape, columns, sign in (
            (layout.driven_receiver, layout.slots.slot_receiver, layout.receiver_kinematic, 1),
            (layout.driven_other, layout.slots.slot_other, layout.other_kinematic, -1),
        ):
            if driven:
                twist = columns @ control  # (*B, K, 3)
                arm = geometry.points - poses.index_select(-2, shape)[..., :2]
                spun = arm.flip(-1) * layout.slots.turn
                velocity = torch.addcmul(twist[..., :2], twist[..., 2:], spun)
                known = known + sign * (frames * velocity.unsqueeze(-2)).sum(-1)

    if layout.mass_matrix is None or layout.gravity_force is None:
        M = scene.mass_matrix().to(dtype=dtype, device=q.device)
        f = _gravity_force(scene, dtype, q.device)
    else:
        M, f = layout.mass_matrix, layout.gravity_force
    f = f.expand(*batch, -1, 3) if force is None else f + force
    if friction is not None:
        mu = friction
    elif layout.mu is not None:
        mu = layout.mu
    else:
        values = [
            torch.as_tensor(source, dtype=dtype, device=q.device).expand(batch)
            for source in layout.friction_sources
        ]
        mu = torch.stack(values, dim=-1).index_select(-1, layout.slot_friction)
    problem = ContactProblem.unchecked(
        M=M,
        v=state.v.flatten(-2),
        f=f.flatten(-2),
        Jn=rows[..., 0, :],
        Jt=torch.stack([Jt_row, -Jt_row], dim=-2),
        phi=geometry.phi,
        mu=mu,
        h=scene.h,
        mask=geometry.active,
        bn=known[..., 0],
        bt=torch.stack([known[..., 1], -known[..., 1]], dim=-1),
    )
    return problem, geometry
