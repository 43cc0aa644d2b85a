"""Robots as members of spatial scenes, against finite differences and closed-form statics.

The hinge robot is one revolute joint (axis −y, so ``q > 0`` raises the arm) carrying a
uniform bar of mass ``m = 0.5`` kg and length 0.3 m along its x axis (centre of mass at
``l = 0.15`` m, inertia about the hinge ``I_c + m l² = 0.00375 + 0.01125 = 0.015`` kg m²).
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from torchcontact.contact import ContactProblem, lcp_residual, solve
from torchcontact.geometry import Box, HalfSpace, quat_to_matrix
from torchcontact.robots import Robot, load
from torchcontact.sim import (
    UNSOLVED,
    Body,
    RobotMember,
    Scene,
    Simulator,
    contact_problem,
    tangent_directions,
)

G = 9.81
HINGE_URDF = """<?xml version="1.0"?>
<robot name="hinge">
  <link name="base"/>
  <joint name="hinge" type="revolute">
    <parent link="base"/>
    <child link="arm"/>
    <origin xyz="0 0 0" rpy="0 0 0"/>
    <axis xyz="0 -1 0"/>
    <limit lower="-3" upper="3" effort="0" velocity="0"/>
  </joint>
  <link name="arm">
    <inertial>
      <origin xyz="0.15 0 0" rpy="0 0 0"/>
      <mass value="0.5"/>
      <inertia ixx="1e-5" ixy="0" ixz="0" iyy="0.00375" iyz="0" izz="0.00375"/>
    </inertial>
    <collision>
      <origin xyz="0.15 0 0" rpy="0 0 0"/>
      <geometry><box size="0.3 0.02 0.02"/></geometry>
    </collision>
  </link>
</robot>
"""
HINGE_MASS, HINGE_COM, HINGE_INERTIA = 0.5, 0.15, 0.015


@pytest.fixture
def hinge(tmp_path: Path) -> Robot:
    path = tmp_path / "hinge.urdf"
    path.write_text(HINGE_URDF)
    return Robot.from_urdf(path)


def pose(position: tuple[float, float, float], yaw: float = 0.0) -> torch.Tensor:
    """``(7,)`` a pose turned by ``yaw`` about world z."""
    half = 0.5 * yaw
    return torch.tensor([*position, math.cos(half), 0.0, 0.0, math.sin(half)], dtype=torch.float64)


def world_point(robot: Robot, base: torch.Tensor, q: torch.Tensor, link: str, local: torch.Tensor):
    """World position of a link-fixed point, from forward kinematics and the base pose."""
    transform = robot.forward_kinematics(q, link)
    inner = transform[:3, :3] @ local + transform[:3, 3]
    return quat_to_matrix(base[3:]) @ inner + base[:3]


def link_local(robot: Robot, base: torch.Tensor, q: torch.Tensor, link: str, point: torch.Tensor):
    """A world point's coordinates in a link's frame."""
    transform = robot.forward_kinematics(q, link)
    inner = quat_to_matrix(base[3:]).T @ (point - base[:3])
    return transform[:3, :3].T @ (inner - transform[:3, 3])


def hinge_scene(
    robot: Robot, *, mode: str = "servo", base: torch.Tensor | None = None, **servo: float
) -> Simulator:
    member = RobotMember(
        "arm", robot, mode=mode, base_pose=pose((0.0, 0.0, 0.2)) if base is None else base, **servo
    )
    box = Body("box", Box((0.05, 0.05, 0.05)), mass=1.0)
    ground = Body("ground", HalfSpace.ground(), kind="static")
    return Simulator(Scene(bodies=(ground, box), robots=(member,)))


def test_hinge_slots_and_columns(hinge: Robot) -> None:
    """One box–box group (8 slots) after the box–ground group; n = 6 + 1."""
    scene = hinge_scene(hinge).scene
    assert scene.num_slots == 16
    assert scene.num_dofs == 7
    assert [(g.start, g.count) for g in scene.robot_slot_groups] == [(8, 8)]


@pytest.mark.parametrize("mode", ["servo", "kinematic"])
def test_contact_rows_are_finite_differences_of_the_contact_point(hinge: Robot, mode: str) -> None:
    """A robot slot's gap rate and slip rates along its directions, as functions of the joint
    velocity (servo: the problem's last column) and of commanded joint and base motion
    (kinematic: ``bn``, ``bt``), equal central differences of the link-fixed contact point's
    world position along the motion."""
    yaw, angle = 0.4, -0.3
    base = pose((0.01, -0.02, 0.2), yaw)
    simulator = hinge_scene(hinge, mode=mode, base=base)
    scene = simulator.scene
    # The box under the arm's far end, turned with the base.
    centre = (0.2 * math.cos(yaw), 0.2 * math.sin(yaw), 0.05)
    q = pose(centre, yaw + 0.1).view(1, 1, 7)
    q_robot = torch.tensor([[angle]], dtype=torch.float64)
    state = simulator.initial_state(q=q, q_robot=q_robot, robot_base=base.view(1, 1, 7))
    joint_rate = torch.tensor([[0.7]], dtype=torch.float64)
    base_twist = torch.tensor([[[0.03, -0.02, 0.05, 0.1, -0.2, 0.3]]], dtype=torch.float64)
    problem, geometry = contact_problem(
        scene, state, joint_command=joint_rate, base_twist=base_twist
    )
    slots = [k for k in range(8, 16) if bool(geometry.active[0, k])]
    assert slots, "the arm must touch the box"
    directions = tangent_directions(geometry.normals[0], scene.friction_directions)
    eps = 1e-6
    for k in slots:
        point = geometry.points[0, k]
        local = link_local(hinge, base, q_robot[0], "arm", point)
        normal, tangents = geometry.normals[0, k], directions[k]

        def moved(
            t: float, rate: float, twist: torch.Tensor, local: torch.Tensor = local
        ) -> torch.Tensor:
            turned = torch.cat([base[:3] + t * twist[:3], _turn(base[3:], t * twist[3:])])
            # the base turns about its own origin, which moves with twist[:3]
            return world_point(hinge, turned, q_robot[0] + t * rate, "arm", local)

        if mode == "servo":
            still = torch.zeros(6, dtype=torch.float64)
            velocity = (moved(eps, 1.0, still) - moved(-eps, 1.0, still)) / (2 * eps)
            column = problem.Jn[0, k, 6], problem.Jt[0, k, :, 6]
            torch.testing.assert_close(column[0], normal @ velocity, rtol=0, atol=1e-8)
            torch.testing.assert_close(column[1], tangents @ velocity, rtol=0, atol=1e-8)
            # the same rows as Robot.contact_jacobian, in the robot's base frame
            turn = quat_to_matrix(base[3:]).T
            jn, jt = hinge.contact_jacobian(
                q_robot[0], "arm", point=local, normal=turn @ normal, tangents=tangents @ turn.T
            )
            torch.testing.assert_close(column[0], jn[0], rtol=0, atol=1e-14)
            torch.testing.assert_close(column[1], jt[:, 0], rtol=0, atol=1e-14)
        else:
            assert problem.num_dofs == 6
        rate = float(joint_rate) if mode == "kinematic" else 0.0
        velocity = (moved(eps, rate, base_twist[0, 0]) - moved(-eps, rate, base_twist[0, 0])) / (
            2 * eps
        )
        torch.testing.assert_close(problem.bn[0, k], normal @ velocity, rtol=0, atol=1e-8)
        torch.testing.assert_close(problem.bt[0, k], tangents @ velocity, rtol=0, atol=1e-8)


def _turn(quaternion: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """``exp(rotation) ⊗ quaternion`` by Rodrigues (independent of the library's helpers)."""
    angle = float(torch.linalg.vector_norm(rotation))
    if angle == 0.0:
        return quaternion
    axis = rotation / angle
    w, v = math.cos(angle / 2), math.sin(angle / 2) * axis
    a0, a = quaternion[0], quaternion[1:]
    return torch.cat([(w * a0 - v @ a).view(1), w * a + a0 * v + torch.linalg.cross(v, a)])


def kinetic_energy(robot: Robot, q: torch.Tensor, qd: torch.Tensor) -> float:
    """Σ ½ m |v_c|² + ½ ωᵀ I_w ω over the links, with each centre of mass's velocity and each
    link's angular velocity from central differences of forward kinematics."""
    eps = 1e-6
    plus = robot.forward_kinematics(q + eps * qd)
    minus = robot.forward_kinematics(q - eps * qd)
    energy = 0.0
    for inertial in robot.inertials:
        a, b = plus[inertial.link], minus[inertial.link]
        com_velocity = ((a[:3, :3] - b[:3, :3]) @ inertial.com + a[:3, 3] - b[:3, 3]) / (2 * eps)
        relative = a[:3, :3] @ b[:3, :3].T  # exp(2 eps [ω]×)
        skew = (relative - relative.T) / 2
        omega = torch.stack([skew[2, 1], skew[0, 2], skew[1, 0]]) / (2 * eps)
        middle = robot.forward_kinematics(q, inertial.link)[:3, :3]
        inertia = middle @ inertial.inertia @ middle.T
        energy += 0.5 * inertial.mass * float(com_velocity @ com_velocity)
        energy += 0.5 * float(omega @ inertia @ omega)
    return energy


@pytest.mark.parametrize("name", ["hinge", "bhand", "wam7", "wam7_bhand", "parallel_jaw"])
def test_mass_matrix_is_the_links_kinetic_energy(hinge: Robot, name: str) -> None:
    """½ q̇ᵀ M(q) q̇ equals the links' kinetic energy from finite differences of forward
    kinematics, for random q and q̇ (enough q̇ to fix every entry of the symmetric M); so
    does M from the caller's link Jacobians (``links=``, as a simulator step passes them)."""
    robot = hinge if name == "hinge" else load(name)
    generator = torch.Generator().manual_seed(3)
    low, high = robot.lower.clamp(min=-2.0), robot.upper.clamp(max=2.0)
    for _ in range(2):
        q = low + (high - low) * torch.rand(robot.dof, generator=generator, dtype=torch.float64)
        for M in (robot.mass_matrix(q), robot.mass_matrix(q, links=robot.link_jacobians(q))):
            torch.testing.assert_close(M, M.T, rtol=0, atol=1e-15)
            for _ in range(robot.dof * (robot.dof + 1) // 2 + 1):
                qd = torch.randn(robot.dof, generator=generator, dtype=torch.float64)
                expected = kinetic_energy(robot, q, qd)
                actual = 0.5 * float(qd @ M @ qd)
                assert actual == pytest.approx(expected, rel=1e-7, abs=1e-12)
    if name == "hinge":
        torch.testing.assert_close(
            robot.mass_matrix(torch.tensor([0.3], dtype=torch.float64)),
            torch.tensor([[HINGE_INERTIA]], dtype=torch.float64),
            rtol=1e-12,
            atol=0.0,
        )


def test_mass_matrix_rejects_links_that_do_not_fit_q() -> None:
    robot = load("bhand")
    q = torch.zeros(2, robot.dof, dtype=torch.float64)
    transforms, jacobians = robot.link_jacobians(q)
    with pytest.raises(ValueError, match="links must be the pair"):
        robot.mass_matrix(q, links=[transforms, jacobians])  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"links\[0\]"):
        robot.mass_matrix(q, links=(transforms[0], jacobians))
    with pytest.raises(ValueError, match=r"links\[1\]"):
        robot.mass_matrix(q, links=(transforms, jacobians[..., :-1]))
    with pytest.raises(ValueError, match=r"links\[1\]"):
        robot.mass_matrix(q, links=(transforms, jacobians.float()))
    bad = jacobians.clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"links\[1\]"):
        robot.mass_matrix(q, links=(transforms, bad))


def far_box(batch: int = 1) -> torch.Tensor:
    return pose((1.0, 1.0, 0.05)).expand(batch, 1, 7)


def test_servo_holds_the_arm_against_gravity_with_the_static_torque(hinge: Robot) -> None:
    """At rest, the servo torque K_p (q* − q) equals the weight's moment m g l cos q, with
    stiff gains (K_p h² / I = 0.67 per step, which an explicit servo cannot integrate)."""
    simulator = hinge_scene(hinge, stiffness=100.0, damping=2.0, torque_limit=10.0)
    state = simulator.initial_state(q=far_box(), q_robot=torch.zeros(1, 1, dtype=torch.float64))
    target = torch.full((150, 1, 1), 0.2, dtype=torch.float64)
    run = simulator.rollout(state, steps=150, joint_commands=target)
    q, qd = run.q_robot[-1, 0, 0], run.v_robot[-1, 0, 0]
    assert abs(float(qd)) < 1e-9
    servo = 100.0 * (0.2 - q)
    torch.testing.assert_close(servo, HINGE_MASS * G * HINGE_COM * torch.cos(q), rtol=1e-8, atol=0)
    assert float(run.q_robot.abs().max()) < 0.25  # no overshoot growth


def test_saturated_servo_applies_its_torque_limit(hinge: Robot) -> None:
    """With τ_max below the weight's moment the arm falls from horizontal at the angular
    acceleration (τ_max − m g l) / I of the hinge's closed-form inertia."""
    limit = 0.5 * HINGE_MASS * G * HINGE_COM
    simulator = hinge_scene(hinge, stiffness=100.0, damping=2.0, torque_limit=limit)
    state = simulator.initial_state(q=far_box(), q_robot=torch.zeros(1, 1, dtype=torch.float64))
    result = simulator.step(state, joint_command=torch.full((1, 1), 0.5, dtype=torch.float64))
    expected = simulator.scene.h * (limit - HINGE_MASS * G * HINGE_COM) / HINGE_INERTIA
    torch.testing.assert_close(
        result.state.v_robot[0, 0], torch.tensor(expected, dtype=torch.float64), rtol=1e-12, atol=0
    )


def test_kinematic_joints_follow_their_commands(hinge: Robot) -> None:
    """A kinematic arm follows the commanded joint velocity and base twist exactly, and does
    not yield: its tip, carried at 0.1 m/s, pushes a 1 kg box along the ground (μ = 0.5)
    at the tip's own speed."""
    simulator = hinge_scene(hinge, mode="kinematic", base=pose((0.0, 0.0, 0.05)))
    h, steps = simulator.scene.h, 40
    # The arm's end face at x = 0.3 (q = 0), the box's near face at x = 0.31.
    state = simulator.initial_state(
        q=pose((0.36, 0.0, 0.05)).view(1, 1, 7), q_robot=torch.zeros(1, 1, dtype=torch.float64)
    )
    rates = torch.full((steps, 1, 1), 1e-3, dtype=torch.float64)
    twists = torch.zeros(steps, 1, 1, 6, dtype=torch.float64)
    twists[..., 0] = 0.1
    run = simulator.rollout(state, steps=steps, joint_commands=rates, base_twists=twists)
    time = h * torch.arange(steps + 1, dtype=torch.float64)
    torch.testing.assert_close(run.q_robot[:, 0, 0], 1e-3 * time, rtol=0, atol=1e-12)
    torch.testing.assert_close(run.robot_base[:, 0, 0, 0], 0.1 * time, rtol=0, atol=1e-12)
    # Tip speed along x: base speed minus the joint rate's (tiny) contribution at 0.3 m.
    tip = run.q[-1, 0, 0, 0] - 0.36
    assert float(tip) > 0.02  # pushed for about 0.3 s
    torch.testing.assert_close(
        run.v[-5:, 0, 0, 0], torch.full((5,), 0.1, dtype=torch.float64), rtol=0, atol=1e-3 * 0.3
    )
    assert not bool((run.solver == UNSOLVED).any())


# Grasp threshold: a box squeezed by servo fingers whose torque limits give a total normal
# force F_n is lifted by a kinematic base iff μ F_n ≥ m g. The base accelerates at
# LIFT_ACCELERATION up to LIFT_SPEED, so holding needs μ F_n ≥ m (g + a): the masses tried,
# m = μ F_n / (ratio g) with ratio = 1.05 and 0.95, are 5 % on either side of the static
# threshold and clear of the 1 % that the acceleration adds.
MU, LIFT_ACCELERATION, LIFT_SPEED = 0.5, 0.1, 0.05


def lift(simulator: Simulator, state, *, close: int, steps: int, targets: torch.Tensor):
    """Close for ``close`` steps at rest, then lift the base; returns the rollout."""
    total = close + steps
    twists = torch.zeros(total, 1, 1, 6, dtype=torch.float64)
    time = simulator.scene.h * torch.arange(1, steps + 1, dtype=torch.float64)
    twists[close:, 0, 0, 2] = (LIFT_ACCELERATION * time).clamp(max=LIFT_SPEED)
    run = simulator.rollout(state, steps=total, joint_commands=targets, base_twists=twists)
    assert not bool((run.solver == UNSOLVED).any())
    return run


def check_threshold(run, ratio: float, box_z: float, *, close: int) -> None:
    """Above the threshold the box rises with the base without slipping; below, it stays on
    the ground while the fingers slide up its faces."""
    relative = run.q[close:, 0, 0, 2] - run.robot_base[close:, 0, 0, 2]
    rise = float(run.robot_base[-1, 0, 0, 2] - run.robot_base[close, 0, 0, 2])
    assert rise > 0.02
    if ratio > 1:
        torch.testing.assert_close(relative, relative[:1].expand_as(relative), rtol=0, atol=1e-9)
        assert float(run.q[-1, 0, 0, 2]) == pytest.approx(box_z + rise, abs=1e-9)
    else:
        assert float(run.q[-1, 0, 0, 2]) == pytest.approx(box_z, abs=1e-6)
        assert float(relative[0] - relative[-1]) == pytest.approx(rise, abs=1e-6)


def pad_gripper(tmp_path: Path, height: float) -> Robot:
    """The parallel-jaw gripper with a 5 mm sphere pad on each finger's inner face, ``height``
    from the palm, instead of the whole finger box: a box face against a box face touches in
    four corners whose normal impulses the rigid LCP does not determine (any split of the
    grip between them solves it, and a pivoting solver may load one corner, which twists the
    box); one pad per finger makes the grip a single point on each face."""
    text = (Path(load("parallel_jaw").source)).read_text()
    finger = """    <collision>
      <origin xyz="0.005 0.03 0" rpy="0 0 0"/>
      <geometry><box size="0.01 0.06 0.02"/></geometry>
    </collision>"""
    pad = f"""    <collision>
      <origin xyz="0.005 {height} 0" rpy="0 0 0"/>
      <geometry><sphere radius="0.005"/></geometry>
    </collision>"""
    assert text.count(finger) == 2
    path = tmp_path / "pad_gripper.urdf"
    path.write_text(text.replace(finger, pad))
    return Robot.from_urdf(path)


@pytest.mark.parametrize("ratio", [1.05, 0.95])
def test_parallel_jaw_lifts_the_box_iff_friction_carries_its_weight(
    tmp_path: Path, ratio: float
) -> None:
    """The jaw's coordinate moves both fingers (coupled), so its force limit F is the sum of
    the two pads' normal forces: F_n = F, and the box (m = μ F / (ratio g)) follows the lift
    iff ratio ≥ 1. The gripper points down (palm normal −z, fingers along ±x), the pads at
    the box's centre of mass."""
    force = 4.0
    half = math.sqrt(0.5)
    gripper = RobotMember(
        "gripper",
        pad_gripper(tmp_path, 0.045),
        stiffness=1000.0,
        damping=10.0,
        torque_limit=force,
        base_pose=torch.tensor([0.0, 0.0, 0.075, half, -half, 0.0, 0.0], dtype=torch.float64),
    )
    box = Body("box", Box((0.03, 0.03, 0.03)), mass=MU * force / (ratio * G))
    ground = Body("ground", HalfSpace.ground(), kind="static")
    simulator = Simulator(Scene(bodies=(ground, box), robots=(gripper,), friction=MU))
    state = simulator.initial_state(
        q=pose((0.0, 0.0, 0.03)).view(1, 1, 7), q_robot=torch.tensor([[0.032]], dtype=torch.float64)
    )
    close, steps = 20, 80
    targets = torch.zeros(close + steps, 1, 1, dtype=torch.float64)  # closed: saturated
    run = lift(simulator, state, close=close, steps=steps, targets=targets)
    # The grip: both pads' normal impulses sum to h F (robot slots follow the 8 ground slots).
    grip = run.pn[close - 1, 0, 8:].sum() / simulator.scene.h
    assert float(grip) == pytest.approx(force, rel=1e-9)
    check_threshold(run, ratio, 0.03, close=close)


def outer_cap_point(hand: Robot, theta: float, finger: int = 1) -> torch.Tensor:
    """The point of finger ``finger``'s outer capsule that faces the grasp (hand frame): the
    end cap's centre (0.05, 0, 0) in the outer link frame, offset by the radius D3 towards the
    hand's centre (+y for F1 and F2, −y for F3)."""
    q = torch.tensor([0.0, theta, theta, theta], dtype=torch.float64)
    transform = hand.forward_kinematics(q, f"bhand_f{finger}_outer")
    centre = transform[:3, :3] @ torch.tensor([0.05, 0.0, 0.0], dtype=torch.float64)
    side = 1.0 if finger < 3 else -1.0
    return centre + transform[:3, 3] + torch.tensor([0.0, side * 0.0095, 0.0], dtype=torch.float64)


@pytest.mark.parametrize("ratio", [1.05, 0.95])
def test_barretthand_lifts_the_box_iff_friction_carries_its_weight(ratio: float) -> None:
    """The BarrettHand pointing down grasps a box on its vertical faces, finger 3 opposing
    fingers 1 and 2 (spread 0), with the outer links' tips at the box's centre of mass.

    The box half width w = 0.06 m is where the fingertip's height in the hand is extremal
    (θ ≈ 0.95), so the tip closes horizontally and the box's weight does not load the finger
    joints. Each finger's servo is saturated at its torque limit (gravity compensated), so
    its pad presses with N = τ / λ, λ the lever ∂p_y/∂θ of the pad point from central
    differences of forward kinematics (along the coupled coordinate: inner θ, outer θ/3).
    Finger 3 has twice the limit, gains and damping of fingers 1 and 2, so that the box is
    squeezed without being pushed: N₃ = N₁ + N₂ and F_n = 4 τ / λ."""
    hand = load("bhand")
    tau, eps = 0.2, 1e-6
    theta = 0.9536  # the pad point's |y| = 0.06
    assert float(outer_cap_point(hand, theta)[1]) == pytest.approx(-0.06, abs=1e-4)
    lever = float(outer_cap_point(hand, theta + eps)[1] - outer_cap_point(hand, theta - eps)[1])
    lever /= 2 * eps
    total_normal = 4 * tau / lever
    member = RobotMember(
        "hand",
        hand,
        stiffness=torch.tensor([50.0, 5.0, 5.0, 10.0], dtype=torch.float64),
        damping=torch.tensor([1.0, 0.05, 0.05, 0.1], dtype=torch.float64),
        torque_limit=torch.tensor([10.0, tau, tau, 2 * tau], dtype=torch.float64),
        gravity_compensation=True,
        # palm down (turned by π about x): hand y → world −y, hand z → world −z
        base_pose=torch.tensor([0.0, 0.0, 0.2264, 0.0, 1.0, 0.0, 0.0], dtype=torch.float64),
    )
    box = Body("box", Box((0.04, 0.06, 0.04)), mass=MU * total_normal / (ratio * G))
    ground = Body("ground", HalfSpace.ground(), kind="static")
    simulator = Simulator(Scene(bodies=(ground, box), robots=(member,), friction=MU))
    start = 0.85
    state = simulator.initial_state(
        q=pose((0.0, 0.0, 0.04)).view(1, 1, 7),
        q_robot=torch.tensor([[0.0, start, start, start]], dtype=torch.float64),
    )
    close, steps = 40, 80
    # Finger targets ramp closed at 1 rad/s past the box (the servos saturate on contact).
    ramp = (start + simulator.scene.h * torch.arange(1, close + steps + 1)).clamp(max=1.3)
    targets = torch.zeros(close + steps, 1, 4, dtype=torch.float64)
    targets[:, 0, 1:] = ramp[:, None].to(torch.float64)
    run = lift(simulator, state, close=close, steps=steps, targets=targets)
    torch.testing.assert_close(
        run.q_robot[close, 0, 1:], torch.full((3,), theta, dtype=torch.float64), rtol=0, atol=2e-4
    )
    grip = run.pn[close - 1, 0, 8:].sum() / simulator.scene.h
    assert float(grip) == pytest.approx(total_normal, rel=1e-3)
    check_threshold(run, ratio, 0.04, close=close)


def test_bad_robot_members_and_inputs_are_rejected(hinge: Robot) -> None:
    with pytest.raises(ValueError, match="mode must be"):
        RobotMember("arm", hinge, mode="torque")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="stiffness must be >= 0"):
        RobotMember("arm", hinge, stiffness=-1.0)
    with pytest.raises(ValueError, match=r"damping must be a number or have shape \(1,\)"):
        RobotMember("arm", hinge, damping=torch.ones(2))
    with pytest.raises(ValueError, match="torque_limit must be > 0"):
        RobotMember("arm", hinge, torque_limit=0.0)
    with pytest.raises(ValueError, match="base_pose"):
        RobotMember("arm", hinge, base_pose=torch.tensor([0.0, 0, 0, 2, 0, 0, 0]))
    with pytest.raises(ValueError, match="no <collision> primitives"):
        RobotMember("arm", Robot.from_urdf(_bare(hinge)))
    ground = Body("ground", HalfSpace.ground(), kind="static")
    box = Body("box", Box((0.05, 0.05, 0.05)), mass=1.0)
    with pytest.raises(ValueError, match="unique among bodies and robots"):
        Scene(bodies=(ground, box), robots=(RobotMember("box", hinge),))
    simulator = hinge_scene(hinge)
    with pytest.raises(ValueError, match=r"q_robot of shape \(\*B, 1\) is required"):
        simulator.initial_state(q=far_box())
    state = simulator.initial_state(q=far_box(), q_robot=torch.zeros(1, 1, dtype=torch.float64))
    with pytest.raises(ValueError, match="joint_command"):
        simulator.step(state, joint_command=torch.zeros(1, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="base_twist"):
        simulator.step(state, base_twist=torch.full((1, 1, 6), math.nan, dtype=torch.float64))


def _bare(robot: Robot) -> str:
    """The hinge's URDF without its collision element (a path next to the hinge's)."""
    path = Path(robot.source).with_name("bare.urdf")
    text = HINGE_URDF
    start, end = text.index("    <collision>"), text.index("</collision>") + len("</collision>\n")
    path.write_text(text[:start] + text[end:])
    return str(path)


def test_scenes_without_robots_keep_their_state_layout() -> None:
    """A robot-free state has empty robot fields, so existing constructors keep working."""
    ground = Body("ground", HalfSpace.ground(), kind="static")
    simulator = Simulator(Scene(bodies=(ground, Body("box", Box((0.1, 0.1, 0.1)), mass=1.0))))
    state = simulator.initial_state(q=pose((0.0, 0.0, 0.1)).expand(3, 1, 7))
    assert state.q_robot is not None
    assert state.q_robot.shape == (3, 0)
    assert state.robot_base is not None
    assert state.robot_base.shape == (3, 0, 7)
    run = simulator.rollout(state, steps=2)
    assert run.q_robot is not None
    assert run.q_robot.shape == (3, 3, 0)


def test_batched_robot_scenes_equal_the_scenes_one_by_one(hinge: Robot) -> None:
    """A batch of arms (different angles, bases, commands) pressing boxes steps as each scene
    alone: no robot quantity mixes batch entries."""
    simulator = hinge_scene(hinge, stiffness=50.0, damping=1.0, torque_limit=2.0)
    q = torch.stack([pose((0.2, 0.0, 0.05)), pose((0.21, 0.01, 0.05), 0.1), far_box()[0, 0]])
    q_robot = torch.tensor([[-0.34], [-0.3], [0.0]], dtype=torch.float64)
    base = torch.stack([pose((0.0, 0.0, 0.2)), pose((0.0, 0.0, 0.21), 0.05), pose((0.0, 0, 0.2))])
    state = simulator.initial_state(q=q.unsqueeze(1), q_robot=q_robot, robot_base=base.unsqueeze(1))
    commands = torch.tensor([[[-1.0]], [[-0.5]], [[0.3]]], dtype=torch.float64).expand(3, 3, 1)
    twists = torch.zeros(3, 3, 1, 6, dtype=torch.float64)
    twists[..., 2] = torch.tensor([0.0, -0.05, 0.02], dtype=torch.float64)[:, None]
    batched = simulator.rollout(
        state, steps=3, joint_commands=commands.transpose(0, 1), base_twists=twists.transpose(0, 1)
    )
    for b in range(3):
        alone = simulator.rollout(
            state[b : b + 1],
            steps=3,
            joint_commands=commands[b : b + 1].transpose(0, 1),
            base_twists=twists[b : b + 1].transpose(0, 1),
        )
        for name in ("q", "v", "q_robot", "v_robot", "robot_base"):
            torch.testing.assert_close(
                getattr(batched, name)[:, b], getattr(alone, name)[:, 0], rtol=0, atol=1e-12
            )
        # A box resting on four corners splits its weight between them in no unique way (the
        # solvers' answers differ by ~1e-10 with the batch's compaction width): compare each
        # group's total impulse.
        for group in (slice(0, 8), slice(8, 16)):
            torch.testing.assert_close(
                batched.pn[:, b, group].sum(-1), alone.pn[:, 0, group].sum(-1), rtol=0, atol=1e-12
            )
    assert float(batched.pn[:, 0, 8:].sum()) > 0  # the first arm presses its box


def test_rollout_gradients_through_the_robot_agree_with_finite_differences(hinge: Robot) -> None:
    """d/d(initial joint angle, servo target, base speed) of the arm's and the box's final
    state, while the servo arm presses the box (active contacts every step): autograd through
    the mode-fixed steps against central differences of the same rollouts."""
    simulator = hinge_scene(hinge, stiffness=50.0, damping=1.0, torque_limit=10.0)

    def outcome(inputs: torch.Tensor) -> torch.Tensor:
        angle, target, speed = inputs.unbind()
        state = simulator.initial_state(
            q=pose((0.2, 0.0, 0.05)).view(1, 1, 7), q_robot=angle.view(1, 1)
        )
        twists = torch.zeros(4, 1, 1, 6, dtype=torch.float64)
        twists = twists + torch.stack(
            [speed, speed * 0, speed * 0, speed * 0, speed * 0, speed * 0]
        ).view(1, 1, 1, 6)
        run = simulator.rollout(
            state, steps=4, joint_commands=target.view(1, 1, 1).expand(4, 1, 1), base_twists=twists
        )
        assert float(run.pn[:, 0, 8:].sum(-1).min().detach()) > 0  # pressing at every step
        return torch.stack([run.q_robot[-1, 0, 0], run.v_robot[-1, 0, 0], run.q[-1, 0, 0, 0]])

    inputs = torch.tensor([-0.3434, -0.6, 0.05], dtype=torch.float64, requires_grad=True)
    jacobian = torch.autograd.functional.jacobian(outcome, inputs)
    eps = 1e-6
    expected = torch.stack(
        [
            (outcome(inputs.detach() + eps * e) - outcome(inputs.detach() - eps * e)) / (2 * eps)
            for e in torch.eye(3, dtype=torch.float64)
        ],
        dim=-1,
    )
    torch.testing.assert_close(jacobian, expected, rtol=1e-5, atol=1e-7)


ELBOW_URDF = HINGE_URDF.replace(
    "</robot>",
    """  <joint name="elbow" type="revolute">
    <parent link="arm"/>
    <child link="forearm"/>
    <origin xyz="0.3 0 0" rpy="0 0 0"/>
    <axis xyz="0 -1 0"/>
    <limit lower="-3" upper="3" effort="0" velocity="0"/>
  </joint>
  <link name="forearm">
    <inertial>
      <origin xyz="0.1 0 0" rpy="0 0 0"/>
      <mass value="0.2"/>
      <inertia ixx="1e-5" ixy="0" ixz="0" iyy="0.0006667" iyz="0" izz="0.0006667"/>
    </inertial>
    <collision>
      <origin xyz="0.1 0 0" rpy="0 0 0"/>
      <geometry><box size="0.2 0.02 0.02"/></geometry>
    </collision>
  </link>
</robot>""",
)


def test_kinematic_joints_of_a_servo_robot(tmp_path: Path) -> None:
    """A servo robot whose first joint is kinematic (``kinematic_joints``): the problem has a
    column for the servoed elbow only, whose rows on a forearm contact are central
    differences of the contact point along the elbow angle; the commanded shoulder rate and
    the base twist enter ``bn``, ``bt`` as differences along that motion; the shoulder follows
    its command exactly."""
    path = tmp_path / "elbow.urdf"
    path.write_text(ELBOW_URDF)
    robot = Robot.from_urdf(path)
    base = pose((0.0, 0.0, 0.2), 0.2)
    member = RobotMember("arm", robot, kinematic_joints=("hinge",), base_pose=base)
    box = Body("box", Box((0.05, 0.05, 0.05)), mass=1.0)
    ground = Body("ground", HalfSpace.ground(), kind="static")
    simulator = Simulator(Scene(bodies=(ground, box), robots=(member,)))
    assert simulator.scene.num_dofs == 7
    centre = (0.45 * math.cos(0.2), 0.45 * math.sin(0.2), 0.05)
    q_robot = torch.tensor([[0.0, -0.5]], dtype=torch.float64)
    state = simulator.initial_state(
        q=pose(centre, 0.2).view(1, 1, 7), q_robot=q_robot, robot_base=base.view(1, 1, 7)
    )
    command = torch.tensor([[0.4, -0.6]], dtype=torch.float64)  # shoulder rate, elbow target
    twist = torch.tensor([[[0.02, 0.01, -0.03, 0.0, 0.1, 0.2]]], dtype=torch.float64)
    problem, geometry = contact_problem(
        simulator.scene, state, joint_command=command, base_twist=twist
    )
    slots = [k for k in range(16, 24) if bool(geometry.active[0, k])]  # forearm–box slots
    assert slots
    directions = tangent_directions(geometry.normals[0], simulator.scene.friction_directions)
    eps = 1e-6
    for k in slots:
        local = link_local(robot, base, q_robot[0], "forearm", geometry.points[0, k])
        normal, tangents = geometry.normals[0, k], directions[k]

        def moved(t: float, rates: torch.Tensor, motion: torch.Tensor, local=local):
            turned = torch.cat([base[:3] + t * motion[:3], _turn(base[3:], t * motion[3:])])
            return world_point(robot, turned, q_robot[0] + t * rates, "forearm", local)

        still = torch.zeros(6, dtype=torch.float64)
        elbow = torch.tensor([0.0, 1.0], dtype=torch.float64)
        velocity = (moved(eps, elbow, still) - moved(-eps, elbow, still)) / (2 * eps)
        torch.testing.assert_close(problem.Jn[0, k, 6], normal @ velocity, rtol=0, atol=1e-8)
        torch.testing.assert_close(problem.Jt[0, k, :, 6], tangents @ velocity, rtol=0, atol=1e-8)
        shoulder = torch.tensor([0.4, 0.0], dtype=torch.float64)
        velocity = (moved(eps, shoulder, twist[0, 0]) - moved(-eps, shoulder, twist[0, 0])) / (
            2 * eps
        )
        torch.testing.assert_close(problem.bn[0, k], normal @ velocity, rtol=0, atol=1e-8)
        torch.testing.assert_close(problem.bt[0, k], tangents @ velocity, rtol=0, atol=1e-8)
    run = simulator.rollout(
        state, steps=5, joint_commands=command.expand(5, 1, 2), base_twists=twist.expand(5, 1, 1, 6)
    )
    time = simulator.scene.h * torch.arange(6, dtype=torch.float64)
    torch.testing.assert_close(run.q_robot[:, 0, 0], 0.4 * time, rtol=0, atol=1e-12)
    torch.testing.assert_close(
        run.v_robot[1:, 0, 0], torch.full((5,), 0.4, dtype=torch.float64), rtol=0, atol=1e-15
    )


def test_an_exact_answer_within_retry_residual_is_accepted() -> None:
    """A BarrettHand grasp's contact problem (16 slots, 10 degrees of freedom: the box and
    the hand's four servoed joints; recorded from the Barrett box experiment, seed 1, whose
    trial failed there) on which Lemke's pivoting stops short of its own tolerance and the QP
    fallback does not converge in its rounds. Lemke's answer solves the LCP to a residual
    (the Stewart–Trinkle complementarity conditions, ``lcp_residual``) far below
    ``retry_residual``: the step accepts it, and with ``retry_residual`` below that residual
    it reports the entry unsolved instead."""
    fields = torch.load(
        Path(__file__).parent / "data" / "barretthand_grasp_lemke_stall.pt", weights_only=True
    )
    problem = ContactProblem(**fields)
    lemke = solve(problem, "lemke")
    assert not bool(lemke.status.converged.any())
    residual = lcp_residual(problem, v_next=lemke.v_next, pn=lemke.pn, pt=lemke.pt)
    assert float(residual) < 1e-8
    assert not bool(solve(problem, "qp").status.converged.any())
    scene = Scene(bodies=(Body("box", Box((0.05, 0.05, 0.05)), mass=1.0),))
    guess = torch.zeros(1, problem.num_slots, dtype=torch.long)
    solution, solver = Simulator(scene)._solve(problem, guess)
    assert int(solver[0]) != UNSOLVED
    accepted = lcp_residual(problem, v_next=solution.v_next, pn=solution.pn, pt=solution.pt)
    assert float(accepted) < 1e-8
    strict = Simulator(scene, retry_residual=0.1 * float(residual))
    _, strict_solver = strict._solve(problem, guess)
    assert int(strict_solver[0]) == UNSOLVED
