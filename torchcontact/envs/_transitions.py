"""Recorded steps of the peg-in-hole task: what the belief model is fitted on."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

_F64 = torch.float64


def as_tensor(value: Any, dtype: torch.dtype) -> Tensor:
    """``value`` (array-like: NumPy array, tensor, sequence) as a tensor of ``dtype``."""
    return torch.as_tensor(np.asarray(value), dtype=dtype)


@dataclass(frozen=True, kw_only=True)
class PegTransitions:
    """Recorded environment steps of the peg-in-hole task (what the filter model is fit on).

    Attributes:
        grasp: ``(T, 3)`` the peg's pose in the gripper frame before the step.
        next_grasp: ``(T, 3)`` the same after the step.
        actions: ``(T,)`` long actions.
        classes: ``(T,)`` long contact classes before the step.
        next_classes: ``(T,)`` long contact classes after it.
        next_triggered: ``(T, S)`` bool noise-free tactile readings after it.
        first: ``(T,)`` bool, the step is the first of its episode (its ``grasp`` is a reset).
    """

    grasp: Tensor
    next_grasp: Tensor
    actions: Tensor
    classes: Tensor
    next_classes: Tensor
    next_triggered: Tensor
    first: Tensor

    def __post_init__(self) -> None:
        T = self.actions.shape[0]
        expected = {
            "grasp": (T, 3),
            "next_grasp": (T, 3),
            "actions": (T,),
            "classes": (T,),
            "next_classes": (T,),
            "first": (T,),
        }
        for name, shape in expected.items():
            value = getattr(self, name)
            if not isinstance(value, Tensor) or tuple(value.shape) != shape:
                raise ValueError(f"{name} must be a {shape} tensor, got {_shape(value)}")
        if self.next_triggered.ndim != 2 or self.next_triggered.shape[0] != T:
            raise ValueError(f"next_triggered must be (T, S), got {_shape(self.next_triggered)}")
        if not bool(torch.isfinite(self.grasp).all() and torch.isfinite(self.next_grasp).all()):
            raise ValueError("grasp and next_grasp must be finite")

    @property
    def num_steps(self) -> int:
        """``T``, the number of recorded steps."""
        return int(self.actions.shape[0])

    @classmethod
    def from_infos(
        cls,
        before: Mapping[str, NDArray[Any]],
        actions: NDArray[np.int64],
        after: Mapping[str, NDArray[Any]],
        *,
        valid: NDArray[np.bool_],
        first: NDArray[np.bool_],
    ) -> PegTransitions:
        """The steps of a vector environment between two of its ``infos``.

        Args:
            before: infos before the step (keys ``peg_in_gripper``, ``contact_class``).
            actions: ``(B,)`` actions taken.
            after: infos after the step (also ``tactile_triggered``).
            valid: ``(B,)`` entries that really stepped (not an auto-reset).
            first: ``(B,)`` entries whose ``before`` is the first state of an episode.
        """
        keep = np.flatnonzero(valid)

        def take(info: Mapping[str, NDArray[Any]], key: str) -> NDArray[Any]:
            return np.asarray(info[key])[keep]

        return cls(
            grasp=as_tensor(take(before, "peg_in_gripper"), _F64),
            next_grasp=as_tensor(take(after, "peg_in_gripper"), _F64),
            actions=as_tensor(np.asarray(actions)[keep], torch.long),
            classes=as_tensor(take(before, "contact_class"), torch.long),
            next_classes=as_tensor(take(after, "contact_class"), torch.long),
            next_triggered=as_tensor(take(after, "tactile_triggered"), torch.bool),
            first=as_tensor(np.asarray(first)[keep], torch.bool),
        )

    @classmethod
    def concat(cls, parts: Sequence[PegTransitions]) -> PegTransitions:
        """All steps of ``parts``, in order."""
        if not parts:
            raise ValueError("parts must hold at least one PegTransitions")
        return cls(**{f.name: torch.cat([getattr(p, f.name) for p in parts]) for f in fields(cls)})


def _shape(value: object) -> object:
    return tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__


__all__ = ["PegTransitions", "as_tensor"]
