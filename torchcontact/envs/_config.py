"""Configuration of the planar peg-in-hole task."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from itertools import pairwise

#: Default cell edges of the manipulation-state grid (see :class:`PegInHoleConfig`).
DEFAULT_X_EDGES = (-0.08, -0.04, -0.02, -0.01, -0.005, -0.002, 0.002, 0.005, 0.01, 0.02, 0.04, 0.08)
DEFAULT_Y_EDGES = (-0.03, -0.02, -0.01, -0.005, 0.0, 0.005, 0.01, 0.02, 0.04, 0.08)
DEFAULT_ANGLE_EDGES = (-0.2, -0.1, -0.05, -0.02, 0.02, 0.05, 0.1, 0.2)

_POSITIVE = (
    "peg_width",
    "peg_height",
    "peg_mass",
    "hole_depth",
    "block_width",
    "insertion_depth",
    "finger_width",
    "finger_height",
    "pad_length",
    "finger_mass",
    "finger_inertia",
    "h",
    "gravity",
    "grip_friction",
    "hole_friction",
    "friction",
    "finger_frequency",
    "finger_damping",
    "max_finger_force",
    "move_step",
    "turn_step",
    "tactile_radius",
    "contact_radius",
    "contact_angle",
)
_NON_NEGATIVE = (
    "clearance",
    "chamfer",
    "grip_force",
    "margin",
    "occlusion_radius",
    "success_reward",
    "step_cost",
    "drop_penalty",
)
_RANGES = (
    "workspace_x",
    "workspace_y",
    "workspace_angle",
    "start_x",
    "start_height",
    "start_angle",
    "grasp_offset",
    "grasp_angle",
)
_EDGES = ("x_edges", "y_edges", "angle_edges")


@dataclass(frozen=True, kw_only=True)
class PegInHoleConfig:
    """Every parameter of :class:`~torchcontact.envs.PegInHole2D`, SI units (m, kg, s, N, rad).

    World frame: ``x`` to the right, ``y`` up (gravity ``−y``), the hole centred on ``x = 0``
    with its mouth (the top of the blocks) at ``y = hole_depth`` and the table at ``y = 0``.
    Construction validates every field and raises ``ValueError`` naming the field at fault.

    Attributes:
        peg_width: width of the rectangular peg.
        peg_height: length of the peg.
        peg_mass: mass of the peg.
        clearance: hole width minus peg width (``>= 0``).
        chamfer: leg of the 45° chamfer cut from each block's corner at the hole mouth
            (``0``: sharp edges).
        hole_depth: height of the blocks that form the hole (the hole's floor is the table).
        block_width: width of each block.
        insertion_depth: depth below the mouth that the peg's bottom must reach for success.
        finger_width: width of a finger along the closing axis.
        finger_height: height of a finger.
        pad_length: length of the flat pad at a finger's tip (the finger tapers to it).
        finger_mass: mass of each finger.
        finger_inertia: rotational inertia of each finger about its centroid, kg·m² (its mount
            and the robot behind it, far above the inertia of the finger's own shape; it sets
            how stiff the fingers' angle servo can be).
        h: simulator time step.
        substeps: simulator steps per environment step.
        settle_steps: simulator steps at reset with the gripper at rest (lets the grasp load).
        gravity: gravitational acceleration (along ``−y``).
        grip_force: constant force pressing each finger onto the peg.
        grip_friction: friction coefficient between the fingers and the peg.
        hole_friction: friction between the peg and the blocks and table.
        friction: friction of every other pair (fingers against blocks or table).
        margin: gap below which a slot is a contact candidate.
        finger_frequency: natural frequency of the finger position servo, rad/s.
        finger_damping: damping ratio of the finger servo.
        max_finger_force: saturation of the servo force on a finger.
        move_step: gripper translation of one move action.
        turn_step: gripper rotation of one turn action.
        workspace_x: ``(low, high)`` bounds of the gripper's ``x``.
        workspace_y: bounds of the gripper's ``y``.
        workspace_angle: bounds of the gripper's angle.
        start_x: range of the initial gripper ``x`` (uniform).
        start_height: range of the initial height of the peg's bottom above the mouth.
        start_angle: range of the initial gripper angle.
        grasp_offset: range of the distance from the finger pads down to the peg's centre.
        grasp_angle: range of the peg's initial angle relative to the fingers.
        max_steps: environment steps before truncation: the limit of
            :class:`~torchcontact.envs.PegInHole2DVector` unless it is given
            ``max_episode_steps``, and the default's is the registered spec's
            ``max_episode_steps`` (:class:`~torchcontact.envs.PegInHole2D` itself never
            truncates: gymnasium's ``TimeLimit`` does).
        success_reward: reward on reaching the insertion depth.
        step_cost: cost of every step (subtracted).
        drop_penalty: cost of losing the peg from the grasp (subtracted; ends the episode).
        pose_noise_std: ``(σx, σy, σθ)`` of the noisy vision pose of the peg.
        occlusion_radius: the camera loses the peg while the peg's bottom centre lies within
            this distance of the centre of the hole's mouth ``(0, hole_depth)`` (the gripper
            and the blocks hide it): the noisy observation's ``peg_pose`` is then NaN in all
            three components, and the lateral offset of the peg in the grasp is observable only
            by touch (the tactile readings are unaffected). ``0`` (the default): always seen.
            :data:`~torchcontact.envs.OCCLUDED_CONFIG` is the variant registered as
            ``"torchcontact/PegInHole2DOccluded-v0"``.
        tactile_counts: sensors on the peg's bottom, right, top and left sides.
        tactile_radius: sensing radius of each tactile sensor.
        tactile_half_angle: half-angle of each sensor's cone of triggering normals.
        tactile_false_positive: probability that an untouched sensor reads ``True``.
        tactile_false_negative: probability that a touched sensor reads ``False``.
        x_edges: cell edges along ``x`` of the peg's bottom centre relative to the hole centre
            (strictly increasing; finer near the hole).
        y_edges: cell edges along ``y`` of the peg's bottom centre relative to the mouth.
        angle_edges: cell edges of the peg's angle.
        contact_radius: location tolerance ``δ_r`` of the contact states reported in ``info``.
        contact_angle: normal tolerance ``δ_θ`` of those contact states.
    """

    peg_width: float = 0.04
    peg_height: float = 0.16
    peg_mass: float = 0.1
    clearance: float = 0.004
    chamfer: float = 0.005
    hole_depth: float = 0.06
    block_width: float = 0.25
    insertion_depth: float = 0.03
    finger_width: float = 0.02
    finger_height: float = 0.05
    pad_length: float = 0.01
    finger_mass: float = 0.5
    finger_inertia: float = 0.01
    h: float = 0.01
    substeps: int = 2
    settle_steps: int = 5
    gravity: float = 9.81
    grip_force: float = 4.0
    grip_friction: float = 0.6
    hole_friction: float = 0.3
    friction: float = 0.5
    margin: float = 0.005
    finger_frequency: float = 150.0
    finger_damping: float = 1.0
    max_finger_force: float = 30.0
    move_step: float = 0.002
    turn_step: float = 0.02
    workspace_x: tuple[float, float] = (-0.2, 0.2)
    workspace_y: tuple[float, float] = (0.05, 0.4)
    workspace_angle: tuple[float, float] = (-0.5, 0.5)
    start_x: tuple[float, float] = (-0.08, 0.08)
    start_height: tuple[float, float] = (0.01, 0.05)
    start_angle: tuple[float, float] = (-0.1, 0.1)
    grasp_offset: tuple[float, float] = (0.03, 0.05)
    grasp_angle: tuple[float, float] = (-0.05, 0.05)
    max_steps: int = 200
    success_reward: float = 1.0
    step_cost: float = 0.01
    drop_penalty: float = 1.0
    pose_noise_std: tuple[float, float, float] = (0.002, 0.002, 0.02)
    occlusion_radius: float = 0.0
    tactile_counts: tuple[int, int, int, int] = (2, 5, 2, 5)
    tactile_radius: float = 0.015
    tactile_half_angle: float = math.pi / 4
    tactile_false_positive: float = 0.02
    tactile_false_negative: float = 0.05
    x_edges: tuple[float, ...] = DEFAULT_X_EDGES
    y_edges: tuple[float, ...] = DEFAULT_Y_EDGES
    angle_edges: tuple[float, ...] = DEFAULT_ANGLE_EDGES
    contact_radius: float = 0.01
    contact_angle: float = math.pi / 8

    def __post_init__(self) -> None:
        for item in fields(self):
            value = getattr(self, item.name)
            if isinstance(value, list):
                object.__setattr__(self, item.name, tuple(value))
        for name in _POSITIVE:
            _check_number(name, getattr(self, name), low=0.0, strict=True)
        for name in _NON_NEGATIVE:
            _check_number(name, getattr(self, name), low=0.0, strict=False)
        for name in ("substeps", "settle_steps", "max_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")
        for name in _RANGES:
            _check_range(name, getattr(self, name))
        for name in _EDGES:
            _check_edges(name, getattr(self, name))
        self._check_geometry()
        self._check_sensing()

    def _check_geometry(self) -> None:
        if self.chamfer >= min(self.hole_depth, self.block_width):
            raise ValueError(
                f"chamfer must be < min(hole_depth, block_width) = "
                f"{min(self.hole_depth, self.block_width)}, got {self.chamfer}"
            )
        if self.insertion_depth > self.hole_depth:
            raise ValueError(
                f"insertion_depth must be <= hole_depth = {self.hole_depth}, "
                f"got {self.insertion_depth}"
            )
        if self.pad_length > self.finger_height:
            raise ValueError(
                f"pad_length must be <= finger_height = {self.finger_height}, got {self.pad_length}"
            )
        if self.grasp_offset[1] > self.peg_height / 2 - self.pad_length / 2:
            raise ValueError(
                "grasp_offset must keep the pads on the peg (high <= peg_height/2 - "
                f"pad_length/2 = {self.peg_height / 2 - self.pad_length / 2}), "
                f"got {self.grasp_offset}"
            )
        if max(abs(a) for a in self.grasp_angle) >= math.pi / 4:
            raise ValueError(f"grasp_angle must lie within (-π/4, π/4), got {self.grasp_angle}")
        if self.margin < self.move_step / self.substeps:
            raise ValueError(
                "margin must be >= move_step / substeps (the gripper's travel in one "
                f"simulator step, {self.move_step / self.substeps}), got {self.margin}"
            )

    def _check_sensing(self) -> None:
        std = self.pose_noise_std
        if len(std) != 3:
            raise ValueError(f"pose_noise_std must hold 3 numbers, got {std!r}")
        for value in std:
            _check_number("pose_noise_std", value, low=0.0, strict=False)
        counts = self.tactile_counts
        if (
            len(counts) != 4
            or any(isinstance(n, bool) or not isinstance(n, int) or n < 0 for n in counts)
            or sum(counts) == 0
        ):
            raise ValueError(f"tactile_counts must be four ints >= 0, not all 0, got {counts!r}")
        if not 0.0 <= self.tactile_half_angle <= math.pi:
            raise ValueError(
                f"tactile_half_angle must lie in [0, π], got {self.tactile_half_angle}"
            )
        for name in ("tactile_false_positive", "tactile_false_negative"):
            value = getattr(self, name)
            _check_number(name, value, low=0.0, strict=False)
            if value > 1.0:
                raise ValueError(f"{name} must lie in [0, 1], got {value}")

    @property
    def hole_width(self) -> float:
        """Width of the hole, ``peg_width + clearance``."""
        return self.peg_width + self.clearance


def _check_number(name: str, value: object, *, low: float, strict: bool) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    if not math.isfinite(value) or (value <= low if strict else value < low):
        relation = ">" if strict else ">="
        raise ValueError(f"{name} must be finite and {relation} {low}, got {value!r}")


def _check_range(name: str, value: object) -> None:
    if (
        not isinstance(value, tuple)
        or len(value) != 2
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        or not all(math.isfinite(v) for v in value)
        or value[0] > value[1]
    ):
        raise ValueError(f"{name} must be a (low, high) pair of finite numbers, got {value!r}")


def _check_edges(name: str, value: object) -> None:
    if (
        not isinstance(value, tuple)
        or not value
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        or not all(math.isfinite(v) for v in value)
        or any(b <= a for a, b in pairwise(value))
    ):
        raise ValueError(
            f"{name} must be a non-empty, strictly increasing tuple of finite numbers, "
            f"got {value!r}"
        )
