"""A robot: batched forward kinematics, geometric Jacobians and contact Jacobians.

Frames. Every transform is a homogeneous matrix ``T`` ``(*B, 4, 4)`` that maps homogeneous point
coordinates in a link's frame to the robot's base frame (the URDF root link, called "world" below):
``p_world = T p_link``. Every Jacobian is expressed in the world frame.

Coordinates. ``q`` ``(*B, dof)`` holds the actuated joint coordinates (rad for revolute joints, m
for prismatic ones) in the order of :attr:`Robot.joint_names`. Joints coupled to others by URDF
``<mimic>`` tags (the BarrettHand's F2 spread and outer finger joints, the parallel-jaw gripper's
right finger) follow through the :class:`~torchcontact.robots.JointCoupling` ``q_full = C q + c``;
load a robot with ``coupled=False`` to drive every joint independently (e.g. a BarrettHand finger
after its TorqueSwitch clutch has broken away).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from types import MappingProxyType
from typing import overload

import torch
from pytorch_kinematics.chain import Chain
from torch import Tensor

from torchcontact._checks import (
    broadcast_batch,
    check_float,
    check_like,
    check_tensor,
    check_trailing,
    check_unit_rows,
    read_text_file,
)
from torchcontact.robots._coupling import JointCoupling
from torchcontact.robots._links import LinkInertial, LinkShape, link_inertial, link_shape
from torchcontact.robots._urdf import UrdfModel, build_chain, parse_urdf


@dataclass(frozen=True, eq=False)
class _Kinematics:
    """A robot's chain and constant tensors in one dtype on one device.

    Attributes:
        chain: The pytorch-kinematics chain.
        joint_frames: ``(n_full,)`` long: index of the frame each joint moves (its child link).
        axes: ``(n_full, 3)``: each joint's axis in its child link frame.
        revolute: ``(n_full,)`` bool: revolute (True) or prismatic (False).
        ancestors: ``(n_frames, n_full)``: 1 where the joint moves the frame, else 0.
        matrix: Coupling ``C`` ``(n_full, dof)``, or None for the identity.
        offset: Coupling ``c`` ``(n_full,)``, or None for the identity.
    """

    chain: Chain
    joint_frames: Tensor
    axes: Tensor
    revolute: Tensor
    ancestors: Tensor
    matrix: Tensor | None
    offset: Tensor | None


@dataclass(frozen=True, eq=False)
class Robot:
    """A kinematic robot model built from a URDF through pytorch-kinematics.

    Create one with :func:`torchcontact.robots.load` or :meth:`Robot.from_urdf`. Works for float32
    and float64 inputs on any device: the chain is converted to the input's dtype and device on
    first use and cached. Inputs are never cast silently; every argument is validated.

    Attributes:
        name: The robot's name (the URDF ``robot`` name attribute).
        source: Where the description was read from.
        coupling: The map from actuated coordinates to the full joint vector.
        link_names: Every link (frame) name, base first.
        link_parents: Every link except the base -> the link it is attached to.
        lower: Lower joint limits of the actuated joints, float64 ``(dof,)`` (rad or m).
        upper: Upper joint limits of the actuated joints, float64 ``(dof,)`` (rad or m).
    """

    name: str
    source: str
    coupling: JointCoupling = field(repr=False)
    link_names: tuple[str, ...] = field(repr=False)
    link_parents: Mapping[str, str] = field(repr=False)
    lower: Tensor = field(repr=False)
    upper: Tensor = field(repr=False)
    _model: UrdfModel = field(repr=False)
    _cache: dict[tuple[torch.dtype, torch.device], _Kinematics] = field(
        default_factory=dict, repr=False
    )

    @classmethod
    def from_urdf(cls, path: str | Path, *, coupled: bool = True) -> Robot:
        """Read a robot from a URDF file.

        Args:
            path: The URDF file.
            coupled: Apply the URDF ``<mimic>`` tags, so that only independent joints are
                coordinates (True), or treat every non-fixed joint as an independent coordinate
                (False).

        Returns:
            The robot.

        Raises:
            ValueError: ``path`` names no readable UTF-8 file, ``coupled`` is not a bool, or the
                URDF is malformed or uses unsupported features.
        """
        if not isinstance(coupled, bool):
            raise ValueError(f"coupled must be a bool, got {coupled!r}")
        text = read_text_file("path", path)
        source = Path(str(path))
        model = parse_urdf(text, source=str(source))
        chain = build_chain(model)
        full_names = tuple(str(n) for n in chain.get_joint_parameter_names())
        joints = {joint.name: joint for joint in model.joints}
        if coupled:
            coupling = JointCoupling.from_mimic(
                full_names, {n: joints[n].mimic for n in full_names}
            )
        else:
            coupling = JointCoupling.identity(full_names)
        actuated = [joints[n] for n in coupling.actuated_names]
        robot = cls(
            name=model.name,
            source=str(source),
            coupling=coupling,
            link_names=tuple(str(chain.idx_to_frame[i]) for i in range(len(chain.idx_to_frame))),
            link_parents=MappingProxyType({j.child: j.parent for j in model.joints}),
            lower=torch.tensor([j.lower for j in actuated], dtype=torch.float64),
            upper=torch.tensor([j.upper for j in actuated], dtype=torch.float64),
            _model=model,
        )
        robot._cache[(torch.float64, torch.device("cpu"))] = robot._constants(chain)
        return robot

    @property
    def dof(self) -> int:
        """Number of actuated coordinates (the length of ``q``)."""
        return len(self.coupling.actuated_names)

    @property
    def joint_names(self) -> tuple[str, ...]:
        """Names of the actuated joints, in the order of ``q``'s last dimension."""
        return self.coupling.actuated_names

    @cached_property
    def inertials(self) -> tuple[LinkInertial, ...]:
        """The mass properties of every link with an URDF ``<inertial>``, in file order."""
        return tuple(link_inertial(element) for element in self._model.inertials)

    @cached_property
    def collision_shapes(self) -> tuple[LinkShape, ...]:
        """Every link's collision primitives from the URDF ``<collision>`` elements, in file order.

        ``<box>`` is a :class:`~torchcontact.geometry.Box`, ``<sphere>`` a
        :class:`~torchcontact.geometry.Sphere`, and ``<cylinder radius="r" length="L">`` (URDF
        has no capsule) the :class:`~torchcontact.geometry.Capsule` of radius ``r`` around the
        cylinder's axis segment of length ``L`` (hemispherical caps added beyond both ends);
        each with its pose in its link's frame.
        """
        return tuple(link_shape(element) for element in self._model.collisions)

    def _constants(self, chain: Chain) -> _Kinematics:
        """Index tables and constants of ``chain``, in the chain's dtype and device."""
        dtype, device = chain.dtype, chain.device
        joint_of_frame = [int(j) for j in chain.joint_indices]
        n_full = len(self.coupling.full_names)
        joint_frames = [joint_of_frame.index(j) for j in range(n_full)]
        kinds = {joint.name: joint.kind for joint in self._model.joints}
        ancestors = torch.zeros(len(joint_of_frame), n_full, dtype=dtype, device=device)
        for f, path in enumerate(chain.parents_indices):
            for p in path.tolist():
                if joint_of_frame[p] >= 0:
                    ancestors[f, joint_of_frame[p]] = 1.0
        identity = self.coupling.is_identity
        return _Kinematics(
            chain=chain,
            joint_frames=torch.tensor(joint_frames, dtype=torch.long, device=device),
            axes=chain.axes.to(dtype=dtype, device=device),
            revolute=torch.tensor(
                [kinds[n] == "revolute" for n in self.coupling.full_names], device=device
            ),
            ancestors=ancestors,
            matrix=None if identity else self.coupling.matrix.to(dtype=dtype, device=device),
            offset=None if identity else self.coupling.offset.to(dtype=dtype, device=device),
        )

    def _kinematics(self, dtype: torch.dtype, device: torch.device) -> _Kinematics:
        """The chain and constants for ``dtype`` on ``device`` (built on first use, then cached)."""
        key = (dtype, device)
        if key not in self._cache:
            chain = build_chain(self._model).to(dtype=dtype, device=device)
            self._cache[key] = self._constants(chain)
        return self._cache[key]

    def _check_q(self, q: object) -> Tensor:
        q = check_float("q", q)
        check_trailing(
            "q", q, trailing=(self.dof,), what=f"(*B, {self.dof}) (joints {list(self.joint_names)})"
        )
        return q

    def _frame_index(self, link: object) -> int:
        if not isinstance(link, str) or link not in self.link_names:
            raise ValueError(f"link must be one of {list(self.link_names)}, got {link!r}")
        return self.link_names.index(link)

    def _transforms(self, q: Tensor) -> tuple[Tensor, _Kinematics]:
        """World transforms of every frame, frame-major: ``(n_frames, *B, 4, 4)``."""
        kin = self._kinematics(q.dtype, q.device)
        q_full = q if kin.matrix is None or kin.offset is None else q @ kin.matrix.T + kin.offset
        flat = q_full.reshape(-1, q_full.shape[-1])
        transforms: Tensor = kin.chain.forward_kinematics_tensor(flat)
        return transforms.reshape(len(self.link_names), *q.shape[:-1], 4, 4), kin

    @overload
    def forward_kinematics(self, q: Tensor, link: None = None) -> dict[str, Tensor]: ...

    @overload
    def forward_kinematics(self, q: Tensor, link: str) -> Tensor: ...

    def forward_kinematics(self, q: Tensor, link: str | None = None) -> dict[str, Tensor] | Tensor:
        """Batched forward kinematics.

        Args:
            q: Actuated joint coordinates ``(*B, dof)``, float32 or float64.
            link: A link name to get only that link's transform; None for every link.

        Returns:
            With ``link``: the link's transform ``(*B, 4, 4)`` (link frame -> world frame). Without:
            a dict from every name in :attr:`link_names` to its transform ``(*B, 4, 4)``. Same dtype
            and device as ``q``.

        Raises:
            ValueError: ``q`` is not a tensor, has the wrong last dimension or dtype or holds
                NaN/inf, or ``link`` is not a link name.
        """
        q = self._check_q(q)
        frame = None if link is None else self._frame_index(link)
        transforms, _ = self._transforms(q)
        if frame is not None:
            return transforms[frame]
        return {name: transforms[i] for i, name in enumerate(self.link_names)}

    def jacobian(self, q: Tensor, link: str, *, point: Tensor | None = None) -> Tensor:
        """Geometric Jacobian of a point fixed on a link, in the world frame.

        ``J q̇ = [v; ω]``: ``v`` is the world-frame velocity of the point, ``ω`` the link's
        world-frame angular velocity. For coupled robots the columns are actuated coordinates:
        ``J = J_full C``.

        Args:
            q: Actuated joint coordinates ``(*B, dof)``, float32 or float64.
            link: Name of the link the point is fixed to.
            point: The point in ``link``'s frame ``(*B', 3)`` (m), same dtype and device as ``q``;
                its batch shape broadcasts with ``q``'s. None (default) for the link frame's origin.

        Returns:
            ``(*B'', 6, dof)`` with rows ``[v; ω]``, where ``B''`` is the broadcast of ``B`` and
            ``B'``; same dtype and device as ``q``.

        Raises:
            ValueError: ``q`` or ``point`` is not a tensor, or has the wrong shape, dtype or
                device, NaN/inf, non-broadcastable batches, or an unknown ``link``.
        """
        q = self._check_q(q)
        frame = self._frame_index(link)
        if point is not None:
            point = check_float("point", point)
            check_like("point", point, reference_name="q", reference=q)
            check_trailing("point", point, trailing=(3,), what="(*B, 3)")
            broadcast_batch([("q", q.shape[:-1]), ("point", point.shape[:-1])])
        transforms, kin = self._transforms(q)
        pose = transforms[frame]
        x = pose[..., :3, 3]
        if point is not None:
            x = (pose[..., :3, :3] @ point.unsqueeze(-1)).squeeze(-1) + x
        # Axis z_j and origin o_j of every joint, world frame: (*B, n_full, 3).
        moving = transforms[kin.joint_frames].movedim(0, -3)
        z = (moving[..., :3, :3] @ kin.axes.unsqueeze(-1)).squeeze(-1)
        o = moving[..., :3, 3]
        lever = x.unsqueeze(-2) - o
        z = z.expand_as(lever)
        revolute = kin.revolute.unsqueeze(-1)
        linear = torch.where(revolute, torch.linalg.cross(z, lever), z)
        angular = torch.where(revolute, z, torch.zeros_like(z))
        columns = torch.cat([linear, angular], dim=-1) * kin.ancestors[frame].unsqueeze(-1)
        jacobian = columns.transpose(-1, -2)
        if kin.matrix is not None:
            jacobian = jacobian @ kin.matrix
        return jacobian

    def link_jacobians(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Every link's transform and the geometric Jacobian of its frame origin.

        Args:
            q: Actuated joint coordinates ``(*B, dof)``, float32 or float64.

        Returns:
            The transforms ``(*B, L, 4, 4)`` (link frame -> world frame) and the Jacobians
            ``(*B, L, 6, dof)`` with rows ``[v; ω]`` (world-frame velocity of each link frame's
            origin and the link's angular velocity), ``L = len(link_names)`` in that order.

        Raises:
            ValueError: ``q`` is not a finite float tensor of shape ``(*B, dof)``.
        """
        q = self._check_q(q)
        transforms, kin = self._transforms(q)
        transforms = transforms.movedim(0, -3)  # (*B, L, 4, 4)
        x = transforms[..., :3, 3]
        moving = transforms.index_select(-3, kin.joint_frames)  # (*B, n_full, 4, 4)
        z = (moving[..., :3, :3] @ kin.axes.unsqueeze(-1)).squeeze(-1)
        o = moving[..., :3, 3]
        lever = x.unsqueeze(-2) - o.unsqueeze(-3)  # (*B, L, n_full, 3)
        z = z.unsqueeze(-3).expand_as(lever)
        revolute = kin.revolute.unsqueeze(-1)
        linear = torch.where(revolute, torch.linalg.cross(z, lever), z)
        angular = torch.where(revolute, z, torch.zeros_like(z))
        columns = torch.cat([linear, angular], dim=-1) * kin.ancestors.unsqueeze(-1)
        jacobians = columns.transpose(-1, -2)
        if kin.matrix is not None:
            jacobians = jacobians @ kin.matrix
        return transforms, jacobians

    def _com_jacobians(
        self, q: Tensor, links: tuple[Tensor, Tensor] | None = None
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Masses ``(Li,)``, centre-of-mass Jacobians ``(*B, Li, 3, dof)``, angular Jacobians
        ``(*B, Li, 3, dof)`` and world inertias about the centres of mass ``(*B, Li, 3, 3)`` of
        the links with an inertial (from ``links``, :meth:`link_jacobians` at ``q``, if
        given)."""
        transforms, jacobians = self.link_jacobians(q) if links is None else links
        frames = torch.tensor(
            [self.link_names.index(i.link) for i in self.inertials],
            dtype=torch.long,
            device=q.device,
        )
        masses = torch.tensor([i.mass for i in self.inertials], dtype=q.dtype, device=q.device)
        com = torch.stack([i.com for i in self.inertials]).to(q)
        inertia = torch.stack([i.inertia for i in self.inertials]).to(q)
        pose, jacobian = transforms.index_select(-3, frames), jacobians.index_select(-3, frames)
        rotation = pose[..., :3, :3]
        arm = (rotation @ com.unsqueeze(-1)).squeeze(-1)  # com - origin, world frame
        angular = jacobian[..., 3:, :]
        # v_com = v_origin + ω × arm, column by column.
        spin = torch.linalg.cross(
            angular.transpose(-1, -2),
            arm.unsqueeze(-2).expand(*arm.shape[:-1], angular.shape[-1], 3),
        ).transpose(-1, -2)
        linear = jacobian[..., :3, :] + spin
        return masses, linear, angular, rotation @ inertia @ rotation.transpose(-1, -2)

    def mass_matrix(self, q: Tensor, *, links: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """Joint-space mass matrix ``M(q) = Σ_links m Jcᵀ Jc + Jωᵀ I_w Jω``.

        ``Jc`` is the Jacobian of the link's centre of mass and ``Jω`` of its angular velocity
        (:meth:`link_jacobians`), ``I_w`` its inertia about the centre of mass in the world
        frame, over the links with an URDF ``<inertial>``: the kinetic energy of the links moving
        with joint velocities ``q̇`` is ``½ q̇ᵀ M q̇`` (the base is fixed). ``M`` does not depend
        on the base frame's orientation, so it holds for a robot placed anywhere.

        Args:
            q: Actuated joint coordinates ``(*B, dof)``, float32 or float64.
            links: :meth:`link_jacobians` at ``q`` where the caller has them already (a
                simulator step needs them for the contact rows too); computed when ``None``.

        Returns:
            ``(*B, dof, dof)`` symmetric positive semi-definite (definite when every coordinate
            moves some mass).

        Raises:
            ValueError: ``q`` is not a finite float tensor of shape ``(*B, dof)``, ``links``
                is not a pair of finite tensors of :meth:`link_jacobians`' shapes at ``q``, or
                the robot has no link inertials.
        """
        if not self.inertials:
            raise ValueError(f"robot {self.name!r} has no link <inertial> elements")
        if links is not None:
            q = self._check_q(q)
            if not isinstance(links, tuple) or len(links) != 2:
                raise ValueError("links must be the pair (transforms, jacobians) of link_jacobians")
            L = len(self.link_names)
            for name, value, event in (
                ("links[0]", links[0], (L, 4, 4)),
                ("links[1]", links[1], (L, 6, self.dof)),
            ):
                check_tensor(name, value, event_shape=event, like=q)
                if value.shape[:-3] != q.shape[:-1]:
                    raise ValueError(
                        f"{name} has shape {tuple(value.shape)}; expected {(*q.shape[:-1], *event)}"
                    )
        masses, linear, angular, inertia = self._com_jacobians(q, links)
        translational = masses[:, None, None] * (linear.transpose(-1, -2) @ linear)
        rotational = angular.transpose(-1, -2) @ inertia @ angular
        return (translational + rotational).sum(-3)

    def gravity_force(self, q: Tensor, gravity: Tensor) -> Tensor:
        """Generalized gravity force on the actuated coordinates, ``Σ_links m Jcᵀ g``.

        Args:
            q: Actuated joint coordinates ``(*B, dof)``, float32 or float64.
            gravity: Gravitational acceleration in the robot's base frame ``(*B, 3)`` (m/s²),
                same dtype and device as ``q``; its batch broadcasts with ``q``'s.

        Returns:
            ``(*B, dof)`` joint torques (N m) or forces (N) that gravity exerts.

        Raises:
            ValueError: ``q`` or ``gravity`` is not a finite float tensor of its shape, or the
                robot has no link inertials.
        """
        if not self.inertials:
            raise ValueError(f"robot {self.name!r} has no link <inertial> elements")
        gravity = check_float("gravity", gravity)
        check_trailing("gravity", gravity, trailing=(3,), what="(*B, 3)")
        masses, linear, _, _ = self._com_jacobians(q)
        check_like("gravity", gravity, reference_name="q", reference=q)
        weight = masses.unsqueeze(-1) * gravity.unsqueeze(-2)  # (*B, Li, 3)
        return (weight.unsqueeze(-2) @ linear).squeeze(-2).sum(-2)

    def contact_jacobian(
        self, q: Tensor, link: str, *, point: Tensor, normal: Tensor, tangents: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Map from joint velocities to a contact point's velocity along a normal and tangents.

        With ``v_p`` the world-frame velocity of the robot's material point at the contact,

            Jn q̇ = n · v_p,        Jt[d] q̇ = t_d · v_p.

        Use in a :class:`~torchcontact.contact.ContactProblem` between this robot link (body B) and
        another body A, with ``normal`` n pointing from A toward B (out of A, so the gap grows when
        the robot point moves along n) and ``tangents`` the problem's friction directions t_d:

        * kinematically driven robot (its velocity is the control): the robot enters through the
          known velocity terms, ``bn = Jn q̇`` ``(*B,)`` and ``bt = Jt q̇`` ``(*B, D)``;
        * dynamic robot (its joint velocities are generalized coordinates): ``Jn`` and ``Jt`` are
          the robot's columns of the problem's ``Jn`` ``(K, n)`` and ``Jt`` ``(K, D, n)`` rows,
          next to A's columns (which carry the opposite sign), with the robot's joint-space mass
          matrix in the problem's ``M``.

        If your normal points from the robot into A instead, negate ``Jn`` (and use ``-t_d``).

        Args:
            q: Actuated joint coordinates ``(*B, dof)``, float32 or float64.
            link: Name of the link in contact.
            point: Contact point in ``link``'s frame ``(*B, 3)`` (m).
            normal: Unit contact normal in the world frame ``(*B, 3)``.
            tangents: Unit friction directions in the world frame, orthogonal to ``normal``,
                ``(*B, D, 3)`` (D ≥ 1; e.g. +t and -t in the plane).

        All tensors share ``q``'s dtype and device; their batch shapes broadcast.

        Returns:
            ``Jn`` ``(*B, dof)`` and ``Jt`` ``(*B, D, dof)``.

        Raises:
            ValueError: An argument is not a tensor, or wrong shape, dtype, device, NaN/inf, a
                non-unit normal or tangent, a tangent not orthogonal to the normal,
                non-broadcastable batches, or an unknown ``link``.
        """
        q = self._check_q(q)
        point = check_float("point", point)
        normal = check_float("normal", normal)
        tangents = check_float("tangents", tangents)
        for name, value in (("point", point), ("normal", normal), ("tangents", tangents)):
            check_like(name, value, reference_name="q", reference=q)
        check_trailing("point", point, trailing=(3,), what="(*B, 3)")
        check_trailing("normal", normal, trailing=(3,), what="(*B, 3)")
        if tangents.ndim < 2 or tangents.shape[-1] != 3 or tangents.shape[-2] < 1:
            shape = tuple(tangents.shape)
            raise ValueError(f"tangents must have shape (*B, D, 3) with D >= 1, got {shape}")
        check_unit_rows("normal", normal)
        check_unit_rows("tangents", tangents)
        broadcast_batch(
            [
                ("q", q.shape[:-1]),
                ("point", point.shape[:-1]),
                ("normal", normal.shape[:-1]),
                ("tangents", tangents.shape[:-2]),
            ]
        )
        tol = 1e-6 if q.dtype == torch.float64 else 1e-3
        dots = tangents @ normal.unsqueeze(-1)
        if dots.numel() and float(dots.abs().max()) > tol:
            raise ValueError(f"tangents must be orthogonal to normal (|t · n| <= {tol:g})")
        linear = self.jacobian(q, link, point=point)[..., :3, :]
        jn = (normal.unsqueeze(-2) @ linear).squeeze(-2)
        jt = tangents @ linear
        return jn, jt
