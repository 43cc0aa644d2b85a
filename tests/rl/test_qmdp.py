"""QMDP: a tiger-like problem with hand-computed values, batching and broadcasting against
loops, validation."""

from __future__ import annotations

from typing import Any

import pytest
import torch

from torchcontact.rl import qmdp_action, qmdp_values

LISTEN, OPEN_LEFT, OPEN_RIGHT = 0, 1, 2

# Two states: tiger behind the left door (0) or the right door (1). Listening costs 1;
# opening the tiger's door costs 50, opening the other door pays 10.
TIGER_Q = torch.tensor(
    [
        [-1.0, -50.0, 10.0],  # tiger left: open the right door
        [-1.0, 10.0, -50.0],  # tiger right: open the left door
    ],
    dtype=torch.float64,
)


@pytest.mark.parametrize(
    ("belief", "values", "action"),
    [
        # 0.5·(−50) + 0.5·10 = −20 for either door: listening (−1) is the safe action.
        ((0.5, 0.5), (-1.0, -20.0, -20.0), LISTEN),
        # right door: 0.9·10 + 0.1·(−50) = 4; left door: 0.9·(−50) + 0.1·10 = −44.
        ((0.9, 0.1), (-1.0, -44.0, 4.0), OPEN_RIGHT),
        ((0.1, 0.9), (-1.0, 4.0, -44.0), OPEN_LEFT),
        ((1.0, 0.0), (-1.0, -50.0, 10.0), OPEN_RIGHT),
    ],
)
def test_tiger(belief: tuple[float, float], values: tuple[float, ...], action: int) -> None:
    p = torch.tensor(belief, dtype=torch.float64)
    torch.testing.assert_close(
        qmdp_values(TIGER_Q, p), torch.tensor(values, dtype=torch.float64), rtol=0, atol=1e-12
    )
    chosen = qmdp_action(TIGER_Q, p)
    assert chosen.dtype == torch.long
    assert chosen.shape == ()
    assert int(chosen) == action


def test_batched_equals_looped() -> None:
    generator = torch.Generator().manual_seed(0)
    B, K, A = (3, 4), 5, 6
    q = torch.randn(*B, K, A, generator=generator, dtype=torch.float64)
    p = torch.rand(*B, K, generator=generator, dtype=torch.float64)
    p = p / p.sum(-1, keepdim=True)
    values, actions = qmdp_values(q, p), qmdp_action(q, p)
    assert values.shape == (*B, A)
    assert actions.shape == B
    for i in range(B[0]):
        for j in range(B[1]):
            expected = sum(p[i, j, k] * q[i, j, k] for k in range(K))
            torch.testing.assert_close(values[i, j], expected, rtol=0, atol=1e-12)
            assert int(actions[i, j]) == max(range(A), key=lambda a: float(expected[a]))


def test_shared_table_broadcasts_over_beliefs() -> None:
    generator = torch.Generator().manual_seed(1)
    q = torch.randn(4, 3, generator=generator, dtype=torch.float64)
    p = torch.softmax(torch.randn(7, 4, generator=generator, dtype=torch.float64), -1)
    values = qmdp_values(q, p)
    assert values.shape == (7, 3)
    for n in range(7):
        torch.testing.assert_close(values[n], qmdp_values(q, p[n]), rtol=0, atol=1e-12)
    torch.testing.assert_close(values, p @ q, rtol=0, atol=1e-12)


def test_dtype_promotion_and_ties() -> None:
    q = torch.tensor([[1.0, 1.0, 0.0]], dtype=torch.float32)
    p = torch.tensor([1.0], dtype=torch.float64)
    assert qmdp_values(q, p).dtype == torch.float64
    assert int(qmdp_action(q, p)) == 0  # the lowest index among ties


@pytest.mark.parametrize(
    ("q", "p", "name"),
    [
        (TIGER_Q, torch.tensor([0.5, 0.25, 0.25], dtype=torch.float64), "probabilities"),
        (TIGER_Q, torch.tensor([1.2, -0.2], dtype=torch.float64), "probabilities"),
        (TIGER_Q, torch.tensor([0.5, 0.4], dtype=torch.float64), "probabilities"),
        (TIGER_Q, torch.tensor([torch.nan, 1.0], dtype=torch.float64), "probabilities"),
        (TIGER_Q, torch.tensor([1, 0]), "probabilities"),
        (TIGER_Q, torch.tensor(1.0, dtype=torch.float64), "probabilities"),
        (TIGER_Q[0], torch.tensor([0.5, 0.5], dtype=torch.float64), "q_values"),
        (TIGER_Q.clone().fill_(torch.inf), torch.tensor([0.5, 0.5]), "q_values"),
        (TIGER_Q.long(), torch.tensor([0.5, 0.5]), "q_values"),
        ([[1.0]], torch.tensor([1.0]), "q_values"),
        (TIGER_Q.expand(3, 2, 3), torch.full((4, 2), 0.5), "batch shapes"),
        (torch.zeros(2, 0), torch.tensor([0.5, 0.5]), "q_values"),
    ],
)
def test_bad_inputs_raise(q: Any, p: Any, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        qmdp_values(q, p)
    with pytest.raises(ValueError, match=name):
        qmdp_action(q, p)
