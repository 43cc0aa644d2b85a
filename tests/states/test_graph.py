"""The manipulation graph: counts, smoothing, exports, sampling, persistence, drawing."""

from __future__ import annotations

import math

import matplotlib
import pytest
import torch

from tests.states.scenes import SLIDE, box_step, stack
from torchcontact.states import (
    ContactFeature,
    ContactState,
    FeatureGrid,
    ManipulationGraph,
    ManipulationState,
    PartnerKind,
    PoseGrid,
    manipulation_states,
)

matplotlib.use("Agg")


def _state(i: int) -> ManipulationState:
    """Distinct placeholder states: the robot at pose key ``(i, 0, 0)``, no contact."""
    return ManipulationState((i, 0, 0), ContactState())


M0, M1, M2, M3 = (_state(i) for i in range(4))


def _graph(smoothing: float = 0.0) -> ManipulationGraph:
    """m0 —a0→ m1 three times (rewards 1, 2, 4), m0 —a0→ m2 once (reward 0.1),
    m0 —a1→ m0 twice (reward −1), m1 —a1→ m2 once (reward 1/3)."""
    graph = ManipulationGraph(2, smoothing=smoothing, default_reward=-5.0)
    for reward in (1.0, 2.0, 4.0):
        graph.observe(M0, 0, M1, reward)
    graph.observe(M0, 0, M2, 0.1)
    graph.observe(M0, 1, M0, -1.0)
    graph.observe(M0, 1, M0, -1.0)
    graph.observe(M1, 1, M2, 1 / 3)
    return graph


@pytest.mark.bitwise(
    "probabilities are ratios of small integer counts, correctly rounded by IEEE division"
)
def test_counts_and_probabilities_without_smoothing() -> None:
    graph = _graph()
    assert graph.states == (M0, M1, M2)  # first-seen order
    assert graph.count(M0, 0, M1) == 3
    assert graph.count(M0, 0) == 4
    assert graph.count(M0) == graph.visits(M0) == 6
    assert graph.count(M0, next_state=M2) == 1
    assert graph.visits(M2) == 0
    torch.testing.assert_close(
        graph.transition_probabilities(M0, 0), torch.tensor([0.0, 0.75, 0.25]), rtol=0, atol=0
    )
    torch.testing.assert_close(
        graph.transition_probabilities(M0, 1), torch.tensor([1.0, 0.0, 0.0]), rtol=0, atol=0
    )
    # Unvisited pairs without smoothing: a self-loop.
    torch.testing.assert_close(
        graph.transition_probabilities(M1, 0), torch.tensor([0.0, 1.0, 0.0]), rtol=0, atol=0
    )
    torch.testing.assert_close(
        graph.transition_probabilities(M2, 1), torch.tensor([0.0, 0.0, 1.0]), rtol=0, atol=0
    )


def test_dirichlet_smoothing() -> None:
    alpha, K = 0.5, 3
    graph = _graph(smoothing=alpha)
    # (N(m, a, m′) + α) / (N(m, a) + α K) with N(m0, a0, ·) = (0, 3, 1).
    expected = torch.tensor([0.5 / 5.5, 3.5 / 5.5, 1.5 / 5.5])
    torch.testing.assert_close(graph.transition_probabilities(M0, 0), expected, rtol=1e-15, atol=0)
    # Unvisited pairs with smoothing: the prior, uniform over the known states.
    torch.testing.assert_close(
        graph.transition_probabilities(M2, 0), torch.full((K,), 1 / K), rtol=1e-15, atol=0
    )
    # A new state changes K and so every smoothed row.
    graph.add_state(M3)
    torch.testing.assert_close(
        graph.transition_probabilities(M0, 0),
        torch.tensor([0.5 / 6.0, 3.5 / 6.0, 1.5 / 6.0, 0.5 / 6.0]),
        rtol=1e-15,
        atol=0,
    )


def test_mean_rewards() -> None:
    graph = _graph()
    assert graph.mean_reward(M0, 0, M1) == (1.0 + 2.0 + 4.0) / 3
    assert graph.mean_reward(M1, 1, M2) == 1 / 3
    assert graph.mean_reward(M2, 0, M0) == -5.0  # default for unseen transitions
    rewards = graph.reward_tensor()
    assert rewards.shape == (2, 3, 3)
    assert float(rewards[0, 0, 1]) == 7.0 / 3
    assert float(rewards[1, 0, 0]) == -1.0
    assert float(rewards[0, 2, 2]) == -5.0


def test_merging_states_adds_their_counts_and_rewards() -> None:
    graph = _graph(smoothing=0.5)
    # m1 and m2 become one state; m0 stays alone.
    merged = graph.merged(lambda m: M1 if m in (M1, M2) else m)
    assert merged.states == (M0, M1)
    assert (merged.smoothing, merged.default_reward) == (0.5, -5.0)
    assert merged.count(M0, 0, M1) == 4  # three to m1 + one to m2
    assert merged.count(M1, 1, M1) == 1  # m1 → m2
    assert merged.count(M0, 1, M0) == 2
    assert merged.mean_reward(M0, 0, M1) == (1.0 + 2.0 + 4.0 + 0.1) / 4
    # Merging by an injective key reproduces the graph.
    same = graph.merged(lambda m: m)
    assert same.to_json() == graph.to_json()
    with pytest.raises(ValueError, match="ManipulationState"):
        graph.merged(lambda m: m.pose)  # type: ignore[arg-type,return-value]


@pytest.mark.bitwise("ratios of small integer counts; a one-hot policy row adds exact zeros")
def test_transition_exports() -> None:
    graph = _graph(smoothing=0.25)
    T = graph.transition_tensor()
    assert T.shape == (2, 3, 3)
    torch.testing.assert_close(T.sum(-1), torch.ones(2, 3), rtol=0, atol=1e-15)
    for a in range(2):
        for i, state in enumerate(graph.states):
            assert torch.equal(T[a, i], graph.transition_probabilities(state, a))
    uniform = graph.transition_matrix()
    torch.testing.assert_close(uniform, 0.5 * (T[0] + T[1]), rtol=1e-15, atol=1e-15)
    weighted = graph.transition_matrix(torch.tensor([0.2, 0.8]))
    torch.testing.assert_close(weighted, 0.2 * T[0] + 0.8 * T[1], rtol=1e-15, atol=1e-15)
    policy = torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.5, 0.5]])
    per_state = graph.transition_matrix(policy)
    torch.testing.assert_close(per_state[0], T[0, 0], rtol=0, atol=0)
    torch.testing.assert_close(per_state[1], T[1, 1], rtol=0, atol=0)
    torch.testing.assert_close(per_state.sum(-1), torch.ones(3), rtol=0, atol=1e-15)
    assert graph.transition_tensor(dtype=torch.float32).dtype == torch.float32
    with pytest.raises(ValueError, match="rows summing to 1"):
        graph.transition_matrix(torch.tensor([0.5, 0.6]))
    with pytest.raises(ValueError, match=r"action_probabilities must have shape \(2,\) or"):
        graph.transition_matrix(torch.ones(2, 2) / 2)


@pytest.mark.bitwise("mean rewards are sums of a few decimals divided by counts, in one order")
def test_sampling_frequencies_match_probabilities() -> None:
    graph = _graph(smoothing=0.5)
    n = 30_000
    gen = torch.Generator().manual_seed(11)
    ids = torch.zeros(n, dtype=torch.long)
    next_ids, rewards = graph.sample_ids(ids, torch.zeros(n, dtype=torch.long), generator=gen)
    p = graph.transition_probabilities(M0, 0)
    frequency = torch.bincount(next_ids, minlength=3).double() / n
    sigma = (p * (1 - p) / n).sqrt()
    assert bool(((frequency - p).abs() <= 5 * sigma).all()), (frequency, p)
    # Rewards are the mean rewards of the sampled transitions (default where never seen).
    expected = torch.tensor([-5.0, 7.0 / 3, 0.1])[next_ids]
    assert torch.equal(rewards, expected)
    # Mixed pairs in one call: each row follows its own (m, a).
    pairs = torch.tensor([[0, 1]] * 100 + [[1, 1]] * 100)
    next_ids, _ = graph.sample_ids(pairs[:, 0], pairs[:, 1], generator=gen)
    assert next_ids.shape == (200,)
    # Without smoothing, deterministic rows are reproduced exactly.
    sharp = _graph()
    next_state, reward = sharp.sample(M0, 1, generator=gen)
    assert next_state == M0
    assert reward == -1.0
    assert sharp.sample(M2, 0, generator=gen) == (M2, -5.0)  # unvisited: self-loop


@pytest.mark.bitwise("the same code on the same inputs in the same process")
def test_sampling_is_reproducible_with_a_generator() -> None:
    graph = _graph(smoothing=1.0)
    ids, actions = torch.randint(0, 3, (50,)), torch.randint(0, 2, (50,))
    a = graph.sample_ids(ids, actions, generator=torch.Generator().manual_seed(3))
    b = graph.sample_ids(ids, actions, generator=torch.Generator().manual_seed(3))
    assert torch.equal(a[0], b[0])
    assert torch.equal(a[1], b[1])


@pytest.mark.bitwise("an unvisited pair's self-loop has probability 1 exactly")
def test_unknown_states_and_bad_actions() -> None:
    graph = _graph()
    with pytest.raises(KeyError, match="unknown state"):
        graph.transition_probabilities(M3, 0)
    with pytest.raises(KeyError, match="unknown state"):
        graph.sample(M3, 0)
    with pytest.raises(KeyError, match="unknown state"):
        graph.count(M3)
    assert M3 not in graph
    assert graph.add_state(M3) == 3
    assert M3 in graph
    torch.testing.assert_close(
        graph.transition_probabilities(M3, 1), torch.tensor([0.0, 0.0, 0.0, 1.0]), rtol=0, atol=0
    )
    with pytest.raises(ValueError, match=r"action must lie in \[0, 2\), got 2"):
        graph.observe(M0, 2, M1, 0.0)
    with pytest.raises(ValueError, match="reward must be finite"):
        graph.observe(M0, 0, M1, math.nan)
    with pytest.raises(ValueError, match="next_state must be a ManipulationState"):
        graph.observe(_state(9), 0, "m1", 0.0)  # type: ignore[arg-type]
    assert _state(9) not in graph  # nothing was recorded
    with pytest.raises(ValueError, match=r"state_ids must lie in \[0, 4\)"):
        graph.sample_ids(torch.tensor([4]), torch.tensor([0]))
    with pytest.raises(ValueError, match="num_actions must be an int >= 1"):
        ManipulationGraph(0)
    with pytest.raises(ValueError, match="smoothing must be a finite number >= 0"):
        ManipulationGraph(2, smoothing=-1.0)


@pytest.mark.bitwise("Python's float repr round-trips every float exactly")
def test_json_round_trip_is_exact(tmp_path) -> None:
    graph = _graph(smoothing=0.3)
    feature = ContactFeature(PartnerKind.ROBOT, (-7, 1), (0, 2), True)
    graph.observe(M2, 1, ManipulationState((1, 2, 3), ContactState((feature,))), 0.1 + 0.2)
    path = tmp_path / "graph.json"
    graph.save(path)
    loaded = ManipulationGraph.load(path)
    assert loaded.to_json() == graph.to_json()
    assert loaded.states == graph.states
    assert loaded.num_actions == 2
    assert loaded.smoothing == 0.3
    assert loaded.default_reward == -5.0
    assert torch.equal(loaded.transition_tensor(), graph.transition_tensor())
    assert torch.equal(loaded.reward_tensor(), graph.reward_tensor())
    assert loaded.mean_reward(M2, 1, graph.states[-1]) == 0.1 + 0.2  # not 0.3
    # The loaded graph keeps counting where the saved one stopped.
    loaded.observe(M0, 0, M1, 1.0)
    assert loaded.count(M0, 0, M1) == 4
    with pytest.raises(ValueError, match=r"not a torchcontact\.ManipulationGraph"):
        ManipulationGraph.from_json("[]")


def test_networkx_export() -> None:
    graph = _graph()
    digraph = graph.to_networkx()
    assert digraph.number_of_nodes() == 3
    # Observed pairs: (m0, m1), (m0, m2), (m0, m0), (m1, m2).
    assert digraph.number_of_edges() == 4
    assert set(digraph.edges) == {(0, 1), (0, 2), (0, 0), (1, 2)}
    edge = digraph.edges[0, 1]
    assert edge["count"] == 3
    assert edge["probability"] == 3 / 6
    assert edge["mean_reward"] == 7.0 / 3
    assert edge["counts"] == {0: 3}
    assert digraph.nodes[0]["visits"] == 6
    assert digraph.nodes[2]["state"] == M2
    assert sum(p for _, _, p in digraph.out_edges(0, data="probability")) == 1.0


def test_draw_writes_a_png(tmp_path) -> None:
    import matplotlib.pyplot as plt

    ax = _graph().draw()
    path = tmp_path / "graph.png"
    ax.figure.savefig(path)
    plt.close(ax.figure)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert path.stat().st_size > 1000


@pytest.mark.bitwise("deterministic rows hold probability 1 exactly")
def test_box_resting_sliding_and_tipping() -> None:
    """Synthetic contact tensors of a pushed box give three states and the expected edges.

    Actions: 0 wait, 1 push low (the box slides), 2 push high (it tips on its right edge).
    """
    contact_grid = FeatureGrid(dim=2, radius=0.05, angle=math.radians(15))
    pose_grid = PoseGrid(dim=2, position_step=0.05, angle_step=math.pi / 8)
    tip = math.radians(8)
    episode = [  # (box step, action taken after it)
        (box_step(x=0.0), 0),
        (box_step(x=0.0), 1),
        (box_step(x=0.02, corner_modes=(SLIDE, SLIDE), finger=(-0.5, 0.0)), 1),
        (box_step(x=0.05, corner_modes=(SLIDE + 1, SLIDE), finger=(-0.5, 0.0)), 1),
        (box_step(x=0.09, corner_modes=(SLIDE, SLIDE), finger=(-0.5, 0.0)), 2),
        (box_step(x=0.59, tip=tip, finger=(-0.5, 0.15)), 2),
        (box_step(x=0.59, tip=tip, finger=(-0.5, 0.15)), 0),
        (box_step(x=0.12), None),
    ]
    contacts = stack([step[0][0] for step in episode])
    robot = torch.stack([step[0][1] for step in episode])
    states = manipulation_states(
        contacts, robot_pose=robot, contact_grid=contact_grid, pose_grid=pose_grid
    )
    rest, slide, tipped = states[0], states[2], states[5]
    assert len({rest, slide, tipped}) == 3
    assert states == [rest, rest, slide, slide, slide, tipped, tipped, rest]
    # The contact states, feature by feature (cell side 0.0707 m, central +y / +x bins).
    assert [(f.cell, f.direction, f.sliding) for f in rest.contact.environment] == [
        ((-7, -4), (2, 2), False),
        ((7, -4), (2, 2), False),
    ]
    assert not rest.robot_contact
    assert [f.sliding for f in slide.contact.environment] == [True, True]
    assert [(f.cell, f.direction) for f in slide.contact.robot] == [((-7, 0), (0, 2))]
    assert [(f.cell, f.sliding) for f in tipped.contact.environment] == [((7, -4), False)]
    assert [f.cell for f in tipped.contact.robot] == [(-7, 2)]
    assert (str(rest.contact), str(slide.contact), str(tipped.contact)) == (
        "E2st",
        "E2sl R1st",
        "E1st R1st",
    )

    graph = ManipulationGraph(3)
    rewards = [0.0, 0.02, 0.03, 0.04, 0.0, 0.0, 0.0]
    for t in range(len(episode) - 1):
        action = episode[t][1]
        assert action is not None
        graph.observe(states[t], action, states[t + 1], rewards[t])
    assert graph.states == (rest, slide, tipped)
    expected = torch.zeros(3, 3, 3)
    expected[0, 0, 0] = 1.0  # wait at rest: stays
    expected[1, 0, 1] = 1.0  # push low at rest: slides
    expected[1, 1, 1] = 1.0  # push low while sliding: keeps sliding (twice)
    expected[2, 1, 2] = 1.0  # push high while sliding: tips
    expected[2, 2, 2] = 1.0  # push high while tipped: stays tipped
    expected[0, 2, 0] = 1.0  # wait while tipped: falls back to rest
    expected[0, 1, 1] = 1.0  # unvisited (slide, wait): self-loop
    expected[1, 2, 2] = 1.0  # unvisited (tipped, push low): self-loop
    expected[2, 0, 0] = 1.0  # unvisited (rest, push high): self-loop
    assert torch.equal(graph.transition_tensor(), expected)
    assert graph.count(slide, 1, slide) == 2
    assert graph.mean_reward(slide, 1, slide) == (0.03 + 0.04) / 2
    assert graph.to_networkx().number_of_edges() == 6  # the six observed (m, m′) pairs


def test_draw_shows_ids_on_the_nodes_and_a_legend_of_their_labels() -> None:
    import matplotlib.pyplot as plt

    graph = _graph()
    ax = graph.draw()
    legend = ax.get_legend()
    assert legend is not None
    texts = [text.get_text() for text in legend.get_texts()]
    assert texts == [f"{i}: {state}" for i, state in enumerate(graph.states)]
    on_nodes = sorted(text.get_text() for text in ax.texts)
    assert on_nodes == sorted(str(i) for i in range(graph.num_states))
    plt.close(ax.figure)
    _, ax = plt.subplots()
    graph.draw(ax, labels={0: "start", 1: "middle", 2: "goal"})
    assert [t.get_text() for t in ax.get_legend().get_texts()] == [
        "0: start",
        "1: middle",
        "2: goal",
    ]
    plt.close(ax.figure)
