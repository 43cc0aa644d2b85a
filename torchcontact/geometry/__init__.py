"""Geometry: planar polygons, half-planes, rigid transforms, quaternions and contact slots.

``TIE_TOLERANCE`` is the relative tolerance (of the longest edge) within which the slot
generation (:func:`polygon_slots`) takes two edges as equally close; simulators that find the
closest edges themselves use it too.
"""

from torchcontact.geometry._quaternion import (
    quat_conj,
    quat_exp,
    quat_log,
    quat_mul,
    quat_to_matrix,
)
from torchcontact.geometry._se2 import (
    cross2,
    perpendicular,
    point_velocity,
    rotation_matrix,
    transform_points,
    wrap_angle,
    wrench_row,
)
from torchcontact.geometry._shapes import HalfPlane, Polygon
from torchcontact.geometry._slots import (
    TIE_TOLERANCE,
    SlotGeometry,
    concat_slots,
    halfplane_slots,
    polygon_slots,
)

__all__ = [
    "TIE_TOLERANCE",
    "HalfPlane",
    "Polygon",
    "SlotGeometry",
    "concat_slots",
    "cross2",
    "halfplane_slots",
    "perpendicular",
    "point_velocity",
    "polygon_slots",
    "quat_conj",
    "quat_exp",
    "quat_log",
    "quat_mul",
    "quat_to_matrix",
    "rotation_matrix",
    "transform_points",
    "wrap_angle",
    "wrench_row",
]
