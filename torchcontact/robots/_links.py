"""What a robot's links carry besides their frames: inertias and collision primitives."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact.geometry import Box, Capsule, Sphere, quat_mul
from torchcontact.robots._urdf import UrdfCollision, UrdfInertial, origin_matrix


@dataclass(frozen=True, eq=False)
class LinkInertial:
    """A link's mass properties, in the link frame.

    Attributes:
        link: The link's name.
        mass: Mass in kg.
        com: ``(3,)`` float64 centre of mass in the link frame (m).
        inertia: ``(3, 3)`` float64 inertia about the centre of mass, axes of the link frame
            (kg m²).
    """

    link: str
    mass: float
    com: Tensor
    inertia: Tensor


@dataclass(frozen=True, eq=False)
class LinkShape:
    """A collision primitive fixed to a robot link.

    Attributes:
        link: The link's name.
        shape: A :class:`~torchcontact.geometry.Box`, :class:`~torchcontact.geometry.Sphere` or
            :class:`~torchcontact.geometry.Capsule` (axis = the shape frame's z axis), centred on
            its shape frame.
        pose: ``(7,)`` float64 the shape frame in the link frame: position (m) and unit
            quaternion ``(w, x, y, z)``.
    """

    link: str
    shape: Box | Sphere | Capsule
    pose: Tensor


def rpy_quaternion(rpy: tuple[float, float, float]) -> Tensor:
    """``(4,)`` float64 unit quaternion ``(w, x, y, z)`` of URDF roll-pitch-yaw angles
    (``R = Rz(yaw) Ry(pitch) Rx(roll)``)."""
    halves = [0.5 * torch.tensor(angle, dtype=torch.float64) for angle in rpy]
    elementary = []
    for axis, half in enumerate(halves):
        quaternion = torch.zeros(4, dtype=torch.float64)
        quaternion[0], quaternion[axis + 1] = torch.cos(half), torch.sin(half)
        elementary.append(quaternion)
    roll, pitch, yaw = elementary
    return quat_mul(yaw, quat_mul(pitch, roll))


def link_inertial(element: UrdfInertial) -> LinkInertial:
    """The :class:`LinkInertial` of a parsed ``<inertial>`` (inertia turned into link axes)."""
    ixx, ixy, ixz, iyy, iyz, izz = element.inertia
    principal = torch.tensor(
        [[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]], dtype=torch.float64
    )
    rotation = origin_matrix(element.xyz, element.rpy)[:3, :3]
    return LinkInertial(
        link=element.link,
        mass=element.mass,
        com=torch.tensor(element.xyz, dtype=torch.float64),
        inertia=rotation @ principal @ rotation.T,
    )


def link_shape(element: UrdfCollision) -> LinkShape:
    """The :class:`LinkShape` of a parsed ``<collision>`` (a cylinder is a capsule of that
    radius whose axis segment has the cylinder's length)."""
    shape: Box | Sphere | Capsule
    if element.kind == "box":
        shape = Box(0.5 * torch.tensor(element.size, dtype=torch.float64))
    elif element.kind == "sphere":
        shape = Sphere(element.size[0])
    else:
        shape = Capsule(element.size[0], 0.5 * element.size[1])
    position = torch.tensor(element.xyz, dtype=torch.float64)
    return LinkShape(
        link=element.link, shape=shape, pose=torch.cat([position, rpy_quaternion(element.rpy)])
    )
