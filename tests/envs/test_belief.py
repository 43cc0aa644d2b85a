"""The peg-in-hole belief model and filter: exact measurement model, graph rows, tracking."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from torchcontact.envs import (
    PegBelief,
    PegControl,
    PegInHole2DVector,
    PegInHoleBeliefModel,
    PegInHoleConfig,
    PegInHoleFilter,
    PegInHoleStates,
    PegTransitions,
)
from torchcontact.envs._belief_model import compose
from torchcontact.experiments import (
    NUM_BELIEF_FEATURES,
    PotentialShaping,
    QLookup,
    Setting,
    evaluate,
    qmdp_actions,
    run_round,
)
from torchcontact.rl import DynaQ, QNetwork
from torchcontact.states import ManipulationState

CONFIG = PegInHoleConfig(max_steps=25)


@pytest.fixture(scope="module")
def fitted() -> tuple[PegInHoleBeliefModel, DynaQ, PegTransitions]:
    env = PegInHole2DVector(num_envs=4, config=CONFIG)
    agent = DynaQ(7, epsilon=0.5, planning_steps=0, seed=1)
    rounds = [run_round(env, agent, seed=s, shaping=PotentialShaping(5.0)) for s in range(2)]
    data = PegTransitions.concat([r.transitions for r in rounds])
    return PegInHoleBeliefModel.fit(data, agent.graph, task=env.task), agent, data


def test_vision_model_is_the_exact_pose_composition(
    fitted: tuple[PegInHoleBeliefModel, DynaQ, PegTransitions],
) -> None:
    model, _, _ = fitted
    filt = PegInHoleFilter(model, num_particles=24)
    generator = torch.Generator().manual_seed(0)
    gripper = torch.rand(5, 3, generator=generator, dtype=torch.float64) - 0.5
    observation = {"peg_pose": gripper, "gripper_pose": gripper, "tactile": np.zeros((5, 14))}
    belief = filt.init(observation)
    control = PegControl(
        state_ids=belief.state_ids, gripper_after=gripper, actions=torch.zeros(5, dtype=torch.long)
    )
    dynamics = model.mode_dynamics(belief.rbpf, control)
    x = torch.randn(5, 3, generator=generator, dtype=torch.float64) * 0.05
    predicted = torch.einsum("bkij,bj->bki", dynamics.H, x) + dynamics.d
    torch.testing.assert_close(
        predicted, compose(gripper, x)[:, None].expand(5, 24, 3), rtol=0, atol=1e-15
    )
    assert dynamics.transition_rows is not None
    torch.testing.assert_close(
        dynamics.transition_rows.sum(-1), torch.ones(5, 24, dtype=torch.float64)
    )


def test_transition_rows_shrink_the_graph_counts_toward_the_class_level(
    fitted: tuple[PegInHoleBeliefModel, DynaQ, PegTransitions],
) -> None:
    model, agent, _ = fitted
    states = model.task.states
    index, counts = agent.graph.count_entries()
    i, a = int(index[0, 0]), int(index[1, 0])
    source = states.index(agent.graph.states[i])
    next_classes = torch.zeros(24, dtype=torch.float64)
    mask = (index[0] == i) & (index[1] == a)
    for j, n in zip(index[2][mask].tolist(), counts[mask].tolist(), strict=True):
        next_classes[states.index(agent.graph.states[j]) % 24] += n
    prior = model.class_transition[a, source % 24]
    expected = (next_classes + prior) / (next_classes.sum() + 1.0)  # graph_prior = 1
    torch.testing.assert_close(model.state_transition[model.state_row[source], a], expected)


def test_filter_tracks_the_peg_better_than_the_camera(
    fitted: tuple[PegInHoleBeliefModel, DynaQ, PegTransitions],
) -> None:
    model, _, _ = fitted
    env = PegInHole2DVector(num_envs=6, config=CONFIG, observation="noisy")
    filt = PegInHoleFilter(model, num_particles=32)
    observation, info = env.reset(seed=50)
    belief = filt.init(observation)
    rng = np.random.default_rng(0)
    generator = torch.Generator().manual_seed(0)
    camera, tracked = [], []
    for _ in range(20):
        actions = rng.integers(0, 7, size=6)
        observation, _, terminated, truncated, info = env.step(actions)
        belief = filt.step(belief, actions, observation, generator=generator)
        truth = torch.as_tensor(info["peg_pose"])[:, :2]
        camera.append((torch.as_tensor(observation["peg_pose"])[:, :2] - truth).norm(dim=-1))
        tracked.append((filt.pose_mean(belief)[:, :2] - truth).norm(dim=-1))
        assert not (terminated | truncated).any()
    rmse_camera = torch.stack(camera[5:]).pow(2).mean().sqrt()
    rmse_filter = torch.stack(tracked[5:]).pow(2).mean().sqrt()
    assert rmse_filter < 0.6 * rmse_camera


@pytest.mark.bitwise("the entries that are not restarted are passed through untouched")
def test_restart_replaces_exactly_the_entries_of_new_episodes(
    fitted: tuple[PegInHoleBeliefModel, DynaQ, PegTransitions],
) -> None:
    model, _, _ = fitted
    env = PegInHole2DVector(num_envs=3, config=CONFIG, observation="noisy")
    filt = PegInHoleFilter(model, num_particles=24)
    observation, _ = env.reset(seed=7)
    generator = torch.Generator().manual_seed(0)
    belief = filt.init(observation)
    for action in (4, 1):
        observation, *_ = env.step(np.full(3, action))
        belief = filt.step(belief, np.full(3, action), observation, generator=generator)
    other, _ = PegInHole2DVector(num_envs=3, config=CONFIG, observation="noisy").reset(seed=99)
    where = np.array([False, True, False])
    restarted = filt.restart(belief, where, other)
    fresh = filt.init(other)
    pairs = [(restarted.gripper, fresh.gripper, belief.gripper)]
    pairs.append((restarted.state_ids, fresh.state_ids, belief.state_ids))
    for name in ("modes", "log_weights", "log_evidence", "history", "degenerate"):
        pairs.append(tuple(getattr(b.rbpf, name) for b in (restarted, fresh, belief)))
    for name in ("gaussians", "prior"):
        for part in ("mean", "cov"):
            pairs.append(
                tuple(getattr(getattr(b.rbpf, name), part) for b in (restarted, fresh, belief))
            )
    for got, new, old in pairs:
        # The restarted entry is a fresh start computed in a batch of another size.
        torch.testing.assert_close(got[1], new[1], rtol=1e-12, atol=1e-15)
        assert torch.equal(got[0], old[0])
        assert torch.equal(got[2], old[2])
    assert not torch.equal(fresh.gripper[0], belief.gripper[0])  # the restart changed something


def _known_states(agent: DynaQ) -> list[ManipulationState]:
    """States with Q values of their own: acted from, or terminal."""
    return [
        s  # type: ignore[misc]
        for s in agent.states
        if agent.is_terminal(s) or agent.action_counts(s).any()
    ]


def _numpy_qmdp(
    lookup: QLookup, ids: torch.Tensor, weights: torch.Tensor, keys: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The reference: per episode, a loop over the particles adding ``w_i / Σ w`` times the Q row
    of each particle's state; then the action of highest value, among ties the first one, or
    the one of highest key (the tie rule of ``greedy_action``)."""
    table, rows = lookup.table.numpy(), lookup.row.numpy()
    values = np.zeros((ids.shape[0], table.shape[1]))
    actions = np.zeros(ids.shape[0], dtype=np.int64)
    for b in range(ids.shape[0]):
        w = weights[b].numpy()
        for i, wi in zip(ids[b].tolist(), w, strict=True):
            values[b] += wi / w.sum() * table[rows[i]]
        best = np.flatnonzero(values[b] == values[b].max())
        actions[b] = best[0] if keys is None else best[np.argmax(keys[b, best])]
    return values, actions


def test_qmdp_actions_equal_a_numpy_loop_over_particles_with_the_tie_rule(
    fitted: tuple[PegInHoleBeliefModel, DynaQ, PegTransitions],
) -> None:
    model, agent, _ = fitted
    lookup = QLookup(agent, model.task.states)
    M, A = lookup.table.shape
    generator = torch.Generator().manual_seed(5)
    # Small integer Q values and dyadic weights: every weighted sum is exact, ties are exact.
    lookup.table = torch.randint(-4, 5, (M, A), generator=generator).to(torch.float64)
    ids = torch.randint(0, model.task.states.num_states, (6, 8), generator=generator)
    weights = torch.full((6, 8), 1 / 8, dtype=torch.float64)
    weights[:3] = torch.tensor([1 / 2, 1 / 4, 1 / 8, 1 / 16, 1 / 32, 1 / 64, 1 / 128, 1 / 128])
    row = int(lookup.row[ids[0, 0]])
    lookup.table[row] = torch.tensor([0.0, 1.0, 3.0, -1.0, 2.0, 3.0, 3.0])  # 2, 5, 6 tie
    ids[0] = ids[0, 0]  # every particle of episode 0 in that state
    values, expected = _numpy_qmdp(lookup, ids, weights)
    assert np.sum(values[0] == values[0].max()) == 3  # the tie is really there
    got = qmdp_actions(lookup, ids, weights)
    assert got.dtype == torch.long
    assert got.tolist() == expected.tolist()
    assert int(got[0]) == 2  # the lowest of the tied actions
    for seed in range(4):  # with a generator: the tied action of highest key
        keys = torch.rand(6, A, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
        _, expected = _numpy_qmdp(lookup, ids, weights, keys.numpy())
        got = qmdp_actions(lookup, ids, weights, generator=torch.Generator().manual_seed(seed))
        assert got.tolist() == expected.tolist()
        assert int(got[0]) in (2, 5, 6)


def test_qmdp_needs_a_row_for_every_state(
    fitted: tuple[PegInHoleBeliefModel, DynaQ, PegTransitions],
) -> None:
    model, agent, _ = fitted
    lookup = QLookup(agent, model.task.states, nearest=False)
    assert not lookup.complete
    ids = torch.zeros(1, 4, dtype=torch.long)
    with pytest.raises(ValueError, match=r"^lookup must give every state a row"):
        qmdp_actions(lookup, ids, torch.full((1, 4), 0.25, dtype=torch.float64))


def test_probabilities_drop_the_particles_without_a_row(
    fitted: tuple[PegInHoleBeliefModel, DynaQ, PegTransitions],
) -> None:
    model, agent, _ = fitted
    lookup = QLookup(agent, model.task.states, nearest=False)
    known = [model.task.states.index(s) for s in _known_states(agent)[:5]]
    unknown = next(i for i in range(model.task.states.num_states) if not lookup.known[i])
    ids = torch.tensor([[known[0], known[1], unknown, known[0]], [unknown] * 4])
    weights = torch.tensor([[0.1, 0.2, 0.3, 0.4], [0.25] * 4], dtype=torch.float64)
    expected = torch.zeros(2, lookup.num_rows, dtype=torch.float64)
    for i, w in zip(ids[0].tolist(), weights[0].tolist(), strict=True):
        if i != unknown:
            expected[0, int(lookup.row[i])] += w / 0.7
    torch.testing.assert_close(lookup.probabilities(ids, weights), expected, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("setting", ["qmdp", "neural"])
def test_evaluate_computes_the_particle_ids_once_per_step_and_qmdp_is_the_numpy_loop(
    fitted: tuple[PegInHoleBeliefModel, DynaQ, PegTransitions],
    monkeypatch: pytest.MonkeyPatch,
    setting: Setting,
) -> None:
    model, agent, _ = fitted
    lookup = QLookup(agent, model.task.states)
    env = PegInHole2DVector(num_envs=3, config=CONFIG, observation="noisy")
    filt = PegInHoleFilter(model, num_particles=24)
    network = QNetwork.from_table(lookup.table.float(), NUM_BELIEF_FEATURES, hidden=(8,))
    seen: list[tuple[torch.Tensor, torch.Tensor]] = []
    taken: list[np.ndarray] = []
    particle_states, step, ids_of = filt.particle_states, env.step, PegInHoleStates.ids
    calls = {"ids": 0}

    def counted_ids(self: PegInHoleStates, peg_pose: torch.Tensor, *args: Any) -> torch.Tensor:
        calls["ids"] += peg_pose.ndim == 3  # (B, N, 3): the particles (the env's are (B, 3))
        return ids_of(self, peg_pose, *args)

    def recorded_states(belief: PegBelief) -> tuple[torch.Tensor, torch.Tensor]:
        seen.append(particle_states(belief))
        return seen[-1]

    def recorded_step(actions: np.ndarray) -> Any:
        taken.append(np.array(actions))
        return step(actions)

    monkeypatch.setattr(PegInHoleStates, "ids", counted_ids)
    monkeypatch.setattr(filt, "particle_states", recorded_states)
    monkeypatch.setattr(env, "step", recorded_step)
    result = evaluate(env, setting, lookup=lookup, seed=3, filt=filt, network=network)
    decisions = int(result.lengths.max())
    assert len(seen) == len(taken) == decisions > 1
    # One computation per belief (the start and each filter step), shared by the policy and
    # the filter's graph transition rows.
    assert calls["ids"] == decisions + 1
    # The untrained network is the QMDP head: both settings act as the NumPy loop does (the
    # tie keys are drawn inside evaluate: a tied episode takes one of its best actions).
    for (ids, weights), actions in zip(seen, taken, strict=True):
        values, expected = _numpy_qmdp(lookup, ids, weights)
        best = values.max(1)
        tol = 1e-5 * (1 + np.abs(best))  # float32 network, float64 reference
        assert np.all(values[np.arange(3), actions] >= best - tol)
        second = np.sort(values, axis=1)[:, -2]
        clear = best - second > tol
        assert actions[clear].tolist() == expected[clear].tolist()


@pytest.mark.bitwise("a row of Q values is looked up and copied, not computed")
def test_unknown_states_borrow_the_nearest_known_row(
    fitted: tuple[PegInHoleBeliefModel, DynaQ, PegTransitions],
) -> None:
    model, agent, _ = fitted
    states = model.task.states
    lookup = QLookup(agent, states)
    known = _known_states(agent)
    assert 0 < len(known) < agent.num_states  # some states were only reached, never left
    classes = {s.contact for s in known}
    generator = torch.Generator().manual_seed(3)
    sample = torch.randint(0, states.num_states, (300,), generator=generator).tolist()
    sample += [states.index(s) for s in agent.states]  # type: ignore[arg-type]
    values, own = lookup.values(torch.tensor(sample))
    for i, id_ in enumerate(sample):
        key = states.key(id_)
        if key in known:  # its own row
            assert bool(own[i])
            torch.testing.assert_close(values[i], agent.q_values(key), rtol=0, atol=0)
            continue
        assert not bool(own[i])
        same = [s for s in known if s.contact == key.contact] if key.contact in classes else known
        distance = [sum(abs(a - b) for a, b in zip(s.pose, key.pose, strict=True)) for s in same]
        nearest = same[distance.index(min(distance))]  # known lists states in row order
        torch.testing.assert_close(values[i], agent.q_values(nearest), rtol=0, atol=0)
