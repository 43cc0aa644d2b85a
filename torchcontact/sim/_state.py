"""The batched state of a planar scene."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor


@dataclass(frozen=True, eq=False)
class SceneState:
    """Poses and twists of a batch of scenes, world frame.

    Attributes:
        q: ``(*B, Nd, 3)`` poses ``(x, y, θ)`` of the dynamic bodies.
        v: ``(*B, Nd, 3)`` twists ``(vx, vy, ω)`` of the dynamic bodies.
        q_kinematic: ``(*B, Nk, 3)`` poses of the kinematic bodies.
        mode: ``(*B, K)`` long contact modes of the previous step (the simulator's first
            guess for this step; zeros when unknown).
    """

    q: Tensor
    v: Tensor
    q_kinematic: Tensor
    mode: Tensor

    @property
    def batch_shape(self) -> torch.Size:
        """Leading batch shape ``*B``."""
        return self.q.shape[:-2]

    def map_tensors(self, fn: Any) -> SceneState:
        """Apply ``fn`` to every field (indexing or reshaping the batch)."""
        return replace(
            self, q=fn(self.q), v=fn(self.v), q_kinematic=fn(self.q_kinematic), mode=fn(self.mode)
        )

    def __getitem__(self, index: Any) -> SceneState:
        """Index the batch dimensions."""
        return self.map_tensors(lambda t: t[index])
