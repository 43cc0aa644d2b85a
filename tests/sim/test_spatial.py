"""Spatial scenes in the one engine, against closed-form rigid-body mechanics.

The inclines tilt gravity instead of the ground: the ground's normal stays ``+z`` (whose
friction directions start along ``+x``), and gravity ``g (sin θ, 0, −cos θ)`` pulls down a slope
along ``+x``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import pytest
import torch

from torchcontact.geometry import Box, HalfPlane, HalfSpace, Polygon, Sphere
from torchcontact.sim import (
    SOLVED_BY_GUESS,
    UNSOLVED,
    Body,
    Scene,
    Simulator,
    spatial_mass_matrix,
)

G = 9.81
IDENTITY = (1.0, 0.0, 0.0, 0.0)


def incline(theta: float, mu: float, body: Body, *, directions: int = 8) -> Simulator:
    gravity = (G * math.sin(theta), 0.0, -G * math.cos(theta))
    ground = Body("ground", HalfSpace.ground(), kind="static")
    scene = Scene(
        bodies=(ground, body),
        gravity=gravity,
        friction=mu,
        h=0.01,
        friction_directions=directions,
    )
    return Simulator(scene)


def resting(z: float, batch: int = 1) -> torch.Tensor:
    return torch.tensor([[0.0, 0.0, z, *IDENTITY]], dtype=torch.float64).expand(batch, 1, 7)


def accelerations(simulator: Simulator, z: float, steps: int) -> torch.Tensor:
    run = simulator.rollout(simulator.initial_state(q=resting(z)), steps=steps)
    return (run.v[1:, 0, 0, :] - run.v[:-1, 0, 0, :]) / simulator.scene.h


@pytest.mark.parametrize("directions", [4, 8])
def test_sphere_rolls_without_slipping_at_five_sevenths_g_sin_theta(directions: int) -> None:
    """μ = 0.5 > (2/7) tan 30°: rolling, a = (5/7) g sin θ and ω = v / r, at every step."""
    theta, radius = math.radians(30.0), 0.1
    simulator = incline(theta, 0.5, Body("ball", Sphere(radius), mass=1.0), directions=directions)
    run = simulator.rollout(simulator.initial_state(q=resting(radius)), steps=40)
    a = (run.v[1:, 0, 0, 0] - run.v[:-1, 0, 0, 0]) / simulator.scene.h
    expected = 5.0 / 7.0 * G * math.sin(theta)
    torch.testing.assert_close(a, torch.full_like(a, expected), rtol=1e-6, atol=0.0)
    # rolling: the contact point does not slip (v = ω_y r), and the ball stays on the ground
    torch.testing.assert_close(run.v[-1, 0, 0, 4] * radius, run.v[-1, 0, 0, 0], rtol=1e-9, atol=0.0)
    torch.testing.assert_close(
        run.q[:, 0, 0, 2], torch.full((41,), radius, dtype=torch.float64), rtol=0.0, atol=1e-12
    )
    assert (run.mode[:, 0, 0] == 1).all()  # sticking


def test_sphere_slides_at_g_sin_minus_mu_cos() -> None:
    """μ = 0.1 < (2/7) tan 30° ≈ 0.165: sliding down the slope along a friction direction."""
    theta, mu = math.radians(30.0), 0.1
    simulator = incline(theta, mu, Body("ball", Sphere(0.1), mass=2.0))
    a = accelerations(simulator, 0.1, 30)[:, 0]
    expected = G * (math.sin(theta) - mu * math.cos(theta))
    torch.testing.assert_close(a, torch.full_like(a, expected), rtol=1e-6, atol=0.0)


def test_box_on_a_twenty_degree_incline_does_not_creep() -> None:
    """tan 20° ≈ 0.36 < μ = 0.5: four redundant sticking corners hold the box; over 2 s its
    speed stays below 1e-9 m/s (the regularised solve's error, not a creep)."""
    simulator = incline(math.radians(20.0), 0.5, Body("box", Box([0.1, 0.1, 0.05]), mass=1.0))
    run = simulator.rollout(simulator.initial_state(q=resting(0.05)), steps=200)
    assert float(run.v.abs().max()) <= 1e-9
    assert (run.solver == SOLVED_BY_GUESS)[1:].all()


def test_a_sliding_box_stops_at_the_step_the_scheme_predicts() -> None:
    """A box sliding along a friction direction on level ground loses μ g h of speed per step
    and stops at step ⌈v₀ / (μ g h)⌉."""
    mu, v0, h = 0.4, 1.0, 0.01
    ground = Body("ground", HalfSpace.ground(), kind="static")
    scene = Scene(bodies=(ground, Body("box", Box([0.2, 0.1, 0.05]), mass=1.0)), friction=mu, h=h)
    simulator = Simulator(scene)
    v = torch.zeros(1, 1, 6, dtype=torch.float64)
    v[..., 0] = v0
    run = simulator.rollout(simulator.initial_state(q=resting(0.05), v=v), steps=40)
    speed = run.v[:, 0, 0, 0]
    stop = math.ceil(v0 / (mu * G * h))
    expected = torch.clamp(v0 - mu * G * h * torch.arange(41, dtype=torch.float64), min=0.0)
    torch.testing.assert_close(speed, expected, rtol=0.0, atol=1e-9)
    assert float(speed[stop - 1]) > 0
    assert float(speed[stop].abs()) <= 1e-9


def test_penetration_is_removed_at_the_recovery_speed() -> None:
    """A box 5 mm into the ground leaves at the scene's recovery speed, not at d / h."""
    ground = Body("ground", HalfSpace.ground(), kind="static")
    box = Body("box", Box([0.1, 0.1, 0.05]), mass=1.0)
    for speed in (0.1, 0.02):
        scene = Scene(bodies=(ground, box), gravity=(0.0, 0.0, 0.0), recovery_speed=speed)
        simulator = Simulator(scene)
        result = simulator.step(simulator.initial_state(q=resting(0.045)))
        torch.testing.assert_close(
            result.state.v[0, 0, 2], torch.tensor(speed, dtype=torch.float64), rtol=1e-9, atol=0.0
        )


def test_batched_equals_one_by_one() -> None:
    """Boxes dropped at random orientations: a batch steps like each scene alone."""
    ground = Body("ground", HalfSpace.ground(), kind="static")
    scene = Scene(bodies=(ground, Body("box", Box([0.1, 0.07, 0.05]), mass=1.0)), friction=0.6)
    simulator = Simulator(scene)
    generator = torch.Generator().manual_seed(3)
    quaternion = torch.randn(4, 4, dtype=torch.float64, generator=generator)
    quaternion = quaternion / quaternion.norm(dim=-1, keepdim=True)
    q = torch.cat(
        [torch.zeros(4, 2, dtype=torch.float64), torch.full((4, 1), 0.125), quaternion], -1
    )
    state = simulator.initial_state(q=q.unsqueeze(1).to(torch.float64))
    together = simulator.rollout(state, steps=25)
    for b in range(4):
        alone = simulator.rollout(state[b : b + 1], steps=25)
        torch.testing.assert_close(alone.q[:, 0], together.q[:, b], rtol=1e-9, atol=1e-10)


def test_scene_validation() -> None:
    ground = Body("ground", HalfSpace.ground(), kind="static")
    with pytest.raises(ValueError, match="all planar or all spatial"):
        Scene(bodies=(ground, Body("box", Polygon.box(1.0, 0.5), mass=1.0)))
    with pytest.raises(ValueError, match="gravity"):
        Scene(bodies=(ground, Body("ball", Sphere(0.1))), gravity=(0.0, -9.81))
    with pytest.raises(ValueError, match="friction_directions"):
        Scene(bodies=(ground, Body("ball", Sphere(0.1))), friction_directions=5)
    with pytest.raises(ValueError, match="HalfSpace can only be static"):
        Body("wall", HalfSpace.ground())
    with pytest.raises(ValueError, match="inertia"):
        Body("ball", Sphere(0.1), inertia=torch.eye(3) * -1.0)
    with pytest.raises(ValueError, match="pose"):
        Body("block", Box([0.1, 0.1, 0.1]), kind="static")
    planar = Scene(
        bodies=(Body("floor", HalfPlane.ground(), kind="static"), Body("b", Polygon.box(1.0, 0.5)))
    )
    assert planar.gravity == (0.0, -9.81)
    assert planar.dimension == 2
    simulator = Simulator(Scene(bodies=(ground, Body("ball", Sphere(0.1)))))
    with pytest.raises(ValueError, match="quaternions"):
        simulator.initial_state(
            q=torch.tensor([[0.0, 0.0, 0.1, 2.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
        )
    with pytest.raises(ValueError, match="q"):
        simulator.initial_state(q=torch.zeros(1, 3, dtype=torch.float64))


def push(height: float, *, mu: float = 0.8, steps: int = 50) -> tuple[float, float]:
    """A 0.2 m cube (1 kg) pushed at 5 cm/s by a frictionless kinematic sphere whose centre is
    at ``height``: the cube's tilt (rad) and its travel (m) after ``steps`` steps."""
    scene = Scene(
        bodies=(
            Body("ground", HalfSpace.ground(), kind="static"),
            Body("box", Box([0.1, 0.1, 0.1]), mass=1.0),
            Body("pusher", Sphere(0.02), kind="kinematic"),
        ),
        friction=mu,
        pair_friction={("box", "pusher"): 0.0},
    )
    simulator = Simulator(scene)
    state = simulator.initial_state(
        q=resting(0.1),
        q_kinematic=torch.tensor([[[-0.12, 0.0, height, *IDENTITY]]], dtype=torch.float64),
    )
    controls = torch.zeros(steps, 1, 1, 6, dtype=torch.float64)
    controls[..., 0] = 0.05
    run = simulator.rollout(state, steps=steps, controls=controls)
    quaternion = run.q[-1, 0, 0, 3:]
    tilt = 2.0 * math.atan2(float(quaternion[1:].norm()), abs(float(quaternion[0])))
    return tilt, float(run.q[-1, 0, 0, 0])


@pytest.mark.parametrize("fraction", [0.99, 1.01])
def test_a_pushed_box_tips_iff_the_push_is_above_w_over_two_mu(fraction: float) -> None:
    """Pushing at height H with force F: the box slides when F reaches μ m g and tips when
    F H reaches m g w / 2, so it tips iff H > w / (2 μ) (0.125 m here); 1 % either side of the
    threshold decides."""
    threshold = 0.2 / (2 * 0.8)
    tilt, travel = push(fraction * threshold)
    if fraction < 1:
        assert tilt <= 1e-9
        assert travel == pytest.approx(0.05 * 0.01 * 50, abs=1e-9)  # it moves with the pusher
    else:
        assert tilt >= 0.1


def test_random_drops_never_gain_energy() -> None:
    """Boxes dropped with random poses and twists: kinetic plus potential energy never increases
    from one step to the next by more than 1e-9 J (rounding; the gap term cannot add energy to
    a body that starts separated)."""
    mass = 1.3
    ground = Body("ground", HalfSpace.ground(), kind="static")
    scene = Scene(bodies=(ground, Body("box", Box([0.15, 0.1, 0.05]), mass=mass)), friction=0.6)
    simulator = Simulator(scene)
    generator = torch.Generator().manual_seed(0)
    B = 12
    quaternion = torch.randn(B, 4, dtype=torch.float64, generator=generator)
    quaternion = quaternion / quaternion.norm(dim=-1, keepdim=True)
    height = 0.2 + 0.1 * torch.rand(B, 1, dtype=torch.float64, generator=generator)
    q = torch.cat([torch.zeros(B, 2, dtype=torch.float64), height, quaternion], -1)[:, None]
    v = torch.randn(B, 1, 6, dtype=torch.float64, generator=generator)
    run = simulator.rollout(simulator.initial_state(q=q, v=v), steps=100, strict=False)
    solved = (run.solver != UNSOLVED).all(dim=0)
    assert int(solved.sum()) >= B - 1
    M = spatial_mass_matrix(scene.masses(), scene.inertias(), run.q[..., 3:])
    twist = run.v.reshape(101, B, 6)
    kinetic = 0.5 * (twist.unsqueeze(-2) @ M @ twist.unsqueeze(-1)).reshape(101, B)
    energy = kinetic + mass * G * run.q[:, :, 0, 2]
    assert float((energy[1:] - energy[:-1])[:, solved].max()) <= 1e-9
    assert float(energy[-1].max()) < float(energy[0].min())  # it came to rest


@pytest.mark.parametrize("angle", [math.pi / 8, math.pi / 5, math.pi / 3])
def test_sliding_off_the_friction_directions_decelerates_within_the_polyhedral_bounds(
    angle: float,
) -> None:
    """The 8-direction cone is inscribed in the circular one: a box sliding between friction
    directions loses between μ g h cos(π/8) and μ g h of speed per step (mid-face at π/8)."""
    mu, h, v0 = 0.4, 0.01, 1.0
    ground = Body("ground", HalfSpace.ground(), kind="static")
    scene = Scene(bodies=(ground, Body("box", Box([0.2, 0.1, 0.05]), mass=1.0)), friction=mu, h=h)
    simulator = Simulator(scene)
    v = torch.zeros(1, 1, 6, dtype=torch.float64)
    v[..., 0], v[..., 1] = v0 * math.cos(angle), v0 * math.sin(angle)
    run = simulator.rollout(simulator.initial_state(q=resting(0.05), v=v), steps=10)
    speed = run.v[:, 0, 0, :2].norm(dim=-1)
    loss = speed[:-1] - speed[1:]
    low, high = mu * G * h * math.cos(math.pi / 8), mu * G * h
    assert float(loss.min()) >= low * (1 - 1e-9)
    assert float(loss.max()) <= high * (1 + 1e-9)
    if angle == math.pi / 8:  # exactly mid-face: the lower bound, straight on
        torch.testing.assert_close(loss, torch.full_like(loss, low), rtol=1e-9, atol=0.0)


def test_rollout_gradients_equal_richardson_finite_differences() -> None:
    """A box sliding and turning on the ground for five steps: gradients of its final pose
    and twist with respect to the pair friction and the initial twist, against central
    differences extrapolated from two steps (the modes stay the same under the perturbation)."""
    mu = torch.tensor(0.35, dtype=torch.float64, requires_grad=True)
    v0 = torch.tensor([[[0.8, 0.3, 0.0, 0.0, 0.0, 1.5]]], dtype=torch.float64, requires_grad=True)
    weights = torch.randn(13, dtype=torch.float64, generator=torch.Generator().manual_seed(5))

    def loss(friction: torch.Tensor, twist: torch.Tensor) -> torch.Tensor:
        ground = Body("ground", HalfSpace.ground(), kind="static")
        box = Body("box", Box([0.2, 0.1, 0.05]), mass=1.0)
        scene = Scene(bodies=(ground, box), pair_friction={("box", "ground"): friction})
        simulator = Simulator(scene)
        run = simulator.rollout(simulator.initial_state(q=resting(0.05), v=twist), steps=5)
        return (torch.cat([run.q[-1, 0, 0], run.v[-1, 0, 0]]) * weights).sum()

    grad_mu, grad_v = torch.autograd.grad(loss(mu, v0), (mu, v0))

    def richardson(fn: Callable[[float], torch.Tensor], step: float) -> torch.Tensor:
        def central(e: float) -> torch.Tensor:
            return (fn(e) - fn(-e)) / (2 * e)

        return (4 * central(step / 2) - central(step)) / 3

    with torch.no_grad():
        fd_mu = richardson(lambda e: loss(mu + e, v0), 1e-4)
        fd_v = torch.stack(
            [
                richardson(
                    lambda e, i=i: loss(mu, v0 + e * torch.eye(6, dtype=torch.float64)[i]), 1e-4
                )
                for i in range(6)
            ]
        )
    torch.testing.assert_close(grad_mu, fd_mu, rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(grad_v.reshape(6), fd_v, rtol=1e-6, atol=1e-9)
