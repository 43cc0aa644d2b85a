"""The per-mode linearization of :class:`~torchcontact.filters.PlanarContactModel`, fast.

It computes what the model's definition asks for: central differences of the mode-fixed step
(:func:`~torchcontact.sim.contact_problem`, :func:`~torchcontact.contact.solve_mode`,
semi-implicit Euler), and :func:`~torchcontact.contact.is_consistent` at the centre with the
mode's gaps closed. The tensors are small (a few modes, a dozen slots), so the time goes into
the number of tensor operations, not their size; this module uses few:

* the slot geometry of every slot group at once from body-frame tables built once per scene
  (a half-plane is a polygon of one unbounded edge), at the seven poses of the stencil (the
  centre and ``±ε`` along ``x``, ``y``, ``θ``; the twist points share the centre's geometry);
* each mode's system holds only the slots that the mode activates and that are candidates at
  the centre: ``solve_mode``'s system is the identity on every other row (so the candidates
  are the centre's at every point of the stencil, where ``contact_problem`` at a shifted pose
  could drop or add a slot crossing the margin within ``±ε``: a spurious jump);
* ``solve_mode``'s two iterated Tikhonov passes (the second, the friction split among
  redundant sticking contacts, only for modes with sticking slots, as ``solve_mode`` on one
  mode: it leaves the step unchanged where the mode's system is solvable, and decides the
  regularised answer where it is not);
* ``is_consistent``'s tests on every slot, knowing which carry impulses;
* nothing is validated: the model checks its inputs at its public methods.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact.contact._mode_solve import (
    _FRICTION_COST,
    _MIN_LOAD_SHARE,
    _REFINEMENTS,
    _WEIGHTED_REFINEMENTS,
)
from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.geometry._slots import _TIE_TOLERANCE
from torchcontact.sim import Scene

#: Offset of padding edges (signed distance about ``-_FAR``: never the closest edge).
_FAR = 1e30
#: One-sided differences this far apart straddle a discontinuity of the geometry.
_KINK_RATIO = 10.0
#: State size: pose and twist.
_STATE = 6
#: Per-slot features of :func:`slot_rows`: ``φ``, ``Jn`` (3), ``Jt`` (3), ``bn``, ``bt``.
_FEATURES = 9


@dataclass(frozen=True, eq=False)
class SlotLayout:
    """Tables of a scene with one dynamic body (the tracked one), built once.

    Shapes are the polygons and half-planes of the scene, in the order ``[tracked body,
    kinematic bodies, static polygons, half-planes]`` (that of their poses), padded to ``V``
    edges: a polygon's padding vertices repeat its first vertex and its padding edges have zero
    normal and direction and lie far away; a half-plane is a single edge of unbounded length
    (and no direction), at the zero pose. Slot groups (``G``) pair a receiver's vertices with
    the other shape's edges.

    Attributes:
        frame: ``(Ns, 3V, 2)`` body-frame vertices, outward edge normals and edge directions
            of every shape (edge ``e`` runs from vertex ``e`` to ``e + 1``).
        static_poses: ``(Nf, 3)`` poses of the static shapes.
        receiver: ``(G,)`` shape of each group's vertices.
        other: ``(G,)`` shape of its edges.
        edge_offset: ``(G, 1, 2V)`` ``a_e · n_e`` and ``a_e · d_e`` of the other shape's edges
            in its body frame (``a_e`` the edge's first vertex).
        facing_offset: ``(G, 1, V)`` ``(a_e − c) · n_e``, ``c`` the other shape's vertex mean.
        edge_reach: ``(G, 1, V)`` the other shape's edge lengths plus the margin.
        tie_tolerance: ``(G, 1, 1)`` absolute tolerance of equally close edges.
        slot_source: ``(S,)`` each slot's index among the groups' ``G·V`` vertex slots.
        dynamic_sign: ``(S, 1)`` ``+1`` where the tracked body is the slot's receiver (owns its
            vertex), ``-1`` where it is the other body.
        kinematic: ``(S,)`` index of the slot's kinematic body (0 if it has none).
        kinematic_sign: ``(S, 1)`` ``+1`` where the kinematic body is the receiver, ``-1``
            where it is the other body, 0 where the slot has none.
        mu: ``(S,)`` friction coefficients.
        inverse_mass: ``(3,)`` diagonal of the tracked body's inverse mass matrix.
        gravity_step: ``(3,)`` the contact-free velocity change of a step, ``h M⁻¹ f``.
        turn: ``(2,)`` ``(−1, 1)``: ``u.flip(-1) * turn`` turns ``u`` by +90°.
        h: time step, seconds.
        margin: candidate margin, metres.
        stencil: ``(14, 6)`` the finite-difference points in units of ``ε``: zero, the unit
            vectors, their negatives and zero again (the consistency check's point).
        stencil_pose: ``(14,)`` index of each point's pose among those of ``stencil_poses``.
        stencil_poses: ``(7, 3)`` the distinct pose offsets in units of ``ε``.
    """

    frame: Tensor
    static_poses: Tensor
    receiver: Tensor
    other: Tensor
    edge_offset: Tensor
    facing_offset: Tensor
    edge_reach: Tensor
    tie_tolerance: Tensor
    slot_source: Tensor
    dynamic_sign: Tensor
    kinematic: Tensor
    kinematic_sign: Tensor
    mu: Tensor
    inverse_mass: Tensor
    gravity_step: Tensor
    turn: Tensor
    h: float
    margin: float
    stencil: Tensor
    stencil_pose: Tensor
    stencil_poses: Tensor


@dataclass(frozen=True, eq=False)
class ModeTable:
    """A model's per-slot modes as the linearization uses them, built once.

    Attributes:
        modes: ``(K, S)`` long per-slot modes.
        acting: ``(K, S)`` bool, the slot carries an impulse in the mode (mode ≥ 1).
        slide: ``(K, S)`` float64 ``±μ`` of slots sliding with friction along ``±t``, else 0.
    """

    modes: Tensor
    acting: Tensor
    slide: Tensor


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
    frame = torch.zeros(len(shapes), 3 * V, 2, dtype=f64)
    edge_offset = torch.full((len(shapes), 2 * V), _FAR, dtype=f64)
    facing_offset = torch.zeros(len(shapes), V, dtype=f64)
    edge_length = torch.zeros(len(shapes), V, dtype=f64)
    for s, body_index in enumerate(shapes):
        shape = scene.bodies[body_index].shape
        if isinstance(shape, HalfPlane):  # one edge, everywhere within reach
            frame[s, V] = shape.normal
            edge_offset[s, 0], edge_offset[s, V] = shape.point @ shape.normal, 0.0
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

    receiver, other = [], []
    slot_source: list[int] = []
    dynamic_sign: list[float] = []
    kinematic: list[int] = []
    kinematic_sign: list[float] = []
    mu: list[float] = []
    for g, group in enumerate(scene.slot_groups):
        receiver.append(shape_index[group.receiver])
        other.append(shape_index[group.other])
        friction = torch.as_tensor(scene.pair_mu(group.receiver, group.other)).detach()
        if friction.numel() != 1:
            raise ValueError(
                "scene: the linearization needs scalar friction coefficients, got a tensor of "
                f"shape {tuple(friction.shape)}"
            )
        partner = group.other if group.receiver == tracked else group.receiver
        moving = scene.bodies[partner].kind == "kinematic"
        for j in range(group.count):
            slot_source.append(g * V + j)
            dynamic_sign.append(1.0 if group.receiver == tracked else -1.0)
            kinematic.append(scene.kinematic.index(partner) if moving else 0)
            kinematic_sign.append(0.0 if not moving else 1.0 if group.receiver == partner else -1.0)
            mu.append(float(friction))

    body = scene.bodies[tracked]
    mass, inertia = float(body.mass_value().detach()), float(body.inertia_value().detach())
    gravity = torch.tensor([*scene.gravity, 0.0], dtype=f64)
    groups = torch.tensor(other, dtype=torch.long)
    static_poses = torch.zeros(len(static) + len(planes), 3, dtype=f64)
    for s, body_index in enumerate(static):
        pose = scene.bodies[body_index].pose
        assert pose is not None
        static_poses[s] = pose.detach()
    eye = torch.eye(_STATE, dtype=f64)
    fields = {
        "frame": frame,
        "static_poses": static_poses,
        "receiver": torch.tensor(receiver, dtype=torch.long),
        "other": groups,
        "edge_offset": edge_offset[groups].unsqueeze(-2),
        "facing_offset": facing_offset[groups].unsqueeze(-2),
        "edge_reach": edge_length[groups].unsqueeze(-2) + scene.margin,
        "tie_tolerance": _TIE_TOLERANCE  # of a half-plane: 0, it has a single edge
        * edge_length[groups].nan_to_num(posinf=0.0).amax(-1)[:, None, None],
        "slot_source": torch.tensor(slot_source, dtype=torch.long),
        "dynamic_sign": torch.tensor(dynamic_sign, dtype=f64).unsqueeze(-1),
        "kinematic": torch.tensor(kinematic, dtype=torch.long),
        "kinematic_sign": torch.tensor(kinematic_sign, dtype=f64).unsqueeze(-1),
        "mu": torch.tensor(mu, dtype=f64),
        "inverse_mass": torch.tensor([1.0 / mass, 1.0 / mass, 1.0 / inertia], dtype=f64),
        "gravity_step": scene.h * gravity,
        "turn": torch.tensor([-1.0, 1.0], dtype=f64),
        "stencil": torch.cat([eye.new_zeros(1, _STATE), eye, -eye, eye.new_zeros(1, _STATE)]),
        "stencil_pose": torch.tensor([0, 1, 2, 3, 0, 0, 0, 4, 5, 6, 0, 0, 0, 0]),
        "stencil_poses": torch.cat([eye.new_zeros(1, 3), eye[:3, :3], -eye[:3, :3]]),
    }
    return SlotLayout(
        **{name: value.to(device) for name, value in fields.items()},
        h=float(scene.h),
        margin=float(scene.margin),
    )


def mode_table(layout: SlotLayout, modes: Tensor) -> ModeTable:
    """The :class:`ModeTable` of ``(K, S)`` long per-slot modes."""
    modes = modes.to(layout.mu.device)
    sign = (modes == 2).to(torch.float64) - (modes == 3).to(torch.float64)
    return ModeTable(modes=modes, acting=modes >= 1, slide=sign * layout.mu)


def slot_geometry(layout: SlotLayout, q: Tensor, q_kinematic: Tensor) -> tuple[Tensor, Tensor]:
    """The slot geometry of :func:`~torchcontact.sim.contact_problem`, every group at once.

    For a vertex against a polygon the closest edge is the one of largest signed distance,
    ties going to the edge that faces the vertex from the polygon's vertex mean, as in
    :func:`~torchcontact.geometry.polygon_slots`.

    Args:
        layout: the scene's layout.
        q: ``(*P, 3)`` poses of the tracked body.
        q_kinematic: ``(*P, Nk, 3)`` poses of the kinematic bodies.

    Returns:
        ``(*P, S, 5)`` slot points (2), normals (2, from each slot's other body into its
        receiver) and gaps ``φ``, and the ``(*P, S)`` bool candidates.
    """
    static = layout.static_poses.expand(*q.shape[:-1], -1, 3)
    poses = torch.cat([q.unsqueeze(-2), q_kinematic, static], dim=-2)  # (*P, Ns, 3)
    cos, sin = torch.cos(poses[..., 2]), torch.sin(poses[..., 2])
    rotation = torch.stack([cos, sin, -sin, cos], dim=-1).unflatten(-1, (2, 2))  # Rᵀ
    rotated = layout.frame @ rotation  # (*P, Ns, 3V, 2)
    V = layout.facing_offset.shape[-1]
    origin = poses[..., :2].unsqueeze(-2)
    points = (rotated[..., :V, :] + origin).index_select(-3, layout.receiver)  # (*P, G, V, 2)
    edges = rotated.index_select(-3, layout.other)[..., V:, :]  # normals, directions
    relative = points - origin.index_select(-3, layout.other)
    projection = relative @ edges.mT - layout.edge_offset  # (*P, G, V, 2V)
    distance, along = projection[..., :V], projection[..., V:]
    phi = distance.amax(dim=-1, keepdim=True)
    tie = distance >= phi - layout.tie_tolerance
    closest = torch.where(tie, distance + layout.facing_offset, -_FAR).argmax(-1, keepdim=True)
    normal = edges.gather(-2, closest.expand(*closest.shape[:-1], 2))
    reach = layout.edge_reach.expand(*closest.shape[:-1], V).gather(-1, closest)
    along = along.gather(-1, closest)
    candidate = (along >= -layout.margin) & (along <= reach) & (phi <= layout.margin)
    geometry = torch.cat([points, normal, phi], dim=-1).flatten(-3, -2)
    source = layout.slot_source
    return geometry.index_select(-2, source), candidate.flatten(-3).index_select(-1, source)


def slot_rows(
    layout: SlotLayout, q: Tensor, q_kinematic: Tensor, v_kinematic: Tensor
) -> tuple[Tensor, Tensor]:
    """Every slot's rows of the contact problem (the tracked body's columns of them).

    Args:
        layout: the scene's layout.
        q: ``(*P, 3)`` poses of the tracked body.
        q_kinematic: ``(*P, Nk, 3)`` poses of the kinematic bodies.
        v_kinematic: ``(*P, Nk, 3)`` their twists.

    Returns:
        ``(*P, S, 9)``: ``φ``, the normal row ``Jn`` (3), the row ``Jt`` of friction direction
        ``+t`` (3; direction ``−t`` is its negative), and the known velocities ``bn`` and
        ``bt`` (along ``+t``); and the ``(*P, S)`` bool candidates.
    """
    geometry, candidate = slot_geometry(layout, q, q_kinematic)
    point, normal = geometry[..., :2], geometry[..., 2:4]
    tangent = normal.flip(-1) * layout.turn  # n turned by +90°
    offset = point - q[..., None, :2]
    moment = offset[..., :1] * normal[..., 1:] - offset[..., 1:] * normal[..., :1]  # r × n
    along = (offset * normal).sum(-1, keepdim=True)  # r × t = r · n
    rows = layout.dynamic_sign * torch.cat([normal, moment, tangent, along], dim=-1)
    known = torch.zeros_like(normal)
    if q_kinematic.shape[-2]:
        # Point velocities of the slots' kinematic bodies (a slot without one has sign 0).
        body = torch.cat([q_kinematic, v_kinematic], dim=-1).index_select(-2, layout.kinematic)
        turned = (point - body[..., :2]).flip(-1) * layout.turn
        velocity = body[..., 3:5] + body[..., 5:] * turned
        known = torch.stack([(velocity * normal).sum(-1), (velocity * tangent).sum(-1)], -1)
        known = layout.kinematic_sign * known
    return torch.cat([geometry[..., 4:], rows, known], dim=-1), candidate


def _tikhonov(A: Tensor, b: Tensor, weights: Tensor, refinements: int) -> Tensor:
    """``solve_mode``'s iterated Tikhonov solve of ``A x = b``.

    Iterates ``(A + ε P) x_{i+1} = b + ε P x_i`` from ``x_0 = 0`` with ``P = diag(weights)``
    and ``ε = √eps · max(1, max |diag A|)`` (the 1 of ``solve_mode``'s identity rows, those of
    the slots a mode leaves out): the solution when ``A`` is nonsingular, the one of least
    ``xᵀ P x`` when it is singular and consistent.

    Args:
        A: ``(*B, m, m)`` system matrices.
        b: ``(*B, m, 1)`` right-hand sides.
        weights: ``(*B, m, 1)`` positive regularisation weights.
        refinements: number of iterations.

    Returns:
        ``(*B, m, 1)``.
    """
    scale = A.diagonal(dim1=-2, dim2=-1).abs().amax(dim=-1)[..., None, None].clamp_min(1.0)
    shift = torch.finfo(A.dtype).eps ** 0.5 * scale * weights
    LU, pivots, _ = torch.linalg.lu_factor_ex(A + torch.diag_embed(shift.squeeze(-1)))
    x: Tensor = torch.linalg.lu_solve(LU, pivots, b)
    for _ in range(refinements - 1):
        x = torch.linalg.lu_solve(LU, pivots, b + shift * x)
    return x


def linearize_modes(
    layout: SlotLayout,
    table: ModeTable,
    x: Tensor,
    q_kinematic: Tensor,
    v_kinematic: Tensor,
    *,
    fd_step: float,
    consistency_gap: float,
    consistency_tolerance: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """Every mode's step linearized at ``x`` by central differences, and its consistency.

    Args:
        layout: the scene's layout.
        table: the ``K`` modes.
        x: ``(B, 6)`` float64 linearization points.
        q_kinematic: ``(B, Nk, 3)`` float64 kinematic poses.
        v_kinematic: ``(B, Nk, 3)`` float64 kinematic twists.
        fd_step: step ``ε`` of the differences.
        consistency_gap: gaps of a mode's slots within ``±consistency_gap`` are taken as
            closed by the check: a mean a millimetre off a contact (whose ``φ/h`` correction
            would turn its impulse around) does not count against the mode, while a contact
            held across a wider gap (a box "stuck" to a finger it has left) does.
        consistency_tolerance: relative tolerance of the check.

    Returns:
        ``F (B, K, 6, 6)``, ``c (B, K, 6)`` and ``(B, K)`` bool: the mode is consistent.
    """
    f64 = torch.float64
    B, (K, S), h, eps = x.shape[0], table.modes.shape, layout.h, fd_step
    P = len(layout.stencil_poses)
    features, candidate = slot_rows(
        layout,
        x[:, None, :3] + eps * layout.stencil_poses,
        q_kinematic.unsqueeze(1).expand(B, P, -1, 3),
        v_kinematic.unsqueeze(1).expand(B, P, -1, 3),
    )  # (B, 7, S, 9), (B, 7, S)
    centre, candidate = features[:, 0], candidate[:, 0]  # (B, S, 9), (B, S)

    # Each mode's slots: those it activates among the candidates, in slot order, then others.
    acting = candidate.unsqueeze(1) & table.acting  # (B, K, S)
    W = max(1, int(acting.sum(-1).max()))
    keep = torch.argsort(acting.to(torch.uint8), dim=-1, descending=True, stable=True)[..., :W]
    mode = torch.where(acting, table.modes, 0)  # (B, K, S)
    picked = mode.gather(-1, keep)  # (B, K, W)
    slide = table.slide.expand(B, K, S).gather(-1, keep)
    index = keep[:, :, None, :, None].expand(B, K, P, W, _FEATURES)
    rows = features.unsqueeze(1).expand(B, K, P, S, _FEATURES).gather(3, index)
    phi, Jn, Jt, bn, bt = rows[:, :, layout.stencil_pose].split([1, 3, 3, 1, 1], dim=-1)

    # solve_mode on those slots: B·K·14 problems. Constraint rows C: normals, then tangents;
    # impulse rows G: the same with μ Jt_d added to the normals of sliding slots. The rows of
    # acting normals and sticking tangents make the Schur system A = C M⁻¹ Gᵀ, x = impulses;
    # the other rows are the identity, with a zero right side.
    on = torch.cat([picked >= 1, picked == 1], dim=-1)[:, :, None, :, None]  # (B, K, 1, 2W, 1)
    on_f = on.to(f64)
    C = torch.cat([Jn, Jt], dim=-2) * on_f  # (B, K, 14, 2W, 3)
    G = torch.cat([Jn + slide[:, :, None, :, None] * Jt, Jt], dim=-2) * on_f
    U = (G * layout.inverse_mass).mT  # M⁻¹ Gᵀ
    A = C @ U + torch.diag_embed(1.0 - on_f.squeeze(-1))
    point = x.unsqueeze(1) + eps * layout.stencil  # (B, 14, 6)
    v_free = point[..., 3:] + layout.gravity_step
    # The last point closes the mode's gaps up to the dead zone (the consistency check).
    closed = phi[:, :, -1:] - phi[:, :, -1:].clamp(-consistency_gap, consistency_gap)
    phi = torch.cat([phi[:, :, :-1], closed], dim=2)
    target = torch.cat([bn + phi / h, bt], dim=-2)  # (B, K, 14, 2W, 1)
    b = -(target * on_f + C @ v_free[:, None, :, :, None])
    impulses = _tikhonov(A, b, torch.ones_like(b), _REFINEMENTS)
    weighted = (picked == 1).any(dim=-1)  # (B, K)
    if bool(weighted.any()):
        # Redundant sticking rows leave the impulse split free: solve_mode prefers normal
        # support and shares friction in proportion to the normal loads.
        load = impulses[..., :W, :].clamp(min=0.0)
        share = load.amax(dim=-2, keepdim=True).clamp_min(torch.finfo(f64).eps)
        friction = _FRICTION_COST * share / (load + _MIN_LOAD_SHARE * share)
        weights = torch.cat([torch.ones_like(load), friction], dim=-2)[weighted]
        split = _tikhonov(A[weighted], b[weighted], weights, _WEIGHTED_REFINEMENTS)
        impulses = impulses.index_put((weighted,), split)
    v_next = v_free.unsqueeze(1) + (U @ impulses).squeeze(-1)  # (B, K, 14, 3)

    # Central differences of f = (q + h v⁺, v⁺), one-sided at a kink.
    f = torch.cat([point[:, None, :, :3] + h * v_next, v_next], dim=-1)  # (B, K, 14, 6)
    f0 = f[:, :, :1]
    forward = (f[:, :, 1 : 1 + _STATE] - f0) / eps  # (B, K, j, i) = ∂f_i/∂x_j
    backward = (f0 - f[:, :, 1 + _STATE : 1 + 2 * _STATE]) / eps
    size_f = torch.linalg.vector_norm(forward, dim=-1, keepdim=True)
    size_b = torch.linalg.vector_norm(backward, dim=-1, keepdim=True)
    kink = torch.maximum(size_f, size_b) > _KINK_RATIO * (torch.minimum(size_f, size_b) + 1.0)
    one_sided = torch.where(size_f <= size_b, forward, backward)
    F = torch.where(kink, one_sided, 0.5 * (forward + backward)).mT  # (B, K, 6, 6)
    c = f0.squeeze(2) - (F @ x[:, None, :, None]).squeeze(-1)

    # is_consistent at the last point, on every slot (impulses scattered back).
    v_touch = v_next[:, :, -1]  # (B, K, 3)
    impulse = impulses[:, :, -1, :, 0]  # (B, K, 2W)
    pn = torch.zeros_like(acting, dtype=f64).scatter(-1, keep, impulse[..., :W])
    tangential = torch.zeros_like(pn).scatter(-1, keep, impulse[..., W:])
    phi_all = centre[:, None, :, 0]  # (B, 1, S)
    phi_all = torch.where(
        table.acting, phi_all - phi_all.clamp(-consistency_gap, consistency_gap), phi_all
    )  # (B, K, S): every slot of the mode closed, candidate or not
    velocity = centre[:, None, :, 1:7].unflatten(-1, (2, 3)) @ v_touch[:, :, None, :, None]
    gap_rate = velocity[..., 0, 0] + centre[:, None, :, 7] + phi_all / h  # (B, K, S)
    slip = velocity[..., 1, 0] + centre[:, None, :, 8]
    scale = torch.cat([v_free[:, -1], centre[..., 7]], dim=-1).abs().amax(-1)[:, None, None]
    scale = torch.maximum(scale, phi_all.abs().amax(-1, keepdim=True) / h)
    v_tol = consistency_tolerance * (1.0 + scale)
    p_tol = consistency_tolerance * (1.0 + pn.abs().amax(dim=-1, keepdim=True))
    mu = layout.mu
    stuck = (slip.abs() <= v_tol) & (tangential.abs() <= mu * pn + p_tol)
    slip_d = torch.where(mode == 3, -slip, slip)
    slides = (slip_d + slip.abs() <= v_tol) & (mu * pn >= -p_tol)
    pressed = (gap_rate.abs() <= v_tol) & (pn >= -p_tol) & torch.where(mode == 1, stuck, slides)
    separated = (gap_rate >= -v_tol) | ~candidate.unsqueeze(1)
    return F, c, torch.where(mode == 0, separated, pressed).all(dim=-1)
