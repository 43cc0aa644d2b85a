"""Geometry: planar polygons and half-planes, spatial boxes, spheres, capsules and half-spaces,
rigid transforms, quaternions and contact slots.

``TIE_TOLERANCE`` is the relative tolerance (of the longest edge) within which the slot
generation (:func:`planar_slots`) takes two edges as equally close. ``FACE_PREFERENCE`` is the
relative margin by which a box-box separating axis must beat a preferred one
(:func:`spatial_slots`).
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
from torchcontact.geometry._spatial_contact import (
    FACE_PREFERENCE,
    SPATIAL_SLOT_COUNTS,
    SpatialSlotTable,
    slot_witness_points,
    spatial_slot_table,
    spatial_slots,
)
from torchcontact.geometry._spatial_shapes import Box, Capsule, HalfSpace, Sphere

__all__ = [
    "FACE_PREFERENCE",
    "SPATIAL_SLOT_COUNTS",
    "TIE_TOLERANCE",
    "Box",
    "Capsule",
    "HalfPlane",
    "HalfSpace",
    "PlanarSlotTable",
    "Polygon",
    "SlotGeometry",
    "SpatialSlotTable",
    "Sphere",
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
    "slot_witness_points",
    "spatial_slot_table",
    "spatial_slots",
    "transform_points",
    "wrap_angle",
    "wrench_row",
]
