"""The quantization grid that turns contact locations and normals into canonical features."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact._checks import check_dim, check_dtype, check_float, check_positive

# For each major axis of a normal, the remaining axes in increasing order.
_OTHER_AXES = {2: ((1,), (0,)), 3: ((1, 2), (0, 2), (0, 1))}


@dataclass(frozen=True)
class FeatureGrid:
    r"""Canonical quantization of contact locations (tolerance ``δ_r``) and normals (``δ_θ``).

    A contact is reduced to two integer keys in the object frame:

    * **location cell** ``c ∈ ℤ^d``: ``c_i = ⌊p_i / s + ½⌋`` with cell side
      ``s = 2 δ_r / √d``, i.e. the cube ``[(c_i − ½) s, (c_i + ½) s)`` per coordinate (half-open:
      a coordinate exactly on a boundary goes to the upper cell). The cell's canonical location
      is ``c s``; every point of the cell lies within ``δ_r`` of it (the cube's circumradius is
      ``s √d / 2 = δ_r``), so two contacts in one cell are at most ``2 δ_r`` apart.
    * **direction bin** ``(f, b_1, …, b_{d−1})`` from a cube map: the face ``f = 2 i + [n_i < 0]``
      of the normal's largest-magnitude axis ``i`` (ties go to the lowest axis), and the
      gnomonic coordinates ``u_j = n_j / |n_i| ∈ [−1, 1]`` of the other axes binned into ``N``
      equal bins, ``b_j = min(⌊(u_j + 1) / g⌋, N − 1)`` with ``g = 2 / N``.
      ``N = ⌈√(d − 1) / δ_θ⌉``, rounded up to an odd number so that the object's axes are bin
      centres. The angle between a normal and its bin's canonical direction is at most the
      distance from the bin centre in the tangent plane, ``g √(d − 1) / 2 ≤ δ_θ``.

    So "inside the tolerance" means, precisely: a feature collects the contacts whose locations
    lie within ``δ_r`` of one canonical location and whose normals lie within ``δ_θ`` of one
    canonical direction. Anything that keeps every contact inside its cell and bin — a
    permutation of slots, a rigid motion of the whole scene, a perturbation smaller than the
    distance to the cell boundary — leaves the keys unchanged. A contact at a cell's centre
    may move by ``s / 2 = δ_r / √d`` in any direction; a normal at a face centre may turn by
    ``atan(g / 2)``, less towards the cube's edges, where bins subtend smaller angles. Two
    contacts closer than ``δ_r`` can still straddle a boundary and form two features: every
    canonical (hashable, order-free) discretization has boundaries; these are the boundaries
    of this grid, fixed in the object frame.

    Attributes:
        dim: 2 (planar) or 3 (spatial).
        radius: location tolerance ``δ_r`` in metres, ``> 0``.
        angle: normal-direction tolerance ``δ_θ`` in radians, ``> 0``.
    """

    dim: int
    radius: float
    angle: float

    def __post_init__(self) -> None:
        check_dim("dim", self.dim)
        object.__setattr__(self, "radius", check_positive("radius", self.radius))
        object.__setattr__(self, "angle", check_positive("angle", self.angle))

    @property
    def cell_size(self) -> float:
        """Side ``s = 2 δ_r / √d`` of a location cell, metres."""
        return 2.0 * self.radius / math.sqrt(self.dim)

    @property
    def bins(self) -> int:
        """Number ``N`` (odd) of direction bins along each gnomonic axis of a cube face."""
        n = math.ceil(math.sqrt(self.dim - 1) / self.angle)
        return n if n % 2 else n + 1

    @property
    def num_directions(self) -> int:
        """Number of direction bins on the whole circle or sphere, ``2 d N^(d−1)``."""
        return 2 * self.dim * math.prod([self.bins] * (self.dim - 1))

    def quantize(self, points: Tensor, normals: Tensor) -> tuple[Tensor, Tensor]:
        """Location cells and direction bins of contacts, vectorized.

        Args:
            points: ``(*B, d)`` contact points in the object frame.
            normals: ``(*B, d)`` unit contact normals in the object frame (zero normals give
                an arbitrary bin; mask them out).

        Returns:
            ``cells (*B, d)`` long location cells and ``directions (*B, d)`` long direction
            keys ``(f, b_1, …, b_{d−1})``.

        Raises:
            ValueError: the tensors are not finite float ``(*B, d)`` tensors of equal shape.
        """
        d = self.dim
        check_float("points", points, trailing=(d,), what=f"(*B, {d})")
        check_float("normals", normals, trailing=(d,), what=f"(*B, {d})")
        if normals.shape != points.shape:
            raise ValueError(f"normals must have shape {tuple(points.shape)}, got {normals.shape}")
        cells = _to_long("points", torch.floor(points / self.cell_size + 0.5))
        axis = normals.abs().argmax(dim=-1, keepdim=True)
        major = normals.gather(-1, axis)
        others = torch.tensor(_OTHER_AXES[d], device=normals.device)[axis.squeeze(-1)]
        scale = torch.where(major == 0, torch.ones_like(major), major.abs())
        u = normals.gather(-1, others) / scale
        g = 2.0 / self.bins
        bins = torch.floor((u + 1.0) / g).long().clamp(0, self.bins - 1)
        face = 2 * axis + (major < 0).long()
        return cells, torch.cat([face, bins], dim=-1)

    def location(self, cells: Tensor, *, dtype: torch.dtype | None = None) -> Tensor:
        """Canonical locations ``c s`` of location cells.

        Args:
            cells: ``(*B, d)`` long location cells.
            dtype: floating dtype of the result (default: torch's default dtype).

        Returns:
            ``(*B, d)`` cell centres in the object frame, metres.
        """
        check_dtype("cells", cells, torch.long, f"(*B, {self.dim})")
        return cells.to(dtype or torch.get_default_dtype()) * self.cell_size

    def direction(self, directions: Tensor, *, dtype: torch.dtype | None = None) -> Tensor:
        """Canonical unit normals (bin centres) of direction keys.

        Args:
            directions: ``(*B, d)`` long direction keys ``(f, b_1, …, b_{d−1})``.
            dtype: floating dtype of the result (default: torch's default dtype).

        Returns:
            ``(*B, d)`` unit normals in the object frame.

        Raises:
            ValueError: a key lies outside the grid.
        """
        d, n = self.dim, self.bins
        check_dtype("directions", directions, torch.long, f"(*B, {d})")
        face, bins = directions[..., 0], directions[..., 1:]
        if bool(((face < 0) | (face >= 2 * d)).any()) or bool(((bins < 0) | (bins >= n)).any()):
            raise ValueError(f"directions must hold faces in [0, {2 * d}) and bins in [0, {n})")
        dtype = dtype or torch.get_default_dtype()
        axis = (face // 2).unsqueeze(-1)
        sign = (1 - 2 * (face % 2)).to(dtype).unsqueeze(-1)
        others = torch.tensor(_OTHER_AXES[d], device=directions.device)[axis.squeeze(-1)]
        u = -1.0 + (bins.to(dtype) + 0.5) * (2.0 / n)
        vector = torch.zeros(directions.shape, dtype=dtype, device=directions.device)
        vector = vector.scatter(-1, axis, sign).scatter(-1, others, u)
        unit: Tensor = vector / torch.linalg.vector_norm(vector, dim=-1, keepdim=True)
        return unit


#: Keys beyond this magnitude would overflow int64 (or lose precision in the float).
_LARGEST_KEY = 2.0**52


def _to_long(name: str, keys: Tensor) -> Tensor:
    """Integer-valued float ``keys`` as long, refusing values that do not fit exactly."""
    if keys.numel() and float(keys.abs().max()) > _LARGEST_KEY:
        raise ValueError(f"{name} is too large for the grid: a key exceeds 2**52 cells")
    return keys.long()
