"""Planar shapes: convex polygons (boxes, triangles, pegs) and half-planes (ground, walls)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact._checks import check_float, check_int, check_positive, check_real, describe
from torchcontact.geometry._se2 import cross2, perpendicular


@dataclass(frozen=True, eq=False)
class Polygon:
    """A convex polygon in its body frame, origin at its centroid.

    Attributes:
        vertices: ``(V, 2)`` float64 vertices in counter-clockwise order, body frame, metres,
            with the centroid at the origin.
    """

    vertices: Tensor

    def __post_init__(self) -> None:
        vertices = check_float("vertices", self.vertices, trailing=(2,), min_ndim=2, what="(V, 2)")
        if vertices.dim() != 2 or vertices.shape[0] < 3:
            raise ValueError(
                f"vertices must have shape (V, 2) with at least 3 points, got {describe(vertices)}"
            )
        edges = vertices.roll(-1, dims=0) - vertices
        turns = cross2(edges, edges.roll(-1, dims=0))
        if not bool((turns > 0).all()):
            raise ValueError(
                "vertices must form a strictly convex polygon in counter-clockwise order"
            )
        area, centroid, _ = _area_moments(vertices)
        scale = float(vertices.abs().max())
        if float(centroid.abs().max()) > 1e-9 * max(scale, 1.0):
            raise ValueError(
                f"vertices must have their centroid at the origin (got {centroid.tolist()}); "
                "use Polygon.centered(...)"
            )
        del area

    @staticmethod
    def centered(vertices: Tensor) -> tuple[Polygon, Tensor]:
        """Build a polygon from arbitrary counter-clockwise vertices.

        Returns:
            The polygon (vertices shifted so the centroid is the origin) and the ``(2,)``
            centroid that was subtracted.
        """
        vertices = torch.as_tensor(vertices, dtype=torch.float64)
        _, centroid, _ = _area_moments(vertices)
        return Polygon(vertices - centroid), centroid

    @staticmethod
    def box(width: float, height: float) -> Polygon:
        """An axis-aligned ``width × height`` rectangle centred on the origin."""
        a, b = check_positive("width", width) / 2, check_positive("height", height) / 2
        return Polygon(torch.tensor([[-a, -b], [a, -b], [a, b], [-a, b]], dtype=torch.float64))

    @staticmethod
    def triangle(base: float, height: float) -> Polygon:
        """An isosceles triangle with a horizontal base and its apex above, centroid at origin."""
        base, height = check_positive("base", base), check_positive("height", height)
        corners = torch.tensor(
            [[-base / 2, 0.0], [base / 2, 0.0], [0.0, height]], dtype=torch.float64
        )
        return Polygon.centered(corners)[0]

    @staticmethod
    def regular(sides: int, radius: float) -> Polygon:
        """A regular polygon with ``sides`` vertices on a circle of ``radius``."""
        sides = check_int("sides", sides, low=3)
        radius = check_positive("radius", radius)
        angles = torch.arange(sides, dtype=torch.float64) * (2 * math.pi / sides) - math.pi / 2
        return Polygon(radius * torch.stack([torch.cos(angles), torch.sin(angles)], -1))

    @property
    def num_vertices(self) -> int:
        """Number of vertices ``V``."""
        return self.vertices.shape[0]

    @property
    def area(self) -> float:
        """Area in m²."""
        return float(_area_moments(self.vertices)[0])

    def unit_inertia(self) -> float:
        """Polar moment of inertia per unit mass about the centroid, ``∫ r² dA / A`` (m²)."""
        area, _, second_moment = _area_moments(self.vertices)
        return float(second_moment / area)

    def edge_normals(self) -> Tensor:
        """``(V, 2)`` outward unit normals of the edges ``v_i → v_{i+1}``, body frame."""
        edges = self.vertices.roll(-1, dims=0) - self.vertices
        return -perpendicular(edges / edges.norm(dim=-1, keepdim=True))


@dataclass(frozen=True, eq=False)
class HalfPlane:
    """The static region ``{p : n · (p − p0) ≤ 0}`` (ground, walls), world frame.

    Attributes:
        point: ``(2,)`` a point ``p0`` on the boundary, metres.
        normal: ``(2,)`` unit outward normal ``n`` (points out of the solid, e.g. up for ground).
    """

    point: Tensor
    normal: Tensor

    def __post_init__(self) -> None:
        for name in ("point", "normal"):
            value = check_float(name, getattr(self, name), trailing=(2,), what="(2,)")
            if value.shape != (2,):
                raise ValueError(f"{name} must have shape (2,), got {tuple(value.shape)}")
        if abs(float(self.normal.norm()) - 1.0) > 1e-9:
            raise ValueError(f"normal must have unit length, got {self.normal.tolist()}")

    @staticmethod
    def ground(height: float = 0.0, angle: float = 0.0) -> HalfPlane:
        """Ground through ``(0, height)`` tilted by ``angle`` rad (counter-clockwise)."""
        height, angle = check_real("height", height), check_real("angle", angle)
        normal = torch.tensor([-math.sin(angle), math.cos(angle)], dtype=torch.float64)
        return HalfPlane(torch.tensor([0.0, height], dtype=torch.float64), normal)


def _area_moments(vertices: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Area, centroid and polar second moment about the centroid of a simple polygon.

    Shoelace formulas: with ``c_i = x_i y_{i+1} − x_{i+1} y_i``, ``A = Σ c_i / 2``,
    ``C = Σ (p_i + p_{i+1}) c_i / (6A)`` and
    ``J_O = Σ c_i (|p_i|² + p_i·p_{i+1} + |p_{i+1}|²) / 12`` about the origin; the
    parallel-axis theorem moves ``J`` to the centroid.
    """
    p, p_next = vertices, vertices.roll(-1, dims=0)
    c = cross2(p, p_next)
    area = c.sum() / 2
    centroid = ((p + p_next) * c.unsqueeze(-1)).sum(0) / (6 * area)
    j_origin = (c * ((p * p).sum(-1) + (p * p_next).sum(-1) + (p_next * p_next).sum(-1))).sum() / 12
    return area, centroid, j_origin - area * (centroid * centroid).sum()
