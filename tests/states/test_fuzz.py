"""Property tests of the states entry points: every input gives the right answer or a
ValueError that names the argument (or the file's field) at fault; never another exception
type, never a silent NaN/inf."""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcontact.states import (
    ContactFeature,
    ContactSet,
    ContactState,
    ContactStateRegistry,
    FeatureGrid,
    ManipulationGraph,
    ManipulationState,
    PoseGrid,
    StateTable,
    TactileArray,
    contact_states,
    manipulation_states,
    rectangle_sensors,
)

FUZZ = settings(max_examples=100, deadline=None, derandomize=True)


def attempt(call: Callable[[], Any]) -> tuple[Any, str | None]:
    """``(call(), None)``, or ``(None, message)`` if it raised a ValueError."""
    try:
        return call(), None
    except ValueError as error:
        return None, str(error)


def _state(i: int) -> ManipulationState:
    feature = ContactFeature("environment", (i, 0), (2, 0), i % 2 == 0)
    return ManipulationState((i, -i, 0), ContactState((feature,)))


def _graph() -> ManipulationGraph:
    graph = ManipulationGraph(3, smoothing=0.0, default_reward=-1.0)
    for step in range(30):
        i, a = step % 5, step % 3
        graph.observe(_state(i), a, _state((i * 2 + a) % 6), float(step % 7) - 3.0)
    return graph


GRAPH_DATA = json.loads(_graph().to_json())


# ------------------------------------------------------------------- graph files


def test_the_reported_corruptions_are_named() -> None:
    for row, field in (
        ([0, 0, 1, -1, 0.0], "count"),  # was turned into a self-loop silently
        ([0, 0, 1, 1, math.nan], "reward_sum"),
        ([0, 0, 1, 1, math.inf], "reward_sum"),
        ([-1, 0, 1, 1, 0.0], "m"),  # aliased the last state
        ([99, 0, 1, 1, 0.0], "m"),  # failed later with IndexError
        ([0, 7, 1, 1, 0.0], "a"),
    ):
        data = dict(GRAPH_DATA, transitions=[row])
        with pytest.raises(ValueError, match=rf"text field 'transitions'\[0\] {field}"):
            ManipulationGraph.from_json(json.dumps(data))
    for text, message in (
        ("{", "text is not valid JSON"),
        (b"\xff\xfe", "text is not valid JSON"),
        (json.dumps(dict(GRAPH_DATA, format="other")), "text is not a"),
        (json.dumps({k: v for k, v in GRAPH_DATA.items() if k != "states"}), "'states'"),
        (json.dumps(dict(GRAPH_DATA, version=2)), "'version'"),
    ):
        with pytest.raises(ValueError, match=message):
            ManipulationGraph.from_json(text)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="text must be a JSON str"):
        ManipulationGraph.from_json(5)  # type: ignore[arg-type]


JUNK = st.sampled_from(
    [None, -1, 0, 1, 2, 99, 1.5, -0.5, math.nan, math.inf, True, "x", [], {}, [0, 0], 10**20]
)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(
    st.sampled_from(["drop", "replace", "row", "cell", "state", "append", "truncate"]),
    st.sampled_from(sorted(GRAPH_DATA)),
    st.integers(0, 10**6),
    JUNK,
)
def test_mutated_graph_files_load_correctly_or_name_the_field(
    kind: str, key: str, index: int, junk: object
) -> None:
    data = copy.deepcopy(GRAPH_DATA)
    rows, states = data["transitions"], data["states"]
    if kind == "drop":
        del data[key]
    elif kind == "replace":
        data[key] = junk
    elif kind == "row":
        rows[index % len(rows)] = junk
    elif kind == "cell":
        rows[index % len(rows)][index % 5] = junk
    elif kind == "state":
        states[index % len(states)] = junk if index % 2 else {"pose": junk, "contact": []}
    elif kind == "append":
        rows.append(copy.deepcopy(rows[index % len(rows)]))  # a duplicate transition
    text = json.dumps(data)
    if kind == "truncate":
        text = text[: index % len(text)]
    graph, message = attempt(lambda: ManipulationGraph.from_json(text))
    if message is not None:
        assert message.startswith("text")
        return
    # Loaded: a valid graph whose model is finite and row-stochastic.
    probabilities, rewards = graph.transition_tensor(), graph.reward_tensor()
    assert bool(torch.isfinite(probabilities).all())
    assert bool(torch.isfinite(rewards).all())
    assert bool((probabilities >= 0).all())
    torch.testing.assert_close(
        probabilities.sum(-1), torch.ones(probabilities.shape[:-1], dtype=probabilities.dtype)
    )
    assert ManipulationGraph.from_json(graph.to_json()).to_json() == graph.to_json()


def test_unreadable_graph_and_registry_files_name_the_path(tmp_path: Path) -> None:
    binary = tmp_path / "graph.json"
    binary.write_bytes(b"\x80\x81 not text")
    for path in (tmp_path / "missing.json", tmp_path, binary):
        with pytest.raises(ValueError, match="path"):
            ManipulationGraph.load(path)
        with pytest.raises(ValueError, match="path"):
            ContactStateRegistry.load(path)
    with pytest.raises(ValueError, match="path"):
        ManipulationGraph.load(5)  # type: ignore[arg-type]


REGISTRY_DATA = json.loads(
    ContactStateRegistry(
        FeatureGrid(2, 0.1, 0.2), [s.contact for s in map(_state, range(4))]
    ).to_json()
)


@FUZZ
@given(st.sampled_from(["drop", "replace", "grid", "state"]), st.integers(0, 100), JUNK)
def test_mutated_registry_files_load_or_name_the_field(kind: str, index: int, junk: object) -> None:
    data = copy.deepcopy(REGISTRY_DATA)
    keys = sorted(data)
    if kind == "drop":
        del data[keys[index % len(keys)]]
    elif kind == "replace":
        data[keys[index % len(keys)]] = junk
    elif kind == "grid":
        data["grid"][sorted(data["grid"])[index % 3]] = junk
    else:
        data["states"][index % len(data["states"])] = [junk] if index % 2 else junk
    registry, message = attempt(lambda: ContactStateRegistry.from_json(json.dumps(data)))
    if message is not None:
        assert message.startswith("text")
        return
    assert ContactStateRegistry.from_json(registry.to_json()).states == registry.states


# --------------------------------------------------------------------- graph queries


@FUZZ
@given(
    st.lists(
        st.one_of(st.floats(-0.5, 1.5), st.sampled_from([math.nan, math.inf, -math.inf])),
        min_size=3,
        max_size=3,
    ),
    st.sampled_from([torch.float32, torch.float64, torch.float16, torch.int64, torch.complex64]),
)
def test_transition_matrix_policy_is_stochastic_or_named(
    weights: list[float], dtype: torch.dtype
) -> None:
    graph = _graph()
    policy = torch.tensor(weights).to(dtype)
    matrix, message = attempt(lambda: graph.transition_matrix(policy, dtype=torch.float64))
    if message is not None:
        assert message.startswith("action_probabilities")
        return
    w = np.asarray(weights)
    assert np.all(w >= 0)
    assert abs(w.sum() - 1) <= 1e-6
    reference = np.einsum("a,aij->ij", w, graph.transition_tensor(dtype=torch.float64).numpy())
    np.testing.assert_allclose(matrix.numpy(), reference, atol=1e-6)


@FUZZ
@given(
    st.lists(st.integers(-3, 9), max_size=6),
    st.lists(st.integers(-2, 4), max_size=6),
    st.sampled_from([torch.long, torch.int32, torch.float64]),
)
def test_sample_ids_in_range_or_named(
    ids: list[int], actions: list[int], dtype: torch.dtype
) -> None:
    graph = _graph()
    n = min(len(ids), len(actions))
    state_ids = torch.tensor(ids[:n], dtype=dtype)
    picked = torch.tensor(actions[:n], dtype=torch.long)
    result, message = attempt(lambda: graph.sample_ids(state_ids, picked))
    if message is not None:
        assert message.split()[0].rstrip(":") in {"state_ids", "actions"}
        return
    next_ids, rewards = result
    assert next_ids.shape == (n,)
    assert rewards.shape == (n,)
    assert bool(((next_ids >= 0) & (next_ids < graph.num_states)).all())
    assert bool(torch.isfinite(rewards).all())


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda g: g.index(_state(40)), "state"),
        (lambda g: g.count(_state(40)), "state"),
        (lambda g: g.sample(_state(40), 0), "state"),
        (lambda g: g.transition_tensor(dtype=torch.int64), "dtype"),
        (lambda g: g.reward_tensor(dtype=torch.float16), "dtype"),
        (lambda g: g.observe(_state(0), 0, _state(1), "1.0"), "reward"),
        (lambda g: ManipulationGraph(2, smoothing="a"), "smoothing"),
        (lambda g: g.merged(lambda s: 5), "state"),
    ],
)
def test_graph_arguments_are_named(call: Callable[[ManipulationGraph], object], name: str) -> None:
    with pytest.raises(ValueError, match=name):
        call(_graph())


def test_state_tables_raise_value_errors() -> None:
    table = StateTable(["a", "b"])
    with pytest.raises(ValueError, match="unknown state"):
        table.index("c")
    with pytest.raises(KeyError):  # still a KeyError for mapping-style callers
        table.index("c")
    with pytest.raises(ValueError, match="index"):
        table[2]
    with pytest.raises(ValueError, match="index"):
        table["a"]  # type: ignore[index]
    with pytest.raises(ValueError, match="state must be hashable"):
        table.add([1])  # type: ignore[arg-type]
    assert [1] not in table


# --------------------------------------------------------------------------- tactile

RATES = st.one_of(
    st.one_of(st.floats(-0.5, 1.5), st.sampled_from([math.nan, math.inf, -math.inf])),
    st.sampled_from([0.0, 1.0, "0.1", None, True]),
)


@FUZZ
@given(RATES, RATES, st.sampled_from([0.0, 0.5, -1.0, math.nan, "x"]))
def test_tactile_rates_are_probabilities_or_named(
    false_positive: object, false_negative: object, min_impulse: object
) -> None:
    positions = torch.tensor([[0.0, 0.0], [1.0, 0.0]])
    array, message = attempt(
        lambda: TactileArray(
            positions,
            torch.tensor([[0.0, 1.0], [1.0, 0.0]]),
            0.1,
            0.5,
            false_positive=false_positive,  # type: ignore[arg-type]
            false_negative=false_negative,  # type: ignore[arg-type]
            min_impulse=min_impulse,  # type: ignore[arg-type]
        )
    )
    if message is not None:
        assert message.split()[0].rstrip(":") in {"false_positive", "false_negative", "min_impulse"}
        return
    for rate in (false_positive, false_negative):
        assert isinstance(rate, float)
        assert 0.0 <= rate <= 1.0
    triggers = torch.tensor([[True, False], [False, True], [False, False]])
    probability = array.reading_probability(triggers)
    assert bool(((probability >= 0) & (probability <= 1)).all())
    readings = torch.tensor([[True, False], [False, False]])
    log_likelihood = array.log_likelihood(readings, triggers)
    assert log_likelihood.shape == (2, 3)
    assert not bool(torch.isnan(log_likelihood).any())
    assert not bool(torch.isposinf(log_likelihood).any())
    # An independent reference: the product of per-sensor probabilities.
    p = probability.numpy()
    expected = np.prod(np.where(readings.numpy()[:, None, :], p, 1 - p), axis=-1)
    np.testing.assert_allclose(np.exp(log_likelihood.numpy()), expected, atol=1e-12)


@FUZZ
@given(
    st.integers(0, 3),
    st.sampled_from([torch.bool, torch.float64, torch.float32, torch.float16, torch.int64]),
    st.one_of(st.floats(-0.5, 1.5), st.just(math.nan)),
)
def test_tactile_triggers_and_empty_batches(batch: int, dtype: torch.dtype, value: float) -> None:
    array = rectangle_sensors(
        half_extents=(0.1, 0.1),
        counts=(1, 1, 1, 1),
        radius=0.05,
        half_angle=0.5,
        false_positive=0.1,
        false_negative=0.2,
        dtype=torch.float64,
    )
    triggers = torch.full((batch, 4), value).to(dtype)
    probability, message = attempt(lambda: array.reading_probability(triggers))
    if message is not None:
        assert message.startswith("triggers")
        return
    assert probability.shape == (batch, 4)
    assert bool(((probability >= 0) & (probability <= 1)).all())
    readings = array.sample(triggers, generator=torch.Generator().manual_seed(0))
    assert readings.shape == (batch, 4)
    assert readings.dtype == torch.bool


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda a: a.sample(torch.zeros(1, 4, dtype=torch.bool), generator=5), "generator"),
        (lambda a: a.triggered(5), "contacts"),
        (lambda a: a.trigger_table([5], FeatureGrid(2, 0.1, 0.1)), "states"),
        (lambda a: a.trigger_table([], 5), "grid"),
        (lambda a: a.log_likelihood(torch.zeros(1, 4), torch.zeros(1, 4)), "readings"),
        (
            lambda a: rectangle_sensors(
                half_extents="ab", counts=(1, 1, 1, 1), radius=0.1, half_angle=0.1
            ),
            "half_extents",
        ),
        (
            lambda a: rectangle_sensors(
                half_extents=(1.0, 1.0), counts=(True, 1, 1, 1), radius=0.1, half_angle=0.1
            ),
            "counts",
        ),
        (
            lambda a: rectangle_sensors(
                half_extents=(1.0, 1.0),
                counts=(1, 1, 1, 1),
                radius=0.1,
                half_angle=0.1,
                dtype=torch.int64,
            ),
            "dtype",
        ),
    ],
)
def test_tactile_arguments_are_named(call: Callable[[TactileArray], object], name: str) -> None:
    array = rectangle_sensors(
        half_extents=(0.1, 0.1), counts=(1, 1, 1, 1), radius=0.05, half_angle=0.5
    )
    with pytest.raises(ValueError, match=name):
        call(array)


# ------------------------------------------------------------ states and their files


@FUZZ
@given(st.integers(0, 3), st.sampled_from([1.0, 1e30, -1e300, math.inf]))
def test_contact_and_manipulation_states_of_any_batch(batch: int, scale: float) -> None:
    grid, pose_grid = FeatureGrid(2, 0.05, 0.2), PoseGrid(2, 0.01, 0.1)
    points = torch.full((batch, 2, 2), 0.1) * scale
    contacts, message = attempt(
        lambda: ContactSet(
            points=points,
            normals=torch.tensor([[0.0, 1.0], [1.0, 0.0]]).expand(batch, 2, 2),
            pn=torch.ones(batch, 2),
            mode=torch.ones(batch, 2, dtype=torch.long),
            partner=torch.tensor([0, 1]),
            partner_kind=("environment", "robot"),
        )
    )
    if message is not None:
        assert message.startswith("points")
        return
    states, message = attempt(lambda: contact_states(contacts, grid))
    if message is not None:
        assert message.startswith("points")  # keys that do not fit an int64
        return
    assert len(states) == batch
    robot_pose = torch.zeros(batch, 3)
    assert (
        len(
            manipulation_states(
                contacts, robot_pose=robot_pose, contact_grid=grid, pose_grid=pose_grid
            )
        )
        == batch
    )
    with pytest.raises(ValueError, match="pose"):
        pose_grid.quantize(torch.full((1, 3), 1e300))
    with pytest.raises(ValueError, match="index"):
        contacts[batch]
    with pytest.raises(ValueError, match="grid"):
        contact_states(contacts, 5)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="pose_grid"):
        manipulation_states(contacts, robot_pose=robot_pose, contact_grid=grid, pose_grid=5)  # type: ignore[arg-type]


@FUZZ
@given(JUNK, st.integers(0, 3))
def test_state_from_json_round_trips_or_names_data(junk: object, where: int) -> None:
    good = _state(3).to_json()
    data: Any = copy.deepcopy(good)
    if where == 0:
        data = junk
    elif where == 1:
        data["pose"] = junk
    elif where == 2:
        data["contact"] = junk
    else:
        data["contact"][0][where % 4] = junk
    state, message = attempt(lambda: ManipulationState.from_json(data))
    if message is not None:
        assert message.split()[0].rstrip(":") in {
            "data",
            "data['pose']",
            "pose",
            "kind",
            "cell",
            "features",
            "sliding",
        }
        return
    assert ManipulationState.from_json(state.to_json()) == state
