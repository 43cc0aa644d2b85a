"""The spatial contact model and the RBPF on SE(3), against independent references: central
finite differences on the manifold (Richardson-extrapolated) for the per-mode Jacobians, the
SE(3) EKF (``ekf_predict``/``ekf_update`` with a closed-form free-flight step) for the RBPF
with one mode and no contact, exact enumeration for the tactile likelihood, closed-form
weighted means of rotations about one axis for the Karcher mixture mean."""

from __future__ import annotations

import dataclasses
import itertools
import math

import pytest
import torch
from torch import Tensor

from torchcontact.experiments import BarrettBoxGrasp, box_filter_scene
from torchcontact.filters import (
    RBPF,
    SE3,
    Gaussian,
    RobotControl,
    SpatialContactModel,
    ekf_predict,
    ekf_update,
    project_out_of_contact,
)
from torchcontact.filters._mode_gate import gate_log_weight
from torchcontact.filters._spatial_contact_model import group_states
from torchcontact.geometry import Box, HalfSpace, Sphere, quat_exp, quat_mul, quat_to_matrix
from torchcontact.robots import load
from torchcontact.sim import Body, RobotMember, Scene, Simulator, contact_problem
from torchcontact.states import TactileArray

DT = torch.float64
H = 0.01
#: Half extents of the tracked box, metres.
HALF = (0.02, 0.02, 0.03)
#: The hand upside down (palm facing down); its palm face lies 0.084 m below its base.
HAND_DOWN = (0.0, 1.0, 0.0, 0.0)
PALM_DEPTH = 0.084


def hand_scene(*, height: float, cube: bool = False) -> Scene:
    """The box on the table under a kinematic BarrettHand whose base is at ``height``."""
    base = torch.tensor([0.0, 0.0, height, *HAND_DOWN], dtype=DT)
    member = RobotMember("hand", load("bhand"), mode="kinematic", base_pose=base)
    half = (0.025, 0.025, 0.025) if cube else HALF
    box = Body("box", Box(half), mass=0.3)
    table = Body("table", HalfSpace.ground(), kind="static")
    return Scene(bodies=(table, box), robots=(member,), friction=0.5, friction_directions=4, h=H)


def finger_scene() -> Scene:
    """The box on the table and a kinematic ball (a finger) against its −x face."""
    box = Body("box", Box(HALF), mass=0.3)
    table = Body("table", HalfSpace.ground(), kind="static")
    finger = Body("finger", Sphere(0.01), kind="kinematic")
    return Scene(bodies=(table, box, finger), friction=0.4, friction_directions=4, h=H)


def state(position: tuple[float, float, float], twist: tuple[float, ...] = (0.0,) * 6) -> Tensor:
    """``(13,)`` the box at ``position``, unrotated, with ``twist``."""
    return torch.tensor([*position, 1.0, 0.0, 0.0, 0.0, *twist], dtype=DT)


def simulated_mode(scene: Scene, x: Tensor, **inputs: Tensor) -> Tensor:
    """``(S,)`` the contact mode of the simulator's (Lemke's) step from ``x``."""
    simulator = Simulator(scene)
    kinematic = inputs.pop("q_kinematic", None)
    control = inputs.pop("control", None)
    joint_command = inputs.pop("joint_command", None)
    base_twist = inputs.pop("base_twist", None)
    start = simulator.initial_state(
        q=x[None, None, :7],
        v=x[None, None, 7:],
        q_kinematic=kinematic,
        **inputs,
    )
    result = simulator.step(start, control, joint_command=joint_command, base_twist=base_twist)
    return result.mode[0]


def model_of(scene: Scene, modes: Tensor, **options: object) -> SpatialContactModel:
    K = modes.shape[0]
    return SpatialContactModel(
        scene=scene,
        modes=modes,
        Q=1e-8 * torch.eye(12, dtype=DT),
        R=torch.diag(torch.tensor([25e-6] * 3 + [1.2e-3] * 3, dtype=DT)),
        transition=torch.full((K, K), 1.0 / K, dtype=DT),
        **options,  # type: ignore[arg-type]
    )


def finite_difference_jacobian(
    model: SpatialContactModel, x: Tensor, mode: int, control: RobotControl | None
) -> Tensor:
    """``(12, 12)`` central differences of ``δ ↦ local(f(x), f(retract(x, δ)))``,
    Richardson-extrapolated (error O(ε⁴))."""
    ids = torch.tensor(mode)
    base = model.step(x, mode=ids, control=control)

    def along(delta: Tensor) -> Tensor:
        return SE3.local(base, model.step(SE3.retract(x, delta), mode=ids, control=control))

    def central(eps: float) -> Tensor:
        columns = []
        for j in range(12):
            e = torch.zeros(12, dtype=DT)
            e[j] = eps
            columns.append((along(e) - along(-e)) / (2 * eps))
        return torch.stack(columns, dim=-1)

    eps = 1e-4
    return (4 * central(eps / 2) - central(eps)) / 3


def assert_jacobian_matches(
    model: SpatialContactModel, x: Tensor, control: RobotControl, *, relative: float = 1e-7
) -> None:
    # No gap closed: the linearization is that of step() itself (closing: its own test).
    model = dataclasses.replace(model, consistency_gap=0.0)
    F, f, converged = model.linearize(x, control=control)
    assert bool(converged.all())
    for k in range(model.num_modes):
        expected = finite_difference_jacobian(model, x, k, control)
        # Rounding of the steps (1e-15 relative) over 2ε = 1e-4 bounds the difference error at
        # ~1e-10 of the largest entry (100: the gap term 1/h); the derivative's Tikhonov
        # iterates converge to ~1e-9 of it.
        scale = float(expected.abs().max())
        torch.testing.assert_close(F[k], expected, rtol=0.0, atol=relative * scale)
        # The linearization solves on the slots some mode activates, the step on all.
        torch.testing.assert_close(
            f[k], model.step(x, mode=torch.tensor(k), control=control), rtol=0.0, atol=1e-10
        )


def test_jacobian_of_a_box_resting_on_redundant_corners() -> None:
    """Four coplanar sticking corners (a singular, consistent system) and the free flight,
    under a hand far above: the exact Jacobian equals finite differences on the manifold."""
    scene = hand_scene(height=0.4)
    control = RobotControl(q_robot=torch.zeros(4, dtype=DT), v_robot=torch.zeros(4, dtype=DT))
    x = state((0.0, 0.0, HALF[2]), (0.01, -0.02, 0.0, 0.1, 0.05, -0.2))
    mode = simulated_mode(scene, x, q_robot=control.q_robot[None])
    assert int((mode[:4] >= 1).sum()) == 4  # the four bottom corners touch
    modes = torch.stack([mode, torch.zeros_like(mode)])
    assert_jacobian_matches(model_of(scene, modes), x, control)


def test_a_mode_whose_gain_exceeds_max_gain_is_not_solved() -> None:
    """The box at rest on four sticking corners: its Jacobian's largest entry is the gap
    term 1/h = 100 (a gap δφ closes at δφ/h in one step). With ``max_gain`` just below it
    the mode counts as not solved, just above it as solved; the free flight (entries of
    order one and h) is solved either way."""
    scene = hand_scene(height=0.4)
    control = RobotControl(q_robot=torch.zeros(4, dtype=DT), v_robot=torch.zeros(4, dtype=DT))
    x = state((0.0, 0.0, HALF[2]))
    mode = simulated_mode(scene, x, q_robot=control.q_robot[None])
    modes = torch.stack([mode, torch.zeros_like(mode)])
    gain = 1.0 / scene.h
    for max_gain, expected in ((0.99 * gain, [False, True]), (1.01 * gain, [True, True])):
        model = model_of(scene, modes, consistency_gap=0.0, max_gain=max_gain)
        assert model.linearize(x, control=control)[2].tolist() == expected


def sliding_along(scene: Scene, x: Tensor, slot: int, twist: Tensor, **inputs: Tensor) -> int:
    """The sliding mode code ``2 + d`` of ``slot`` whose friction impulse (direction ``d``)
    opposes the slip of a body moving with ``twist`` (``d`` minimizes ``Jt_d · twist``)."""
    simulator = Simulator(scene)
    control = inputs.pop("control", None)
    base_twist = inputs.pop("base_twist", None)
    start = simulator.initial_state(q=x[None, None, :7], v=x[None, None, 7:], **inputs)
    problem, _ = contact_problem(scene, start, control=control, base_twist=base_twist)
    return 2 + int((problem.Jt[0, slot] @ twist).argmin())


def test_jacobian_of_a_box_pushed_by_a_finger() -> None:
    """A ball pushing a box in the air along +x (off its centre: the box turns), sticking to
    it or sliding along its face, and the box in free flight."""
    scene = finger_scene()
    # Turned (its faces' normals off the horizontal plane, across which the friction
    # directions' basis switches hemispheres), the ball touching its −x face.
    turn = quat_exp(torch.tensor([0.0, 0.2, 0.3], dtype=DT))
    x = torch.cat([torch.tensor([0.0, 0.0, 0.2], dtype=DT), turn])
    x = torch.cat([x, torch.tensor([0.05, 0.0, 0.01, 0.0, 0.3, 0.0], dtype=DT)])
    offset = torch.tensor([-HALF[0] - 0.01, 0.005, 0.01], dtype=DT)
    centre = x[:3] + quat_to_matrix(turn) @ offset
    ball = torch.cat([centre, torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=DT)])[None]
    push = torch.tensor([[0.2, 0.01, 0.0, 0.0, 0.0, 0.0]], dtype=DT)
    finger = next(
        g.start
        for g in scene.slot_groups
        if "finger" in (scene.bodies[g.other].name, scene.bodies[g.receiver].name)
    )
    inputs = {"q_kinematic": ball[None], "control": push[None]}
    down = torch.tensor([0.0, 0.0, -1.0, 0.0, 0.0, 0.0], dtype=DT)
    modes = torch.zeros(3, scene.num_slots, dtype=torch.long)
    modes[0, finger] = 1
    modes[1, finger] = sliding_along(scene, x, finger, down, **dict(inputs))
    control = RobotControl(
        q_robot=torch.zeros(0, dtype=DT),
        v_robot=torch.zeros(0, dtype=DT),
        q_kinematic=ball,
        v_kinematic=push,
    )
    assert_jacobian_matches(model_of(scene, modes), x, control)


def finger_on_a_tilted_box() -> tuple[Scene, Tensor, Tensor, Tensor, Tensor, int]:
    """Finger 1's outer link closing at 0.5 rad/s on a tilted box held in the air: the scene,
    the state, the joint angles and velocities, three modes (the link's first slot sticking,
    both its slots sliding against the box's upward slip, nothing touching) and the link's
    first slot."""
    scene = hand_scene(height=0.224)
    turn = quat_exp(torch.tensor([0.15, 0.1, 0.2], dtype=DT))
    x = torch.cat([torch.tensor([0.0, 0.0, 0.1], dtype=DT), turn, torch.zeros(6, dtype=DT)])
    q_robot = torch.tensor([0.0, 1.64, 0.0, 0.0], dtype=DT)
    v_robot = torch.tensor([0.0, 0.5, 0.0, 0.0], dtype=DT)
    outer = next(
        g.start
        for g in scene.robot_slot_groups
        if scene.robots[0].robot.collision_shapes[g.shape].link == "bhand_f1_outer"
    )
    up = torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0, 0.0], dtype=DT)
    modes = torch.zeros(3, scene.num_slots, dtype=torch.long)
    modes[0, outer] = 1
    for slot in (outer, outer + 1):
        modes[1, slot] = sliding_along(scene, x, slot, up, q_robot=q_robot[None])
    return scene, x, q_robot, v_robot, modes, outer


def test_jacobian_of_a_barrett_finger_closing_on_a_box() -> None:
    """Finger 1's outer link, closing at 0.5 rad/s (the joint velocity enters through the
    problem's known velocity terms), touches a tilted box held in the air at two points of
    its capsule: sticking at one, sliding at both, and free flight. Sticking at both
    contradicts the gaps' closing (the box would have to follow the link rigidly and close
    both gaps): its solve does not converge."""
    scene, x, q_robot, v_robot, modes, outer = finger_on_a_tilted_box()
    control = RobotControl(q_robot=q_robot, v_robot=v_robot)
    assert_jacobian_matches(model_of(scene, modes), x, control)
    both = modes[:1].clone()
    both[0, outer + 1] = 1
    _, _, converged = model_of(scene, both).linearize(x, control=control)
    assert not bool(converged[0])


def test_only_the_solved_modes_are_differentiated() -> None:
    """Finger 1 closing on the tilted box at two points at once: where it touches (A) and
    1 cm further along +x (B, the box free). The table: the link's first slot sticking, both
    its slots sticking (contradicts itself at A: not solved there), the simulator's mode at A
    (the first slot sliding) and free flight (the simulator's at B). Each solved (point, mode)
    pair's Jacobian equals finite differences at its point, its offset the steps seen from
    the chart (``step()``), and the simulator's mode at each point passes the gate with the
    simulator's (Lemke's) step; the unsolved pair keeps the placeholders (the identity, the
    point itself) and log-weight -inf."""
    scene, x, q_robot, v_robot, modes, outer = finger_on_a_tilted_box()
    points = torch.stack([x, x + torch.tensor([0.01, *([0.0] * 12)], dtype=DT)])
    simulator = Simulator(scene)
    start = simulator.initial_state(
        q=points[:, None, :7], v=points[:, None, 7:], q_robot=q_robot.expand(2, 4)
    )
    result = simulator.step(start, joint_command=v_robot.expand(2, 4))
    exact = torch.cat([result.state.q[:, 0], result.state.v[:, 0]], dim=-1)  # (2, 13)
    both = modes[0].clone()
    both[outer + 1] = 1
    assert (result.mode[1] == modes[2]).all()  # B: free flight (integers: exact)
    table = torch.stack([modes[0], both, result.mode[0], modes[2]])
    model = model_of(scene, table, consistency_gap=0.0)
    control = RobotControl(q_robot=q_robot, v_robot=v_robot)
    F, f, converged = model.linearize(points, control=control)
    assert converged.tolist() == [[True, False, True, True], [True, True, True, True]]
    for p, k in converged.nonzero().tolist():
        expected = finite_difference_jacobian(model, points[p], k, control)
        scale = float(expected.abs().max())  # the tolerance of assert_jacobian_matches
        torch.testing.assert_close(F[p, k], expected, rtol=0.0, atol=1e-7 * scale)
    assert (F[0, 1] == torch.eye(12, dtype=DT)).all()  # the placeholder is copied
    assert (f[0, 1] == points[0]).all()
    for p, k in ((0, 2), (1, 3)):  # the simulator's modes: its steps to the solver's 1e-9
        torch.testing.assert_close(f[p, k], exact[p], rtol=0.0, atol=1e-9)
    belief = RBPF(model, 4).init(
        Gaussian(points, 1e-10 * torch.eye(12, dtype=DT).expand(2, 12, 12))
    )
    belief = dataclasses.replace(belief, modes=torch.zeros(2, 4, dtype=torch.long))
    dynamics = model.mode_dynamics(belief, control)
    weights = dynamics.mode_log_weight
    assert weights is not None
    assert float(weights[0, 1]) == -math.inf
    assert float(weights[0, 2]) == 0.0  # the gate's constants: exact
    assert float(weights[1, 3]) == 0.0
    assert (dynamics.F[0, 1] == torch.eye(12, dtype=DT)).all()
    for p in range(2):
        chart = model.step(points[p], mode=torch.tensor(0), control=control)  # the likely one
        for k in converged[p].nonzero()[:, 0].tolist():
            step = model.step(points[p], mode=torch.tensor(k), control=control)
            torch.testing.assert_close(
                dynamics.c[p, k], SE3.local(chart, step), rtol=0.0, atol=1e-10
            )


def test_jacobian_of_a_box_sliding_on_redundant_corners() -> None:
    """A box sliding along +x (and turning) on its four bottom corners: a singular system
    whose friction rows share the normal rows' redundancy (the step is unique)."""
    scene = finger_scene()
    x = state((0.0, 0.0, HALF[2]), (0.3, 0.05, 0.0, 0.0, 0.0, 0.5))
    ball = torch.tensor([[0.5, 0.5, 0.5, 1.0, 0.0, 0.0, 0.0]], dtype=DT)
    forward = torch.tensor([1.0, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=DT)
    mode = torch.zeros(scene.num_slots, dtype=torch.long)
    for corner in range(4):
        mode[corner] = sliding_along(scene, x, corner, forward, q_kinematic=ball[None])
    control = RobotControl(
        q_robot=torch.zeros(0, dtype=DT), v_robot=torch.zeros(0, dtype=DT), q_kinematic=ball
    )
    assert_jacobian_matches(model_of(scene, mode[None]), x, control)


def test_jacobian_of_a_box_dragged_by_the_palm() -> None:
    """The hand's palm on the box top, moved sideways and turned by its base: the box sticks
    to the palm on four corners and slides on the table on four (redundant on either side;
    robot rows through the base twist)."""
    scene = hand_scene(height=HALF[2] * 2 + PALM_DEPTH)
    zeros = torch.zeros(4, dtype=DT)
    twist = torch.tensor([[0.05, 0.02, 0.0, 0.0, 0.0, 0.1]], dtype=DT)
    x = state((0.0, 0.0, HALF[2]))
    inputs = {"q_robot": zeros[None], "base_twist": twist[None]}
    mode = torch.zeros(scene.num_slots, dtype=torch.long)
    for corner in range(4):
        mode[corner] = sliding_along(scene, x, corner, twist[0], **dict(inputs))
    mode[8:12] = 1  # the box corners under the palm's face
    control = RobotControl(q_robot=zeros, v_robot=zeros, base_twist=twist)
    # Tilting the box breaks the parallel faces of the sandwich: the step's spin ω_z jumps
    # by ~1e-6 rad/s (solve_mode's split among the eight corners changes), so the central
    # differences of ω_z along the tilts are off by up to ~5e-4 (5e-6 of the largest entry).
    assert_jacobian_matches(model_of(scene, mode[None]), x, control, relative=2e-5)


def free_flight(x: Tensor) -> Tensor:
    """Closed-form step of a cube in free flight (isotropic inertia: no gyroscopic term):
    ``v⁺ = v + h g``, ``p⁺ = p + h v⁺``, ``q⁺ = Exp(h ω) ⊗ q``."""
    gravity = torch.tensor([0.0, 0.0, -9.81], dtype=x.dtype)
    v = x[7:10] + H * gravity
    q = quat_mul(quat_exp(H * x[10:13]), x[3:7])
    return torch.cat([x[:3] + H * v, q / q.norm(), v, x[10:13]])


def test_one_mode_without_contact_is_the_se3_ekf() -> None:
    """One mode (every slot separated), a cube in free flight far above the table: every
    particle of the RBPF is the EKF on SE(3), and the evidence its log-likelihoods, through
    an occluded step (NaN) and a position-only one (mask)."""
    scene = hand_scene(height=1.0, cube=True)
    modes = torch.zeros(1, scene.num_slots, dtype=torch.long)
    model = model_of(scene, modes)
    control = RobotControl(q_robot=torch.zeros(4, dtype=DT), v_robot=torch.zeros(4, dtype=DT))
    axis = torch.tensor([0.3, -0.2, 0.9], dtype=DT)
    start = torch.cat(
        [
            torch.tensor([0.1, 0.2, 0.5], dtype=DT),
            quat_exp(0.7 * axis / axis.norm()),
            torch.tensor([0.2, -0.1, 0.3, 1.5, -2.0, 0.7], dtype=DT),
        ]
    )
    spread = torch.linspace(1.0, 3.0, 12, dtype=DT)
    prior = Gaussian(start, torch.diag(1e-4 * spread))
    rbpf = RBPF(model, 3)
    belief = rbpf.init(prior)
    reference, log_evidence = prior, torch.zeros((), dtype=DT)
    g = torch.Generator().manual_seed(0)
    nan = torch.full((7,), math.nan, dtype=DT)
    position_only = torch.tensor([True] * 3 + [False] * 3)
    for t in range(5):
        truth = free_flight(reference.mean)
        noise = 0.01 * torch.randn(6, generator=g, dtype=DT)
        y = nan if t == 2 else SE3.retract(truth[:7], noise)  # occluded at t = 2
        mask = position_only if t == 3 else None  # the orientation unknown at t = 3
        belief = rbpf.step(belief, y, control=control, mask=mask)
        reference = ekf_predict(reference, free_flight, Q=model.Q, manifold=SE3)
        reference, log_lik = ekf_update(
            reference,
            y,
            lambda x: x[:7],
            R=model.R,
            mask=mask,
            manifold=SE3,
            measurement_manifold=SE3,
        )
        log_evidence = log_evidence + log_lik
        for i in range(3):
            torch.testing.assert_close(
                belief.gaussians.mean[i], reference.mean, rtol=0.0, atol=1e-10
            )
            torch.testing.assert_close(
                belief.gaussians.cov[i], reference.cov, rtol=1e-8, atol=1e-14
            )
        torch.testing.assert_close(belief.log_evidence, log_evidence, rtol=1e-9, atol=1e-9)


def test_rbpf_keeps_unit_quaternions_while_the_box_tips() -> None:
    """A spinning box pressed by the palm, 1,000 particles with spread orientations: every
    particle's quaternion and the Karcher mean stay unit (to rounding)."""
    scene = hand_scene(height=HALF[2] * 2 + PALM_DEPTH)
    zeros = torch.zeros(4, dtype=DT)
    twist = torch.tensor([[0.05, 0.0, -0.01, 0.0, 0.0, 0.5]], dtype=DT)
    x = state((0.0, 0.0, HALF[2]), (0.0, 0.0, 0.0, 0.0, 0.0, 1.0))
    mode = simulated_mode(scene, x, q_robot=zeros[None], base_twist=twist[None])
    free = torch.zeros_like(mode)
    model = model_of(scene, torch.stack([mode, free]))
    control = RobotControl(q_robot=zeros, v_robot=zeros, base_twist=twist)
    rbpf = RBPF(model, 1000, proposal="all_modes")
    belief = rbpf.init(
        Gaussian(x, torch.diag(torch.tensor([1e-6] * 3 + [0.05] * 3 + [1e-4] * 6, dtype=DT)))
    )
    generator = torch.Generator().manual_seed(1)
    for _ in range(5):
        y = x[:7] + 0.01 * torch.randn(7, generator=generator, dtype=DT)
        y = torch.cat([y[:3], y[3:] / y[3:].norm()])
        belief = rbpf.step(belief, y, control=control, generator=generator)
        quaternions = belief.gaussians.mean[..., 3:7]
        torch.testing.assert_close(
            quaternions.norm(dim=-1), torch.ones(1000, dtype=DT), rtol=0.0, atol=1e-12
        )
        torch.testing.assert_close(
            belief.mean()[3:7].norm(), torch.tensor(1.0, dtype=DT), rtol=0.0, atol=1e-12
        )
        assert bool(torch.isfinite(belief.log_evidence))


def test_karcher_mean_of_rotations_about_one_axis() -> None:
    """Particles turned about one axis by angles θ_i (some stored as −q, the same rotation):
    the mixture mean turns by the weighted mean angle, positions and twists average."""
    scene = hand_scene(height=1.0)
    model = model_of(scene, torch.zeros(1, scene.num_slots, dtype=torch.long))
    rbpf = RBPF(model, 4)
    axis = torch.tensor([1.0, 2.0, -2.0], dtype=DT) / 3.0
    angles = torch.tensor([0.1, -0.3, 0.5, 0.2], dtype=DT)
    weights = torch.tensor([0.1, 0.4, 0.3, 0.2], dtype=DT)
    quaternions = quat_exp(angles[:, None] * axis)
    signs = torch.tensor([1.0, -1.0, 1.0, -1.0], dtype=DT)[:, None]
    rest = torch.randn(4, 9, generator=torch.Generator().manual_seed(2), dtype=DT)
    means = torch.cat([rest[:, :3], signs * quaternions, rest[:, 3:]], dim=-1)
    belief = rbpf.init(Gaussian(means[0], torch.eye(12, dtype=DT)))
    belief = dataclasses.replace(
        belief, log_weights=weights.log(), gaussians=Gaussian(means, belief.gaussians.cov)
    )
    mean = belief.mean()
    expected_rotation = quat_exp((weights * angles).sum() * axis)
    turn = quat_mul(expected_rotation * torch.tensor([1.0, -1, -1, -1], dtype=DT), mean[3:7])
    assert abs(abs(float(turn[0])) - 1.0) < 1e-12
    torch.testing.assert_close(
        mean[:3], (weights[:, None] * rest[:, :3]).sum(0), rtol=0, atol=1e-12
    )
    torch.testing.assert_close(
        mean[7:], (weights[:, None] * rest[:, 3:]).sum(0), rtol=0, atol=1e-12
    )


def test_tactile_likelihood_is_normalized_and_reads_the_palm() -> None:
    """Pads on the palm (two on the touched face, one away) and a finger link: for every
    mode, the likelihood summed over all 2^4 readings is 1; with noise-free pads a mode that
    touches the palm predicts exactly the pads under the box's corners."""
    scene = hand_scene(height=HALF[2] * 2 + PALM_DEPTH)
    palm_face = 0.084
    positions = torch.tensor(
        [[0.02, 0.02, palm_face], [0.0, 0.0, palm_face], [-0.04, 0.04, 0.0]], dtype=DT
    )
    normals = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]], dtype=DT)
    palm = TactileArray(positions, normals, radius=0.005, half_angle=0.3)
    noisy_palm = TactileArray(
        positions, normals, radius=0.005, half_angle=0.3, false_positive=0.1, false_negative=0.2
    )
    finger = TactileArray(
        torch.tensor([[0.03, 0.0, 0.0]], dtype=DT),
        torch.tensor([[0.0, 0.0, 1.0]], dtype=DT),
        radius=0.01,
        half_angle=0.5,
        false_positive=0.05,
        false_negative=0.1,
    )
    touching = torch.zeros(scene.num_slots, dtype=torch.long)
    touching[:4] = 1
    touching[8:12] = 1
    modes = torch.stack([touching, torch.zeros_like(touching)])
    zeros = torch.zeros(4, dtype=DT)
    control = RobotControl(q_robot=zeros, v_robot=zeros)
    pose = state((0.0, 0.0, HALF[2]))[:7]
    readings = torch.tensor(list(itertools.product([False, True], repeat=4)))
    model = model_of(scene, modes, tactile={"bhand_palm": noisy_palm, "bhand_f1_inner": finger})
    log_lik = model.tactile_log_likelihood(readings, pose=pose, control=control)  # (16, K)
    torch.testing.assert_close(log_lik.exp().sum(0), torch.ones(2, dtype=DT), rtol=0, atol=1e-12)
    # Noise-free: the palm's pad under the box corner (0.02, 0.02) (the hand is turned about x,
    # so the corner (0.02, −0.02) of the world lies at (0.02, 0.02) in the palm frame) is on.
    exact = model_of(scene, modes, tactile={"bhand_palm": palm})
    expected = torch.tensor([True, False, False])
    log_exact = exact.tactile_log_likelihood(
        torch.stack([expected, torch.zeros(3, dtype=torch.bool)]), pose=pose, control=control
    )
    assert float(log_exact[0, 0]) == 0.0  # the touching mode predicts these readings
    assert float(log_exact[0, 1]) == -math.inf  # the free mode cannot
    assert float(log_exact[1, 1]) == 0.0


def box_stuck_to_a_moving_ball() -> tuple[Scene, Tensor, RobotControl, Tensor, Tensor]:
    """The box resting on the table and a ball moving along +x against its side: the
    scene, the state, the control, a mode sticking the box to the table and to the ball
    (its equalities contradict each other) and the mode resting on the table alone."""
    scene = finger_scene()
    x = state((0.0, 0.0, HALF[2]))
    ball = torch.tensor([[-HALF[0] - 0.01, 0.0, 0.01, 1.0, 0.0, 0.0, 0.0]], dtype=DT)
    control = RobotControl(
        q_robot=torch.zeros(0, dtype=DT),
        v_robot=torch.zeros(0, dtype=DT),
        q_kinematic=ball,
        v_kinematic=torch.tensor([[0.3, 0.0, 0.0, 0.0, 0.0, 0.0]], dtype=DT),
    )
    stuck = torch.zeros(scene.num_slots, dtype=torch.long)
    stuck[:4] = 1
    finger_slots = [
        s
        for g in scene.slot_groups
        if "finger" in (scene.bodies[g.other].name, scene.bodies[g.receiver].name)
        for s in range(g.start, g.start + g.count)
    ]
    stuck[finger_slots] = 1
    resting = torch.zeros_like(stuck)
    resting[:4] = 1
    return scene, x, control, stuck, resting


def test_self_contradicting_mode_is_ruled_out() -> None:
    """The box sticking to the table and to a ball that moves: the equalities contradict
    each other, solve_mode does not converge, and the mode's log-weight is -inf."""
    scene, x, control, stuck, resting = box_stuck_to_a_moving_ball()
    model = model_of(scene, torch.stack([stuck, resting]))
    _, _, converged = model.linearize(x, control=control)
    assert converged.tolist() == [False, True]
    belief = RBPF(model, 2).init(Gaussian(x, 1e-6 * torch.eye(12, dtype=DT)))
    weights = model.mode_dynamics(belief, control).mode_log_weight
    assert weights is not None
    assert float(weights[0]) == -math.inf
    assert math.isfinite(float(weights[1]))


def test_the_chart_is_the_mean_where_the_likely_mode_is_not_solved() -> None:
    """The belief's most probable mode contradicts itself (not solved): every mode's step is
    expressed at the mean, not at that mode's meaningless answer, so the solved mode's offset
    is its own step seen from the mean (``step()`` through the simulator's assembly)."""
    scene, x, control, stuck, resting = box_stuck_to_a_moving_ball()
    model = model_of(scene, torch.stack([stuck, resting]))
    belief = RBPF(model, 2).init(Gaussian(x, 1e-6 * torch.eye(12, dtype=DT)))
    belief = dataclasses.replace(belief, modes=torch.tensor([0, 0]))  # the unsolved mode
    dynamics = model.mode_dynamics(belief, control)
    torch.testing.assert_close(dynamics.chart, x, rtol=0.0, atol=1e-15)
    step = model.step(x, mode=torch.tensor(1), control=control)
    torch.testing.assert_close(dynamics.c[1], SE3.local(x, step), rtol=0.0, atol=1e-10)


def test_a_point_no_mode_explains_holds_its_state() -> None:
    """The same box with only the self-contradicting mode in the table and the inconsistent
    modes ruled out: no mode's step is trusted, so the point holds its state for the step
    (the identity Jacobian, the state itself as the step, log-weight 0) rather than losing
    every mode."""
    scene, x, control, stuck, _ = box_stuck_to_a_moving_ball()
    model = model_of(scene, stuck[None], inconsistency_penalty=math.inf)
    F, f, converged = model.linearize(x, control=control)
    assert converged.tolist() == [False]
    assert (F[0] == torch.eye(12, dtype=DT)).all()  # the held step is copied, not computed
    assert (f[0] == x).all()
    belief = RBPF(model, 1).init(Gaussian(x, 1e-6 * torch.eye(12, dtype=DT)))
    weights = model.mode_dynamics(belief, control).mode_log_weight
    assert weights is not None
    assert float(weights[0]) == 0.0


@pytest.mark.parametrize(
    ("change", "name"),
    [
        ({"modes": torch.zeros(2, 3, dtype=torch.long)}, "modes"),
        ({"modes": torch.full((1, 34), 99, dtype=torch.long)}, "modes"),
        ({"Q": torch.eye(6, dtype=DT)}, "Q"),
        ({"R": torch.eye(7, dtype=DT)}, "R"),
        ({"R": -torch.eye(6, dtype=DT)}, "R"),
        ({"transition": torch.ones(1, 1, dtype=DT) * 2}, "transition"),
        ({"inconsistency_penalty": -1.0}, "inconsistency_penalty"),
        ({"max_gain": 0.0}, "max_gain"),
        ({"tactile": {"no_such_link": None}}, "tactile"),
        ({"scene": "table"}, "scene"),
    ],
)
def test_bad_fields_name_the_field(change: dict, name: str) -> None:
    scene = hand_scene(height=1.0)
    fields = {
        "scene": scene,
        "modes": torch.zeros(1, scene.num_slots, dtype=torch.long),
        "Q": torch.eye(12, dtype=DT),
        "R": torch.eye(6, dtype=DT),
        "transition": torch.ones(1, 1, dtype=DT),
    }
    fields.update(change)
    with pytest.raises(ValueError, match=name):
        SpatialContactModel(**fields)


def servo_hand_scene() -> Scene:
    """The box on the table under a BarrettHand at 0.224 m whose joints are servoed (PD with
    the experiment's gains and torque limits, gravity compensated)."""
    base = torch.tensor([0.0, 0.0, 0.224, *HAND_DOWN], dtype=DT)
    member = RobotMember(
        "hand",
        load("bhand"),
        mode="servo",
        base_pose=base,
        stiffness=torch.tensor([50.0, 5.0, 5.0, 10.0], dtype=DT),
        damping=torch.tensor([1.0, 0.05, 0.05, 0.1], dtype=DT),
        torque_limit=torch.tensor([10.0, 0.25, 0.25, 0.5], dtype=DT),
        gravity_compensation=True,
    )
    box = Body("box", Box(HALF), mass=0.3)
    table = Body("table", HalfSpace.ground(), kind="static")
    return Scene(bodies=(table, box), robots=(member,), friction=0.5, friction_directions=4, h=H)


def test_a_servo_hand_is_stepped_with_the_box() -> None:
    """Finger 1 of a servoed BarrettHand (PD towards a closed target, torque limited) closing
    on the tilted box held in the air: the model steps the finger's joint with the box from
    its measured state under the command, so its step under the simulator's own (Lemke) mode
    is the simulator's step, and its Jacobian matches finite differences of that step."""
    scene = servo_hand_scene()
    _, x, q_robot, v_robot, _, _ = finger_on_a_tilted_box()
    command = torch.tensor([0.0, 2.2, 0.0, 0.0], dtype=DT)
    simulator = Simulator(scene)
    start = simulator.initial_state(
        q=x[None, None, :7], v=x[None, None, 7:], q_robot=q_robot[None], v_robot=v_robot[None]
    )
    result = simulator.step(start, joint_command=command[None])
    mode = result.mode[0]
    assert bool((mode >= 1).any())  # the finger touches the box
    exact = torch.cat([result.state.q[0, 0], result.state.v[0, 0]])
    model = model_of(scene, mode[None])
    control = RobotControl(q_robot=q_robot, v_robot=v_robot, joint_command=command)
    torch.testing.assert_close(
        model.step(x, mode=torch.tensor(0), control=control), exact, rtol=0.0, atol=1e-9
    )
    assert_jacobian_matches(model, x, control)
    with pytest.raises(ValueError, match=r"control\.joint_command"):
        model.step(x, mode=torch.tensor(0), control=RobotControl(q_robot=q_robot, v_robot=v_robot))


def test_measured_joint_velocities_weigh_the_modes() -> None:
    """Proprioception: finger 1 closes on the box and is slowed by it (the simulator's Lemke
    step gives its measured velocity at the end of the step). The mode with the finger's
    contact predicts exactly that velocity; the mode without predicts the finger's free
    motion, the simulator's step with the box out of reach. With a belief of negligible
    covariance each child's measurement likelihood is N(v_measured; v_k, σ² I), so the two
    modes' log-weights differ by -|v_measured - v_free|² / (2σ²). The gate is off and no gap
    closed (the steps are those of step())."""
    scene = servo_hand_scene()
    _, x, q_robot, v_robot, _, _ = finger_on_a_tilted_box()
    command = torch.tensor([0.0, 2.2, 0.0, 0.0], dtype=DT)
    simulator = Simulator(scene)

    def end_velocity(box: Tensor) -> tuple[Tensor, Tensor]:
        start = simulator.initial_state(
            q=box[None, None, :7],
            v=box[None, None, 7:],
            q_robot=q_robot[None],
            v_robot=v_robot[None],
        )
        result = simulator.step(start, joint_command=command[None])
        assert result.state.v_robot is not None
        return result.state.v_robot[0], result.mode[0]

    measured, touching = end_velocity(x)
    away = x.clone()
    away[2] = 0.5  # out of the fingers' reach
    free, _ = end_velocity(away)
    assert float((measured - free).abs().max()) > 1e-3  # the box slows the finger
    sigma = 0.05
    modes = torch.stack([touching, torch.zeros_like(touching)])
    model = model_of(
        scene, modes, joint_velocity_sigma=sigma, inconsistency_penalty=0.0, consistency_gap=0.0
    )
    belief = RBPF(model, 2).init(Gaussian(x, 1e-16 * torch.eye(12, dtype=DT)))
    control = RobotControl(
        q_robot=q_robot, v_robot=v_robot, joint_command=command, v_robot_next=measured
    )
    dynamics = model.mode_dynamics(belief, control)
    weights = dynamics.particle_log_weight
    assert weights is not None
    expected = -0.5 * float(((measured - free) / sigma).pow(2).sum())
    normalizer = -0.5 * 4 * math.log(2 * math.pi * sigma**2)
    torch.testing.assert_close(
        weights[:, 0], torch.full((2,), normalizer, dtype=DT), rtol=0.0, atol=1e-6
    )
    torch.testing.assert_close(
        weights[:, 1] - weights[:, 0], torch.full((2,), expected, dtype=DT), rtol=1e-6, atol=0.0
    )


def test_projection_moves_the_box_with_a_servoed_finger_it_sticks_to() -> None:
    """A particle whose mode has the box stick to finger 1's outer link, which closes at
    0.5 rad/s (a servo joint: its motion is a column of the contact rows, not a known velocity
    term): the projection's twist makes the box's contact point move with the finger's, whose
    velocity is the finite difference of the link's forward kinematics (central, ε = 1e-6
    rad: error ~ε² |p̈| ≈ 1e-12 m/s, far below the pseudo-measurement's softness, std
    s = 1e-6 m/s against a prior std of 0.1 m/s)."""
    scene = servo_hand_scene()
    _, x, q_robot, v_robot, modes, outer = finger_on_a_tilted_box()
    model = model_of(scene, modes[:1])
    belief = RBPF(model, 1).init(Gaussian(x, 0.01 * torch.eye(12, dtype=DT)))
    control = RobotControl(q_robot=q_robot, v_robot=v_robot, joint_command=torch.zeros(4, dtype=DT))
    projected = project_out_of_contact(
        belief, scene, gap_sigma=1e-6 * scene.h, control=control, mode_table=modes[:1]
    )
    twist = projected.gaussians.mean[0, 7:]
    # The contact point and the link's motion, independently of the contact problem.
    state_ = Simulator(scene).initial_state(
        q=x[None, None, :7], v=x[None, None, 7:], q_robot=q_robot[None]
    )
    _, geometry = contact_problem(scene, state_, joint_command=torch.zeros(1, 4, dtype=DT))
    point = geometry.points[0, outer]
    robot = scene.robots[0].robot
    base = torch.eye(4, dtype=DT)
    base[:3, :3] = quat_to_matrix(torch.tensor(HAND_DOWN, dtype=DT))
    base[:3, 3] = torch.tensor([0.0, 0.0, 0.224], dtype=DT)

    def link(q: Tensor) -> Tensor:
        return base @ robot.forward_kinematics(q, "bhand_f1_outer")

    held = torch.linalg.solve(link(q_robot), torch.cat([point, torch.ones(1, dtype=DT)]))
    eps = 1e-6
    finger = (link(q_robot + eps * v_robot) @ held - link(q_robot - eps * v_robot) @ held)[:3]
    finger = finger / (2 * eps)
    box = twist[:3] + torch.linalg.cross(twist[3:], point - x[:3])
    torch.testing.assert_close(box, finger, rtol=0.0, atol=1e-6)
    assert float(finger.norm()) > 0.01  # the finger does move


def test_bad_step_inputs_name_the_argument() -> None:
    scene = hand_scene(height=1.0)
    model = model_of(scene, torch.zeros(1, scene.num_slots, dtype=torch.long))
    x = state((0.0, 0.0, 0.5))
    zeros = torch.zeros(4, dtype=DT)
    control = RobotControl(q_robot=zeros, v_robot=zeros)
    mode = torch.tensor(0)
    with pytest.raises(ValueError, match="x"):
        model.step(x[:12], mode=mode, control=control)
    with pytest.raises(ValueError, match="x"):
        model.step(torch.cat([x[:3], 2 * x[3:7], x[7:]]), mode=mode, control=control)
    with pytest.raises(ValueError, match="mode"):
        model.step(x, mode=torch.tensor(1), control=control)
    with pytest.raises(ValueError, match="control"):
        model.step(x, mode=mode)
    with pytest.raises(ValueError, match=r"control\.q_robot"):
        model.step(x, mode=mode, control=RobotControl(q_robot=zeros[:3], v_robot=zeros))
    nan = RobotControl(q_robot=zeros, v_robot=torch.full((4,), math.nan, dtype=DT))
    with pytest.raises(ValueError, match=r"control\.v_robot"):
        model.step(x, mode=mode, control=nan)
    with pytest.raises(ValueError, match="readings"):
        model.tactile_log_likelihood(torch.zeros(3), pose=x[:7], control=control)
    with pytest.raises(ValueError, match="pose"):
        model.tactile_log_likelihood(torch.zeros(0, dtype=torch.bool), pose=x[:6], control=control)


def test_projection_lifts_a_box_out_of_the_table() -> None:
    """A box 5 mm into the table, isotropic tangent covariance p: the four bottom corners'
    pseudo-measurements 0 = φ + δz ± b δθx ∓ a δθy (+ e, var σ²) decouple z, whose posterior
    is the closed-form scalar update var = 1 / (1/p + 4/σ²), δz = var · 4 · 5 mm / σ²; the
    orientation and twist keep their means."""
    scene = hand_scene(height=1.0)
    model = model_of(scene, torch.zeros(1, scene.num_slots, dtype=torch.long))
    depth, p, sigma = 0.005, 1e-4, 1e-3
    x = state((0.01, -0.02, HALF[2] - depth), (0.1, 0.0, 0.0, 0.0, 0.0, 0.2))
    belief = RBPF(model, 2).init(Gaussian(x, p * torch.eye(12, dtype=DT)))
    zeros = torch.zeros(4, dtype=DT)
    control = RobotControl(q_robot=zeros, v_robot=zeros)
    projected = project_out_of_contact(belief, scene, gap_sigma=sigma, control=control)
    var = 1.0 / (1.0 / p + 4.0 / sigma**2)
    lifted = x.clone()
    lifted[2] += var * 4.0 * depth / sigma**2
    for i in range(2):
        torch.testing.assert_close(projected.gaussians.mean[i], lifted, rtol=0.0, atol=1e-12)
        torch.testing.assert_close(
            projected.gaussians.cov[i, 2, 2], torch.tensor(var, dtype=DT), rtol=1e-9, atol=0.0
        )
    # Nothing penetrates: the belief comes back unchanged.
    above = RBPF(model, 2).init(Gaussian(state((0.0, 0.0, 0.2)), p * torch.eye(12, dtype=DT)))
    assert project_out_of_contact(above, scene, gap_sigma=sigma, control=control) is above


def test_from_rollout_counts_the_visited_modes() -> None:
    """Boxes dropped onto the table: the table is the distinct mode vectors the simulator
    visited (counted here with a Python set), the first-mode distribution and the
    transitions their smoothed frequencies."""
    scene = hand_scene(height=0.6)
    simulator = Simulator(scene)
    q = torch.tensor(
        [
            [[0.0, 0.0, HALF[2] + 0.002, 1.0, 0.0, 0.0, 0.0]],
            [[0.1, 0.0, HALF[2], 1.0, 0.0, 0.0, 0.0]],
        ],
        dtype=DT,
    )
    v = torch.tensor([[[0.0, 0.0, 0.0, 0.0, 0.0, 0.0]], [[0.3, 0.0, 0.0, 0.0, 0.0, 0.0]]], dtype=DT)
    start = simulator.initial_state(q=q, v=v, q_robot=torch.zeros(2, 4, dtype=DT))
    rollout = simulator.rollout(start, steps=6)
    seen = {tuple(m.tolist()) for m in rollout.mode.reshape(-1, scene.num_slots)}
    smoothing = 0.1
    model = SpatialContactModel.from_rollout(
        scene,
        rollout,
        Q=1e-8 * torch.eye(12, dtype=DT),
        R=1e-4 * torch.eye(6, dtype=DT),
        smoothing=smoothing,
    )
    assert {tuple(m.tolist()) for m in model.modes} == seen
    assert model.num_modes == len(seen) >= 2
    K = model.num_modes
    rows = {tuple(m.tolist()): k for k, m in enumerate(model.modes)}
    first = [rows[tuple(m.tolist())] for m in rollout.mode[0]]
    expected = torch.full((K,), smoothing, dtype=DT)
    for k in first:
        expected[k] += 1
    torch.testing.assert_close(model.initial, expected / expected.sum(), rtol=1e-12, atol=0.0)
    counts = torch.full((K, K), smoothing, dtype=DT)
    for b in range(2):
        path = [rows[tuple(m.tolist())] for m in rollout.mode[:, b]]
        for i, j in itertools.pairwise(path):
            counts[i, j] += 1
    torch.testing.assert_close(
        model.transition, counts / counts.sum(-1, keepdim=True), rtol=1e-12, atol=0.0
    )


def test_bad_filter_inputs_name_the_argument() -> None:
    """The RBPF on SE(3): a prior with an ambient (13, 13) covariance, a camera pose of six
    numbers, a mask over the seven ambient components."""
    scene = hand_scene(height=1.0)
    model = model_of(scene, torch.zeros(1, scene.num_slots, dtype=torch.long))
    rbpf = RBPF(model, 2)
    x = state((0.0, 0.0, 0.5))
    with pytest.raises(ValueError, match="prior"):
        rbpf.init(Gaussian(x, torch.eye(13, dtype=DT)))
    belief = rbpf.init(Gaussian(x, 1e-4 * torch.eye(12, dtype=DT)))
    zeros = torch.zeros(4, dtype=DT)
    control = RobotControl(q_robot=zeros, v_robot=zeros)
    with pytest.raises(ValueError, match="y"):
        rbpf.step(belief, x[:6], control=control)
    with pytest.raises(ValueError, match="mask"):
        rbpf.step(belief, x[:7], control=control, mask=torch.ones(7, dtype=torch.bool))


def test_projection_sets_a_box_on_the_table_its_mode_touches() -> None:
    """The same closed form from above: a box 5 mm over the table in a mode whose four bottom
    corners touch is set down (the same update with gap +5 mm); in a mode where the table
    does not touch, and without the mode table, it stays where it is."""
    scene = hand_scene(height=1.0)
    touching = torch.zeros(2, scene.num_slots, dtype=torch.long)
    touching[0, :4] = 1  # mode 0: the bottom corners stick; mode 1: nothing touches
    model = model_of(scene, touching)
    height, p, sigma = 0.005, 1e-4, 1e-3
    x = state((0.01, -0.02, HALF[2] + height))  # at rest: the twist's rows read zero
    belief = RBPF(model, 2).init(Gaussian(x, p * torch.eye(12, dtype=DT)))
    belief = dataclasses.replace(belief, modes=torch.tensor([0, 1]))
    zeros = torch.zeros(4, dtype=DT)
    control = RobotControl(q_robot=zeros, v_robot=zeros)
    projected = project_out_of_contact(
        belief, scene, gap_sigma=sigma, control=control, mode_table=touching
    )
    var = 1.0 / (1.0 / p + 4.0 / sigma**2)
    lowered = x.clone()
    lowered[2] -= var * 4.0 * height / sigma**2
    torch.testing.assert_close(projected.gaussians.mean[0], lowered, rtol=0.0, atol=1e-12)
    torch.testing.assert_close(projected.gaussians.mean[1], x, rtol=0.0, atol=1e-15)
    unmoved = project_out_of_contact(belief, scene, gap_sigma=sigma, control=control)
    assert unmoved is belief
    with pytest.raises(ValueError, match="mode_table"):
        project_out_of_contact(
            belief, scene, gap_sigma=sigma, control=control, mode_table=touching[:, :3]
        )


def test_projection_sets_the_box_on_the_corners_its_resolved_mode_touches() -> None:
    """A table of slot-group states names all eight corners of the box-table group;
    ``slot_modes`` at a box 5 mm over the table resolves it to the four bottom corners (the
    top ones are 6.5 cm up), and the projection with that per-batch table lowers the box as
    the closed form of the test above (four pseudo-measurements of the gap +5 mm)."""
    scene = hand_scene(height=1.0)
    table = next(g for g in scene.slot_groups)
    sticking = torch.zeros(1, scene.num_slots, dtype=torch.long)
    sticking[0, table.start : table.start + table.count] = 1
    model = model_of(
        scene, sticking, resolve_slots=True, inconsistency_penalty=math.inf, consistency_gap=0.01
    )
    height, p, sigma = 0.005, 1e-4, 1e-3
    x = state((0.01, -0.02, HALF[2] + height))
    zeros = torch.zeros(4, dtype=DT)
    control = RobotControl(q_robot=zeros, v_robot=zeros)
    resolved = model.slot_modes(x[None], control=control)  # (1, K, S)
    bottom = torch.zeros(scene.num_slots, dtype=torch.long)
    bottom[table.start : table.start + 4] = 1  # the box's bottom corners come first
    assert (resolved[0, 0] == bottom).all()  # integers: exact
    belief = RBPF(model, 1).init(Gaussian(x[None], p * torch.eye(12, dtype=DT)[None]))
    projected = project_out_of_contact(
        belief, scene, gap_sigma=sigma, control=control, mode_table=resolved
    )
    var = 1.0 / (1.0 / p + 4.0 / sigma**2)
    lowered = x.clone()
    lowered[2] -= var * 4.0 * height / sigma**2
    torch.testing.assert_close(projected.gaussians.mean[0, 0], lowered, rtol=0.0, atol=1e-12)


def test_projection_stops_the_twist_its_mode_forbids() -> None:
    """A box resting on the table with a twist (v, ω) and a diagonal covariance: in a mode
    whose four bottom corners stick, the projection brings the twist to zero (the only twist
    under which four corners on a plane neither move nor slip); in one where they slide, only
    the normal rates are constrained (vz + (ω × r)_z = 0 at four corners: vz = ωx = ωy = 0)
    and, the covariance being diagonal, vx, vy and ωz stay. Tolerances: with pseudo-measurement
    std s = σ/h = 1e-6 m/s, prior variance p = 0.01 and lever arms r of a few centimetres, a
    constrained component keeps about |ω| s² / (p r²) ≈ 3e-8 of its value."""
    scene = hand_scene(height=1.0)
    modes = torch.zeros(2, scene.num_slots, dtype=torch.long)
    modes[0, :4] = 1  # sticking
    modes[1, :4] = 2  # sliding (along the first friction direction)
    model = model_of(scene, modes)
    twist = (0.1, -0.05, 0.02, 0.3, -0.2, 0.4)
    x = state((0.0, 0.0, HALF[2]), twist)
    belief = RBPF(model, 2).init(Gaussian(x, 0.01 * torch.eye(12, dtype=DT)))
    belief = dataclasses.replace(belief, modes=torch.tensor([0, 1]))
    zeros = torch.zeros(4, dtype=DT)
    control = RobotControl(q_robot=zeros, v_robot=zeros)
    sigma = 1e-6 * scene.h
    projected = project_out_of_contact(
        belief, scene, gap_sigma=sigma, control=control, mode_table=modes
    )
    mean = projected.gaussians.mean
    torch.testing.assert_close(mean[0, 7:], torch.zeros(6, dtype=DT), rtol=0.0, atol=1e-6)
    kept = torch.tensor(twist, dtype=DT)[[0, 1, 5]]
    torch.testing.assert_close(mean[1, [7, 8, 12]], kept, rtol=0.0, atol=1e-12)
    torch.testing.assert_close(mean[1, [9, 10, 11]], torch.zeros(3, dtype=DT), rtol=0.0, atol=1e-6)
    torch.testing.assert_close(mean[:, :7], x[:7].expand(2, 7), rtol=0.0, atol=1e-12)


def test_gaps_within_the_tolerance_are_closed() -> None:
    """A box 2 mm over the table, its bottom corners sticking: with the gap closed the step
    is the one from 2 mm lower (the table's rows do not change under a vertical shift), so
    the box stays 2 mm up at rest instead of dropping 2 mm in one step, and the Jacobian is
    the lowered state's; without closing (gap 0) it is step()'s, which drops."""
    scene = hand_scene(height=1.0)
    modes = torch.zeros(1, scene.num_slots, dtype=torch.long)
    modes[0, :4] = 1
    lift = 0.002
    x = state((0.01, -0.02, HALF[2] + lift))
    lowered = state((0.01, -0.02, HALF[2]))
    zeros = torch.zeros(4, dtype=DT)
    control = RobotControl(q_robot=zeros, v_robot=zeros)
    closing = model_of(scene, modes, consistency_gap=0.003)
    F, f, converged = closing.linearize(x, control=control)
    F_low, f_low, _ = closing.linearize(lowered, control=control)
    assert bool(converged.all())
    shifted = f_low.clone()
    shifted[..., 2] += lift
    torch.testing.assert_close(f, shifted, rtol=0.0, atol=1e-12)
    torch.testing.assert_close(F, F_low, rtol=0.0, atol=1e-9 * float(F_low.abs().max()))
    assert float(f[0, 2]) == pytest.approx(HALF[2] + lift, abs=1e-9)  # stays up, at rest
    open_model = model_of(scene, modes, consistency_gap=0.0)
    _, f_open, _ = open_model.linearize(x, control=control)
    torch.testing.assert_close(
        f_open[0], open_model.step(x, mode=torch.tensor(0), control=control), rtol=0, atol=1e-10
    )
    assert float(f_open[0, 2]) == pytest.approx(HALF[2], abs=1e-9)  # the gap closes in a step


@pytest.mark.parametrize(
    ("gap", "expected"),
    [(0.01, [0.0, -math.inf]), (0.0002, [-math.inf, 0.0]), (0.0, [-math.inf, 0.0])],
)
def test_penetrations_within_the_gap_do_not_rule_out_separated_slots(
    gap: float, expected: list[float]
) -> None:
    """A box rising at 0.15 m/s whose mean lies 6 mm inside the table (the scene's
    ``recovery_speed`` of 0.1 m/s caps the penetration the problem sees at 1 mm), two modes:
    free flight (every slot separated), whose step leaves at v⁺ = 0.15 − g h = 0.052 m/s,
    and the bottom corners sticking. With the penetration taken as touching (gap 10 mm),
    free flight is consistent (its corners' gap rate v⁺ > 0) and its step is the closed-form
    flight, while sticking corners would pull the box down (pn < 0). With a gap of 0.2 mm
    the corners stay 0.8 mm inside: free flight would penetrate further (gap rate
    v⁺ − 0.0008 / h < 0) and is ruled out, and the sticking corners push the box out
    (pn > 0); likewise without the gap."""
    scene = hand_scene(height=1.0)
    modes = torch.zeros(2, scene.num_slots, dtype=torch.long)
    modes[1, :4] = 1
    rise, depth = 0.15, 0.006
    x = state((0.01, -0.02, HALF[2] - depth), (0.0, 0.0, rise, 0.0, 0.0, 0.0))
    zeros = torch.zeros(4, dtype=DT)
    control = RobotControl(q_robot=zeros, v_robot=zeros)
    model = model_of(scene, modes, inconsistency_penalty=math.inf, consistency_gap=gap)
    _, f, converged = model.linearize(x, control=control)
    assert converged.tolist() == [True, True]
    v_up = rise - 9.81 * H
    assert float(f[0, 9]) == pytest.approx(v_up, abs=1e-12)  # free flight: closed form
    assert float(f[0, 2]) == pytest.approx(HALF[2] - depth + H * v_up, abs=1e-12)
    belief = RBPF(model, 2).init(Gaussian(x, 1e-8 * torch.eye(12, dtype=DT)))
    weights = model.mode_dynamics(belief, control).mode_log_weight
    assert weights is not None
    assert weights.tolist() == expected  # 0 and -inf are exact


def test_group_states_take_the_largest_state_of_each_group() -> None:
    """Hand-written modes: the table group (the box's corners) with one corner sticking and
    one sliding along direction 3 is sliding (code 2) on every corner; a finger link group
    with one sticking slot is sticking on all its slots; untouched groups stay 0."""
    scene = hand_scene(height=1.0)
    table = next(g for g in scene.slot_groups)
    link = scene.robot_slot_groups[2]
    mode = torch.zeros(scene.num_slots, dtype=torch.long)
    mode[table.start] = 1
    mode[table.start + 1] = 2 + 3
    mode[link.start] = 1
    expected = torch.zeros_like(mode)
    expected[table.start : table.start + table.count] = 2
    expected[link.start : link.start + link.count] = 1
    assert (group_states(scene, mode[None]) == expected).all()  # integers: exact


def test_resolved_slots_reproduce_the_simulators_step() -> None:
    """A box sliding at 0.3 m/s along +x on the table, its mode given as group states only
    (the table group sliding, every one of its 8 corner slots coded 2): at the state the
    resolution keeps the 4 bottom corners (the top ones are 6 cm up), turns their friction
    against the slip, and the step equals the simulator's exact (Lemke) step; the same
    state with the table group sticking is inconsistent (the friction would leave the cone)."""
    scene = hand_scene(height=1.0)
    x = state((0.0, 0.0, HALF[2]), (0.3, 0.0, 0.0, 0.0, 0.0, 0.0))
    zeros = torch.zeros(4, dtype=DT)
    control = RobotControl(q_robot=zeros, v_robot=zeros)
    table = next(g for g in scene.slot_groups)
    sliding = torch.zeros(scene.num_slots, dtype=torch.long)
    sliding[table.start : table.start + table.count] = 2
    sticking = torch.where(sliding >= 1, 1, sliding)
    model = model_of(
        scene,
        torch.stack([sliding, sticking]),
        resolve_slots=True,
        inconsistency_penalty=math.inf,
        consistency_gap=0.003,
    )
    _, f, converged = model.linearize(x, control=control)
    assert converged.tolist() == [True, True]
    simulator = Simulator(scene)
    start = simulator.initial_state(q=x[None, None, :7], v=x[None, None, 7:], q_robot=zeros[None])
    result = simulator.step(start)
    exact = torch.cat([result.state.q[0, 0], result.state.v[0, 0]])
    torch.testing.assert_close(f[0], exact, rtol=0.0, atol=1e-9)
    belief = RBPF(model, 2).init(Gaussian(x, 1e-8 * torch.eye(12, dtype=DT)))
    weights = model.mode_dynamics(belief, control).mode_log_weight
    assert weights is not None
    assert float(weights[0]) == 0.0
    assert float(weights[1]) == -math.inf


def test_no_consistent_mode_leaves_the_solved_ones_to_the_evidence() -> None:
    """With the inconsistent modes ruled out (penalty inf), an entry with no consistent mode
    keeps its solved modes (those nearly consistent, if any are) at log-weight 0; unsolved
    ones stay -inf, and an entry with a consistent mode is gated as usual."""
    consistent = torch.tensor([[False, False, False], [True, False, False]])
    converged = torch.tensor([[True, False, True], [True, True, False]])
    weight = gate_log_weight(consistent, penalty=math.inf, dtype=DT, converged=converged)
    inf = math.inf
    expected = torch.tensor([[0.0, -inf, 0.0], [0.0, -inf, -inf]], dtype=DT)
    assert (weight == expected).all()  # 0 and ±inf are exact
    # with a looser verdict, only the stranded entry's nearly consistent solved modes stay
    nearly = torch.tensor([[False, True, True], [False, False, False]])
    weight = gate_log_weight(
        consistent, penalty=math.inf, dtype=DT, converged=converged, nearly=nearly
    )
    expected = torch.tensor([[-inf, -inf, 0.0], [0.0, -inf, -inf]], dtype=DT)
    assert (weight == expected).all()  # 0 and ±inf are exact
    finite = gate_log_weight(consistent, penalty=5.0, dtype=DT, converged=converged)
    assert (finite == torch.tensor([[-5.0, -inf, -5.0], [0.0, -5.0, -inf]], dtype=DT)).all()


@pytest.mark.slow  # compiles the BarrettHand's assembly: minutes on a CPU
def test_compiled_linearization_matches_finite_differences_and_the_eager_one() -> None:
    """``compiled=True`` (the contact assembly of the tangent replicas as a compiled graph
    and its compiled backward) on the BarrettHand finger closing on a tilted box: the
    Jacobians against finite differences as for the eager model, and the steps, Jacobians and
    gate against the eager model's. The compiled kernels sum in another order: the problems'
    fields agree to rounding (1e-15 relative), which the mode solves amplify by their
    regularised condition (~1e6, the Tikhonov shift √eps of the diagonal): 1e-9 of the
    largest entry."""
    scene, x, q_robot, v_robot, modes, outer = finger_on_a_tilted_box()
    modes[2, outer : outer + 2] = 1  # contradicts itself: not solved
    control = RobotControl(q_robot=q_robot, v_robot=v_robot)
    # No gap closed: the linearization is that of step() (see assert_jacobian_matches).
    compiled = model_of(scene, modes, compiled=True, consistency_gap=0.0)
    eager = model_of(scene, modes, consistency_gap=0.0)
    F, f, converged = compiled.linearize(x, control=control)
    F_eager, f_eager, converged_eager = eager.linearize(x, control=control)
    assert (converged == converged_eager).all()  # bools: exact
    assert converged.tolist() == [True, True, False]
    for k in range(2):  # the tolerance of assert_jacobian_matches
        expected = finite_difference_jacobian(eager, x, k, control)
        scale = float(expected.abs().max())
        torch.testing.assert_close(F[k], expected, rtol=0.0, atol=1e-7 * scale)
    torch.testing.assert_close(F, F_eager, rtol=0.0, atol=1e-9 * float(F_eager.abs().max()))
    torch.testing.assert_close(f, f_eager, rtol=0.0, atol=1e-12)
    belief = RBPF(eager, 8, proposal="all_modes").init(Gaussian(x, 1e-6 * torch.eye(12, dtype=DT)))
    dynamics = compiled.mode_dynamics(belief, control)
    reference = eager.mode_dynamics(belief, control)
    assert (dynamics.mode_log_weight == reference.mode_log_weight).all()  # 0 or -inf: exact
    for name in ("F", "c", "chart"):
        value, expected = getattr(dynamics, name), getattr(reference, name)
        scale = max(float(expected.abs().max()), 1.0)
        torch.testing.assert_close(value, expected, rtol=0.0, atol=1e-9 * scale)


def test_compiled_must_be_a_bool() -> None:
    scene = finger_scene()
    modes = torch.zeros(1, scene.num_slots, dtype=torch.long)
    with pytest.raises(ValueError, match="compiled"):
        model_of(scene, modes, compiled=1)


def barrett_box_resting_against_finger_3() -> tuple[SpatialContactModel, Tensor, RobotControl]:
    """A state of the Barrett box grasp (trial 1, step 46, seed 0): the box at rest on the
    table, finger 3 closing on it at 0.51 rad/s while fingers 1 and 2 are still away; the
    model's one mode is the simulator's slot-group states there (the table sliding, finger
    3's outer link sticking)."""
    settings = BarrettBoxGrasp()
    scene = box_filter_scene(settings, (0.031450, 0.027911, 0.039465))
    x = torch.tensor(
        [0.602438, -0.017674, 0.039465, 0.9991033, 0.0, 0.0, -0.0423402, *([0.0] * 6)],
        dtype=DT,
    )
    x[3:7] = x[3:7] / x[3:7].norm()
    arm = [0.435822, 0.689164, -0.815362, 1.667488, 0.567571, 1.037421, 2.577444]
    q_robot = torch.tensor([*arm, 0.0, 1.075, 1.075, 1.075], dtype=DT)
    v_robot = torch.tensor([*([0.0] * 7), 0.0, 1.5, 1.5, 0.508687], dtype=DT)
    simulated = torch.zeros(scene.num_slots, dtype=torch.long)
    simulated[2:4] = 8  # two corners sliding
    simulated[-1] = 1  # finger 3's outer link
    model = model_of(
        scene,
        group_states(scene, simulated[None]),
        resolve_slots=True,
        inconsistency_penalty=5.0,
        consistency_gap=0.01,
    )
    return model, x, RobotControl(q_robot=q_robot, v_robot=v_robot)


def test_exact_resolution_gives_the_physics_mode_at_the_point() -> None:
    """At a grasp state where the resolution rules leave the simulator's mode inconsistent
    (-5, the penalty), the exact resolution takes the slots of Lemke's solution there: the
    mode passes the gate (0), and its step is the simulator's (no gap closed, no penetration
    at the state: the same problem; 1e-9 of the unit velocities)."""
    model, x, control = barrett_box_resting_against_finger_3()
    belief = RBPF(model, 1).init(Gaussian(x, 1e-10 * torch.eye(12, dtype=DT)))
    rules = dataclasses.replace(model, exact_resolution=False)
    rules_weight = rules.mode_dynamics(belief, control).mode_log_weight
    exact_weight = model.mode_dynamics(belief, control).mode_log_weight
    assert rules_weight is not None
    assert exact_weight is not None
    assert float(rules_weight[0]) == -5.0  # the gate's constants: exact
    assert float(exact_weight[0]) == 0.0
    # the step of the resolved mode, gaps as they are, against the simulator's step
    _, f, converged = dataclasses.replace(model, consistency_gap=0.0).linearize(x, control=control)
    assert bool(converged[0])
    simulator = Simulator(model.scene)
    start = simulator.initial_state(
        q=x[None, None, :7], v=x[None, None, 7:], q_robot=control.q_robot[None]
    )
    result = simulator.step(start, joint_command=control.v_robot[None])
    exact = torch.cat([result.state.q[0, 0], result.state.v[0, 0]])
    torch.testing.assert_close(f[0], exact, rtol=0.0, atol=1e-9)
    slots = model.slot_modes(x, control=control)[0]
    assert ((slots >= 1) == (result.mode[0] >= 1)).all()  # integers: exact


def test_particles_whose_gaps_contradict_a_mode_are_penalized() -> None:
    """Mode 0 closes the four bottom corners on the table, mode 1 separates them. The
    closed-form corner gaps of each particle (z + (R c)_z over the corners c = (±a, ±b, -h))
    decide the verdict: a mode is contradicted where a corner it closes is more than
    ``consistency_gap`` (3 mm) above the table or a corner it separates is more than 3 mm
    inside. The model judges from the belief's mean (the resting box, which carries the
    weight) to first order in each particle's offset, which agrees away from the threshold."""
    scene = hand_scene(height=1.0)
    modes = torch.zeros(2, scene.num_slots, dtype=torch.long)
    modes[0, :4] = 1
    penalty = 7.0
    model = model_of(scene, modes, particle_penalty=penalty)
    a, b, c = HALF
    tilt = quat_exp(torch.tensor([0.4, 0.0, 0.0], dtype=DT))
    particles = torch.stack(
        [
            state((0.0, 0.0, c)),  # resting
            state((0.0, 0.0, c + 0.02)),  # 2 cm up
            state((0.0, 0.0, c - 0.02)),  # 2 cm into the table
            torch.cat([state((0.0, 0.0, c))[:3], tilt, torch.zeros(6, dtype=DT)]),  # tipped
            state((0.0, 0.0, c + 0.002)),  # within the tolerance
        ]
    )
    N = particles.shape[0]
    belief = RBPF(model, N).init(Gaussian(particles[0], 1e-6 * torch.eye(12, dtype=DT)))
    g = belief.gaussians
    belief = dataclasses.replace(
        belief,
        gaussians=Gaussian(particles, g.cov),
        log_weights=torch.tensor([0.0] + [-40.0] * (N - 1), dtype=DT),
    )
    zeros = torch.zeros(4, dtype=DT)
    dynamics = model.mode_dynamics(belief, RobotControl(q_robot=zeros, v_robot=zeros))
    corners = torch.tensor([[sx * a, sy * b, -c] for sx in (-1, 1) for sy in (-1, 1)], dtype=DT)
    gaps = (
        particles[:, None, 2]
        + torch.einsum("nij,cj->nci", quat_to_matrix(particles[:, 3:7]), corners)[..., 2]
    )  # (N, 4)
    gap = model.consistency_gap
    expected = torch.stack([(gaps > gap).any(-1), (gaps < -gap).any(-1)], dim=-1)  # (N, 2)
    verdicts = [[False, False], [True, False], [False, True], [True, True], [False, False]]
    assert expected.tolist() == verdicts  # both verdicts occur
    assert dynamics.particle_log_weight is not None
    assert (dynamics.particle_log_weight == -penalty * expected.to(DT)).all()  # 0 or -7
    off = model_of(scene, modes).mode_dynamics(belief, RobotControl(q_robot=zeros, v_robot=zeros))
    assert off.particle_log_weight is None


def test_a_step_faster_than_max_speed_change_is_not_solved() -> None:
    """A box in free flight, spinning about its vertical principal axis (no gyroscopic
    torque): its step changes the velocity by g h downwards and nothing else, so the fastest
    point's velocity changes by exactly g h (closed form). A bound just below rules the
    step out, one just above keeps it."""
    scene = hand_scene(height=1.0)
    modes = torch.zeros(1, scene.num_slots, dtype=torch.long)
    x = state((0.0, 0.0, 0.5), (0.1, 0.0, 0.0, 0.0, 0.0, 4.0))
    zeros = torch.zeros(4, dtype=DT)
    control = RobotControl(q_robot=zeros, v_robot=zeros)
    g_h = 9.81 * H
    verdicts = []
    for bound in (0.99 * g_h, 1.01 * g_h, math.inf):
        model = model_of(scene, modes, max_speed_change=bound)
        _, f, solved = model.linearize(x, control=control)
        verdicts.append(bool(solved[0]))
        if solved[0]:
            change = f[0, 7:] - x[7:]
            expected = torch.tensor([0.0, 0.0, -g_h, 0.0, 0.0, 0.0], dtype=DT)
            torch.testing.assert_close(change, expected, rtol=0.0, atol=1e-12)
    assert verdicts == [False, True, True]
    with pytest.raises(ValueError, match="max_speed_change"):
        model_of(scene, modes, max_speed_change=0.0)
