"""Dyna-Q: optimality against exact value iteration, the planning speed-up, the planning
distribution, determinism, exact checkpoint resume, the graph as the model, validation."""

from __future__ import annotations

import copy
import io
import math
from collections import Counter
from typing import Any

import numpy as np
import pytest
import torch

from tests.rl.worlds import Cell, GridWorld, greedy_rollout, run_episode
from torchcontact.rl import DynaQ, Sampler, qmdp_action
from torchcontact.states import ContactState, ManipulationState

SAMPLERS: list[Sampler] = ["index", "graph"]


def test_learns_the_optimal_policy_of_a_maze() -> None:
    """The greedy path is a shortest path (BFS) and, once every pair is tried, the Q table
    equals the exact Q* of value iteration on the true maze."""
    world, gamma = GridWorld(), 0.9
    agent = DynaQ(4, alpha=0.5, gamma=gamma, epsilon=0.1, planning_steps=20, seed=0)
    for _ in range(30):
        run_episode(world, agent)
    shortest = world.shortest_path()
    assert shortest == 8
    path = greedy_rollout(world, agent)
    assert path[-1] == world.goal
    assert len(path) - 1 == shortest  # return −8, the optimum
    q_star = world.optimal_q(gamma)
    for cell in path[:-1]:  # every greedy action is optimal
        assert q_star[cell][agent.greedy(cell)] == pytest.approx(q_star[cell].max(), abs=1e-12)
    # Every (cell, action) of the maze was tried, so the learned model is the maze; planning
    # to convergence (α = 1 on a deterministic model) gives exactly Q*.
    graph = agent.graph
    assert set(agent.states) == set(world.cells)
    for cell in world.cells:
        if cell != world.goal:
            assert all(graph.count(graph.states[agent.index(cell)], a) > 0 for a in range(4))
    agent.alpha = 1.0
    agent.plan(20_000)
    for cell in world.cells:
        np.testing.assert_allclose(agent.q_values(cell).numpy(), q_star[cell], rtol=0, atol=1e-9)
    v_start = -(1 - gamma**shortest) / (1 - gamma)
    assert float(agent.q_values(world.start).max()) == pytest.approx(v_start, abs=1e-9)


def _episodes_to_optimal(planning_steps: int, seed: int, world: GridWorld) -> int:
    agent = DynaQ(4, alpha=0.5, gamma=0.95, epsilon=0.1, planning_steps=planning_steps, seed=seed)
    shortest = world.shortest_path()
    for episode in range(1, 201):
        run_episode(world, agent)
        if len(greedy_rollout(world, agent)) - 1 == shortest:
            return episode
    raise AssertionError(f"no optimal greedy policy after 200 episodes (n={planning_steps})")


def test_planning_needs_several_times_fewer_episodes() -> None:
    world = GridWorld()
    seeds = range(5)
    without = np.mean([_episodes_to_optimal(0, seed, world) for seed in seeds])
    with_planning = np.mean([_episodes_to_optimal(20, seed, world) for seed in seeds])
    assert without >= 3 * with_planning, (without, with_planning)


def _model_fixed_point(agent: DynaQ, gamma: float, penalty: float = 0.0) -> np.ndarray:
    """Value iteration on the agent's learned graph: unvisited pairs stay 0 (as in the agent),
    states reached as terminal have value 0; rewards less ``penalty / √N(s, a)``."""
    graph, A, K = agent.graph, agent.num_actions, agent.num_states
    T = graph.transition_tensor(dtype=torch.float64).numpy()
    R = graph.reward_tensor(dtype=torch.float64).numpy()
    counts = np.array([[graph.count(graph.states[i], a) for a in range(A)] for i in range(K)])
    visited = counts > 0
    terminal = np.array([agent.is_terminal(s) for s in agent.states])
    expected_reward = np.einsum("aij,aij->ia", T, R) - penalty / np.sqrt(np.maximum(counts, 1))
    q = np.zeros((K, A))
    for _ in range(600):
        value = np.where(terminal, 0.0, q.max(-1))
        q = np.where(visited, expected_reward + gamma * np.einsum("aij,j->ia", T, value), 0.0)
    return q


@pytest.mark.parametrize("sampler", SAMPLERS)
@pytest.mark.parametrize("penalty", [0.0, 0.3])
def test_planning_converges_to_the_graph_model_fixed_point(
    sampler: Sampler, penalty: float
) -> None:
    """After little exploration (so many pairs are unvisited), planning with α = 1 converges
    to the Bellman fixed point of the learned (penalized) model computed from the graph's
    tensors."""
    world, gamma = GridWorld(), 0.9
    agent = DynaQ(
        4,
        alpha=0.5,
        gamma=gamma,
        epsilon=0.3,
        planning_steps=5,
        seed=4,
        sampler=sampler,
        planning_penalty=penalty,
    )
    for _ in range(2):
        run_episode(world, agent)
    agent.alpha = 1.0
    agent.plan(20_000)
    np.testing.assert_allclose(
        agent.q_table().numpy(), _model_fixed_point(agent, gamma, penalty), rtol=0, atol=1e-9
    )


@pytest.mark.parametrize("penalty", [0.0, 0.3])
def test_sweep_is_value_iteration_on_the_graph_model(penalty: float) -> None:
    """One call of ``sweep`` lands on the fixed point that 600 dense Bellman backups over the
    graph's tensors reach, from any starting table (here, the half-learned one)."""
    world, gamma = GridWorld(slip=0.2), 0.9
    agent = DynaQ(
        4, alpha=0.5, gamma=gamma, epsilon=0.3, planning_steps=0, seed=4, planning_penalty=penalty
    )
    _train(agent, world, np.random.default_rng(1), world.start, 300)
    result = agent.sweep(tolerance=1e-12)
    assert result.converged
    assert result.residual <= 1e-12
    assert 10 < result.sweeps < 600
    np.testing.assert_allclose(
        agent.q_table().numpy(), _model_fixed_point(agent, gamma, penalty), rtol=0, atol=1e-10
    )
    again = agent.sweep(tolerance=1e-12)
    assert again.sweeps == 1  # already a fixed point


def test_the_planning_penalty_prefers_the_well_tried_action_over_one_lucky_sample() -> None:
    """Action 0 paid 1.0 in each of 100 tries, action 1 paid 1.2 once: the plain model's
    sweep prefers action 1, the penalized one (β = 0.5: 1.0 − 0.05 against 1.2 − 0.5) action 0.
    Real updates are not penalized."""
    values = {}
    for penalty in (0.0, 0.5):
        agent = DynaQ(2, alpha=1.0, gamma=0.9, planning_steps=0, seed=0, planning_penalty=penalty)
        for _ in range(100):
            agent.observe("s", 0, 1.0, "end", True)
        agent.observe("s", 1, 1.2, "end", True)
        assert agent.q_values("s").tolist() == [1.0, 1.2]
        agent.sweep()
        values[penalty] = agent.q_values("s").tolist()
        assert agent.planning_penalty == penalty
        assert DynaQ.from_state_dict(agent.state_dict()).planning_penalty == penalty
    assert values[0.0] == pytest.approx([1.0, 1.2], abs=1e-15)
    assert values[0.5] == pytest.approx([0.95, 0.7], abs=1e-15)


def test_sweep_reports_non_convergence() -> None:
    agent = DynaQ(1, gamma=1.0, seed=0)
    agent.observe("a", 0, 1.0, "a", False)  # a reward loop: the values grow without bound
    result = agent.sweep(max_sweeps=5)
    assert not result.converged
    assert result.sweeps == 5
    assert result.residual == pytest.approx(1.0)
    with pytest.raises(ValueError, match="tolerance"):
        agent.sweep(tolerance=0.0)
    with pytest.raises(ValueError, match="max_sweeps"):
        agent.sweep(max_sweeps=0)


def test_least_tried_exploration_tries_every_action_before_repeating_one() -> None:
    agent = DynaQ(5, epsilon=1.0, planning_steps=0, seed=3, exploration="least_tried")
    agent.observe("s", 2, 0.0, "t", False)
    agent.observe("s", 4, 0.0, "t", False)
    picked = []
    for _ in range(3):
        action = agent.act("s")
        assert action in (0, 1, 3)  # never one already tried while others are not
        agent.observe("s", action, 0.0, "t", False)
        picked.append(action)
    assert sorted(picked) == [0, 1, 3]
    np.testing.assert_array_equal(agent.action_counts("s"), [1, 1, 1, 1, 1])
    np.testing.assert_array_equal(agent.action_counts("unknown"), [0] * 5)
    # Once every count is equal, every action is a candidate again (uniform among them).
    assert {agent.act("s") for _ in range(200)} == set(range(5))
    clone = DynaQ.from_state_dict(agent.state_dict())
    assert clone.exploration == "least_tried"


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_planning_samples_the_empirical_distribution(sampler: Sampler) -> None:
    """With α = 1 and γ = 0 one planning update sets Q(s, a) to the sampled transition's
    mean reward, which identifies the sampled next state; the frequencies match the counts."""
    agent = DynaQ(2, alpha=1.0, gamma=0.0, epsilon=0.0, planning_steps=0, seed=3, sampler=sampler)
    counts = {"x": 3, "y": 1, "z": 4}
    reward_of = {"x": 10.0, "y": 20.0, "z": 30.0}
    for nxt, n in counts.items():
        for _ in range(n):
            agent.observe("s", 1, reward_of[nxt], nxt, False)
    draws = 4000
    seen: Counter[float] = Counter()
    for _ in range(draws):
        agent.plan(1)
        seen[float(agent.q_values("s")[1])] += 1
    assert set(seen) <= set(reward_of.values())
    total = sum(counts.values())
    for nxt, n in counts.items():
        p = n / total
        tolerance = 5 * math.sqrt(p * (1 - p) / draws)
        assert seen[reward_of[nxt]] / draws == pytest.approx(p, abs=tolerance)
    assert agent.planning_updates == draws


def test_planning_uses_the_mean_reward() -> None:
    agent = DynaQ(1, alpha=1.0, gamma=0.0, epsilon=0.0, planning_steps=0, seed=0)
    for reward in (1.0, 2.0, 4.0):
        agent.observe("s", 0, reward, "t", False)
    assert float(agent.q_values("s")[0]) == 4.0  # the last real update
    agent.plan(1)
    assert float(agent.q_values("s")[0]) == 7.0 / 3.0
    assert agent.graph.mean_reward(
        agent.graph.states[0], 0, agent.graph.states[1]
    ) == pytest.approx(7.0 / 3.0, abs=0)


def test_q_update_by_hand() -> None:
    agent = DynaQ(2, alpha=0.5, gamma=0.9, epsilon=0.0, planning_steps=0, seed=0)
    agent.observe("a", 0, 1.0, "b", False)  # 0.5 · (1 + 0.9 · 0) = 0.5
    agent.observe("b", 1, 2.0, "a", False)  # 0.5 · (2 + 0.9 · 0.5) = 1.225
    agent.observe("a", 0, 1.0, "b", False)  # 0.5 + 0.5 · (1 + 0.9 · 1.225 − 0.5) = 1.30125
    agent.observe("a", 1, -1.0, "c", True)  # 0.5 · (−1) = −0.5, no bootstrap
    expected = np.array([[1.30125, -0.5], [0.0, 1.225], [0.0, 0.0]])
    np.testing.assert_allclose(agent.q_table().numpy(), expected, rtol=1e-15, atol=0)
    assert agent.states == ("a", "b", "c")
    assert agent.is_terminal("c")
    assert not agent.is_terminal("a")
    assert not agent.is_terminal("unknown")
    assert agent.steps == 4
    assert agent.planning_updates == 0


def test_visit_step_sizes_average_the_first_targets_then_stay_at_alpha() -> None:
    """``α(s, a) = max(α, 1/N(s, a))``: with terminal targets (no bootstrap) the first
    ``1/α`` updates give the running mean of the rewards, later ones the constant-α rule."""
    rewards = [3.0, -1.0, 5.0, 2.0, 7.0, -4.0]
    agent = DynaQ(
        2, alpha=0.25, gamma=0.9, epsilon=0.0, planning_steps=0, seed=0, step_size="visits"
    )
    expected = 0.0
    for n, reward in enumerate(rewards, start=1):
        agent.observe("s", 1, reward, "t", True)
        if n <= 4:
            assert float(agent.q_values("s")[1]) == pytest.approx(np.mean(rewards[:n]), abs=1e-15)
        expected += max(0.25, 1 / n) * (reward - expected)
        assert float(agent.q_values("s")[1]) == pytest.approx(expected, abs=1e-15)
    assert agent.step_size == "visits"
    constant = DynaQ(2, alpha=0.25, gamma=0.9, epsilon=0.0, planning_steps=0, seed=0)
    constant.observe("s", 1, 3.0, "t", True)
    assert float(constant.q_values("s")[1]) == 0.75  # α · target: the once-tried undervalued
    # Planning updates of a pair use its real visit count: one visit, one planning update
    # from a model that says "reward 3, then t (value 2)" gives exactly that target.
    planner = DynaQ(
        1, alpha=0.1, gamma=0.5, epsilon=0.0, planning_steps=0, seed=0, step_size="visits"
    )
    planner.observe("t", 0, 4.0, "end", True)  # Q(t) = 4
    planner.observe("s", 0, 3.0, "t", False)  # Q(s) = 3 + 0.5 · 4 = 5
    planner.observe("t", 0, 0.0, "end", True)  # Q(t) = 4 + ½ (0 − 4) = 2 (two visits)
    for _ in range(50):
        planner.plan(1)
    assert float(planner.q_values("s")[0]) == pytest.approx(3.0 + 0.5 * 2.0, abs=1e-12)
    clone = DynaQ.from_state_dict(planner.state_dict())
    assert clone.step_size == "visits"


def test_act_breaks_ties_at_random_and_greedy_takes_the_lowest() -> None:
    agent = DynaQ(3, alpha=1.0, gamma=0.0, epsilon=0.0, planning_steps=0, seed=1)
    agent.observe("s", 0, 1.0, "t", True)
    agent.observe("s", 2, 1.0, "t", True)  # Q(s) = (1, 0, 1)
    draws = 4000
    actions = Counter(agent.act("s") for _ in range(draws))
    assert set(actions) == {0, 2}
    assert actions[0] / draws == pytest.approx(0.5, abs=5 * math.sqrt(0.25 / draws))
    assert agent.greedy("s") == 0
    unknown = Counter(agent.act("never seen") for _ in range(draws))  # all zeros: all tie
    for a in range(3):
        assert unknown[a] / draws == pytest.approx(1 / 3, abs=5 * math.sqrt(2 / 9 / draws))
    assert agent.greedy("never seen") == 0
    assert "never seen" not in agent  # acting registers nothing


def test_epsilon_exploration_rate() -> None:
    agent = DynaQ(4, alpha=1.0, gamma=0.0, epsilon=0.3, planning_steps=0, seed=2)
    agent.observe("u", 1, 1.0, "t", True)  # unique maximum at action 1
    draws = 10_000
    actions = Counter(agent.act("u") for _ in range(draws))
    p = 0.7 + 0.3 / 4
    assert actions[1] / draws == pytest.approx(p, abs=5 * math.sqrt(p * (1 - p) / draws))
    agent.epsilon = 0.0
    assert {agent.act("u") for _ in range(100)} == {1}


def _train(
    agent: DynaQ, world: GridWorld, rng: np.random.Generator, cell: Cell, steps: int
) -> tuple[Cell, list[int]]:
    """``steps`` ε-greedy steps from ``cell`` (episodes restart at the start)."""
    actions = []
    for _ in range(steps):
        action = agent.act(cell)
        nxt, reward, terminal = world.step(cell, action, rng)
        agent.observe(cell, action, reward, nxt, terminal)
        actions.append(action)
        cell = world.start if terminal else nxt
    return cell, actions


def test_deterministic_given_the_seed() -> None:
    world = GridWorld(slip=0.2)
    runs = []
    for seed in (7, 7, 8):
        agent = DynaQ(4, alpha=0.5, gamma=0.9, epsilon=0.2, planning_steps=5, seed=seed)
        _, actions = _train(agent, world, np.random.default_rng(0), world.start, 400)
        runs.append((agent.q_table().numpy(), actions, agent.states))
    assert np.array_equal(runs[0][0], runs[1][0])
    assert runs[0][1:] == runs[1][1:]
    assert runs[0][1] != runs[2][1]


@pytest.mark.parametrize("sampler", SAMPLERS)
def test_checkpoint_resumes_exactly(sampler: Sampler) -> None:
    world = GridWorld(slip=0.2)
    rng = np.random.default_rng(5)
    agent = DynaQ(4, alpha=0.5, gamma=0.9, epsilon=0.2, planning_steps=7, seed=3, sampler=sampler)
    cell, _ = _train(agent, world, rng, world.start, 137)  # stops mid-episode
    agent.epsilon = 0.15  # settings changed during a run are saved too
    buffer = io.BytesIO()
    torch.save(agent.state_dict(), buffer)
    env_state = copy.deepcopy(rng.bit_generator.state)
    saved = agent.state_dict()

    _, actions = _train(agent, world, rng, cell, 300)
    assert not np.array_equal(saved["q_table"].numpy(), agent.q_table().numpy())  # a snapshot

    buffer.seek(0)
    restored = DynaQ(4, alpha=0.9, gamma=0.5, epsilon=0.9, planning_steps=1, seed=99)
    restored.load_state_dict(torch.load(buffer, weights_only=False))
    assert restored.epsilon == 0.15
    assert restored.sampler == sampler
    rng.bit_generator.state = env_state
    _, actions_restored = _train(restored, world, rng, cell, 300)

    assert actions_restored == actions
    assert np.array_equal(restored.q_table().numpy(), agent.q_table().numpy())
    assert restored.graph.to_json() == agent.graph.to_json()
    assert restored.states == agent.states
    assert (restored.steps, restored.planning_updates) == (agent.steps, agent.planning_updates)
    assert restored.steps == 437
    clone = DynaQ.from_state_dict(agent.state_dict())
    assert np.array_equal(clone.q_table().numpy(), agent.q_table().numpy())


def test_failed_load_leaves_the_agent_unchanged() -> None:
    agent = DynaQ(2, planning_steps=0, seed=0)
    agent.observe("a", 0, 1.0, "b", False)
    good = agent.state_dict()
    with pytest.raises(ValueError, match="num_actions"):
        DynaQ(3).load_state_dict(good)
    with pytest.raises(ValueError, match="state_dict"):
        agent.load_state_dict({"format": "something else"})
    bad: dict[str, Any] = dict(good, q_table=torch.zeros(5, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="q_table"):
        agent.load_state_dict(bad)
    bad = dict(good, edge_count=good["edge_count"] + 1)
    with pytest.raises(ValueError, match="sampling index"):
        agent.load_state_dict(bad)
    assert agent.states == ("a", "b")
    assert float(agent.q_values("a")[0]) == 0.1


def test_manipulation_states_are_the_graph_states() -> None:
    """With ManipulationState states the agent's ids are the graph's ids, so the Q table
    lines up with the graph's (filter's) mode table."""
    m = [ManipulationState((i, 0, 0), ContactState()) for i in range(3)]
    agent = DynaQ(2, alpha=1.0, gamma=0.0, epsilon=0.0, planning_steps=0, seed=0)
    agent.observe(m[2], 1, 5.0, m[0], False)
    agent.observe(m[0], 0, -1.0, m[1], False)
    agent.observe(m[0], 0, -1.0, m[1], False)
    agent.observe(m[0], 0, -3.0, m[2], False)
    graph = agent.graph
    assert graph.states == agent.states == (m[2], m[0], m[1])
    assert graph.count(m[0], 0, m[1]) == 2
    transition = graph.transition_tensor(dtype=torch.float64)
    assert transition[0, graph.index(m[0])].tolist() == [1 / 3, 0.0, 2 / 3]
    table = agent.q_table()
    assert table[graph.index(m[2]), 1] == 5.0
    belief = torch.zeros(3, dtype=torch.float64)
    belief[graph.index(m[2])] = 1.0
    assert int(qmdp_action(table, belief)) == 1


def test_other_states_get_stand_ins_in_the_graph() -> None:
    agent = DynaQ(2, planning_steps=0, seed=0)
    agent.observe((0, 0), 1, -1.0, (0, 1), False)
    agent.observe((0, 1), 0, -1.0, (0, 0), False)
    assert agent.graph.states == (
        ManipulationState((0,), ContactState()),
        ManipulationState((1,), ContactState()),
    )
    assert agent.index((0, 1)) == 1
    with pytest.raises(ValueError, match="collides"):
        agent.observe(ManipulationState((1,), ContactState()), 0, 0.0, (0, 0), False)
    assert agent.num_states == 2


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"num_actions": 0}, "num_actions"),
        ({"num_actions": True}, "num_actions"),
        ({"num_actions": 2.0}, "num_actions"),
        ({"alpha": 0.0}, "alpha"),
        ({"alpha": 1.5}, "alpha"),
        ({"alpha": math.nan}, "alpha"),
        ({"gamma": -0.1}, "gamma"),
        ({"gamma": 1.01}, "gamma"),
        ({"epsilon": -0.1}, "epsilon"),
        ({"epsilon": math.inf}, "epsilon"),
        ({"planning_steps": -1}, "planning_steps"),
        ({"planning_steps": 2.5}, "planning_steps"),
        ({"seed": -1}, "seed"),
        ({"sampler": "dense"}, "sampler"),
        ({"exploration": "boltzmann"}, "exploration"),
        ({"step_size": "harmonic"}, "step_size"),
        ({"planning_penalty": -0.1}, "planning_penalty"),
        ({"planning_penalty": math.inf}, "planning_penalty"),
    ],
)
def test_bad_settings_raise(kwargs: dict[str, Any], name: str) -> None:
    arguments: dict[str, Any] = {"num_actions": 3, **kwargs}
    with pytest.raises(ValueError, match=name):
        DynaQ(**arguments)


@pytest.mark.parametrize(
    ("transition", "name"),
    [
        (("s", 3, 0.0, "t", False), "action"),
        (("s", -1, 0.0, "t", False), "action"),
        (("s", 1.0, 0.0, "t", False), "action"),
        (("s", True, 0.0, "t", False), "action"),
        (("s", 0, math.nan, "t", False), "reward"),
        (("s", 0, math.inf, "t", False), "reward"),
        (("s", 0, "1", "t", False), "reward"),
        (("s", 0, 0.0, "t", 1), "terminal"),
        ((["s"], 0, 0.0, "t", False), "state"),
        (("s", 0, 0.0, {"t"}, False), "next_state"),
    ],
)
def test_bad_transitions_raise(transition: tuple[Any, ...], name: str) -> None:
    agent = DynaQ(3, seed=0)
    with pytest.raises(ValueError, match=name):
        agent.observe(*transition)
    assert agent.num_states == 0
    assert agent.steps == 0


def test_other_bad_inputs_raise() -> None:
    agent = DynaQ(3, seed=0)
    with pytest.raises(ValueError, match="state"):
        agent.act(["unhashable"])
    with pytest.raises(ValueError, match="num_updates"):
        agent.plan(-1)
    with pytest.raises(ValueError, match="epsilon"):
        agent.epsilon = 2.0
    with pytest.raises(KeyError):
        agent.index("unknown")


def test_optimistic_initial_values_make_greedy_try_untried_actions() -> None:
    """With Q₀ = 1 above every return, a greedy agent moves on to an untried action after one
    costly try; with Q₀ = 0 the tried action (a small positive return) stays preferred."""
    for initial, expected in ((1.0, 1), (0.0, 0)):
        agent = DynaQ(3, alpha=0.5, gamma=0.9, epsilon=0.0, planning_steps=0, initial_value=initial)
        assert agent.q_values("unknown").tolist() == [initial] * 3
        agent.observe("s", 0, 0.1, "end", True)
        assert agent.q_values("s")[0].item() == pytest.approx(initial + 0.5 * (0.1 - initial))
        assert agent.greedy("s") == expected
        restored = DynaQ.from_state_dict(agent.state_dict())
        assert restored.initial_value == initial
        assert restored.q_values("new").tolist() == [initial] * 3
