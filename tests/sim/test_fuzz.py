"""Property tests of the simulator's entry points: right shapes and answers, or a ValueError.

Every bad argument (wrong dtype, shape, NaN/inf, dtype mix, negative physical parameter) must
raise ``ValueError`` whose message starts with the argument's name; empty batches and zero
steps are legal and give empty results of the documented shapes.
"""

from __future__ import annotations

import math
from typing import Any

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import Body, Scene, Simulator, penetration

FUZZ = settings(max_examples=40, deadline=None, derandomize=True)


def _scene(**kwargs: Any) -> Scene:
    """A box on the ground and a kinematic finger: ``Nd = Nk = 1``, ``K = 4 + 4 + 4``."""
    return Scene(
        bodies=(
            Body("ground", HalfPlane.ground(), kind="static"),
            Body("box", Polygon.box(1.0, 0.5), mass=2.0),
            Body("finger", Polygon.box(0.1, 0.1), kind="kinematic"),
        ),
        **kwargs,
    )


SCENE = _scene()
SIM = Simulator(SCENE)
K = SCENE.num_slots


def _spoil(value: torch.Tensor, how: str) -> Any:
    """A damaged copy: NaN/inf entry, wrong dtype, wrong shape, or a list."""
    if how in ("nan", "inf"):
        bad = value.clone()
        bad.view(-1)[0] = math.nan if how == "nan" else math.inf
        return bad
    if how == "shape":
        return value[..., :2]
    if how == "list":
        return value.tolist()
    dtypes = {"int": torch.long, "half": torch.float16, "complex": torch.complex128}
    return value.to(dtypes.get(how, torch.float32))


def _expected(which: str, how: str) -> str:
    """The message expected: it names ``which``, or, for a float32 ``q`` among float64
    arguments, the first argument whose dtype differs from ``q``'s (``q`` is the reference)."""
    if which == "q" and how == "f32":
        return r"^(v|q_kinematic) must have the dtype and device of q"
    return rf"^{which}\b"


HOW = st.sampled_from(["nan", "inf", "shape", "list", "int", "half", "complex", "f32"])


def _poses(batch: int) -> tuple[torch.Tensor, torch.Tensor]:
    q = torch.tensor([0.0, 0.25, 0.0], dtype=torch.float64).expand(batch, 1, 3).clone()
    q_kinematic = torch.tensor([2.0, 2.0, 0.0], dtype=torch.float64).expand(batch, 1, 3).clone()
    return q, q_kinematic


@FUZZ
@given(batch=st.integers(1, 3), how=HOW, which=st.sampled_from(["q", "q_kinematic"]))
def test_penetration_names_a_bad_pose(batch: int, how: str, which: str) -> None:
    q, q_kinematic = _poses(batch)
    poses = {"q": q, "q_kinematic": q_kinematic}
    poses[which] = _spoil(poses[which], how)
    with pytest.raises(ValueError, match=_expected(which, how)):
        penetration(SCENE, **poses)


@FUZZ
@given(batch=st.integers(1, 3), how=HOW, which=st.sampled_from(["q", "v", "q_kinematic"]))
def test_initial_state_names_a_bad_argument(batch: int, how: str, which: str) -> None:
    q, q_kinematic = _poses(batch)
    arguments = {"q": q, "v": torch.zeros_like(q), "q_kinematic": q_kinematic}
    arguments[which] = _spoil(arguments[which], how)
    with pytest.raises(ValueError, match=_expected(which, how)):
        SIM.initial_state(**arguments)


@FUZZ
@given(
    batch=st.integers(1, 2),
    how=HOW,
    which=st.sampled_from(["control", "force", "friction"]),
)
def test_step_names_a_bad_control(batch: int, how: str, which: str) -> None:
    q, q_kinematic = _poses(batch)
    state = SIM.initial_state(q=q, q_kinematic=q_kinematic)
    good = {
        "control": torch.zeros(batch, 1, 3, dtype=torch.float64),
        "force": torch.zeros(batch, 1, 3, dtype=torch.float64),
        "friction": torch.full((batch, K), 0.5, dtype=torch.float64),
    }
    arguments = {which: _spoil(good[which], how)}
    with pytest.raises(ValueError, match=rf"^{which}\b"):
        SIM.step(state, **arguments)


@FUZZ
@given(
    density=st.one_of(st.floats(max_value=0.0), st.sampled_from([math.nan, math.inf])),
    friction=st.one_of(st.floats(max_value=-1e-12), st.sampled_from([math.nan, math.inf])),
    h=st.one_of(st.floats(max_value=0.0), st.sampled_from([math.nan, "0.01"])),
    mass=st.floats(max_value=0.0),
)
def test_negative_physical_parameters_are_named(
    density: float, friction: float, h: Any, mass: float
) -> None:
    with pytest.raises(ValueError, match=r"^density\b"):
        Body("b", Polygon.box(1.0, 0.5), density=density)
    with pytest.raises(ValueError, match=r"^mass\b"):
        Body("b", Polygon.box(1.0, 0.5), mass=mass)
    with pytest.raises(ValueError, match=r"^mass\b"):
        Body("b", Polygon.box(1.0, 0.5), mass=torch.tensor(mass))
    with pytest.raises(ValueError, match=r"^friction\b"):
        _scene(friction=friction)
    with pytest.raises(ValueError, match=r"^friction\b"):
        _scene(friction=torch.tensor([friction]))
    with pytest.raises(ValueError, match=r"^pair_friction\["):
        _scene(pair_friction={("box", "ground"): friction})
    with pytest.raises(ValueError, match=r"^h\b"):
        _scene(h=h)
    q, q_kinematic = _poses(1)
    state = SIM.initial_state(q=q, q_kinematic=q_kinematic)
    if not math.isnan(friction):
        with pytest.raises(ValueError, match=r"^friction\b"):
            SIM.step(state, friction=torch.full((1, K), friction, dtype=torch.float64))


def test_penetration_reports_the_documented_findings() -> None:
    """A NaN finger or body pose, or a float32/float64 mix, is an error, not a quiet answer."""
    q, q_kinematic = _poses(1)
    with pytest.raises(ValueError, match=r"^q_kinematic contains NaN"):
        penetration(SCENE, q=q, q_kinematic=q_kinematic * math.nan)
    with pytest.raises(ValueError, match=r"^q contains NaN"):
        penetration(SCENE, q=q * math.nan, q_kinematic=q_kinematic)
    with pytest.raises(ValueError, match=r"^q_kinematic must have the dtype"):
        penetration(SCENE, q=q.float(), q_kinematic=q_kinematic)
    with pytest.raises(ValueError, match="float32 or float64"):
        SIM.initial_state(q=q.half(), q_kinematic=q_kinematic.half())


@pytest.mark.parametrize("batch", [(0,), (2, 0)])
def test_empty_batches_step_and_roll_out(batch: tuple[int, ...]) -> None:
    q = torch.zeros(*batch, 1, 3, dtype=torch.float64)
    state = SIM.initial_state(q=q, q_kinematic=q.clone())
    result = SIM.step(state, torch.zeros(*batch, 1, 3, dtype=torch.float64))
    assert result.state.q.shape == (*batch, 1, 3)
    assert result.pn.shape == (*batch, K)
    assert result.solver.shape == batch
    rollout = SIM.rollout(state, steps=3)
    assert rollout.q.shape == (4, *batch, 1, 3)
    assert rollout.pt.shape == (3, *batch, K, 2)
    phi, Jn, penetrating = penetration(SCENE, q=q, q_kinematic=q.clone())
    assert phi.shape == (*batch, K)
    assert Jn.shape == (*batch, K, 3)
    assert penetrating.shape == (*batch, K)


@pytest.mark.bitwise("a rollout of zero steps returns the initial poses untouched")
def test_rollout_of_zero_steps_is_the_initial_state() -> None:
    q, q_kinematic = _poses(2)
    state = SIM.initial_state(q=q, q_kinematic=q_kinematic)
    rollout = SIM.rollout(state, steps=0)
    torch.testing.assert_close(rollout.q, q.unsqueeze(0), rtol=0, atol=0)
    assert rollout.pn.shape == (0, 2, K)
    assert rollout.mode.dtype == torch.long
    assert rollout.active.dtype == torch.bool
    assert rollout.solver.shape == (0, 2)
    for steps, name in ((-1, "steps"), (1.5, "steps")):
        with pytest.raises(ValueError, match=rf"^{name}"):
            SIM.rollout(state, steps=steps)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"^controls"):
        SIM.rollout(state, steps=2, controls=torch.zeros(2, 2, 1, 3, dtype=torch.float32))


def test_free_fall_of_one_step_matches_closed_form() -> None:
    """Far from everything: v⁺ = v + h g and q⁺ = q + h v⁺ (semi-implicit Euler)."""
    q = torch.tensor([[[5.0, 10.0, 0.3]]], dtype=torch.float64)
    v = torch.tensor([[[1.0, -2.0, 0.5]]], dtype=torch.float64)
    q_kinematic = torch.tensor([[[-5.0, 10.0, 0.0]]], dtype=torch.float64)
    result = SIM.step(SIM.initial_state(q=q, v=v, q_kinematic=q_kinematic))
    expected_v = v + SCENE.h * torch.tensor([0.0, -9.81, 0.0], dtype=torch.float64)
    torch.testing.assert_close(result.state.v, expected_v, rtol=0, atol=1e-12)
    torch.testing.assert_close(result.state.q, q + SCENE.h * expected_v, rtol=0, atol=1e-12)


@FUZZ
@given(
    bad=st.one_of(
        st.floats(max_value=0.0), st.sampled_from([math.nan, math.inf, -math.inf, "1", None])
    )
)
def test_shape_constructors_name_a_bad_size(bad: Any) -> None:
    for build, name in (
        (lambda: Polygon.box(bad, 1.0), "width"),
        (lambda: Polygon.box(1.0, bad), "height"),
        (lambda: Polygon.triangle(bad, 1.0), "base"),
        (lambda: Polygon.regular(5, bad), "radius"),
        (lambda: Polygon.regular(bad, 1.0), "sides"),
    ):
        with pytest.raises(ValueError, match=rf"^{name}\b"):
            build()
    if not isinstance(bad, float) or not math.isfinite(bad):
        with pytest.raises(ValueError, match=r"^angle\b"):
            HalfPlane.ground(angle=bad)


@pytest.mark.parametrize("how", ["nan", "int", "half", "complex", "list", "shape"])
def test_polygon_and_halfplane_name_bad_tensors(how: str) -> None:
    square = Polygon.box(1.0, 1.0).vertices
    point = torch.zeros(2, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^vertices\b"):
        Polygon(square.T.contiguous() if how == "shape" else _spoil(square, how))
    with pytest.raises(ValueError, match=r"^point\b"):
        HalfPlane(torch.zeros(3) if how == "shape" else _spoil(point, how), point + 1.0)
