"""Contact-slot generation between planar shapes by closest features (vertex against edge).

Every pair of shapes yields a fixed number of slots, one per vertex that could touch the other
shape, so scenes batch without ragged tensors; the ``active`` flag says which slots are
contact candidates this step (gap within the margin).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact.geometry._se2 import perpendicular
from torchcontact.geometry._shapes import HalfPlane

#: Relative tolerance (of the longest edge) within which two edges are equally close.
TIE_TOLERANCE = 1e-9


@dataclass(frozen=True, eq=False)
class SlotGeometry:
    """Candidate contacts of one shape pair: vertices of the *receiving* shape against the other.

    Attributes:
        points: ``(*B, S, 2)`` contact points (the receiving shape's vertices), world frame.
        normals: ``(*B, S, 2)`` unit contact normals pointing from the other shape into the
            receiving one, world frame.
        phi: ``(*B, S)`` signed gaps along the normals (negative when penetrating), metres.
        active: ``(*B, S)`` bool: the slot is a contact candidate (gap ≤ margin, and for
            polygon edges the vertex projects onto the edge within the margin).
    """

    points: Tensor
    normals: Tensor
    phi: Tensor
    active: Tensor


def halfplane_slots(vertices: Tensor, plane: HalfPlane, *, margin: float) -> SlotGeometry:
    """Slots of a polygon's vertices against a half-plane.

    Args:
        vertices: ``(*B, V, 2)`` polygon vertices, world frame.
        plane: the half-plane (its outward normal becomes the contact normal).
        margin: gap below which a vertex is a candidate, metres.

    Returns:
        ``V`` slots, with ``φ = n · (p − p0)``.
    """
    normal = plane.normal.to(vertices)
    phi = (vertices - plane.point.to(vertices)) @ normal
    return SlotGeometry(
        points=vertices,
        normals=normal.expand_as(vertices),
        phi=phi,
        active=phi <= margin,
    )


def polygon_slots(vertices: Tensor, other: Tensor, *, margin: float) -> SlotGeometry:
    """Slots of one polygon's vertices against another convex polygon's edges.

    For each vertex ``p`` the closest feature is the edge ``e`` of the other polygon with the
    largest signed distance ``n_e · (p − a_e)`` (for a convex polygon this is the distance to
    the polygon when the vertex lies in the edge's slab, and its penetration depth inside).
    Ties (a vertex at a corner) go to the edge that faces ``p`` from the other polygon's
    vertex centroid.

    Args:
        vertices: ``(*B, V, 2)`` vertices of the receiving polygon, world frame.
        other: ``(*B, E, 2)`` counter-clockwise vertices of the other polygon, world frame.
        margin: gap below which a vertex is a candidate, metres.

    Returns:
        ``V`` slots.
    """
    start = other
    edge = other.roll(-1, dims=-2) - other
    length = edge.norm(dim=-1, keepdim=True)
    direction = edge / length
    outward = -perpendicular(direction)  # (*B, E, 2)
    relative = vertices.unsqueeze(-2) - start.unsqueeze(-3)  # (*B, V, E, 2)
    distance = (relative * outward.unsqueeze(-3)).sum(-1)  # (*B, V, E)
    phi = distance.amax(dim=-1)
    # A vertex exactly at a corner is equally far from both edges there (aligned boxes side by
    # side): take the edge that faces the vertex from the other polygon's centre.
    tie = distance >= phi.unsqueeze(-1) - TIE_TOLERANCE * length.squeeze(-1).amax(
        -1, keepdim=True
    ).unsqueeze(-1)
    from_center = vertices - other.mean(dim=-2, keepdim=True)
    facing = from_center @ outward.transpose(-1, -2)  # (*B, V, E)
    closest = torch.where(tie, facing, torch.finfo(facing.dtype).min).argmax(dim=-1)
    index = closest.unsqueeze(-1).expand(*closest.shape, 2)
    normals = outward.gather(-2, index)
    along = (
        relative.gather(-2, index.unsqueeze(-2)).squeeze(-2) * direction.gather(-2, index)
    ).sum(-1)
    extent = length.squeeze(-1).gather(-1, closest)
    within = (along >= -margin) & (along <= extent + margin)
    return SlotGeometry(points=vertices, normals=normals, phi=phi, active=(phi <= margin) & within)


def concat_slots(parts: list[SlotGeometry]) -> SlotGeometry:
    """Concatenate slot sets along the slot dimension."""
    return SlotGeometry(
        points=torch.cat([p.points for p in parts], dim=-2),
        normals=torch.cat([p.normals for p in parts], dim=-2),
        phi=torch.cat([p.phi for p in parts], dim=-1),
        active=torch.cat([p.active for p in parts], dim=-1),
    )
