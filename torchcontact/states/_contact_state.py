"""Contact states: canonical sets of contact features, computed from batched contact tensors."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from torchcontact._checks import check_instance
from torchcontact.states._contact_set import PARTNER_KINDS, ContactSet, PartnerKind
from torchcontact.states._grid import FeatureGrid


@dataclass(frozen=True, order=True)
class ContactFeature:
    """One feature of a contact state: a cluster of contacts with one partner kind.

    Attributes:
        kind: what the object touches (:class:`PartnerKind`; strings are converted).
        cell: location cell in the object frame, ``d`` ints (see :class:`FeatureGrid`).
        direction: direction key ``(f, b_1, …, b_{d−1})`` of the contact normals.
        sliding: ``True`` if any contact of the feature slides, ``False`` if all stick.
    """

    kind: PartnerKind
    cell: tuple[int, ...]
    direction: tuple[int, ...]
    sliding: bool

    def __post_init__(self) -> None:
        if self.kind not in tuple(PartnerKind):
            kinds = [k.value for k in PartnerKind]
            raise ValueError(f"kind must be one of {kinds}, got {self.kind!r}")
        object.__setattr__(self, "kind", PartnerKind(self.kind))
        for name in ("cell", "direction"):
            if not isinstance(getattr(self, name), (tuple, list)):
                raise ValueError(f"{name} must be a tuple of ints, got {getattr(self, name)!r}")
        cell, direction = tuple(self.cell), tuple(self.direction)
        if len(cell) not in (2, 3) or len(direction) != len(cell):
            raise ValueError(
                f"cell and direction must both hold d = 2 or 3 ints, got {cell} and {direction}"
            )
        if not all(isinstance(i, int) and not isinstance(i, bool) for i in cell + direction):
            raise ValueError(f"cell and direction must hold ints, got {cell} and {direction}")
        if not isinstance(self.sliding, bool):
            raise ValueError(f"sliding must be a bool, got {self.sliding!r}")
        object.__setattr__(self, "cell", cell)
        object.__setattr__(self, "direction", direction)

    def to_json(self) -> list[Any]:
        """``[kind, cell, direction, sliding]`` with JSON-native types."""
        return [self.kind.value, list(self.cell), list(self.direction), self.sliding]

    @classmethod
    def from_json(cls, data: Any) -> ContactFeature:
        """Inverse of :meth:`to_json`.

        Raises:
            ValueError: ``data`` is not ``[kind, cell, direction, sliding]`` of a feature.
        """
        if not isinstance(data, (list, tuple)) or len(data) != 4:
            raise ValueError(f"data must be [kind, cell, direction, sliding], got {data!r}")
        kind, cell, direction, sliding = data
        return cls(kind, cell, direction, sliding)


@dataclass(frozen=True, order=True)
class ContactState:
    """A contact state: the set of features through which the object touches its partners.

    A contact state (Section III of the seed paper) groups contacts whose locations lie within
    ``δ_r`` and whose normals agree within ``δ_θ`` into features, and records whether each
    feature sticks or slides. The features are kept sorted (partner kind first, environment
    before robot), so two states with the same features are equal and hash alike whatever order
    the features were given in. The empty state (no contact) is ``ContactState(())``.

    Attributes:
        features: the features; at most one per ``(kind, cell, direction)``.

    References:
        Seed paper, Section III and Fig. 2. J. Xiao and X. Ji, "On automatic generation of
        high-level contact state space", IJRR 20(7), 2001 (the contact-state graph).
    """

    features: tuple[ContactFeature, ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.features, (tuple, list)) or not all(
            isinstance(f, ContactFeature) for f in self.features
        ):
            raise ValueError(f"features must be a tuple of ContactFeature, got {self.features!r}")
        features = tuple(sorted(self.features))
        keys = [(f.kind, f.cell, f.direction) for f in features]
        if len(set(keys)) != len(keys):
            raise ValueError("features must hold at most one feature per (kind, cell, direction)")
        if len({len(f.cell) for f in features}) > 1:
            raise ValueError("features must all have the same dimension d")
        object.__setattr__(self, "features", features)

    @property
    def environment(self) -> tuple[ContactFeature, ...]:
        """Features of contacts with the environment."""
        return tuple(f for f in self.features if f.kind is PartnerKind.ENVIRONMENT)

    @property
    def robot(self) -> tuple[ContactFeature, ...]:
        """Features of contacts with the robot."""
        return tuple(f for f in self.features if f.kind is PartnerKind.ROBOT)

    def to_json(self) -> list[Any]:
        """The features as JSON-native lists (see :meth:`ContactFeature.to_json`)."""
        return [f.to_json() for f in self.features]

    @classmethod
    def from_json(cls, data: Any) -> ContactState:
        """Inverse of :meth:`to_json`.

        Raises:
            ValueError: ``data`` is not a list of features.
        """
        if not isinstance(data, list):
            raise ValueError(f"data must be a list of features, got {type(data).__name__}")
        return cls(tuple(ContactFeature.from_json(f) for f in data))

    def __str__(self) -> str:
        """A short label: features per kind, e.g. ``"E2st R1sl"`` (``"free"`` if empty)."""
        parts = []
        for kind, features in (("E", self.environment), ("R", self.robot)):
            slide = sum(f.sliding for f in features)
            stick = len(features) - slide
            text = (f"{stick}st" if stick else "") + (f"{slide}sl" if slide else "")
            parts += [kind + text] if text else []
        return " ".join(parts) or "free"


def contact_states(contacts: ContactSet, grid: FeatureGrid) -> list[ContactState]:
    """The contact state of every batch element.

    Each active slot (a real slot with mode ``>= 1``) becomes a key ``(kind, cell, direction)``
    by :meth:`FeatureGrid.quantize` in the object frame; slots with equal keys form one feature,
    which slides if any of its slots slides. The quantization and the grouping (``torch.unique``
    over ``(batch, key)`` rows) are vectorized; building the hashable :class:`ContactState`
    objects loops over the batch in Python, ``O(prod(*B) + number of features)``.

    Args:
        contacts: the contacts, ``points (*B, K, d)`` and friends.
        grid: the quantization; ``grid.dim`` must equal ``contacts.dim``.

    Returns:
        ``prod(*B)`` contact states in row-major (C) order of the batch shape.

    Raises:
        ValueError: the grid's dimension differs from the contacts'.
    """
    check_instance("contacts", contacts, ContactSet)
    check_instance("grid", grid, FeatureGrid)
    if grid.dim != contacts.dim:
        raise ValueError(f"grid.dim must equal contacts.dim = {contacts.dim}, got {grid.dim}")
    points, normals = contacts.object_frame()
    cells, directions = grid.quantize(points, normals)
    B, K, d = math.prod(contacts.batch_shape), contacts.num_slots, contacts.dim
    batch = torch.arange(B, device=points.device).unsqueeze(-1).expand(B, K)
    kind = contacts.kind_code.expand(B, K)
    columns = (batch.unsqueeze(-1), kind.unsqueeze(-1), cells.reshape(B, K, d))
    rows = torch.cat([*columns, directions.reshape(B, K, d)], dim=-1)
    active = contacts.active.reshape(B, K)
    keys, inverse = torch.unique(rows[active], dim=0, return_inverse=True)
    sliding = torch.zeros(keys.shape[0], dtype=torch.long, device=keys.device)
    sliding = sliding.scatter_reduce(
        0, inverse, contacts.sliding.reshape(B, K)[active].long(), "amax"
    )
    grouped: list[list[ContactFeature]] = [[] for _ in range(B)]
    for key, slide in zip(keys.tolist(), sliding.tolist(), strict=True):
        grouped[key[0]].append(
            ContactFeature(
                PARTNER_KINDS[key[1]], tuple(key[2 : 2 + d]), tuple(key[2 + d :]), bool(slide)
            )
        )
    return [ContactState(tuple(features)) for features in grouped]
