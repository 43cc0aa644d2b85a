"""Property tests of the gymnasium environments' inputs: invalid actions and configs raise.

gymnasium's convention is to raise on an invalid action; here it is ``ValueError`` naming the
argument. An action is an integer in ``[0, 7)``: floats (even integral ones), bools, strings,
NaN and out-of-range values are refused, never cast (``2.5`` must not become ``2``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcontact.envs import ACTION_NAMES, PegInHole2D, PegInHole2DVector, PegInHoleConfig

FUZZ = settings(max_examples=60, deadline=None, derandomize=True)
NUM_ACTIONS = len(ACTION_NAMES)

BAD_ACTION = st.one_of(
    st.integers(max_value=-1),
    st.integers(min_value=NUM_ACTIONS),
    st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(),
    st.text(max_size=2),
    st.none(),
    st.lists(st.integers(0, NUM_ACTIONS - 1), min_size=1, max_size=2),
)


@pytest.fixture(scope="module")
def env() -> PegInHole2D:
    environment = PegInHole2D()
    environment.reset(seed=0)
    return environment


@pytest.fixture(scope="module")
def vector() -> PegInHole2DVector:
    environments = PegInHole2DVector(num_envs=2)
    environments.reset(seed=0)
    return environments


@FUZZ
@given(action=BAD_ACTION)
def test_invalid_actions_raise_value_error(env: PegInHole2D, action: Any) -> None:
    with pytest.raises(ValueError, match=r"^action must be an int"):
        env.step(action)


@FUZZ
@given(
    first=st.one_of(
        st.integers(max_value=-1),
        st.integers(min_value=NUM_ACTIONS, max_value=2**40),
        st.floats(allow_nan=True, allow_infinity=True),
        st.text(min_size=1, max_size=1, alphabet="0123456"),
    ),
    second=st.integers(0, NUM_ACTIONS - 1),
)
def test_invalid_vector_actions_raise_value_error(
    vector: PegInHole2DVector, first: Any, second: int
) -> None:
    actions = np.array([first, second]) if not isinstance(first, str) else np.array([first, "1"])
    with pytest.raises(ValueError, match=r"^actions must be 2 ints"):
        vector.step(actions)


def test_vector_actions_of_the_wrong_shape_or_type_raise(vector: PegInHole2DVector) -> None:
    for actions in (np.array([1]), np.array([[1, 2]]), 3, [[1], [1, 2]], np.array([True, False])):
        with pytest.raises(ValueError, match=r"^actions must be 2 ints"):
            vector.step(actions)  # type: ignore[arg-type]


def test_valid_actions_of_any_integer_type_step(
    env: PegInHole2D, vector: PegInHole2DVector
) -> None:
    env.step(np.int64(3))
    env.step(2)
    vector.step(np.array([1, 2], dtype=np.int32))
    vector.step([0, 6])  # type: ignore[arg-type]


@FUZZ
@given(
    name=st.sampled_from(["h", "peg_mass", "peg_width", "friction", "finger_mass", "gravity"]),
    value=st.one_of(
        st.floats(max_value=0.0), st.sampled_from([math.nan, math.inf, "0.1", None, True])
    ),
)
def test_bad_config_values_are_named(name: str, value: Any) -> None:
    with pytest.raises(ValueError, match=rf"^{name} "):
        PegInHoleConfig(**{name: value})


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"observation": "pixels"}, "observation"),
        ({"render_mode": "human"}, "render_mode"),
        ({"config": {"h": 0.01}}, "config"),
    ],
)
def test_bad_constructor_arguments_are_named(kwargs: dict[str, Any], name: str) -> None:
    with pytest.raises(ValueError, match=rf"^{name} "):
        PegInHole2D(**kwargs)
    if name != "render_mode":  # the vector environment does not render
        with pytest.raises(ValueError, match=rf"^{name} "):
            PegInHole2DVector(num_envs=2, **kwargs)
    with pytest.raises(ValueError, match=r"^num_envs "):
        PegInHole2DVector(num_envs=0)
