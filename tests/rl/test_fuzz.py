"""Property tests of the rl entry points: every input gives the right answer or a ValueError
that names the argument at fault; never another exception type, never a silent NaN/inf."""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcontact.rl import (
    DynaQ,
    QNetwork,
    ReplayBuffer,
    Transitions,
    dqn_loss,
    qmdp_action,
    qmdp_values,
    update_target,
)

FUZZ = settings(max_examples=100, deadline=None, derandomize=True)
BAD_DTYPES = [torch.float16, torch.bfloat16, torch.int64, torch.int32, torch.bool, torch.complex64]


def attempt(call: Callable[[], Any]) -> tuple[Any, str | None]:
    """``(call(), None)``, or ``(None, message)`` if it raised a ValueError."""
    try:
        return call(), None
    except ValueError as error:
        return None, str(error)


def value_error_or(call: Callable[[], Any], name: str) -> Any:
    """``call()``, or ``None`` if it raised a ValueError whose message names ``name``."""
    result, message = attempt(call)
    assert message is None or name in message, f"{message!r} does not name {name!r}"
    return result


# ----------------------------------------------------------------------------------- QMDP


def _belief(draw: st.DrawFn, batch: tuple[int, ...], K: int, dtype: torch.dtype) -> torch.Tensor:
    weights = draw(
        st.lists(st.floats(0.0, 10.0), min_size=math.prod(batch) * K, max_size=math.prod(batch) * K)
    )
    w = np.asarray(weights, dtype=np.float64).reshape(*batch, K) + 1e-3
    return torch.tensor(w / w.sum(-1, keepdims=True), dtype=dtype)


@st.composite
def qmdp_inputs(draw: st.DrawFn) -> tuple[torch.Tensor, torch.Tensor]:
    K, A = draw(st.integers(1, 5)), draw(st.integers(1, 4))
    batch = tuple(draw(st.lists(st.integers(0, 3), max_size=2)))
    dtype = draw(st.sampled_from([torch.float32, torch.float64]))
    q = draw(st.lists(st.floats(-1e3, 1e3), min_size=K * A, max_size=K * A))
    return torch.tensor(q, dtype=dtype).reshape(K, A), _belief(draw, batch, K, dtype)


@FUZZ
@given(qmdp_inputs())
def test_qmdp_matches_numpy_argmax_of_the_weighted_sum(
    inputs: tuple[torch.Tensor, torch.Tensor],
) -> None:
    q, p = inputs
    values = qmdp_values(q, p)
    reference = p.double().numpy() @ q.double().numpy()
    assert values.shape == (*p.shape[:-1], q.shape[1])
    tol = 1e-9 if q.dtype == torch.float64 else 1e-2
    np.testing.assert_allclose(values.double().numpy(), reference, atol=tol, rtol=1e-5)
    actions = qmdp_action(q, p)
    assert actions.shape == p.shape[:-1]
    assert actions.dtype == torch.long
    picked = np.take_along_axis(reference, actions.numpy()[..., None], -1)[..., 0]
    np.testing.assert_allclose(picked, reference.max(-1) if reference.size else picked, atol=tol)


@FUZZ
@given(qmdp_inputs(), st.integers(0, 4), st.sampled_from(["negative", "scale", "nan", "inf"]))
def test_qmdp_refuses_non_stochastic_beliefs(
    inputs: tuple[torch.Tensor, torch.Tensor], index: int, kind: str
) -> None:
    q, p = inputs
    p = p.reshape(-1, q.shape[0]).clone()
    if p.shape[0] == 0:
        p = torch.full((1, q.shape[0]), 1.0 / q.shape[0], dtype=q.dtype)
    k = index % q.shape[0]
    if kind == "negative":
        p[0, k] = -0.5
    elif kind == "scale":
        p[0] *= 1.01
    else:
        p[0, k] = math.nan if kind == "nan" else math.inf
    with pytest.raises(ValueError, match="probabilities"):
        qmdp_action(q, p)


@FUZZ
@given(qmdp_inputs(), st.sampled_from(BAD_DTYPES), st.booleans())
def test_qmdp_refuses_other_dtypes(
    inputs: tuple[torch.Tensor, torch.Tensor], dtype: torch.dtype, on_q: bool
) -> None:
    q, p = inputs
    name = "q_values" if on_q else "probabilities"
    q, p = (q.to(dtype), p) if on_q else (q, p.to(dtype))
    with pytest.raises(ValueError, match=name):
        qmdp_action(q, p)


def test_qmdp_empty_batch_and_overflow() -> None:
    q = torch.randn(3, 2, dtype=torch.float64)
    assert qmdp_action(q, torch.zeros(0, 3, dtype=torch.float64)).shape == (0,)
    assert qmdp_values(q, torch.zeros(2, 0, 3, dtype=torch.float64)).shape == (2, 0, 2)
    huge = torch.full((2, 1), torch.finfo(torch.float32).max, dtype=torch.float32)
    p = torch.tensor([0.5, 0.5002], dtype=torch.float32)  # sums to 1 within sqrt(eps)
    with pytest.raises(ValueError, match="q_values"):
        qmdp_values(huge, p)


# ------------------------------------------------------------------------------- DynaQ


def _trained_agent(sampler: str = "index") -> DynaQ:
    agent = DynaQ(3, planning_steps=2, seed=1, sampler=sampler)  # type: ignore[arg-type]
    for step in range(20):
        s = step % 4
        agent.observe(s, step % 3, float(step % 5) - 2.0, (s * 3 + 1) % 5, s == 3)
    return agent


AGENT = _trained_agent()
STATE = AGENT.state_dict()
TENSOR_KEYS = sorted(k for k, v in STATE.items() if isinstance(v, torch.Tensor))


def test_zero_counts_are_refused_instead_of_a_nan_q_table() -> None:
    # The finding: counts of 0 in both the index and the graph loaded, then sweep() divided
    # by them and the Q table became NaN.
    state = copy.deepcopy(STATE)
    state["edge_count"][0] = 0
    graph = json.loads(state["graph"])
    pair, target = int(state["edge_pair"][0]), int(state["edge_next"][0])
    s, a = state["pairs"][pair].tolist()
    for row in graph["transitions"]:
        if row[:3] == [s, a, target]:
            row[3] = 0
    state["graph"] = json.dumps(graph)
    with pytest.raises(ValueError, match="state_dict graph"):
        DynaQ(3).load_state_dict(state)


@pytest.mark.parametrize("key", sorted(STATE))
def test_every_missing_key_is_named(key: str) -> None:
    state = {k: v for k, v in STATE.items() if k != key}
    optional = {"version", "initial_value", "exploration", "step_size", "planning_penalty"}
    if key in optional:
        DynaQ(3).load_state_dict(state)
        return
    match = "state_dict" if key == "format" else f"state_dict.*{key}"
    with pytest.raises(ValueError, match=match):
        DynaQ(3).load_state_dict(state)


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("torch_rng", torch.zeros(3, dtype=torch.uint8)),
        ("torch_rng", 5),
        ("numpy_rng", {"bit_generator": "nope"}),
        ("numpy_rng", 7),
        ("q_table", "abc"),
        ("states", 5),
        ("graph", 5),
        ("graph", "{"),
        ("pairs", torch.tensor([[90, 0]])),
        ("steps", -1),
        ("seed", -1),
        ("num_actions", "3"),
    ],
)
def test_corrupt_entries_are_named(key: str, value: object) -> None:
    state = dict(STATE, **{key: value})
    with pytest.raises(ValueError, match=f"state_dict.*{key}"):
        DynaQ(3).load_state_dict(state)


MUTATIONS = ["drop", "none", "string", "negative", "nan", "empty", "float16", "int", "zero"]


def _mutate(value: object, kind: str, index: int) -> object:
    if kind == "none":
        return None
    if kind == "string":
        return "corrupt"
    if not isinstance(value, torch.Tensor):
        return {"negative": -1, "nan": math.nan, "zero": 0, "int": 10**30}.get(kind, [value])
    if kind == "empty":
        return value[:0]
    if kind == "float16":
        return value.to(torch.float16)
    if kind == "int":
        return value.to(torch.int32)
    mutated = value.clone()
    if mutated.numel() == 0:
        return mutated
    flat = mutated.view(-1)
    k = index % flat.numel()
    if kind == "nan" and mutated.dtype.is_floating_point:
        flat[k] = math.nan
    elif kind == "negative" and mutated.dtype not in (torch.bool, torch.uint8):
        flat[k] = -1
    elif kind == "zero" and mutated.dtype != torch.bool:
        flat[k] = 0
    return mutated


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.sampled_from(sorted(STATE)), st.sampled_from(MUTATIONS), st.integers(0, 1000))
def test_mutated_state_dicts_load_correctly_or_raise_a_named_value_error(
    key: str, kind: str, index: int
) -> None:
    state = copy.deepcopy(STATE)
    if kind == "drop":
        del state[key]
    else:
        state[key] = _mutate(state[key], kind, index)
    agent = DynaQ(3)
    _, message = attempt(lambda: agent.load_state_dict(state))
    if message is not None:
        assert "state_dict" in message
        assert agent.num_states == 0  # a failed load leaves the agent unchanged
        return
    # Loaded: the agent must be usable, with finite values after planning and a sweep.
    agent.plan(5)
    result = agent.sweep(max_sweeps=200)
    assert math.isfinite(result.residual)
    assert bool(torch.isfinite(agent.q_table()).all())
    assert agent.act(0) in range(3)


@pytest.mark.bitwise("the same code on the same inputs in the same process")
def test_a_loaded_agent_continues_exactly() -> None:
    for sampler in ("index", "graph"):
        agent = _trained_agent(sampler)
        clone = DynaQ.from_state_dict(copy.deepcopy(agent.state_dict()))
        for step in range(10):
            args = (step % 4, step % 3, 1.0, (step + 1) % 4, False)
            agent.observe(*args)
            clone.observe(*args)
        assert torch.equal(agent.q_table(), clone.q_table())


REWARDS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-5, 5),
    st.sampled_from(["1", None, 1j, True]),
)


@FUZZ
@given(
    st.one_of(st.integers(-2, 4), st.sampled_from([1.0, "0", None, True])),
    REWARDS,
    st.sampled_from([True, False, 0, "yes", np.bool_(True)]),
    st.sampled_from([0, 1, "s", (1, 2), [1], None]),
)
def test_observe_learns_or_names_the_argument(
    action: object, reward: object, terminal: object, state: object
) -> None:
    agent = DynaQ(3, planning_steps=3, seed=0)
    agent.observe(0, 0, 1.0, 1, False)
    _, message = attempt(
        lambda: agent.observe(state, action, reward, 2, terminal)  # type: ignore[arg-type]
    )
    if message is not None:
        assert message.split()[0].rstrip(":") in {"action", "reward", "terminal", "state"}
    assert bool(torch.isfinite(agent.q_table()).all())
    assert value_error_or(lambda: agent.act(state), "state") in (None, 0, 1, 2)


@FUZZ
@given(st.sampled_from([*BAD_DTYPES, torch.float32, torch.float64, "float", None]))
def test_q_table_dtype(dtype: object) -> None:
    table = value_error_or(lambda: AGENT.q_table(dtype=dtype), "dtype")  # type: ignore[arg-type]
    values = value_error_or(lambda: AGENT.q_values(0, dtype=dtype), "dtype")  # type: ignore[arg-type]
    if dtype in (torch.float32, torch.float64):
        assert table.dtype == dtype
        assert values.shape == (3,)
    else:
        assert table is None
        assert values is None


def test_unknown_state_index_is_a_value_error() -> None:
    with pytest.raises(ValueError, match="unknown state"):
        AGENT.index("nowhere")


# ------------------------------------------------------------------- replay buffer, DQN


def _buffer() -> ReplayBuffer:
    buffer = ReplayBuffer(4, 2, dtype=torch.float64, seed=3)
    buffer.add(
        observation=torch.ones(3, 2, dtype=torch.float64),
        action=torch.tensor([0, 1, 2]),
        reward=torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64),
        next_observation=torch.zeros(3, 2, dtype=torch.float64),
        terminal=torch.tensor([False, True, False]),
    )
    return buffer


BUFFER_STATE = _buffer().state_dict()


@settings(max_examples=120, deadline=None, derandomize=True)
@given(st.sampled_from(sorted(BUFFER_STATE)), st.sampled_from(MUTATIONS), st.integers(0, 100))
def test_mutated_buffer_states_load_or_raise_a_named_value_error(
    key: str, kind: str, index: int
) -> None:
    state = copy.deepcopy(BUFFER_STATE)
    if kind == "drop":
        del state[key]
    else:
        state[key] = _mutate(state[key], kind, index)
    buffer = ReplayBuffer(4, 2, dtype=torch.float64)
    _, message = attempt(lambda: buffer.load_state_dict(state))
    if message is not None:
        assert "state_dict" in message
        return
    if len(buffer):
        batch = buffer.sample(5)
        assert bool(torch.isfinite(batch.observations).all())
        assert bool((batch.actions >= 0).all())


@FUZZ
@given(
    st.sampled_from([0, 1, -1, "1", 1.5, None, torch.tensor(1), torch.tensor(1.0)]),
    REWARDS,
    st.sampled_from([False, True, 1, "no", torch.tensor(True)]),
)
def test_buffer_add_stores_or_names_the_argument(
    action: object, reward: object, terminal: object
) -> None:
    buffer = ReplayBuffer(4, 2, dtype=torch.float64)
    _, message = attempt(
        lambda: buffer.add(
            observation=torch.zeros(2, dtype=torch.float64),
            action=action,  # type: ignore[arg-type]
            reward=reward,  # type: ignore[arg-type]
            next_observation=torch.zeros(2, dtype=torch.float64),
            terminal=terminal,  # type: ignore[arg-type]
        )
    )
    if message is not None:
        assert message.split()[0].rstrip(":") in {"action", "reward", "terminal"}
        assert len(buffer) == 0
        return
    assert len(buffer) == 1
    assert bool(torch.isfinite(buffer.sample(1).rewards).all())


def test_empty_batches_have_the_right_shapes() -> None:
    buffer = ReplayBuffer(4, 2)
    buffer.add(
        observation=torch.zeros(0, 2),
        action=torch.zeros(0, dtype=torch.long),
        reward=torch.zeros(0),
        next_observation=torch.zeros(0, 2),
        terminal=torch.zeros(0, dtype=torch.bool),
    )
    assert len(buffer) == 0
    network = QNetwork(1, 1, 2)
    assert network(torch.zeros(0, 2)).shape == (0, 2)
    empty = Transitions(
        torch.zeros(0, 2),
        torch.zeros(0, dtype=torch.long),
        torch.zeros(0),
        torch.zeros(0, 2),
        torch.zeros(0, dtype=torch.bool),
    )
    loss = dqn_loss(network, QNetwork(1, 1, 2), empty, 0.9)
    assert loss.shape == ()
    assert float(loss.detach()) == 0.0


@FUZZ
@given(
    st.sampled_from(Transitions._fields),
    st.sampled_from(["list", "float16", "complex", "nan", "shape", "none"]),
)
def test_dqn_loss_names_a_bad_batch_field(field: str, kind: str) -> None:
    good = _buffer().sample(4)
    network, target = QNetwork(1, 1, 3, dtype=torch.float64), QNetwork(1, 1, 3, dtype=torch.float64)
    value = getattr(good, field)
    bad: object = {
        "list": value.tolist(),
        "none": None,
        "float16": value.to(torch.float16),
        "complex": value.to(torch.complex64),
        "shape": value[:2],
        "nan": value.double() * math.nan,
    }[kind]
    batch = good._replace(**{field: bad})
    loss, message = attempt(lambda: dqn_loss(network, target, batch, 0.9))
    if message is not None:
        assert field in message or "features" in message
        return
    assert bool(torch.isfinite(loss))


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda: dqn_loss(5, QNetwork(1, 1, 2), _buffer().sample(1), 0.9), "online"),  # type: ignore[arg-type]
        (
            lambda: dqn_loss(
                QNetwork(1, 1, 2), QNetwork(1, 1, 2), _buffer().sample(1), 0.9, double="x"
            ),
            "double",
        ),  # type: ignore[arg-type]
        (lambda: update_target(target=5, online=QNetwork(1, 1, 2)), "target"),  # type: ignore[arg-type]
        (lambda: QNetwork(2, 0, 2, dtype=torch.int64), "dtype"),
        (lambda: QNetwork(2, 0, 2, hidden="ab"), "hidden"),  # type: ignore[arg-type]
    ],
)
def test_network_arguments_are_named(call: Callable[[], object], name: str) -> None:
    with pytest.raises(ValueError, match=name):
        call()
