"""The peg belief model on the contact physics, against independent references: the LCP
simulator's step, the closed-form motion of a held peg, an enumeration of the transition rows,
and the Kalman filter of a free-falling peg."""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from torchcontact.envs import (
    HELD_FREE,
    NUM_CONTACT_CLASSES,
    GraphClassTransition,
    PegControl,
    PegInHoleConfig,
    PegInHoleTask,
    PegPhysicsModel,
    filter_scene,
    slot_map,
)
from torchcontact.envs._belief_model import compose
from torchcontact.envs._physics_model import _rule_out_unstable, grasp_prior
from torchcontact.filters import (
    RBPF,
    Gaussian,
    KinematicControl,
    ModeDynamics,
    PlanarContactModel,
    kf_predict,
    kf_update,
)
from torchcontact.sim import Simulator
from torchcontact.states import ManipulationGraph

F64 = torch.float64
TASK = PegInHoleTask(PegInHoleConfig())
A = 7


def _graph(rows: torch.Tensor | None = None) -> GraphClassTransition:
    """A graph transition: ``rows (M, A, C)`` for states ``0..M-1``, the rest uniform."""
    C = NUM_CONTACT_CLASSES
    uniform = torch.full((1, A, C), 1.0 / C, dtype=F64)
    rows = uniform[:0] if rows is None else rows
    M = rows.shape[0]
    state_row = torch.full((TASK.states.num_states,), M, dtype=torch.long)
    state_row[:M] = torch.arange(M)
    return GraphClassTransition(
        class_transition=torch.full((A, C, C), 1.0 / C, dtype=F64),
        state_transition=torch.cat([rows, uniform]),
        state_row=state_row,
    )


def _model(
    table: torch.Tensor,
    mode_class: list[int],
    within: list[float],
    *,
    graph: GraphClassTransition | None = None,
    noise: float = 1e-4,
) -> PegPhysicsModel:
    K = table.shape[0]
    contact = PlanarContactModel(
        scene=filter_scene(TASK),
        modes=table,
        Q=noise**2 * torch.eye(6, dtype=F64),
        R=1e-4 * torch.eye(3, dtype=F64),
        transition=torch.full((A, K, K), 1.0 / K, dtype=F64),
        initial=torch.full((K,), 1.0 / K, dtype=F64),
        inconsistency_penalty=0.0,
    )
    return PegPhysicsModel(
        task=TASK,
        contact=contact,
        mode_class=torch.tensor(mode_class),
        within_class=torch.tensor(within, dtype=F64),
        graph=_graph() if graph is None else graph,
        grasp_prior=grasp_prior(TASK),
        twist_prior=1e-4 * torch.eye(3, dtype=F64),
    )


def _placeholder() -> PegPhysicsModel:
    S = filter_scene(TASK).num_slots
    return _model(torch.zeros(1, S, dtype=torch.long), [0], [1.0])


def test_filter_scene_keeps_the_peg_slots_of_the_task_scene() -> None:
    scene = filter_scene(TASK)
    assert scene.h == pytest.approx(TASK.config.substeps * TASK.config.h, rel=1e-12)
    index = slot_map(TASK.scene, scene)
    # Every filter slot names the same bodies in the task's scene: the peg and one partner.
    receivers = {
        s: (TASK.scene.bodies[g.receiver].name, TASK.scene.bodies[g.other].name)
        for g in TASK.scene.slot_groups
        for s in range(g.start, g.start + g.count)
    }
    names = [receivers[int(i)] for i in index]
    assert all("peg" in pair for pair in names)
    assert len(set(index.tolist())) == scene.num_slots
    peg_slots = sum(1 for pair in receivers.values() if "peg" in pair)
    assert scene.num_slots == peg_slots


def _setup(
    grasp: tuple[float, ...], motion: tuple[float, ...], height: float
) -> tuple[Tensor, Tensor, Tensor, Tensor, KinematicControl]:
    """Gripper poses before and after, the peg's pose and state, the fingers on the peg."""
    before = torch.tensor([[0.15, height, 0.0]], dtype=F64)
    after = before + torch.tensor([motion], dtype=F64)
    peg = compose(before, torch.tensor([grasp], dtype=F64))
    fingers = _placeholder().finger_control(before, after, peg)
    x = torch.cat([peg, torch.zeros(1, 3, dtype=F64)], -1)
    return before, after, peg, x, fingers


def _linearized(
    model: PegPhysicsModel, x: Tensor, before: Tensor, after: Tensor
) -> tuple[Tensor, Tensor]:
    """``F (K, 6, 6)`` and ``c (K, 6)`` of ``mode_dynamics`` at a belief whose mean is ``x``."""
    belief = RBPF(model, 4).init(Gaussian(x[0], 1e-8 * torch.eye(6, dtype=F64)), (1,))
    control = PegControl(
        state_ids=torch.zeros(1, 4, dtype=torch.long),
        gripper_after=after,
        actions=torch.zeros(1, dtype=torch.long),
        gripper_before=before,
    )
    dynamics = model.mode_dynamics(belief, control)
    return dynamics.F[0], dynamics.c[0]


def test_the_mode_step_equals_the_simulator_step_at_its_mode() -> None:
    """The LCP simulator (Lemke) steps the filter's scene with the peg's bottom on the right
    block and the fingers lowered along it; the model's step at the mode the simulator found,
    and its linearization at that point, give the simulator's next state."""
    c = TASK.config
    grasp = (0.0, -0.04, 0.0)
    before, after, peg, x, fingers = _setup(
        grasp, (0.0, -0.002, 0.0), c.hole_depth + c.peg_height / 2 - grasp[1]
    )
    simulator = Simulator(filter_scene(TASK))
    result = simulator.step(
        simulator.initial_state(q=peg[:, None], q_kinematic=fingers.q), fingers.v
    )
    truth = torch.cat([result.state.q[:, 0], result.state.v[:, 0]], -1)
    assert bool(result.mode.ne(0).any()), "the scenario must have contacts"
    table = torch.cat([torch.zeros_like(result.mode), result.mode])
    model = _model(table, [0, 12], [1.0, 1.0])
    predicted = model.contact.step(x, mode=torch.tensor([1]), control=fingers)
    torch.testing.assert_close(predicted, truth, rtol=0, atol=1e-8)
    F, c_ = _linearized(model, x, before, after)
    torch.testing.assert_close(F[1] @ x[0] + c_[1], truth[0], rtol=0, atol=1e-8)


@pytest.mark.parametrize(
    ("grasp", "motion"),
    [((0.0, -0.04, 0.0), (0.0, 0.002, 0.0)), ((0.001, -0.035, 0.03), (0.002, -0.002, 0.02))],
)
def test_sticking_pads_carry_the_peg_rigidly_with_the_gripper(
    grasp: tuple[float, ...], motion: tuple[float, ...]
) -> None:
    """With the pads sticking, the peg's twist is the gripper frame's rigid twist at the peg:
    ``v = v_g + ω × (p − g)``, ``ω = ω_g``, and its pose after the step ``q + h v``
    (closed-form kinematics; gravity is carried by the pads)."""
    before, after, _, x, fingers = _setup(grasp, motion, 0.3)
    scene = filter_scene(TASK)
    state = Simulator(scene).initial_state(q=x[:, None, :3], q_kinematic=fingers.q)
    result = Simulator(scene).step(state, fingers.v)
    pads = torch.zeros(scene.num_slots, dtype=torch.bool)
    for group in scene.slot_groups:
        if scene.bodies[group.receiver].name.startswith("finger") or scene.bodies[
            group.other
        ].name.startswith("finger"):
            pads[group.start : group.start + group.count] = True
    touching = pads & (result.geometry.phi[0].abs() < 1e-9)
    assert int(touching.sum()) >= 2, "the pads must touch the peg"
    model = _model(touching.long()[None], [HELD_FREE], [1.0])
    h = scene.h
    v_g = (after - before) / h
    arm = x[:, :2] - before[:, :2]
    v = torch.cat(
        [v_g[:, :2] + v_g[:, 2:] * torch.stack([-arm[:, 1], arm[:, 0]], -1), v_g[:, 2:]], -1
    )
    expected = torch.cat([x[:, :3] + h * v, v], -1)
    predicted = model.contact.step(x, mode=torch.tensor([0]), control=fingers)
    torch.testing.assert_close(predicted, expected, rtol=0, atol=1e-9)
    F, c = _linearized(model, x, before, after)
    torch.testing.assert_close(F[0] @ x[0] + c[0], expected[0], rtol=0, atol=1e-9)


def test_transition_rows_are_the_graph_class_rows_spread_over_each_class_modes() -> None:
    generator = torch.Generator().manual_seed(3)
    S = filter_scene(TASK).num_slots
    table = torch.zeros(4, S, dtype=torch.long)
    table[1:, -1] = torch.tensor([1, 2, 3])  # distinct rows
    classes, within = [HELD_FREE, HELD_FREE, 16, 12], [0.75, 0.25, 1.0, 1.0]
    M = 3
    rows = torch.distributions.Dirichlet(torch.ones(NUM_CONTACT_CLASSES, dtype=F64)).sample((M, A))
    model = _model(table, classes, within, graph=_graph(rows))
    x = torch.zeros(2, 6, dtype=F64)
    x[:, 1] = 0.3
    belief = RBPF(model, 5).init(Gaussian(x, 1e-6 * torch.eye(6, dtype=F64).expand(2, 6, 6)))
    ids = torch.randint(0, TASK.states.num_states, (2, 5), generator=generator)
    ids[0, :3] = torch.arange(3)  # states with their own rows
    actions = torch.tensor([2, 5])
    gripper = torch.tensor([[0.0, 0.34, 0.0], [0.0, 0.34, 0.0]], dtype=F64)
    control = PegControl(
        state_ids=ids, gripper_after=gripper, actions=actions, gripper_before=gripper
    )
    got = model.mode_dynamics(belief, control).transition_rows
    assert got is not None
    expected = torch.zeros(2, 5, 4, dtype=F64)
    for b in range(2):
        for n in range(5):
            state = int(ids[b, n])
            row = rows[state, int(actions[b])] if state < M else torch.full((24,), 1 / 24)
            weights = [float(row[c]) * w for c, w in zip(classes, within, strict=True)]
            total = sum(weights)
            expected[b, n] = torch.tensor([w / total for w in weights], dtype=F64)
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=0)
    assert bool((got >= 0).all())
    torch.testing.assert_close(got.sum(-1), torch.ones(2, 5, dtype=F64), rtol=0, atol=1e-12)


def test_one_separated_mode_reduces_to_the_kalman_filter_of_a_falling_peg() -> None:
    """One mode, every slot separated: the peg falls freely under gravity, a linear model
    ``q⁺ = q + h v⁺, v⁺ = v + h g``; the RBPF is then one Kalman filter."""
    S = filter_scene(TASK).num_slots
    model = _model(torch.zeros(1, S, dtype=torch.long), [0], [1.0], noise=1e-3)
    h, g = model.contact.scene.h, TASK.config.gravity
    F = torch.eye(6, dtype=F64)
    F[:3, 3:] = h * torch.eye(3, dtype=F64)
    c = torch.tensor([0.0, -(h**2) * g, 0.0, 0.0, -h * g, 0.0], dtype=F64)
    Q, R = model.contact.Q, model.contact.R
    H = torch.eye(3, 6, dtype=F64)
    generator = torch.Generator().manual_seed(0)
    mean = torch.tensor([[0.02, 0.3, 0.01, 0.0, 0.0, 0.0], [-0.05, 0.25, 0.0, 0.1, 0.0, 0.0]])
    prior = Gaussian(mean.to(F64), 1e-5 * torch.eye(6, dtype=F64).expand(2, 6, 6))
    rbpf = RBPF(model, 3)
    belief = rbpf.init(prior)
    reference, evidence = prior, torch.zeros(2, dtype=F64)
    gripper = torch.tensor([[0.02, 0.34, 0.0], [-0.05, 0.29, 0.0]], dtype=F64)
    for step in range(3):
        y = reference.mean[:, :3] + 0.01 * torch.randn(2, 3, generator=generator, dtype=F64)
        control = PegControl(
            state_ids=torch.zeros(2, 3, dtype=torch.long),
            gripper_after=gripper,
            actions=torch.full((2,), step),
            gripper_before=gripper,
        )
        belief = rbpf.step(belief, y, action=torch.full((2,), step), control=control)
        reference = kf_predict(reference, F=F, c=c, Q=Q)
        reference, log_likelihood = kf_update(reference, y, H=H, R=R)
        evidence = evidence + log_likelihood
    for n in range(3):
        torch.testing.assert_close(belief.gaussians.mean[:, n], reference.mean, rtol=0, atol=1e-9)
        torch.testing.assert_close(belief.gaussians.cov[:, n], reference.cov, rtol=0, atol=1e-12)
    torch.testing.assert_close(belief.log_evidence, evidence, rtol=1e-9, atol=1e-9)


def test_fit_builds_modes_of_classes_and_rejects_bad_input() -> None:
    S = TASK.scene.num_slots
    filter_slots = slot_map(TASK.scene, filter_scene(TASK))
    modes = torch.zeros(10, S, dtype=torch.long)
    modes[:6, filter_slots[-1]] = 1  # six held steps, four free-falling ones
    classes = torch.tensor([HELD_FREE] * 6 + [0] * 4)
    graph_rows = _graph()
    model = PegPhysicsModel(
        task=TASK,
        contact=_placeholder().contact,
        mode_class=torch.tensor([0]),
        within_class=torch.ones(1, dtype=F64),
        graph=graph_rows,
        grasp_prior=grasp_prior(TASK),
        twist_prior=torch.eye(3, dtype=F64),
    )
    assert model.num_modes == 1
    graph = ManipulationGraph(A)
    fitted = PegPhysicsModel.fit(modes, classes, graph, task=TASK)
    assert fitted.num_modes == 2
    assert sorted(fitted.mode_class.tolist()) == [0, HELD_FREE]
    torch.testing.assert_close(fitted.within_class, torch.ones(2, dtype=F64))
    # The episode starts held: the initial distribution is on the held mode.
    held = int((fitted.mode_class == HELD_FREE).nonzero())
    assert float(fitted.initial[held]) == pytest.approx(1.0, abs=1e-12)
    with pytest.raises(ValueError, match="slot_modes"):
        PegPhysicsModel.fit(modes[:, :5], classes, graph, task=TASK)
    with pytest.raises(ValueError, match="classes"):
        PegPhysicsModel.fit(modes, classes[:3], graph, task=TASK)
    with pytest.raises(ValueError, match="within_class"):
        _model(torch.zeros(2, filter_slots.numel(), dtype=torch.long), [8, 8], [0.5, 0.6])
    belief = RBPF(model, 2).init(Gaussian(torch.zeros(6, dtype=F64), torch.eye(6, dtype=F64)))
    with pytest.raises(ValueError, match="gripper_before"):
        model.mode_dynamics(
            belief,
            PegControl(
                state_ids=torch.zeros(1, 2, dtype=torch.long),
                gripper_after=torch.zeros(1, 3, dtype=F64),
                actions=torch.zeros(1, dtype=torch.long),
            ),
        )


def test_modes_with_unstable_linearizations_are_ruled_out() -> None:
    """A mode whose Jacobian is not finite or explodes gets log-weight -inf and identity
    dynamics; the others pass unchanged."""
    F = torch.eye(6, dtype=F64).repeat(2, 3, 1, 1)
    c = torch.ones(2, 3, 6, dtype=F64)
    F[0, 1, 0, 0] = math.nan
    F[1, 2, 3, 4] = 1e6
    eye3 = torch.eye(3, dtype=F64)
    dynamics = ModeDynamics(F=F, c=c, Q=eye3, H=eye3, d=c[..., :3], R=eye3)
    out = _rule_out_unstable(dynamics)
    assert out.mode_log_weight is not None
    ruled_out = torch.tensor([[False, True, False], [False, False, True]])
    assert bool((torch.isinf(out.mode_log_weight) == ruled_out).all())
    assert bool((out.mode_log_weight[~ruled_out] == 0).all())  # exact zeros: nothing added
    expected_F = torch.where(ruled_out[..., None, None], torch.eye(6, dtype=F64), F)
    torch.testing.assert_close(out.F, expected_F, rtol=0, atol=1e-15)
    torch.testing.assert_close(out.c, torch.where(ruled_out[..., None], 0.0, c), rtol=0, atol=1e-15)
