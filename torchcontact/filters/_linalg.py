"""Small batched linear algebra in the batch-last layout used by every filter kernel.

The filters work on many small matrices at once (thousands of 6 × 6 covariances). On a CPU,
``torch.matmul`` over a ``(B, 6, 6)`` batch pays a per-matrix BLAS call and is several times
slower than elementwise arithmetic over a *batch-last* ("structure of arrays") layout, where a
batch of ``r × c`` matrices is one tensor ``(r, c, *B)`` whose trailing, contiguous batch
dimensions vectorize (and runs no intra-op thread pool for small batches, which also avoids
LAPACK's per-matrix overhead and its thread start-up cost). The kernels below take and
return that layout:

* a batch of vectors is ``(n, *B)``, a batch of matrices ``(r, c, *B)``;
* every operand of one call carries the same number of batch dimensions (use ``1`` to
  broadcast), so the event dimensions always lead.

:func:`to_batch_last` / :func:`to_batch_first` convert from/to the public ``(*B, n)`` /
``(*B, r, c)`` layout; the public tensors the filters return are views of batch-last storage,
so chaining filter calls does not copy. Matrices up to ``_UNROLL_MAX`` rows are factored by an
unrolled elementwise Cholesky.
"""

from __future__ import annotations

import torch
from torch import Tensor

_UNROLL_MAX = 8  # largest matrix handled by the unrolled Cholesky and triangular solves
_REDUCE_MAX = 1 << 15  # largest broadcast intermediate of a product; beyond it, accumulate


def to_batch_last(x: Tensor, event_ndim: int, batch_ndim: int) -> Tensor:
    """Move the trailing ``event_ndim`` dims of ``x`` to the front; pad the batch dims with 1s.

    Args:
        x: ``(*B', *E)`` with ``len(E) == event_ndim`` and ``len(B') <= batch_ndim``.
        event_ndim: number of trailing event dimensions (1 for vectors, 2 for matrices).
        batch_ndim: number of batch dimensions of the result.

    Returns:
        ``(*E, *B)`` contiguous, where ``B`` is ``B'`` left-padded with 1s to ``batch_ndim``
        (no copy when ``x`` already is a view of batch-last storage).
    """
    pad = batch_ndim - (x.ndim - event_ndim)
    if pad > 0:
        x = x.reshape((1,) * pad + tuple(x.shape))
    src = list(range(x.ndim - event_ndim, x.ndim))
    return x.movedim(src, list(range(event_ndim))).contiguous()


def to_batch_first(x: Tensor, event_ndim: int) -> Tensor:
    """Inverse of :func:`to_batch_last`: ``(*E, *B)`` → a ``(*B, *E)`` view (no copy)."""
    return x.movedim(list(range(event_ndim)), list(range(x.ndim - event_ndim, x.ndim)))


def _product(
    a: Tensor,
    b: Tensor,
    a_dims: tuple[int, int],
    b_dims: tuple[int, int],
    size: int | None = None,
) -> Tensor:
    """``out[i, j] = Σ_l a[i, l] b[l, j]`` where ``a``'s (i, l) and ``b``'s (l, j) dims are given.

    Small batches use one broadcast product and a reduction (fewest kernel launches); large
    ones accumulate over ``l`` to keep the intermediate in cache. The two round differently, so
    a caller that computes a block of a larger product passes that product's ``size``
    (entries of the broadcast intermediate) to get the block's entries to the bit.
    """
    rows, inner, cols = a.shape[a_dims[0]], a.shape[a_dims[1]], b.shape[b_dims[1]]
    if size is None:
        size = rows * inner * cols
        for sa, sb in zip(a.shape[2:], b.shape[2:], strict=True):  # same batch ndim
            size *= max(sa, sb)
    # as (i, l, 1, *B) and (1, l, j, *B)
    a3 = a.unsqueeze(2) if a_dims == (0, 1) else a.transpose(0, 1).unsqueeze(2)
    b3 = b.unsqueeze(0) if b_dims == (0, 1) else b.transpose(0, 1).unsqueeze(0)
    if size <= _REDUCE_MAX:
        return (a3 * b3).sum(1)
    a_cols = a3.unbind(1)  # each (i, 1, *B)
    b_rows = b3.unbind(1)  # each (1, j, *B)
    out = a_cols[0] * b_rows[0]
    for a_col, b_row in zip(a_cols[1:], b_rows[1:], strict=True):
        out.addcmul_(a_col, b_row)
    return out


def mm(a: Tensor, b: Tensor, *, size: int | None = None) -> Tensor:
    """``a @ b``: ``(r, k, *B)``, ``(k, c, *B)`` → ``(r, c, *B)``."""
    return _product(a, b, (0, 1), (0, 1), size)


def mm_t(a: Tensor, b: Tensor, *, size: int | None = None) -> Tensor:
    """``a @ bᵀ``: ``(r, k, *B)``, ``(c, k, *B)`` → ``(r, c, *B)``."""
    return _product(a, b, (0, 1), (1, 0), size)


def mtm(a: Tensor, b: Tensor, *, size: int | None = None) -> Tensor:
    """``aᵀ @ b``: ``(k, r, *B)``, ``(k, c, *B)`` → ``(r, c, *B)``."""
    return _product(a, b, (1, 0), (0, 1), size)


def mv(a: Tensor, v: Tensor) -> Tensor:
    """``a @ v``: ``(r, k, *B)``, ``(k, *B)`` → ``(r, *B)``."""
    return (a * v.unsqueeze(0)).sum(1)


def mtv(a: Tensor, v: Tensor) -> Tensor:
    """``aᵀ @ v``: ``(k, r, *B)``, ``(k, *B)`` → ``(r, *B)``."""
    return (a * v.unsqueeze(1)).sum(0)


def add_(fresh: Tensor, other: Tensor, *, alpha: float = 1.0) -> Tensor:
    """``fresh + alpha * other``, in place in ``fresh`` when it already has the broadcast shape.

    ``fresh`` must be a temporary that nothing else holds (the output of a kernel here): large
    batches then allocate fewer fresh buffers, and autograd is unaffected because none of these
    kernels saves its output for the backward pass.
    """
    if all(o == 1 or o == f for f, o in zip(fresh.shape, other.shape, strict=True)):
        return fresh.add_(other, alpha=alpha)
    return torch.add(fresh, other, alpha=alpha)


def symmetrize(a: Tensor) -> Tensor:
    """``(A + Aᵀ) / 2`` for ``(n, n, *B)``; the result is exactly symmetric."""
    return (a + a.transpose(0, 1)).mul_(0.5)


def eye(n: int, batch_ndim: int, like: Tensor) -> Tensor:
    """Identity ``(n, n, 1, ..., 1)`` with ``batch_ndim`` trailing 1s, dtype/device of ``like``."""
    return torch.eye(n, dtype=like.dtype, device=like.device).reshape((n, n) + (1,) * batch_ndim)


def _unrolled_cholesky(a: Tensor, *, semidefinite: bool) -> list[list[Tensor]]:
    """Entry-wise Cholesky of ``(m, m, *B)``: ``low[i][j]`` is ``L[i, j]`` (``(*B)``, ``j <= i``).

    Strict mode takes square roots of the pivots as they are (a non-positive pivot gives NaN or
    inf downstream). Semi-definite mode clamps non-positive pivots to zero and zeroes the rest
    of that column, with finite gradients everywhere.
    """
    m = a.shape[0]
    rows = [row.unbind(0) for row in a.unbind(0)]
    low: list[list[Tensor]] = [[] for _ in range(m)]
    for j in range(m):
        pivot = rows[j][j]
        for k in range(j):
            pivot = torch.addcmul(pivot, low[j][k], low[j][k], value=-1)
        if semidefinite:
            # 1/sqrt(pivot) where positive, else 0 (no NaN, finite gradients)
            inv = torch.rsqrt(pivot.clamp_min(torch.finfo(pivot.dtype).tiny)) * (pivot > 0)
            diag = pivot * inv
        else:
            diag = torch.sqrt(pivot)
            inv = torch.reciprocal(diag)
        for i in range(j + 1, m):
            acc = rows[i][j]
            for k in range(j):
                acc = torch.addcmul(acc, low[i][k], low[j][k], value=-1)
            low[i].append(acc * inv)
        low[j].append(diag)
    return low


def _dense_lower(low: list[list[Tensor]]) -> Tensor:
    """``(n, n, *B)`` lower-triangular matrix from the entries of :func:`_unrolled_cholesky`."""
    n = len(low)
    zero = torch.zeros_like(low[0][0])
    entries = [low[i][j] if j <= i else zero for i in range(n) for j in range(n)]
    return torch.stack(entries).reshape(n, n, *zero.shape)


def psd_cholesky(a: Tensor, *, entrywise: bool = False) -> Tensor:
    """Lower factor ``L`` with ``L Lᵀ = A`` of symmetric positive **semi**-definite matrices.

    The plain factorization is tried first; if any matrix of the batch has a non-positive
    pivot, the batch is refactored by :func:`semidefinite_cholesky` (one host
    synchronization). With ``entrywise`` every matrix takes the semi-definite factorization
    directly: no host synchronization, for compiled kernels, and the same factor to rounding
    on positive definite matrices (its pivots' reciprocal square roots are computed as
    ``rsqrt`` instead of ``1 / sqrt``). Only the lower triangle is read. Matrices above
    ``_UNROLL_MAX`` always take the semi-definite factorization.

    Args:
        a: ``(n, n, *B)``.
        entrywise: the semi-definite factorization for every matrix (no host sync).

    Returns:
        ``(n, n, *B)`` lower-triangular factor.
    """
    if entrywise or a.shape[0] > _UNROLL_MAX:
        return semidefinite_cholesky(a)
    low = _dense_lower(_unrolled_cholesky(a, semidefinite=False))
    if bool(torch.isfinite(low).all()):
        return low
    return semidefinite_cholesky(a)


def semidefinite_cholesky(a: Tensor) -> Tensor:
    """The factor of positive semi-definite matrices with non-positive pivots clamped to zero.

    The rest of a clamped pivot's column is zeroed: exact for singular PSD matrices, a PSD
    projection of rounding noise below zero otherwise (never a NaN; gradients stay finite).
    Only the lower triangle is read. Elementwise kernels only (LAPACK's batched Cholesky has
    no semi-definite mode, and a per-matrix cost).

    Args:
        a: ``(n, n, *B)``.

    Returns:
        ``(n, n, *B)`` lower-triangular factor.
    """
    n = a.shape[0]
    if n <= _UNROLL_MAX:
        return _dense_lower(_unrolled_cholesky(a, semidefinite=True))
    # Column-oriented variant for larger matrices: n vectorized iterations instead of n³/6.
    lower = torch.ones(n, n, dtype=a.dtype, device=a.device).tril()
    lower = lower.reshape((n, n) + (1,) * (a.ndim - 2))
    cols: list[Tensor] = []
    for j in range(n):
        v = a[:, j]
        if j:
            prev = torch.stack(cols, dim=1)  # (n, j, *B)
            v = v - (prev * prev[j].unsqueeze(0)).sum(1)
        pivot = v[j]
        scale = torch.rsqrt(pivot.clamp_min(torch.finfo(pivot.dtype).tiny)) * (pivot > 0)
        cols.append(v * (scale.unsqueeze(0) * lower[:, j]))
    return torch.stack(cols, dim=1)


class Cholesky:
    """Lower Cholesky factor ``L`` of a batch of symmetric positive definite matrices, with
    triangular solves.

    Only the lower triangle of the input is read. A matrix that is not positive definite gives
    non-finite results (never an exception), so a batched caller checks once at the end.
    Matrices up to ``_UNROLL_MAX`` use the unrolled elementwise kernel, larger ones LAPACK.

    Args:
        a: ``(m, m, *B)``.
    """

    def __init__(self, a: Tensor) -> None:
        m = a.shape[0]
        self.size = m
        self._dense: Tensor | None = None
        self._entries: list[list[Tensor]] = []
        if m > _UNROLL_MAX:
            dense, info = torch.linalg.cholesky_ex(to_batch_first(a, 2))
            dense = torch.where((info == 0)[..., None, None], dense, torch.nan)
            self._dense = to_batch_last(dense, 2, a.ndim - 2)
        else:
            self._entries = _unrolled_cholesky(a, semidefinite=False)

    def solve(self, b: Tensor) -> Tensor:
        """``L⁻¹ b`` for ``b`` ``(m, *R)`` with ``R`` broadcasting against ``*B`` on the right
        (``(m, c, *B)`` for a matrix, ``(m, *B)`` for a vector)."""
        if self._dense is not None:
            return _dense_solve(self._dense, b, transpose=False)
        low = self._entries
        rows: list[Tensor] = []
        for i, b_i in enumerate(b.unbind(0)):
            acc = b_i
            for k in range(i):
                acc = torch.addcmul(acc, low[i][k], rows[k], value=-1)
            rows.append(acc / low[i][i])
        return torch.stack(rows)

    def solve_transpose(self, b: Tensor) -> Tensor:
        """``L⁻ᵀ b``, shapes as in :meth:`solve`."""
        if self._dense is not None:
            return _dense_solve(self._dense, b, transpose=True)
        low, m = self._entries, self.size
        b_rows = b.unbind(0)
        rows: list[Tensor] = []  # rows[j] is the solution row m - 1 - j
        for i in reversed(range(m)):
            acc = b_rows[i]
            for k in range(i + 1, m):
                acc = torch.addcmul(acc, low[k][i], rows[m - 1 - k], value=-1)
            rows.append(acc / low[i][i])
        return torch.stack(rows[::-1])

    def log_det(self) -> Tensor:
        """``log det(L Lᵀ)``, ``(*B)``."""
        if self._dense is not None:
            return 2.0 * torch.log(torch.diagonal(self._dense, dim1=0, dim2=1)).sum(-1)
        diag = torch.stack([self._entries[i][i] for i in range(self.size)])
        return 2.0 * torch.log(diag).sum(0)


def _dense_solve(low: Tensor, b: Tensor, *, transpose: bool) -> Tensor:
    """LAPACK triangular solve with ``L`` or ``Lᵀ``: ``low (m, m, *B)``, ``b`` as in ``solve``."""
    vector = b.ndim == low.ndim - 1
    rhs = b.unsqueeze(1) if vector else b
    batch = torch.broadcast_shapes(rhs.shape[2:], low.shape[2:])
    low_f = to_batch_first(low.expand(*low.shape[:2], *batch), 2)
    rhs_f = to_batch_first(rhs.expand(*rhs.shape[:2], *batch), 2)
    x = torch.linalg.solve_triangular(low_f.mT if transpose else low_f, rhs_f, upper=transpose)
    out = to_batch_last(x, 2, len(batch))
    return out.squeeze(1) if vector else out
