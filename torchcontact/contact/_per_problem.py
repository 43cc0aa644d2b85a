"""The loop shared by the per-problem (NumPy) reference solvers, Lemke and the QP fallback."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from numpy.typing import NDArray

from torchcontact.contact._lcp import (
    contact_mode,
    delassus,
    free_constraint_velocity,
    lcp_residual,
    relative_residual,
)
from torchcontact.contact._problem import ContactProblem
from torchcontact.contact._solution import Solution, SolveStatus

FloatArray = NDArray[np.float64]

#: Solves one problem restricted to its real slots: ``(W, q, mu, D) -> (p, ok, iterations)``
#: with ``W (N, N)`` the Delassus matrix and ``q (N,)`` the free constraint velocities of the
#: stacked rows ``[normals (K); friction directions (K·D)]``, ``mu (K,)``, and ``p (N,)`` the
#: stacked impulses ``[pn; pt]``.
SolveOne = Callable[[FloatArray, FloatArray, FloatArray, int], tuple[FloatArray, bool, int]]


def solve_one_by_one(
    problem: ContactProblem,
    solve_one: SolveOne,
    *,
    tolerance: float,
    mode_atol: float | None,
    normalize: bool = False,
) -> Solution:
    """Run ``solve_one`` on every problem of the batch (float64, NumPy) and collect a Solution.

    Args:
        problem: the contact problem, batch ``*B``, any device (converted to float64 on the
            CPU and detached; the solution returns to its device).
        solve_one: the per-problem solver.
        tolerance: tolerance on :func:`relative_residual` for ``converged``.
        mode_atol: tolerance of :func:`contact_mode` (``None``: its default).
        normalize: hand ``solve_one`` each problem in units that make its data of order one
            (:func:`_lcp_units`), for solvers whose internal tolerances are absolute.

    Returns:
        The :class:`Solution` in the problem's dtype and device; ``status.converged`` requires
        both ``solve_one``'s own success and the residual test.
    """
    batch, K, D = problem.batch_shape, problem.num_slots, problem.num_directions
    # NumPy solves each problem on the CPU: the batch moves there (and back in restore_batch)
    cpu = torch.device("cpu")
    flat = problem.to(dtype=torch.float64, device=cpu).flatten().map_tensors(torch.Tensor.detach)
    with torch.no_grad():
        W, Minv_JT = delassus(flat)
        v_free = flat.v_free()
        q_contact = free_constraint_velocity(flat, v_free=v_free)
    W_np, q_np = W.numpy(), q_contact.numpy()
    mask_np, mu_np = flat.slot_mask.numpy(), flat.mu.numpy()
    count = W_np.shape[0]
    impulses = np.zeros((count, K + K * D))
    succeeded = np.zeros(count, dtype=bool)
    iterations = np.zeros(count, dtype=np.int64)
    for index in range(count):
        slots = np.flatnonzero(mask_np[index])
        rows = np.concatenate([slots, K + (slots[:, None] * D + np.arange(D)).ravel()])
        W_rows, q_rows = W_np[index][np.ix_(rows, rows)], q_np[index][rows]
        velocity, impulse = _lcp_units(W_rows, q_rows) if normalize else (1.0, 1.0)
        p, ok, used = solve_one(
            W_rows * (impulse / velocity), q_rows / velocity, mu_np[index][slots], D
        )
        impulses[index, rows] = impulse * p
        succeeded[index], iterations[index] = ok, used

    p_all = torch.from_numpy(impulses)
    v_next = v_free + (Minv_JT @ p_all.unsqueeze(-1)).squeeze(-1)
    pn, pt = p_all[:, :K], p_all[:, K:].unflatten(-1, (K, D))
    residual = lcp_residual(flat, v_next=v_next, pn=pn, pt=pt)
    relative = relative_residual(flat, v_next=v_next, pn=pn, pt=pt, v_free=v_free)
    converged = torch.from_numpy(succeeded) & (relative <= tolerance)
    status = SolveStatus(
        converged=converged, residual=residual, iterations=torch.from_numpy(iterations)
    )
    mode = contact_mode(flat, v_next=v_next, pn=pn, pt=pt, atol=mode_atol)
    solution = Solution(v_next=v_next, pn=pn, pt=pt, mode=mode, status=status)
    return solution.restore_batch(batch, dtype=problem.dtype, device=problem.device)


def _lcp_units(W: FloatArray, q: FloatArray) -> tuple[float, float]:
    """Velocity and impulse units that make one problem's LCP data of order one.

    With ``p = impulse · p'`` and constraint velocities ``velocity · w'``, the LCP
    ``w = W p + q`` becomes ``w' = W (impulse / velocity) p' + q / velocity``; the friction
    cone rows are unchanged (``μ pn − Σ pt`` scales with the impulses, ``σ`` with the
    velocities). The velocity unit is the largest negative entry of ``q`` (what drives the
    impulses: a large positive entry, a slot far away, needs none) and the impulse unit the
    one that makes the largest entry of ``W`` one. The solvers' pivot and stopping tolerances
    are absolute, so this makes them relative: the answer is the same at every scale of
    ``h``, ``M`` and ``v``.
    """
    velocity = float(-q.min()) if q.size and q.min() < 0.0 else 1.0
    largest = float(np.abs(W).max()) if W.size else 0.0
    impulse = velocity / largest if largest > 0.0 else 1.0
    return velocity, impulse
