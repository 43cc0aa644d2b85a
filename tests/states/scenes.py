"""Box scenes for the contact-state tests, and slow reference implementations.

The box (half extents ``(A, B)``) rests on the ground ``y = 0``; its slots come from
:func:`planar_box_contacts`: four corners (environment) and a finger (robot).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from torchcontact.states import (
    ContactFeature,
    ContactSet,
    ContactState,
    PartnerKind,
    planar_box_contacts,
)

A, B = 0.5, 0.25
STICK, SLIDE = 1, 2


def box_step(
    *,
    x: float,
    tip: float = 0.0,
    corner_modes: tuple[int, int] = (STICK, STICK),
    finger: tuple[float, float] | None = None,
) -> tuple[ContactSet, torch.Tensor]:
    """One time step of the box pushed on its left face, batch shape ``()``.

    Args:
        x: world x of the box centre, or of the bottom-right corner when ``tip > 0``.
        tip: clockwise tipping angle about the bottom-right corner; the bottom-left corner
            lifts off (mode 0) and the bottom-right one sticks.
        corner_modes: modes of the bottom corners on flat ground.
        finger: sticking finger contact on the left face, box frame; ``None``: the finger
            waits 0.1 m left of the box without touching.

    Returns:
        The contact set and the finger's world pose ``(3,)`` (oriented like the box).
    """
    theta = -tip
    c, s = math.cos(theta), math.sin(theta)
    if tip > 0:  # the centre is the corner plus the rotated offset from corner to centre
        centre = (x + c * (-A) - s * B, s * (-A) + c * B)
        modes = [0, STICK, 0, 0]
    else:
        centre = (x, B)
        modes = [*corner_modes, 0, 0]
    pose = torch.tensor([*centre, theta])
    point = torch.tensor([-A - 0.1, 0.0] if finger is None else finger)
    contacts = planar_box_contacts(
        pose=pose,
        corner_modes=torch.tensor(modes),
        finger=point,
        finger_normal=torch.tensor([1.0, 0.0]),
        finger_mode=torch.tensor(0 if finger is None else STICK),
    )
    world = torch.tensor([[c, -s], [s, c]]) @ point + pose[:2]
    return contacts, torch.cat([world, pose[2:]])


def stack(sets: list[ContactSet]) -> ContactSet:
    """Stack batch-less contact sets into batch shape ``(len(sets),)``."""
    poses = [c.pose for c in sets]
    return ContactSet(
        points=torch.stack([c.points for c in sets]),
        normals=torch.stack([c.normals for c in sets]),
        pn=torch.stack([c.pn for c in sets]),
        mode=torch.stack([c.mode for c in sets]),
        partner=sets[0].partner,
        partner_kind=sets[0].partner_kind,
        pose=torch.stack([p for p in poses if p is not None]),
    )


def reference_rotation(pose: np.ndarray) -> np.ndarray:
    """Rotation matrix of a planar ``(x, y, θ)`` or spatial ``(p, q_wxyz)`` pose (scipy)."""
    if pose.shape[-1] == 3:
        c, s = math.cos(pose[2]), math.sin(pose[2])
        return np.array([[c, -s], [s, c]])
    return Rotation.from_quat(pose[3:], scalar_first=True).as_matrix()


def reference_keys(
    point: np.ndarray, normal: np.ndarray, *, radius: float, angle: float
) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The FeatureGrid keys of one object-frame contact, written out with Python math."""
    d = len(point)
    side = 2 * radius / math.sqrt(d)
    cell = tuple(math.floor(float(p) / side + 0.5) for p in point)
    n = normal / np.linalg.norm(normal)
    axis = max(range(d), key=lambda i: (abs(n[i]), -i))  # lowest axis wins ties
    bins = math.ceil(math.sqrt(d - 1) / angle)
    bins += 1 - bins % 2
    width = 2.0 / bins
    key = [2 * axis + (1 if n[axis] < 0 else 0)]
    for j in range(d):
        if j != axis:
            u = n[j] / abs(n[axis])
            key.append(min(math.floor((u + 1.0) / width), bins - 1))
    return cell, tuple(key)


def reference_state(
    contacts: ContactSet, index: tuple[int, ...], *, radius: float, angle: float
) -> ContactState:
    """Contact state of batch element ``index``, one contact at a time (NumPy, scipy)."""
    points = contacts.points[index].numpy()
    normals = contacts.normals[index].numpy()
    if contacts.pose is not None:
        pose = contacts.pose[index].numpy()
        R = reference_rotation(pose)
        d = points.shape[-1]
        points = (points - pose[:d]) @ R
        normals = normals @ R
    assert contacts.mask is not None
    features: dict[tuple[Any, ...], bool] = {}
    for k in range(contacts.num_slots):
        mode = int(contacts.mode[index][k])
        if not bool(contacts.mask[index][k]) or mode == 0:
            continue
        kind = PartnerKind(contacts.partner_kind[int(contacts.partner[k])])
        cell, direction = reference_keys(points[k], normals[k], radius=radius, angle=angle)
        key = (kind, cell, direction)
        features[key] = features.get(key, False) or mode >= 2
    return ContactState(tuple(ContactFeature(*key, sliding) for key, sliding in features.items()))
