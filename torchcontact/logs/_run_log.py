"""The in-memory form of a recorded run: time-major tensors, checked on construction."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from torchcontact._checks import all_finite, describe

F64 = torch.float64


def _check(name: str, value: object, dtype: torch.dtype, shape: tuple[int, ...]) -> Tensor:
    """``value`` as a CPU tensor of ``dtype`` and ``shape``; float ones finite."""
    if not isinstance(value, Tensor) or value.dtype != dtype or tuple(value.shape) != shape:
        raise ValueError(
            f"{name}: expected a {dtype} tensor of shape {shape}, got {describe(value)}"
        )
    if value.device.type != "cpu":
        raise ValueError(f"{name}: expected a CPU tensor, got one on {value.device}")
    if value.is_floating_point() and not all_finite(value):
        raise ValueError(f"{name}: expected finite values, got NaN or inf")
    return value


def _check_names(name: str, value: object) -> tuple[str, ...]:
    if not isinstance(value, tuple) or not all(isinstance(v, str) and v for v in value):
        raise ValueError(f"{name}: expected a tuple of non-empty str, got {value!r}")
    if len(set(value)) != len(value):
        raise ValueError(f"{name}: expected distinct names, got {value!r}")
    return value


@dataclass(frozen=True, eq=False)
class ContactTruth:
    """The simulator's contact slots over each step of a run (ground truth), ``K`` slots.

    Attributes:
        mode: ``(T, K)`` int64 slot modes (0 separated, 1 sticking, ``2 + d`` sliding along
            friction direction ``d``).
        normal_impulse: ``(T, K)`` float64 normal impulses, N s.
        friction_impulse: ``(T, K, 2)`` float64 friction impulses along ``+t`` and ``-t``, N s.
        point: ``(T, K, 2)`` float64 slot points at the start of each step, world frame, m.
        normal: ``(T, K, 2)`` float64 slot unit normals, world frame.
        candidate: ``(T, K)`` bool: the slot is a real candidate.
        solver: ``(T,)`` int64 solver code of each step (:class:`~torchcontact.sim.StepResult`).
    """

    mode: Tensor
    normal_impulse: Tensor
    friction_impulse: Tensor
    point: Tensor
    normal: Tensor
    candidate: Tensor
    solver: Tensor

    def __post_init__(self) -> None:
        mode = self.mode
        if not isinstance(mode, Tensor) or mode.dim() != 2:
            raise ValueError(f"mode: expected a (T, K) int64 tensor, got {describe(mode)}")
        T, K = mode.shape
        _check("mode", mode, torch.int64, (T, K))
        _check("normal_impulse", self.normal_impulse, F64, (T, K))
        for name in ("friction_impulse", "point", "normal"):
            _check(name, getattr(self, name), F64, (T, K, 2))
        _check("candidate", self.candidate, torch.bool, (T, K))
        _check("solver", self.solver, torch.int64, (T,))


@dataclass(frozen=True, eq=False)
class RunLog:
    """One recorded run (a physical run or a simulated trial), time-major.

    The run has ``T + 1`` instants ``t_0 … t_T`` (``time_ns``) and ``T`` steps; step ``k``
    goes from ``t_k`` to ``t_{k+1}``. Poses are planar ``(x, y, θ)`` in the world frame (m,
    rad), twists ``(vx, vy, ω)`` (m/s, rad/s). Every tensor is on the CPU; every float tensor
    is float64 and finite except ``vision``, which is NaN at the instants with no
    measurement.

    Attributes:
        name: the run's name.
        h: the time step ``t_{k+1} - t_k``, seconds.
        body: the tracked body, which the camera measures.
        joints: the names of the robot's ``J`` coordinates (joint angles, or the ``x``, ``y``,
            ``θ`` of kinematically driven bodies, e.g. ``"left.x"``).
        time_ns: ``(T + 1,)`` int64 instants, nanoseconds (the log's time base).
        robot_position: ``(T + 1, J)`` the robot's coordinates at each instant.
        robot_velocity: ``(T, J)`` their velocity held over each step (the control).
        vision: ``(T + 1, 3)`` the camera's pose of ``body`` at each instant, NaN where none.
        tactile: ``(T, S)`` bool readings of ``S`` tactile sensors over each step.
        source: free-form JSON-able description of what produced the run (e.g. the
            experiment's settings).
        prior_mean: ``(6,)`` the filters' initial mean of ``body``'s pose and twist, or
            ``None``.
        prior_covariance: ``(6, 6)`` its covariance, or ``None`` (given with ``prior_mean``).
        bodies: the names of the ``Nd`` bodies of ``truth_pose`` (empty without it).
        truth_pose: ``(T + 1, Nd, 3)`` true poses, or ``None``.
        truth_twist: ``(T + 1, Nd, 3)`` true twists, or ``None`` (given with ``truth_pose``).
        truth_contacts: the true contact slots, or ``None``.
        parameters: true physical parameters by name (e.g. ``{"friction": 0.47}``).

    Raises:
        ValueError: a field has the wrong type, dtype or shape, a float is not finite (or
            ``vision`` has ``inf`` or a partly NaN row), the instants do not increase, or an
            optional group is half given.
    """

    name: str
    h: float
    body: str
    joints: tuple[str, ...]
    time_ns: Tensor
    robot_position: Tensor
    robot_velocity: Tensor
    vision: Tensor
    tactile: Tensor
    source: dict[str, Any] = field(default_factory=dict)
    prior_mean: Tensor | None = None
    prior_covariance: Tensor | None = None
    bodies: tuple[str, ...] = ()
    truth_pose: Tensor | None = None
    truth_twist: Tensor | None = None
    truth_contacts: ContactTruth | None = None
    parameters: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"name: expected a non-empty str, got {self.name!r}")
        if not isinstance(self.body, str) or not self.body:
            raise ValueError(f"body: expected a non-empty str, got {self.body!r}")
        h = self.h
        if not isinstance(h, float) or not (0 < h < math.inf):
            raise ValueError(f"h: expected a finite float > 0, got {h!r}")
        J = len(_check_names("joints", self.joints))
        time_ns = self.time_ns
        if not isinstance(time_ns, Tensor) or time_ns.dim() != 1 or time_ns.shape[0] < 2:
            raise ValueError(
                f"time_ns: expected a (T + 1,) tensor, T >= 1, got {describe(time_ns)}"
            )
        T = time_ns.shape[0] - 1
        _check("time_ns", time_ns, torch.int64, (T + 1,))
        if not bool((time_ns[1:] > time_ns[:-1]).all()) or int(time_ns[0]) < 0:
            raise ValueError("time_ns: expected non-negative, strictly increasing instants")
        _check("robot_position", self.robot_position, F64, (T + 1, J))
        _check("robot_velocity", self.robot_velocity, F64, (T, J))
        vision = self.vision
        if not isinstance(vision, Tensor) or vision.dtype != F64 or vision.shape != (T + 1, 3):
            raise ValueError(
                f"vision: expected a float64 tensor of shape {(T + 1, 3)}, got {describe(vision)}"
            )
        missing = torch.isnan(vision)
        if bool(torch.isinf(vision).any()) or not bool((missing == missing[:, :1]).all()):
            raise ValueError("vision: expected finite rows or all-NaN rows (no measurement)")
        tactile = self.tactile
        if not isinstance(tactile, Tensor) or tactile.dim() != 2:
            raise ValueError(f"tactile: expected a (T, S) bool tensor, got {describe(tactile)}")
        _check("tactile", tactile, torch.bool, (T, tactile.shape[1]))
        if not isinstance(self.source, dict):
            raise ValueError(f"source: expected a dict, got {type(self.source).__name__}")
        if (self.prior_mean is None) != (self.prior_covariance is None):
            raise ValueError("prior_mean, prior_covariance: give both or neither")
        if self.prior_mean is not None:
            _check("prior_mean", self.prior_mean, F64, (6,))
            _check("prior_covariance", self.prior_covariance, F64, (6, 6))
        Nd = len(_check_names("bodies", self.bodies))
        if (self.truth_pose is None) != (self.truth_twist is None):
            raise ValueError("truth_pose, truth_twist: give both or neither")
        if (self.truth_pose is None) != (Nd == 0):
            raise ValueError("bodies: name the bodies of truth_pose, and only with it")
        if self.truth_pose is not None:
            _check("truth_pose", self.truth_pose, F64, (T + 1, Nd, 3))
            _check("truth_twist", self.truth_twist, F64, (T + 1, Nd, 3))
        if self.truth_contacts is not None:
            if not isinstance(self.truth_contacts, ContactTruth):
                raise ValueError(
                    f"truth_contacts: expected a ContactTruth, got {describe(self.truth_contacts)}"
                )
            steps = self.truth_contacts.mode.shape[0]
            if steps != T:
                raise ValueError(f"truth_contacts: expected T = {T} steps, got {steps}")
        if not isinstance(self.parameters, dict) or not all(
            isinstance(k, str) and isinstance(v, float) and math.isfinite(v)
            for k, v in self.parameters.items()
        ):
            raise ValueError(
                f"parameters: expected a dict of str to finite float, got {self.parameters!r}"
            )

    @property
    def steps(self) -> int:
        """``T``."""
        return int(self.time_ns.shape[0]) - 1
