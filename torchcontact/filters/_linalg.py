"""Small batched linear algebra in the batch-last layout used by every filter kernel.

The filters work on many small matrices at once (thousands of 6 × 6 covariances). On a CPU,
``torch.matmul`` over a ``(B, 6, 6)`` batch pays a per-matrix BLAS call and is several times
slower than elementwise arithmetic over a *batch-last* ("structure of arrays") layout, where a
batch of ``r × c`` matrices is one tensor ``(r, c, *B)`` whose trailing, contiguous batch
dimensions vectorize. The kernels below take and return that layout:

* a batch of vectors is ``(n, *B)``, a batch of matrices ``(r, c, *B)``;
* every operand of one call carries the same number of batch dimensions (use ``1`` to
  broadcast), so the event dimensions always lead.

:func:`to_batch_last` / :func:`to_batch_first` convert from/to the public ``(*B, n)`` /
``(*B, r, c)`` layout; the public tensors the filters return are views of batch-last storage,
so chaining filter calls never copies. Matrix sizes up to ``_UNROLL_MAX`` use unrolled
elementwise Cholesky and triangular solves; larger ones fall back to LAPACK.
"""

from __future__ import annotations

import torch
from torch import Tensor

_UNROLL_MAX = 8  # largest Cholesky / triangular-solve size handled by the unrolled kernels
_MATMUL_LOOP_MIN = 1 << 18  # intermediate size above which mm() accumulates instead of reducing


def to_batch_last(x: Tensor, event_ndim: int, batch_ndim: int) -> Tensor:
    """Move the trailing ``event_ndim`` dims of ``x`` to the front; pad the batch dims with 1s.

    Args:
        x: ``(*B', *E)`` with ``len(E) == event_ndim`` and ``len(B') <= batch_ndim``.
        event_ndim: number of trailing event dimensions (1 for vectors, 2 for matrices).
        batch_ndim: number of batch dimensions of the result.

    Returns:
        ``(*E, *B)`` contiguous, where ``B`` is ``B'`` left-padded with 1s to ``batch_ndim``
        (a no-op copy-free view when ``x`` already is a view of batch-last storage).
    """
    pad = batch_ndim - (x.ndim - event_ndim)
    if pad > 0:
        x = x.reshape((1,) * pad + tuple(x.shape))
    src = list(range(x.ndim - event_ndim, x.ndim))
    return x.movedim(src, list(range(event_ndim))).contiguous()


def to_batch_first(x: Tensor, event_ndim: int) -> Tensor:
    """Inverse of :func:`to_batch_last`: ``(*E, *B)`` → a ``(*B, *E)`` view (no copy)."""
    return x.movedim(list(range(event_ndim)), list(range(x.ndim - event_ndim, x.ndim)))


def transpose(a: Tensor) -> Tensor:
    """``(r, c, *B)`` → ``(c, r, *B)`` view."""
    return a.transpose(0, 1)


def mm(a: Tensor, b: Tensor) -> Tensor:
    """Batched matrix product ``a @ b``: ``(r, k, *B)``, ``(k, c, *B)`` → ``(r, c, *B)``."""
    r, k = a.shape[0], a.shape[1]
    c = b.shape[1]
    batch = torch.broadcast_shapes(a.shape[2:], b.shape[2:])
    if r * k * c * batch.numel() <= _MATMUL_LOOP_MIN:
        return (a.unsqueeze(2) * b.unsqueeze(0)).sum(1)
    out = a[:, 0].unsqueeze(1) * b[0].unsqueeze(0)
    for i in range(1, k):
        out = torch.addcmul(out, a[:, i].unsqueeze(1), b[i].unsqueeze(0))
    return out


def mv(a: Tensor, v: Tensor) -> Tensor:
    """Batched matrix-vector product: ``(r, k, *B)``, ``(k, *B)`` → ``(r, *B)``."""
    return (a * v.unsqueeze(0)).sum(1)


def symmetrize(a: Tensor) -> Tensor:
    """``(A + Aᵀ) / 2`` for ``(n, n, *B)``; the result is exactly symmetric."""
    return 0.5 * (a + a.transpose(0, 1))


def eye(n: int, batch_ndim: int, like: Tensor) -> Tensor:
    """Identity ``(n, n, 1, ..., 1)`` with ``batch_ndim`` trailing 1s, dtype/device of ``like``."""
    return torch.eye(n, dtype=like.dtype, device=like.device).reshape((n, n) + (1,) * batch_ndim)


def cholesky(a: Tensor) -> Tensor:
    """Lower Cholesky factor of symmetric positive definite ``(m, m, *B)`` matrices.

    A matrix that is not positive definite yields a factor with non-finite entries (never an
    exception), so batched callers can check the whole batch at once.
    """
    m = a.shape[0]
    if m > _UNROLL_MAX:
        low, info = torch.linalg.cholesky_ex(to_batch_first(a, 2))
        low = torch.where((info == 0)[..., None, None], low, torch.nan)
        return to_batch_last(low, 2, a.ndim - 2)
    cols: list[Tensor] = []
    for j in range(m):
        v = a[j:, j]
        for k in range(j):
            v = v - cols[k][j:] * cols[k][j]
        v = v / torch.sqrt(v[0])
        cols.append(torch.cat([v.new_zeros((j, *v.shape[1:])), v]) if j > 0 else v)
    return torch.stack(cols, dim=1)


def solve_lower(low: Tensor, b: Tensor) -> Tensor:
    """Solve ``L X = B`` by forward substitution: ``(m, m, *B)``, ``(m, c, *B)`` → ``(m, c, *B)``."""
    m = low.shape[0]
    if m > _UNROLL_MAX:
        x = torch.linalg.solve_triangular(
            to_batch_first(low, 2), to_batch_first(b, 2), upper=False
        )
        return to_batch_last(x, 2, x.ndim - 2)
    rows: list[Tensor] = []
    for i in range(m):
        acc = b[i]
        for k in range(i):
            acc = acc - low[i, k].unsqueeze(0) * rows[k]
        rows.append(acc / low[i, i].unsqueeze(0))
    return torch.stack(rows)


def solve_lower_transpose(low: Tensor, b: Tensor) -> Tensor:
    """Solve ``Lᵀ X = B`` by back substitution: ``(m, m, *B)``, ``(m, c, *B)`` → ``(m, c, *B)``."""
    m = low.shape[0]
    if m > _UNROLL_MAX:
        x = torch.linalg.solve_triangular(
            to_batch_first(low, 2).mT, to_batch_first(b, 2), upper=True
        )
        return to_batch_last(x, 2, x.ndim - 2)
    rows: list[Tensor] = []  # rows[j] is the solution row m - 1 - j
    for i in reversed(range(m)):
        acc = b[i]
        for k in range(i + 1, m):
            acc = acc - low[k, i].unsqueeze(0) * rows[m - 1 - k]
        rows.append(acc / low[i, i].unsqueeze(0))
    return torch.stack(rows[::-1])


def cholesky_solve(low: Tensor, b: Tensor) -> Tensor:
    """Solve ``(L Lᵀ) X = B`` given the lower Cholesky factor: ``(m, c, *B)`` → ``(m, c, *B)``."""
    return solve_lower_transpose(low, solve_lower(low, b))


def log_det_cholesky(low: Tensor) -> Tensor:
    """``log det(L Lᵀ)`` from the lower Cholesky factor ``(m, m, *B)`` → ``(*B)``."""
    return 2.0 * torch.log(torch.diagonal(low, dim1=0, dim2=1)).sum(-1)
