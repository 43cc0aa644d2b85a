"""Planar scenes: bodies, their kinds and mass properties, friction, gravity and contact pairs."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal

import torch
from torch import Tensor

from torchcontact._checks import check_float, check_positive, check_real, describe
from torchcontact.geometry import HalfPlane, Polygon

BodyKind = Literal["dynamic", "kinematic", "static"]


@dataclass(frozen=True, eq=False)
class Body:
    """A rigid body of a planar scene.

    Attributes:
        name: unique name in the scene.
        shape: a convex :class:`~torchcontact.geometry.Polygon` (body frame at its centroid) or,
            for static bodies only, a :class:`~torchcontact.geometry.HalfPlane`.
        kind: ``"dynamic"`` (moved by the contact dynamics), ``"kinematic"`` (its twist is a
            control input, e.g. a robot finger) or ``"static"`` (fixed).
        mass: mass in kg of a dynamic body: a float, or a scalar tensor (which may require
            grad). Default: ``density × area``.
        inertia: moment of inertia about the centroid, kg·m². Default: uniform density,
            ``mass × ∫r² dA / A`` (so a tensor mass carries its gradient into the inertia).
        density: areal density in kg/m² used when ``mass`` is not given.
        pose: ``(3,)`` world pose ``(x, y, θ)`` of a static polygon (ignored otherwise).
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
        if isinstance(self.shape, HalfPlane) and self.kind != "static":
            raise ValueError(f"body {self.name!r}: a HalfPlane can only be static")
        if not isinstance(self.shape, (Polygon, HalfPlane)):
            raise ValueError(f"body {self.name!r}: shape must be a Polygon or a HalfPlane")
        needs_pose = self.kind == "static" and isinstance(self.shape, Polygon)
        if needs_pose and self.pose is None:
            raise ValueError(f"pose: body {self.name!r} is a static polygon and needs a pose (3,)")
        if self.pose is not None:
            check_float("pose", self.pose, trailing=(3,), min_ndim=1, what="(3,)")
            if self.pose.dim() != 1:
                raise ValueError(f"pose must have shape (3,), got {tuple(self.pose.shape)}")
        check_positive("density", self.density)
        for name in ("mass", "inertia"):
            value = getattr(self, name)
            if isinstance(value, Tensor):
                check_float(name, value, what="()")
                if value.dim() != 0:
                    raise ValueError(f"{name} must be a scalar tensor, got {describe(value)}")
                if not float(value.detach()) > 0:
                    raise ValueError(f"{name} must be > 0, got {float(value)}")
            elif value is not None:
                check_positive(name, value)

    def mass_value(self) -> Tensor:
        """The mass as a float64 scalar tensor (keeps a tensor's graph)."""
        if self.mass is not None:
            return torch.as_tensor(self.mass, dtype=torch.float64)
        assert isinstance(self.shape, Polygon)
        return torch.tensor(self.density * self.shape.area, dtype=torch.float64)

    def inertia_value(self) -> Tensor:
        """The moment of inertia about the centroid as a float64 scalar tensor."""
        if self.inertia is not None:
            return torch.as_tensor(self.inertia, dtype=torch.float64)
        assert isinstance(self.shape, Polygon)
        return self.mass_value() * self.shape.unit_inertia()


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


@dataclass(frozen=True, eq=False)
class Scene:
    """A planar scene of rigid bodies in a vertical plane.

    Generalized coordinates are the dynamic bodies' poses ``(x, y, θ)`` in scene order
    (``n = 3 × number of dynamic bodies``); kinematic bodies' poses are part of the state and
    their twists are the control; static bodies never move. Every pair of bodies that
    includes a dynamic one can touch: a polygon pair contributes a slot for every vertex of
    each against the other, a polygon–half-plane pair one slot per polygon vertex.

    Attributes:
        bodies: the bodies, names unique.
        h: time step in seconds.
        gravity: gravitational acceleration ``(gx, gy)`` in m/s², world frame.
        friction: default friction coefficient of a pair (float or tensor broadcastable to the
            batch, which may require grad).
        pair_friction: friction of named pairs ``{(name_a, name_b): μ}`` (either order).
        margin: gap below which a slot becomes a contact candidate, metres.
    """

    bodies: tuple[Body, ...]
    h: float = 0.01
    gravity: tuple[float, float] = (0.0, -9.81)
    friction: float | Tensor = 0.5
    pair_friction: Mapping[tuple[str, str], float | Tensor] = field(default_factory=dict)
    margin: float = 0.02

    def __post_init__(self) -> None:
        if not isinstance(self.bodies, tuple) or not all(isinstance(b, Body) for b in self.bodies):
            raise ValueError(f"bodies must be a tuple of Body, got {describe(self.bodies)}")
        names = [body.name for body in self.bodies]
        if len(set(names)) != len(names):
            raise ValueError(f"bodies must have unique names, got {names}")
        if not self.dynamic:
            raise ValueError("bodies must include at least one dynamic body")
        check_positive("h", self.h)
        check_real("margin", self.margin, low=0.0)
        if not isinstance(self.gravity, tuple) or len(self.gravity) != 2:
            raise ValueError(f"gravity must be a pair (gx, gy), got {self.gravity!r}")
        for index, component in enumerate(self.gravity):
            check_real(f"gravity[{index}]", component)
        _check_friction("friction", self.friction)
        if not isinstance(self.pair_friction, Mapping):
            raise ValueError(f"pair_friction must be a mapping, got {describe(self.pair_friction)}")
        for pair, value in self.pair_friction.items():
            if not isinstance(pair, tuple) or len(pair) != 2:
                raise ValueError(f"pair_friction keys must be name pairs, got {pair!r}")
            a, b = pair
            if a not in names or b not in names:
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

    @property
    def num_dofs(self) -> int:
        """``n``, three per dynamic body."""
        return 3 * len(self.dynamic)

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
                for receiver, other in ((i, j), (j, i)):
                    shape = self.bodies[receiver].shape
                    if isinstance(shape, HalfPlane):
                        continue
                    groups.append(SlotGroup(receiver, other, start, shape.num_vertices))
                    start += shape.num_vertices
        return tuple(groups)

    @property
    def num_slots(self) -> int:
        """``K``, the total number of contact slots."""
        return sum(group.count for group in self.slot_groups)

    def pair_mu(self, a: int, b: int) -> float | Tensor:
        """Friction coefficient between bodies ``a`` and ``b``."""
        names = (self.bodies[a].name, self.bodies[b].name)
        for key in (names, names[::-1]):
            if key in self.pair_friction:
                return self.pair_friction[key]
        return self.friction

    def mass_matrix(self) -> Tensor:
        """``(n, n)`` float64 block-diagonal mass matrix ``diag(m, m, I)`` per dynamic body."""
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
