"""CompactSimulator against the reference Simulator: same geometry, same step, to round-off."""

from __future__ import annotations

import pytest
import torch

from torchcontact.envs import CompactSimulator, PegInHoleConfig, build_scene
from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import UNSOLVED, Body, Scene, SceneState, Simulator, contact_problem


def peg_scene() -> Scene:
    return build_scene(PegInHoleConfig())[0]


def grasp_states(scene: Scene, batch: int, seed: int) -> SceneState:
    """Perturbed poses of a peg held between two fingers above the hole (many contacts)."""
    _, pad_offset = build_scene(PegInHoleConfig())
    generator = torch.Generator().manual_seed(seed)
    half_width = PegInHoleConfig().peg_width / 2
    x = 0.04 * torch.rand(batch, generator=generator, dtype=torch.float64) - 0.02
    y = 0.11 + 0.03 * torch.rand(batch, generator=generator, dtype=torch.float64)
    centre = torch.stack([x, y, torch.zeros_like(x)], dim=-1)
    offset = torch.tensor(
        [
            [0.0, 0.0, 0.0],
            [-half_width - pad_offset, 0.04, 0.0],
            [half_width + pad_offset, 0.04, 0.0],
        ],
        dtype=torch.float64,
    )
    q = centre[:, None, :] + offset
    q = q + 0.002 * torch.randn(q.shape, generator=generator, dtype=torch.float64)
    v = 0.2 * torch.randn(q.shape, generator=generator, dtype=torch.float64)
    return Simulator(scene).initial_state(q=q, v=v)


def test_geometry_matches_the_simulators_assembly() -> None:
    scene = peg_scene()
    state = grasp_states(scene, 32, seed=0)
    _, reference = contact_problem(scene, state)
    geometry = CompactSimulator(scene).geometry(state)
    for name in ("points", "normals", "phi"):
        torch.testing.assert_close(
            getattr(geometry, name), getattr(reference, name), atol=1e-14, rtol=0
        )
    assert torch.equal(geometry.active, reference.active)
    assert int(reference.active.sum()) > 4 * 32  # the grasp: several candidates per entry


@pytest.mark.filterwarnings("ignore:OSQP exited:UserWarning")
def test_step_matches_simulator_step_from_the_same_states() -> None:
    scene = peg_scene()
    reference, compact = Simulator(scene), CompactSimulator(scene, retry_sticking=False)
    state = grasp_states(scene, 24, seed=1)
    generator = torch.Generator().manual_seed(2)
    exact = 0
    for _ in range(5):
        force = 3.0 * torch.randn(state.q.shape, generator=generator, dtype=torch.float64)
        expected = reference.step(state, force=force)
        actual = compact.step(state, force=force)
        assert torch.equal(actual.solver, expected.solver)
        # Where no solver converged the step holds no solution, only the last attempt.
        solved = expected.solver != UNSOLVED
        # Relative to the state's size: an unwrapped angle of a spinning body reaches
        # hundreds of radians, whose last digits differ with the CPU's kernels.
        for name in ("q", "v"):
            torch.testing.assert_close(
                getattr(actual.state, name)[solved],
                getattr(expected.state, name)[solved],
                atol=1e-10,
                rtol=1e-10,
            )
        torch.testing.assert_close(actual.pn[solved], expected.pn[solved], atol=1e-10, rtol=1e-10)
        torch.testing.assert_close(actual.pt[solved], expected.pt[solved], atol=1e-10, rtol=1e-10)
        assert torch.equal(actual.mode[solved], expected.mode[solved])
        exact += int((expected.solver > 0).sum())
        state = expected.state
    assert exact > 10  # the fallback path (Lemke, re-solve) was exercised, not only guesses


def test_kinematic_bodies_enter_through_the_known_velocity_terms() -> None:
    """A finger driven by its twist pushes a box: the step equals the simulator's."""
    scene = Scene(
        bodies=(
            Body("ground", HalfPlane.ground(), kind="static"),
            Body("box", Polygon.box(1.0, 0.5), mass=2.0),
            Body("finger", Polygon.box(0.1, 0.3), kind="kinematic"),
            Body(
                "wall", Polygon.regular(5, 0.3), kind="static", pose=torch.tensor([2.0, 0.3, 0.1])
            ),
        ),
        friction=0.4,
        h=0.01,
    )
    q = torch.tensor([[[0.0, 0.25, 0.0]], [[0.3, 0.26, 0.05]]], dtype=torch.float64)
    q_finger = torch.tensor([[[-0.55, 0.2, 0.0]], [[-0.26, 0.2, 0.1]]], dtype=torch.float64)
    control = torch.tensor([[[0.3, 0.0, 0.0]], [[0.5, -0.1, 0.4]]], dtype=torch.float64)
    reference, compact = Simulator(scene), CompactSimulator(scene, retry_sticking=False)
    state = reference.initial_state(q=q, q_kinematic=q_finger)
    for _ in range(20):
        expected = reference.step(state, control)
        actual = compact.step(state, control)
        torch.testing.assert_close(actual.state.q, expected.state.q, atol=1e-12, rtol=0)
        torch.testing.assert_close(
            actual.state.q_kinematic, expected.state.q_kinematic, atol=1e-15, rtol=0
        )
        # Impulse splits among redundant contacts converge to ~1e-10 relative.
        torch.testing.assert_close(actual.pn, expected.pn, atol=1e-9, rtol=0)
        assert torch.equal(actual.mode, expected.mode)
        state = expected.state
    assert float(state.q[0, 0, 0]) > 0.05  # the finger did push the box


def test_bad_arguments_name_the_argument() -> None:
    scene = peg_scene()
    compact = CompactSimulator(scene)
    state = grasp_states(scene, 2, seed=0)
    with pytest.raises(ValueError, match="force"):
        compact.step(state, force=torch.zeros(2, 2, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="control"):
        compact.step(state, torch.zeros(2, 1, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"state\.q"):
        compact.step(state.map_tensors(lambda t: t[0]))
    with pytest.raises(ValueError, match="scene"):
        CompactSimulator("not a scene")  # type: ignore[arg-type]
