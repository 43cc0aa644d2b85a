"""Spatial shapes: boxes, spheres and capsules (bodies) and half-spaces (ground, walls).

A body shape sits in its body frame with its centroid at the origin and its principal axes
along the frame's axes. Mass properties mirror the planar :class:`Polygon`: ``volume`` (m³)
and ``unit_inertia()``, the inertia tensor per unit mass about the centroid in the body frame
(m²), so that a body of mass ``m`` has the inertia tensor ``m · unit_inertia()``;
``mass_properties(density=...)`` or ``mass_properties(mass=...)`` gives both at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact._checks import check_float, check_positive, check_real, describe


def _vector3(name: str, value: object) -> Tensor:
    """``value`` (a tensor or a sequence of three reals) as a finite float64 ``(3,)`` tensor."""
    if not isinstance(value, Tensor):
        try:
            value = torch.tensor(value, dtype=torch.float64)
        except (TypeError, ValueError, RuntimeError):
            raise ValueError(
                f"{name} must be a (3,) tensor or three reals, got {type(value).__name__}"
            ) from None
    tensor = check_float(name, value, trailing=(3,), what="(3,)")
    if tensor.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {describe(tensor)}")
    return tensor.to(torch.float64)


def _mass_properties(
    volume: float, unit_inertia: Tensor, density: float | None, mass: float | None
) -> tuple[float, Tensor]:
    """Mass (kg) and ``(3, 3)`` inertia tensor (kg·m²) from exactly one of density and mass."""
    if (density is None) == (mass is None):
        raise ValueError("mass_properties: give exactly one of density (kg/m³) and mass (kg)")
    if mass is None:
        mass = check_positive("density", density) * volume
    else:
        mass = check_positive("mass", mass)
    return mass, mass * unit_inertia


def corner_signs(dtype: torch.dtype, device: torch.device | str | None = None) -> Tensor:
    """``(8, 3)`` the signs ``(±1, ±1, ±1)`` of a box's corners, x fastest."""
    signs = [[sx, sy, sz] for sz in (-1.0, 1.0) for sy in (-1.0, 1.0) for sx in (-1.0, 1.0)]
    return torch.tensor(signs, dtype=dtype, device=device)


@dataclass(frozen=True, eq=False)
class Box:
    """A box centred on its body frame's origin, edges along the frame's axes.

    Inertia per unit mass about the centroid: ``diag(b² + c², a² + c², a² + b²) / 3`` for
    half extents ``(a, b, c)`` (the ``m (w² + h²) / 12`` of full side lengths).

    Attributes:
        half_extents: ``(3,)`` float64 half side lengths along the body x, y and z axes,
            metres, each ``> 0`` (a tensor or three reals on construction).
    """

    half_extents: Tensor

    def __post_init__(self) -> None:
        half = _vector3("half_extents", self.half_extents)
        if not bool((half > 0).all()):
            raise ValueError(f"half_extents must all be > 0, got {half.tolist()}")
        object.__setattr__(self, "half_extents", half)

    @property
    def volume(self) -> float:
        """Volume ``8 a b c`` in m³."""
        return float(8 * self.half_extents.prod())

    @property
    def bounding_radius(self) -> float:
        """Distance ``√(a² + b² + c²)`` of the farthest points (the corners) from the
        centroid, metres."""
        return float(torch.linalg.vector_norm(self.half_extents))

    def unit_inertia(self) -> Tensor:
        """``(3, 3)`` float64 inertia tensor per unit mass about the centroid, body frame (m²)."""
        square = self.half_extents**2
        return torch.diag(square.sum() - square) / 3

    def mass_properties(
        self, *, density: float | None = None, mass: float | None = None
    ) -> tuple[float, Tensor]:
        """Mass and inertia of the solid box of uniform density.

        Args:
            density: kg/m³ (then ``mass = density · volume``), or ``None``.
            mass: kg, or ``None``; exactly one of ``density`` and ``mass`` is given.

        Returns:
            The mass (kg) and the ``(3, 3)`` float64 inertia tensor about the centroid,
            body frame (kg·m²).
        """
        return _mass_properties(self.volume, self.unit_inertia(), density, mass)

    def corners(self) -> Tensor:
        """``(8, 3)`` float64 corners in the body frame, ``(±a, ±b, ±c)`` with x fastest."""
        return corner_signs(torch.float64, self.half_extents.device) * self.half_extents


@dataclass(frozen=True, eq=False)
class Sphere:
    """A ball centred on its body frame's origin.

    Inertia per unit mass about the centre: ``(2/5) r² I``.

    Attributes:
        radius: metres, ``> 0``.
    """

    radius: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "radius", check_positive("radius", self.radius))

    @property
    def volume(self) -> float:
        """Volume ``(4/3) π r³`` in m³."""
        return 4 / 3 * math.pi * self.radius**3

    @property
    def bounding_radius(self) -> float:
        """Distance ``r`` of the farthest points from the centre, metres."""
        return self.radius

    def unit_inertia(self) -> Tensor:
        """``(3, 3)`` float64 inertia tensor per unit mass about the centre, body frame (m²)."""
        return torch.eye(3, dtype=torch.float64) * (0.4 * self.radius**2)

    def mass_properties(
        self, *, density: float | None = None, mass: float | None = None
    ) -> tuple[float, Tensor]:
        """Mass and inertia of the solid ball of uniform density.

        Args:
            density: kg/m³ (then ``mass = density · volume``), or ``None``.
            mass: kg, or ``None``; exactly one of ``density`` and ``mass`` is given.

        Returns:
            The mass (kg) and the ``(3, 3)`` float64 inertia tensor about the centre,
            body frame (kg·m²).
        """
        return _mass_properties(self.volume, self.unit_inertia(), density, mass)


@dataclass(frozen=True, eq=False)
class Capsule:
    """The points within ``radius`` of the segment from ``(0, 0, −l)`` to ``(0, 0, l)``
    (``l = half_length``; the axis is the body z axis), centroid at the origin.

    Inertia per unit mass about the centroid, from a cylinder of mass fraction
    ``m_c = 2l / (2l + 4r/3)`` and two hemispheres of fraction ``m_s = 1 − m_c`` (each
    hemisphere's centroid ``3r/8`` from its flat face, parallel-axis theorem):

        I_zz = m_c r² / 2 + m_s · 2r² / 5
        I_xx = I_yy = m_c (r² / 4 + l² / 3) + m_s (2r² / 5 + l² + 3 l r / 4)

    Attributes:
        radius: metres, ``> 0``.
        half_length: half the length of the axis segment, metres, ``>= 0`` (0: a sphere).
    """

    radius: float
    half_length: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "radius", check_positive("radius", self.radius))
        object.__setattr__(
            self, "half_length", check_real("half_length", self.half_length, low=0.0)
        )

    @property
    def volume(self) -> float:
        """Volume ``π r² (2l) + (4/3) π r³`` in m³."""
        r, length = self.radius, 2 * self.half_length
        return math.pi * r * r * length + 4 / 3 * math.pi * r**3

    @property
    def bounding_radius(self) -> float:
        """Distance ``l + r`` of the farthest points (the caps' tips) from the centroid,
        metres."""
        return self.half_length + self.radius

    def unit_inertia(self) -> Tensor:
        """``(3, 3)`` float64 inertia tensor per unit mass about the centroid, body frame (m²)."""
        r, half = self.radius, self.half_length
        cylinder = 2 * half / (2 * half + 4 * r / 3)
        spheres = 1 - cylinder
        axial = cylinder * r * r / 2 + spheres * 0.4 * r * r
        transverse = cylinder * (r * r / 4 + half * half / 3) + spheres * (
            0.4 * r * r + half * half + 0.75 * half * r
        )
        return torch.diag(torch.tensor([transverse, transverse, axial], dtype=torch.float64))

    def mass_properties(
        self, *, density: float | None = None, mass: float | None = None
    ) -> tuple[float, Tensor]:
        """Mass and inertia of the solid capsule of uniform density.

        Args:
            density: kg/m³ (then ``mass = density · volume``), or ``None``.
            mass: kg, or ``None``; exactly one of ``density`` and ``mass`` is given.

        Returns:
            The mass (kg) and the ``(3, 3)`` float64 inertia tensor about the centroid,
            body frame (kg·m²).
        """
        return _mass_properties(self.volume, self.unit_inertia(), density, mass)


@dataclass(frozen=True, eq=False)
class HalfSpace:
    """The region ``{p : n · (p − p0) ≤ 0}`` (ground, walls), in its body frame (the world
    frame at the identity pose), of infinite mass.

    Attributes:
        point: ``(3,)`` float64 point ``p0`` on the boundary plane, metres (a tensor or three
            reals on construction).
        normal: ``(3,)`` float64 unit outward normal ``n`` (out of the solid: up for ground).
    """

    point: Tensor
    normal: Tensor

    def __post_init__(self) -> None:
        point, normal = _vector3("point", self.point), _vector3("normal", self.normal)
        if abs(float(normal.norm()) - 1.0) > 1e-9:
            raise ValueError(f"normal must have unit length, got {normal.tolist()}")
        object.__setattr__(self, "point", point)
        object.__setattr__(self, "normal", normal)

    @staticmethod
    def ground(height: float = 0.0, angle: float = 0.0) -> HalfSpace:
        """The ground through ``(0, 0, height)``, turned by ``angle`` rad about the y axis:
        normal ``(sin θ, 0, cos θ)`` (``+z`` at ``angle = 0``), so that for ``angle > 0`` it
        descends along ``+x`` (an incline of slope ``θ``)."""
        height, angle = check_real("height", height), check_real("angle", angle)
        return HalfSpace(
            torch.tensor([0.0, 0.0, height], dtype=torch.float64),
            torch.tensor([math.sin(angle), 0.0, math.cos(angle)], dtype=torch.float64),
        )


SpatialShape = Box | Sphere | Capsule | HalfSpace
