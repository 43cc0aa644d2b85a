"""Contact slots between planar shapes: every vertex against the closest edge of the other shape.

A *slot group* pairs the vertices of a receiving polygon with the edges of another shape (a
convex polygon, or a half-plane: one unbounded edge). Every group yields one slot per vertex of
its receiver, so scenes batch without ragged tensors; a slot's ``active`` flag says whether it is
a contact candidate this step.

The shapes and groups of a scene go into a :class:`PlanarSlotTable` once
(:func:`planar_slot_table`); :func:`planar_slots` then computes every slot of every group from the
shapes' poses in a fixed number of tensor operations (no loop over groups, no host
synchronization, no data-dependent shapes: :func:`torch.compile` traces it), optionally with the
exact derivatives of its outputs along given directions of the poses (forward tangents).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import torch
from torch import Tensor

from torchcontact.geometry._se2 import cross2, dot2
from torchcontact.geometry._shapes import HalfPlane, Polygon

#: Relative tolerance (of the longest edge) within which two edges are equally close.
TIE_TOLERANCE = 1e-9
#: Offset of padding edges (their signed distance is about ``-_FAR``: never the closest edge).
_FAR = 1e30


@dataclass(frozen=True, eq=False)
class SlotGeometry:
    """Contact slots: features of receiving shapes against the closest feature of other shapes
    (planar: vertices against edges), in ``d`` dimensions (``d = 2`` planar).

    With forward tangents (:func:`planar_slots`' ``pose_tangents``), ``points``, ``normals``
    and ``phi`` hold a stacked dimension ``1 + T`` after the batch: the values, then their
    derivatives along the ``T`` pose directions.

    Attributes:
        points: ``(*B, S, d)`` contact points (the receiving shapes' vertices), world frame.
        normals: ``(*B, S, d)`` unit contact normals pointing from the other shape into the
            receiving one, world frame.
        phi: ``(*B, S)`` signed gaps along the normals (negative when penetrating), metres.
        active: ``(*B, S)`` bool: the slot is a contact candidate (gap ≤ margin, and the
            vertex projects onto the closest edge within the margin).
    """

    points: Tensor
    normals: Tensor
    phi: Tensor
    active: Tensor


@dataclass(frozen=True, eq=False)
class PlanarSlotTable:
    """Body-frame tables of ``Ns`` planar shapes and ``G`` slot groups between them.

    Shapes are padded to ``V`` vertices (the most of any polygon) and ``E`` edges (the most of
    any shape that is some group's other shape; a half-plane has one): a polygon's padding
    vertices repeat its first vertex and its padding edges have zero normal and lie ``_FAR``
    away; a half-plane is a single edge of unbounded length, its rows being world rows at the
    zero pose. Edge ``e`` runs from vertex ``e`` to vertex ``e + 1``.

    Attributes:
        frame: ``(Ns, V + E + 1, 2)`` body-frame rows of every shape: vertices, outward edge
            normals and the origin (zero). An edge's direction is its normal turned by +90°.
        frame_turned: ``(Ns, V + E + 1, 2)`` the same rows turned by +90°, so that a shape at
            angle ``θ`` has the rows ``cos θ · frame + sin θ · frame_turned``.
        translated: ``(V + E + 1, 1)`` 1 on the rows that move with the shape's position (the
            vertices and the origin), 0 on the normals.
        group_shapes: ``(2G,)`` shape index of each group's receiver, then of its other shape.
        edge_offset: ``(G, 1, 2E)`` ``a_e · n_e`` and ``a_e · d_e`` of the other shape's edges
            in its body frame (``a_e`` the edge's first vertex).
        facing_offset: ``(G, 1, E)`` ``(a_e − c) · n_e``, ``c`` the other shape's vertex mean.
        edge_reach: ``(G, 1, E)`` the other shape's edge lengths plus the margin.
        tie_tolerance: ``(G, 1, 1)`` absolute tolerance of equally close edges
            (``TIE_TOLERANCE`` times the other shape's longest edge; 0 for a half-plane).
        slot_source: ``(S,)`` long: each slot's index among the groups' ``G·V`` padded
            vertex slots (group-major).
        slot_receiver: ``(S,)`` long: shape index of each slot's receiver.
        slot_other: ``(S,)`` long: shape index of each slot's other shape.
        turn: ``(2,)`` ``(−1, 1)``: ``u.flip(-1) * turn`` turns ``u`` by +90°.
        margin: candidate margin, metres.
    """

    frame: Tensor
    frame_turned: Tensor
    translated: Tensor
    group_shapes: Tensor
    edge_offset: Tensor
    facing_offset: Tensor
    edge_reach: Tensor
    tie_tolerance: Tensor
    slot_source: Tensor
    slot_receiver: Tensor
    slot_other: Tensor
    turn: Tensor
    margin: float

    @property
    def num_slots(self) -> int:
        """``S``, the number of slots."""
        return self.slot_source.shape[0]

    def to(
        self, *, dtype: torch.dtype, device: torch.device | str | None = None
    ) -> PlanarSlotTable:
        """The table with its float tensors in ``dtype`` and every tensor on ``device``."""
        converted: dict[str, Any] = {}
        for item in fields(self):
            value = getattr(self, item.name)
            if isinstance(value, Tensor):
                target = dtype if value.is_floating_point() else value.dtype
                converted[item.name] = value.to(device=device, dtype=target)
        return replace(self, **converted)

    def subtable(self, groups: Sequence[int]) -> tuple[PlanarSlotTable, Tensor, Tensor]:
        """The table of some of its groups, over only the shapes they name.

        Its groups are ``groups`` in that order, its slots theirs in this table's slot order,
        its shapes theirs in this table's shape order; the vertex and edge padding is cut to
        what they need. Its rows are this table's numbers, so :func:`planar_slots` on it
        computes those slots with the same operations on the same numbers (the padding edges
        it drops never win a slot's closest edge, the padding vertices are never slots).

        Args:
            groups: distinct indices of this table's groups (at least one).

        Returns:
            The table, the ``(Ns',)`` long indices of its shapes among this table's (select
            their poses with ``poses.index_select(-2, shapes)``) and the ``(S',)`` long indices
            of its slots among this table's.

        Raises:
            ValueError: ``groups`` is empty, repeats a group or names one that is not there.
        """
        G, E = self.facing_offset.shape[0], self.facing_offset.shape[-1]
        V = self.frame.shape[-2] - E - 1
        chosen = list(groups)
        valid = all(isinstance(g, int) and 0 <= g < G for g in chosen)
        if not chosen or not valid or len(set(chosen)) != len(chosen):
            raise ValueError(f"groups must be distinct group indices in [0, {G}), got {groups!r}")
        device = self.slot_source.device
        picked = torch.tensor(chosen, dtype=torch.long, device=device)
        renumber = torch.full((G,), -1, dtype=torch.long, device=device)
        renumber[picked] = torch.arange(len(chosen), device=device)
        slot_group = self.slot_source // V
        slots = (renumber[slot_group] >= 0).nonzero().squeeze(-1)
        vertex = self.slot_source[slots] % V
        members = torch.cat([self.group_shapes[:G][picked], self.group_shapes[G:][picked]])
        shapes = members.unique()  # sorted
        reshape = torch.full((self.frame.shape[0],), -1, dtype=torch.long, device=device)
        reshape[shapes] = torch.arange(len(shapes), device=device)
        # The real edges of a group's other shape come first and have unit normals, the
        # padding edges zero normals.
        others = self.frame[self.group_shapes[G:][picked], V : V + E]
        num_vertices = int(vertex.max()) + 1
        num_edges = int((others != 0).any(-1).sum(-1).max())
        edges = torch.arange(num_edges, device=device)
        rows = torch.cat([torch.arange(num_vertices, device=device), V + edges])
        rows = torch.cat([rows, rows.new_full((1,), V + E)])
        return (
            replace(
                self,
                frame=self.frame[shapes][:, rows],
                frame_turned=self.frame_turned[shapes][:, rows],
                translated=self.translated[rows],
                group_shapes=reshape[members],
                edge_offset=self.edge_offset[picked][..., torch.cat([edges, E + edges])],
                facing_offset=self.facing_offset[picked][..., :num_edges],
                edge_reach=self.edge_reach[picked][..., :num_edges],
                tie_tolerance=self.tie_tolerance[picked],
                slot_source=renumber[slot_group[slots]] * num_vertices + vertex,
                slot_receiver=reshape[self.slot_receiver[slots]],
                slot_other=reshape[self.slot_other[slots]],
            ),
            shapes,
            slots,
        )


def planar_slot_table(
    shapes: Sequence[Polygon | HalfPlane],
    groups: Sequence[tuple[int, int]],
    *,
    margin: float,
) -> PlanarSlotTable:
    """The float64 CPU :class:`PlanarSlotTable` of shapes and slot groups.

    Args:
        shapes: the ``Ns`` shapes (at least one polygon).
        groups: ``G`` pairs ``(receiver, other)`` of indices into ``shapes``: the receiver
            must be a polygon; its vertices make the group's slots, in vertex order.
        margin: gap below which a slot becomes a candidate, metres, ``>= 0``.

    Raises:
        ValueError: naming ``shapes``, ``groups`` or ``margin`` when it breaks these rules.
    """
    if not shapes or not all(isinstance(s, (Polygon, HalfPlane)) for s in shapes):
        raise ValueError("shapes must be a non-empty sequence of Polygon and HalfPlane")
    if not any(isinstance(s, Polygon) for s in shapes):
        raise ValueError("shapes must hold at least one Polygon")
    for pair in groups:
        valid = (
            isinstance(pair, tuple)
            and len(pair) == 2
            and all(isinstance(i, int) and 0 <= i < len(shapes) for i in pair)
        )
        if not valid or not isinstance(shapes[pair[0]], Polygon):
            raise ValueError(
                f"groups must be pairs (receiver, other) of shape indices whose receiver is a "
                f"Polygon, got {pair!r}"
            )
    if not isinstance(margin, (int, float)) or not margin >= 0:
        raise ValueError(f"margin must be a real >= 0, got {margin!r}")
    f64 = torch.float64
    V = max(s.num_vertices for s in shapes if isinstance(s, Polygon))
    edges = [s.num_vertices if isinstance(s, Polygon) else 1 for s in shapes]
    E = max((edges[other] for _, other in groups), default=1)
    Ns = len(shapes)
    turn = torch.tensor([-1.0, 1.0], dtype=f64)
    frame = torch.zeros(Ns, V + E + 1, 2, dtype=f64)
    edge_offset = torch.full((Ns, 2 * E), _FAR, dtype=f64)
    facing_offset = torch.zeros(Ns, E, dtype=f64)
    edge_length = torch.zeros(Ns, E, dtype=f64)
    for s, shape in enumerate(shapes):
        if isinstance(shape, HalfPlane):  # one edge, everywhere within reach
            normal = shape.normal.to(f64)
            frame[s, V] = normal
            edge_offset[s, 0], edge_offset[s, E] = shape.point.to(f64) @ normal, -_FAR
            edge_length[s, 0] = torch.inf
            continue
        local = shape.vertices.to(f64)
        n = len(local)
        frame[s, :n], frame[s, n:V] = local, local[0]
        # The edges of a polygon that is no group's other shape are never used (E may be less).
        m = min(n, E)
        local, ahead = local[:m], local.roll(-1, dims=0)[:m]
        outward = shape.edge_normals().to(f64)[:m]
        direction = outward.flip(-1) * turn
        frame[s, V : V + m] = outward
        edge_offset[s, :m] = (local * outward).sum(-1)
        edge_offset[s, E : E + m] = (local * direction).sum(-1)
        facing_offset[s, :m] = ((local - shape.vertices.to(f64).mean(dim=0)) * outward).sum(-1)
        edge_length[s, :m] = (ahead - local).norm(dim=-1)
    translated = torch.zeros(V + E + 1, 1, dtype=f64)
    translated[:V] = translated[-1] = 1.0

    receivers = [pair[0] for pair in groups]
    others = torch.tensor([pair[1] for pair in groups], dtype=torch.long)
    slot_source: list[int] = []
    slot_receiver: list[int] = []
    slot_other: list[int] = []
    for g, (receiver, other) in enumerate(groups):
        count = shapes[receiver].num_vertices  # type: ignore[union-attr]
        slot_source.extend(g * V + j for j in range(count))
        slot_receiver.extend([receiver] * count)
        slot_other.extend([other] * count)
    lengths = edge_length[others]
    return PlanarSlotTable(
        frame=frame,
        frame_turned=frame.flip(-1) * turn,
        translated=translated,
        group_shapes=torch.cat([torch.tensor(receivers, dtype=torch.long), others]),
        edge_offset=edge_offset[others].unsqueeze(-2),
        facing_offset=facing_offset[others].unsqueeze(-2),
        edge_reach=lengths.unsqueeze(-2) + margin,
        tie_tolerance=TIE_TOLERANCE * lengths.nan_to_num(posinf=0.0).amax(-1)[:, None, None],
        slot_source=torch.tensor(slot_source, dtype=torch.long),
        slot_receiver=torch.tensor(slot_receiver, dtype=torch.long),
        slot_other=torch.tensor(slot_other, dtype=torch.long),
        turn=turn,
        margin=float(margin),
    )


def planar_slots(
    table: PlanarSlotTable, poses: Tensor, pose_tangents: Tensor | None = None
) -> SlotGeometry:
    """Every slot of every group of a table, from the shapes' poses.

    For each vertex ``p`` of a receiver, the closest feature is the edge ``e`` of the other
    shape with the largest signed distance ``φ = n_e · (p − a_e)`` (for a convex polygon the
    distance to it when ``p`` lies in the edge's slab, and the penetration depth inside). Ties
    within the table's ``tie_tolerance`` (a vertex at a corner, aligned boxes side by side) go to
    the edge that faces ``p`` from the other shape's vertex mean ``c``, the largest
    ``n_e · (p − c)``. The slot is a candidate when ``φ <= margin`` and ``p`` projects onto
    the edge within the margin.

    With ``pose_tangents`` the derivatives are propagated exactly through the same operations
    (plain tensor operations): a rotated row's derivative along ``θ`` is the row turned by
    +90°, a translated row's along ``(x, y)`` is that direction; ``φ`` takes the derivative of
    its arg-max edge (at a tie, the edge whose normal the slot takes: a one-sided derivative);
    the discrete choices (closest edge, candidates) are held fixed. They are stacked behind the
    values, so that the linear operations (gathers, slices) run once on both.

    Args:
        table: the shapes and groups.
        poses: ``(*B, Ns, 3)`` world poses ``(x, y, θ)`` of the table's shapes (a half-plane's
            rows are world rows at the zero pose).
        pose_tangents: ``(*B, T, Ns, 3)`` directions along which to differentiate the poses,
            or ``None``.

    Returns:
        The :class:`SlotGeometry` of the ``S`` slots; with ``pose_tangents`` its ``points``
        ``(*B, 1 + T, S, 2)``, ``normals`` ``(*B, 1 + T, S, 2)`` and ``phi``
        ``(*B, 1 + T, S)`` hold the values, then their derivatives.
    """
    G, E = table.facing_offset.shape[0], table.facing_offset.shape[-1]
    V = table.frame.shape[-2] - E - 1
    angle = poses[..., 2, None, None]
    rotated = table.frame * torch.cos(angle) + table.frame_turned * torch.sin(angle)
    world = torch.addcmul(rotated, table.translated, poses[..., None, :2])  # (*B, Ns, 2V+1, 2)
    if pose_tangents is not None:
        # The rows' derivatives: translated rows move with (x, y), every row turns with θ.
        turned = rotated.flip(-1) * table.turn
        moving = torch.addcmul(
            turned.unsqueeze(-4) * pose_tangents[..., 2, None, None],
            table.translated,
            pose_tangents[..., None, :2],
        )  # (*B, T, Ns, 2V+1, 2)
        world = torch.cat([world.unsqueeze(-4), moving], dim=-4)
    shapes = world.index_select(-3, table.group_shapes)
    points, other = shapes[..., :G, :V, :], shapes[..., G:, :, :]  # (*B, [D,] G, ·, 2)
    normals = other[..., V : V + E, :]
    relative = points - other[..., V + E :, :]  # (*B, [D,] G, V, 2)
    stacked = pose_tangents is not None
    relative_value = relative[..., 0, :, :, :] if stacked else relative
    # Signed distances of every vertex to every edge: (*B, G, V, E).
    distance = _dot(relative_value, normals[..., 0, :, :, :] if stacked else normals)
    distance = distance - table.edge_offset[..., :E]
    phi = distance.amax(dim=-1, keepdim=True)
    tie = distance >= phi - table.tie_tolerance
    closest = torch.where(tie, distance + table.facing_offset, -_FAR).argmax(-1, keepdim=True)
    # The closest edge: its outward normal is the slot's normal; the vertex must project onto
    # it within the margin (along its direction d = n turned by +90°: r · d = n × r).
    index = closest.expand(*closest.shape[:-1], 2)  # (*B, G, V, 2)
    if stacked:
        normal = normals.gather(-2, index.unsqueeze(-4).expand(*normals.shape[:-2], V, 2))
        normal_value = normal[..., 0, :, :, :]
    else:
        normal = normal_value = normals.gather(-2, index)  # (*B, G, V, 2)
    lengthwise = table.edge_offset[..., E:].expand(*closest.shape[:-1], E).gather(-1, closest)
    along = cross2(normal_value, relative_value).unsqueeze(-1) - lengthwise
    reach = table.edge_reach.expand(*closest.shape[:-1], E).gather(-1, closest)
    active = (along >= -table.margin) & (along <= reach) & (phi <= table.margin)  # (*B, G, V, 1)
    if stacked:
        # φ's derivative: that of the closest edge's distance (the one whose normal it takes).
        turning = dot2(
            relative[..., 1:, :, :, :],
            normal[..., :1, :, :, :],
            relative_value.unsqueeze(-4),
            normal[..., 1:, :, :, :],
        )
        phi = torch.cat([phi.unsqueeze(-4), turning.unsqueeze(-1)], dim=-4)  # (*B, D, G, V, 1)
    source = table.slot_source
    return SlotGeometry(
        points=points.flatten(-3, -2).index_select(-2, source),
        normals=normal.flatten(-3, -2).index_select(-2, source),
        phi=phi.flatten(-3).index_select(-1, source),
        active=active.flatten(-3).index_select(-1, source),
    )


def _dot(rows: Tensor, columns: Tensor) -> Tensor:
    """``(..., R, C)`` dot products of ``rows (..., R, 2)`` with ``columns (..., C, 2)``.

    The batched matrix product ``rows @ columns.mT`` of tiny matrices, elementwise: CPU batched
    GEMM runs one small kernel per matrix.
    """
    return torch.addcmul(
        rows[..., :, None, 0] * columns[..., None, :, 0],
        rows[..., :, None, 1],
        columns[..., None, :, 1],
    )
