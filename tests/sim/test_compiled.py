"""``Simulator(compiled=True)`` on boxes: the compiled step at the previous modes, corrected by
the active-set iteration's kernel calls, against closed-form physics and against the eager step
(the peg grasp, the scene that broke its first version: ``test_compiled_peg.py``).

Tolerances: the compiled step fuses loops and orders its slots differently, so its results differ
from the eager step's by rounding amplified by the conditioning of the mode-decoupled system.
Velocities and poses, unique whatever the impulse split, agree to 1e-10 relative (1e-11 absolute,
of a 0.1–1 m/s scale). Impulses, whose split on redundant contacts is set by the Tikhonov
regularisation (ε = √eps · max|diag A|, which amplifies rounding by up to 1/√eps), agree to 1e-7
of the largest normal impulse.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import pytest
import torch

from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import (
    SOLVED_BY_GUESS,
    Body,
    Scene,
    SceneState,
    Simulator,
)

F64 = torch.float64
G, H, MASS, MU = 9.81, 0.01, 2.0, 0.5


def _count_eager_steps(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """A list that grows at every eager step (``Simulator._step_compacted``) by the number of
    scenes that step takes."""
    calls: list[int] = []
    eager = Simulator._step_compacted

    def counted(self: Simulator, state: SceneState, *args: Any) -> Any:
        calls.append(math.prod(state.batch_shape))
        return eager(self, state, *args)

    monkeypatch.setattr(Simulator, "_step_compacted", counted)
    return calls


def _box_scene() -> Scene:
    return Scene(
        bodies=(
            Body("ground", HalfPlane.ground(), kind="static"),
            Body("box", Polygon.box(1.0, 0.5), mass=MASS),
        ),
        friction=MU,
        h=H,
    )


def _boxes(batch: int, seed: int) -> tuple[Simulator, SceneState]:
    """Boxes on the ground, sliding, tipping over a corner and resting, perturbed."""
    sim = Simulator(_box_scene())
    generator = torch.Generator().manual_seed(seed)
    kind = torch.arange(batch) % 3
    theta = torch.where(kind == 1, 1.2, 0.0).to(F64)
    theta = theta + 0.05 * torch.rand(batch, generator=generator, dtype=F64)
    corner = torch.tensor([-0.5, -0.25], dtype=F64)
    cos, sin = torch.cos(theta), torch.sin(theta)
    x = -(cos * corner[0] - sin * corner[1])
    y = -(sin * corner[0] + cos * corner[1])
    q = torch.stack([x, y, theta], dim=-1).unsqueeze(1)
    v = torch.zeros(batch, 1, 3, dtype=F64)
    v[:, 0, 0] = torch.where(kind == 0, 0.5 + torch.rand(batch, generator=generator), 0.0)
    return sim, sim.initial_state(q=q, v=v)


def _assert_same(actual: Any, expected: Any, *, atol: float = 1e-11) -> None:
    """Poses, twists and modes of two states (or rollouts)."""
    torch.testing.assert_close(actual.q, expected.q, rtol=1e-10, atol=atol)
    torch.testing.assert_close(actual.v, expected.v, rtol=1e-10, atol=atol)
    # Modes are integers: exact.
    assert bool((actual.mode == expected.mode).all())


def _assert_impulses(actual: torch.Tensor, expected: torch.Tensor, largest: torch.Tensor) -> None:
    """Impulses to 1e-7 of the largest normal impulse."""
    scale = 1e-7 * float(largest.abs().max())
    torch.testing.assert_close(actual, expected, rtol=0.0, atol=scale)


@pytest.mark.slow  # compiles the step: minutes on a CPU
def test_compiled_boxes_follow_closed_form_physics(monkeypatch: pytest.MonkeyPatch) -> None:
    """A box sliding at 1 m/s (decelerates at μg, stops when predicted), one resting (no
    drift, carries its weight) and one falling freely (semi-implicit Euler: ``v_k = −g h k``,
    ``y_k = y_0 − g h² k (k + 1) / 2``), one batch, stepped compiled. The mode changes are
    the active-set iteration's kernel calls, the sliding box's first step included (its
    corners close while slipping, so they start sliding): no step is eager."""
    calls = _count_eager_steps(monkeypatch)
    sim = Simulator(_box_scene(), compiled=True)
    q = torch.tensor([[[0.0, 0.25, 0.0]], [[3.0, 0.25, 0.0]], [[6.0, 2.0, 0.0]]], dtype=F64)
    v = torch.zeros(3, 1, 3, dtype=F64)
    v[0, 0, 0] = 1.0
    steps = 30
    with torch.no_grad():
        run = sim.rollout(sim.initial_state(q=q, v=v), steps=steps)
    k = torch.arange(steps + 1, dtype=F64)
    sliding = (1.0 - MU * G * H * k).clamp(min=0.0)
    torch.testing.assert_close(run.v[:, 0, 0, 0], sliding, atol=1e-9, rtol=0)
    assert float(run.v[:, 1].abs().max()) < 1e-10
    torch.testing.assert_close(run.q[:, 1], q[1].expand(steps + 1, 1, 3), atol=1e-10, rtol=0)
    # The resting box's weight over a step, m g h, on its two bottom corners.
    torch.testing.assert_close(
        run.pn[:, 1].sum(-1), torch.full((steps,), MASS * G * H, dtype=F64), atol=1e-10, rtol=0
    )
    torch.testing.assert_close(run.v[:, 2, 0, 1], -G * H * k, atol=1e-10, rtol=0)
    torch.testing.assert_close(
        run.q[:, 2, 0, 1], 2.0 - G * H**2 * k * (k + 1) / 2, atol=1e-10, rtol=0
    )
    assert bool((run.solver == SOLVED_BY_GUESS).all())
    assert calls == []


@pytest.mark.slow  # compiles the step: minutes on a CPU
def test_compiled_box_pushed_by_a_kinematic_finger_slides_at_its_speed() -> None:
    """One scene, unbatched, pushed at a constant speed u by a frictionless kinematic finger
    (the ``control`` input of the kernel): the box ends up sliding at u; the ground's normal
    impulse per step is m g h, the finger's the ground's friction μ m g h."""
    scene = Scene(
        bodies=(
            Body("ground", HalfPlane.ground(), kind="static"),
            Body("box", Polygon.box(1.0, 0.5), mass=MASS),
            Body("finger", Polygon.box(0.1, 0.8), kind="kinematic"),
        ),
        friction=MU,
        pair_friction={("box", "finger"): 0.0},
        h=H,
    )
    sim = Simulator(scene, compiled=True)
    speed = 0.4
    state = sim.initial_state(
        q=torch.tensor([[0.0, 0.25, 0.0]], dtype=F64),
        q_kinematic=torch.tensor([[-0.56, 0.3, 0.0]], dtype=F64),
    )
    control = torch.tensor([[speed, 0.0, 0.0]], dtype=F64)
    solver = []
    with torch.no_grad():
        for _ in range(60):
            result = sim.step(state, control)
            state = result.state
            solver.append(int(result.solver))
    torch.testing.assert_close(
        state.v[0], torch.tensor([speed, 0.0, 0.0], dtype=F64), atol=1e-9, rtol=0
    )
    support, pushing = [
        sum(result.pn[group.start : group.start + group.count].sum() for group in groups)
        for groups in (
            [g for g in scene.slot_groups if {g.receiver, g.other} == {0, 1}],
            [g for g in scene.slot_groups if {g.receiver, g.other} == {1, 2}],
        )
    ]
    assert float(support) == pytest.approx(MASS * G * H, rel=1e-9)
    assert float(pushing) == pytest.approx(MU * MASS * G * H, rel=1e-9)
    assert solver[-30:] == [SOLVED_BY_GUESS] * 30  # the compiled kernel carries the push


@pytest.mark.slow  # compiles the step for several numbers of active slots: minutes on a CPU
def test_compiled_box_rollouts_equal_eager(monkeypatch: pytest.MonkeyPatch) -> None:
    """Seeded rollouts of sliding, tipping and resting boxes; then a batch half of whose
    entries have wrong previous modes (every slot sliding the wrong way): the entries that the
    eager step's active-set iteration corrects, the compiled step corrects by the kernel's
    calls on them (all of them with the full iteration count); the others (all three with no
    iterations allowed) take the eager step (one call, on them alone); the same answers either
    way."""
    calls = _count_eager_steps(monkeypatch)
    steps = 40
    for seed in (0, 1):
        eager, state = _boxes(6, seed)
        compiled = replace(eager, compiled=True)
        expected = eager.rollout(state, steps=steps)
        before = len(calls)
        actual = compiled.rollout(state, steps=steps)
        # The eager rollout steps eagerly every time; the compiled one only where the
        # active-set iteration's kernel calls leave a mode inconsistent.
        assert len(calls) - before < steps // 4
        _assert_same(actual, expected)
        _assert_impulses(actual.pn, expected.pn, expected.pn)
        _assert_impulses(actual.pt, expected.pt, expected.pn)
        assert bool((actual.solver == expected.solver).all())

    settled = eager.rollout(state, steps=5)
    last = SceneState(
        q=settled.q[-1], v=settled.v[-1], q_kinematic=settled.q_kinematic[-1], mode=settled.mode[-1]
    )
    flipped = torch.where(last.mode == 2, 3, 2)
    wrong = replace(last, mode=torch.where(torch.arange(6)[:, None] < 3, flipped, last.mode))
    for iterations, unsolved in ((compiled.active_set_iterations, 0), (0, 3)):
        expected = replace(eager, active_set_iterations=iterations).step(wrong)
        # The entries the eager step's active set leaves to the exact solvers (codes 1, 2).
        assert int((expected.solver != SOLVED_BY_GUESS).sum()) == unsolved
        before = len(calls)
        actual = replace(compiled, active_set_iterations=iterations).step(wrong)
        assert calls[before:] == ([unsolved] if unsolved else [])
        assert bool((actual.solver == expected.solver).all())
        _assert_same(actual.state, expected.state)
        _assert_impulses(actual.pn, expected.pn, expected.pn)
        _assert_impulses(actual.pt, expected.pt, expected.pn)


def test_compiled_steps_with_gradients_run_eagerly(monkeypatch: pytest.MonkeyPatch) -> None:
    """With an input that requires grad the step is the eager one (no compilation), and its
    gradient reaches the input."""
    calls = _count_eager_steps(monkeypatch)
    eager, state = _boxes(3, 0)
    compiled = replace(eager, compiled=True)
    state = eager.rollout(state, steps=2)
    q = state.q[-1].clone().requires_grad_(True)
    start = SceneState(q=q, v=state.v[-1], q_kinematic=state.q_kinematic[-1], mode=state.mode[-1])
    calls.clear()
    result = compiled.step(start)
    assert len(calls) == 1
    result.state.q.sum().backward()
    assert q.grad is not None
    assert bool(torch.isfinite(q.grad).all())


@pytest.mark.parametrize("value", [1, "yes", None])
def test_compiled_must_be_a_bool(value: object) -> None:
    with pytest.raises(ValueError, match="compiled must be a bool"):
        Simulator(_box_scene(), compiled=value)  # type: ignore[arg-type]
