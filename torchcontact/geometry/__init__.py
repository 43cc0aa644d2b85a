"""Geometry: planar polygons, half-planes, rigid transforms, quaternions and contact slots."""

from torchcontact.geometry._quaternion import quat_mul
from torchcontact.geometry._se2 import (
    cross2,
    perpendicular,
    point_velocity,
    rotation_matrix,
    transform_points,
    wrench_row,
)
from torchcontact.geometry._shapes import HalfPlane, Polygon
from torchcontact.geometry._slots import (
    SlotGeometry,
    concat_slots,
    halfplane_slots,
    polygon_slots,
)

__all__ = [
    "HalfPlane",
    "Polygon",
    "SlotGeometry",
    "concat_slots",
    "cross2",
    "halfplane_slots",
    "perpendicular",
    "point_velocity",
    "polygon_slots",
    "quat_mul",
    "rotation_matrix",
    "transform_points",
    "wrench_row",
]
