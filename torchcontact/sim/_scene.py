"""Scenes, planar or spatial: bodies, their kinds and mass properties, friction, gravity and
contact pairs."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal

import torch
from torch import Tensor

from torchcontact._checks import check_float, check_int, check_positive, check_real, describe
from torchcontact.geometry import (
    SPATIAL_SLOT_COUNTS,
    Box,
    Capsule,
    HalfPlane,
    HalfSpace,
    Polygon,
    Sphere,
)
from torchcontact.sim._robot_member import RobotMember

BodyKind = Literal["dynamic", "kinematic", "static"]
#: Shapes of planar scenes, and of spatial scenes.
PLANAR_SHAPES = (Polygon, HalfPlane)
SPATIAL_SHAPES = (Box, Sphere, Capsule, HalfSpace)
#: Pose and twist sizes by dimension: ``(x, y, θ)``, ``(vx, vy, ω)`` in the plane;
#: position + unit quaternion ``(w, x, y, z)``, ``(v, ω)`` in space.
POSE_SIZE = {2: 3, 3: 7}
TWIST_SIZE = {2: 3, 3: 6}
#: Default speed in m/s at which a spatial scene's contacts push penetrating bodies apart.
SPATIAL_RECOVERY_SPEED = 0.1


@dataclass(frozen=True, eq=False)
class Body:
    """A rigid body of a planar or spatial scene.

    Attributes:
        name: unique name in the scene.
        shape: planar: a convex :class:`~torchcontact.geometry.Polygon` (body frame at its
            centroid) or, for static bodies only, a :class:`~torchcontact.geometry.HalfPlane`;
            spatial: a :class:`~torchcontact.geometry.Box`,
            :class:`~torchcontact.geometry.Sphere` or :class:`~torchcontact.geometry.Capsule`
            (body frame at the centroid, along the principal axes) or, for static bodies only,
            a :class:`~torchcontact.geometry.HalfSpace`.
        kind: ``"dynamic"`` (moved by the contact dynamics), ``"kinematic"`` (its twist is a
            control input, e.g. a robot finger) or ``"static"`` (fixed).
        mass: mass in kg of a dynamic body: a float, or a scalar tensor (which may require
            grad). Default: ``density × area``.
        inertia: planar: moment of inertia about the centroid, kg·m²; spatial: the ``(3, 3)``
            inertia tensor about the centroid in the body frame. Default: uniform density,
            ``mass × unit_inertia`` of the shape (so a tensor mass carries its gradient into
            the inertia).
        density: density used when ``mass`` is not given: kg/m² (planar), kg/m³ (spatial).
        pose: world pose of a static polygon, box, sphere or capsule (ignored otherwise):
            ``(3,)`` ``(x, y, θ)``, or ``(7,)`` position and unit quaternion ``(w, x, y, z)``.
    """

    name: str
    shape: Polygon | HalfPlane
    kind: BodyKind = "dynamic"
    mass: float | Tensor | None = None
    inertia: float | Tensor | None = None
    density: float = 100.0
    pose: Tensor | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str):
            raise ValueError(f"name must be a str, got {type(self.name).__name__}")
        if not isinstance(self.kind, str) or self.kind not in ("dynamic", "kinematic", "static"):
            raise ValueError(f"kind must be 'dynamic', 'kinematic' or 'static', got {self.kind!r}")
        if not isinstance(self.shape, PLANAR_SHAPES + SPATIAL_SHAPES):
            raise ValueError(
                f"body {self.name!r}: shape must be a Polygon or a HalfPlane (planar), or a "
                f"Box, Sphere, Capsule or HalfSpace (spatial), got {describe(self.shape)}"
            )
        if isinstance(self.shape, (HalfPlane, HalfSpace)) and self.kind != "static":
            raise ValueError(
                f"body {self.name!r}: a {type(self.shape).__name__} can only be static"
            )
        size = POSE_SIZE[self.dimension]
        needs_pose = self.kind == "static" and not isinstance(self.shape, (HalfPlane, HalfSpace))
        if needs_pose and self.pose is None:
            raise ValueError(
                f"pose: body {self.name!r} is a static {type(self.shape).__name__} and needs a "
                f"pose ({size},)"
            )
        if self.pose is not None:
            check_float("pose", self.pose, trailing=(size,), min_ndim=1, what=f"({size},)")
            if self.pose.dim() != 1:
                raise ValueError(f"pose must have shape ({size},), got {tuple(self.pose.shape)}")
            if size == 7 and abs(float(self.pose[3:].norm()) - 1.0) > 1e-9:
                quaternion = self.pose[3:].tolist()
                raise ValueError(
                    f"pose: the quaternion pose[3:] must have unit norm, got {quaternion}"
                )
        check_positive("density", self.density)
        inertia_shape = () if self.dimension == 2 else (3, 3)
        for name, shape in (("mass", ()), ("inertia", inertia_shape)):
            value = getattr(self, name)
            if isinstance(value, Tensor) or (name == "inertia" and shape and value is not None):
                value = check_float(name, torch.as_tensor(value), what=str(shape))
                if tuple(value.shape) != shape:
                    raise ValueError(f"{name} must have shape {shape}, got {describe(value)}")
                if shape:
                    object.__setattr__(self, name, value)
                    eigenvalues = torch.linalg.eigvalsh(value.detach().double())
                    symmetric = bool(torch.allclose(value, value.mT, rtol=1e-9, atol=0.0))
                    if not symmetric or not float(eigenvalues.min()) > 0:
                        raise ValueError(
                            f"inertia must be symmetric positive definite, got {value.tolist()}"
                        )
                elif not float(value.detach()) > 0:
                    raise ValueError(f"{name} must be > 0, got {float(value)}")
            elif value is not None:
                check_positive(name, value)

    @property
    def dimension(self) -> int:
        """2 for a planar shape, 3 for a spatial one."""
        return 2 if isinstance(self.shape, PLANAR_SHAPES) else 3

    def mass_value(self) -> Tensor:
        """The mass as a float64 scalar tensor (keeps a tensor's graph)."""
        if self.mass is not None:
            return torch.as_tensor(self.mass, dtype=torch.float64)
        if isinstance(self.shape, Polygon):
            return torch.tensor(self.density * self.shape.area, dtype=torch.float64)
        assert isinstance(self.shape, (Box, Sphere, Capsule))
        return torch.tensor(self.density * self.shape.volume, dtype=torch.float64)

    def inertia_value(self) -> Tensor:
        """The inertia about the centroid, float64 (keeps a tensor's graph): a scalar tensor
        (planar) or the ``(3, 3)`` body-frame tensor (spatial)."""
        if self.inertia is not None:
            return torch.as_tensor(self.inertia, dtype=torch.float64)
        assert isinstance(self.shape, (Polygon, Box, Sphere, Capsule))
        return self.mass_value() * torch.as_tensor(self.shape.unit_inertia(), dtype=torch.float64)


@dataclass(frozen=True)
class SlotGroup:
    """The slots contributed by one ordered shape pair: vertices of ``receiver`` against ``other``.

    Attributes:
        receiver: index into ``Scene.bodies`` of the body whose vertices make the slots.
        other: index of the body they may touch (the normal points from it into ``receiver``).
        start: index of the group's first slot in the scene's slot list.
        count: number of slots (the receiver's vertices).
    """

    receiver: int
    other: int
    start: int
    count: int


@dataclass(frozen=True)
class RobotSlotGroup:
    """The slots between one robot collision primitive and one dynamic body.

    The primitive is the slots' receiver (the normal points from the body into it).

    Attributes:
        robot: index into ``Scene.robots``.
        shape: index into that robot's :attr:`~torchcontact.robots.Robot.collision_shapes`.
        other: index into ``Scene.bodies`` of the dynamic body.
        start: index of the group's first slot in the scene's slot list (after every
            :class:`SlotGroup`'s).
        count: number of slots.
    """

    robot: int
    shape: int
    other: int
    start: int
    count: int


@dataclass(frozen=True, eq=False)
class Scene:
    """A scene of rigid bodies: planar (in a vertical plane) or spatial, by its shapes.

    Generalized coordinates are the dynamic bodies' twists in scene order: ``(vx, vy, ω)``
    per body in a planar scene (``n = 3 Nd``), ``(v, ω)`` in a spatial one (``n = 6 Nd``);
    kinematic bodies' poses are part of the state and their twists are the control; static
    bodies never move. Every pair of bodies that includes a dynamic one can touch. Planar: a
    polygon pair contributes a slot for every vertex of each against the other, a
    polygon–half-plane pair one slot per polygon vertex. Spatial: a pair contributes the
    fixed number of slots of its shape types
    (:data:`~torchcontact.geometry.SPATIAL_SLOT_COUNTS`), with ``friction_directions``
    directions per contact.

    The polyhedral friction cone of ``D`` directions is inscribed in Coulomb's circular cone:
    friction against sliding along a direction is ``μ pn``, and midway between two
    directions it is ``μ pn cos(π/D)``. ``D = 8`` (the default) keeps every direction within
    8 % of the circular cone at twice the unknowns of ``D = 4`` (29 %).

    Robots (spatial scenes only, :class:`~torchcontact.sim.RobotMember`): each collision
    primitive of a robot's links touches every dynamic body (not the static or kinematic
    bodies, nor other primitives), with the slots of its shape pair; these slots follow the
    bodies' slots. A servo robot's actuated joints follow the dynamic bodies' twists in the
    generalized velocity, robots in scene order: ``n = 6 Nd + Σ dof`` over the servo robots.

    Penetration is removed by the contacts' gap term ``φ/h``: a body found ``d`` deep would
    leave at ``d/h`` (0.5 m/s for 5 mm at h = 10 ms). ``recovery_speed`` bounds that speed:
    the gap enters the problem as ``max(φ, −h · recovery_speed)``.

    Attributes:
        bodies: the bodies, names unique, all planar or all spatial.
        h: time step in seconds.
        gravity: gravitational acceleration in m/s², world frame: ``(gx, gy)`` planar,
            ``(gx, gy, gz)`` spatial; default ``(0, −9.81)`` or ``(0, 0, −9.81)``.
        friction: default friction coefficient of a pair (float or tensor broadcastable to the
            batch, which may require grad).
        pair_friction: friction of named pairs ``{(name_a, name_b): μ}`` (either order).
        margin: gap below which a slot becomes a contact candidate, metres.
        friction_directions: ``D`` of a spatial scene, even and ``>= 4`` (planar scenes have
            ``+t`` and ``−t``).
        recovery_speed: the largest speed in m/s at which contacts push penetrating bodies
            apart; default unbounded for planar scenes and ``SPATIAL_RECOVERY_SPEED``
            (0.1 m/s) for spatial ones.
        robots: the robots in the scene (spatial scenes), names unique among bodies and
            robots.
    """

    bodies: tuple[Body, ...]
    h: float = 0.01
    gravity: tuple[float, ...] | None = None
    friction: float | Tensor = 0.5
    pair_friction: Mapping[tuple[str, str], float | Tensor] = field(default_factory=dict)
    margin: float = 0.02
    friction_directions: int = 8
    recovery_speed: float | None = None
    robots: tuple[RobotMember, ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.bodies, tuple) or not all(isinstance(b, Body) for b in self.bodies):
            raise ValueError(f"bodies must be a tuple of Body, got {describe(self.bodies)}")
        names = [body.name for body in self.bodies]
        if len(set(names)) != len(names):
            raise ValueError(f"bodies must have unique names, got {names}")
        if not self.dynamic:
            raise ValueError("bodies must include at least one dynamic body")
        dimensions = {body.dimension for body in self.bodies}
        if len(dimensions) != 1:
            kinds = [f"{body.name}: {type(body.shape).__name__}" for body in self.bodies]
            raise ValueError(f"bodies must be all planar or all spatial, got {kinds}")
        check_positive("h", self.h)
        check_real("margin", self.margin, low=0.0)
        dimension = self.dimension
        if not isinstance(self.robots, tuple) or not all(
            isinstance(r, RobotMember) for r in self.robots
        ):
            raise ValueError(f"robots must be a tuple of RobotMember, got {describe(self.robots)}")
        if self.robots and dimension != 3:
            raise ValueError("robots: only spatial scenes can hold robots")
        members = names + [robot.name for robot in self.robots]
        if len(set(members)) != len(members):
            raise ValueError(
                f"robots must have names unique among bodies and robots, got {members}"
            )
        if self.gravity is None:
            object.__setattr__(
                self, "gravity", (0.0, -9.81) if dimension == 2 else (0.0, 0.0, -9.81)
            )
        names_of_axes = "(gx, gy)" if dimension == 2 else "(gx, gy, gz)"
        if not isinstance(self.gravity, tuple) or len(self.gravity) != dimension:
            raise ValueError(f"gravity must be a tuple {names_of_axes}, got {self.gravity!r}")
        check_int("friction_directions", self.friction_directions, low=4)
        if self.friction_directions % 2:
            raise ValueError(f"friction_directions must be even, got {self.friction_directions}")
        if self.recovery_speed is None:
            speed = math.inf if dimension == 2 else SPATIAL_RECOVERY_SPEED
            object.__setattr__(self, "recovery_speed", speed)
        if not (isinstance(self.recovery_speed, (int, float)) and self.recovery_speed > 0):
            raise ValueError(f"recovery_speed must be a number > 0, got {self.recovery_speed!r}")
        for index, component in enumerate(self.gravity):
            check_real(f"gravity[{index}]", component)
        _check_friction("friction", self.friction)
        if not isinstance(self.pair_friction, Mapping):
            raise ValueError(f"pair_friction must be a mapping, got {describe(self.pair_friction)}")
        for pair, value in self.pair_friction.items():
            if not isinstance(pair, tuple) or len(pair) != 2:
                raise ValueError(f"pair_friction keys must be name pairs, got {pair!r}")
            a, b = pair
            if a not in members or b not in members:
                raise ValueError(f"pair_friction names an unknown body pair ({a!r}, {b!r})")
            _check_friction(f"pair_friction[{pair!r}]", value)

    @cached_property
    def dynamic(self) -> tuple[int, ...]:
        """Indices of the dynamic bodies (their order defines the generalized coordinates)."""
        return tuple(i for i, body in enumerate(self.bodies) if body.kind == "dynamic")

    @cached_property
    def kinematic(self) -> tuple[int, ...]:
        """Indices of the kinematic bodies (their order defines the control)."""
        return tuple(i for i, body in enumerate(self.bodies) if body.kind == "kinematic")

    @cached_property
    def dimension(self) -> int:
        """2 for a planar scene, 3 for a spatial one."""
        return self.bodies[0].dimension

    @property
    def pose_size(self) -> int:
        """Entries of a body pose: 3 ``(x, y, θ)`` or 7 (position, unit quaternion)."""
        return POSE_SIZE[self.dimension]

    @property
    def twist_size(self) -> int:
        """Entries of a body twist: 3 ``(vx, vy, ω)`` or 6 ``(v, ω)``."""
        return TWIST_SIZE[self.dimension]

    @property
    def num_dofs(self) -> int:
        """``n``: three (planar) or six (spatial) per dynamic body, then the servo robots'
        joints."""
        return self.twist_size * len(self.dynamic) + self.num_servo_joints

    @property
    def num_robot_joints(self) -> int:
        """``Nj``: the actuated joints of every robot, in robot order (the state's
        ``q_robot``)."""
        return sum(robot.dof for robot in self.robots)

    @property
    def num_servo_joints(self) -> int:
        """The actuated joints of the servo robots (generalized coordinates)."""
        return sum(len(robot.servo_joints) for robot in self.robots)

    @cached_property
    def servo_columns(self) -> tuple[int, ...]:
        """Where the servo joints sit among every robot's actuated joints (``q_robot``'s
        entries), in the order of the problem's generalized coordinates after the dynamic
        bodies' twists."""
        columns: list[int] = []
        offset = 0
        for robot in self.robots:
            columns.extend(offset + joint for joint in robot.servo_joints)
            offset += robot.dof
        return tuple(columns)

    @cached_property
    def robot_slot_groups(self) -> tuple[RobotSlotGroup, ...]:
        """The slot groups of every robot collision primitive against every dynamic body."""
        groups: list[RobotSlotGroup] = []
        start = sum(group.count for group in self.slot_groups)
        for r, member in enumerate(self.robots):
            for s, link_shape in enumerate(member.robot.collision_shapes):
                for body in self.dynamic:
                    kinds = (
                        type(link_shape.shape).__name__,
                        type(self.bodies[body].shape).__name__,
                    )
                    count = SPATIAL_SLOT_COUNTS.get(kinds) or SPATIAL_SLOT_COUNTS[kinds[::-1]]
                    groups.append(RobotSlotGroup(r, s, body, start, count))
                    start += count
        return tuple(groups)

    def index(self, name: str) -> int:
        """Index of the body called ``name``."""
        for i, body in enumerate(self.bodies):
            if body.name == name:
                return i
        raise ValueError(f"no body named {name!r}")

    @cached_property
    def slot_groups(self) -> tuple[SlotGroup, ...]:
        """The slot groups of every pair that can touch, in a fixed order."""
        groups: list[SlotGroup] = []
        start = 0
        for i, a in enumerate(self.bodies):
            for j in range(i + 1, len(self.bodies)):
                b = self.bodies[j]
                if "dynamic" not in (a.kind, b.kind):
                    continue
                if self.dimension == 3:
                    # One group per pair, its slots on the body that is not a half-space.
                    receiver, other = (j, i) if isinstance(a.shape, HalfSpace) else (i, j)
                    count = _spatial_slot_count(a, b)
                    groups.append(SlotGroup(receiver, other, start, count))
                    start += count
                    continue
                for receiver, other in ((i, j), (j, i)):
                    shape = self.bodies[receiver].shape
                    if isinstance(shape, HalfPlane):
                        continue
                    groups.append(SlotGroup(receiver, other, start, shape.num_vertices))
                    start += shape.num_vertices
        return tuple(groups)

    @property
    def num_slots(self) -> int:
        """``K``, the total number of contact slots (bodies' slots, then robots')."""
        bodies = sum(group.count for group in self.slot_groups)
        return bodies + sum(group.count for group in self.robot_slot_groups)

    def pair_mu(self, a: int, b: int, *, robot: bool = False) -> float | Tensor:
        """Friction coefficient between bodies ``a`` and ``b`` (with ``robot``: between the
        robot ``a`` of ``Scene.robots`` and body ``b``; ``pair_friction`` names robots by their
        member name)."""
        first = self.robots[a].name if robot else self.bodies[a].name
        names = (first, self.bodies[b].name)
        for key in (names, names[::-1]):
            if key in self.pair_friction:
                return self.pair_friction[key]
        return self.friction

    def mass_matrix(self) -> Tensor:
        """``(n, n)`` float64 block-diagonal mass matrix ``diag(m, m, I)`` per dynamic body of
        a planar scene (a spatial scene's depends on the pose:
        :func:`~torchcontact.sim.spatial_mass_matrix`)."""
        if self.dimension != 2:
            raise ValueError("mass_matrix: a spatial scene's mass matrix depends on the pose")
        diagonal = []
        for i in self.dynamic:
            mass = self.bodies[i].mass_value()
            diagonal.extend([mass, mass, self.bodies[i].inertia_value()])
        return torch.diag(torch.stack(diagonal))

    def point_force(self, q: Tensor, *, body: str, point: Tensor, force: Tensor) -> Tensor:
        """Generalized force of a force applied at a point of a dynamic body.

        Args:
            q: ``(*B, Nd, 3)`` dynamic-body poses (world frame).
            body: name of the dynamic body.
            point: ``(*B, 2)`` or ``(2,)`` application point in the body's frame, metres.
            force: ``(*B, 2)`` or ``(2,)`` force in the world frame, newtons.

        Returns:
            ``(*B, Nd, 3)`` generalized force ``(fx, fy, τ)``, with ``τ = r × F`` for the
            world offset ``r`` of the point, on that body and zero elsewhere.
        """
        if self.dimension != 2:
            raise ValueError("point_force: only for planar scenes")
        index = self.index(body)
        if index not in self.dynamic:
            raise ValueError(f"body must name a dynamic body, got {body!r}")
        column = self.dynamic.index(index)
        pose = q[..., column, :]
        cos, sin = torch.cos(pose[..., 2]), torch.sin(pose[..., 2])
        offset = torch.stack(
            [cos * point[..., 0] - sin * point[..., 1], sin * point[..., 0] + cos * point[..., 1]],
            dim=-1,
        )
        torque = offset[..., 0] * force[..., 1] - offset[..., 1] * force[..., 0]
        wrench = torch.cat([force.expand_as(offset), torque.unsqueeze(-1)], dim=-1)
        columns = [torch.zeros_like(wrench)] * len(self.dynamic)
        columns[column] = wrench
        return torch.stack(columns, dim=-2)

    def masses(self) -> Tensor:
        """``(Nd,)`` float64 masses of the dynamic bodies."""
        return torch.stack([self.bodies[i].mass_value() for i in self.dynamic])

    def inertias(self) -> Tensor:
        """Inertias about the centroids of the dynamic bodies, float64: ``(Nd,)`` planar,
        ``(Nd, 3, 3)`` body-frame tensors spatial."""
        return torch.stack([self.bodies[i].inertia_value() for i in self.dynamic])


def _spatial_slot_count(a: Body, b: Body) -> int:
    """Slots of the contact routine between two spatial bodies' shapes (every pair of types
    that can touch has one)."""
    kinds = (type(a.shape).__name__, type(b.shape).__name__)
    return SPATIAL_SLOT_COUNTS.get(kinds) or SPATIAL_SLOT_COUNTS[kinds[::-1]]


def _check_friction(name: str, value: object) -> None:
    """Check a friction coefficient: a finite real ``>= 0`` or such a float tensor.

    Raises:
        ValueError: naming ``name`` otherwise.
    """
    if isinstance(value, Tensor):
        check_float(name, value)
        if value.numel() and float(value.detach().min()) < 0:
            raise ValueError(f"{name} must be >= 0, got minimum {float(value.detach().min())}")
    else:
        check_real(name, value, low=0.0)
