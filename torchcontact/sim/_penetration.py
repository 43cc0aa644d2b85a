"""The penetrating contact slots of many states, without assembling the rest of the problem."""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact._checks import check_batched, check_float
from torchcontact.geometry import PlanarSlotTable, Polygon, planar_slots
from torchcontact.sim._assemble import SceneLayout, dynamic_rows, scene_layout, shape_poses
from torchcontact.sim._scene import Scene


@dataclass(frozen=True, eq=False)
class _Part:
    """Some of a scene's slot groups, as a table of their own.

    Attributes:
        table: the groups' :meth:`~torchcontact.geometry.PlanarSlotTable.subtable`.
        shapes: ``(Ns',)`` long: its shapes' indices among the layout's.
        slots: ``(S',)`` long: its slots' indices among the scene's ``K``.
    """

    table: PlanarSlotTable
    shapes: Tensor
    slots: Tensor


@dataclass(frozen=True, eq=False)
class _Culling:
    """A scene's slot groups split for :func:`penetration` (cached per scene, dtype, device).

    Attributes:
        layout: the scene's layout.
        unbounded: the groups whose other shape is a half-plane (computed for every state), or
            ``None``.
        boxed: the groups whose other shape is a polygon (computed for the states that pass
            the bounding-box test), or ``None``.
        vertices: ``(Nb, V, 2)`` and ``vertices_turned``: ``boxed``'s body-frame vertex rows
            (padded by repeating the first vertex) and the same turned by +90°.
        receivers: ``(Gb,)`` long: the shape of each of ``boxed``'s groups' receivers among
            its shapes; ``others`` the same for the other shapes.
        radius: the largest distance of a vertex of ``boxed``'s shapes from its centroid.
    """

    layout: SceneLayout
    unbounded: _Part | None
    boxed: _Part | None
    vertices: Tensor
    vertices_turned: Tensor
    receivers: Tensor
    others: Tensor
    radius: float


_CULLINGS: weakref.WeakKeyDictionary[Scene, dict[tuple[torch.dtype, torch.device], _Culling]]
_CULLINGS = weakref.WeakKeyDictionary()


def _culling(scene: Scene, dtype: torch.dtype, device: torch.device) -> _Culling:
    """The scene's cached :class:`_Culling` in ``dtype`` on ``device``."""
    cullings = _CULLINGS.setdefault(scene, {})
    key = (dtype, device)
    if key not in cullings:
        layout = scene_layout(scene, dtype, device)
        if not isinstance(layout.slots, PlanarSlotTable):
            raise ValueError("scene: penetration queries are for planar scenes")
        split: dict[bool, list[int]] = {False: [], True: []}
        for g, group in enumerate(scene.slot_groups):
            split[isinstance(scene.bodies[group.other].shape, Polygon)].append(g)
        parts = [
            _Part(*layout.slots.subtable(groups)) if groups else None
            for groups in (split[False], split[True])
        ]
        boxed = parts[1]
        vertices = vertices_turned = layout.slots.frame[:0]
        receivers = others = layout.slots.group_shapes[:0]
        radius = 0.0
        if boxed is not None:
            table = boxed.table
            E, G = table.facing_offset.shape[-1], table.facing_offset.shape[0]
            V = table.frame.shape[-2] - E - 1
            vertices, vertices_turned = table.frame[:, :V], table.frame_turned[:, :V]
            receivers, others = table.group_shapes[:G], table.group_shapes[G:]
            radius = float(vertices.norm(dim=-1).max())
        cullings[key] = _Culling(
            layout, parts[0], boxed, vertices, vertices_turned, receivers, others, radius
        )
    return cullings[key]


def _near(culling: _Culling, poses: Tensor) -> Tensor:
    """``(P,)`` bool: some receiver vertex of some polygon–polygon group lies in the other
    polygon's bounding box, widened by ``√ε`` of the coordinates' scale (``ε`` the dtype's
    machine epsilon).

    The batch runs last (``(·, P)`` rows, contiguous), so that every operation is one long
    elementwise loop.
    """
    boxed = culling.boxed
    assert boxed is not None
    pose = poses.permute(1, 2, 0).contiguous().index_select(0, boxed.shapes)  # (Nb, 3, P)
    x, y, angle = pose[:, 0:1], pose[:, 1:2], pose[:, 2:3]
    cos, sin = torch.cos(angle), torch.sin(angle)  # (Nb, 1, P)
    vertices, turned = culling.vertices[..., None], culling.vertices_turned[..., None]
    world_x = torch.addcmul(torch.addcmul(x, vertices[:, :, 0], cos), turned[:, :, 0], sin)
    world_y = torch.addcmul(torch.addcmul(y, vertices[:, :, 1], cos), turned[:, :, 1], sin)
    scale = torch.maximum(x.abs(), y.abs()).amax(0) + culling.radius  # (1, P)
    widening = math.sqrt(torch.finfo(pose.dtype).eps) * scale
    near = torch.zeros_like(scale, dtype=torch.bool)
    for world in (world_x, world_y):  # (Nb, V, P)
        low = (world.amin(1, keepdim=True) - widening).index_select(0, culling.others)
        high = (world.amax(1, keepdim=True) + widening).index_select(0, culling.others)
        vertex = world.index_select(0, culling.receivers)  # (Gb, V, P)
        inside = (vertex >= low) & (vertex <= high)
        near = inside if world is world_x else near & inside
    return near.flatten(0, 1).any(0)


def penetration(scene: Scene, *, q: Tensor, q_kinematic: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Which contact slots of a batch of states penetrate, with their gaps and normal rows.

    A slot penetrates when it is a candidate (:class:`~torchcontact.geometry.SlotGeometry`'s
    ``active``) with a negative gap. Where it does, its gap and its row of ``Jn`` are those of
    :func:`~torchcontact.sim.contact_problem` at the state (the same functions on the same
    numbers), less everything the problem also holds (velocities, tangents, known terms,
    friction): the cheap query of a filter that projects many particles out of the bodies
    (thousands of poses per step), where most particles touch nothing but the ground.

    So the slots of a vertex against a half-plane are computed for every state, those of a
    polygon against another polygon (all such groups at once) only for the states where some
    vertex of some such group's receiver lies inside its other polygon's axis-aligned bounding
    box, widened by ``√ε`` (``ε`` the dtype's machine epsilon) times the coordinates' scale
    (the largest ``|x|``, ``|y|`` of those bodies' positions plus their largest vertex
    radius). The culling is exact: a vertex outside a convex polygon's box is outside the
    polygon, at a positive signed distance from one of its edges' lines (at least its
    distance from the box times the sine of half the polygon's sharpest angle), and the
    widening exceeds the rounding of the vertex transforms and of the gaps (tens of ``ε`` of
    that scale) for any polygon whose angles are not sharper than about ``60 √ε`` rad (1e-6 rad
    in float64, 1.2° in float32), so no culled slot has a negative gap. The slots that are
    computed come from sub-tables of the scene's slot table (its rows: the same numbers), the
    normal rows only where a slot penetrates; one host synchronization sizes the states that
    pass the box test, one per sub-table its penetrating slots.

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
    P, K = math.prod(batch), scene.num_slots
    culling = _culling(scene, q.dtype, q.device)
    layout = culling.layout
    poses = shape_poses(
        layout, q.reshape(P, num_dynamic, 3), q_kinematic.reshape(P, num_kinematic, 3)
    )
    flat_phi = q.new_zeros(P * K)
    flat_penetrating = torch.zeros(P * K, dtype=torch.bool, device=q.device)
    flat_Jn = q.new_zeros(P * K, 3 * num_dynamic)
    parts: list[tuple[_Part, Tensor | None]] = []
    if culling.unbounded is not None:
        parts.append((culling.unbounded, None))  # every state
    if culling.boxed is not None and P > 0:
        parts.append((culling.boxed, _near(culling, poses).nonzero().squeeze(-1)))
    for part, rows in parts:
        picked = poses if rows is None else poses.index_select(0, rows)
        if picked.shape[0] == 0:
            continue
        geometry = planar_slots(part.table, picked.index_select(-2, part.shapes))
        state, column = (geometry.active & (geometry.phi < 0)).nonzero().unbind(-1)
        slot = part.slots[column]
        index = K * (state if rows is None else rows[state]) + slot
        flat_phi[index] = geometry.phi[state, column]
        flat_penetrating[index] = True
        flat_Jn[index] = dynamic_rows(
            layout,
            picked[state],
            geometry.points[state, column][:, None],
            geometry.normals[state, column][:, None, None],
            slot[:, None],
        )[:, 0, 0]
    return (
        flat_phi.reshape(*batch, K),
        flat_Jn.reshape(*batch, K, 3 * num_dynamic),
        flat_penetrating.reshape(*batch, K),
    )
