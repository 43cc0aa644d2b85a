"""Neural Q on belief features: the QMDP start of QNetwork, DQN converging to known Q values,
the loss and target updates by hand, the replay buffer and the exploration schedule."""

from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
import pytest
import torch
from torch import nn

from torchcontact.rl import (
    EpsilonSchedule,
    QNetwork,
    ReplayBuffer,
    Transitions,
    dqn_loss,
    qmdp_values,
    update_target,
)

# ------------------------------------------------------------------------------ QNetwork


def test_from_table_starts_at_the_qmdp_values() -> None:
    generator = torch.Generator().manual_seed(0)
    K, F, A = 5, 7, 3
    table = torch.randn(K, A, generator=generator, dtype=torch.float64)
    network = QNetwork.from_table(table, F, hidden=(16, 16))
    p = torch.softmax(torch.randn(2, 3, K, generator=generator, dtype=torch.float64), -1)
    other = torch.randn(2, 3, F, generator=generator, dtype=torch.float64)
    values = network(torch.cat([p, other], -1))
    assert values.shape == (2, 3, A)
    assert values.dtype == torch.float64
    torch.testing.assert_close(values, qmdp_values(table, p), rtol=0, atol=1e-12)
    torch.testing.assert_close(network.qmdp(p), qmdp_values(table, p), rtol=0, atol=1e-12)
    # The residual's first layers are random: the output ignores them only through the
    # zero last layer, so one gradient step moves the network off the QMDP values.
    optimizer = torch.optim.SGD(network.parameters(), lr=0.1)
    network(torch.cat([p, other], -1)).square().sum().backward()
    optimizer.step()
    assert not torch.allclose(network(torch.cat([p, other], -1)), qmdp_values(network.table, p))


@pytest.mark.bitwise("a zero-initialized output layer gives exact zeros")
def test_linear_network_without_other_features() -> None:
    network = QNetwork(3, 0, 2, hidden=())
    assert network.input_size == 3
    p = torch.tensor([[0.2, 0.3, 0.5]])
    assert torch.equal(network(p), torch.zeros(1, 2))


def test_a_residual_on_the_other_features_alone() -> None:
    """``residual_on_probabilities=False``: the values are the QMDP values plus an MLP of the
    other features only, computed here layer by layer from the weights."""
    generator = torch.Generator().manual_seed(1)
    K, F, A = 6, 4, 3
    table = torch.randn(K, A, generator=generator, dtype=torch.float64)
    network = QNetwork.from_table(table, F, hidden=(5,), residual_on_probabilities=False)
    first, last = network.residual[0], network.residual[2]
    assert first.in_features == F
    with torch.no_grad():  # move the output layer off zero
        last.weight.copy_(torch.randn(A, 5, generator=generator, dtype=torch.float64))
        last.bias.copy_(torch.randn(A, generator=generator, dtype=torch.float64))
    p = torch.softmax(torch.randn(2, K, generator=generator, dtype=torch.float64), -1)
    other = torch.randn(2, F, generator=generator, dtype=torch.float64)
    hidden = torch.clamp(other @ first.weight.T + first.bias, min=0.0)
    expected = qmdp_values(table, p) + hidden @ last.weight.T + last.bias
    values = network(torch.cat([p, other], -1))
    torch.testing.assert_close(values, expected, rtol=1e-12, atol=1e-12)
    shuffled = torch.cat([p.flip(-1), other], -1)
    torch.testing.assert_close(
        network.residual_values(shuffled), expected - qmdp_values(table, p), rtol=0, atol=1e-12
    )
    with pytest.raises(ValueError, match="num_features must be >= 1"):
        QNetwork(K, 0, A, residual_on_probabilities=False)
    with pytest.raises(ValueError, match="residual_on_probabilities must be a bool"):
        QNetwork(K, F, A, residual_on_probabilities=1)  # type: ignore[arg-type]


def test_a_gated_residual_is_the_mlp_times_its_gate_feature() -> None:
    """``gate=j``: the residual is feature ``z_j`` times the MLP, computed here layer by layer:
    zero (QMDP exactly) where ``z_j = 0``, the plain MLP where ``z_j = 1``."""
    generator = torch.Generator().manual_seed(2)
    K, F, A = 5, 4, 3
    table = torch.randn(K, A, generator=generator, dtype=torch.float64)
    network = QNetwork.from_table(table, F, hidden=(6,), residual_on_probabilities=False, gate=3)
    first, last = network.residual[0], network.residual[2]
    with torch.no_grad():  # move the output layer off zero
        last.weight.copy_(torch.randn(A, 6, generator=generator, dtype=torch.float64))
        last.bias.copy_(torch.randn(A, generator=generator, dtype=torch.float64))
    p = torch.softmax(torch.randn(3, K, generator=generator, dtype=torch.float64), -1)
    other = torch.randn(3, F, generator=generator, dtype=torch.float64)
    other[:, 3] = torch.tensor([0.0, 1.0, 0.5], dtype=torch.float64)
    hidden = torch.clamp(other @ first.weight.T + first.bias, min=0.0)
    mlp = hidden @ last.weight.T + last.bias
    expected = qmdp_values(table, p) + other[:, 3:] * mlp
    values = network(torch.cat([p, other], -1))
    torch.testing.assert_close(values, expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(values[0], qmdp_values(table, p[0]), rtol=1e-12, atol=1e-12)
    for gate in (-1, F):
        with pytest.raises(ValueError, match="gate"):
            QNetwork(K, F, A, gate=gate)


def _chain_q_star(K: int, gamma: float) -> np.ndarray:
    """Value iteration on the chain: states 0 … K−1, K−1 terminal, actions left / right,
    reward 1 on entering K−1."""
    q = np.zeros((K - 1, 2))
    value = np.zeros(K)
    for _ in range(200):
        for s in range(K - 1):
            for a, nxt in enumerate((max(s - 1, 0), s + 1)):
                q[s, a] = 1.0 if nxt == K - 1 else gamma * value[nxt]
        value[: K - 1] = q.max(1)
    return q


def test_dqn_learns_the_q_values_of_a_chain() -> None:
    """Online double DQN with a replay buffer, ε schedule and soft target updates on the
    belief features of a fully observed 5-state chain converges to the exact Q*."""
    torch.manual_seed(0)
    K, gamma, steps = 5, 0.9, 600
    q_star = _chain_q_star(K, gamma)
    np.testing.assert_allclose(q_star[:, 1], [0.729, 0.81, 0.9, 1.0])
    features = torch.cat(
        [
            torch.eye(K, dtype=torch.float64),  # the belief: certain of the state
            torch.linspace(0, 1, K, dtype=torch.float64)[:, None],  # "pose"
            torch.ones(K, 1, dtype=torch.float64),
        ],
        dim=-1,
    )
    online = QNetwork(K, 2, 2, hidden=(32,), dtype=torch.float64)
    target = copy.deepcopy(online)
    optimizer = torch.optim.Adam(online.parameters(), lr=1e-2)
    buffer = ReplayBuffer(2000, K + 2, dtype=torch.float64, seed=0)
    schedule = EpsilonSchedule(1.0, 0.1, steps // 3)
    rng = np.random.default_rng(0)
    state = int(rng.integers(K - 1))
    for step in range(steps):
        if rng.random() < schedule(step):
            action = int(rng.integers(2))
        else:
            with torch.no_grad():
                action = int(online(features[state]).argmax())
        nxt = max(state - 1, 0) if action == 0 else state + 1
        done = nxt == K - 1
        buffer.add(
            observation=features[state],
            action=action,
            reward=float(done),
            next_observation=features[nxt],
            terminal=done,
        )
        state = int(rng.integers(K - 1)) if done else nxt
        if len(buffer) >= 64:
            loss = dqn_loss(online, target, buffer.sample(64), gamma, double=True)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            update_target(target=target, online=online, tau=0.05)
    with torch.no_grad():
        learned = online(features[: K - 1]).numpy()
    np.testing.assert_allclose(learned, q_star, rtol=0, atol=0.02)


# ------------------------------------------------------------------- loss and targets


def _linear(weight: list[list[float]]) -> nn.Linear:
    layer = nn.Linear(2, 2, bias=False, dtype=torch.float64)
    with torch.no_grad():
        layer.weight.copy_(torch.tensor(weight, dtype=torch.float64))
    return layer


def _hand_batch() -> Transitions:
    return Transitions(
        observations=torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=torch.float64),
        actions=torch.tensor([1, 0]),
        rewards=torch.tensor([0.5, -1.0], dtype=torch.float64),
        next_observations=torch.tensor([[0.0, 1.0], [1.0, 0.0]], dtype=torch.float64),
        terminals=torch.tensor([False, True]),
    )


@pytest.mark.parametrize(
    ("double", "delta", "expected"),
    [
        # Q(s, a) = (3, 2). Targets: 0.5 + 0.9 · max(0, −1) = 0.5 and −1 (terminal);
        # errors 2.5 and 3 → Huber_1 = 2.0 and 2.5.
        (False, 1.0, 2.25),
        # Double DQN: online picks argmax (2, 4) = 1 at s′, target values it −1, so the
        # first target is 0.5 − 0.9 = −0.4; errors 3.4 and 3 → 2.9 and 2.5.
        (True, 1.0, 2.7),
        # δ = 5 keeps both errors quadratic: (2.5² + 3²) / 4.
        (False, 5.0, 3.8125),
    ],
)
def test_dqn_loss_by_hand(double: bool, delta: float, expected: float) -> None:
    online = _linear([[1.0, 2.0], [3.0, 4.0]])
    target = _linear([[5.0, 0.0], [0.0, -1.0]])
    loss = dqn_loss(online, target, _hand_batch(), 0.9, double=double, huber_delta=delta)
    assert loss.item() == pytest.approx(expected, abs=1e-12)
    loss.backward()
    assert target.weight.grad is None
    if delta == 1.0:  # both errors are clipped to 1, halved by the mean
        expected_grad = torch.tensor([[0.0, 0.5], [0.5, 0.0]], dtype=torch.float64)
        torch.testing.assert_close(online.weight.grad, expected_grad, rtol=0, atol=1e-15)


@pytest.mark.bitwise("a hard update copies the parameters")
def test_update_target_hard_and_soft() -> None:
    online = QNetwork(3, 2, 2, hidden=(4,), dtype=torch.float64)
    target = QNetwork(3, 2, 2, hidden=(4,), dtype=torch.float64)
    with torch.no_grad():
        for parameter in online.parameters():
            parameter.normal_()
    before = [p.detach().clone() for p in target.parameters()]
    update_target(target=target, online=online, tau=0.25)
    for old, new, followed in zip(before, target.parameters(), online.parameters(), strict=True):
        torch.testing.assert_close(new, 0.75 * old + 0.25 * followed, rtol=0, atol=1e-15)
    update_target(target=target, online=online)
    for new, followed in zip(target.parameters(), online.parameters(), strict=True):
        assert torch.equal(new, followed)


# -------------------------------------------------------------------------- replay buffer


def _add(buffer: ReplayBuffer, steps: range) -> None:
    """Transition t: observation (t, −t), action t mod 3, reward t, next (t + 1, 0),
    terminal for even t; all at once."""
    t = torch.tensor(list(steps), dtype=torch.float64)
    buffer.add(
        observation=torch.stack([t, -t], -1),
        action=torch.tensor([s % 3 for s in steps]),
        reward=t,
        next_observation=torch.stack([t + 1, torch.zeros_like(t)], -1),
        terminal=torch.tensor([s % 2 == 0 for s in steps]),
    )


@pytest.mark.bitwise("the buffer stores and returns copies of small integers")
def test_ring_buffer_keeps_the_last_capacity_transitions() -> None:
    buffer = ReplayBuffer(4, 2, dtype=torch.float64)
    for t in range(7):  # one at a time
        buffer.add(
            observation=torch.tensor([t, -t], dtype=torch.float64),
            action=t % 3,
            reward=float(t),
            next_observation=torch.tensor([t + 1, 0], dtype=torch.float64),
            terminal=t % 2 == 0,
        )
    assert len(buffer) == 4
    assert buffer.state_dict()["rewards"].tolist() == [4.0, 5.0, 6.0, 3.0]  # t in row t mod 4
    _add(buffer, range(7, 12))  # a batch that wraps around
    assert buffer.state_dict()["rewards"].tolist() == [8.0, 9.0, 10.0, 11.0]
    _add(buffer, range(12, 18))  # more than the capacity: the last 4 survive
    state = buffer.state_dict()
    assert state["rewards"].tolist() == [16.0, 17.0, 14.0, 15.0]
    assert state["actions"].tolist() == [16 % 3, 17 % 3, 14 % 3, 15 % 3]
    assert state["terminals"].tolist() == [True, False, True, False]
    assert state["observations"][:, 1].tolist() == [-16.0, -17.0, -14.0, -15.0]
    assert state["position"] == 18 % 4
    batch = buffer.sample(50)
    t = batch.rewards
    assert set(t.tolist()) <= {14.0, 15.0, 16.0, 17.0}
    assert torch.equal(batch.observations, torch.stack([t, -t], -1))
    assert torch.equal(batch.next_observations[:, 0], t + 1)
    assert torch.equal(batch.actions, t.long() % 3)
    assert torch.equal(batch.terminals, t.long() % 2 == 0)


@pytest.mark.bitwise("sampling returns copies of stored entries")
def test_sampling_is_uniform_and_seeded() -> None:
    buffers = [ReplayBuffer(8, 2, dtype=torch.float64, seed=seed) for seed in (1, 1, 2)]
    for buffer in buffers:
        _add(buffer, range(4))
    draws = 20_000
    rewards = buffers[0].sample(draws).rewards
    for t in range(4):
        frequency = float((rewards == t).double().mean())
        assert frequency == pytest.approx(0.25, abs=5 * math.sqrt(0.25 * 0.75 / draws))
    after = buffers[0].sample(32).rewards
    assert not torch.equal(after, rewards[:32])  # the generator moved on
    for buffer, same in ((buffers[1], True), (buffers[2], False)):
        assert torch.equal(buffer.sample(draws).rewards, rewards) is same
        assert torch.equal(buffer.sample(32).rewards, after) is same


@pytest.mark.bitwise("sampling returns copies of stored entries")
def test_buffer_state_dict_resumes_sampling() -> None:
    buffer = ReplayBuffer(16, (1, 2), seed=3)
    t = torch.arange(10.0)
    buffer.add(
        observation=t[:, None, None].expand(10, 1, 2),
        action=torch.zeros(10, dtype=torch.long),
        reward=t,
        next_observation=t[:, None, None].expand(10, 1, 2),
        terminal=torch.zeros(10, dtype=torch.bool),
    )
    buffer.sample(5)
    state = buffer.state_dict()
    expected = [buffer.sample(4).rewards for _ in range(3)]
    restored = ReplayBuffer(16, (1, 2), seed=99)
    restored.load_state_dict(state)
    assert len(restored) == 10
    for batch in expected:
        assert torch.equal(restored.sample(4).rewards, batch)
    with pytest.raises(ValueError, match="capacity"):
        ReplayBuffer(8, (1, 2)).load_state_dict(state)
    with pytest.raises(ValueError, match="observation_shape"):
        ReplayBuffer(16, 2).load_state_dict(state)


# ------------------------------------------------------------------------------ schedule


def test_epsilon_schedule() -> None:
    schedule = EpsilonSchedule(1.0, 0.1, 10)
    assert schedule(0) == 1.0
    assert schedule(5) == pytest.approx(0.55, abs=1e-15)
    assert schedule(10) == 0.1
    assert schedule(1000) == 0.1
    assert EpsilonSchedule(0.5, 0.2, 0)(0) == 0.2
    assert EpsilonSchedule(0.1, 0.5, 4)(2) == pytest.approx(0.3, abs=1e-15)  # may rise too


# ------------------------------------------------------------------------------ validation


@pytest.mark.parametrize(
    ("build", "name"),
    [
        (lambda: QNetwork(0, 1, 2), "num_states"),
        (lambda: QNetwork(2, -1, 2), "num_features"),
        (lambda: QNetwork(2, 1, 0), "num_actions"),
        (lambda: QNetwork(2, 1, 2, hidden=(0,)), "hidden"),
        (lambda: QNetwork.from_table(torch.zeros(3), 1), "q_table"),
        (lambda: QNetwork.from_table(torch.zeros(3, 2, dtype=torch.long), 1), "q_table"),
        (lambda: QNetwork.from_table(torch.full((3, 2), math.nan), 1), "q_table"),
        (lambda: ReplayBuffer(0, 2), "capacity"),
        (lambda: ReplayBuffer(4, 2, dtype=torch.long), "dtype"),
        (lambda: ReplayBuffer(4, 2, seed=-1), "seed"),
        (lambda: EpsilonSchedule(1.5, 0.1, 10), "start"),
        (lambda: EpsilonSchedule(1.0, -0.1, 10), "end"),
        (lambda: EpsilonSchedule(1.0, 0.1, -1), "steps"),
        (lambda: EpsilonSchedule()(-1), "step"),
    ],
)
def test_bad_construction_raises(build: Any, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        build()


def test_bad_network_inputs_raise() -> None:
    network = QNetwork(3, 1, 2, dtype=torch.float64)
    with pytest.raises(ValueError, match="features"):
        network(torch.zeros(5, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="features"):
        network(torch.zeros(5, 4, dtype=torch.float32))
    with pytest.raises(ValueError, match="features"):
        network(torch.full((4,), math.inf, dtype=torch.float64))
    with pytest.raises(ValueError, match="probabilities"):
        network.qmdp(torch.zeros(4, dtype=torch.float64))


def _transition(**changes: Any) -> dict[str, Any]:
    fields: dict[str, Any] = {
        "observation": torch.zeros(2),
        "action": 1,
        "reward": 0.0,
        "next_observation": torch.zeros(2),
        "terminal": False,
    }
    return fields | changes


@pytest.mark.parametrize(
    ("changes", "name"),
    [
        ({"observation": torch.zeros(3)}, "observation"),
        ({"observation": torch.zeros(2, dtype=torch.long)}, "observation"),
        ({"observation": torch.tensor([math.nan, 0.0])}, "observation"),
        ({"next_observation": torch.zeros(2, 2)}, "next_observation"),
        ({"action": 1.0}, "action"),
        ({"action": -1}, "action"),
        ({"action": torch.tensor([1, 2])}, "action"),
        ({"reward": math.nan}, "reward"),
        ({"reward": torch.zeros(3)}, "reward"),
        ({"terminal": 1}, "terminal"),
    ],
)
def test_bad_transitions_raise(changes: dict[str, Any], name: str) -> None:
    buffer = ReplayBuffer(4, 2)
    with pytest.raises(ValueError, match=name):
        buffer.add(**_transition(**changes))
    assert len(buffer) == 0


def test_bad_sampling_and_loss_inputs_raise() -> None:
    buffer = ReplayBuffer(4, 2, dtype=torch.float64)
    with pytest.raises(ValueError, match="empty"):
        buffer.sample(1)
    buffer.add(**_transition(observation=torch.zeros(2, dtype=torch.float64)))
    with pytest.raises(ValueError, match="batch_size"):
        buffer.sample(0)
    online = _linear([[1.0, 0.0], [0.0, 1.0]])
    target = copy.deepcopy(online)
    batch = _hand_batch()
    with pytest.raises(ValueError, match="gamma"):
        dqn_loss(online, target, batch, 1.5)
    with pytest.raises(ValueError, match="huber_delta"):
        dqn_loss(online, target, batch, 0.9, huber_delta=0.0)
    with pytest.raises(ValueError, match="batch"):
        dqn_loss(online, target, tuple(batch), 0.9)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="actions"):
        dqn_loss(online, target, batch._replace(actions=torch.tensor([0, 2])), 0.9)
    with pytest.raises(ValueError, match="actions"):
        dqn_loss(online, target, batch._replace(actions=torch.tensor([0.0, 1.0])), 0.9)
    with pytest.raises(ValueError, match="terminals"):
        dqn_loss(online, target, batch._replace(terminals=torch.tensor([0, 1])), 0.9)
    with pytest.raises(ValueError, match="next_observations"):
        dqn_loss(online, target, batch._replace(next_observations=torch.zeros(3, 2)), 0.9)
    with pytest.raises(ValueError, match="tau"):
        update_target(target=target, online=online, tau=0.0)
    with pytest.raises(ValueError, match="target"):
        update_target(target=online, online=online)
    with pytest.raises(ValueError, match="shapes"):
        update_target(target=nn.Linear(3, 2), online=online)
