"""Geometry: planar polygons, half-planes, rigid transforms, quaternions and contact slots.

``TIE_TOLERANCE`` is the relative tolerance (of the longest edge) within which the slot
generation (:func:`planar_slots`) takes two edges as equally close.
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
    dot2,
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
    PlanarSlotTable,
    SlotGeometry,
    planar_slot_table,
    planar_slots,
)

__all__ = [
    "TIE_TOLERANCE",
    "HalfPlane",
    "PlanarSlotTable",
    "Polygon",
    "SlotGeometry",
    "cross2",
    "dot2",
    "perpendicular",
    "planar_slot_table",
    "planar_slots",
    "point_velocity",
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
