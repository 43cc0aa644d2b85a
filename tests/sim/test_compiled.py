"""``Simulator(compiled=True)``: the compiled step at the previous modes gives the eager step's
results to rounding, and an entry whose previous modes are wrong goes through the eager path.

Each test compiles the step once (tens of seconds on a CPU). Tolerances: the compiled step
solves the uncompacted problem (all ``K`` slots, in slot order) with fused loops, so its
results differ from the eager step's by rounding amplified by the conditioning of the
mode-decoupled system; velocities and poses, unique whatever the impulse split, agree to
1e-10 relative (absolute: 1e-10 of the 0.1–1 m/s velocity scale; observed ~1e-13);
impulses, whose split on redundant contacts is set by the Tikhonov regularisation
(ε = √eps · max|diag A|, which amplifies rounding by up to 1/√eps: √eps ≈ 1.5e-8 of the
largest impulse at worst), to 1e-7 of the largest impulse (observed ~1e-12).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import torch

from torchcontact.envs import PegInHoleConfig, PegInHoleTask
from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import SOLVED_BY_GUESS, Body, Scene, SceneState, Simulator

F64 = torch.float64


def _count_eager_steps(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """A list that grows by one at every eager step (``Simulator._step_compacted``)."""
    calls: list[int] = []
    eager = Simulator._step_compacted

    def counted(self: Simulator, *args: Any) -> Any:
        calls.append(1)
        return eager(self, *args)

    monkeypatch.setattr(Simulator, "_step_compacted", counted)
    return calls


def _boxes(batch: int, seed: int) -> tuple[Simulator, SceneState]:
    """Boxes on the ground: sliding, tipping over a corner and resting, perturbed."""
    scene = Scene(
        bodies=(
            Body("ground", HalfPlane.ground(), kind="static"),
            Body("box", Polygon.box(1.0, 0.5), mass=2.0),
        ),
        friction=0.5,
        h=0.01,
    )
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
    return Simulator(scene), Simulator(scene).initial_state(q=q, v=v)


def _assert_same(actual: Any, expected: Any) -> None:
    """Poses, twists and modes of two states (or rollouts)."""
    torch.testing.assert_close(actual.q, expected.q, rtol=1e-10, atol=1e-11)
    torch.testing.assert_close(actual.v, expected.v, rtol=1e-10, atol=1e-11)
    torch.testing.assert_close(actual.mode, expected.mode, rtol=0, atol=0)


def _assert_impulses(actual: torch.Tensor, expected: torch.Tensor, largest: torch.Tensor) -> None:
    """Impulses to 1e-7 of the largest normal impulse."""
    scale = 1e-7 * float(largest.abs().max())
    torch.testing.assert_close(actual, expected, rtol=0.0, atol=scale)


def test_compiled_box_rollouts_equal_eager(monkeypatch: pytest.MonkeyPatch) -> None:
    """Seeded rollouts of sliding, tipping and resting boxes; then a batch half of whose
    entries have wrong previous modes (every slot sliding the wrong way): those take the eager
    step (one call, on them), with the same answers."""
    calls = _count_eager_steps(monkeypatch)
    steps = 40
    for seed in (0, 1):
        eager, state = _boxes(6, seed)
        compiled = replace(eager, compiled=True)
        expected = eager.rollout(state, steps=steps)
        before = len(calls)
        actual = compiled.rollout(state, steps=steps)
        # The eager rollout steps eagerly every time; the compiled one only where the
        # previous modes fail (the first step, from separated, and mode changes).
        assert len(calls) - before < steps // 2
        _assert_same(actual, expected)
        _assert_impulses(actual.pn, expected.pn, expected.pn)
        _assert_impulses(actual.pt, expected.pt, expected.pn)
        torch.testing.assert_close(actual.solver, expected.solver, rtol=0, atol=0)

    # Boxes after a few steps, half of them given wrong previous modes.
    settled = eager.rollout(state, steps=5)
    last = SceneState(
        q=settled.q[-1], v=settled.v[-1], q_kinematic=settled.q_kinematic[-1], mode=settled.mode[-1]
    )
    flipped = torch.where(last.mode == 2, 3, 2)
    wrong = replace(last, mode=torch.where(torch.arange(6)[:, None] < 3, flipped, last.mode))
    before = len(calls)
    actual = compiled.step(wrong)
    assert len(calls) - before == 1
    assert bool((actual.solver[3:] == SOLVED_BY_GUESS).all())
    expected = eager.step(wrong)
    _assert_same(actual.state, expected.state)
    _assert_impulses(actual.pn, expected.pn, expected.pn)
    _assert_impulses(actual.pt, expected.pt, expected.pn)


def test_compiled_peg_in_hole_equals_eager(monkeypatch: pytest.MonkeyPatch) -> None:
    """The peg-in-hole task (a grasped peg, a dozen candidate slots) reset and moved by a few
    actions, with the eager and the compiled simulator."""
    calls = _count_eager_steps(monkeypatch)
    task = PegInHoleTask(PegInHoleConfig())
    rng = np.random.default_rng(0)
    samples = torch.from_numpy(np.stack([task.sample_start(rng) for _ in range(4)]))
    actions = torch.from_numpy(rng.integers(0, len(task.action_deltas), size=(3, 4)))
    runs = []
    for compiled in (False, True):
        task.simulator = replace(task.simulator, compiled=compiled)
        before = len(calls)
        physics = [task.reset(samples)]
        for action in actions:
            physics.append(task.step(physics[-1], action))
        runs.append((physics, len(calls) - before))
    (expected, eager_calls), (actual, compiled_calls) = runs
    assert compiled_calls < eager_calls
    for a, e in zip(actual, expected, strict=True):
        _assert_same(a.state, e.state)
        _assert_impulses(a.pn, e.pn, e.pn)


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


def test_compiled_must_be_a_bool() -> None:
    eager, _ = _boxes(1, 0)
    with pytest.raises(ValueError, match="compiled: expected a bool"):
        Simulator(eager.scene, compiled=1)  # type: ignore[arg-type]
