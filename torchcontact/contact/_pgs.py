"""Batched projected Gauss–Seidel for large batches of contact problems."""

from __future__ import annotations

import torch
from torch import Tensor

from torchcontact._checks import check_int, check_positive
from torchcontact.contact._lcp import (
    contact_mode,
    default_tolerance,
    delassus,
    lcp_residual,
    relative_residual,
)
from torchcontact.contact._problem import ContactProblem
from torchcontact.contact._solution import Solution, SolveStatus


def solve_pgs(
    problem: ContactProblem,
    *,
    max_sweeps: int = 500,
    tol: float | None = None,
    check_every: int = 10,
) -> Solution:
    r"""Projected Gauss–Seidel on the impulses of every problem of the batch at once.

    Each sweep visits the contact slots in order; the batch is processed as one tensor, so the
    only Python loop runs over the ``K`` slots of a sweep. For slot ``k``, with the end
    velocity ``v⁺ = v_free + M⁻¹ Jᵀ p`` kept current:

    * normal: ``pn_k ← max(0, pn_k − (Jn_k v⁺ + bn_k + φ_k/h) / W_kk)``;
    * friction: ``pt_k ← Π(pt_k − (Jt_k v⁺ + bt_k) / L_k)`` with ``Π`` the Euclidean
      projection on ``{pt ≥ 0, Σ_d pt_d ≤ μ_k pn_k}`` and ``L_k`` a Gershgorin bound on
      the block's largest eigenvalue. The fixed points of this projected-gradient step are
      exactly the friction rows of the Stewart–Trinkle LCP (the cap's multiplier is σ); for
      ``D = 2`` the step is exact along the tangent.

    PGS converges linearly; it is not a reference solver. The residual of every problem is
    checked every ``check_every`` sweeps and the sweeps stop when all have met ``tol``.

    Args:
        problem: the contact problem, batch ``*B``.
        max_sweeps: sweep limit.
        tol: tolerance on the scale-invariant :func:`relative_residual`; default 1e-9
            (float64) or 1e-4 (float32).
        check_every: sweeps between residual checks.

    Returns:
        The :class:`Solution`; ``status.converged`` is ``False`` where the residual exceeds
        the tolerance after the last sweep. Not differentiable (no autograd graph).

    References:
        E. Catto, "Iterative dynamics with temporal coherence", GDC 2005.
        K. Erleben, "Velocity-based shock propagation for multibody dynamics animation",
        ACM TOG 26(2), 2007.
    """
    check_int("max_sweeps", max_sweeps, low=1)
    check_int("check_every", check_every, low=1)
    tolerance = default_tolerance(problem.dtype) if tol is None else check_positive("tol", tol)
    K, D = problem.num_slots, problem.num_directions
    with torch.no_grad():
        W, Minv_JT = delassus(problem)
        v_free = problem.v_free()
        mask = problem.slot_mask.to(problem.dtype)
        pn = torch.zeros_like(problem.phi)
        pt = torch.zeros_like(problem.b_tangent)
        v = v_free.clone()
        diag = W.diagonal(dim1=-2, dim2=-1)
        W_nn = diag[..., :K].clamp(min=torch.finfo(problem.dtype).tiny)
        W_tt = W[..., K:, K:].unflatten(-2, (K, D)).unflatten(-1, (K, D))
        block = W_tt.diagonal(dim1=-4, dim2=-2).movedim(-1, -3)  # (*B, K, D, D)
        lipschitz = block.abs().sum(dim=-1).amax(dim=-1).clamp(min=torch.finfo(problem.dtype).tiny)
        Minv_Jn = Minv_JT[..., :K]
        Minv_Jt = Minv_JT[..., K:].unflatten(-1, (K, D))
        bias = problem.b_normal + problem.phi / problem.h

        sweeps = 0
        converged = torch.zeros(problem.batch_shape, dtype=torch.bool, device=problem.device)
        while sweeps < max_sweeps:
            for k in range(K):
                gap_rate = (problem.Jn[..., k, :] * v).sum(dim=-1) + bias[..., k]
                new_pn = (pn[..., k] - gap_rate / W_nn[..., k]).clamp(min=0.0) * mask[..., k]
                v = v + Minv_Jn[..., k] * (new_pn - pn[..., k]).unsqueeze(-1)
                pn[..., k] = new_pn
                slip = (problem.Jt[..., k, :, :] @ v.unsqueeze(-1)).squeeze(-1)
                slip = slip + problem.b_tangent[..., k, :]
                step = pt[..., k, :] - slip / lipschitz[..., k].unsqueeze(-1)
                cap = problem.mu[..., k] * new_pn
                new_pt = project_capped_simplex(step, cap) * mask[..., k].unsqueeze(-1)
                v = v + (Minv_Jt[..., k, :] @ (new_pt - pt[..., k, :]).unsqueeze(-1)).squeeze(-1)
                pt[..., k, :] = new_pt
            sweeps += 1
            if sweeps % check_every == 0 or sweeps == max_sweeps:
                v = v_free + (Minv_JT @ torch.cat([pn, pt.flatten(-2)], -1).unsqueeze(-1))[..., 0]
                converged = (
                    relative_residual(problem, v_next=v, pn=pn, pt=pt, v_free=v_free) <= tolerance
                )
                if bool(converged.all()):
                    break
        v_next = v_free + (Minv_JT @ torch.cat([pn, pt.flatten(-2)], -1).unsqueeze(-1))[..., 0]
        residual = lcp_residual(problem, v_next=v_next, pn=pn, pt=pt)
        converged = (
            relative_residual(problem, v_next=v_next, pn=pn, pt=pt, v_free=v_free) <= tolerance
        )
        mode = contact_mode(problem, v_next=v_next, pn=pn, pt=pt, atol=max(10 * tolerance, 1e-7))
    iterations = torch.full(problem.batch_shape, sweeps, dtype=torch.long, device=problem.device)
    status = SolveStatus(converged=converged, residual=residual, iterations=iterations)
    return Solution(v_next=v_next, pn=pn, pt=pt, mode=mode, status=status)


def project_capped_simplex(x: Tensor, cap: Tensor) -> Tensor:
    """Euclidean projection of ``x`` onto ``{y ≥ 0, Σ y ≤ cap}`` (batched).

    Args:
        x: ``(*B, D)`` points.
        cap: ``(*B,)`` non-negative caps.

    Returns:
        ``(*B, D)`` projections: ``max(x, 0)`` when its sum is within the cap, otherwise the
        projection onto the simplex ``{y ≥ 0, Σ y = cap}`` (Held, Wolfe and Crowder 1974).
    """
    positive = x.clamp(min=0.0)
    inside = positive.sum(dim=-1) <= cap
    sorted_x = x.sort(dim=-1, descending=True).values
    cumulative = sorted_x.cumsum(dim=-1) - cap.unsqueeze(-1)
    counts = torch.arange(1, x.shape[-1] + 1, dtype=x.dtype, device=x.device)
    support = (sorted_x - cumulative / counts) > 0
    last = (support.to(torch.long) * torch.arange(x.shape[-1], device=x.device)).amax(dim=-1)
    theta = cumulative.gather(-1, last.unsqueeze(-1)) / (last.unsqueeze(-1) + 1).to(x.dtype)
    on_simplex = (x - theta).clamp(min=0.0)
    return torch.where(inside.unsqueeze(-1), positive, on_simplex)
