"""The simulator end to end through the scene builder, against closed-form physics."""

from __future__ import annotations

import math

import pytest
import torch

from torchcontact.contact import SEPARATED, STICKING, solve
from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import SOLVED_BY_GUESS, Body, Scene, SceneState, Simulator, contact_problem

G, H = 9.81, 0.01
WIDTH, HEIGHT, MASS = 1.0, 0.5, 2.0


def box_on_ground(
    *, mu: float | torch.Tensor = 0.4, angle: float = 0.0, mass=MASS, **bodies
) -> Simulator:
    scene = Scene(
        bodies=(
            Body("ground", HalfPlane.ground(angle=angle), kind="static"),
            Body("box", Polygon.box(WIDTH, HEIGHT), mass=mass),
            *bodies.values(),
        ),
        friction=mu,
        h=H,
    )
    return Simulator(scene)


def pose(x: float, y: float, theta: float, batch: tuple[int, ...] = ()) -> torch.Tensor:
    return torch.tensor([x, y, theta], dtype=torch.float64).expand(*batch, 1, 3).clone()


def energy(sim: Simulator, q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Kinetic + gravitational potential energy of a single-body scene, per batch entry."""
    M = sim.scene.mass_matrix()
    kinetic = 0.5 * (v.flatten(-2) @ M * v.flatten(-2)).sum(-1)
    return kinetic + MASS * G * q[..., 0, 1]


def test_sliding_box_decelerates_at_mu_g_and_stops_when_predicted() -> None:
    sim = box_on_ground(mu=0.4)
    run = sim.rollout(sim.initial_state(q=pose(0, 0.25, 0), v=pose(1.0, 0, 0)), steps=40)
    expected = (1.0 - 0.4 * G * H * torch.arange(41, dtype=torch.float64)).clamp(min=0)
    torch.testing.assert_close(run.v[:, 0, 0], expected, atol=1e-9, rtol=0)
    torch.testing.assert_close(
        run.q[:, 0, 1], torch.full((41,), 0.25, dtype=torch.float64), atol=1e-12, rtol=0
    )
    assert (run.solver == SOLVED_BY_GUESS).float().mean() > 0.9  # the fast path carries the rollout


@pytest.mark.parametrize("degrees", [15.0, 30.0])
def test_incline_sticks_iff_tan_below_mu_else_slides_down_at_closed_form_rate(
    degrees: float,
) -> None:
    mu, angle = 0.4, math.radians(degrees)
    sim = box_on_ground(mu=mu, angle=angle)
    # Rest the box on the incline: its centre sits b along the incline's normal.
    center = 0.25 * torch.tensor([-math.sin(angle), math.cos(angle)], dtype=torch.float64)
    run = sim.rollout(
        sim.initial_state(q=pose(float(center[0]), float(center[1]), angle)), steps=20
    )
    downhill = torch.tensor([-math.cos(angle), -math.sin(angle)], dtype=torch.float64)
    speed = run.v[:, 0, :2] @ downhill
    if math.tan(angle) < mu:
        assert run.v.abs().max().item() < 1e-10
    else:
        accel = G * (math.sin(angle) - mu * math.cos(angle))
        torch.testing.assert_close(
            speed, accel * H * torch.arange(21, dtype=torch.float64), atol=1e-9, rtol=0
        )
        assert run.v[:, 0, 2].abs().max().item() < 1e-9


def test_resting_box_has_zero_drift_and_carries_its_weight() -> None:
    sim = box_on_ground()
    state = sim.initial_state(q=pose(0.3, 0.25, 0))
    result = sim.step(state)
    run = sim.rollout(state, steps=100)
    assert (run.q - state.q).abs().max().item() < 1e-12
    assert result.pn.sum().item() == pytest.approx(MASS * G * H, abs=1e-12)
    assert result.mode.tolist()[:2] == [STICKING, STICKING]


@pytest.mark.parametrize("ratio", [0.9, 1.1])
def test_push_tips_or_slides_at_the_statics_threshold(ratio: float) -> None:
    """F < μ m g pushing the left face at height y tips the box iff F y > m g a."""
    mu = 0.5
    sim = box_on_ground(mu=mu)
    force_value = 0.8 * mu * MASS * G
    height = ratio * MASS * G * (WIDTH / 2) / force_value
    # Generalized force of F = (f, 0) at body point r = (−a, y − b): torque r × F = −(y − b) f.
    force = torch.tensor(
        [[[force_value, 0.0, -(height - HEIGHT / 2) * force_value]]], dtype=torch.float64
    )
    state = sim.initial_state(q=pose(0, 0.25, 0).unsqueeze(0))
    result = sim.step(state, force=force)
    if ratio < 1:
        assert result.state.v.abs().max().item() < 1e-12
    else:
        assert result.mode[0, :2].tolist() == [SEPARATED, STICKING]
        inertia = MASS * (WIDTH**2 + HEIGHT**2) / 12
        pivot = inertia + MASS * ((WIDTH / 2) ** 2 + (HEIGHT / 2) ** 2)
        omega = -H * (force_value * height - MASS * G * WIDTH / 2) / pivot
        assert result.state.v[0, 0, 2].item() == pytest.approx(omega, abs=1e-10)


def test_push_low_above_friction_limit_slides() -> None:
    mu = 0.5
    sim = box_on_ground(mu=mu)
    force_value = 1.5 * mu * MASS * G
    force = torch.tensor([[[force_value, 0.0, 0.0]]], dtype=torch.float64)
    result = sim.step(sim.initial_state(q=pose(0, 0.25, 0).unsqueeze(0)), force=force)
    assert result.state.v[0, 0, 0].item() == pytest.approx(
        H * (force_value - mu * MASS * G) / MASS, abs=1e-12
    )
    assert abs(result.state.v[0, 0, 2].item()) < 1e-12


def test_plastic_impact_stops_the_fall_without_bounce() -> None:
    sim = box_on_ground()
    state = sim.initial_state(q=pose(0, 0.26, 0), v=pose(0, -2.0, 0))
    run = sim.rollout(state, steps=10)
    landed = run.pn.sum(-1) > 0
    first = int(torch.nonzero(landed)[0])
    # The landing step closes the gap exactly (v⁺ = −φ/h), the next one stops the box dead,
    # and it stays on the ground: no bounce.
    gap = run.q[first, 0, 1].item() - 0.25
    assert run.v[first + 1, 0, 1].item() == pytest.approx(-gap / H, abs=1e-12)
    assert run.q[first + 1 :, 0, 1].sub(0.25).abs().max().item() < 1e-12
    assert run.v[first + 2 :, 0, 1].abs().max().item() < 1e-12


def test_box_tipped_past_balance_comes_to_rest_on_its_side() -> None:
    sim = box_on_ground(mu=0.6)
    theta = 1.3  # the balance angle on a corner is atan(W / H) ≈ 1.107 rad
    a, b = WIDTH / 2, HEIGHT / 2
    corner = torch.tensor([-a, -b], dtype=torch.float64)
    rotation = torch.tensor(
        [[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]]
    )
    center = -(rotation.double() @ corner)
    run = sim.rollout(
        sim.initial_state(q=pose(float(center[0]), float(center[1]), theta)), steps=250
    )
    final = run.q[-1, 0]
    assert final[2].item() == pytest.approx(math.pi / 2, abs=1e-6)
    assert final[1].item() == pytest.approx(a, abs=1e-6)
    assert run.v[-1].abs().max().item() < 1e-8


def test_energy_never_increases_without_applied_forces() -> None:
    gen = torch.Generator().manual_seed(0)
    batch = 32
    sim = box_on_ground(mu=0.5)
    theta = 0.6 * (torch.rand(batch, generator=gen, dtype=torch.float64) - 0.5)
    lowest = 0.5 * torch.sin(theta).abs() + 0.25 * torch.cos(theta)
    q = torch.stack(
        [
            torch.zeros(batch, dtype=torch.float64),
            lowest + 0.2 * torch.rand(batch, generator=gen, dtype=torch.float64),
            theta,
        ],
        -1,
    )
    v = torch.randn(batch, 3, generator=gen, dtype=torch.float64)
    run = sim.rollout(sim.initial_state(q=q.unsqueeze(1), v=v.unsqueeze(1)), steps=150)
    energies = energy(sim, run.q, run.v)  # (T + 1, B)
    increase = (energies[1:] - energies[:-1]).max().item()
    assert increase < 1e-3 * MASS * G * H  # a tiny fraction of one step's work of gravity
    assert energies[-1].max().item() < energies[0].min().item() + 1.0


def test_block_pushed_by_a_kinematic_finger_moves_with_it() -> None:
    finger = Body("finger", Polygon.box(0.1, 0.3), kind="kinematic")
    sim = box_on_ground(mu=0.3, finger=finger)
    state = sim.initial_state(q=pose(0, 0.25, 0), q_kinematic=pose(-0.6, 0.2, 0))
    speed = 0.2
    controls = torch.tensor([speed, 0.0, 0.0], dtype=torch.float64).expand(80, 1, 3)
    run = sim.rollout(state, steps=80, controls=controls)
    touching = run.pn[:, sim.scene.slot_groups[1].start :].sum(-1) > 0
    assert bool(touching[-20:].all())
    torch.testing.assert_close(
        run.v[-20:, 0, 0], torch.full((20,), speed, dtype=torch.float64), atol=1e-9, rtol=0
    )
    # Gap between finger face and block face stays closed once pushing.
    gap = (run.q[-1, 0, 0] - 0.5) - (run.q_kinematic[-1, 0, 0] + 0.05)
    assert abs(gap.item()) < 1e-9


def test_batched_rollout_equals_per_scene_rollouts() -> None:
    gen = torch.Generator().manual_seed(1)
    sim = box_on_ground(mu=0.5)
    q = pose(0, 0.3, 0, (6,)) + 0.1 * torch.rand(6, 1, 3, generator=gen, dtype=torch.float64)
    v = torch.randn(6, 1, 3, generator=gen, dtype=torch.float64)
    batched = sim.rollout(sim.initial_state(q=q, v=v), steps=60)
    for i in range(6):
        single = sim.rollout(sim.initial_state(q=q[i], v=v[i]), steps=60)
        torch.testing.assert_close(single.q, batched.q[:, i], atol=1e-10, rtol=0)
        torch.testing.assert_close(single.mode, batched.mode[:, i])


def test_rollout_gradients_match_closed_form_and_finite_differences() -> None:
    """Sliding for 15 steps (mode constant): x_T = x0 + h Σ_k (v0 − k μ g h)."""
    steps = 15
    mu = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
    mass = torch.tensor(MASS, dtype=torch.float64, requires_grad=True)
    v0 = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)

    def final_x(mu_value, mass_value, v0_value):
        sim = box_on_ground(mu=mu_value, mass=mass_value)
        v = torch.stack([v0_value, torch.zeros_like(v0_value), torch.zeros_like(v0_value)]).reshape(
            1, 3
        )
        run = sim.rollout(sim.initial_state(q=pose(0, 0.25, 0), v=v), steps=steps)
        return run.q[-1, 0, 0]

    x = final_x(mu, mass, v0)
    d_mu, d_mass, d_v0 = torch.autograd.grad(x, (mu, mass, v0))
    k_sum = steps * (steps + 1) / 2
    assert d_v0.item() == pytest.approx(steps * H, abs=1e-10)
    assert d_mu.item() == pytest.approx(-H * G * H * k_sum, abs=1e-10)
    assert abs(d_mass.item()) < 1e-10
    eps = 1e-6
    with torch.no_grad():
        fd_mu = (final_x(mu + eps, mass, v0) - final_x(mu - eps, mass, v0)) / (2 * eps)
    assert d_mu.item() == pytest.approx(fd_mu.item(), abs=1e-7)


def test_gradient_with_respect_to_control_and_initial_pose() -> None:
    """A finger pushing a block: d(block x)/d(finger speed) and d/d(x0) vs finite differences."""
    finger = Body("finger", Polygon.box(0.1, 0.3), kind="kinematic")
    sim = box_on_ground(mu=0.3, finger=finger)

    def final_x(speed, x0):
        q = torch.stack(
            [x0, torch.tensor(0.25, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64)]
        ).reshape(1, 3)
        state = sim.initial_state(q=q, q_kinematic=pose(-0.55, 0.2, 0))
        controls = torch.stack([speed, torch.zeros_like(speed), torch.zeros_like(speed)]).expand(
            30, 1, 3
        )
        return sim.rollout(state, steps=30, controls=controls).q[-1, 0, 0]

    speed = torch.tensor(0.2, dtype=torch.float64, requires_grad=True)
    x0 = torch.tensor(0.0, dtype=torch.float64, requires_grad=True)
    d_speed, d_x0 = torch.autograd.grad(final_x(speed, x0), (speed, x0))
    eps = 1e-6
    with torch.no_grad():
        fd_speed = (final_x(speed + eps, x0) - final_x(speed - eps, x0)) / (2 * eps)
        fd_x0 = (final_x(speed, x0 + eps) - final_x(speed, x0 - eps)) / (2 * eps)
    assert d_speed.item() == pytest.approx(fd_speed.item(), abs=1e-6)
    assert d_x0.item() == pytest.approx(fd_x0.item(), abs=1e-6)
    assert d_speed.item() > 0.1  # pushing faster moves the block further


def test_stacked_boxes_rest_and_the_ground_carries_both() -> None:
    """Dynamic–dynamic contact: a small box on a big one, both at rest."""
    top = Body("top", Polygon.box(0.4, 0.2), mass=1.0)
    sim = box_on_ground(mu=0.5, top=top)
    q = torch.tensor([[0.0, 0.25, 0.0], [0.1, 0.6, 0.0]], dtype=torch.float64)
    state = sim.initial_state(q=q)
    run = sim.rollout(state, steps=50)
    assert (run.q - q).abs().max().item() < 1e-12
    groups = {(g.receiver, g.other): g for g in sim.scene.slot_groups}
    ground_box = groups[(1, 0)]
    top_on_box = groups[(2, 1)]
    ground_impulse = run.pn[-1, ground_box.start : ground_box.start + ground_box.count].sum()
    top_impulse = run.pn[-1, top_on_box.start : top_on_box.start + top_on_box.count].sum()
    assert ground_impulse.item() == pytest.approx((MASS + 1.0) * G * H, abs=1e-12)
    assert top_impulse.item() == pytest.approx(1.0 * G * H, abs=1e-12)


def test_box_sliding_onto_a_box_decelerates_both_by_momentum_exchange() -> None:
    """A 1 kg box hits a resting 2 kg box on frictionless ground: plastic impact, v = v0/3."""
    hitter = Body("hitter", Polygon.box(0.5, 0.5), mass=1.0)
    sim = box_on_ground(mu=0.0, hitter=hitter)
    q = torch.tensor([[0.0, 0.25, 0.0], [-0.76, 0.25, 0.0]], dtype=torch.float64)
    v = torch.tensor([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0]], dtype=torch.float64)
    run = sim.rollout(sim.initial_state(q=q, v=v), steps=10)
    torch.testing.assert_close(
        run.v[-1, :, 0], torch.full((2,), 0.5, dtype=torch.float64), atol=1e-12, rtol=0
    )
    momentum = run.v[:, 0, 0] * MASS + run.v[:, 1, 0] * 1.0
    torch.testing.assert_close(
        momentum, torch.full((11,), 1.5, dtype=torch.float64), atol=1e-12, rtol=0
    )


def test_box_starting_to_slide_or_landing_on_a_corner_stays_on_the_fast_path_at_lemke() -> None:
    """A box launched at 1 m/s on its two bottom corners, and a box tipping over a corner until
    its second corner lands (μ = 0.5): every step is solved from the previous modes by the
    active set (no exact solver), its velocities equal Lemke's on the same contact problem,
    and the first sliding step is the closed form ``v = 1 − μ g h`` with the weight carried.

    From separated modes, corners that close while slipping start sliding against their
    slip: started sticking instead, the launched box's active set cycled between a corner
    pulling and the corners sticking, and the landing corner's stuck rows contradicted the
    pivot's, so Lemke solved both steps. The velocities of the Stewart–Trinkle LCP are
    unique here; both solutions are exact to rounding (condition numbers ~10), so 1e-9 m/s.
    """
    sim = box_on_ground(mu=0.5)
    theta = 1.2  # past the balance angle atan(W / H) ≈ 1.107 rad: it tips onto its side
    corner = torch.tensor([-WIDTH / 2, -HEIGHT / 2], dtype=torch.float64)
    rotation = torch.tensor(
        [[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]],
        dtype=torch.float64,
    )
    tipping = -(rotation @ corner)
    q = torch.cat([pose(0, HEIGHT / 2, 0), pose(float(tipping[0]), float(tipping[1]), theta)])
    v = torch.cat([pose(1.0, 0, 0), pose(0, 0, 0)])
    state = sim.initial_state(q=q.unsqueeze(1), v=v.unsqueeze(1))
    run = sim.rollout(state, steps=160)
    assert bool((run.solver == SOLVED_BY_GUESS).all())
    expected = torch.tensor([1.0 - 0.5 * G * H, 0.0, 0.0], dtype=torch.float64)
    torch.testing.assert_close(run.v[1, 0, 0], expected, atol=1e-12, rtol=0)
    assert run.pn[0, 0].sum().item() == pytest.approx(MASS * G * H, rel=1e-12)
    # The tipping box lands: two corners carry it at the end, one before.
    landed = (run.mode[:, 1] != SEPARATED).sum(-1)
    assert landed[0] == 1
    assert landed[-1] == 2
    problem, _ = contact_problem(
        sim.scene,
        SceneState(
            q=run.q[:-1].flatten(0, 1),
            v=run.v[:-1].flatten(0, 1),
            q_kinematic=run.q_kinematic[:-1].flatten(0, 1),
            mode=run.mode.flatten(0, 1),
        ),
    )
    oracle = solve(problem, "lemke")
    assert bool(oracle.status.converged.all())
    torch.testing.assert_close(
        run.v[1:].flatten(0, 1), oracle.v_next.unflatten(-1, (1, 3)), atol=1e-9, rtol=0
    )
