"""Synthetic contacts of a planar box on flat ground, pushed by a finger (tests, tutorials)."""

from __future__ import annotations

import torch
from torch import Tensor

from torchcontact._checks import check_dtype, check_float
from torchcontact.contact import BOX_CORNER_SIGNS
from torchcontact.states._contact_set import ContactSet, PartnerKind
from torchcontact.states._frames import rotation_matrix


def planar_box_contacts(
    *,
    pose: Tensor,
    corner_modes: Tensor,
    finger: Tensor,
    finger_normal: Tensor,
    finger_mode: Tensor,
    half_extents: tuple[float, float] = (0.5, 0.25),
) -> ContactSet:
    """Contacts of planar boxes with the ground ``y = 0`` and with one robot finger.

    The tensors are written out, not simulated: the caller says which corners touch the
    ground and how (``corner_modes``) and where the finger touches. Slots 0–3 are the corners
    in :data:`torchcontact.contact.BOX_CORNER_SIGNS` order (bottom-left, bottom-right,
    top-right, top-left in the body frame) with partner 0 (the environment) and the world
    normal ``+y``; slot 4 is the finger, partner 1 (the robot). Active slots carry a unit
    normal impulse.

    Args:
        pose: ``(*B, 3)`` box poses ``(x, y, θ)`` in the world frame.
        corner_modes: ``(*B, 4)`` long modes of the corners (0 off the ground).
        finger: ``(*B, 2)`` finger contact point in the box frame.
        finger_normal: ``(*B, 2)`` unit normal in the box frame, pointing into the box.
        finger_mode: ``(*B,)`` long mode of the finger contact (0 not touching).
        half_extents: ``(a, b)`` half width and half height, metres.

    Returns:
        The :class:`ContactSet`, ``K = 5``, points and normals in the world frame, ``pose``
        set.

    Raises:
        ValueError: wrong shapes or dtypes.
    """
    pose = check_float("pose", pose, trailing=(3,), what="(*B, 3)")
    batch = pose.shape[:-1]
    dtype, device = pose.dtype, pose.device
    check_dtype("corner_modes", corner_modes, torch.long, "(*B, 4)")
    check_dtype("finger_mode", finger_mode, torch.long, "(*B,)")
    for name, value in (("finger", finger), ("finger_normal", finger_normal)):
        check_float(name, value, trailing=(2,), what="(*B, 2)")
        if value.shape != (*batch, 2):
            raise ValueError(f"{name} must have shape {(*batch, 2)}, got {tuple(value.shape)}")
    if corner_modes.shape != (*batch, 4) or finger_mode.shape != batch:
        raise ValueError(
            f"corner_modes and finger_mode must have shapes {(*batch, 4)} and {tuple(batch)}, "
            f"got {tuple(corner_modes.shape)} and {tuple(finger_mode.shape)}"
        )
    signs = torch.tensor(BOX_CORNER_SIGNS, dtype=dtype, device=device)
    corners = (signs * torch.tensor(half_extents, dtype=dtype, device=device)).expand(*batch, 4, 2)
    body = torch.cat([corners, finger.unsqueeze(-2)], dim=-2)  # (*B, 5, 2)
    R = rotation_matrix(pose, 2)
    points = body @ R.transpose(-1, -2) + pose[..., None, :2]
    up = torch.tensor([0.0, 1.0], dtype=dtype, device=device).expand(*batch, 4, 2)
    pushed = (R @ finger_normal.unsqueeze(-1)).squeeze(-1).unsqueeze(-2)
    mode = torch.cat([corner_modes, finger_mode.unsqueeze(-1)], dim=-1)
    return ContactSet(
        points=points,
        normals=torch.cat([up, pushed], dim=-2),
        pn=(mode > 0).to(dtype),
        mode=mode,
        partner=torch.tensor([0, 0, 0, 0, 1], device=device),
        partner_kind=(PartnerKind.ENVIRONMENT, PartnerKind.ROBOT),
        pose=pose,
    )
