r"""Robots as members of a spatial scene: joints as degrees of freedom, a torque-limited servo.

A :class:`RobotMember` places a :class:`~torchcontact.robots.Robot` in a scene at a base pose
(fixed, or moved kinematically by a commanded base twist, e.g. a hand carried by an arm). Its
links' collision primitives (:attr:`~torchcontact.robots.Robot.collision_shapes`) touch the
scene's dynamic bodies. Its actuated joints either

* are generalized coordinates of the contact problem (``mode="servo"``): the problem's velocity
  is ``[dynamic-body twists, servo joint velocities]``, the joint-space mass matrix
  ``M(q) = Σ_links Jcᵀ m Jc + Jωᵀ I_w Jω`` (:meth:`~torchcontact.robots.Robot.mass_matrix`)
  is a block of the problem's, and a contact on a link has the rows
  ``[u, r × u] · J_link`` (``J_link`` the world-frame Jacobian of the link frame's origin,
  ``r`` from that origin to the contact point: the same rows as
  :meth:`~torchcontact.robots.Robot.contact_jacobian`); or
* follow commanded joint velocities (``mode="kinematic"``, arms that do not yield): their
  motion enters the contact problem only through the known velocity terms ``bn``, ``bt``.

A servo robot may also name ``kinematic_joints`` that follow commanded velocities while the
others are servoed, e.g. the WAM's joints of a ``"wam7_bhand"`` driven along a planned
trajectory while the BarrettHand's fingers yield to the object. The mass matrix of the servo
joints is then the block of ``M(q)`` on them: the inertial forces that the kinematic joints'
(or the base's) accelerations exert on the servo joints are neglected.

Servo. A PD law with torque limits on the actuated coordinates (for the BarrettHand the coupled
finger coordinates of :class:`~torchcontact.robots.JointCoupling`),

.. math::

    \tau = \mathrm{clip}\big(K_p (q^* - q^+) - K_d \dot q^+,\; -\tau_{max},\; \tau_{max}\big),
    \qquad q^+ = q + h \dot q^+ ,

is integrated implicitly, so that it is stable at any step (h = 10 ms with fingers of a few
grams and stiff gains). Per joint, the step first evaluates the torque at the start of the
step, ``K_p (q^* − q) − K_d q̇``: if its magnitude is within the limit, the joint is in the
linear regime and the implicit terms are folded into the problem, ``M_eff = M + h K_d +
h² K_p`` (diagonal added) and the generalized force ``K_p (q^* − q − h q̇) − K_d q̇``; otherwise
the joint is saturated and its torque is the constant ``± τ_max``. Gravity on the links
(:meth:`~torchcontact.robots.Robot.gravity_force`) is added in both cases (unless the servo
compensates it, ``gravity_compensation``); velocity-product
(Coriolis, centrifugal) terms of the joints and the inertial forces of an accelerating base
are neglected (slow, servoed motion).

Why a rigid grasp stays a feasible LCP: a finger squeezing a rigid box is a dynamic coordinate
with a finite mass and a bounded torque, not an infinitely stiff constraint; the normal
impulse a contact needs to stop it is finite (it balances ``h τ_max`` plus the momentum the
finger brings), and a saturated servo cannot demand more. The grip force is therefore the
torque limit mapped through the contact Jacobian, ``τ_max = Jnᵀ f_n`` at rest (for a prismatic
jaw, ``f_n = τ_max`` exactly).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from torchcontact._checks import check_float, describe
from torchcontact.geometry import quat_to_matrix
from torchcontact.robots import Robot

RobotMode = Literal["servo", "kinematic"]


@dataclass(frozen=True, eq=False)
class RobotMember:
    """A robot in a spatial scene (see the module docstring for the dynamics).

    Attributes:
        name: unique name among the scene's bodies and robots.
        robot: the robot (from :func:`torchcontact.robots.load`); it needs collision shapes,
            and link inertials in ``"servo"`` mode.
        mode: ``"servo"`` (joints are degrees of freedom driven by the PD servo towards
            commanded target positions) or ``"kinematic"`` (joints follow commanded
            velocities).
        stiffness: ``K_p``, N m/rad (N/m for prismatic joints), a number or ``(dof,)``.
        damping: ``K_d``, N m s/rad (N s/m), a number or ``(dof,)``.
        torque_limit: ``τ_max``, N m (N), ``> 0``, a number or ``(dof,)`` (``inf``: unlimited).
        base_pose: ``(7,)`` default world pose of the robot's base frame (its URDF root link):
            position and unit quaternion ``(w, x, y, z)``; default the identity.
        gravity_compensation: the servo also cancels the links' weight (adds
            ``−Σ m Jcᵀ g``), as the WAM's and many hands' controllers do; the torque limit
            then bounds the PD part only.
        kinematic_joints: names of actuated joints
            (:attr:`~torchcontact.robots.Robot.joint_names`) of a servo robot that follow
            commanded velocities instead (every joint of a ``"kinematic"`` robot does).
    """

    name: str
    robot: Robot
    mode: RobotMode = "servo"
    stiffness: float | Tensor = 10.0
    damping: float | Tensor = 0.1
    torque_limit: float | Tensor = float("inf")
    base_pose: Tensor | None = None
    gravity_compensation: bool = False
    kinematic_joints: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.name, str):
            raise ValueError(f"name must be a str, got {type(self.name).__name__}")
        if not isinstance(self.robot, Robot):
            raise ValueError(f"robot must be a Robot, got {describe(self.robot)}")
        if self.mode not in ("servo", "kinematic"):
            raise ValueError(f"mode must be 'servo' or 'kinematic', got {self.mode!r}")
        if not self.robot.collision_shapes:
            raise ValueError(
                f"robot: {self.robot.name!r} has no <collision> primitives to touch the scene"
            )
        if self.mode == "servo" and not self.robot.inertials:
            raise ValueError(
                f"robot: a servo robot needs link <inertial> elements, {self.robot.name!r} has none"
            )
        names = self.robot.joint_names
        if not isinstance(self.kinematic_joints, tuple) or any(
            name not in names for name in self.kinematic_joints
        ):
            raise ValueError(
                f"kinematic_joints must be a tuple of names among {list(names)}, got "
                f"{self.kinematic_joints!r}"
            )
        if not isinstance(self.gravity_compensation, bool):
            raise ValueError(
                f"gravity_compensation must be a bool, got {self.gravity_compensation!r}"
            )
        dof = self.robot.dof
        for name, low, strict in (
            ("stiffness", 0.0, False),
            ("damping", 0.0, False),
            ("torque_limit", 0.0, True),
        ):
            value = torch.as_tensor(getattr(self, name), dtype=torch.float64)
            if value.dim() > 1 or value.numel() not in (1, dof):
                raise ValueError(
                    f"{name} must be a number or have shape ({dof},), got {describe(value)}"
                )
            value = value.expand(dof).clone()
            if (
                bool(value.isnan().any())
                or bool((value < low).any())
                or (strict and bool((value <= low).any()))
            ):
                relation = ">" if strict else ">="
                raise ValueError(f"{name} must be {relation} {low}, got {value.tolist()}")
            if name != "torque_limit" and not bool(value.isfinite().all()):
                raise ValueError(f"{name} must be finite, got {value.tolist()}")
            object.__setattr__(self, name, value)
        if self.base_pose is None:
            object.__setattr__(
                self, "base_pose", torch.tensor([0.0, 0, 0, 1, 0, 0, 0], dtype=torch.float64)
            )
        else:
            pose = check_float("base_pose", self.base_pose, trailing=(7,), what="(7,)")
            if pose.dim() != 1 or abs(float(pose[3:].norm()) - 1.0) > 1e-9:
                raise ValueError(
                    f"base_pose must be (7,) with a unit quaternion, got {pose.tolist()}"
                )

    @property
    def dof(self) -> int:
        """The robot's actuated coordinates."""
        return self.robot.dof

    @property
    def servo_joints(self) -> tuple[int, ...]:
        """Indices (among the actuated coordinates) of the servoed joints, the robot's
        generalized coordinates in the contact problem."""
        if self.mode == "kinematic":
            return ()
        names = self.robot.joint_names
        return tuple(i for i, name in enumerate(names) if name not in self.kinematic_joints)

    @property
    def driven_joints(self) -> tuple[int, ...]:
        """Indices of the joints that follow commanded velocities."""
        servo = self.servo_joints
        return tuple(i for i in range(self.dof) if i not in servo)


def servo_terms(
    member: RobotMember, q: Tensor, qd: Tensor, target: Tensor, h: float
) -> tuple[Tensor, Tensor]:
    """The implicit PD servo's added mass and generalized force (module docstring).

    Args:
        member: the servo robot.
        q: ``(P, dof)`` joint positions.
        qd: ``(P, dof)`` joint velocities.
        target: ``(P, dof)`` commanded joint positions ``q*``.
        h: the time step.

    Returns:
        ``(P, dof)`` the diagonal ``h K_d + h² K_p`` added to the mass matrix (zero on saturated
        joints) and ``(P, dof)`` the servo's generalized force (without gravity).
    """
    assert isinstance(member.stiffness, Tensor)
    assert isinstance(member.damping, Tensor)
    assert isinstance(member.torque_limit, Tensor)
    kp, kd, limit = (t.to(q) for t in (member.stiffness, member.damping, member.torque_limit))
    start = kp * (target - q) - kd * qd
    saturated = start.abs() > limit
    linear = kp * (target - q - h * qd) - kd * qd
    torque = torch.where(saturated, torch.sign(start) * limit, linear)
    added = torch.where(saturated, 0.0, h * kd + h * h * kp)
    return added, torque


@dataclass(frozen=True, eq=False)
class RobotStep:
    """The robots of a flat batch of scene states at the start of a step, world frame.

    Attributes:
        origins: per robot, ``(P, L, 3)`` its link frames' origins.
        jacobians: per robot, ``(P, L, 6, Ns_r)`` the geometric Jacobians ``[v; ω]`` of its
            link frames' origins in the world frame, columns of its servo joints.
        known_twists: per robot, ``(P, L, 6)`` the links' twists ``(v, ω)`` (at each link
            origin) that do not depend on the problem's unknowns: the base's motion, plus the
            commanded velocities of its kinematic joints.
        shape_poses: ``(P, S, 7)`` world poses of every robot's collision primitives, robots
            in scene order.
        mass: ``(P, Ns, Ns)`` the servo robots' joint-space mass matrices with the implicit
            servo terms folded in, block diagonal (``Ns`` servo joints).
        force: ``(P, Ns)`` their generalized forces: servo torque plus gravity.
        velocity: ``(P, Ns)`` their joint velocities at the start of the step.
    """

    origins: tuple[Tensor, ...]
    jacobians: tuple[Tensor, ...]
    known_twists: tuple[Tensor, ...]
    shape_poses: Tensor
    mass: Tensor
    force: Tensor
    velocity: Tensor


def robot_step(
    members: tuple[RobotMember, ...],
    *,
    q_robot: Tensor,
    v_robot: Tensor,
    robot_base: Tensor,
    joint_command: Tensor | None,
    base_twist: Tensor | None,
    gravity: tuple[float, ...],
    h: float,
) -> RobotStep:
    """The :class:`RobotStep` of a flat batch ``(P,)``.

    Args:
        members: the scene's robots.
        q_robot: ``(P, Nj)`` joint positions, robots in order.
        v_robot: ``(P, Nj)`` joint velocities.
        robot_base: ``(P, R, 7)`` base poses, world frame.
        joint_command: ``(P, Nj)``: servo robots' target positions, kinematic robots' joint
            velocities; ``None``: servo targets at the current positions (damping only), no
            kinematic joint motion.
        base_twist: ``(P, R, 6)`` base twists ``(v, ω)`` (world frame, at the base frame's
            origin), or ``None`` (at rest).
        gravity: gravitational acceleration, world frame.
        h: time step.
    """
    P, dtype, device = q_robot.shape[0], q_robot.dtype, q_robot.device
    g = torch.tensor(gravity, dtype=dtype, device=device)
    origins, jacobians, known, shapes, masses, forces, velocities = [], [], [], [], [], [], []
    start = 0
    for r, member in enumerate(members):
        robot, span = member.robot, slice(start, start + member.dof)
        start += member.dof
        q, qd = q_robot[:, span], v_robot[:, span]
        base = robot_base[:, r]
        rotation = quat_to_matrix(base[:, 3:])  # (P, 3, 3)
        links = robot.link_jacobians(q)
        transforms, jacobian = links  # (P, L, 4, 4), (P, L, 6, dof)
        turn = rotation.unsqueeze(1)
        origin = (turn @ transforms[..., :3, 3:]).squeeze(-1) + base[:, None, :3]
        link_rotation = turn @ transforms[..., :3, :3]
        jacobian = torch.cat([turn @ jacobian[..., :3, :], turn @ jacobian[..., 3:, :]], dim=-2)
        twist = origin.new_zeros(P, origin.shape[1], 6)
        if base_twist is not None:
            spin = base_twist[:, r, None, 3:].expand_as(origin)
            linear = base_twist[:, r, None, :3] + torch.linalg.cross(
                spin, origin - base[:, None, :3]
            )
            twist = torch.cat([linear, spin], dim=-1)
        servo = torch.tensor(member.servo_joints, dtype=torch.long, device=device)
        driven = torch.tensor(member.driven_joints, dtype=torch.long, device=device)
        if driven.numel() and joint_command is not None:
            rates = joint_command[:, span].index_select(-1, driven)
            twist = twist + (jacobian.index_select(-1, driven) @ rates[:, None, :, None]).squeeze(
                -1
            )
        for link_shape in robot.collision_shapes:
            frame = robot.link_names.index(link_shape.link)
            local = link_shape.pose.to(dtype=dtype, device=device)
            position = (link_rotation[:, frame] @ local[:3, None]).squeeze(-1) + origin[:, frame]
            orientation = _rotation_quaternion(link_rotation[:, frame] @ quat_to_matrix(local[3:]))
            shapes.append(torch.cat([position, orientation], dim=-1))
        origins.append(origin)
        jacobians.append(jacobian.index_select(-1, servo))
        known.append(twist)
        if servo.numel():
            target = q if joint_command is None else joint_command[:, span]
            added, torque = servo_terms(member, q, qd, target, h)
            if not member.gravity_compensation:
                torque = torque + robot.gravity_force(q, g @ rotation)  # gravity Rᵀ g, base frame
            mass = robot.mass_matrix(q, links=links)
            mass = mass.index_select(-1, servo).index_select(-2, servo)
            masses.append(mass + torch.diag_embed(added.index_select(-1, servo)))
            forces.append(torque.index_select(-1, servo))
            velocities.append(qd.index_select(-1, servo))
    mass = _batched_block_diag(masses) if masses else q_robot.new_zeros(P, 0, 0)
    empty = q_robot.new_zeros(P, 0)
    return RobotStep(
        origins=tuple(origins),
        jacobians=tuple(jacobians),
        known_twists=tuple(known),
        shape_poses=torch.stack(shapes, dim=1) if shapes else q_robot.new_zeros(P, 0, 7),
        mass=mass,
        force=torch.cat(forces, dim=-1) if forces else empty,
        velocity=torch.cat(velocities, dim=-1) if velocities else empty,
    )


def _batched_block_diag(blocks: list[Tensor]) -> Tensor:
    """``(P, Σn, Σn)`` the block-diagonal matrix of ``(P, nᵢ, nᵢ)`` blocks."""
    total = sum(block.shape[-1] for block in blocks)
    rows, start = [], 0
    for block in blocks:
        n = block.shape[-1]
        left = block.new_zeros(*block.shape[:-1], start)
        right = block.new_zeros(*block.shape[:-1], total - start - n)
        rows.append(torch.cat([left, block, right], dim=-1))
        start += n
    return torch.cat(rows, dim=-2)


def _rotation_quaternion(rotation: Tensor) -> Tensor:
    """``(*B, 4)`` unit quaternions ``(w, x, y, z)`` of rotation matrices ``(*B, 3, 3)``.

    Shepperd's method: of the four expressions ``4w² = 1 + tr R``, ``4x² = 1 + R₀₀ − R₁₁ − R₂₂``
    (and ``y``, ``z`` alike) the largest (``≥ 1``) gives one component by a square root and the
    others by division, which is accurate and differentiable for every rotation. (Every
    branch is evaluated with its square root's argument clamped to ``≥ 1e-12``, so that the
    branches not taken have finite values and zero gradients.)

    Reference: S. W. Shepperd, "Quaternion from rotation matrix", Journal of Guidance and
    Control 1(3), 1978.
    """
    r = rotation
    r00, r11, r22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    w_x, w_y, w_z = (
        r[..., 2, 1] - r[..., 1, 2],
        r[..., 0, 2] - r[..., 2, 0],
        r[..., 1, 0] - r[..., 0, 1],
    )
    xy, xz, yz = (
        r[..., 0, 1] + r[..., 1, 0],
        r[..., 0, 2] + r[..., 2, 0],
        r[..., 1, 2] + r[..., 2, 1],
    )
    squares = torch.stack(
        [1 + r00 + r11 + r22, 1 + r00 - r11 - r22, 1 - r00 + r11 - r22, 1 - r00 - r11 + r22],
        dim=-1,
    )
    s = 2 * torch.sqrt(squares.clamp(min=1e-12))  # 4 |component| per branch
    candidates = torch.stack(
        [
            torch.stack([s[..., 0] / 4, w_x / s[..., 0], w_y / s[..., 0], w_z / s[..., 0]], -1),
            torch.stack([w_x / s[..., 1], s[..., 1] / 4, xy / s[..., 1], xz / s[..., 1]], -1),
            torch.stack([w_y / s[..., 2], xy / s[..., 2], s[..., 2] / 4, yz / s[..., 2]], -1),
            torch.stack([w_z / s[..., 3], xz / s[..., 3], yz / s[..., 3], s[..., 3] / 4], -1),
        ],
        dim=-2,
    )  # (*B, 4 branches, 4)
    best = squares.argmax(-1)[..., None, None].expand(*squares.shape[:-1], 1, 4)
    return candidates.gather(-2, best).squeeze(-2)
