"""Contact slots between spatial shapes: a fixed number of candidate contacts per pair of shapes.

A *slot group* pairs a receiving shape with another shape; it yields a fixed number of slots
(by the pair's types, :data:`SPATIAL_SLOT_COUNTS`), so that every scene batches without ragged
tensors, and each slot's ``active`` flag says whether it is a contact candidate this step. The
conventions are the planar engine's (:class:`SlotGeometry`): a slot's point lies on the
receiving shape, its unit normal points from the other shape into the receiving one, and its
gap ``φ`` is signed (``≥ 0`` separated), so that the other shape's witness point is
``points − φ · normals`` (:func:`slot_witness_points`).

Contacts per pair (either order; receiver first below):

- box–half-space (8 slots): the box's corners against the plane;
- sphere–half-space (1) and capsule–half-space (2, the end spheres of the capsule);
- sphere–box (1): the closest point of the centre to the box (inside: the nearest face);
- capsule–box (3): the point of the axis segment closest to the box (the minimum of the box's
  signed distance along the segment, convex, found exactly among the 49 parameters where a
  piece of it is stationary or has a kink), and the two ends of the part of the segment over the
  face that the closest point's normal names (so a capsule lying on a face has two contacts); a
  slot the others make redundant is not active. Each slot is the contact of a ball of the
  capsule's radius on its axis with the box, exact while the axis stays outside the box; when it
  enters, the depth is that of the deepest axis point (less than the capsule's penetration);
- sphere–sphere (1), sphere–capsule (1: the ball on the capsule's axis point closest to the
  centre) and capsule–capsule (3: the closest points of the axes, and the two ends of the part
  of the first axis alongside the second, each as a ball on the first axis against the second
  capsule, so that parallel capsules touch along a line; redundant slots are not active);
- box–box (8): the separating-axis test over the 15 axes (the 6 face normals, the 9 edge
  cross products), choosing B's face normals, then A's, then edge axes, the first whose overlap
  is within :data:`FACE_PREFERENCE` of the least (so that boxes resting on each other keep a
  face manifold); on a face axis, the incident face of the other box (the face most
  anti-parallel to the reference face) is clipped to the reference face: the clipped
  polygon's vertices (at most 8: incident corners over the reference face, reference corners
  under the incident face, crossings of their edges) are the slots, at their depth below the
  reference face; on an edge axis, one slot at the closest points of the two edges
  [Ericson 2005, §4.4 and §5.1.9]. The depth is exact for penetrating boxes up to that
  preference (at most ``FACE_PREFERENCE`` times deeper than the least penetration). For
  separated boxes the face manifold's gaps are never less than the boxes' distance; where none
  reaches it (two edges or corners approaching askew), or on an edge axis, and the boxes are
  separated by no more than ``margin``, the slots are one slot at the exact closest points
  instead (the nearest of the 16 corners against the other box and the 144 edge pairs), so the
  least gap is the distance. Beyond the margin no slot is a candidate and the gaps are only
  bounds (at least the separation along the chosen axis).

Ericson, C. *Real-Time Collision Detection*. Morgan Kaufmann, 2005.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any, TypeVar

import torch
from torch import Tensor

from torchcontact._checks import check_float, check_unit_rows
from torchcontact.geometry._quaternion import quat_to_matrix
from torchcontact.geometry._se2 import cross2
from torchcontact.geometry._slots import TIE_TOLERANCE, SlotGeometry
from torchcontact.geometry._spatial_shapes import (
    Box,
    Capsule,
    HalfSpace,
    SpatialShape,
    Sphere,
    corner_signs,
)

#: Slots per pair of shape types, receiving shape first (either order gives the same count).
SPATIAL_SLOT_COUNTS: dict[tuple[str, str], int] = {
    ("Box", "HalfSpace"): 8,
    ("Sphere", "HalfSpace"): 1,
    ("Capsule", "HalfSpace"): 2,
    ("Sphere", "Box"): 1,
    ("Capsule", "Box"): 3,
    ("Box", "Box"): 8,
    ("Sphere", "Sphere"): 1,
    ("Sphere", "Capsule"): 1,
    ("Capsule", "Capsule"): 3,
}

#: Relative margin by which a box-box separating axis must beat a preferred one: B's face
#: normals are preferred to A's and face normals to edge cross products, so that resting and
#: nearly aligned boxes keep a face manifold (several points) rather than flicker to a single
#: edge point; the reported depth then exceeds the least penetration by at most this fraction.
FACE_PREFERENCE = 0.05

_Item = TypeVar("_Item", "SpatialSlotTable", "_Block")
_Kernel = Callable[[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, float], tuple[Tensor, ...]]


@dataclass(frozen=True, eq=False)
class _Block:
    """The groups of one pair type, in the kernel's order (its receiver first).

    Attributes:
        kind: the pair's type names, e.g. ``("Capsule", "Box")``.
        first: ``(G,)`` long shape indices of the kernel's receiver.
        second: ``(G,)`` long shape indices of the kernel's other shape.
        first_params: ``(G, P)`` the first shapes' parameters (see :func:`_params`).
        second_params: ``(G, Q)`` the second shapes' parameters.
        flipped: the groups' receivers are the kernel's other shapes.
    """

    kind: tuple[str, str]
    first: Tensor
    second: Tensor
    first_params: Tensor
    second_params: Tensor
    flipped: bool


@dataclass(frozen=True, eq=False)
class SpatialSlotTable:
    """``Ns`` spatial shapes and ``G`` slot groups between them, grouped by pair type.

    Attributes:
        blocks: the groups of each pair type present (internal layout).
        slot_order: ``(S,)`` long: for each slot in group order, its index among the blocks'
            slots laid end to end (``None`` when the two orders agree).
        slot_group: ``(S,)`` long: each slot's group index.
        slot_receiver: ``(S,)`` long: shape index of each slot's receiver.
        slot_other: ``(S,)`` long: shape index of each slot's other shape.
        num_shapes: ``Ns``.
        margin: candidate margin, metres.
    """

    blocks: tuple[_Block, ...]
    slot_order: Tensor | None
    slot_group: Tensor
    slot_receiver: Tensor
    slot_other: Tensor
    num_shapes: int
    margin: float

    @property
    def num_slots(self) -> int:
        """``S``, the number of slots."""
        return self.slot_group.shape[0]

    def to(
        self, *, dtype: torch.dtype, device: torch.device | str | None = None
    ) -> SpatialSlotTable:
        """The table with its float tensors in ``dtype`` and every tensor on ``device``."""

        def convert(item: _Item) -> _Item:
            changed: dict[str, Any] = {}
            for entry in fields(item):
                value = getattr(item, entry.name)
                if isinstance(value, Tensor):
                    target = dtype if value.is_floating_point() else value.dtype
                    changed[entry.name] = value.to(device=device, dtype=target)
            return replace(item, **changed)

        converted = convert(self)
        return replace(converted, blocks=tuple(convert(block) for block in self.blocks))


def _params(shape: SpatialShape) -> list[float]:
    """A shape's parameters: a box's half extents, a sphere's ``(r,)``, a capsule's
    ``(r, l)``, a half-space's point and normal (body frame)."""
    if isinstance(shape, Box):
        return shape.half_extents.tolist()
    if isinstance(shape, Sphere):
        return [shape.radius]
    if isinstance(shape, Capsule):
        return [shape.radius, shape.half_length]
    return [*shape.point.tolist(), *shape.normal.tolist()]


def spatial_slot_table(
    shapes: Sequence[SpatialShape],
    groups: Sequence[tuple[int, int]],
    *,
    margin: float,
) -> SpatialSlotTable:
    """The float64 CPU :class:`SpatialSlotTable` of shapes and slot groups.

    Args:
        shapes: the ``Ns`` shapes (:class:`Box`, :class:`Sphere`, :class:`Capsule`,
            :class:`HalfSpace`).
        groups: ``G`` pairs ``(receiver, other)`` of indices into ``shapes`` whose types
            form a pair of :data:`SPATIAL_SLOT_COUNTS` (in either order). A group's slots
            follow the previous group's, in the order the module docstring lists them.
        margin: gap below which a slot becomes a candidate, metres, ``>= 0``.

    Raises:
        ValueError: naming ``shapes``, ``groups`` or ``margin`` when it breaks these rules.
    """
    kinds = (Box, Sphere, Capsule, HalfSpace)
    if not shapes or not all(isinstance(s, kinds) for s in shapes):
        raise ValueError("shapes must be a non-empty sequence of Box, Sphere, Capsule, HalfSpace")
    names = [type(s).__name__ for s in shapes]
    members: dict[tuple[tuple[str, str], bool], list[tuple[int, int, int]]] = {}
    counts: list[int] = []
    for g, pair in enumerate(groups):
        valid = (
            isinstance(pair, tuple)
            and len(pair) == 2
            and all(isinstance(i, int) and 0 <= i < len(shapes) for i in pair)
            and pair[0] != pair[1]
        )
        if not valid:
            raise ValueError(
                f"groups must be pairs (receiver, other) of distinct shape indices in "
                f"[0, {len(shapes)}), got {pair!r}"
            )
        receiver, other = pair
        kind = (names[receiver], names[other])
        flipped = kind not in SPATIAL_SLOT_COUNTS
        if flipped:
            kind = kind[::-1]
        if kind not in SPATIAL_SLOT_COUNTS:
            raise ValueError(
                f"groups: no contact between a {names[receiver]} and a {names[other]} "
                f"(group {g}: {pair!r}); supported pairs: {sorted(SPATIAL_SLOT_COUNTS)}"
            )
        first, second = (other, receiver) if flipped else (receiver, other)
        members.setdefault((kind, flipped), []).append((g, first, second))
        counts.append(SPATIAL_SLOT_COUNTS[kind])
    if not isinstance(margin, (int, float)) or not margin >= 0 or margin == float("inf"):
        raise ValueError(f"margin must be a finite real >= 0, got {margin!r}")

    long, f64 = torch.long, torch.float64
    starts = [0, *itertools.accumulate(counts)]
    blocks: list[_Block] = []
    order: list[int] = []  # the group-order slot index of each block slot
    for (kind, flipped), entries in members.items():
        count = SPATIAL_SLOT_COUNTS[kind]
        blocks.append(
            _Block(
                kind=kind,
                first=torch.tensor([e[1] for e in entries], dtype=long),
                second=torch.tensor([e[2] for e in entries], dtype=long),
                first_params=torch.tensor([_params(shapes[e[1]]) for e in entries], dtype=f64),
                second_params=torch.tensor([_params(shapes[e[2]]) for e in entries], dtype=f64),
                flipped=flipped,
            )
        )
        order.extend(starts[e[0]] + k for e in entries for k in range(count))
    slot_order: Tensor | None = None
    if order != sorted(order):
        slot_order = torch.empty(len(order), dtype=long)
        slot_order[torch.tensor(order, dtype=long)] = torch.arange(len(order), dtype=long)
    slot_group = torch.repeat_interleave(
        torch.arange(len(groups)), torch.tensor(counts, dtype=long)
    )
    receivers = torch.tensor([pair[0] for pair in groups], dtype=long)
    others = torch.tensor([pair[1] for pair in groups], dtype=long)
    return SpatialSlotTable(
        blocks=tuple(blocks),
        slot_order=slot_order,
        slot_group=slot_group,
        slot_receiver=receivers[slot_group],
        slot_other=others[slot_group],
        num_shapes=len(shapes),
        margin=float(margin),
    )


def spatial_slots(table: SpatialSlotTable, poses: Tensor) -> SlotGeometry:
    """Every slot of every group of a table, from the shapes' poses.

    One pass of tensor operations per pair type present (no loop over groups or batch
    entries). Differentiable in the poses, the discrete choices (separating axis, reference
    and incident faces, clipped vertices, the closest parameter's candidate) held fixed.

    Args:
        table: the shapes and groups (its float tensors are cast to ``poses``' dtype and
            device here).
        poses: ``(*B, Ns, 7)`` float32/float64 world poses of the table's shapes, position
            then unit quaternion ``(w, x, y, z)`` (a half-space's point and normal are in its
            body frame: at the identity pose, the world frame).

    Returns:
        The :class:`SlotGeometry` of the ``S`` slots: ``points`` ``(*B, S, 3)`` on the
        receivers, ``normals`` ``(*B, S, 3)`` from the other shapes into the receivers,
        ``phi`` ``(*B, S)``, ``active`` ``(*B, S)``, world frame.

    Raises:
        ValueError: ``poses`` is not a finite float tensor of shape ``(*B, Ns, 7)`` with unit
            quaternions.
    """
    poses = check_float(
        "poses",
        poses,
        trailing=(table.num_shapes, 7),
        min_ndim=2,
        what=f"(*B, {table.num_shapes}, 7)",
    )
    check_unit_rows("poses[..., 3:] (quaternions)", poses[..., 3:].detach())
    table = table.to(dtype=poses.dtype, device=poses.device)
    position, rotation = poses[..., :3], quat_to_matrix(poses[..., 3:])
    points_parts, normal_parts, phi_parts, valid_parts = [], [], [], []
    for block in table.blocks:
        points, normals, phi, valid = _KERNELS[block.kind](
            position.index_select(-2, block.first),
            rotation.index_select(-3, block.first),
            block.first_params,
            position.index_select(-2, block.second),
            rotation.index_select(-3, block.second),
            block.second_params,
            table.margin,
        )
        if block.flipped:  # the receiver is the kernel's other shape: its witness, reversed
            points, normals = points - phi.unsqueeze(-1) * normals, -normals
        points_parts.append(points.flatten(-3, -2))
        normal_parts.append(normals.flatten(-3, -2))
        phi_parts.append(phi.flatten(-2))
        valid_parts.append(valid.flatten(-2))
    points, normals = _in_order(points_parts, -2, table), _in_order(normal_parts, -2, table)
    phi, valid = _in_order(phi_parts, -1, table), _in_order(valid_parts, -1, table)
    return SlotGeometry(
        points=points, normals=normals, phi=phi, active=valid & (phi <= table.margin)
    )


def _in_order(parts: list[Tensor], dim: int, table: SpatialSlotTable) -> Tensor:
    """The blocks' slot values laid end to end along ``dim``, in group order."""
    joined = parts[0] if len(parts) == 1 else torch.cat(parts, dim)
    return joined if table.slot_order is None else joined.index_select(dim, table.slot_order)


def slot_witness_points(slots: SlotGeometry) -> tuple[Tensor, Tensor]:
    """The two shapes' witness points of each slot: ``points`` on the receiver and
    ``points − φ · normals`` on the other shape.

    Args:
        slots: ``(*B, S, d)`` points and normals, ``(*B, S)`` gaps.

    Returns:
        ``(*B, S, d)`` points on the receivers and on the other shapes, world frame.
    """
    return slots.points, slots.points - slots.phi.unsqueeze(-1) * slots.normals


# --- kernels: (*B, G, ·) poses of the first and second shapes, (G, ·) parameters ------------
# Each returns points (*B, G, K, 3) on the first shape, normals (*B, G, K, 3) from the second
# into the first, gaps φ (*B, G, K) and validity (*B, G, K).


def _tolerance(dtype: torch.dtype, scale: Tensor) -> Tensor:
    """Absolute tie tolerance for lengths of size ``scale``: ``TIE_TOLERANCE`` relative in
    float64, 64 ulps in float32 (where ``TIE_TOLERANCE`` is below rounding)."""
    return max(TIE_TOLERANCE, 64 * torch.finfo(dtype).eps) * scale


def _sign(x: Tensor) -> Tensor:
    """``±1`` by the sign of ``x`` (``+1`` at zero)."""
    return torch.where(x < 0, -1.0, 1.0).to(x.dtype)


def _safe_divide(numerator: Tensor, denominator: Tensor, fallback: float) -> Tensor:
    """``numerator / denominator``, ``fallback`` where the denominator is zero (finite
    gradients on both branches)."""
    zero = denominator.abs() <= torch.finfo(denominator.dtype).tiny
    safe = torch.where(zero, torch.ones_like(denominator), denominator)
    return torch.where(zero, fallback, numerator / safe)


def _to_world(rotation: Tensor, position: Tensor, local: Tensor) -> Tensor:
    """``(*B, G, K, 3)`` world points ``R p + t`` of body points ``local`` ``(..., K, 3)``."""
    return _rotate(rotation, local) + position.unsqueeze(-2)


def _rotate(rotation: Tensor, vectors: Tensor) -> Tensor:
    """``R v`` for vectors ``(..., K, 3)`` and rotations ``(..., 3, 3)``, elementwise (CPU
    batched GEMM runs one small kernel per matrix)."""
    columns = rotation.unsqueeze(-3)
    turned = torch.addcmul(vectors[..., :1] * columns[..., 0], vectors[..., 1:2], columns[..., 1])
    return torch.addcmul(turned, vectors[..., 2:], columns[..., 2])


def _unrotate(rotation: Tensor, vectors: Tensor) -> Tensor:
    """``Rᵀ v`` for vectors ``(..., K, 3)`` and rotations ``(..., 3, 3)``, elementwise."""
    columns = rotation.unsqueeze(-3)
    return torch.stack([_dot3(vectors, columns[..., j]) for j in range(3)], -1)


def _dot3(a: Tensor, b: Tensor) -> Tensor:
    """Dot products over a last dimension of 3, component by component (on the CPU, several
    times faster than a reduction over so short a dimension)."""
    return torch.addcmul(
        torch.addcmul(a[..., 0] * b[..., 0], a[..., 1], b[..., 1]), a[..., 2], b[..., 2]
    )


def _norm3(a: Tensor) -> Tensor:
    """Euclidean norms over a last dimension of 3 (gradient 0 at 0, as ``vector_norm``'s)."""
    square = _dot3(a, a)
    positive = square > 0
    return torch.where(positive, torch.sqrt(torch.where(positive, square, 1.0)), 0.0)


def _points_vs_plane(
    centres: Tensor, radius: Tensor, normal: Tensor, point: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Balls of centres ``(*B, G, K, 3)`` and radius ``(G, 1)`` against planes through
    ``point`` with normal ``normal`` (``(*B, G, 3)``, world)."""
    normal = normal.unsqueeze(-2).expand_as(centres)
    distance = _dot3(centres - point.unsqueeze(-2), normal) - radius
    points = centres - radius.unsqueeze(-1) * normal
    return points, normal, distance, torch.ones_like(distance, dtype=torch.bool)


def _half_space_world(rotation: Tensor, position: Tensor, params: Tensor) -> tuple[Tensor, Tensor]:
    """World ``(normal, point)`` ``(*B, G, 3)`` of half-spaces with body parameters ``(G, 6)``."""
    normal = _rotate(rotation, params[:, None, 3:]).squeeze(-2)
    point = _rotate(rotation, params[:, None, :3]).squeeze(-2) + position
    return normal, point


def _box_corners(half: Tensor) -> Tensor:
    """``(G, 8, 3)`` body corners of boxes of half extents ``(G, 3)``, x fastest."""
    return corner_signs(half.dtype, half.device) * half.unsqueeze(-2)


def _box_half_space(
    position: Tensor,
    rotation: Tensor,
    half: Tensor,
    plane_position: Tensor,
    plane_rotation: Tensor,
    plane: Tensor,
    margin: float,
) -> tuple[Tensor, ...]:
    """Box corners (8) against a half-space."""
    del margin  # every slot is computed
    corners = _to_world(rotation, position, _box_corners(half))
    normal, point = _half_space_world(plane_rotation, plane_position, plane)
    return _points_vs_plane(corners, torch.zeros_like(half[:, :1]), normal, point)


def _sphere_half_space(
    position: Tensor,
    rotation: Tensor,
    sphere: Tensor,
    plane_position: Tensor,
    plane_rotation: Tensor,
    plane: Tensor,
    margin: float,
) -> tuple[Tensor, ...]:
    """A sphere (1) against a half-space."""
    del margin  # every slot is computed
    del rotation
    normal, point = _half_space_world(plane_rotation, plane_position, plane)
    return _points_vs_plane(position.unsqueeze(-2), sphere[:, :1], normal, point)


def _capsule_ends(position: Tensor, rotation: Tensor, capsule: Tensor) -> Tensor:
    """``(*B, G, 2, 3)`` world end points ``t ∓ l · axis`` of capsule axes."""
    axis = rotation[..., :, 2] * capsule[:, 1:2]
    return torch.stack([position - axis, position + axis], dim=-2)


def _capsule_half_space(
    position: Tensor,
    rotation: Tensor,
    capsule: Tensor,
    plane_position: Tensor,
    plane_rotation: Tensor,
    plane: Tensor,
    margin: float,
) -> tuple[Tensor, ...]:
    """A capsule's end balls (2) against a half-space."""
    del margin  # every slot is computed
    normal, point = _half_space_world(plane_rotation, plane_position, plane)
    return _points_vs_plane(
        _capsule_ends(position, rotation, capsule), capsule[:, :1], normal, point
    )


def _box_distance(local: Tensor, half: Tensor) -> Tensor:
    """Signed distance ``(..., K)`` of box-frame points ``(..., K, 3)`` to boxes ``(G, 1, 3)``."""
    excess = local.abs() - half
    outside = _norm3(excess.clamp(min=0.0))
    return outside + excess.amax(-1).clamp(max=0.0)


def _balls_vs_box(local: Tensor, radius: Tensor, half: Tensor) -> tuple[Tensor, Tensor]:
    """Balls of box-frame centres ``local`` ``(*B, G, K, 3)`` and radius ``(G, 1)`` against
    boxes of half extents ``(G, 3)``: box-frame normals (from the box into the ball) and gaps.

    Outside, the normal is along the centre minus its closest box point; inside, it is the
    nearest face's outward normal and the gap is minus that face's depth, minus the radius.
    """
    half = half.unsqueeze(-2)
    closest = torch.maximum(torch.minimum(local, half), -half)
    offset = local - closest
    square = _dot3(offset, offset).unsqueeze(-1)
    outside = (local.abs() > half).any(-1, keepdim=True)
    distance = torch.sqrt(torch.where(outside, square, torch.ones_like(square)))
    depth = half - local.abs()
    face = depth.argmin(-1, keepdim=True)
    inward = torch.zeros_like(local).scatter(-1, face, _sign(local.gather(-1, face)))
    normal = torch.where(outside, offset / distance, inward)
    gap = torch.where(outside, distance, -depth.gather(-1, face)).squeeze(-1) - radius
    return normal, gap


def _balls(
    centre: Tensor, radius: Tensor, other_centre: Tensor, other_radius: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Two balls (centres ``(..., 3)``, radii broadcasting to ``(..., 1)``): the point on the
    first, the unit normal from the second into the first (``+z`` for coincident centres) and
    the gap ``(...)``."""
    offset = centre - other_centre
    distance = _norm3(offset).unsqueeze(-1)
    apart = distance > 0
    up = torch.zeros_like(offset)
    up[..., 2] = 1.0
    normal = torch.where(apart, offset / torch.where(apart, distance, 1.0), up)
    gap = (distance - radius - other_radius).squeeze(-1)
    return centre - radius * normal, normal, gap


def _on_segment(point: Tensor, centre: Tensor, axis: Tensor, half: Tensor) -> Tensor:
    """The closest points ``(..., 3)`` to ``point`` of segments ``centre + s axis``,
    ``|s| <= half`` (unit ``axis``; ``half`` ``(..., 1)``)."""
    along = _dot3(point - centre, axis).unsqueeze(-1)
    return centre + torch.minimum(torch.maximum(along, -half), half) * axis


def _sphere_sphere(
    position: Tensor,
    rotation: Tensor,
    sphere: Tensor,
    other_position: Tensor,
    other_rotation: Tensor,
    other_sphere: Tensor,
    margin: float,
) -> tuple[Tensor, ...]:
    """A sphere (1) against a sphere."""
    del rotation, other_rotation, margin
    points, normal, gap = _balls(position, sphere[:, :1], other_position, other_sphere[:, :1])
    gap = gap.unsqueeze(-1)
    return points.unsqueeze(-2), normal.unsqueeze(-2), gap, torch.ones_like(gap, dtype=torch.bool)


def _sphere_capsule(
    position: Tensor,
    rotation: Tensor,
    sphere: Tensor,
    capsule_position: Tensor,
    capsule_rotation: Tensor,
    capsule: Tensor,
    margin: float,
) -> tuple[Tensor, ...]:
    """A sphere (1) against a capsule: the ball on the axis point closest to the centre."""
    del rotation, margin
    nearest = _on_segment(position, capsule_position, capsule_rotation[..., 2], capsule[:, 1:2])
    points, normal, gap = _balls(position, sphere[:, :1], nearest, capsule[:, :1])
    gap = gap.unsqueeze(-1)
    return points.unsqueeze(-2), normal.unsqueeze(-2), gap, torch.ones_like(gap, dtype=torch.bool)


def _capsule_capsule(
    position: Tensor,
    rotation: Tensor,
    capsule: Tensor,
    other_position: Tensor,
    other_rotation: Tensor,
    other_capsule: Tensor,
    margin: float,
) -> tuple[Tensor, ...]:
    """A capsule (3: the closest points of the axes, and the ends of the part of the first
    axis alongside the second, so that parallel capsules touch along a line) against a
    capsule. Each slot is a ball on the first axis against the second capsule."""
    del margin
    radius, half = capsule[:, :1], capsule[:, 1:2]
    other_radius, other_half = other_capsule[:, :1], other_capsule[:, 1:2]
    axis, other_axis = rotation[..., 2], other_rotation[..., 2]
    closest, _ = _closest_on_segments(
        (position, axis, half), (other_position, other_axis, other_half)
    )
    # The other axis's ends projected on the first axis, clipped to it.
    ends = other_position.unsqueeze(-2) + torch.stack([-other_half, other_half], -2) * (
        other_axis.unsqueeze(-2)
    )  # (*B, G, 2, 3)
    along = _dot3(ends - position.unsqueeze(-2), axis.unsqueeze(-2))  # (*B, G, 2)
    low = along.amin(-1, keepdim=True).clamp(min=-half)
    high = along.amax(-1, keepdim=True).clamp(max=half)
    over = low <= high
    side = torch.stack([low, high], -2) * axis.unsqueeze(-2) + position.unsqueeze(-2)
    centres = torch.cat([closest.unsqueeze(-2), side], -2)  # (*B, G, 3, 3)
    nearest = _on_segment(
        centres, other_position.unsqueeze(-2), other_axis.unsqueeze(-2), other_half.unsqueeze(-2)
    )
    points, normals, gaps = _balls(
        centres, radius.unsqueeze(-2), nearest, other_radius.unsqueeze(-2)
    )
    scale = torch.maximum(radius + half, other_radius + other_half)
    tolerance = _tolerance(gaps.dtype, scale)
    end_covers = over & (gaps[..., 1:].amin(-1, keepdim=True) <= gaps[..., :1] + tolerance)
    distinct = (high - low) > tolerance
    valid = torch.cat([~end_covers, over, over & distinct], -1)
    return points, normals, gaps, valid


def _sphere_box(
    position: Tensor,
    rotation: Tensor,
    sphere: Tensor,
    box_position: Tensor,
    box_rotation: Tensor,
    half: Tensor,
    margin: float,
) -> tuple[Tensor, ...]:
    """A sphere (1) against a box."""
    del margin  # every slot is computed
    del rotation
    local = _unrotate(box_rotation, (position - box_position).unsqueeze(-2))  # (*B, G, 1, 3)
    radius = sphere[:, :1]
    normal_local, gap = _balls_vs_box(local, radius, half)
    normal = _rotate(box_rotation, normal_local)
    points = position.unsqueeze(-2) - radius.unsqueeze(-1) * normal
    return points, normal, gap, torch.ones_like(gap, dtype=torch.bool)


def _stationary_parameters(start: Tensor, direction: Tensor, half: Tensor) -> Tensor:
    """``(*B, G, 49)`` segment parameters in ``[0, 1]`` among which the box's signed distance
    along ``p(t) = start + t · direction`` (box frame, ``(*B, G, 3)``) takes its minimum.

    The signed distance is convex along the segment; it is the root of a piecewise quadratic
    outside the box (pieces split where a coordinate crosses ``±h``) and the largest of six
    linear functions ``s p_i(t) − h_i`` inside it. Its minimum lies at an end (2), where a
    coordinate crosses a face plane (6), at the stationary point of an outside piece (26 sign
    patterns of the coordinates beyond the box) or where two inside pieces meet (15 pairs).
    """
    h = half.expand_as(start)
    ends = torch.stack([torch.zeros_like(start[..., 0]), torch.ones_like(start[..., 0])], -1)
    crossings = torch.cat(
        [_safe_divide(h - start, direction, 0.0), _safe_divide(-h - start, direction, 0.0)], -1
    )
    patterns = torch.tensor(
        [p for p in itertools.product((-1.0, 0.0, 1.0), repeat=3) if any(p)],
        dtype=start.dtype,
        device=start.device,
    )  # (26, 3)
    used = patterns.abs()
    beyond = direction.unsqueeze(-2) * (start.unsqueeze(-2) - patterns * h.unsqueeze(-2))
    stationary = _safe_divide(
        -(used * beyond).sum(-1), (used * direction.unsqueeze(-2) ** 2).sum(-1), 0.0
    )
    pieces = [(i, s) for i in range(3) for s in (1.0, -1.0)]
    pairs = list(itertools.combinations(range(6), 2))
    first = torch.tensor([pieces[a][0] for a, _ in pairs], device=start.device)
    second = torch.tensor([pieces[b][0] for _, b in pairs], device=start.device)
    first_sign = torch.tensor(
        [pieces[a][1] for a, _ in pairs], dtype=start.dtype, device=start.device
    )
    second_sign = torch.tensor(
        [pieces[b][1] for _, b in pairs], dtype=start.dtype, device=start.device
    )
    meets = _safe_divide(
        h.index_select(-1, first)
        - h.index_select(-1, second)
        - first_sign * start.index_select(-1, first)
        + second_sign * start.index_select(-1, second),
        first_sign * direction.index_select(-1, first)
        - second_sign * direction.index_select(-1, second),
        0.0,
    )
    return torch.cat([ends, crossings, stationary, meets], -1).clamp(0.0, 1.0)


def _capsule_box(
    position: Tensor,
    rotation: Tensor,
    capsule: Tensor,
    box_position: Tensor,
    box_rotation: Tensor,
    half: Tensor,
    margin: float,
) -> tuple[Tensor, ...]:
    """A capsule (3: the closest axis point, the ends of the axis over the face) against a
    box."""
    del margin  # every slot is computed
    radius, length = capsule[:, :1], capsule[:, 1:2]
    centre = _unrotate(box_rotation, (position - box_position).unsqueeze(-2)).squeeze(-2)
    axis = _unrotate(box_rotation, rotation[..., None, :, 2]).squeeze(-2)
    start, direction = centre - length * axis, 2 * length * axis  # box frame, (*B, G, 3)
    candidates = _stationary_parameters(start, direction, half)
    along = start.unsqueeze(-2) + candidates.unsqueeze(-1) * direction.unsqueeze(-2)
    best = _box_distance(along, half.unsqueeze(-2)).argmin(-1, keepdim=True)
    closest = candidates.gather(-1, best)  # (*B, G, 1)
    normal_local, _ = _balls_vs_box(
        start.unsqueeze(-2) + closest.unsqueeze(-1) * direction.unsqueeze(-2), radius, half
    )
    # The part of the segment over the face the closest normal names: |p_j(t)| <= h_j for the
    # two other axes j.
    face = normal_local.squeeze(-2).abs().argmax(-1, keepdim=True)
    h = half.expand_as(start)
    low = _safe_divide(-h - start, direction, -torch.inf)
    high = _safe_divide(h - start, direction, torch.inf)
    parallel = direction.abs() <= torch.finfo(direction.dtype).tiny
    inside = start.abs() <= h
    low, high = torch.minimum(low, high), torch.maximum(low, high)
    low = torch.where(parallel, torch.where(inside, -torch.inf, torch.inf), low)
    high = torch.where(parallel, torch.where(inside, torch.inf, -torch.inf), high)
    is_face = torch.zeros_like(start, dtype=torch.bool).scatter(-1, face, True)
    low = torch.where(is_face, -torch.inf, low).amax(-1, keepdim=True).clamp(min=0.0)
    high = torch.where(is_face, torch.inf, high).amin(-1, keepdim=True).clamp(max=1.0)
    over = low <= high
    ends = torch.cat([torch.where(over, low, closest), torch.where(over, high, closest)], -1)
    parameters = torch.cat([closest, ends], -1)  # (*B, G, 3)
    local = start.unsqueeze(-2) + parameters.unsqueeze(-1) * direction.unsqueeze(-2)
    normal_local, gap = _balls_vs_box(local, radius, half)
    normal = _rotate(box_rotation, normal_local)
    centres = _to_world(box_rotation, box_position, local)
    points = centres - radius.unsqueeze(-1) * normal
    # Redundant slots: the closest point where an end is as deep (the gap is convex along the
    # segment), the second end where the part over the face is a point.
    scale = torch.maximum(half.amax(-1, keepdim=True), radius + length)
    tolerance = _tolerance(gap.dtype, scale)
    end_covers = over & (gap[..., 1:].amin(-1, keepdim=True) <= gap[..., :1] + tolerance)
    distinct = (high - low) * 2 * length > tolerance
    valid = torch.cat([~end_covers, over, over & distinct], -1)
    return points, normal, gap, valid


def _column(rotation: Tensor, index: Tensor) -> Tensor:
    """``(*B, G, 3)`` the columns ``index`` ``(*B, G)`` of rotations ``(*B, G, 3, 3)``."""
    return rotation.gather(-1, index[..., None, None].expand(*index.shape, 3, 1)).squeeze(-1)


def _pick(values: Tensor, index: Tensor) -> Tensor:
    """``(*B, G)`` entries ``index`` ``(*B, G)`` of ``values`` ``(*B, G, 3)``."""
    return values.gather(-1, index.unsqueeze(-1)).squeeze(-1)


def _box_box(
    position: Tensor,
    rotation: Tensor,
    half: Tensor,
    other_position: Tensor,
    other_rotation: Tensor,
    other_half: Tensor,
    margin: float,
) -> tuple[Tensor, ...]:
    """A box (8: the clipped face, or one edge point) against a box."""
    dtype = position.dtype
    half_a = half.expand(*position.shape[:-1], 3)
    half_b = other_half.expand(*position.shape[:-1], 3)
    tolerance = _tolerance(dtype, torch.maximum(half.amax(-1), other_half.amax(-1)))  # (G,)
    tol = tolerance.unsqueeze(-1)
    offset = position - other_position  # from B to A
    axes_a, axes_b = rotation.mT, other_rotation.mT  # rows: the boxes' axes
    edges = torch.linalg.cross(axes_a.unsqueeze(-2), axes_b.unsqueeze(-3)).flatten(-3, -2)
    axes = torch.cat([axes_a, axes_b, edges], -2)  # (*B, G, 15, 3)
    length = _norm3(axes)
    usable = length > torch.finfo(dtype).eps ** 0.5
    unit = axes / torch.where(usable, length, torch.ones_like(length)).unsqueeze(-1)
    reach = _dot3(_unrotate(rotation, unit).abs(), half_a.unsqueeze(-2)) + _dot3(
        _unrotate(other_rotation, unit).abs(), half_b.unsqueeze(-2)
    )
    overlap = reach - _dot3(unit, offset.unsqueeze(-2)).abs()
    overlap = torch.where(usable, overlap, torch.inf)
    # Prefer B's faces (A's corners become the slots), then A's, then edges: the first
    # whose overlap is within FACE_PREFERENCE of the least.
    a_depth, a_axis = overlap[..., :3].min(-1)
    b_depth, b_axis = overlap[..., 3:6].min(-1)
    edge_depth, edge_axis = overlap[..., 6:].min(-1)
    least = torch.minimum(torch.minimum(a_depth, b_depth), edge_depth)
    accepted = least + FACE_PREFERENCE * least.abs() + tolerance
    ref_is_a = b_depth > accepted
    is_edge = ref_is_a & (a_depth > accepted)

    face = _face_contact(
        ref_is_a,
        torch.where(ref_is_a, a_axis, b_axis),
        (position, rotation, half_a),
        (other_position, other_rotation, half_b),
        tolerance,
    )
    edge = _edge_contact(
        edge_axis, unit, (position, rotation, half_a), (other_position, other_rotation, half_b)
    )
    chosen = [
        torch.where(is_edge.view(*is_edge.shape, *([1] * (f.dim() - is_edge.dim()))), e, f)
        for f, e in zip(face, edge, strict=True)
    ]
    points, normals, gaps, valid = chosen
    # Separated boxes within the margin (beyond it no slot is a candidate, the distance being
    # at least the separation): the exact closest pair, one slot, on an edge axis or where the
    # face manifold does not reach it (its gaps are never less than the distance). Only those
    # pairs are computed (a host synchronization), or, inside a region that torch.compile
    # traces, every pair, kept where near (fixed shapes, no synchronization).
    near = (least < -tolerance) & (least >= -margin)
    traced = torch.compiler.is_compiling()
    if not traced and not bool(near.any()):
        return points, normals, gaps, valid
    shape = gaps.shape
    if traced:
        rows = torch.arange(near.numel(), device=near.device)
    else:
        rows = near.reshape(-1).nonzero().squeeze(-1)

    def pick(value: Tensor) -> Tensor:
        return value.reshape(-1, *value.shape[len(shape) - 1 :]).index_select(0, rows)

    point_a, point_b, distance = _closest_pair(
        (pick(position), pick(rotation), pick(half_a)),
        (pick(other_position), pick(other_rotation), pick(half_b)),
    )
    near_points, near_normals, near_gaps, near_valid = (
        pick(points), pick(normals), pick(gaps), pick(valid)
    )  # fmt: skip
    reached = torch.where(near_valid, near_gaps, torch.inf).amin(-1, keepdim=True)
    reached = reached <= distance + pick(tol.expand(*shape[:-1], 1))
    exact = pick(is_edge).unsqueeze(-1) | ~reached  # (N, 1)
    if traced:
        exact = exact & pick(near).unsqueeze(-1)
    direction = _safe_divide(point_a - point_b, distance, 0.0)
    first = torch.arange(8, device=gaps.device) == 0
    replaced = (
        torch.where(exact.unsqueeze(-1), point_a.unsqueeze(-2), near_points),
        torch.where(exact.unsqueeze(-1), direction.unsqueeze(-2), near_normals),
        torch.where(exact, distance, near_gaps),
        torch.where(exact, first, near_valid),
    )
    return tuple(
        full.reshape(-1, *full.shape[len(shape) - 1 :])
        .index_copy(0, rows, part)
        .reshape(full.shape)
        for full, part in zip(chosen, replaced, strict=True)
    )


_Box = tuple[Tensor, Tensor, Tensor]


def _face_contact(
    ref_is_a: Tensor, ref_axis: Tensor, box_a: _Box, box_b: _Box, tolerance: Tensor
) -> tuple[Tensor, ...]:
    """Clip the incident face to the reference face; up to 8 points on A (``(*B, G, 8, ·)``)."""
    flag = ref_is_a.unsqueeze(-1)
    flag2 = flag.unsqueeze(-1)
    t_ref = torch.where(flag, box_a[0], box_b[0])
    r_ref = torch.where(flag2, box_a[1], box_b[1])
    h_ref = torch.where(flag, box_a[2], box_b[2])
    t_inc = torch.where(flag, box_b[0], box_a[0])
    r_inc = torch.where(flag2, box_b[1], box_a[1])
    h_inc = torch.where(flag, box_b[2], box_a[2])
    column = _column(r_ref, ref_axis)
    n_ref = column * _sign(_dot3(t_inc - t_ref, column)).unsqueeze(-1)
    alignment = _unrotate(r_inc, n_ref.unsqueeze(-2)).squeeze(-2)  # (*B, G, 3)
    inc_axis = alignment.abs().argmax(-1)
    n_inc = -_column(r_inc, inc_axis) * _sign(_pick(alignment, inc_axis)).unsqueeze(-1)
    f_ref = t_ref + _pick(h_ref, ref_axis).unsqueeze(-1) * n_ref
    f_inc = t_inc + _pick(h_inc, inc_axis).unsqueeze(-1) * n_inc
    i1, i2 = (ref_axis + 1) % 3, (ref_axis + 2) % 3
    j1, j2 = (inc_axis + 1) % 3, (inc_axis + 2) % 3
    u1, u2 = _column(r_ref, i1), _column(r_ref, i2)
    a, b = _pick(h_ref, i1).unsqueeze(-1), _pick(h_ref, i2).unsqueeze(-1)  # (*B, G, 1)
    w1 = _column(r_inc, j1) * _pick(h_inc, j1).unsqueeze(-1)
    w2 = _column(r_inc, j2) * _pick(h_inc, j2).unsqueeze(-1)
    cycle = torch.tensor(
        [[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]], dtype=a.dtype, device=a.device
    )
    corners = (
        f_inc.unsqueeze(-2) + cycle[:, :1] * w1.unsqueeze(-2) + cycle[:, 1:] * w2.unsqueeze(-2)
    )  # (*B, G, 4, 3), a cycle around the incident face
    relative = corners - f_ref.unsqueeze(-2)
    u = _dot3(relative, u1.unsqueeze(-2))
    v = _dot3(relative, u2.unsqueeze(-2))
    depth = _dot3(relative, n_ref.unsqueeze(-2))  # (*B, G, 4)
    tol = tolerance.unsqueeze(-1)  # (G, 1)

    # 1. incident corners over the reference face.
    corner_valid = (u.abs() <= a + tol) & (v.abs() <= b + tol)

    # 2. reference corners under the incident face (and not at one of its corners).
    quad = torch.stack([u, v], -1)  # (*B, G, 4, 2)
    side = quad.roll(-1, dims=-2) - quad
    area = cross2(quad, quad.roll(-1, dims=-2)).sum(-1, keepdim=True)
    ref_2d = torch.stack([cycle[:, 0] * a, cycle[:, 1] * b], -1)  # (*B, G, 4, 2)
    to_ref = ref_2d.unsqueeze(-2) - quad.unsqueeze(-3)  # (*B, G, 4 ref, 4 inc, 2)
    inward = cross2(side.unsqueeze(-3), to_ref) * _sign(area).unsqueeze(-1)
    inward = inward / torch.hypot(side[..., 0], side[..., 1]).unsqueeze(-2)
    apart = torch.hypot(to_ref[..., 0], to_ref[..., 1]) > tol.unsqueeze(-1)
    ref_valid = ((inward >= -tol.unsqueeze(-1)) & apart).all(-1)
    on_ref = (
        f_ref.unsqueeze(-2)
        + ref_2d[..., :1] * u1.unsqueeze(-2)
        + ref_2d[..., 1:] * u2.unsqueeze(-2)
    )
    lift = _dot3(f_inc.unsqueeze(-2) - on_ref, n_inc.unsqueeze(-2)) / _dot3(n_ref, n_inc).unsqueeze(
        -1
    )
    ref_points = on_ref + lift.unsqueeze(-1) * n_ref.unsqueeze(-2)

    # 3. incident edges crossing the reference edges' lines u = ±a, v = ±b within them.
    across = torch.stack([u, u, v, v], -1)  # (*B, G, 4 edges, 4 lines)
    lengthwise = torch.stack([v, v, u, u], -1)
    line = torch.stack([a, -a, b, -b], -1)  # (*B, G, 1, 4)
    extent = torch.stack([b, b, a, a], -1)
    start, stop = across - line, across.roll(-1, dims=-2) - line
    crossing = (
        (start * stop < 0) & (start.abs() > tol.unsqueeze(-1)) & (stop.abs() > tol.unsqueeze(-1))
    )
    fraction = torch.where(crossing, start / torch.where(crossing, start - stop, 1.0), 0.5)
    sideways = lengthwise + fraction * (lengthwise.roll(-1, dims=-2) - lengthwise)
    cross_valid = crossing & (sideways.abs() < extent - tol.unsqueeze(-1))
    edge_start = corners.unsqueeze(-2)
    edge_step = (corners.roll(-1, dims=-2) - corners).unsqueeze(-2)
    cross_points = (edge_start + fraction.unsqueeze(-1) * edge_step).flatten(-3, -2)
    cross_depth = (
        depth.unsqueeze(-1) + fraction * (depth.roll(-1, dims=-1) - depth).unsqueeze(-1)
    ).flatten(-2)

    points = torch.cat([corners, ref_points, cross_points], -2)  # (*B, G, 24, 3)
    gap = torch.cat([depth, lift, cross_depth], -1)
    valid = torch.cat([corner_valid, ref_valid, cross_valid.flatten(-2)], -1)
    keep = torch.sort(valid.to(torch.uint8), dim=-1, descending=True, stable=True).indices[..., :8]
    points = points.gather(-2, keep.unsqueeze(-1).expand(*keep.shape, 3))
    gap, valid = gap.gather(-1, keep), valid.gather(-1, keep)
    normal = n_ref.unsqueeze(-2).expand_as(points)
    # Points on A: the incident face's when B is the reference; else their projections on
    # A's reference face.
    points = torch.where(flag2, points - gap.unsqueeze(-1) * normal, points)
    normal = torch.where(flag2, -normal, normal)
    return points, normal, gap, valid


def _edge_contact(edge_axis: Tensor, unit: Tensor, box_a: _Box, box_b: _Box) -> tuple[Tensor, ...]:
    """The closest points of A's and B's support edges along an edge axis: one slot of 8."""
    t_a, r_a, h_a = box_a
    t_b, r_b, h_b = box_b
    axis = unit.gather(-2, (6 + edge_axis)[..., None, None].expand(*edge_axis.shape, 1, 3)).squeeze(
        -2
    )
    normal = axis * _sign(_dot3(t_a - t_b, axis)).unsqueeze(-1)  # from B into A
    i, j = edge_axis // 3, edge_axis % 3
    along_a, along_b = _column(r_a, i), _column(r_b, j)
    # The edges: A's farthest along −n, B's farthest along +n (their axis terms dropped).
    keep_a = torch.ones_like(h_a).scatter(-1, i.unsqueeze(-1), 0.0)
    keep_b = torch.ones_like(h_b).scatter(-1, j.unsqueeze(-1), 0.0)
    toward_a = _unrotate(r_a, normal.unsqueeze(-2)).squeeze(-2)
    toward_b = _unrotate(r_b, normal.unsqueeze(-2)).squeeze(-2)
    centre_a = t_a + _rotate(r_a, (-_sign(toward_a) * h_a * keep_a).unsqueeze(-2)).squeeze(-2)
    centre_b = t_b + _rotate(r_b, (_sign(toward_b) * h_b * keep_b).unsqueeze(-2)).squeeze(-2)
    reach_a, reach_b = _pick(h_a, i).unsqueeze(-1), _pick(h_b, j).unsqueeze(-1)
    point_a, point_b = _closest_on_segments(
        (centre_a, along_a, reach_a), (centre_b, along_b, reach_b)
    )
    gap = _dot3(point_a - point_b, normal).unsqueeze(-1)
    points = torch.cat(
        [point_a.unsqueeze(-2), point_a.unsqueeze(-2).expand(*point_a.shape[:-1], 7, 3)], -2
    )
    normals = normal.unsqueeze(-2).expand_as(points)
    gaps = torch.cat([gap, gap.expand(*gap.shape[:-1], 7)], -1)
    valid = torch.zeros_like(gaps, dtype=torch.bool)
    valid[..., 0] = True
    return points, normals, gaps, valid


_Segment = tuple[Tensor, Tensor, Tensor]


def _closest_on_segments(segment_a: _Segment, segment_b: _Segment) -> tuple[Tensor, Tensor]:
    """Closest points ``(..., 3)`` of segments ``c + s u``, ``|s| <= h`` (centre ``c``
    ``(..., 3)``, unit direction ``u`` ``(..., 3)``, half length ``h`` ``(..., 1)``).

    The lines' closest parameters, clamped to one segment, then the other's parameter for it,
    clamped, then the first's again [Ericson 2005, §5.1.9] (parallel segments: from ``s = 0``).
    """
    centre_a, along_a, reach_a = segment_a
    centre_b, along_b, reach_b = segment_b
    between = centre_a - centre_b
    cosine = _dot3(along_a, along_b).unsqueeze(-1)
    d_a = _dot3(along_a, between).unsqueeze(-1)
    d_b = _dot3(along_b, between).unsqueeze(-1)
    s_a, s_b = _clamped_parameters(cosine, d_a, d_b, reach_a, reach_b)
    return centre_a + s_a * along_a, centre_b + s_b * along_b


def _clamped_parameters(
    cosine: Tensor, d_a: Tensor, d_b: Tensor, reach_a: Tensor, reach_b: Tensor
) -> tuple[Tensor, Tensor]:
    """The closest parameters ``(s_a, s_b)`` of two segments from ``u_a · u_b``,
    ``u_a · (c_a − c_b)``, ``u_b · (c_a − c_b)`` and the half lengths (broadcast)."""
    sine2 = 1 - cosine * cosine
    s_a = torch.minimum(
        torch.maximum(_safe_divide(cosine * d_b - d_a, sine2, 0.0), -reach_a), reach_a
    )
    s_b = torch.minimum(torch.maximum(d_b + cosine * s_a, -reach_b), reach_b)
    s_a = torch.minimum(torch.maximum(cosine * s_b - d_a, -reach_a), reach_a)
    return s_a, s_b


def _edge_table(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """A box's 12 edges: ``(12, 3)`` the signs of their centres (0 along the edge) and
    ``(12,)`` long their axes."""
    rows, axes = [], []
    for axis in range(3):
        for first in (-1.0, 1.0):
            for second in (-1.0, 1.0):
                row = [0.0, 0.0, 0.0]
                row[(axis + 1) % 3], row[(axis + 2) % 3] = first, second
                rows.append(row)
                axes.append(axis)
    return (
        torch.tensor(rows, dtype=dtype, device=device),
        torch.tensor(axes, dtype=torch.long, device=device),
    )


def _closest_pair(box_a: _Box, box_b: _Box) -> tuple[Tensor, Tensor, Tensor]:
    """The closest points ``(*B, G, 3)`` of two disjoint boxes and their distance
    ``(*B, G, 1)``: the nearest of every corner against the other box (its clamp into the
    other's frame) and every pair of their edges.

    The 144 edge pairs are compared by scalars only: with ``Δ = c_a − c_b``, the clamped
    parameters (:func:`_closest_on_segments`) need ``u_a · u_b``, ``u_a · Δ`` and ``u_b · Δ``,
    and the squared distance is ``|Δ|² + s_a² + s_b² + 2 s_a u_a·Δ − 2 s_b u_b·Δ −
    2 s_a s_b u_a·u_b``, all from one product of the ``(24, 3)`` rows ``[u; c]`` of each box
    (centres taken from B's centre, so that the squares do not cancel); the nearest pair's
    points are then computed in space.
    """
    t_a, r_a, h_a = box_a
    t_b, r_b, h_b = box_b
    signs = corner_signs(h_a.dtype, h_a.device)
    edge_signs, edge_axes = _edge_table(h_a.dtype, h_a.device)
    # Corners against the other box.
    firsts, seconds = [], []
    for (t_1, r_1, h_1), (t_2, r_2, h_2), flip in ((box_a, box_b, False), (box_b, box_a, True)):
        corners = _to_world(r_1, t_1, signs * h_1.unsqueeze(-2))  # (*B, G, 8, 3)
        local = _unrotate(r_2, corners - t_2.unsqueeze(-2))
        h = h_2.unsqueeze(-2)
        nearest = _to_world(r_2, t_2, torch.maximum(torch.minimum(local, h), -h))
        firsts.append(nearest if flip else corners)
        seconds.append(corners if flip else nearest)
    first, second = torch.cat(firsts, -2), torch.cat(seconds, -2)  # (*B, G, 16, 3)
    corner_distance, corner = _norm3(first - second).min(-1, keepdim=True)
    index = corner.unsqueeze(-1).expand(*corner.shape, 3)
    corner_a, corner_b = first.gather(-2, index).squeeze(-2), second.gather(-2, index).squeeze(-2)
    # Edge pairs, by scalars.
    rows = []
    for t, r, h in ((t_a, r_a, h_a), (t_b, r_b, h_b)):
        centres = _to_world(r, t - t_b, edge_signs * h.unsqueeze(-2))  # (*B, G, 12, 3)
        rows.append(torch.cat([r.index_select(-1, edge_axes).mT, centres], -2))  # (*B, G, 24, 3)
    products = rows[0] @ rows[1].mT  # (*B, G, 24, 24)
    cosine, ua_cb = products[..., :12, :12], products[..., :12, 12:]
    ca_ub, ca_cb = products[..., 12:, :12], products[..., 12:, 12:]
    ua_ca = _dot3(rows[0][..., :12, :], rows[0][..., 12:, :]).unsqueeze(-1)
    ub_cb = _dot3(rows[1][..., :12, :], rows[1][..., 12:, :]).unsqueeze(-2)
    d_a, d_b = ua_ca - ua_cb, ca_ub - ub_cb  # u_a · Δ, u_b · Δ: (*B, G, 12, 12)
    square = (
        _dot3(rows[0][..., 12:, :], rows[0][..., 12:, :]).unsqueeze(-1)
        + _dot3(rows[1][..., 12:, :], rows[1][..., 12:, :]).unsqueeze(-2)
        - 2 * ca_cb
    )
    reach_a = h_a.index_select(-1, edge_axes).unsqueeze(-1)
    reach_b = h_b.index_select(-1, edge_axes).unsqueeze(-2)
    s_a, s_b = _clamped_parameters(cosine, d_a, d_b, reach_a, reach_b)
    square = square + s_a * (s_a + 2 * d_a) + s_b * (s_b - 2 * d_b) - 2 * s_a * s_b * cosine
    best = square.flatten(-2).argmin(-1, keepdim=True)  # (*B, G, 1)
    e, f = best // 12, best % 12
    segments = []
    for row, t, edge, parameter in (
        (rows[0], t_b, e, s_a.flatten(-2).gather(-1, best)),
        (rows[1], t_b, f, s_b.flatten(-2).gather(-1, best)),
    ):
        pick = edge.unsqueeze(-1).expand(*edge.shape, 3)
        along = row[..., :12, :].gather(-2, pick).squeeze(-2)
        centre = row[..., 12:, :].gather(-2, pick).squeeze(-2) + t
        segments.append(centre + parameter * along)
    edge_distance = _norm3(segments[0] - segments[1]).unsqueeze(-1)
    edges_nearer = edge_distance < corner_distance
    return (
        torch.where(edges_nearer, segments[0], corner_a),
        torch.where(edges_nearer, segments[1], corner_b),
        torch.minimum(edge_distance, corner_distance),
    )


_KERNELS: dict[tuple[str, str], _Kernel] = {
    ("Box", "HalfSpace"): _box_half_space,
    ("Sphere", "HalfSpace"): _sphere_half_space,
    ("Capsule", "HalfSpace"): _capsule_half_space,
    ("Sphere", "Box"): _sphere_box,
    ("Capsule", "Box"): _capsule_box,
    ("Box", "Box"): _box_box,
    ("Sphere", "Sphere"): _sphere_sphere,
    ("Sphere", "Capsule"): _sphere_capsule,
    ("Capsule", "Capsule"): _capsule_capsule,
}
