"""Solutions of contact problems and their per-problem solver status."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor


@dataclass(frozen=True, eq=False)
class SolveStatus:
    """How well each problem of a batch was solved.

    Attributes:
        converged: ``(*B,)`` bool, ``True`` where the solver met its tolerance. A solver never
            reports ``True`` for an answer it did not verify.
        residual: ``(*B,)`` natural-map complementarity residual of the Stewart–Trinkle LCP,
            ``max |min(z, w)|`` over all complementarity pairs (see :func:`lcp_residual`).
        iterations: ``(*B,)`` long, pivots (Lemke), projection rounds (QP), sweeps (PGS) or
            1 (mode solve).
    """

    converged: Tensor
    residual: Tensor
    iterations: Tensor

    def map_tensors(self, fn: Any) -> SolveStatus:
        """Apply ``fn`` to every tensor field (indexing, reshaping)."""
        return SolveStatus(fn(self.converged), fn(self.residual), fn(self.iterations))


@dataclass(frozen=True, eq=False)
class Solution:
    """The result of one batched contact step.

    Attributes:
        v_next: ``(*B, n)`` generalized velocity at the end of the step.
        pn: ``(*B, K)`` normal impulses over the step (zero for padding slots).
        pt: ``(*B, K, D)`` friction impulses along each friction direction, ``>= 0``.
        mode: ``(*B, K)`` long contact mode of each slot: 0 separated, 1 sticking,
            ``2 + d`` sliding with the friction impulse along direction ``d``, ``2 + D + d``
            (spatial) sliding with it between directions ``d`` and ``(d + 1) mod D``.
        status: per-problem convergence and residual.
    """

    v_next: Tensor
    pn: Tensor
    pt: Tensor
    mode: Tensor
    status: SolveStatus

    def map_tensors(self, fn: Any) -> Solution:
        """Apply ``fn`` to every tensor field, including the status."""
        return replace(
            self,
            v_next=fn(self.v_next),
            pn=fn(self.pn),
            pt=fn(self.pt),
            mode=fn(self.mode),
            status=self.status.map_tensors(fn),
        )

    def combine(self, other: Solution, fn: Any) -> Solution:
        """Apply ``fn(mine, theirs)`` field by field (status included) to two solutions."""
        return Solution(
            v_next=fn(self.v_next, other.v_next),
            pn=fn(self.pn, other.pn),
            pt=fn(self.pt, other.pt),
            mode=fn(self.mode, other.mode),
            status=SolveStatus(
                converged=fn(self.status.converged, other.status.converged),
                residual=fn(self.status.residual, other.status.residual),
                iterations=fn(self.status.iterations, other.status.iterations),
            ),
        )

    def scatter(self, index: Tensor, update: Solution) -> Solution:
        """This solution of a flat batch ``(B,)`` with entries ``index`` replaced by ``update``.

        Differentiable with respect to both (``index_put`` out of place).
        """
        return self.combine(update, lambda a, b: a.index_put((index,), b.to(a.dtype)))

    def where(self, condition: Tensor, other: Solution) -> Solution:
        """Per entry of a flat batch ``(B,)``: this solution where ``condition``, else ``other``."""

        def pick(a: Tensor, b: Tensor) -> Tensor:
            return torch.where(condition.reshape(-1, *([1] * (a.dim() - 1))), a, b)

        return self.combine(other, pick)

    def restore_batch(
        self, batch_shape: tuple[int, ...], *, dtype: torch.dtype, device: torch.device
    ) -> Solution:
        """Reshape a solution of a flattened batch ``(B,)`` back to ``batch_shape`` and cast its
        floating fields to ``dtype`` on ``device``."""

        def restore(t: Tensor) -> Tensor:
            t = t.reshape((*batch_shape, *t.shape[1:]))
            return t.to(device=device, dtype=dtype if t.is_floating_point() else t.dtype)

        return self.map_tensors(restore)
