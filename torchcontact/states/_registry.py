"""Registries: hashable states ↔ stable integer ids, in first-seen order, saved as JSON."""

from __future__ import annotations

import json
from collections.abc import Hashable, Iterable, Iterator
from dataclasses import asdict
from pathlib import Path
from typing import Any, Generic, TypeVar

import torch
from torch import Tensor

from torchcontact._checks import check_field, check_int, parse_json, read_text_file
from torchcontact.states._contact_set import ContactSet
from torchcontact.states._contact_state import ContactState, contact_states
from torchcontact.states._grid import FeatureGrid

S = TypeVar("S", bound=Hashable)


def _check_hashable(name: str, state: S) -> S:
    try:
        hash(state)
    except TypeError:
        raise ValueError(f"{name} must be hashable, got {type(state).__name__}") from None
    return state


_FORMAT = "torchcontact.ContactStateRegistry"


class UnknownStateError(KeyError, ValueError):
    """A state that is not in a :class:`StateTable` was looked up.

    A ``ValueError`` like every bad argument of the library, and a ``KeyError`` like a failed
    mapping lookup.
    """

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


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
        """The id of ``state``, giving it the next free id if it is new.

        Raises:
            ValueError: ``state`` is not hashable.
        """
        _check_hashable("state", state)
        index = self._ids.get(state)
        if index is None:
            index = self._ids[state] = len(self._states)
            self._states.append(state)
        return index

    def index(self, state: S) -> int:
        """The id of a known ``state``.

        Raises:
            UnknownStateError: ``state`` is unknown (a ``KeyError`` and a ``ValueError``).
        """
        index = self._ids.get(_check_hashable("state", state))
        if index is None:
            raise UnknownStateError(f"state is unknown: unknown state {state!r}")
        return index

    def get(self, state: S, default: int = -1) -> int:
        """The id of ``state``, or ``default`` if it is unknown.

        Raises:
            ValueError: ``state`` is not hashable.
        """
        return self._ids.get(_check_hashable("state", state), default)

    def __getitem__(self, index: int) -> S:
        """The state with id ``index``.

        Raises:
            ValueError: ``index`` is not an int in ``[0, len(self))``.
        """
        return self._states[check_int("index", index, low=0, high=len(self._states))]

    def __contains__(self, state: object) -> bool:
        try:
            return state in self._ids
        except TypeError:  # unhashable: never a key
            return False

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
            ValueError: ``text`` is not JSON or not a saved contact-state registry; the
                message names the field at fault.
        """
        data: Any = parse_json("text", text)
        if not isinstance(data, dict) or data.get("format") != _FORMAT:
            raise ValueError(f"text is not a {_FORMAT} JSON document")
        grid = check_field("text", data, "grid")
        keys = ("dim", "radius", "angle")
        if not isinstance(grid, dict) or sorted(grid) != sorted(keys):
            raise ValueError(f"text field 'grid' must be an object with keys {keys}, got {grid!r}")
        try:
            feature_grid = FeatureGrid(**grid)
        except ValueError as error:
            raise ValueError(f"text field 'grid': {error}") from None
        entries = check_field("text", data, "states")
        if not isinstance(entries, list):
            raise ValueError(f"text field 'states' must be a list, got {type(entries).__name__}")
        states = []
        for k, entry in enumerate(entries):
            try:
                states.append(ContactState.from_json(entry))
            except ValueError as error:
                raise ValueError(f"text field 'states'[{k}]: {error}") from None
        if len(set(states)) != len(states):
            raise ValueError("text field 'states' must hold distinct states")
        return cls(feature_grid, states)

    def save(self, path: str | Path) -> None:
        """Write :meth:`to_json` to ``path``."""
        Path(path).write_text(self.to_json())

    @classmethod
    def load(cls, path: str | Path) -> ContactStateRegistry:
        """Read a registry written by :meth:`save`.

        Raises:
            ValueError: ``path`` cannot be read, or see :meth:`from_json`.
        """
        return cls.from_json(read_text_file("path", path))
