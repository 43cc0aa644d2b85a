"""Property tests of the robots entry points: every input gives the right answer (checked
against the NumPy DH chain of test_wam) or a ValueError that names the argument at fault;
never another exception type, never a silent NaN/inf."""

from __future__ import annotations

import math
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.robots.test_wam import LOWER, UPPER, dh_frames, dh_jacobian
from torchcontact.robots import ROBOT_NAMES, JointCoupling, Robot, load

FUZZ = settings(max_examples=100, deadline=None, derandomize=True)
WAM = load("wam7")
LINKS = [*WAM.link_names, "nope", "", 5, None]
DTYPES = [torch.float64, torch.float32, torch.float16, torch.bfloat16, torch.int64, torch.complex64]


def attempt(call: Callable[[], Any]) -> tuple[Any, str | None]:
    """``(call(), None)``, or ``(None, message)`` if it raised a ValueError."""
    try:
        return call(), None
    except ValueError as error:
        return None, str(error)


@st.composite
def joint_vectors(draw: st.DrawFn) -> torch.Tensor:
    batch = tuple(draw(st.lists(st.integers(0, 3), max_size=2)))
    dof = draw(st.sampled_from([7, 7, 7, 6, 8]))
    dtype = draw(st.sampled_from(DTYPES))
    u = draw(st.lists(st.floats(0.0, 1.0), min_size=7, max_size=7))
    q = LOWER + (UPPER - LOWER) * np.asarray(u)
    values = torch.tensor(np.resize(q, (*batch, dof)), dtype=torch.float64)
    bad = draw(st.sampled_from([None, math.nan, math.inf]))
    if bad is not None and values.numel():
        values.view(-1)[0] = bad
    return values.to(dtype)


@FUZZ
@given(joint_vectors(), st.sampled_from(LINKS))
def test_forward_kinematics_matches_the_dh_chain_or_names_the_argument(
    q: torch.Tensor, link: object
) -> None:
    transform, message = attempt(lambda: WAM.forward_kinematics(q, link))  # type: ignore[arg-type]
    if message is not None:
        assert message.split()[0].rstrip(":") in {"q", "link"}
        return
    assert q.dtype in (torch.float32, torch.float64)
    assert transform.shape == (*q.shape[:-1], 4, 4)
    assert transform.dtype == q.dtype
    assert bool(torch.isfinite(transform).all())
    if link == "wam_tool":
        flat = q.double().reshape(-1, 7).numpy()
        expected = np.stack([dh_frames(row)[7] for row in flat]).reshape(transform.shape)
        tol = 1e-9 if q.dtype == torch.float64 else 1e-4
        np.testing.assert_allclose(transform.double().numpy(), expected, atol=tol)


@FUZZ
@given(
    joint_vectors(),
    st.sampled_from(LINKS),
    st.sampled_from([None, (3,), (1, 3), (2, 3), (4,), (0, 3)]),
    st.sampled_from([torch.float64, torch.float32, torch.int64]),
)
def test_jacobian_matches_the_dh_jacobian_or_names_the_argument(
    q: torch.Tensor, link: object, point_shape: tuple[int, ...] | None, point_dtype: torch.dtype
) -> None:
    point = None if point_shape is None else torch.full(point_shape, 0.05).to(point_dtype)
    jacobian, message = attempt(lambda: WAM.jacobian(q, link, point=point))  # type: ignore[arg-type]
    if message is not None:
        assert message.split()[0].rstrip(":") in {"q", "link", "point"}
        return
    assert bool(torch.isfinite(jacobian).all())
    assert jacobian.shape[-2:] == (6, 7)
    if link == "wam_tool" and q.dtype == torch.float64:
        flat_q = q.reshape(-1, 7).numpy()
        p = np.zeros(3) if point is None else np.full(3, 0.05)
        for row, value in zip(flat_q, jacobian.reshape(-1, 6, 7).numpy(), strict=False):
            tool = dh_frames(row)[7]
            expected = dh_jacobian(row, tool[:3, :3] @ p + tool[:3, 3])
            np.testing.assert_allclose(value, expected, atol=1e-9)


@FUZZ
@given(
    st.integers(0, 3),
    st.sampled_from(["ok", "nan", "long", "f32", "zero", "skew", "D0"]),
    st.sampled_from(["point", "normal", "tangents"]),
)
def test_contact_jacobian_of_any_batch_or_names_the_argument(
    batch: int, kind: str, target: str
) -> None:
    q = torch.zeros(batch, 7, dtype=torch.float64)
    fields = {
        "point": torch.zeros(batch, 3, dtype=torch.float64),
        "normal": torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(batch, 3),
        "tangents": torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
        .expand(batch, 2, 3)
        .clone(),
    }
    value = fields[target].clone()
    if kind == "nan" and value.numel():
        value.view(-1)[0] = math.nan
    elif kind == "long":
        value = value.long()
    elif kind == "f32":
        value = value.float()
    elif kind == "zero":
        value = torch.zeros_like(value)
    elif kind == "skew" and target != "point":
        value = value + 0.3
    elif kind == "D0" and target == "tangents":
        value = value[..., :0, :]
    fields[target] = value
    result, message = attempt(lambda: WAM.contact_jacobian(q, "wam_tool", **fields))
    if message is not None:
        assert message.split()[0].rstrip(":") in {"point", "normal", "tangents"}
        return
    jn, jt = result
    assert jn.shape == (batch, 7)
    assert jt.shape == (batch, 2, 7)
    assert bool(torch.isfinite(jn).all())
    assert bool(torch.isfinite(jt).all())


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda: load("unknown"), "name"),
        (lambda: load(5), "name"),  # type: ignore[arg-type]
        (lambda: load("wam7", coupled="no"), "coupled"),  # type: ignore[arg-type]
        (lambda: Robot.from_urdf("/nonexistent/robot.urdf"), "path"),
        (lambda: Robot.from_urdf(Path("/")), "path"),
        (lambda: Robot.from_urdf(5), "path"),  # type: ignore[arg-type]
        (lambda: WAM.coupling.to_full("q"), "q"),  # type: ignore[arg-type]
        (lambda: WAM.coupling.to_full(torch.zeros(7, dtype=torch.float16)), "q"),
        (lambda: JointCoupling.identity(5), "full_names"),  # type: ignore[arg-type]
        (lambda: JointCoupling.from_mimic(["a"], 5), "mimic"),  # type: ignore[arg-type]
    ],
)
def test_robot_arguments_are_named(call: Callable[[], object], name: str) -> None:
    with pytest.raises(ValueError, match=name):
        call()


CORRUPTIONS = [
    lambda text: text[: len(text) // 2],
    lambda text: text.replace('type="revolute"', 'type="helical"', 1),
    lambda text: text.replace("<limit", "<nolimit", 1),
    lambda text: text.replace('xyz="0 0 1"', 'xyz="0 0 0"', 1),
    lambda text: text.replace('xyz="0 0 1"', 'xyz="0 nan 1"', 1),
    lambda text: text.replace("<robot", "<robt", 1).replace("</robot>", "</robt>"),
    lambda text: text.replace("<child link=", "<child lnk=", 1),
    lambda text: text.replace("</robot>", '<joint name="x" type="fixed"/></robot>'),
]


@settings(max_examples=40, deadline=None, derandomize=True)
@given(st.sampled_from(ROBOT_NAMES), st.sampled_from(range(len(CORRUPTIONS))))
def test_corrupted_urdf_files_load_or_raise_value_error(name: str, which: int) -> None:
    source = Path(load(name).source)
    text = CORRUPTIONS[which](source.read_text(encoding="utf-8"))
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / f"{name}.urdf"
        path.write_text(text, encoding="utf-8")
        robot, message = attempt(lambda: Robot.from_urdf(path))
    if message is not None:
        return
    q = torch.zeros(robot.dof, dtype=torch.float64)
    assert all(bool(torch.isfinite(t).all()) for t in robot.forward_kinematics(q).values())


def test_empty_batches_have_the_right_shapes() -> None:
    q = torch.zeros(0, 2, 7, dtype=torch.float64)
    assert WAM.forward_kinematics(q, "wam_tool").shape == (0, 2, 4, 4)
    assert WAM.jacobian(q, "wam_tool").shape == (0, 2, 6, 7)
    jn, jt = WAM.contact_jacobian(
        q,
        "wam_tool",
        point=torch.zeros(0, 2, 3, dtype=torch.float64),
        normal=torch.zeros(0, 2, 3, dtype=torch.float64),
        tangents=torch.zeros(0, 2, 1, 3, dtype=torch.float64),
    )
    assert jn.shape == (0, 2, 7)
    assert jt.shape == (0, 2, 1, 7)
