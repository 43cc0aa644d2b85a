"""Planar and spatial scenes (with robots) and the batched time-stepping contact simulator."""

from torchcontact.sim._assemble import body_poses, contact_problem, slot_friction
from torchcontact.sim._examples import pushed_box_rollout, pushed_box_scene
from torchcontact.sim._penetration import penetration
from torchcontact.sim._plot import draw_scene
from torchcontact.sim._rigid_body import (
    free_angular_velocity,
    integrate_poses,
    spatial_mass_matrix,
    tangent_basis,
    tangent_directions,
    world_inertia,
)
from torchcontact.sim._robot_member import RobotMember, RobotMode, RobotStep, robot_step
from torchcontact.sim._scene import Body, BodyKind, RobotSlotGroup, Scene, SlotGroup
from torchcontact.sim._simulator import (
    SOLVED_BY_EXACT_MODE,
    SOLVED_BY_GUESS,
    SOLVED_RAW,
    UNSOLVED,
    Rollout,
    Simulator,
    StepResult,
)
from torchcontact.sim._state import SceneState

__all__ = [
    "SOLVED_BY_EXACT_MODE",
    "SOLVED_BY_GUESS",
    "SOLVED_RAW",
    "UNSOLVED",
    "Body",
    "BodyKind",
    "RobotMember",
    "RobotMode",
    "RobotSlotGroup",
    "RobotStep",
    "Rollout",
    "Scene",
    "SceneState",
    "Simulator",
    "SlotGroup",
    "StepResult",
    "body_poses",
    "contact_problem",
    "draw_scene",
    "free_angular_velocity",
    "integrate_poses",
    "penetration",
    "pushed_box_rollout",
    "pushed_box_scene",
    "robot_step",
    "slot_friction",
    "spatial_mass_matrix",
    "tangent_basis",
    "tangent_directions",
    "world_inertia",
]
