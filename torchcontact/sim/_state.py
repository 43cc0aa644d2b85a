"""The batched state of a scene."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor


@dataclass(frozen=True, eq=False)
class SceneState:
    """Poses and twists of a batch of scenes, world frame.

    Attributes:
        q: ``(*B, Nd, 3)`` poses ``(x, y, θ)`` of the dynamic bodies (``(*B, Nd, 7)``
            position and unit quaternion ``(w, x, y, z)`` in a spatial scene).
        v: ``(*B, Nd, 3)`` twists ``(vx, vy, ω)`` of the dynamic bodies (``(*B, Nd, 6)``
            ``(v, ω)`` spatial).
        q_kinematic: ``(*B, Nk, 3)`` (or ``(*B, Nk, 7)``) poses of the kinematic bodies.
        mode: ``(*B, K)`` long contact modes of the previous step (the simulator's first
            guess for this step; zeros when unknown).
        q_robot: ``(*B, Nj)`` the robots' actuated joint positions, robots in scene order
            (rad or m); empty (``Nj = 0``, the default) in scenes without robots.
        v_robot: ``(*B, Nj)`` their joint velocities (default empty).
        robot_base: ``(*B, R, 7)`` world poses of the robots' base frames (default empty,
            ``R = 0``).
    """

    q: Tensor
    v: Tensor
    q_kinematic: Tensor
    mode: Tensor
    q_robot: Tensor | None = None
    v_robot: Tensor | None = None
    robot_base: Tensor | None = None

    def __post_init__(self) -> None:
        batch = self.q.shape[:-2]
        if self.q_robot is None:
            object.__setattr__(self, "q_robot", self.q.new_zeros(*batch, 0))
        if self.v_robot is None:
            object.__setattr__(self, "v_robot", self.q.new_zeros(*batch, 0))
        if self.robot_base is None:
            object.__setattr__(self, "robot_base", self.q.new_zeros(*batch, 0, 7))

    @property
    def batch_shape(self) -> torch.Size:
        """Leading batch shape ``*B``."""
        return self.q.shape[:-2]

    def map_tensors(self, fn: Any) -> SceneState:
        """Apply ``fn`` to every field (indexing or reshaping the batch)."""
        return replace(
            self,
            q=fn(self.q),
            v=fn(self.v),
            q_kinematic=fn(self.q_kinematic),
            mode=fn(self.mode),
            q_robot=fn(self.q_robot),
            v_robot=fn(self.v_robot),
            robot_base=fn(self.robot_base),
        )

    def __getitem__(self, index: Any) -> SceneState:
        """Index the batch dimensions."""
        return self.map_tensors(lambda t: t[index])
