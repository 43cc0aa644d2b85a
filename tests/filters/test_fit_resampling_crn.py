"""Common random numbers through optimal resampling: what the fit's evidence needs to be a
piecewise smooth function of the parameters for a fixed generator."""

from __future__ import annotations

import torch

from torchcontact.filters import optimal_resample

F64 = torch.float64


def test_children_of_equal_weight_are_drawn_alike_whatever_their_rounding() -> None:
    """Children of equal weight (modes with the same prediction) whose weights differ only by
    rounding in one order or the other: the same generator draws the same survivors with the
    same weights (their ranks by weight swap, their indices do not)."""
    base = torch.log(
        torch.tensor([0.3, 0.1, 0.1, 0.1, 0.1, 0.05, 0.05, 0.05, 0.05, 0.1], dtype=F64)
    )
    tied = [1, 2, 3, 4, 9]
    for seed in range(20):
        draws = []
        for sign in (1.0, -1.0):
            lw = base.clone()
            # rounding-sized perturbations that order the tied children one way, then the other
            lw[tied] += sign * 1e-15 * torch.arange(len(tied), dtype=F64)
            draws.append(optimal_resample(lw, 4, generator=torch.Generator().manual_seed(seed)))
        (a, wa), (b, wb) = draws
        assert (a == b).all(), (seed, a, b)  # integer indices: exact
        torch.testing.assert_close(wa, wb, rtol=0, atol=1e-12)


def test_survivors_leave_in_the_order_of_their_index_with_the_closed_form_weights() -> None:
    """Fearnhead–Clifford with ``N = 3`` of weights (0.5, 0.2, 0.2, 0.1): ``c`` solves
    ``Σ min(c w, 1) = 3``: 0.5 c ≥ 1 gives 1 + 0.5 c = 3, c = 4, so child 0 is kept with 0.5
    and two of the others are drawn with weight 1/c = 0.25 each (closed form)."""
    lw = torch.log(torch.tensor([0.1, 0.2, 0.5, 0.2], dtype=F64))
    for seed in range(10):
        index, new_lw = optimal_resample(lw, 3, generator=torch.Generator().manual_seed(seed))
        assert (index[1:] > index[:-1]).all()  # ascending child index
        assert 2 in index.tolist()
        expected = torch.tensor([0.5 if i == 2 else 0.25 for i in index.tolist()], dtype=F64)
        torch.testing.assert_close(new_lw.exp(), expected, rtol=1e-12, atol=0)
