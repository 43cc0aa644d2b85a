"""The BarrettHand box-grasp experiment: ground truth and measurements.

The WAM (``"wam7_bhand"``) carries the BarrettHand palm down to a box lying on a table and
the hand closes on it. The WAM's seven joints are kinematic: they follow a planned approach
(the palm descends vertically above the box's nominal position, joint angles by damped
least-squares inverse kinematics at every step, joint velocities their differences); the
hand's four joints are servoed (spread held at 0, finger targets ramping closed, torque
limited, gravity compensated), so the fingers yield to the box. Per trial the box's size and
mass (shared by the ``trials_per_box`` trials of one simulator batch: a batched scene has one
box shape), its friction and its initial pose (position offset and yaw) are drawn; the hand
always aims at the nominal position, so the first finger to touch pushes the box towards the
others. A tall box pushed high on a grippy table tips over about its bottom edge before the
grasp closes; otherwise it slides into the grasp or is grasped cleanly.

Phases (``steps`` of h = 10 ms): approach (the first :data:`APPROACH_SHARE` of the steps:
the palm descends :data:`APPROACH_DROP` metres), closing (finger targets ramp at
:data:`CLOSE_SPEED`) and hold (the targets stay closed). The camera (Kinect-like: Gaussian
position noise ``camera_sigma`` and a rotation-vector noise of ``camera_sigma_deg`` per
axis, world frame) sees the box during the approach only: the occlusion is defined by
phase, from the first closing step to the end (the closing hand hides the box).

Recorded per step: the box's pose and twist, the true contact state of the box against the
table, the palm and each finger (0 separated, 1 sticking, 2 sliding: a pair is separated
when none of its slots is in contact, sliding when any contact slides, else sticking, the
active/sliding definitions of :class:`~torchcontact.states.ContactSet`), the robot's joint
angles and velocities, the camera measurements, the BarrettHand's tactile pads (one
:class:`~torchcontact.states.TactileArray` per pad link: palm, and each finger's inner and
outer link) with false positives and negatives, and the tip-over step (the first step at
which the box's tilt, the angle between its body z axis and the world z axis, exceeds
:data:`TIP_ANGLE`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact._checks import check_int, check_real
from torchcontact.geometry import Box, HalfSpace, quat_exp, quat_mul, quat_to_matrix
from torchcontact.robots import Robot, load
from torchcontact.sim import UNSOLVED, Body, RobotMember, Rollout, Scene, Simulator
from torchcontact.states import ContactSet, TactileArray

F64 = torch.float64
H = 0.01  # time step, seconds
#: Nominal box position on the table (world frame, metres): where the hand aims.
BOX_XY = (0.6, 0.0)
#: The palm frame's height (metres) at the end of the approach.
PALM_Z = 0.225
APPROACH_DROP = 0.08  # metres the palm descends during the approach
APPROACH_SHARE = 0.25  # share of the steps spent approaching
CLOSE_SHARE = 0.5  # share of the steps spent closing
FINGER_OPEN = 0.7  # finger angle (rad) during the approach
FINGER_CLOSED = 2.4  # last finger target (rad)
CLOSE_SPEED = 1.5  # rad/s of the finger targets while closing
FINGER_TORQUE = 0.25  # N m torque limit of fingers 1 and 2 (finger 3: twice)
TIP_ANGLE = math.radians(5.0)  # tilt beyond which the box has tipped
#: Palm orientation during the grasp: palm down, hand y along world −y (turned π about x).
PALM_DOWN = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=F64)
#: The pairs whose contact state is recorded, in order.
BOX_PAIRS = ("table", "palm", "finger1", "finger2", "finger3")
#: Pad links of the BarrettHand's tactile sensors, in reading order.
PAD_LINKS = (
    "bhand_palm",
    "bhand_f1_inner",
    "bhand_f1_outer",
    "bhand_f2_inner",
    "bhand_f2_outer",
    "bhand_f3_inner",
    "bhand_f3_outer",
)
#: Contact-state codes of a pair.
SEPARATED, STICKING, SLIDING = 0, 1, 2
MIN_STEPS = 12  # every phase gets at least two steps


@dataclass(frozen=True)
class BarrettBoxGrasp:
    """Settings of the BarrettHand box-grasp experiment (ranges are uniform draws)."""

    seed: int = 0
    """seed of the trials"""
    trials: int = 32
    """evaluation trials"""
    trials_per_box: int = 4
    """trials sharing one box size and mass (one simulator batch)"""
    steps: int = 80
    """time steps per trial (h = 0.01 s)"""
    half_x: tuple[float, float] = (0.025, 0.035)
    """range of the box's half length along x (m)"""
    half_y: tuple[float, float] = (0.02, 0.03)
    """range of the box's half width along y, the closing direction (m)"""
    half_z: tuple[float, float] = (0.035, 0.06)
    """range of the box's half height (m)"""
    mass: tuple[float, float] = (0.1, 0.4)
    """range of the box's mass (kg)"""
    friction: tuple[float, float] = (0.3, 0.9)
    """range of the friction coefficient (every pair of the trial)"""
    offset_x: float = 0.01
    """largest |x offset| of the box from its nominal position (m)"""
    offset_y: float = 0.03
    """largest |y offset| (m): which finger touches first"""
    yaw: float = 0.2
    """largest |yaw| of the box (rad)"""
    camera_sigma: float = 0.005
    """camera position noise std (m)"""
    camera_sigma_deg: float = 2.0
    """camera orientation noise std per axis (deg)"""
    false_positive: float = 0.05
    """tactile false-positive rate"""
    false_negative: float = 0.1
    """tactile false-negative rate"""

    def check(self) -> None:
        """Check every setting before any work.

        Raises:
            ValueError: a setting is out of range; the message names it and its range.
        """
        check_int("seed", self.seed, low=0)
        check_int("trials", self.trials, low=1)
        check_int("trials_per_box", self.trials_per_box, low=1)
        check_int("steps", self.steps, low=MIN_STEPS, why="every phase of the grasp")
        for name in ("half_x", "half_y", "half_z", "mass", "friction"):
            low, high = getattr(self, name)
            check_real(f"{name}[0]", low, low=0.0, low_open=name != "friction")
            check_real(f"{name}[1]", high, low=low)
        for name in ("offset_x", "offset_y", "yaw"):
            check_real(name, getattr(self, name), low=0.0)
        for name in ("camera_sigma", "camera_sigma_deg"):
            check_real(name, getattr(self, name), low=0.0, low_open=True)
        for name in ("false_positive", "false_negative"):
            check_real(name, getattr(self, name), low=0.0, high=1.0, high_open=True)

    def camera_std(self) -> Tensor:
        """``(6,)`` float64 camera noise std: position (m), rotation vector (rad)."""
        angle = math.radians(self.camera_sigma_deg)
        return torch.tensor([self.camera_sigma] * 3 + [angle] * 3, dtype=F64)

    def nominal_half_extents(self) -> tuple[float, float, float]:
        """The box's half extents that the filters assume: the middle of each range."""
        return (0.5 * sum(self.half_x), 0.5 * sum(self.half_y), 0.5 * sum(self.half_z))

    def nominal_mass(self) -> float:
        """The mass that the filters assume: the middle of the range."""
        return 0.5 * sum(self.mass)

    def nominal_friction(self) -> float:
        """The friction that the filters assume: the middle of the range."""
        return 0.5 * sum(self.friction)


def grasp_phases(steps: int) -> tuple[slice, slice, slice, Tensor]:
    """The approach, closing and hold step ranges and the ``(T,)`` bool occlusion mask (by
    phase: from the first closing step on)."""
    close_start = max(2, round(APPROACH_SHARE * steps))
    hold_start = max(close_start + 2, round((APPROACH_SHARE + CLOSE_SHARE) * steps))
    occluded = torch.zeros(steps, dtype=torch.bool)
    occluded[close_start:] = True
    return slice(0, close_start), slice(close_start, hold_start), slice(hold_start, steps), occluded


# ----------------------------------------------------------------------------------------------
# the robot and its plan


def barrett_member(robot: Robot | None = None, *, mode: str = "servo") -> RobotMember:
    """The WAM with the BarrettHand at the world origin: WAM joints kinematic, the hand's
    joints servoed (``mode="servo"``) or the whole robot kinematic (``mode="kinematic"``, the
    filters' view: measured joint angles as known control)."""
    robot = load("wam7_bhand") if robot is None else robot
    if mode == "kinematic":
        return RobotMember("wam", robot, mode="kinematic")
    tau = FINGER_TORQUE
    return RobotMember(
        "wam",
        robot,
        stiffness=torch.tensor([0.0] * 7 + [50.0, 5.0, 5.0, 10.0], dtype=F64),
        damping=torch.tensor([0.0] * 7 + [1.0, 0.05, 0.05, 0.1], dtype=F64),
        torque_limit=torch.tensor([1.0] * 7 + [10.0, tau, tau, 2 * tau], dtype=F64),
        gravity_compensation=True,
        kinematic_joints=robot.joint_names[:7],
    )


def barrett_box_scene(
    half_extents: tuple[float, float, float],
    mass: float,
    friction: float | Tensor,
    member: RobotMember,
) -> Scene:
    """Table (static half-space z = 0), the box (dynamic) and the robot; ``friction`` a
    float or ``(B,)`` (every pair)."""
    # Body's annotation names the planar shapes only; it takes the spatial ones too.
    table = Body("table", HalfSpace.ground(), kind="static")  # type: ignore[arg-type]
    box = Body("box", Box(torch.tensor(half_extents, dtype=F64)), mass=mass)  # type: ignore[arg-type]
    return Scene(
        bodies=(table, box),
        robots=(member,),
        friction=friction,
        h=H,
    )


def palm_ik(robot: Robot, position: Tensor, start: Tensor, *, iterations: int = 100) -> Tensor:
    """WAM joint angles placing the palm frame at ``position`` ``(3,)`` palm down.

    Damped least squares on the palm frame's position and orientation error (the WAM's seven
    joints; the hand's are left as in ``start`` ``(dof,)``).

    Raises:
        RuntimeError: the pose error stays above 1e-8.
    """
    target = quat_to_matrix(PALM_DOWN)
    q = start.clone()
    error = math.inf
    for _ in range(iterations):
        transform = robot.forward_kinematics(q, "bhand_palm")
        turn = target @ transform[:3, :3].T
        angle = torch.acos(((turn.diagonal().sum() - 1) / 2).clamp(-1.0, 1.0))
        axis = torch.stack(
            [turn[2, 1] - turn[1, 2], turn[0, 2] - turn[2, 0], turn[1, 0] - turn[0, 1]]
        )
        scale = 0.5 if float(angle) < 1e-9 else float(angle) / (2 * math.sin(float(angle)))
        residual = torch.cat([position - transform[:3, 3], scale * axis])
        error = float(residual.norm())
        if error < 1e-10:
            break
        jacobian = robot.jacobian(q, "bhand_palm")[:, :7]
        damping = 1e-6 * torch.eye(6, dtype=F64)
        q[:7] = q[:7] + jacobian.T @ torch.linalg.solve(jacobian @ jacobian.T + damping, residual)
    if error > 1e-8:
        raise RuntimeError(f"palm_ik: pose error {error:.1e} at {position.tolist()}")
    return q


def approach_plan(robot: Robot, steps: int) -> tuple[Tensor, Tensor]:
    """The robot's initial joint angles ``(dof,)`` and commands ``(T, dof)``: WAM joint
    velocities along the planned approach (palm straight down by :data:`APPROACH_DROP` above
    the nominal box position, then still), servo targets of the hand (spread 0, fingers at
    :data:`FINGER_OPEN`, ramping at :data:`CLOSE_SPEED` to :data:`FINGER_CLOSED`)."""
    approach, closing, _, _ = grasp_phases(steps)
    n = approach.stop
    start = torch.zeros(robot.dof, dtype=F64)
    start[[1, 3, 5]] = torch.tensor([0.6, 1.6, 0.9], dtype=F64)
    path = []
    q = start
    for k in range(n + 1):
        height = PALM_Z + APPROACH_DROP * (1 - k / n)
        q = palm_ik(robot, torch.tensor([*BOX_XY, height], dtype=F64), q)
        path.append(q[:7])
    joints = torch.stack(path)
    commands = torch.zeros(steps, robot.dof, dtype=F64)
    commands[:n, :7] = (joints[1:] - joints[:-1]) / H
    time = H * torch.arange(1, steps + 1, dtype=F64)
    ramp = FINGER_OPEN + CLOSE_SPEED * (time - H * closing.start)
    commands[:, 8:] = ramp.clamp(FINGER_OPEN, FINGER_CLOSED)[:, None]
    initial = torch.cat([joints[0], torch.tensor([0.0] + [FINGER_OPEN] * 3, dtype=F64)])
    return initial, commands


# ----------------------------------------------------------------------------------------------
# slots, contact states and pads


def pair_slots(scene: Scene) -> dict[str, list[int]]:
    """The slot indices of each pair of :data:`BOX_PAIRS` (and ``"arm"``: the WAM's links)."""
    table = scene.index("table")
    slots: dict[str, list[int]] = {name: [] for name in (*BOX_PAIRS, "arm")}
    for group in scene.slot_groups:
        if table in (group.receiver, group.other):
            slots["table"].extend(range(group.start, group.start + group.count))
    shapes = scene.robots[0].robot.collision_shapes
    for robot_group in scene.robot_slot_groups:
        link = shapes[robot_group.shape].link
        if link == "bhand_palm":
            name = "palm"
        elif link.startswith("bhand_f"):
            name = f"finger{link[7]}"
        else:
            name = "arm"
        slots[name].extend(range(robot_group.start, robot_group.start + robot_group.count))
    return slots


def pair_states(mode: Tensor, slots: dict[str, list[int]]) -> Tensor:
    """``(*B, P)`` long contact state of each pair of :data:`BOX_PAIRS` from ``(*B, L)`` per-slot
    modes: :data:`SEPARATED` when none of its slots is in contact, :data:`SLIDING` when any
    contact slides (mode ``>= 2``), else :data:`STICKING`."""
    states = []
    for name in BOX_PAIRS:
        part = mode[..., slots[name]]
        touching = (part > 0).any(-1)
        sliding = (part >= 2).any(-1)
        states.append(torch.where(sliding, SLIDING, torch.where(touching, STICKING, SEPARATED)))
    return torch.stack(states, -1)


def hand_pads(settings: BarrettBoxGrasp, robot: Robot) -> dict[str, TactileArray]:
    """One pad per link of :data:`PAD_LINKS`, in the link's frame: the palm's on the palm
    surface facing the grasp (cone 60°), each finger link's at its collision capsule's centre
    covering the whole link (any normal)."""
    pads = {}
    centres = {shape.link: shape.pose[:3] for shape in robot.collision_shapes}
    for link in PAD_LINKS:
        if link == "bhand_palm":
            position, normal = torch.tensor([0.0, 0.0, 0.084], dtype=F64), (0.0, 0.0, 1.0)
            radius, half_angle = 0.07, math.radians(60.0)
        else:
            position, normal = centres[link], (1.0, 0.0, 0.0)
            radius, half_angle = 0.06, math.pi
        pads[link] = TactileArray(
            positions=position.view(1, 3),
            normals=torch.tensor([normal], dtype=F64),
            radius=radius,
            half_angle=half_angle,
            false_positive=settings.false_positive,
            false_negative=settings.false_negative,
        )
    return pads


def pad_triggers(
    scene: Scene,
    pads: dict[str, TactileArray],
    *,
    q_robot: Tensor,
    robot_base: Tensor,
    points: Tensor,
    normals: Tensor,
    pn: Tensor,
    mode: Tensor,
    active: Tensor,
) -> Tensor:
    """``(*B, S)`` bool noise-free pad triggers of one step (pads in :data:`PAD_LINKS` order).

    Each pad link's robot slots become a :class:`~torchcontact.states.ContactSet` in that
    link's frame (the slot normals point from the box into the link).

    Args:
        scene: the scene (one robot).
        pads: :func:`hand_pads`.
        q_robot: ``(*B, dof)`` joint angles at the start of the step.
        robot_base: ``(*B, 1, 7)`` the robot's base pose.
        points: ``(*B, L, 3)`` slot points (world frame).
        normals: ``(*B, L, 3)`` slot normals (world frame).
        pn: ``(*B, L)`` normal impulses.
        mode: ``(*B, L)`` long contact modes.
        active: ``(*B, L)`` bool slot candidates.
    """
    robot = scene.robots[0].robot
    transforms = robot.forward_kinematics(q_robot)
    base_rotation = quat_to_matrix(robot_base[..., 0, 3:])
    shapes = robot.collision_shapes
    triggers = []
    for link, pad in pads.items():
        slots = [
            k
            for group in scene.robot_slot_groups
            if shapes[group.shape].link == link
            for k in range(group.start, group.start + group.count)
        ]
        rotation = base_rotation @ transforms[link][..., :3, :3]  # link to world
        origin = (base_rotation @ transforms[link][..., :3, 3:]).squeeze(-1) + robot_base[
            ..., 0, :3
        ]
        local = (points[..., slots, :] - origin[..., None, :]) @ rotation
        local_normals = normals[..., slots, :] @ rotation
        contacts = ContactSet(
            points=local,
            normals=local_normals,
            pn=pn[..., slots].clamp_min(0.0),
            mode=mode[..., slots],
            partner=torch.zeros(len(slots), dtype=torch.long),
            partner_kind=["environment"],
            mask=active[..., slots],
        )
        triggers.append(pad.triggered(contacts))
    return torch.cat(triggers, -1)


# ----------------------------------------------------------------------------------------------
# the trials


@dataclass(frozen=True, eq=False)
class BoxTrials:
    """Simulated trials of the box grasp and their measurements (batch ``B``, ``T`` steps).

    Attributes:
        truth: the ground-truth rollout (the groups' batches concatenated).
        scenes: the true scene of each group of ``trials_per_box`` trials.
        group: ``(B,)`` long group (scene) of each trial.
        half_extents: ``(B, 3)`` the boxes' half extents (m).
        mass: ``(B,)`` the boxes' masses (kg).
        friction: ``(B,)`` friction coefficients.
        commands: ``(T, dof)`` joint commands (WAM velocities, hand servo targets).
        states: ``(T, B, P)`` long true contact state of each pair of :data:`BOX_PAIRS` during
            each step.
        y: ``(T, B, 7)`` camera poses after each step (position, unit quaternion), NaN while
            occluded.
        readings: ``(T, B, S)`` bool tactile readings during each step.
        triggers: ``(T, B, S)`` bool noise-free pad triggers.
        occluded: ``(T,)`` bool occlusion mask.
        tip_step: ``(B,)`` long first step after which the tilt exceeds :data:`TIP_ANGLE`;
            ``-1`` if the box never tips.
    """

    truth: Rollout
    scenes: tuple[Scene, ...]
    group: Tensor
    half_extents: Tensor
    mass: Tensor
    friction: Tensor
    commands: Tensor
    states: Tensor
    y: Tensor
    readings: Tensor
    triggers: Tensor
    occluded: Tensor
    tip_step: Tensor

    @property
    def steps(self) -> int:
        """``T``."""
        return int(self.y.shape[0])

    @property
    def batch(self) -> int:
        """``B``."""
        return int(self.y.shape[1])

    @property
    def pose(self) -> Tensor:
        """``(T, B, 7)`` the box's true pose after each step."""
        return self.truth.q[1:, :, 0]

    def subset(self, index: Tensor) -> BoxTrials:
        """The trials ``index`` ``(B',)`` long (their groups keep indexing :attr:`scenes`)."""
        truth = Rollout(
            **{name: getattr(self.truth, name)[:, index] for name in Rollout.__dataclass_fields__}
        )
        return BoxTrials(
            truth=truth,
            scenes=self.scenes,
            group=self.group[index],
            half_extents=self.half_extents[index],
            mass=self.mass[index],
            friction=self.friction[index],
            commands=self.commands,
            states=self.states[:, index],
            y=self.y[:, index],
            readings=self.readings[:, index],
            triggers=self.triggers[:, index],
            occluded=self.occluded,
            tip_step=self.tip_step[index],
        )


def box_tilt(pose: Tensor) -> Tensor:
    """``(*B,)`` angle (rad) between the body z axis of ``(*B, 7)`` poses and world z."""
    rotation = quat_to_matrix(pose[..., 3:7])
    return torch.acos(rotation[..., 2, 2].clamp(-1.0, 1.0))


def first_tip_step(pose: Tensor) -> Tensor:
    """``(B,)`` long first step of ``(T, B, 7)`` poses whose :func:`box_tilt` exceeds
    :data:`TIP_ANGLE`; ``-1`` where none does."""
    tipped = box_tilt(pose) > TIP_ANGLE
    first = tipped.to(torch.long).argmax(0)
    return torch.where(tipped.any(0), first, -1)


def _cat_rollouts(runs: list[Rollout]) -> Rollout:
    """The rollouts' batches side by side (batch dim 1)."""
    fields = {}
    for name in Rollout.__dataclass_fields__:
        parts = [getattr(run, name) for run in runs]
        fields[name] = torch.cat(parts, 1)
    return Rollout(**fields)


def box_trials(settings: BarrettBoxGrasp, *, seed: int | None = None) -> BoxTrials:
    """Simulate the trials (:class:`BarrettBoxGrasp`) and their measurements.

    Args:
        settings: the settings.
        seed: the seed of the draws; default ``settings.seed``.

    Raises:
        RuntimeError: a step that no contact solver solved.
    """
    seed = settings.seed if seed is None else seed
    gen = torch.Generator().manual_seed(seed)
    robot = load("wam7_bhand")
    member = barrett_member(robot)
    T, B, per = settings.steps, settings.trials, settings.trials_per_box
    initial, commands = approach_plan(robot, T)

    def uniform(bounds: tuple[float, float], *shape: int) -> Tensor:
        low, high = bounds
        return low + (high - low) * torch.rand(*shape, generator=gen, dtype=F64)

    def symmetric(bound: float, n: int) -> Tensor:
        return bound * (2 * torch.rand(n, generator=gen, dtype=F64) - 1)

    runs, scenes, groups, halves, masses = [], [], [], [], []
    frictions = uniform(settings.friction, B)
    for g, start in enumerate(range(0, B, per)):
        n = min(per, B - start)
        half = torch.stack(
            [uniform(getattr(settings, k), 1)[0] for k in ("half_x", "half_y", "half_z")]
        )
        mass = float(uniform(settings.mass, 1))
        friction = frictions[start : start + n]
        scene = barrett_box_scene(
            (float(half[0]), float(half[1]), float(half[2])), mass, friction, member
        )
        yaw = symmetric(settings.yaw, n)
        q = torch.zeros(n, 1, 7, dtype=F64)
        q[:, 0, 0] = BOX_XY[0] + symmetric(settings.offset_x, n)
        q[:, 0, 1] = BOX_XY[1] + symmetric(settings.offset_y, n)
        q[:, 0, 2] = float(half[2])
        q[:, 0, 3], q[:, 0, 6] = torch.cos(yaw / 2), torch.sin(yaw / 2)
        simulator = Simulator(scene)
        state = simulator.initial_state(q=q, q_robot=initial.expand(n, -1).clone())
        run = simulator.rollout(
            state,
            steps=T,
            joint_commands=commands[:, None].expand(T, n, -1).contiguous(),
            strict=False,
        )
        failed = (run.solver == UNSOLVED).any(0)
        if bool(failed.any()):
            raise RuntimeError(f"{int(failed.sum())} trials had unsolved steps (seed {seed})")
        runs.append(run)
        scenes.append(scene)
        groups.append(torch.full((n,), g, dtype=torch.long))
        halves.append(half.expand(n, 3))
        masses.append(torch.full((n,), mass, dtype=F64))
    truth = _cat_rollouts(runs)
    scene = scenes[0]
    states = pair_states(truth.mode, pair_slots(scene))
    _, _, _, occluded = grasp_phases(T)
    std = settings.camera_std()
    pose = truth.q[1:, :, 0]
    noise = std * torch.randn(T, B, 6, generator=gen, dtype=F64)
    y = torch.cat(
        [pose[..., :3] + noise[..., :3], quat_mul(quat_exp(noise[..., 3:]), pose[..., 3:])], -1
    )
    y[occluded] = math.nan
    pads = hand_pads(settings, robot)
    assert truth.q_robot is not None
    assert truth.robot_base is not None
    triggers = pad_triggers(
        scene,
        pads,
        q_robot=truth.q_robot[:-1],
        robot_base=truth.robot_base[:-1],
        points=truth.points,
        normals=truth.normals,
        pn=truth.pn,
        mode=truth.mode,
        active=truth.active,
    )
    probability = torch.cat(
        [pad.reading_probability(triggers[..., i : i + 1]) for i, pad in enumerate(pads.values())],
        -1,
    )
    readings = torch.rand(probability.shape, generator=gen, dtype=F64) < probability
    return BoxTrials(
        truth=truth,
        scenes=tuple(scenes),
        group=torch.cat(groups),
        half_extents=torch.cat(halves),
        mass=torch.cat(masses),
        friction=frictions,
        commands=commands,
        states=states,
        y=y,
        readings=readings,
        triggers=triggers,
        occluded=occluded,
        tip_step=first_tip_step(pose),
    )
