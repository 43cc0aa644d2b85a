"""greedy_action: the argmax of batched action values with one tie rule, against NumPy."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchcontact.rl import greedy_action, qmdp_action


def _numpy_greedy(values: np.ndarray, keys: np.ndarray | None) -> np.ndarray:
    """Per row: the maximizing actions; the first, or the one of highest key."""
    out = np.zeros(values.shape[0], dtype=np.int64)
    for b, row in enumerate(values):
        best = np.flatnonzero(row == row.max())
        out[b] = best[0] if keys is None else best[np.argmax(keys[b, best])]
    return out


def _values_with_ties(seed: int, B: int = 400, A: int = 5) -> torch.Tensor:
    """Small integers: many exact ties between actions."""
    generator = torch.Generator().manual_seed(seed)
    return torch.randint(-2, 2, (B, A), generator=generator).to(torch.float64)


def test_ties_go_to_the_lowest_index_without_a_generator() -> None:
    values = _values_with_ties(0)
    tied = (values == values.amax(-1, keepdim=True)).sum(-1) > 1
    assert bool(tied.any())
    got = greedy_action(values)
    assert got.dtype == torch.long
    assert got.tolist() == _numpy_greedy(values.numpy(), None).tolist()


def test_ties_go_to_the_highest_key_of_the_generator() -> None:
    values = _values_with_ties(1)
    keys = torch.rand(values.shape, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    got = greedy_action(values, generator=torch.Generator().manual_seed(9))
    assert got.tolist() == _numpy_greedy(values.numpy(), keys.numpy()).tolist()


def test_random_ties_are_uniform_and_the_generator_advances_the_same_either_way() -> None:
    values = torch.tensor([[1.0, 3.0, 3.0, 0.0, 3.0]] * 6000, dtype=torch.float64)
    generator = torch.Generator().manual_seed(4)
    counts = np.bincount(greedy_action(values, generator=generator).numpy(), minlength=5)
    assert counts[0] == counts[3] == 0
    # Binomial(6000, 1/3): standard deviation 36.5; 5 of them.
    assert np.all(np.abs(counts[[1, 2, 4]] - 2000) < 5 * 36.5)
    other = torch.Generator().manual_seed(4)
    torch.rand(values.shape, generator=other, dtype=torch.float64)
    assert torch.equal(generator.get_state(), other.get_state())
    untied = torch.arange(5.0, dtype=torch.float64).expand(6000, 5)
    assert bool((greedy_action(untied, generator=generator) == 4).all())
    torch.rand(values.shape, generator=other, dtype=torch.float64)
    assert torch.equal(generator.get_state(), other.get_state())


def test_batch_shape_and_float32() -> None:
    values = _values_with_ties(2, B=24).to(torch.float32).reshape(2, 3, 4, 5)
    got = greedy_action(values)
    assert got.shape == (2, 3, 4)
    flat = _numpy_greedy(values.reshape(-1, 5).numpy(), None)
    assert got.reshape(-1).tolist() == flat.tolist()


def test_qmdp_action_breaks_ties_by_the_same_rule() -> None:
    q = torch.tensor([[1.0, 0.0, 1.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
    p = torch.tensor([[1.0, 0.0]] * 200, dtype=torch.float64)  # actions 0 and 2 tie
    assert bool((qmdp_action(q, p) == 0).all())
    keys = torch.rand(200, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    expected = torch.where(keys[:, 0] > keys[:, 2], 0, 2)
    got = qmdp_action(q, p, generator=torch.Generator().manual_seed(2))
    assert got.tolist() == expected.tolist()


@pytest.mark.parametrize(
    ("values", "generator", "name"),
    [
        ([1.0, 2.0], None, "values"),
        (torch.tensor([1, 2]), None, "values"),
        (torch.tensor([1.0, float("nan")]), None, "values"),
        (torch.zeros(3, 0), None, "values"),
        (torch.zeros(()), None, "values"),
        (torch.zeros(3, 2), 7, "generator"),
    ],
)
def test_bad_input_names_the_argument(values: object, generator: object, name: str) -> None:
    with pytest.raises(ValueError, match=f"^{name}"):
        greedy_action(values, generator=generator)  # type: ignore[arg-type]
