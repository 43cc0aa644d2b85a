"""A replay buffer: preallocated tensor storage written as a ring, sampled with a seed."""

from __future__ import annotations

import numbers
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchcontact._checks import (
    FLOAT_DTYPES,
    all_finite,
    check_dtype,
    check_field,
    check_float,
    check_generator_state,
    check_int,
)

_FORMAT = "torchcontact.ReplayBuffer"


class Transitions(NamedTuple):
    """A batch of ``N`` transitions.

    Attributes:
        observations: ``(N, *S)`` observations (belief features) before the action.
        actions: ``(N,)`` long actions.
        rewards: ``(N,)`` rewards.
        next_observations: ``(N, *S)`` observations after the action.
        terminals: ``(N,)`` bool, the episode ended (no bootstrap from the next observation).
    """

    observations: Tensor
    actions: Tensor
    rewards: Tensor
    next_observations: Tensor
    terminals: Tensor


class ReplayBuffer:
    """Fixed-capacity storage of transitions, overwritten oldest first, sampled uniformly.

    The storage is allocated once (``capacity`` rows per field, on ``device``); transition
    number ``t`` (counting from 0 since creation) lives in row ``t mod capacity``. Sampling
    draws row indices with replacement from the buffer's own CPU generator, so a seeded buffer
    gives the same batches, and :meth:`state_dict` / :meth:`load_state_dict` resume it exactly.

    Args:
        capacity: the number of transitions kept, ``>= 1``.
        observation_shape: shape ``S`` of one observation (an int for a vector).
        dtype: floating dtype of observations and rewards (default: torch's default dtype).
        device: storage device.
        seed: seed of the sampling generator, ``>= 0``.

    Raises:
        ValueError: an argument is out of range.
    """

    def __init__(
        self,
        capacity: int,
        observation_shape: int | Sequence[int],
        *,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
        seed: int = 0,
    ) -> None:
        self._capacity = check_int("capacity", capacity, low=1)
        shape = (observation_shape,) if isinstance(observation_shape, int) else observation_shape
        self._shape = tuple(check_int("observation_shape", size, low=0) for size in shape)
        dtype = dtype or torch.get_default_dtype()
        if dtype not in FLOAT_DTYPES:
            raise ValueError(f"dtype must be a floating dtype, got {dtype}")
        self._seed = check_int("seed", seed, low=0)
        factory: dict[str, Any] = {"device": device}
        size = (self._capacity, *self._shape)
        self._observations = torch.zeros(size, dtype=dtype, **factory)
        self._next_observations = torch.zeros(size, dtype=dtype, **factory)
        self._actions = torch.zeros(self._capacity, dtype=torch.long, **factory)
        self._rewards = torch.zeros(self._capacity, dtype=dtype, **factory)
        self._terminals = torch.zeros(self._capacity, dtype=torch.bool, **factory)
        self._position = 0
        self._size = 0
        self._generator = torch.Generator().manual_seed(self._seed)

    @property
    def capacity(self) -> int:
        """The number of transitions kept."""
        return self._capacity

    @property
    def observation_shape(self) -> tuple[int, ...]:
        """``S``, the shape of one observation."""
        return self._shape

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of observations and rewards."""
        return self._observations.dtype

    @property
    def device(self) -> torch.device:
        """Storage device."""
        return self._observations.device

    def __len__(self) -> int:
        return self._size

    def add(
        self,
        *,
        observation: Tensor,
        action: int | Tensor,
        reward: float | Tensor,
        next_observation: Tensor,
        terminal: bool | Tensor,
    ) -> None:
        """Store one transition, or ``N`` at once (later ones overwrite earlier ones when
        ``N`` exceeds the capacity).

        Args:
            observation: ``(*S)`` or ``(N, *S)`` observation before the action.
            action: an int or an integer tensor ``()`` / ``(N,)``, ``>= 0``.
            reward: a number or a tensor ``()`` / ``(N,)``, finite.
            next_observation: like ``observation``, after the action.
            terminal: a bool or a bool tensor ``()`` / ``(N,)``.

        Raises:
            ValueError: a field has the wrong type, shape or value (the message names it).
        """
        obs = self._observation("observation", observation)
        next_obs = self._observation("next_observation", next_observation)
        N = obs.shape[0]
        if next_obs.shape[0] != N:
            raise ValueError(
                f"next_observation must hold {N} observations like observation, "
                f"got {tuple(next_observation.shape)}"
            )
        actions = _as_tensor("action", action, self.device)
        if (
            actions.dtype.is_floating_point
            or actions.dtype.is_complex
            or actions.dtype is torch.bool
        ):
            raise ValueError(f"action must be an integer or integer tensor, got {actions.dtype}")
        actions = self._column("action", actions.long(), N)
        if N and int(actions.min()) < 0:
            raise ValueError("action must be >= 0")
        rewards = _as_tensor("reward", reward, self.device)
        if rewards.dtype.is_complex or rewards.dtype is torch.bool:
            raise ValueError(f"reward must be a real number or tensor, got {rewards.dtype}")
        rewards = self._column("reward", rewards.to(self.dtype), N)
        if not all_finite(rewards):
            raise ValueError("reward contains NaN or inf")
        terminals = _as_tensor("terminal", terminal, self.device)
        if terminals.dtype != torch.bool:
            raise ValueError(f"terminal must be a bool or bool tensor, got {terminals.dtype}")
        terminals = self._column("terminal", terminals, N)
        start, count = self._position, N
        if self._capacity < N:  # only the last `capacity` survive
            start = (self._position + N - self._capacity) % self._capacity
            count = self._capacity
        rows = (start + torch.arange(count, device=self.device)) % self._capacity
        self._observations[rows] = obs[N - count :]
        self._next_observations[rows] = next_obs[N - count :]
        self._actions[rows] = actions[N - count :]
        self._rewards[rows] = rewards[N - count :]
        self._terminals[rows] = terminals[N - count :]
        self._position = (self._position + N) % self._capacity
        self._size = min(self._size + N, self._capacity)

    def _observation(self, name: str, value: object) -> Tensor:
        if not isinstance(value, Tensor) or value.dtype not in FLOAT_DTYPES:
            got = value.dtype if isinstance(value, Tensor) else type(value).__name__
            raise ValueError(f"{name} must be a floating tensor, got {got}")
        shape = tuple(value.shape)
        if shape == self._shape:
            value = value.unsqueeze(0)
        elif len(shape) != len(self._shape) + 1 or shape[1:] != self._shape:
            event = ", ".join(map(str, self._shape))
            raise ValueError(f"{name} must have shape ({event}) or (N, {event}), got {shape}")
        if not all_finite(value):
            raise ValueError(f"{name} contains NaN or inf")
        return value.to(device=self.device, dtype=self.dtype)

    @staticmethod
    def _column(name: str, value: Tensor, size: int) -> Tensor:
        if value.ndim == 0 and size == 1:
            return value.reshape(1)
        if value.shape != (size,):
            raise ValueError(f"{name} must have shape ({size},), got {tuple(value.shape)}")
        return value

    def sample(self, batch_size: int) -> Transitions:
        """``batch_size`` transitions drawn uniformly with replacement.

        Returns:
            :class:`Transitions` of new tensors on the buffer's device.

        Raises:
            ValueError: the buffer is empty or ``batch_size < 1``.
        """
        batch_size = check_int("batch_size", batch_size, low=1)
        if self._size == 0:
            raise ValueError("the buffer is empty: add transitions before sampling")
        rows = torch.randint(self._size, (batch_size,), generator=self._generator)
        rows = rows.to(self.device)
        return Transitions(
            self._observations[rows],
            self._actions[rows],
            self._rewards[rows],
            self._next_observations[rows],
            self._terminals[rows],
        )

    def state_dict(self) -> dict[str, Any]:
        """Storage, ring position, size and sampling-generator state (copies)."""
        return {
            "format": _FORMAT,
            "version": 1,
            "capacity": self._capacity,
            "observation_shape": self._shape,
            "seed": self._seed,
            "observations": self._observations.clone(),
            "actions": self._actions.clone(),
            "rewards": self._rewards.clone(),
            "next_observations": self._next_observations.clone(),
            "terminals": self._terminals.clone(),
            "position": self._position,
            "size": self._size,
            "generator": self._generator.get_state(),
        }

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        """Restore a :meth:`state_dict` of a buffer with the same capacity and observation
        shape (the storage keeps this buffer's dtype and device).

        Raises:
            ValueError: ``state_dict`` is not a replay-buffer state or does not fit.
        """
        if not isinstance(state_dict, Mapping) or state_dict.get("format") != _FORMAT:
            raise ValueError(f"state_dict is not a {_FORMAT} state")

        def field(key: str) -> Any:
            return check_field("state_dict", state_dict, key)

        capacity = check_int("state_dict capacity", field("capacity"), low=1)
        if capacity != self._capacity:
            raise ValueError(f"state_dict has capacity {capacity}, this buffer {self._capacity}")
        shape = field("observation_shape")
        if not isinstance(shape, (tuple, list)) or tuple(shape) != self._shape:
            raise ValueError(
                f"state_dict has observation_shape {shape!r}, this buffer {self._shape}"
            )
        position = check_int("state_dict position", field("position"), low=0)
        size = check_int("state_dict size", field("size"), low=0)
        if position >= self._capacity or size > self._capacity:
            raise ValueError("state_dict position/size exceed the capacity")
        seed = check_int("state_dict seed", field("seed"), low=0)
        generator = check_generator_state("state_dict generator", field("generator"))
        values: dict[str, Tensor] = {}
        for name in ("observations", "actions", "rewards", "next_observations", "terminals"):
            stored: Tensor = getattr(self, f"_{name}")
            value = field(name)
            if name in ("actions", "terminals"):
                value = check_dtype(f"state_dict {name}", value, stored.dtype, "")
            else:
                value = check_float(f"state_dict {name}", value)
            if value.shape != stored.shape:
                raise ValueError(
                    f"state_dict {name} must have shape {tuple(stored.shape)}, "
                    f"got {tuple(value.shape)}"
                )
            values[name] = value
        if bool((values["actions"] < 0).any()):
            raise ValueError("state_dict actions must be >= 0")
        for name, value in values.items():
            getattr(self, f"_{name}").copy_(value)
        self._position, self._size, self._seed = position, size, seed
        self._generator.set_state(generator)

    def __repr__(self) -> str:
        return (
            f"ReplayBuffer(capacity={self._capacity}, observation_shape={self._shape}, "
            f"size={self._size}, dtype={self.dtype}, device={self.device})"
        )


def _as_tensor(name: str, value: object, device: torch.device) -> Tensor:
    """``value`` (a number, a bool or a tensor) as a tensor on ``device``."""
    if not isinstance(value, (Tensor, numbers.Number, np.bool_)):
        raise ValueError(f"{name} must be a number or a tensor, got {type(value).__name__}")
    return torch.as_tensor(value, device=device)
