"""Per-slot mode vectors of a simulated scene: readable labels, touching bodies, table rows."""

from __future__ import annotations

import torch
from torch import Tensor

from torchcontact._checks import describe
from torchcontact.geometry import HalfPlane
from torchcontact.sim import Scene, SlotGroup


def _partner_groups(scene: Scene, body: str) -> list[tuple[int, SlotGroup]]:
    """``(partner index, slot group)`` of every slot group in which ``body`` takes part."""
    names = [b.name for b in scene.bodies]
    if body not in names:
        raise ValueError(f"body: expected one of {names}, got {body!r}")
    index = names.index(body)
    return [
        (group.other if group.receiver == index else group.receiver, group)
        for group in scene.slot_groups
        if index in (group.receiver, group.other)
    ]


def mode_label(scene: Scene, mode: Tensor, *, body: str) -> str:
    """Readable contact state of ``body`` in one ``(L,)`` per-slot mode vector of ``scene``.

    Each body touching ``body`` is named with its contacts' states (slot mode 1: ``stick``,
    2 or 3: ``slide``), the latter with the slip direction (``→`` or ``←``, world x) on a static
    half-plane such as a table (its tangent is known; a polygon's depends on the geometry).
    Equal states are counted (``"table 2 slide→"``), different ones joined
    (``"table stick+slide←"``); partners are listed in the order of ``scene.bodies`` and
    ``"free"`` stands for no contact.

    Args:
        scene: the simulated scene (``L = scene.num_slots``).
        mode: ``(L,)`` long per-slot modes (0 separated, 1 sticking, 2 friction along the
            slot's ``+t``, 3 along ``−t``; see :class:`~torchcontact.sim.Simulator`).
        body: name of the body whose contacts are described.

    Returns:
        E.g. ``"table 2 stick, right 1 slide"``.

    Raises:
        ValueError: ``mode`` is not an ``(L,)`` integer tensor, or ``body`` is not in the scene.
    """
    _check_modes(scene, mode, single=True)
    states: dict[int, list[str]] = {}
    for partner, group in _partner_groups(scene, body):
        shape = scene.bodies[partner].shape
        for slot in mode[group.start : group.start + group.count].tolist():
            if slot == 0:
                continue
            state = "stick" if slot == 1 else "slide"
            if slot > 1 and isinstance(shape, HalfPlane):
                # Friction along +t (mode 2) or -t (mode 3), t = normal turned by +90°; the
                # slip opposes it.
                tangent_x = -float(shape.normal[1])
                slip_x = -tangent_x if slot == 2 else tangent_x
                state += "→" if slip_x > 0 else "←"
            states.setdefault(partner, []).append(state)
    parts = []
    for partner, names in sorted(states.items()):
        kinds = sorted(set(names))
        text = f"{len(names)} {kinds[0]}" if len(kinds) == 1 else "+".join(sorted(names))
        parts.append(f"{scene.bodies[partner].name} {text}")
    return ", ".join(parts) if parts else "free"


def touch_codes(scene: Scene, mode: Tensor, *, body: str) -> Tensor:
    """Which bodies touch ``body``: a bit code per ``(*B, L)`` per-slot mode vector.

    Args:
        scene: the simulated scene (``L = scene.num_slots``).
        mode: ``(*B, L)`` long per-slot modes.
        body: name of the body whose partners are coded.

    Returns:
        ``(*B,)`` long; bit ``i`` is set where a slot shared by ``body`` and
        ``scene.bodies[i]`` is in contact (mode ``>= 1``).

    Raises:
        ValueError: ``mode`` is not a ``(*B, L)`` integer tensor, or ``body`` is not in the
            scene.
    """
    _check_modes(scene, mode, single=False)
    code = torch.zeros(mode.shape[:-1], dtype=torch.long, device=mode.device)
    for partner, group in _partner_groups(scene, body):
        touching = (mode[..., group.start : group.start + group.count] > 0).any(-1)
        code = code | (touching.to(torch.long) << partner)
    return code


def mode_ids(mode: Tensor, table: Tensor) -> Tensor:
    """The row of a mode table holding each per-slot mode vector.

    Args:
        mode: ``(*B, L)`` long per-slot modes.
        table: ``(K, L)`` long distinct mode vectors (e.g. from
            :func:`~torchcontact.filters.collect_modes`).

    Returns:
        ``(*B,)`` long row of ``table`` equal to each mode vector; ``K`` where none is.

    Raises:
        ValueError: ``mode`` or ``table`` is not an integer tensor, or their ``L`` differ.
    """
    for name, value in (("mode", mode), ("table", table)):
        if not isinstance(value, Tensor) or value.is_floating_point() or value.ndim < 1:
            raise ValueError(f"{name}: expected an integer tensor, got {describe(value)}")
    if table.ndim != 2 or table.shape[-1] != mode.shape[-1]:
        raise ValueError(f"table: expected shape (K, {mode.shape[-1]}), got {tuple(table.shape)}")
    match = (mode[..., None, :] == table).all(-1)  # (*B, K)
    found = match.any(-1)
    return torch.where(found, match.to(torch.long).argmax(-1), table.shape[0])


def _check_modes(scene: Scene, mode: object, *, single: bool) -> None:
    """Raise ``ValueError`` unless ``mode`` is an integer ``(L,)`` (``single``) or ``(*B, L)``
    tensor of ``scene``'s ``L`` slots."""
    L = scene.num_slots
    if (
        not isinstance(mode, Tensor)
        or mode.is_floating_point()
        or mode.dtype == torch.bool
        or mode.ndim < 1
        or mode.shape[-1] != L
        or (single and mode.ndim != 1)
    ):
        what = f"({L},)" if single else f"(*B, {L})"
        raise ValueError(f"mode: expected an integer {what} tensor, got {describe(mode)}")
