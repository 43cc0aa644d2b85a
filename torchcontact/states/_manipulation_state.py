"""Manipulation states: the discretized robot–object relative pose with the contact state."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from torchcontact._checks import check_dim, check_field, check_instance, check_positive
from torchcontact.states._contact_set import ContactSet
from torchcontact.states._contact_state import ContactState, contact_states
from torchcontact.states._frames import check_pose, relative_pose
from torchcontact.states._grid import FeatureGrid, _to_long


@dataclass(frozen=True)
class PoseGrid:
    """Discretization of the robot's pose in the object frame.

    Positions are rounded to cells of side ``position_step``: ``⌊x / step + ½⌋`` per coordinate
    (half-open cells, a boundary value goes up). Orientations:

    * planar: the angle into ``N = ⌈2π / angle_step⌉`` bins of width ``2π / N`` centred on
      ``2π k / N`` (so angle 0 is a bin centre and the bins wrap around), key ``k ∈ [0, N)``;
    * spatial: the rotation vector ``r = θ a`` of the unit quaternion with ``w >= 0``
      (``θ ∈ [0, π]``) rounded to cells of side ``angle_step`` per coordinate. At ``θ = π``,
      ``r`` and ``−r`` are the same rotation but may get different keys.

    Attributes:
        dim: 2 (planar pose ``(x, y, θ)``) or 3 (spatial pose ``(p, q_wxyz)``).
        position_step: cell side for positions, metres, ``> 0``.
        angle_step: bin width for orientations, radians, ``> 0``.
    """

    dim: int
    position_step: float
    angle_step: float

    def __post_init__(self) -> None:
        check_dim("dim", self.dim)
        object.__setattr__(
            self, "position_step", check_positive("position_step", self.position_step)
        )
        object.__setattr__(self, "angle_step", check_positive("angle_step", self.angle_step))

    @property
    def angle_bins(self) -> int:
        """Planar: the number ``N`` of angle bins on the circle."""
        return math.ceil(2 * math.pi / self.angle_step)

    def quantize(self, pose: Tensor) -> Tensor:
        """Integer keys of relative poses.

        Args:
            pose: ``(*B, 3)`` planar ``(x, y, θ)`` or ``(*B, 7)`` spatial ``(p, q_wxyz)`` pose
                of the robot in the object frame.

        Returns:
            ``(*B, 3)`` long ``(i_x, i_y, k)`` planar or ``(*B, 6)`` long (position cells,
            rotation-vector cells) spatial.
        """
        pose = check_pose("pose", pose, self.dim)
        position = _to_long("pose", torch.floor(pose[..., : self.dim] / self.position_step + 0.5))
        if self.dim == 2:
            n = self.angle_bins
            k = torch.floor(pose[..., 2] / (2 * math.pi / n) + 0.5).long().remainder(n)
            return torch.cat([position, k.unsqueeze(-1)], dim=-1)
        q = pose[..., 3:] / torch.linalg.vector_norm(pose[..., 3:], dim=-1, keepdim=True)
        q = torch.where(q[..., :1] < 0, -q, q)
        w, v = q[..., :1], q[..., 1:]
        sine = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
        angle = 2 * torch.atan2(sine, w)
        # θ / sin(θ/2) → 2 / w as sin(θ/2) → 0 (and w → 1).
        scale = torch.where(sine > 0, angle / torch.where(sine > 0, sine, 1.0), 2.0 / w)
        rotation = _to_long("pose", torch.floor(v * scale / self.angle_step + 0.5))
        return torch.cat([position, rotation], dim=-1)


@dataclass(frozen=True, order=True)
class ManipulationState:
    """A manipulation state: the discretized relative pose and the contact state.

    Following Section III of the seed paper, a manipulation state holds the robot's pose
    relative to the object (as :meth:`PoseGrid.quantize` keys) and the object's contact state,
    whose features keep contacts with the robot and with the environment apart. Without robot
    contact (:attr:`robot_contact` is ``False``) the relative pose is what tells states apart.

    Attributes:
        pose: relative-pose key (3 ints planar, 6 spatial), or ``()`` where the relative pose
            is not tracked (the state is then its contact state alone).
        contact: the contact state of the object.
    """

    pose: tuple[int, ...]
    contact: ContactState

    def __post_init__(self) -> None:
        if not isinstance(self.pose, (tuple, list)):
            raise ValueError(f"pose must be a tuple of ints, got {self.pose!r}")
        pose = tuple(self.pose)
        if not all(isinstance(i, int) and not isinstance(i, bool) for i in pose):
            raise ValueError(f"pose must hold ints, got {self.pose!r}")
        if not isinstance(self.contact, ContactState):
            raise ValueError(f"contact must be a ContactState, got {type(self.contact).__name__}")
        object.__setattr__(self, "pose", pose)

    @property
    def robot_contact(self) -> bool:
        """Whether the robot touches the object."""
        return bool(self.contact.robot)

    def to_json(self) -> dict[str, Any]:
        """``{"pose": [...], "contact": [...]}`` with JSON-native types."""
        return {"pose": list(self.pose), "contact": self.contact.to_json()}

    @classmethod
    def from_json(cls, data: Any) -> ManipulationState:
        """Inverse of :meth:`to_json`.

        Raises:
            ValueError: ``data`` is not ``{"pose": [...], "contact": [...]}`` of a state.
        """
        pose = check_field("data", data, "pose")
        contact = check_field("data", data, "contact")
        if not isinstance(pose, list):
            raise ValueError(f"data['pose'] must be a list of ints, got {pose!r}")
        return cls(tuple(pose), ContactState.from_json(contact))

    def __str__(self) -> str:
        """A short label, the pose key and the contact state, e.g. ``"(-6, 0, 0) E2st"``."""
        return f"{self.pose} {self.contact}"


def manipulation_states(
    contacts: ContactSet,
    *,
    robot_pose: Tensor,
    contact_grid: FeatureGrid,
    pose_grid: PoseGrid,
) -> list[ManipulationState]:
    """The manipulation state of every batch element.

    Args:
        contacts: the object's contacts, batch shape ``*B``.
        robot_pose: ``(*B, 3)`` or ``(*B, 7)`` robot pose: in the world frame when
            ``contacts.pose`` is given (the relative pose is computed by
            :func:`relative_pose`), else already in the object frame.
        contact_grid: quantization of contact features.
        pose_grid: quantization of the relative pose.

    Returns:
        ``prod(*B)`` manipulation states in row-major order of the batch shape (the keys are
        computed in torch; the hashable states are built in a Python loop over the batch).

    Raises:
        ValueError: the grids' or the pose's dimension or shape do not match the contacts.
    """
    check_instance("contacts", contacts, ContactSet)
    check_instance("contact_grid", contact_grid, FeatureGrid)
    check_instance("pose_grid", pose_grid, PoseGrid)
    if pose_grid.dim != contacts.dim:
        raise ValueError(f"pose_grid.dim must equal contacts.dim = {contacts.dim}")
    robot_pose = check_pose("robot_pose", robot_pose, contacts.dim)
    if robot_pose.shape[:-1] != contacts.batch_shape:
        raise ValueError(
            f"robot_pose must have batch shape {tuple(contacts.batch_shape)}, "
            f"got {tuple(robot_pose.shape)}"
        )
    if contacts.pose is not None:
        robot_pose = relative_pose(contacts.pose, robot_pose)
    keys = pose_grid.quantize(robot_pose)
    keys = keys.reshape(-1, keys.shape[-1])
    states = contact_states(contacts, contact_grid)
    return [
        ManipulationState(tuple(key), state)
        for key, state in zip(keys.tolist(), states, strict=True)
    ]
