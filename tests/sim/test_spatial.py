"""Spatial scenes in the one engine, against closed-form rigid-body mechanics.

The inclines tilt gravity instead of the ground: the ground's normal stays ``+z`` (whose
friction directions start along ``+x``), and gravity ``g (sin θ, 0, −cos θ)`` pulls down a slope
along ``+x``.
"""

from __future__ import annotations

import math

import pytest
import torch

from torchcontact.geometry import Box, HalfPlane, HalfSpace, Polygon, Sphere
from torchcontact.sim import SOLVED_BY_GUESS, Body, Scene, Simulator

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
    assert float(speed[stop - 1]) > 0 and float(speed[stop].abs()) <= 1e-9


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
    with pytest.raises(ValueError, match="no contact routine"):
        Scene(bodies=(Body("a", Sphere(0.1)), Body("b", Sphere(0.1))))
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
    assert planar.gravity == (0.0, -9.81) and planar.dimension == 2
    simulator = Simulator(Scene(bodies=(ground, Body("ball", Sphere(0.1)))))
    with pytest.raises(ValueError, match="quaternions"):
        simulator.initial_state(
            q=torch.tensor([[0.0, 0.0, 0.1, 2.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
        )
    with pytest.raises(ValueError, match="q"):
        simulator.initial_state(q=torch.zeros(1, 3, dtype=torch.float64))
