"""The contacts of one simulated object, from the planar simulator's slot outputs."""

from __future__ import annotations

import torch
from torch import Tensor

from torchcontact.sim import Scene
from torchcontact.states._contact_set import ContactSet, PartnerKind


def object_contacts(
    scene: Scene,
    *,
    body: str,
    q: Tensor,
    points: Tensor,
    normals: Tensor,
    pn: Tensor,
    mode: Tensor,
    active: Tensor,
) -> ContactSet:
    """The contacts of one dynamic body of a simulated scene, as a :class:`ContactSet`.

    Keeps the slots in which ``body`` takes part. In a slot where it is the ``other`` body (a
    vertex of its partner touches one of its edges) the normal is flipped so that it points
    from the partner into ``body``. Kinematic partners are the robot; static and other dynamic
    bodies are the environment. Partner ids are indices into ``scene.bodies``.

    Args:
        scene: the simulated scene.
        body: name of the object (a dynamic body).
        q: ``(*B, Nd, 3)`` dynamic-body poses at the contact time (world frame).
        points: ``(*B, K, 2)`` slot points (world frame), e.g. ``Rollout.points[t]``.
        normals: ``(*B, K, 2)`` slot normals from each slot's ``other`` into its receiver.
        pn: ``(*B, K)`` normal impulses.
        mode: ``(*B, K)`` long contact modes.
        active: ``(*B, K)`` bool slot candidates.

    Returns:
        The contact set of ``body``, world frame, with its pose.
    """
    index = scene.index(body)
    if index not in scene.dynamic:
        raise ValueError(f"body must name a dynamic body, got {body!r}")
    slots: list[int] = []
    signs: list[float] = []
    partners: list[int] = []
    for group in scene.slot_groups:
        if index not in (group.receiver, group.other):
            continue
        receiving = group.receiver == index
        slots.extend(range(group.start, group.start + group.count))
        signs.extend([1.0 if receiving else -1.0] * group.count)
        partners.extend([group.other if receiving else group.receiver] * group.count)
    selection = torch.tensor(slots, dtype=torch.long, device=points.device)
    sign = torch.tensor(signs, dtype=normals.dtype, device=normals.device).unsqueeze(-1)
    kinds = [
        PartnerKind.ROBOT if other.kind == "kinematic" else PartnerKind.ENVIRONMENT
        for other in scene.bodies
    ]
    return ContactSet(
        points=points[..., selection, :],
        normals=sign * normals[..., selection, :],
        pn=pn[..., selection],
        mode=mode[..., selection],
        partner=torch.tensor(partners, dtype=torch.long, device=points.device),
        partner_kind=kinds,
        mask=active[..., selection],
        pose=q[..., scene.dynamic.index(index), :],
    )
