"""The contacts of one object at one time step: the input to contact states and tactile sensors."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import Any

import torch
from torch import Tensor

from torchcontact._checks import check_dim, check_dtype, check_float
from torchcontact.states._frames import check_pose, to_body_frame


class PartnerKind(StrEnum):
    """What the object touches through a contact slot: the environment or the robot."""

    ENVIRONMENT = "environment"
    ROBOT = "robot"


#: Partner kinds in their canonical order (the integer code of a kind is its index here).
PARTNER_KINDS = (PartnerKind.ENVIRONMENT, PartnerKind.ROBOT)


@dataclass(frozen=True, eq=False)
class ContactSet:
    """Contacts of one object with its partners at one time step, batched over ``*B``.

    The fields follow the contact solver's conventions: slot ``k`` is *active* (a contact) when
    it is a real slot and its mode is sticking (1) or sliding (``>= 2``), i.e. it carries a
    normal impulse; mode 0 (separated) and padding slots are ignored.

    With ``pose`` given, ``points`` and ``normals`` are in the world frame and
    :meth:`object_frame` maps them into the object's frame; with ``pose=None`` they are
    already in the object frame. Everything derived from a contact set (contact states, tactile
    readings) is computed in the object frame, so it does not change when the whole scene
    (object and contacts together) is rotated or translated.

    Attributes:
        points: ``(*B, K, d)`` contact points (world frame if ``pose`` is given, else object
            frame), ``d = 2`` planar or ``3`` spatial.
        normals: ``(*B, K, d)`` unit contact normals pointing from the partner into the object,
            in the same frame as ``points`` (normalized again in :meth:`object_frame`).
        pn: ``(*B, K)`` normal impulses, ``>= 0``.
        mode: ``(*B, K)`` long contact modes: 0 separated, 1 sticking, ``>= 2`` sliding (along
            a friction direction or, spatial, between two: the codes of
            :mod:`torchcontact.contact`).
        partner: ``(K,)`` long partner id of each slot, an index into ``partner_kind``.
        partner_kind: kind of each partner id (strings ``"environment"`` / ``"robot"`` are
            converted to :class:`PartnerKind`).
        mask: ``(*B, K)`` bool, ``True`` for real slots; ``None`` means all slots are real.
        pose: ``(*B, 3)`` planar ``(x, y, θ)`` or ``(*B, 7)`` spatial ``(p, q_wxyz)`` pose of the
            object in the world frame, or ``None``.

    Construction validates every field and raises ``ValueError`` naming the field at fault.
    Batch shapes must agree exactly (no broadcasting).
    """

    points: Tensor
    normals: Tensor
    pn: Tensor
    mode: Tensor
    partner: Tensor
    partner_kind: Sequence[PartnerKind | str]
    mask: Tensor | None = None
    pose: Tensor | None = None

    def __post_init__(self) -> None:
        points = check_float("points", self.points, trailing=(-1, -1), what="(*B, K, d)")
        dim = check_dim("points.shape[-1]", points.shape[-1])
        batch, K = points.shape[:-2], points.shape[-2]
        slots = f"({', '.join(['*B', *map(str, batch)])}, {K})"
        normals = check_float("normals", self.normals, trailing=(K, dim), what=f"(*B, {K}, {dim})")
        if normals.shape != points.shape or normals.dtype != points.dtype:
            raise ValueError(
                f"normals must match points ({tuple(points.shape)}, {points.dtype}), "
                f"got ({tuple(normals.shape)}, {normals.dtype})"
            )
        pn = check_float("pn", self.pn, trailing=(K,), what=slots)
        if pn.shape != points.shape[:-1]:
            raise ValueError(f"pn must have shape {tuple(points.shape[:-1])}, got {pn.shape}")
        if bool((pn < 0).any()):
            raise ValueError("pn must be >= 0")
        mode = check_dtype("mode", self.mode, torch.long, slots)
        if mode.shape != points.shape[:-1]:
            raise ValueError(f"mode must have shape {tuple(points.shape[:-1])}, got {mode.shape}")
        if bool((mode < 0).any()):
            raise ValueError("mode must be >= 0 (0 separated, 1 sticking, >= 2 sliding)")
        kinds = self._check_partners(K)
        mask = self.mask
        if mask is None:
            mask = torch.ones(points.shape[:-1], dtype=torch.bool, device=points.device)
        check_dtype("mask", mask, torch.bool, slots)
        if mask.shape != points.shape[:-1]:
            raise ValueError(f"mask must have shape {tuple(points.shape[:-1])}, got {mask.shape}")
        if self.pose is not None:
            pose = check_pose("pose", self.pose, dim)
            if pose.shape[:-1] != batch or pose.dtype != points.dtype:
                raise ValueError(
                    f"pose must have batch shape {tuple(batch)} and dtype {points.dtype}, "
                    f"got {tuple(pose.shape)} and {pose.dtype}"
                )
        norms = torch.linalg.vector_norm(normals, dim=-1)
        if bool(((norms == 0) & mask & (mode > 0)).any()):
            raise ValueError("normals must be non-zero at active slots")
        object.__setattr__(self, "partner_kind", kinds)
        object.__setattr__(self, "mask", mask)

    def _check_partners(self, K: int) -> tuple[PartnerKind, ...]:
        try:
            kinds = tuple(PartnerKind(kind) for kind in self.partner_kind)
        except (TypeError, ValueError) as error:
            raise ValueError(
                f"partner_kind must hold 'environment' or 'robot', got {self.partner_kind!r}"
            ) from error
        partner = check_dtype("partner", self.partner, torch.long, f"({K},)")
        if partner.shape != (K,):
            raise ValueError(f"partner must have shape ({K},), got {tuple(partner.shape)}")
        if K and (int(partner.min()) < 0 or int(partner.max()) >= len(kinds)):
            raise ValueError(
                f"partner ids must lie in [0, {len(kinds)}) (len(partner_kind)), "
                f"got {partner.tolist()}"
            )
        return kinds

    @property
    def dim(self) -> int:
        """Spatial dimension ``d``: 2 planar, 3 spatial."""
        return int(self.points.shape[-1])

    @property
    def batch_shape(self) -> torch.Size:
        """The leading batch shape ``*B``."""
        return self.points.shape[:-2]

    @property
    def num_slots(self) -> int:
        """``K``, the number of contact slots."""
        return int(self.points.shape[-2])

    @property
    def active(self) -> Tensor:
        """``(*B, K)`` bool: real slots that stick or slide (carry an impulse)."""
        assert self.mask is not None
        return self.mask & (self.mode >= 1)

    @property
    def sliding(self) -> Tensor:
        """``(*B, K)`` bool: real slots that slide (mode ``>= 2``)."""
        assert self.mask is not None
        return self.mask & (self.mode >= 2)

    @property
    def kind_code(self) -> Tensor:
        """``(K,)`` long: the partner kind of each slot as its index in :data:`PARTNER_KINDS`."""
        codes = [PARTNER_KINDS.index(PartnerKind(kind)) for kind in self.partner_kind]
        table = torch.tensor(codes, dtype=torch.long, device=self.partner.device)
        return table[self.partner]

    def __getitem__(self, index: Any) -> ContactSet:
        """Index the batch dimensions (slot and coordinate dimensions are kept).

        Raises:
            ValueError: ``index`` is out of range or not a valid index of the batch.
        """
        assert self.mask is not None
        batch = torch.empty(self.batch_shape, dtype=torch.bool, device="meta")
        try:
            batch[index]
        except (IndexError, TypeError, RuntimeError) as error:
            shape = tuple(self.batch_shape)
            raise ValueError(
                f"index {index!r} is not valid for batch shape {shape} ({error})"
            ) from None
        return replace(
            self,
            points=self.points[index],
            normals=self.normals[index],
            pn=self.pn[index],
            mode=self.mode[index],
            mask=self.mask[index],
            pose=None if self.pose is None else self.pose[index],
        )

    def object_frame(self) -> tuple[Tensor, Tensor]:
        """Contact points and unit normals in the object frame.

        Returns:
            ``points (*B, K, d)`` and ``normals (*B, K, d)`` in the object frame; normals are
            normalized (zero normals of inactive slots stay zero).
        """
        points, normals = self.points, self.normals
        if self.pose is not None:
            points, normals = to_body_frame(points, normals, self.pose)
        norms = torch.linalg.vector_norm(normals, dim=-1, keepdim=True)
        return points, torch.where(norms > 0, normals / norms, normals)
