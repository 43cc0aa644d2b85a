"""Manipulation states of the peg-in-hole task: a pose grid around the hole × contact classes.

Every function here is vectorized: a batch of poses (for instance the particles of a filter)
maps to integer state ids in one pass, and an id maps back to a hashable
:class:`~torchcontact.states.ManipulationState` by arithmetic on a fixed table.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import torch
from torch import Tensor

from torchcontact._checks import check_positive
from torchcontact.geometry import wrap_angle
from torchcontact.states import (
    ContactFeature,
    ContactSet,
    ContactState,
    ManipulationState,
    PartnerKind,
)

#: Bits of the environment part of a contact class (support from below, walls on either side).
ENV_LEFT, ENV_RIGHT, ENV_BELOW = 1, 2, 4
#: Grasp part of a contact class: no finger touches, all finger contacts stick, some slide.
GRASP_NONE, GRASP_STICK, GRASP_SLIDE = 0, 1, 2
#: Number of contact classes: 8 environment patterns × 3 grasp states.
NUM_CONTACT_CLASSES = 24
#: The contact class of a peg held firmly and touching nothing else.
HELD_FREE = GRASP_STICK * 8
#: Component of a contact normal (peg frame) above which it counts as along that axis.
_AXIS_THRESHOLD = 0.5


def _canonical_state(index: int) -> ContactState:
    env, grasp = index % 8, index // 8
    features = []
    for bit, face in ((ENV_LEFT, 0), (ENV_RIGHT, 1), (ENV_BELOW, 2)):
        if env & bit:
            features.append(ContactFeature(PartnerKind.ENVIRONMENT, (0, 0), (face, 0), False))
    if grasp != GRASP_NONE:
        sliding = grasp == GRASP_SLIDE
        for face in (0, 1):
            features.append(ContactFeature(PartnerKind.ROBOT, (0, 0), (face, 0), sliding))
    return ContactState(tuple(features))


#: Canonical contact state of each contact class, indexed by class id.
CONTACT_TABLE: tuple[ContactState, ...] = tuple(
    _canonical_state(i) for i in range(NUM_CONTACT_CLASSES)
)


def contact_classes(contacts: ContactSet) -> Tensor:
    """The contact class of the peg in each batch entry, vectorized.

    The class abstracts the peg's contact state (seen from the peg, in its frame) to what the
    task needs. Environment contacts (blocks, table) are sorted by their normal ``n`` (pointing
    into the peg): *below* if ``n_y >= ½`` (the peg rests on something, chamfers included),
    else *left* if ``n_x > ½`` (a wall on the peg's left pushes it right) or *right* if
    ``n_x < −½``; contacts from above are ignored. The grasp is *none* when no finger contact
    carries an impulse, *slide* when one slides, else *stick*. The class id is
    ``8 × grasp + (left + 2 right + 4 below)``; :data:`CONTACT_TABLE` holds a canonical
    :class:`~torchcontact.states.ContactState` for each (environment features on faces 0, 1, 2
    of a one-cell :class:`~torchcontact.states.FeatureGrid`, robot features on faces 0 and 1).

    Args:
        contacts: the peg's contacts (robot partners are the fingers), batch ``*B``, planar.

    Returns:
        ``(*B,)`` long class ids in ``[0, 24)``.

    Raises:
        ValueError: the contacts are not planar.
    """
    if not isinstance(contacts, ContactSet) or contacts.dim != 2:
        raise ValueError("contacts must be a planar ContactSet")
    _, normals = contacts.object_frame()
    robot = contacts.kind_code == 1  # (K,)
    active = contacts.active
    environment = active & ~robot
    nx, ny = normals[..., 0], normals[..., 1]
    below = environment & (ny >= _AXIS_THRESHOLD)
    side = environment & (ny < _AXIS_THRESHOLD)
    left = (side & (nx > _AXIS_THRESHOLD)).any(-1)
    right = (side & (nx < -_AXIS_THRESHOLD)).any(-1)
    env = ENV_LEFT * left.long() + ENV_RIGHT * right.long() + ENV_BELOW * below.any(-1).long()
    touching = (active & robot).any(-1)
    slipping = (contacts.sliding & robot).any(-1)
    grasp = torch.where(
        touching,
        torch.where(slipping, GRASP_SLIDE, GRASP_STICK),
        GRASP_NONE,
    )
    return grasp * 8 + env


@dataclass(frozen=True)
class PegInHoleStates:
    """The discrete manipulation states of the peg-in-hole task.

    A state pairs a cell of the peg's pose relative to the hole with a contact class
    (:func:`contact_classes`). The pose is that of the peg's bottom centre
    ``b = (x, y) + R(θ) (0, −peg_height/2)`` relative to the hole's mouth ``(0, hole_depth)``,
    with the peg's angle wrapped into ``[−π, π)``; each coordinate falls in the half-open cell
    ``[e_{i−1}, e_i)`` of its edges (the outermost cells are unbounded), so away from any contact
    the cell still says on which side of the hole, how high and how tilted the peg is, coarsely
    far away and finely near the mouth. Ids are
    ``id = ((i_x · n_y + i_y) · n_θ + i_θ) · 24 + class``, computed in one vectorized pass.

    Attributes:
        peg_height: length of the peg (locates its bottom centre).
        hole_depth: height of the hole's mouth above the table.
        x_edges: strictly increasing cell edges along ``x``.
        y_edges: strictly increasing cell edges along ``y``.
        angle_edges: strictly increasing cell edges of the angle.
    """

    peg_height: float
    hole_depth: float
    x_edges: tuple[float, ...]
    y_edges: tuple[float, ...]
    angle_edges: tuple[float, ...]

    def __post_init__(self) -> None:
        for name in ("peg_height", "hole_depth"):
            check_positive(name, getattr(self, name))
        for name in ("x_edges", "y_edges", "angle_edges"):
            edges = tuple(getattr(self, name))
            if not edges or any(b <= a for a, b in pairwise(edges)):
                raise ValueError(f"{name} must be non-empty and strictly increasing")
            object.__setattr__(self, name, edges)

    @property
    def shape(self) -> tuple[int, int, int]:
        """Number of cells along ``x``, ``y`` and the angle."""
        return len(self.x_edges) + 1, len(self.y_edges) + 1, len(self.angle_edges) + 1

    @property
    def num_cells(self) -> int:
        """Number of pose cells."""
        nx, ny, na = self.shape
        return nx * ny * na

    @property
    def num_states(self) -> int:
        """Number of manipulation states (ids lie in ``[0, num_states)``)."""
        return self.num_cells * NUM_CONTACT_CLASSES

    def relative_pose(self, peg_pose: Tensor) -> Tensor:
        """The peg's bottom centre and angle relative to the hole's mouth.

        Args:
            peg_pose: ``(*B, 3)`` peg poses ``(x, y, θ)``, world frame.

        Returns:
            ``(*B, 3)``: ``(b_x, b_y − hole_depth, θ)`` with ``θ`` wrapped into ``[−π, π)``.
        """
        peg_pose = _check_poses("peg_pose", peg_pose)
        x, y, theta = peg_pose.unbind(-1)
        half = self.peg_height / 2
        bottom_x = x + half * torch.sin(theta)
        bottom_y = y - half * torch.cos(theta) - self.hole_depth
        return torch.stack([bottom_x, bottom_y, wrap_angle(theta)], dim=-1)

    def cell_indices(self, peg_pose: Tensor) -> Tensor:
        """Per-axis cell indices ``(i_x, i_y, i_θ)`` of peg poses.

        Args:
            peg_pose: ``(*B, 3)`` peg poses, world frame.

        Returns:
            ``(*B, 3)`` long.
        """
        relative = self.relative_pose(peg_pose)
        columns = []
        for axis, edges in enumerate((self.x_edges, self.y_edges, self.angle_edges)):
            boundaries = torch.tensor(edges, dtype=relative.dtype, device=relative.device)
            columns.append(
                torch.bucketize(relative[..., axis].contiguous(), boundaries, right=True)
            )
        return torch.stack(columns, dim=-1)

    def cells(self, peg_pose: Tensor) -> Tensor:
        """Flat pose-cell ids ``(i_x · n_y + i_y) · n_θ + i_θ`` of peg poses, ``(*B,)`` long."""
        index = self.cell_indices(peg_pose)
        _, ny, na = self.shape
        return (index[..., 0] * ny + index[..., 1]) * na + index[..., 2]

    def ids(self, peg_pose: Tensor, contacts: ContactSet | Tensor | int | None = None) -> Tensor:
        """Manipulation-state ids of peg poses, vectorized.

        Args:
            peg_pose: ``(*B, 3)`` peg poses (world frame), e.g. the particles of a filter.
            contacts: the contact class of each pose: a :class:`ContactSet` of the peg with
                batch ``*B`` (classified by :func:`contact_classes`), a long tensor of class
                ids broadcastable to ``*B``, one int for all, or ``None`` for
                :data:`HELD_FREE` (held firmly, touching nothing else).

        Returns:
            ``(*B,)`` long ids in ``[0, num_states)``.

        Raises:
            ValueError: malformed poses or contact classes.
        """
        cells = self.cells(peg_pose)
        if contacts is None:
            classes = torch.full_like(cells, HELD_FREE)
        elif isinstance(contacts, ContactSet):
            classes = contact_classes(contacts)
            if classes.shape != cells.shape:
                raise ValueError(
                    f"contacts must have batch shape {tuple(cells.shape)}, "
                    f"got {tuple(classes.shape)}"
                )
        else:
            classes = torch.as_tensor(contacts, device=cells.device)
            if classes.is_floating_point() or classes.dtype == torch.bool:
                raise ValueError(f"contacts must hold integer class ids, got {classes.dtype}")
            if classes.numel() and (
                int(classes.min()) < 0 or int(classes.max()) >= NUM_CONTACT_CLASSES
            ):
                raise ValueError(f"contacts must hold class ids in [0, {NUM_CONTACT_CLASSES})")
            try:
                classes = torch.broadcast_to(classes.long(), cells.shape)
            except RuntimeError as error:
                raise ValueError(
                    f"contacts of shape {tuple(classes.shape)} do not broadcast to "
                    f"{tuple(cells.shape)}"
                ) from error
        return cells * NUM_CONTACT_CLASSES + classes

    def unravel(self, state_ids: Tensor) -> tuple[Tensor, Tensor]:
        """Per-axis cell indices and contact classes of ids, vectorized (the inverse of
        :meth:`ids`' layout).

        Args:
            state_ids: ``(*B,)`` long ids in ``[0, num_states)``.

        Returns:
            ``(*B, 3)`` long cell indices ``(i_x, i_y, i_θ)`` and ``(*B,)`` long class ids.
        """
        _, ny, na = self.shape
        cell, contact = state_ids // NUM_CONTACT_CLASSES, state_ids % NUM_CONTACT_CLASSES
        return torch.stack([cell // (ny * na), cell // na % ny, cell % na], dim=-1), contact

    def key(self, state_id: int) -> ManipulationState:
        """The hashable manipulation state of an id.

        Its ``pose`` is the cell indices ``(i_x, i_y, i_θ)`` and its ``contact`` the canonical
        contact state of the class (:data:`CONTACT_TABLE`).

        Raises:
            ValueError: ``state_id`` lies outside ``[0, num_states)``.
        """
        if isinstance(state_id, bool) or not 0 <= int(state_id) < self.num_states:
            raise ValueError(f"state_id must lie in [0, {self.num_states}), got {state_id!r}")
        cell, contact = divmod(int(state_id), NUM_CONTACT_CLASSES)
        _, ny, na = self.shape
        rest, i_angle = divmod(cell, na)
        i_x, i_y = divmod(rest, ny)
        return ManipulationState((i_x, i_y, i_angle), CONTACT_TABLE[contact])

    def keys(self, state_ids: Tensor) -> list[ManipulationState]:
        """:meth:`key` of every id of a tensor, in row-major order."""
        return [self.key(int(i)) for i in state_ids.reshape(-1).tolist()]

    def index(self, state: ManipulationState) -> int:
        """The id of a manipulation state built by :meth:`key` (its inverse).

        Raises:
            ValueError: the state is not one of this table's.
        """
        nx, ny, na = self.shape
        pose = state.pose
        if len(pose) != 3 or not all(0 <= i < n for i, n in zip(pose, (nx, ny, na), strict=True)):
            raise ValueError(f"state.pose must be cell indices within {(nx, ny, na)}, got {pose}")
        try:
            contact = CONTACT_TABLE.index(state.contact)
        except ValueError:
            message = f"state.contact is not a canonical contact class: {state.contact}"
            raise ValueError(message) from None
        return ((pose[0] * ny + pose[1]) * na + pose[2]) * NUM_CONTACT_CLASSES + contact


def manipulation_state(
    peg_pose: Tensor,
    *,
    states: PegInHoleStates,
    contacts: ContactSet | Tensor | int | None = None,
) -> Tensor:
    """Manipulation-state ids of peg poses (true or estimated), vectorized.

    The function form of :meth:`PegInHoleStates.ids`, for callers that hold poses rather than an
    environment, e.g. a particle filter with ``(N, 3)`` pose particles and per-particle contact
    classes.

    Args:
        peg_pose: ``(*B, 3)`` peg poses ``(x, y, θ)``, world frame.
        states: the discretization (``env.states``).
        contacts: contact classes, see :meth:`PegInHoleStates.ids`.

    Returns:
        ``(*B,)`` long ids; ``states.key(id)`` gives the hashable state.
    """
    if not isinstance(states, PegInHoleStates):
        raise ValueError(f"states must be a PegInHoleStates, got {type(states).__name__}")
    return states.ids(peg_pose, contacts)


def _check_poses(name: str, pose: object) -> Tensor:
    if not isinstance(pose, Tensor) or not pose.is_floating_point():
        raise ValueError(f"{name} must be a floating tensor of shape (*B, 3)")
    if pose.dim() < 1 or pose.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (*B, 3), got {tuple(pose.shape)}")
    if not bool(torch.isfinite(pose).all()):
        raise ValueError(f"{name} contains NaN or inf")
    return pose
