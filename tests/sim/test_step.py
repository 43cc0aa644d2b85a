"""The simulator's step (assembled at once, solved on the candidate slots) against independent
references: closed-form physics, Lemke on the full uncompacted problem, and Richardson-
extrapolated finite differences of its gradients."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch

from torchcontact.contact import solve
from torchcontact.envs import PegInHoleConfig, build_scene
from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import UNSOLVED, Body, Scene, SceneState, Simulator, contact_problem

F64 = torch.float64
G, H, MASS, MU = 9.81, 0.01, 2.0, 0.3


def _grasp_states(batch: int, seed: int) -> tuple[Simulator, SceneState]:
    """Perturbed poses of a peg held between two fingers above the hole (many slots, a dozen
    candidates)."""
    config = PegInHoleConfig()
    scene, pad_offset = build_scene(config)
    generator = torch.Generator().manual_seed(seed)
    half_width = config.peg_width / 2
    x = 0.04 * torch.rand(batch, generator=generator, dtype=F64) - 0.02
    y = 0.11 + 0.03 * torch.rand(batch, generator=generator, dtype=F64)
    centre = torch.stack([x, y, torch.zeros_like(x)], dim=-1)
    offset = torch.tensor(
        [
            [0.0, 0.0, 0.0],
            [-half_width - pad_offset, 0.04, 0.0],
            [half_width + pad_offset, 0.04, 0.0],
        ],
        dtype=F64,
    )
    q = centre[:, None, :] + offset
    q = q + 0.002 * torch.randn(q.shape, generator=generator, dtype=F64)
    v = 0.2 * torch.randn(q.shape, generator=generator, dtype=F64)
    sim = Simulator(scene)
    return sim, sim.initial_state(q=q, v=v)


@pytest.mark.filterwarnings("ignore:OSQP exited:UserWarning")
def test_step_velocities_equal_lemke_on_the_full_problem_at_grasp_scenes() -> None:
    """Random grasps with random forces: the compacted step's velocities against Lemke's
    solution of the full problem (every slot, candidate or not).

    The velocities of the Stewart–Trinkle LCP are unique here while the impulse split among
    redundant contacts is not, so only velocities are compared. Both solutions are accurate to
    an LCP residual of about 1e-9 (impulses in N·s, velocities in m/s); the grasp's Delassus
    matrix has condition numbers up to ~1e4, so velocities agree to ~1e-6 m/s.
    """
    sim, state = _grasp_states(24, seed=1)
    generator = torch.Generator().manual_seed(2)
    compared = dropped = 0
    for _ in range(4):
        force = 3.0 * torch.randn(state.q.shape, generator=generator, dtype=F64)
        result = sim.step(state, force=force)
        problem, geometry = contact_problem(sim.scene, state, force=force)
        oracle = solve(problem, "lemke")
        both = oracle.status.converged & (result.solver != UNSOLVED)
        v_oracle = oracle.v_next.unflatten(-1, (3, 3))
        torch.testing.assert_close(result.state.v[both], v_oracle[both], atol=1e-6, rtol=1e-6)
        # No impulse on a slot that is not a candidate.
        assert float(result.pn[~geometry.active].abs().max()) == 0.0
        compared += int(both.sum())
        dropped += int((~geometry.active).sum(-1).min())
        state = result.state
    assert compared > 60
    assert dropped > 0  # the solve ran on fewer slots than the problem has


def _pushing_scene(finger: Polygon, *, static_table: bool = False) -> Simulator:
    """A box on the ground (or a static table) and a frictionless kinematic finger."""
    support: Body = (
        Body("table", Polygon.box(3.0, 0.2), kind="static", pose=torch.tensor([0.0, -0.1, 0.0]))
        if static_table
        else Body("ground", HalfPlane.ground(), kind="static")
    )
    scene = Scene(
        bodies=(
            support,
            Body("box", Polygon.box(1.0, 0.5), mass=MASS),
            Body("finger", finger, kind="kinematic"),
        ),
        friction=MU,
        pair_friction={("box", "finger"): 0.0},
        h=H,
    )
    return Simulator(scene)


@pytest.mark.parametrize(
    ("finger", "finger_y", "static_table"),
    [
        (Polygon.box(0.1, 0.8), 0.3, False),  # the box's corners touch the finger's face
        (Polygon.box(0.1, 0.2), 0.2, False),  # the finger's corners touch the box's face
        (Polygon.box(0.1, 0.2), 0.2, True),  # the same on a static polygon instead of ground
    ],
)
def test_box_pushed_by_a_kinematic_finger_slides_at_its_speed_against_mu_m_g(
    finger: Polygon, finger_y: float, static_table: bool
) -> None:
    """Pushed at a constant speed u by a frictionless finger, the box ends up sliding at u: the
    support's normal impulse per step is m g h, the finger's the support's friction μ m g h."""
    sim = _pushing_scene(finger, static_table=static_table)
    speed = 0.4
    state = sim.initial_state(
        q=torch.tensor([[0.0, 0.25, 0.0]], dtype=F64),
        q_kinematic=torch.tensor([[-0.56, finger_y, 0.0]], dtype=F64),
    )
    control = torch.tensor([[speed, 0.0, 0.0]], dtype=F64)
    for _ in range(60):
        result = sim.step(state, control)
        state = result.state
    torch.testing.assert_close(
        state.v[0], torch.tensor([speed, 0.0, 0.0], dtype=F64), atol=1e-9, rtol=0
    )
    support, pushing = [
        sum(result.pn[group.start : group.start + group.count].sum() for group in groups)
        for groups in (
            [g for g in sim.scene.slot_groups if {g.receiver, g.other} == {0, 1}],
            [g for g in sim.scene.slot_groups if {g.receiver, g.other} == {1, 2}],
        )
    ]
    assert float(support) == pytest.approx(MASS * G * H, rel=1e-9)
    assert float(pushing) == pytest.approx(MU * MASS * G * H, rel=1e-9)


def test_box_resting_on_a_tilted_static_polygon_sticks_and_carries_its_weight() -> None:
    """On a slope of 0.2 rad (tan = 0.203 < μ = 0.3) the box sticks: zero velocity, normal
    impulses summing to m g h cos α and friction impulses to m g h sin α."""
    angle = 0.2
    slope = Polygon.box(4.0, 0.2)
    scene = Scene(
        bodies=(
            Body("slope", slope, kind="static", pose=torch.tensor([0.0, 0.0, angle])),
            Body("box", Polygon.box(1.0, 0.5), mass=MASS),
        ),
        friction=MU,
        h=H,
    )
    sim = Simulator(scene)
    normal = torch.tensor([-torch.sin(torch.tensor(angle)), torch.cos(torch.tensor(angle))])
    centre = (0.1 + 0.25) * normal.to(F64)
    q = torch.tensor([[float(centre[0]), float(centre[1]), angle]], dtype=F64)
    state = sim.initial_state(q=q)
    for _ in range(20):
        result = sim.step(state)
        state = result.state
    torch.testing.assert_close(state.v, torch.zeros(1, 3, dtype=F64), atol=1e-10, rtol=0)
    cos, sin = torch.cos(torch.tensor(angle, dtype=F64)), torch.sin(torch.tensor(angle, dtype=F64))
    # The mode solve's Tikhonov shift (√ε of the Delassus scale) leaves ~1e-8 relative.
    assert float(result.pn.sum()) == pytest.approx(float(MASS * G * H * cos), rel=1e-7)
    friction = (result.pt[:, 0] - result.pt[:, 1]).sum()
    assert abs(float(friction)) == pytest.approx(float(MASS * G * H * sin), rel=1e-7)


def _richardson(fn: Callable[[float], torch.Tensor], step: float) -> torch.Tensor:
    """Derivative at 0 of ``fn`` by central differences extrapolated from steps h and h/2."""

    def central(h: float) -> torch.Tensor:
        return (fn(h) - fn(-h)) / (2 * h)

    return (4 * central(step / 2) - central(step)) / 3


def test_step_gradients_equal_richardson_finite_differences() -> None:
    """A box pushed by a finger along the ground, and one sliding freely, with batch-shaped
    pair friction: gradients of the step's velocities with respect to the friction, the poses
    and the twists, against extrapolated central differences (the modes stay the same under
    the small perturbations)."""
    finger = Polygon.box(0.1, 0.2)
    mu = torch.tensor([0.3, 0.5], dtype=F64, requires_grad=True)

    def scene(friction: torch.Tensor) -> Scene:
        return Scene(
            bodies=(
                Body("ground", HalfPlane.ground(), kind="static"),
                Body("box", Polygon.box(1.0, 0.5), mass=MASS),
                Body("finger", finger, kind="kinematic"),
            ),
            friction=0.4,
            pair_friction={("box", "ground"): friction},
            h=H,
        )

    q = torch.tensor([[[0.0, 0.2499, 0.0]], [[0.1, 0.2498, 0.001]]], dtype=F64)
    v = torch.tensor([[[0.3, 0.0, 0.0]], [[0.2, -0.01, 0.0]]], dtype=F64)
    q_finger = torch.tensor([[[-0.55, 0.2, 0.0]], [[-2.0, 0.2, 0.0]]], dtype=F64)
    control = torch.tensor([[[0.5, 0.0, 0.0]], [[0.4, 0.0, 0.0]]], dtype=F64)
    weights = torch.tensor([[[1.0, 2.0, 3.0]], [[-1.0, 0.5, 2.0]]], dtype=F64)

    def loss(friction: torch.Tensor, q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        sim = Simulator(scene(friction))
        state = sim.initial_state(q=q, v=v, q_kinematic=q_finger)
        result = sim.step(state, control)
        return (result.state.v * weights).sum()

    q_var, v_var = q.clone().requires_grad_(True), v.clone().requires_grad_(True)
    value = loss(mu, q_var, v_var)
    d_mu, d_q, d_v = torch.autograd.grad(value, (mu, q_var, v_var))
    assert abs(float(d_mu[1])) > 1e-3  # friction acts on the free box
    with torch.no_grad():
        for b in range(2):
            direction = torch.zeros(2, dtype=F64)
            direction[b] = 1.0
            fd = _richardson(lambda e, d=direction: loss(mu + e * d, q, v), 1e-5)
            assert float(d_mu[b]) == pytest.approx(float(fd), rel=1e-7, abs=1e-9)
            for k in range(3):
                delta = torch.zeros_like(q)
                delta[b, 0, k] = 1.0
                fd_q = _richardson(lambda e, d=delta: loss(mu, q + e * d, v), 1e-6)
                fd_v = _richardson(lambda e, d=delta: loss(mu, q, v + e * d), 1e-5)
                assert float(d_q[b, 0, k]) == pytest.approx(float(fd_q), rel=1e-6, abs=1e-7)
                assert float(d_v[b, 0, k]) == pytest.approx(float(fd_v), rel=1e-7, abs=1e-9)


def test_per_slot_friction_gradient_equals_richardson_finite_differences() -> None:
    """A box sliding on the ground with per-slot friction: the gradient of its velocity with
    respect to the slots' coefficients (the finger is far away)."""
    sim = _pushing_scene(Polygon.box(0.1, 0.2))
    K = sim.scene.num_slots
    state = sim.initial_state(
        q=torch.tensor([[0.0, 0.25, 0.0]], dtype=F64),
        v=torch.tensor([[1.0, 0.0, 0.0]], dtype=F64),
        q_kinematic=torch.tensor([[-2.0, 0.2, 0.0]], dtype=F64),
    )
    base = torch.full((K,), 0.3, dtype=F64)
    base[1] = 0.5
    friction = base.clone().requires_grad_(True)
    vx = sim.step(state, friction=friction).state.v[0, 0]
    (grad,) = torch.autograd.grad(vx, friction)
    with torch.no_grad():
        for k in range(K):
            direction = torch.zeros(K, dtype=F64)
            direction[k] = 1.0
            fd = _richardson(
                lambda e, d=direction: sim.step(state, friction=base + e * d).state.v[0, 0], 1e-5
            )
            assert float(grad[k]) == pytest.approx(float(fd), abs=1e-9)
    # The bottom corners (slots 0 and 1) carry the weight: dvx/dμ_k = −pn_k / m.
    assert float(grad[:2].sum()) < -0.5 * G * H


def test_float32_steps_follow_float64() -> None:
    sim, state = _grasp_states(8, seed=3)
    narrow = state.map_tensors(lambda t: t.float() if t.is_floating_point() else t)
    wide_run = sim.rollout(state, steps=5, strict=False)
    narrow_run = sim.rollout(narrow, steps=5, strict=False)
    assert narrow_run.q.dtype == torch.float32
    solved = (wide_run.solver != UNSOLVED).all(0) & (narrow_run.solver != UNSOLVED).all(0)
    assert int(solved.sum()) >= 6
    torch.testing.assert_close(
        narrow_run.q[:, solved].double(), wide_run.q[:, solved], atol=2e-4, rtol=0
    )


def test_bad_simulator_options_name_the_argument() -> None:
    sim, _ = _grasp_states(1, seed=0)
    for name, value in (
        ("scene", "a scene"),
        ("fallback", ("newton",)),
        ("active_set_iterations", -1),
        ("retry_sticking", 1),
        ("retry_residual", -1e-6),
    ):
        kwargs = {"scene": sim.scene, name: value}
        with pytest.raises(ValueError, match=rf"^{name}\b"):
            Simulator(**kwargs)  # type: ignore[arg-type]
