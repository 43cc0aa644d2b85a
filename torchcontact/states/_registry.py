"""Registries: hashable states ↔ stable integer ids, in first-seen order, saved as JSON."""

from __future__ import annotations

import json
from collections.abc import Hashable, Iterable, Iterator
from dataclasses import asdict
from pathlib import Path
from typing import Any, Generic, TypeVar

import torch
from torch import Tensor

from torchcontact.states._contact_set import ContactSet
from torchcontact.states._contact_state import ContactState, contact_states
from torchcontact.states._grid import FeatureGrid

S = TypeVar("S", bound=Hashable)

_FORMAT = "torchcontact.ContactStateRegistry"


class StateTable(Generic[S]):
    """A bijection between hashable states and the ids ``0, 1, …`` in first-seen order.

    Ids never change once given: adding a state appends it.

    Args:
        states: initial states, given ids in order (duplicates keep their first id).
    """

    def __init__(self, states: Iterable[S] = ()) -> None:
        self._ids: dict[S, int] = {}
        self._states: list[S] = []
        for state in states:
            self.add(state)

    def add(self, state: S) -> int:
        """The id of ``state``, giving it the next free id if it is new."""
        index = self._ids.get(state)
        if index is None:
            index = self._ids[state] = len(self._states)
            self._states.append(state)
        return index

    def index(self, state: S) -> int:
        """The id of a known ``state``.

        Raises:
            KeyError: ``state`` is unknown.
        """
        try:
            return self._ids[state]
        except KeyError:
            raise KeyError(f"unknown state {state!r}") from None

    def get(self, state: S, default: int = -1) -> int:
        """The id of ``state``, or ``default`` if it is unknown."""
        return self._ids.get(state, default)

    def __getitem__(self, index: int) -> S:
        """The state with id ``index`` (``IndexError`` if there is none)."""
        if not 0 <= index < len(self._states):
            raise IndexError(f"id {index} out of range [0, {len(self._states)})")
        return self._states[index]

    def __contains__(self, state: object) -> bool:
        return state in self._ids

    def __len__(self) -> int:
        return len(self._states)

    def __iter__(self) -> Iterator[S]:
        return iter(self._states)

    @property
    def states(self) -> tuple[S, ...]:
        """All states, indexed by id."""
        return tuple(self._states)


class ContactStateRegistry(StateTable[ContactState]):
    """Contact states ↔ stable integer ids for one :class:`FeatureGrid`.

    Ids are given in first-seen order and never change, so a registry saved with
    :meth:`to_json` and loaded with :meth:`from_json` maps the same states to the same ids.

    Args:
        grid: the quantization that defines the states' features.
        states: initial states, given ids in order.
    """

    def __init__(self, grid: FeatureGrid, states: Iterable[ContactState] = ()) -> None:
        if not isinstance(grid, FeatureGrid):
            raise ValueError(f"grid must be a FeatureGrid, got {type(grid).__name__}")
        self.grid = grid
        super().__init__(states)

    def ids(self, contacts: ContactSet, *, add: bool = True) -> Tensor:
        """Contact-state ids of a batch of contact sets.

        The states come from :func:`contact_states` (vectorized quantization; a Python loop
        over the batch builds and looks up the hashable states).

        Args:
            contacts: the contacts, batch shape ``*B``.
            add: register unseen states (``True``) or give them id ``-1`` (``False``).

        Returns:
            ``(*B,)`` long ids, on the contacts' device.
        """
        states = contact_states(contacts, self.grid)
        ids = [self.add(s) if add else self.get(s) for s in states]
        return torch.tensor(ids, dtype=torch.long, device=contacts.points.device).reshape(
            contacts.batch_shape
        )

    def to_json(self) -> str:
        """The grid and the states in id order, as a JSON string."""
        data = {
            "format": _FORMAT,
            "version": 1,
            "grid": asdict(self.grid),
            "states": [s.to_json() for s in self],
        }
        return json.dumps(data)

    @classmethod
    def from_json(cls, text: str) -> ContactStateRegistry:
        """Inverse of :meth:`to_json`.

        Raises:
            ValueError: ``text`` is not a saved contact-state registry.
        """
        data: Any = json.loads(text)
        if not isinstance(data, dict) or data.get("format") != _FORMAT:
            raise ValueError(f"text is not a {_FORMAT} JSON document")
        states = [ContactState.from_json(s) for s in data["states"]]
        return cls(FeatureGrid(**data["grid"]), states)

    def save(self, path: str | Path) -> None:
        """Write :meth:`to_json` to ``path``."""
        Path(path).write_text(self.to_json())

    @classmethod
    def load(cls, path: str | Path) -> ContactStateRegistry:
        """Read a registry written by :meth:`save`."""
        return cls.from_json(Path(path).read_text())
