"""The peg-in-hole task on the planar simulator: scene, gripper servo, batched episode physics.

Everything here acts on a flat batch ``(B,)`` of environments at once; the single and the
vectorized environment are thin layers over :class:`PegInHoleTask` that own the random
generators and the gymnasium bookkeeping.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

from torchcontact.envs._config import PegInHoleConfig
from torchcontact.envs._states import PegInHoleStates
from torchcontact.geometry import HalfPlane, Polygon, wrap_angle
from torchcontact.sim import UNSOLVED, Body, Scene, SceneState, Simulator, StepResult
from torchcontact.states import (
    ContactSet,
    FeatureGrid,
    PartnerKind,
    TactileArray,
    object_contacts,
    rectangle_sensors,
)

#: Names of the discrete actions, in action-id order.
ACTION_NAMES = ("stay", "+x", "-x", "+y", "-y", "+theta", "-theta")
#: Body names of the scene, in scene order.
BODY_NAMES = ("table", "block_left", "block_right", "peg", "finger_left", "finger_right")
#: Columns of the dynamic bodies in ``SceneState.q``.
PEG, FINGER_LEFT, FINGER_RIGHT = 0, 1, 2
#: Samples drawn per reset, in order: gripper x, peg-bottom height above the mouth, gripper
#: angle, grasp offset (pads to peg centre), peg angle relative to the fingers.
NUM_START_SAMPLES = 5

#: LCP residual above which an unsolved simulator step counts as a failure. The exact solvers
#: can stop short on degenerate grasps (four sticking pad contacts); the simulator then keeps
#: the best impulses it found, which are accepted when their residual is this small.
FAILURE_RESIDUAL = 1e-6


@dataclass(frozen=True, eq=False)
class Physics:
    """The batched physical state of ``B`` environments after a simulator step.

    Attributes:
        state: ``(B, ...)`` simulator state (peg, left finger, right finger).
        gripper: ``(B, 3)`` gripper pose ``(x, y, θ)``: the midpoint between the finger pads,
            its ``y`` axis along the fingers.
        contact_q: ``(B, 3, 3)`` dynamic-body poses at the start of the last simulator step
            (the frame of its contact points).
        points: ``(B, K, 2)`` slot points of the last step, world frame.
        normals: ``(B, K, 2)`` slot normals of the last step.
        pn: ``(B, K)`` normal impulses of the last step.
        mode: ``(B, K)`` contact modes of the last step.
        active: ``(B, K)`` slot candidates of the last step.
        unsolved: ``(B,)`` bool: in a simulator step of the last environment step no solver
            converged and the best impulses left an LCP residual above
            :data:`FAILURE_RESIDUAL` (the state is then unreliable; the episode ends).
    """

    state: SceneState
    gripper: Tensor
    contact_q: Tensor
    points: Tensor
    normals: Tensor
    pn: Tensor
    mode: Tensor
    active: Tensor
    unsolved: Tensor

    def index(self, index: Tensor) -> Physics:
        """The entries ``index`` of the batch."""
        return Physics(
            state=self.state[index],
            gripper=self.gripper[index],
            contact_q=self.contact_q[index],
            points=self.points[index],
            normals=self.normals[index],
            pn=self.pn[index],
            mode=self.mode[index],
            active=self.active[index],
            unsolved=self.unsolved[index],
        )

    def put(self, index: Tensor, other: Physics) -> Physics:
        """This batch with entries ``index`` replaced by ``other``'s."""

        def merge(a: Tensor, b: Tensor) -> Tensor:
            return a.index_put((index,), b)

        return Physics(
            state=SceneState(
                q=merge(self.state.q, other.state.q),
                v=merge(self.state.v, other.state.v),
                q_kinematic=merge(self.state.q_kinematic, other.state.q_kinematic),
                mode=merge(self.state.mode, other.state.mode),
            ),
            gripper=merge(self.gripper, other.gripper),
            contact_q=merge(self.contact_q, other.contact_q),
            points=merge(self.points, other.points),
            normals=merge(self.normals, other.normals),
            pn=merge(self.pn, other.pn),
            mode=merge(self.mode, other.mode),
            active=merge(self.active, other.active),
            unsolved=merge(self.unsolved, other.unsolved),
        )


def _finger_polygon(config: PegInHoleConfig, side: int) -> tuple[Polygon, float]:
    """A finger tapering to its pad, and the distance from its centroid to the pad face.

    Args:
        config: the task configuration.
        side: ``−1`` for the left finger (pad facing ``+x``), ``+1`` for the right one.
    """
    a, b, p = config.finger_width / 2, config.finger_height / 2, config.pad_length / 2
    # Right finger: pad on its left side (x = -a); the left finger is its mirror image.
    corners = [(-a, -p), (a, -b), (a, b), (-a, p)]
    if side < 0:
        corners = [(-x, y) for x, y in reversed(corners)]
    polygon, centroid = Polygon.centered(torch.tensor(corners, dtype=torch.float64))
    return polygon, a + side * float(centroid[0])


def _block_polygon(config: PegInHoleConfig, side: int) -> tuple[Polygon, Tensor]:
    """A block beside the hole with its mouth corner chamfered, and its world pose."""
    inner, outer = config.hole_width / 2, config.hole_width / 2 + config.block_width
    top, c = config.hole_depth, config.chamfer
    if c > 0:
        corners = [(inner, 0.0), (outer, 0.0), (outer, top), (inner + c, top), (inner, top - c)]
    else:
        corners = [(inner, 0.0), (outer, 0.0), (outer, top), (inner, top)]
    if side < 0:
        corners = [(-x, y) for x, y in reversed(corners)]
    polygon, centroid = Polygon.centered(torch.tensor(corners, dtype=torch.float64))
    pose = torch.tensor([float(centroid[0]), float(centroid[1]), 0.0], dtype=torch.float64)
    return polygon, pose


def build_scene(config: PegInHoleConfig) -> tuple[Scene, float]:
    """The scene of the task and the finger's centroid-to-pad distance.

    Bodies, in order: the table (half-plane ``y >= 0`` below), the left and right blocks
    (static polygons, chamfered at the mouth), the peg and the two fingers (dynamic).
    """
    left_block, left_pose = _block_polygon(config, -1)
    right_block, right_pose = _block_polygon(config, 1)
    left_finger, pad_offset = _finger_polygon(config, -1)
    right_finger, _ = _finger_polygon(config, 1)
    bodies = (
        Body("table", HalfPlane.ground(0.0), kind="static"),
        Body("block_left", left_block, kind="static", pose=left_pose),
        Body("block_right", right_block, kind="static", pose=right_pose),
        Body("peg", Polygon.box(config.peg_width, config.peg_height), mass=config.peg_mass),
        Body("finger_left", left_finger, mass=config.finger_mass, inertia=config.finger_inertia),
        Body("finger_right", right_finger, mass=config.finger_mass, inertia=config.finger_inertia),
    )
    pairs: dict[tuple[str, str], float] = {}
    for finger in ("finger_left", "finger_right"):
        pairs[("peg", finger)] = config.grip_friction
    for static in ("table", "block_left", "block_right"):
        pairs[("peg", static)] = config.hole_friction
    scene = Scene(
        bodies=bodies,
        h=config.h,
        gravity=(0.0, -config.gravity),
        friction=config.friction,
        pair_friction=pairs,
        margin=config.margin,
    )
    return scene, pad_offset


class PegInHoleTask:
    """Scene, gripper servo, sensors and discretization of the peg-in-hole task (batched).

    Args:
        config: the task configuration.
    """

    def __init__(self, config: PegInHoleConfig) -> None:
        if not isinstance(config, PegInHoleConfig):
            raise ValueError(f"config must be a PegInHoleConfig, got {type(config).__name__}")
        self.config = config
        self.scene, self.pad_offset = build_scene(config)
        self.simulator = Simulator(self.scene)
        finger = self.scene.bodies[self.scene.index("finger_left")]
        self.finger_inertia = float(finger.inertia_value())
        self.sensors: TactileArray = rectangle_sensors(
            half_extents=(config.peg_width / 2, config.peg_height / 2),
            counts=config.tactile_counts,
            radius=config.tactile_radius,
            half_angle=config.tactile_half_angle,
            false_positive=config.tactile_false_positive,
            false_negative=config.tactile_false_negative,
            dtype=torch.float64,
        )
        self.states = PegInHoleStates(
            peg_height=config.peg_height,
            hole_depth=config.hole_depth,
            x_edges=config.x_edges,
            y_edges=config.y_edges,
            angle_edges=config.angle_edges,
        )
        self.contact_grid = FeatureGrid(
            dim=2, radius=config.contact_radius, angle=config.contact_angle
        )
        self.partner_kinds = tuple(
            PartnerKind.ROBOT if name.startswith("finger") else PartnerKind.ENVIRONMENT
            for name in BODY_NAMES
        )
        move, turn = config.move_step, config.turn_step
        self.action_deltas = torch.tensor(
            [
                [0.0, 0.0, 0.0],
                [move, 0.0, 0.0],
                [-move, 0.0, 0.0],
                [0.0, move, 0.0],
                [0.0, -move, 0.0],
                [0.0, 0.0, turn],
                [0.0, 0.0, -turn],
            ],
            dtype=torch.float64,
        )
        self.workspace_low = torch.tensor(
            [config.workspace_x[0], config.workspace_y[0], config.workspace_angle[0]],
            dtype=torch.float64,
        )
        self.workspace_high = torch.tensor(
            [config.workspace_x[1], config.workspace_y[1], config.workspace_angle[1]],
            dtype=torch.float64,
        )

    # -- reset ------------------------------------------------------------------------------

    def sample_start(self, rng: np.random.Generator) -> NDArray[np.float64]:
        """Draw one environment's start: ``NUM_START_SAMPLES`` uniforms in their ranges."""
        c = self.config
        ranges = (c.start_x, c.start_height, c.start_angle, c.grasp_offset, c.grasp_angle)
        return np.array([rng.uniform(low, high) for low, high in ranges], dtype=np.float64)

    def initial_state(self, samples: Tensor) -> tuple[SceneState, Tensor]:
        """Poses of a batch of starts, fingers touching the peg, everything at rest.

        The peg's axis passes through the gripper origin, ``offset`` below it along the peg;
        each finger's pad is placed at the outermost point of the peg's side over the pad's
        extent, so that the pads touch the (possibly tilted) peg without penetrating it.

        Args:
            samples: ``(B, 5)`` rows of :meth:`sample_start`.

        Returns:
            The simulator state and the ``(B, 3)`` gripper poses.
        """
        c = self.config
        gx, height, g_angle, offset, tilt = samples.unbind(-1)
        w, half_h, p = c.peg_width / 2, c.peg_height / 2, c.pad_length / 2
        # Peg centre in the gripper frame, and its angle.
        cx, cy = offset * torch.sin(tilt), -offset * torch.cos(tilt)
        peg_angle = g_angle + tilt
        cos_g, sin_g = torch.cos(g_angle), torch.sin(g_angle)
        world_cy = sin_g * cx + cos_g * cy
        gy = c.hole_depth + height - world_cy + half_h * torch.cos(peg_angle)
        cos_t, sin_t = torch.cos(tilt), torch.sin(tilt)
        pad_x = []
        for side in (-1.0, 1.0):
            sides = []
            for y in (-p, p):
                t = (y - cy - side * w * sin_t) / cos_t
                sides.append(cx + side * w * cos_t - t * sin_t)
            extreme = torch.maximum(*sides) if side > 0 else torch.minimum(*sides)
            pad_x.append(extreme + side * self.pad_offset)
        gripper = torch.stack([gx, gy, g_angle], dim=-1)

        def world(x: Tensor, y: Tensor, angle: Tensor) -> Tensor:
            return torch.stack(
                [gx + cos_g * x - sin_g * y, gy + sin_g * x + cos_g * y, angle], dim=-1
            )

        zero = torch.zeros_like(gx)
        q = torch.stack(
            [
                world(cx, cy, peg_angle),
                world(pad_x[0], zero, g_angle),
                world(pad_x[1], zero, g_angle),
            ],
            dim=-2,
        )
        return self.simulator.initial_state(q=q), gripper

    def reset(self, samples: Tensor) -> Physics:
        """Start a batch of environments and let the grasp settle (``settle_steps`` steps)."""
        state, gripper = self.initial_state(samples)
        return self.simulate(state, gripper, gripper, steps=self.config.settle_steps)

    # -- stepping ---------------------------------------------------------------------------

    def targets(self, gripper: Tensor, actions: Tensor) -> Tensor:
        """Gripper poses after actions ``(B,)``, clamped to the workspace, ``(B, 3)``."""
        return torch.clamp(
            gripper + self.action_deltas[actions], self.workspace_low, self.workspace_high
        )

    def servo_forces(self, state: SceneState, gripper: Tensor, twist: Tensor) -> Tensor:
        """Applied forces: finger servo, grip and gravity compensation.

        Each finger is a dynamic body pushed by three forces (world frame, at its centroid):

        * a servo toward the gripper: along the fingers (gripper ``y``) each finger tracks
          the gripper origin, along the closing axis (gripper ``x``) the fingers' *mean*
          tracks it (the jaws stay centred), and each finger's angle tracks the gripper's.
          The servo is a PD law in its implicit ("stable PD") form,
          ``f = −[k (e + h ė) + d ė] / (1 + (k h² + d h)/m)`` with ``k = m ω²`` and
          ``d = 2 ζ m ω``, which is the force that makes the end-of-step error rate obey the
          implicit PD law when no contact acts; unlike the explicit law it is stable for any
          ``ω h``. Errors are measured against the gripper moving at ``twist``. The linear
          servo force is saturated at ``max_finger_force`` (the torque at
          ``max_finger_force · finger_height / 2``);
        * the grip: ``grip_force`` along the closing axis, towards the other finger;
        * the finger's weight, compensated.

        The peg gets nothing but gravity (added by the simulator): it is held by friction.

        Args:
            state: the batch state.
            gripper: ``(B, 3)`` gripper poses.
            twist: ``(B, 3)`` gripper twist ``(vx, vy, ω)`` over the step.

        Returns:
            ``(B, 3, 3)`` generalized forces on the peg and the two fingers.
        """
        c = self.config
        h, omega, zeta = c.h, c.finger_frequency, c.finger_damping
        shrink = 1.0 + (omega * h) ** 2 + 2.0 * zeta * omega * h
        kp, kd = c.finger_mass * omega**2, 2.0 * zeta * c.finger_mass * omega
        kr, dr = self.finger_inertia * omega**2, 2.0 * zeta * self.finger_inertia * omega
        cos, sin = torch.cos(gripper[:, 2]), torch.sin(gripper[:, 2])
        axis_x = torch.stack([cos, sin], dim=-1).unsqueeze(1)  # (B, 1, 2)
        axis_y = torch.stack([-sin, cos], dim=-1).unsqueeze(1)
        fingers, velocity = state.q[:, 1:], state.v[:, 1:]  # (B, 2, 3)
        offset = fingers[..., :2] - gripper[:, None, :2]
        frame_velocity = twist[:, None, :2] + twist[:, None, 2:3] * torch.stack(
            [-offset[..., 1], offset[..., 0]], dim=-1
        )
        relative = velocity[..., :2] - frame_velocity
        error_x = (offset * axis_x).sum(-1).mean(-1, keepdim=True)  # (B, 1)
        rate_x = (relative * axis_x).sum(-1).mean(-1, keepdim=True)
        error_y = (offset * axis_y).sum(-1)  # (B, 2)
        rate_y = (relative * axis_y).sum(-1)
        servo_x = -(kp * (error_x + h * rate_x) + kd * rate_x) / shrink
        servo_y = -(kp * (error_y + h * rate_y) + kd * rate_y) / shrink
        servo = servo_x.unsqueeze(-1) * axis_x + servo_y.unsqueeze(-1) * axis_y  # (B, 2, 2)
        size = servo.norm(dim=-1, keepdim=True)
        limit = c.max_finger_force
        servo = servo * torch.clamp(limit / torch.clamp(size, min=1e-300), max=1.0)
        inward = torch.tensor([1.0, -1.0], dtype=torch.float64)[None, :, None]
        linear = servo + c.grip_force * inward * axis_x
        linear = linear + torch.tensor([0.0, c.finger_mass * c.gravity], dtype=torch.float64)
        angle_error = wrap_angle(fingers[..., 2] - gripper[:, None, 2])
        angle_rate = velocity[..., 2] - twist[:, None, 2]
        torque = -(kr * (angle_error + h * angle_rate) + dr * angle_rate) / shrink
        torque_limit = limit * c.finger_height / 2
        torque = torch.clamp(torque, -torque_limit, torque_limit)
        finger_forces = torch.cat([linear, torque.unsqueeze(-1)], dim=-1)
        return torch.cat([torch.zeros_like(finger_forces[:, :1]), finger_forces], dim=1)

    def simulate(
        self, state: SceneState, gripper: Tensor, target: Tensor, *, steps: int
    ) -> Physics:
        """Move the gripper to ``target`` at constant twist over ``steps`` simulator steps.

        Args:
            state: the batch state.
            gripper: ``(B, 3)`` gripper poses at the start.
            target: ``(B, 3)`` gripper poses at the end.
            steps: number of simulator steps.

        Returns:
            The physics after the last step.
        """
        h = self.config.h
        twist = (target - gripper) / (steps * h)
        unsolved = torch.zeros(gripper.shape[0], dtype=torch.bool)
        result: StepResult | None = None
        contact_q = state.q
        for k in range(steps):
            pose = gripper + (k * h) * twist
            force = self.servo_forces(state, pose, twist)
            contact_q = state.q
            with torch.no_grad():
                result = self.simulator.step(state, force=force)
            bad = (result.solver == UNSOLVED) & ~(result.residual <= FAILURE_RESIDUAL)
            unsolved = unsolved | bad
            state = result.state
        assert result is not None
        return Physics(
            state=state,
            gripper=target.clone(),
            contact_q=contact_q,
            points=result.geometry.points,
            normals=result.geometry.normals,
            # A failed solve (the episode then ends as dropped) may leave garbage impulses;
            # accepted ones may be a round-off below zero. Reported impulses are >= 0.
            pn=torch.nan_to_num(result.pn, nan=0.0).clamp(min=0.0),
            mode=result.mode,
            active=result.geometry.active,
            unsolved=unsolved,
        )

    def step(self, physics: Physics, actions: Tensor) -> Physics:
        """One environment step of a batch: gripper motions ``actions (B,)`` (long)."""
        target = self.targets(physics.gripper, actions)
        return self.simulate(physics.state, physics.gripper, target, steps=self.config.substeps)

    # -- what the environment reports -------------------------------------------------------

    def peg_contacts(self, physics: Physics) -> ContactSet:
        """The peg's contacts of the last simulator step (fingers are its robot partners)."""
        contacts = object_contacts(
            self.scene,
            body="peg",
            q=physics.contact_q,
            points=physics.points,
            normals=physics.normals,
            pn=physics.pn,
            mode=physics.mode,
            active=physics.active,
        )
        return replace(contacts, partner_kind=self.partner_kinds)

    def peg_in_gripper(self, physics: Physics) -> Tensor:
        """``(B, 3)`` pose of the peg in the gripper frame (angle wrapped)."""
        peg, gripper = physics.state.q[:, PEG], physics.gripper
        cos, sin = torch.cos(gripper[:, 2]), torch.sin(gripper[:, 2])
        dx, dy = peg[:, 0] - gripper[:, 0], peg[:, 1] - gripper[:, 1]
        return torch.stack(
            [cos * dx + sin * dy, -sin * dx + cos * dy, wrap_angle(peg[:, 2] - gripper[:, 2])], -1
        )

    def outcome(self, physics: Physics) -> tuple[Tensor, Tensor]:
        """Success and drop flags, ``(B,)`` bool each.

        Success: the peg's bottom centre lies inside the hole (``|b_x| < hole_width / 2``) at
        least ``insertion_depth`` below the mouth. Dropped: the pads have left the peg (the
        gripper origin lies beyond the peg's end along it, or outside its width), the peg has
        turned more than 45° in the grasp, or the simulator failed to solve a step.
        """
        c = self.config
        relative = self.states.relative_pose(physics.state.q[:, PEG])
        success = (relative[:, 0].abs() < c.hole_width / 2) & (relative[:, 1] <= -c.insertion_depth)
        grasp = self.peg_in_gripper(physics)
        lost = (grasp[:, 1].abs() > c.peg_height / 2) | (
            grasp[:, 0].abs() > c.peg_width / 2 + c.finger_width
        )
        lost = lost | (grasp[:, 2].abs() > math.pi / 4) | physics.unsolved
        lost = lost | ~torch.isfinite(physics.state.q).all(-1).all(-1)
        return success & ~lost, lost

    def state_vector(self, physics: Physics) -> NDArray[np.float64]:
        """``(B, 9)`` oracle observations: peg pose, peg twist, gripper pose."""
        peg = physics.state.q[:, PEG]
        twist = physics.state.v[:, PEG]
        return torch.cat([peg, twist, physics.gripper], dim=-1).numpy().astype(np.float64)
