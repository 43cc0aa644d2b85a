"""The suite's own rule: no digit-exact comparison of floating-point results without a reason."""

from __future__ import annotations

import numpy as np
import pytest
import torch


def test_digit_exact_comparisons_of_floats_fail_an_unmarked_test() -> None:
    a = torch.tensor([0.1, 0.2], dtype=torch.float64)
    with pytest.raises(AssertionError, match="bit for bit"):
        torch.equal(a, a.clone())
    with pytest.raises(AssertionError, match="bit for bit"):
        torch.testing.assert_close(a, a.clone(), rtol=0, atol=0)
    with pytest.raises(AssertionError, match="bit for bit"):
        np.testing.assert_array_equal(a.numpy(), a.numpy())
    # Integers and booleans are exact: compared as they are.
    assert torch.equal(torch.arange(3), torch.arange(3))
    assert not torch.equal(torch.tensor([True]), torch.tensor([False]))
    np.testing.assert_array_equal(np.arange(3), [0, 1, 2])
    torch.testing.assert_close(a, a + 1e-17)  # with a tolerance: allowed


@pytest.mark.bitwise("a clone holds the same bits")
def test_a_marked_test_may_compare_bits() -> None:
    a = torch.tensor([0.1, 0.2], dtype=torch.float64)
    assert torch.equal(a, a.clone())
