"""Mode-decoupled contact dynamics: one batched, differentiable linear solve per problem."""

from __future__ import annotations

import torch
from torch import Tensor

from torchcontact._checks import check_tensor
from torchcontact.contact._lcp import (
    STICKING,
    default_tolerance,
    friction_pair,
    is_face_sliding,
    is_sliding,
    lcp_residual,
    num_modes,
)
from torchcontact.contact._problem import ContactProblem
from torchcontact.contact._solution import Solution, SolveStatus
from torchcontact.contact._tikhonov import (
    ELIMINATION_MAX_ORDER,
    iterated_tikhonov,
    tikhonov_by_elimination,
    tikhonov_system,
)

#: Iterated-Tikhonov refinements of the constraint solve (see :func:`solve_mode`).
SOLVE_MODE_REFINEMENTS = 5
#: Smallest share of the largest normal impulse used to weight a friction split.
SOLVE_MODE_MIN_LOAD_SHARE = 1e-3
#: How much more a sticking friction impulse costs than a normal impulse in the split.
SOLVE_MODE_FRICTION_COST = 1e3
#: Refinements of the weighted pass, whose larger shifts converge more slowly.
SOLVE_MODE_WEIGHTED_REFINEMENTS = 10
#: Fewest problems for which the Schur system is cut to the rows some problem needs: below,
#: the gathers cost more host time than the smaller factorizations save.
COMPACT_MIN_BATCH = 64


def validate_mode(problem: ContactProblem, mode: Tensor) -> Tensor:
    """Check a mode tensor against a problem and broadcast it to ``(*B, K)``.

    Raises:
        ValueError: naming ``mode`` if it is not an integer tensor, does not broadcast to the
            problem's ``(*B, K)`` or holds values outside ``[0, num_modes(D))`` (``[0, 4)``
            planar, ``[0, 2 + 2D)`` spatial).
    """
    if not isinstance(mode, Tensor) or mode.is_floating_point() or mode.dtype == torch.bool:
        raise ValueError("mode must be an integer tensor of shape (*B, K)")
    shape = (*problem.batch_shape, problem.num_slots)
    try:
        mode = mode.to(device=problem.device, dtype=torch.long).expand(shape)
    except RuntimeError as error:
        raise ValueError(f"mode has shape {tuple(mode.shape)}; expected {shape}") from error
    D = problem.num_directions
    if mode.numel() and (int(mode.min()) < 0 or int(mode.max()) >= num_modes(D)):
        raise ValueError(f"mode values must lie in [0, {num_modes(D)}) for D = {D}")
    return mode


def solve_mode(
    problem: ContactProblem,
    mode: Tensor,
    *,
    initial_impulses: tuple[Tensor, Tensor] | None = None,
) -> Solution:
    r"""Solve the contact step with every slot's contact mode fixed.

    With the mode known, the complementarity conditions become equalities and the step is one
    linear system per problem. For slot ``k``:

    * separated (0): ``pn_k = 0`` and ``pt_k = 0``;
    * sticking (1): ``Jn_k v⁺ + bn_k + φ_k/h = 0`` and ``Jt_{k,j} v⁺ + bt_{k,j} = 0`` for a
      basis ``j`` of the tangent space (direction 0; directions 0 and 1 when spatial), with
      free tangential impulse ``λ_k`` along that basis;
    * sliding along ``d`` (``2 + d``, an edge of the friction cone): ``Jn_k v⁺ + bn_k + φ_k/h
      = 0`` and the friction impulse is ``μ_k pn_k`` along direction ``d``;
    * sliding on the face between ``d`` and ``e = (d + 1) mod D`` (``2 + D + d``, spatial
      only): both friction rows are active, ``Jt_{k,d} v⁺ + bt_{k,d} + σ_k = 0 =
      Jt_{k,e} v⁺ + bt_{k,e} + σ_k``, and so is the cone row, ``pt_{k,d} + pt_{k,e} = μ_k
      pn_k``. Eliminating the sliding speed ``σ_k`` leaves ``Jn_k v⁺ + bn_k + φ_k/h = 0`` and
      ``(Jt_{k,d} − Jt_{k,e}) v⁺ + bt_{k,d} − bt_{k,e} = 0`` (the slip lies in the normal cone
      of the face), with friction ``pt_{k,d} = μ_k pn_k / 2 + λ_k``, ``pt_{k,e} = μ_k pn_k / 2
      − λ_k`` for a free ``λ_k``. ``σ_k ≥ 0`` and ``pt ≥ 0`` are left to
      :func:`is_consistent`.

    Eliminating ``v⁺ = v_free + M⁻¹ Gᵀ x`` (``x`` the unknown impulses, ``G`` the rows along
    which they act: ``Jn_k + μ_k (Jt_{k,d} + Jt_{k,e}) / 2`` for sliding slots, ``e = d`` on
    an edge, and ``Jt_{k,d} − Jt_{k,e}`` for the ``λ_k`` of a face) leaves the Schur system
    ``C M⁻¹ Gᵀ x = r`` on the active rows ``C``. Redundant contacts (a box resting on
    two corners with identical friction rows, four coplanar corners in 3-D) make it singular
    but consistent: the end velocity is unique while the impulse split is not. The system is
    solved by iterated Tikhonov regularisation (``(A + εP) x_{i+1} = b + εP x_i``, ``x_0 = 0``,
    ε = √eps·max|diag A|), which converges to the exact solution, to machine precision, when
    the system is nonsingular, and otherwise to the impulses of least ``xᵀPx``: a second
    pass makes sticking friction costlier than normal support and weights each sticking
    slot's friction by the inverse of its normal impulse, so friction carries no more than
    it must and is shared among redundant contacts in proportion to their load (inside every
    cone whenever the total is inside the total cone). Every operation is differentiable.

    Sticking friction impulses are reported as non-negative components along the two
    friction directions that bracket the tangential impulse.

    Args:
        problem: the contact problem, batch ``*B``.
        mode: ``(*B, K)`` integer modes (broadcastable); padding slots are treated as
            separated whatever their mode.
        initial_impulses: optional ``(pn (*B, K), pt (*B, K, D))`` of a known solution with
            this mode (e.g. Lemke's). The iteration starts there, so where redundant contacts
            leave the split free the result keeps that split (and its gradient follows it)
            instead of choosing its own.

    Returns:
        The :class:`Solution`. Its ``status.converged`` says the linear system was solved
        (finite, equality residual within tolerance); whether the result is physically
        consistent with the mode is :func:`is_consistent`'s answer, and
        ``status.residual`` is the LCP residual, zero only when the mode was the right one.
    """
    mode = validate_mode(problem, mode)
    if initial_impulses is not None:
        if not isinstance(initial_impulses, tuple) or len(initial_impulses) != 2:
            raise ValueError("initial_impulses must be a pair (pn, pt) of tensors")
        for name, value, event in (
            ("initial_impulses[0]", initial_impulses[0], (problem.num_slots,)),
            ("initial_impulses[1]", initial_impulses[1], problem.b_tangent.shape[-2:]),
        ):
            check_tensor(name, value, event_shape=event, like=problem.M)
    return solve_mode_unchecked(problem, mode, initial_impulses=initial_impulses)


def solve_mode_unchecked(
    problem: ContactProblem,
    mode: Tensor,
    *,
    initial_impulses: tuple[Tensor, Tensor] | None = None,
    sync_free: bool = False,
) -> Solution:
    """:func:`solve_mode` without validating ``mode`` and ``initial_impulses``.

    For hot paths whose modes are valid by construction (a simulator's mode iterations).

    Args:
        problem: the contact problem, batch ``*B``.
        mode: ``(*B, K)`` long modes in ``[0, num_modes(D))``.
        initial_impulses: as for :func:`solve_mode`.
        sync_free: never synchronise with the host (as :func:`torch.compile` wants it): the
            weighted friction split runs on every problem of the batch and is kept where the
            problem has a sticking slot, instead of running on those problems alone. The
            results are the same.
    """
    mask = problem.slot_mask
    mode = torch.where(mask, mode, torch.zeros_like(mode))
    batch = problem.batch_shape
    K, D, r = problem.num_slots, problem.num_directions, problem.num_tangents
    Jn, Jt, mu = problem.Jn, problem.Jt, problem.mu

    active = mode >= STICKING
    sticking = mode == STICKING
    sliding = is_sliding(mode)
    face = is_face_sliding(mode, num_directions=D)
    first, second = friction_pair(mode, num_directions=D)
    Jt_first = _direction_rows(Jt, first)
    slide_mu = torch.where(sliding, mu, torch.zeros_like(mu))
    # Tangent rows of the unknowns λ (acting and constrained along the same rows): the basis
    # when sticking; on a face, row 0 is the difference of its two directions.
    tangent_rows = Jt[..., :r, :]
    tangent_target = -problem.b_tangent[..., :r]
    tangent_active = sticking.unsqueeze(-1).expand(*batch, K, r)
    if D > 2:
        Jt_second = _direction_rows(Jt, second)
        G_normal = Jn + (0.5 * slide_mu).unsqueeze(-1) * (Jt_first + Jt_second)
        on_face_row = face.unsqueeze(-1) & (torch.arange(r, device=problem.device) == 0)
        # Row 0 chosen on the (K, n) rows, then joined to the others: a choice broadcast over
        # the strided (K, r, n) slice of Jt cost several times more.
        face_row = torch.where(face.unsqueeze(-1), Jt_first - Jt_second, Jt[..., 0, :])
        tangent_rows = torch.cat([face_row.unsqueeze(-2), Jt[..., 1:r, :]], dim=-2)
        bt_pair = problem.b_tangent.gather(-1, torch.stack([first, second], dim=-1))
        face_target = (bt_pair[..., 1] - bt_pair[..., 0]).unsqueeze(-1)
        tangent_target = torch.where(on_face_row, face_target, tangent_target)
        tangent_active = tangent_active | on_face_row
    else:
        G_normal = Jn + slide_mu.unsqueeze(-1) * Jt_first
    J_tangent = tangent_rows.flatten(-3, -2)
    rows_active = torch.cat([active, tangent_active.flatten(-2)], dim=-1)
    # Inactive rows are zeroed in C and G (so in A = C M⁻¹ Gᵀ, where they get a unit
    # diagonal): masking the (m, n) rows is cheaper than masking the (m, m) products.
    zero = torch.zeros((), dtype=problem.dtype, device=problem.device)
    row_mask = rows_active.unsqueeze(-1)
    C = torch.where(row_mask, torch.cat([Jn, J_tangent], dim=-2), zero)
    G = torch.where(row_mask, torch.cat([G_normal, J_tangent], dim=-2), zero)

    v_free = problem.v_free()
    target = torch.cat(
        [-(problem.b_normal + problem.phi / problem.h), tangent_target.flatten(-2)], dim=-1
    )
    start = (
        None
        if initial_impulses is None
        else _impulse_coordinates(Jt, initial_impulses, r, rows_active, mode)
    )
    # The system on the rows that some problem of the batch needs: the inactive rows are
    # moved to the end and dropped where no problem needs them (a unit diagonal there, which
    # the regularisation's and the convergence test's scales still count).
    m = rows_active.shape[-1]
    keep = None if sync_free else _needed_rows(rows_active)
    has_unit_rows = (~rows_active).any(dim=-1, keepdim=True)
    if keep is not None:
        C = C.gather(-2, keep.unsqueeze(-1).expand(*keep.shape, C.shape[-1]))
        G = G.gather(-2, keep.unsqueeze(-1).expand(*keep.shape, G.shape[-1]))
        target, rows_active = target.gather(-1, keep), rows_active.gather(-1, keep)
        start = None if start is None else start.gather(-1, keep)
    Minv_GT = problem.mass_solve(G.transpose(-1, -2))
    rhs = target - (C @ v_free.unsqueeze(-1)).squeeze(-1)
    A = C @ Minv_GT
    A.diagonal(dim1=-2, dim2=-1).add_((~rows_active).to(problem.dtype))
    b = torch.where(rows_active, rhs, zero)
    unit_floor = has_unit_rows.to(problem.dtype)
    # With initial impulses the iteration stays at their split: its fixed points are the
    # solutions, so it returns the one nearest the start, and differentiates along it.
    x = _iterated_tikhonov(
        A,
        b,
        torch.ones_like(b),
        refinements=SOLVE_MODE_REFINEMENTS,
        start=start,
        diagonal_floor=unit_floor,
        sync_free=sync_free,
    )
    if initial_impulses is None and K:
        x = _split_friction(
            A,
            b,
            x,
            sticking.any(dim=-1),
            K=K,
            r=r,
            keep=keep,
            diagonal_floor=unit_floor,
            sync_free=sync_free,
        )
    x_rows = x
    if keep is not None:
        x = torch.zeros((*batch, m), dtype=x.dtype, device=x.device).scatter(-1, keep, x)

    v_next = v_free + (Minv_GT @ x_rows.unsqueeze(-1)).squeeze(-1)
    pn = x[..., :K]
    tangential = x[..., K:].unflatten(-1, (K, r))
    # A sliding slot's friction: μ pn along its direction on an edge; on a face, μ pn / 2 + λ
    # on its first direction and μ pn / 2 − λ on its second.
    one_hot = torch.nn.functional.one_hot
    if D > 2:
        half = 0.5 * slide_mu * pn
        face_lambda = torch.where(face, tangential[..., 0], torch.zeros_like(half))
        pt_slide = one_hot(first, D).to(problem.dtype) * (half + face_lambda).unsqueeze(-1)
        pt_slide = pt_slide + one_hot(second, D).to(problem.dtype) * (half - face_lambda).unsqueeze(
            -1
        )
    else:
        pt_slide = one_hot(first, D).to(problem.dtype) * (slide_mu * pn).unsqueeze(-1)
    pt_stick = _bracket_decomposition(Jt, tangential, sticking, sync_free=sync_free)
    pt = torch.where(sticking.unsqueeze(-1), pt_stick, pt_slide)

    equality_error = _largest((A @ x_rows.unsqueeze(-1)).squeeze(-1) - b)
    # Relative to the system's own terms: the same test at every scale of h, M and v.
    largest_A = torch.maximum(_largest(A.flatten(-2)), unit_floor.squeeze(-1))
    scale = _largest(b) + largest_A * _largest(x)
    scale = scale.clamp(min=torch.finfo(problem.dtype).tiny)
    finite = torch.isfinite(v_next).all(dim=-1) & torch.isfinite(pt).all(dim=(-1, -2))
    tolerance = default_tolerance(problem.dtype)
    converged = finite & (equality_error <= tolerance * scale)
    residual = lcp_residual(problem, v_next=v_next, pn=pn, pt=pt)
    status = SolveStatus(
        converged=converged.detach(),
        residual=residual.detach(),
        iterations=torch.ones(batch, dtype=torch.long, device=problem.device),
    )
    return Solution(v_next=v_next, pn=pn, pt=pt, mode=mode, status=status)


def friction_split_weights(normal_impulses: Tensor, *, dim: int = -1) -> Tensor:
    """Regularisation weights of the sticking friction unknowns in ``solve_mode``'s second pass.

    ``c · s / (pn⁺ + ρ s)`` per slot, with ``pn⁺`` the normal impulse clamped at zero, ``s`` the
    largest of them (floored at eps), ``c = SOLVE_MODE_FRICTION_COST`` and
    ``ρ = SOLVE_MODE_MIN_LOAD_SHARE`` (the normal unknowns weigh 1): friction costs more than
    normal support, and least on the slots that carry the most load.

    Args:
        normal_impulses: the first pass's normal impulses, slots along ``dim``.
        dim: the slot dimension.

    Returns:
        The weights, shaped like ``normal_impulses``.
    """
    load = normal_impulses.clamp(min=0.0)
    # (floored at eps: with no load at all the weights only need to be finite, and a denormal
    # floor would underflow to NaN in the backward pass)
    share = load.amax(dim=dim, keepdim=True).clamp_min(torch.finfo(load.dtype).eps)
    return SOLVE_MODE_FRICTION_COST * share / (load + SOLVE_MODE_MIN_LOAD_SHARE * share)


def _split_friction(
    A: Tensor,
    b: Tensor,
    x: Tensor,
    sticks: Tensor,
    *,
    K: int,
    r: int,
    keep: Tensor | None,
    diagonal_floor: Tensor,
    sync_free: bool,
) -> Tensor:
    """Re-solve the problems with sticking slots with weights that split friction by load.

    Redundant sticking rows leave the split of the impulses free. Prefer normal support over
    friction, and share friction in proportion to the normal impulses (minimum
    ``Σ pn² + c Σ λ²/pn``), which keeps every share inside its cone whenever the total is
    inside the total cone. Only the problems that have a sticking slot are solved again.

    Args:
        A: ``(*B, w, w)`` Schur systems on the rows ``keep`` of the ``m = K + K·r`` rows.
        b: ``(*B, w)`` their right-hand sides.
        x: ``(*B, w)`` the unweighted solutions (their normal impulses set the weights).
        sticks: ``(*B,)`` bool, the problem has a sticking slot.
        K: number of slots.
        r: tangent dimension.
        keep: ``(*B, w)`` the rows of the systems among the ``m`` (``None``: all, ``w = m``).
        diagonal_floor: ``(*B, 1)`` floor of the regularisation's diagonal scale.
        sync_free: solve every problem again and keep the answers of those that stick (no
            host synchronisation).

    Returns:
        ``(*B, w)``: ``x`` with the problems that stick solved again.
    """
    if not sync_free and not bool(sticks.any()):
        return x
    every = sync_free or bool(sticks.all())
    w = x.shape[-1]
    index = torch.nonzero(sticks.reshape(-1)).squeeze(-1) if not every else None
    if index is not None:
        A, b, chosen = A.reshape(-1, w, w)[index], b.reshape(-1, w)[index], x.reshape(-1, w)[index]
        diagonal_floor = diagonal_floor.reshape(-1, 1)[index]
        rows = None if keep is None else keep.reshape(-1, w)[index]
    else:
        chosen, rows = x, keep
    normal = chosen[..., :K]
    if rows is not None:
        normal = torch.zeros(
            (*chosen.shape[:-1], K + K * r), dtype=x.dtype, device=x.device
        ).scatter(-1, rows, chosen)[..., :K]
    tangent_weight = friction_split_weights(normal)
    weights = torch.cat(
        [torch.ones_like(tangent_weight), tangent_weight.repeat_interleave(r, dim=-1)], -1
    )
    if rows is not None:
        weights = weights.gather(-1, rows)
    split = _iterated_tikhonov(
        A,
        b,
        weights,
        refinements=SOLVE_MODE_WEIGHTED_REFINEMENTS,
        diagonal_floor=diagonal_floor,
        sync_free=sync_free,
    )
    if sync_free:
        return torch.where(sticks.unsqueeze(-1), split, x)
    if index is None:
        return split
    return x.reshape(-1, w).index_put((index,), split).reshape(x.shape)


def _needed_rows(rows_active: Tensor) -> Tensor | None:
    """The rows of the Schur system to keep, or ``None`` to keep all.

    Args:
        rows_active: ``(*B, m)`` bool, the rows that carry unknowns.

    Returns:
        ``(*B, w)`` indices of each problem's active rows first (in order), then inactive
        ones, ``w`` the most active rows of any problem (one host synchronisation); ``None``
        where every row is needed somewhere (``w = m``) or the batch has fewer than
        :data:`COMPACT_MIN_BATCH` problems.
    """
    m = rows_active.shape[-1]
    if rows_active.numel() == 0 or rows_active.shape[:-1].numel() < COMPACT_MIN_BATCH:
        return None
    width = int(rows_active.sum(dim=-1).amax())
    if width >= m:
        return None
    order = torch.argsort((~rows_active).to(torch.uint8), dim=-1, stable=True)
    return order[..., :width]


def _direction_rows(Jt: Tensor, direction: Tensor) -> Tensor:
    """``(*B, K, n)`` the row ``Jt[..., k, direction[..., k], :]`` of every slot.

    Args:
        Jt: ``(*B, K, D, n)`` friction-direction rows.
        direction: ``(*B, K)`` long, a direction per slot.
    """
    *batch, K, D, n = Jt.shape
    if not Jt.is_contiguous():
        index = direction[..., None, None].expand(*batch, K, 1, n)
        return Jt.gather(-2, index).squeeze(-2)
    # A contiguous tensor's rows picked from its flattened rows: several times cheaper than
    # gather on a CPU.
    start = torch.arange(0, direction.numel() * D, D, device=Jt.device).view(direction.shape)
    rows = Jt.reshape(-1, n).index_select(0, (start + direction).flatten())
    return rows.view(*batch, K, n)


def _largest(values: Tensor) -> Tensor:
    """``(*B,)`` largest magnitude of ``values (*B, m)``, zero when ``m == 0``."""
    if values.shape[-1] == 0:
        return values.sum(dim=-1)
    return values.abs().amax(dim=-1)


def _iterated_tikhonov(
    A: Tensor,
    b: Tensor,
    weights: Tensor,
    *,
    refinements: int,
    start: Tensor | None = None,
    diagonal_floor: Tensor | None = None,
    sync_free: bool = False,
) -> Tensor:
    """Solve ``A x = b`` (batched, possibly singular but consistent) by iterated Tikhonov.

    :func:`~torchcontact.contact.iterated_tikhonov` with ``S = ε diag(weights)``,
    ``ε = √eps · max(max|diag A|, diagonal_floor)``.

    Args:
        A: ``(*B, m, m)`` system matrices.
        b: ``(*B, m)`` right-hand sides.
        weights: ``(*B, m)`` positive regularisation weights.
        refinements: number of iterations.
        start: ``(*B, m)`` starting point ``x_0`` (treated as a constant), default zeros.
        diagonal_floor: ``(*B, 1)`` floor of the diagonal scale (the unit diagonal of rows
            left out of ``A``), default none.
        sync_free: run every iteration (no host synchronisation) instead of stopping at an
            exact fixed point.

    Returns:
        ``(*B, m)``: the solution when ``A`` is nonsingular; when singular and consistent, the
        solution of least ``(x − x_0)ᵀ S (x − x_0)`` (up to the regularisation's geometric
        convergence).
    """
    if A.shape[-1] == 0:
        return b
    eps = torch.finfo(A.dtype).eps ** 0.5
    diagonal_scale = A.diagonal(dim1=-2, dim2=-1).abs().amax(dim=-1, keepdim=True)
    if diagonal_floor is not None:
        diagonal_scale = torch.maximum(diagonal_scale, diagonal_floor)
    shift = eps * diagonal_scale * weights
    if sync_free and torch.compiler.is_compiling() and A.shape[-1] <= ELIMINATION_MAX_ORDER:
        x = tikhonov_by_elimination(
            A,
            shift,
            b.unsqueeze(-1),
            refinements=refinements,
            start=None if start is None else start.unsqueeze(-1),
        )
        return x.squeeze(-1)
    # Without host synchronisation every iteration runs: as products, after one more solve.
    system = tikhonov_system(A, shift, products=sync_free)
    x = iterated_tikhonov(
        system,
        b.unsqueeze(-1),
        refinements=refinements,
        start=None if start is None else start.unsqueeze(-1),
        stop_at_fixed_point=not sync_free,
    )
    return x.squeeze(-1)


def _impulse_coordinates(
    Jt: Tensor, impulses: tuple[Tensor, Tensor], r: int, rows_active: Tensor, mode: Tensor
) -> Tensor:
    """Unknowns ``x = [pn; λ]`` of the Schur system from impulses ``(pn, pt)``.

    Args:
        Jt: ``(*B, K, D, n)`` friction-direction rows.
        impulses: ``pn (*B, K)`` and ``pt (*B, K, D)``.
        r: tangent dimension (1 planar, 2 spatial).
        rows_active: ``(*B, K + K·r)`` rows of the system that carry unknowns.
        mode: ``(*B, K)`` long modes.

    Returns:
        ``(*B, K + K·r)``, zero on inactive rows; ``λ`` holds a sticking slot's friction
        impulse in the coordinates of the tangent basis (directions ``0..r-1``) and, first, a
        face-sliding slot's ``(pt_d − pt_e) / 2`` (its two directions ``d``, ``e``).
    """
    pn, pt = impulses
    D = Jt.shape[-2]
    if D == 2:
        tangential = (pt[..., 0] - pt[..., 1]).unsqueeze(-1)
    else:
        coords = _basis_coordinates(Jt, torch.ones_like(mode, dtype=torch.bool))
        tangential = (coords @ pt.unsqueeze(-1)).squeeze(-1)
        pt_pair = pt.gather(-1, torch.stack(friction_pair(mode, num_directions=D), dim=-1))
        split = 0.5 * (pt_pair[..., 0] - pt_pair[..., 1])
        face = is_face_sliding(mode, num_directions=D)
        tangential = torch.cat(
            [torch.where(face, split, tangential[..., 0]).unsqueeze(-1), tangential[..., 1:]],
            dim=-1,
        )
    x = torch.cat([pn, tangential.flatten(-2)], dim=-1).to(Jt.dtype)
    return torch.where(rows_active, x, torch.zeros((), dtype=Jt.dtype, device=Jt.device))


def _bracket_decomposition(
    Jt: Tensor, tangential: Tensor, sticking: Tensor, *, sync_free: bool = False
) -> Tensor:
    """Write tangential impulses as non-negative friction-direction components.

    Args:
        Jt: ``(*B, K, D, n)`` friction-direction rows.
        tangential: ``(*B, K, r)`` impulse coordinates along the tangent basis (direction 0,
            or directions 0 and 1 when spatial).
        sticking: ``(*B, K)`` bool; other slots return zeros.
        sync_free: decompose every slot's impulse (no host synchronisation) instead of the
            sticking slots' alone (gathered first: a step's sticking slots are usually a
            small share of all). The results are the same.

    Returns:
        ``(*B, K, D)`` components ``pt ≥ 0`` with ``Σ_d pt_d Jt_d = Σ_j λ_j Jt_j``, using the
        two adjacent directions whose cone contains the impulse (planar: ``+t`` or ``-t``).
    """
    *batch, K, D, n = Jt.shape
    zero = torch.zeros((), dtype=Jt.dtype, device=Jt.device)
    if D == 2:
        lam = tangential[..., 0]
        pt = torch.stack([lam.clamp(min=0.0), (-lam).clamp(min=0.0)], dim=-1)
        return torch.where(sticking.unsqueeze(-1), pt, zero)
    if sync_free or torch.compiler.is_compiling() or Jt.shape[:-2] != sticking.shape:
        return _bracket_components(Jt, tangential, sticking)
    slots = torch.nonzero(sticking.reshape(-1)).squeeze(-1)
    r = tangential.shape[-1]
    chosen = _bracket_components(
        Jt.reshape(-1, D, n).index_select(0, slots),
        tangential.reshape(-1, r).index_select(0, slots),
        torch.ones_like(slots, dtype=torch.bool),
    )
    pt = Jt.new_zeros(sticking.numel(), D).index_put((slots,), chosen)
    return pt.view(*batch, K, D)


def _bracket_components(Jt: Tensor, tangential: Tensor, sticking: Tensor) -> Tensor:
    """:func:`_bracket_decomposition` of spatial slots (``D >= 4``) on every slot given.

    Args:
        Jt: ``(*S, D, n)`` friction-direction rows.
        tangential: ``(*S, 2)`` impulse coordinates along directions 0 and 1.
        sticking: ``(*S,)`` bool; other slots return zeros.

    Returns:
        ``(*S, D)`` the components.
    """
    D = Jt.shape[-2]
    zero = torch.zeros((), dtype=Jt.dtype, device=Jt.device)
    coords = _basis_coordinates(Jt, sticking)
    c_this = coords
    c_next = coords.roll(-1, dims=-1)
    lam = tangential.unsqueeze(-1)  # (*S, 2, 1)

    def cross(a: Tensor, b: Tensor) -> Tensor:
        return a[..., 0, :] * b[..., 1, :] - a[..., 1, :] * b[..., 0, :]

    det = cross(c_this, c_next)
    det = torch.where(det.abs() > 0, det, torch.ones_like(det))
    alpha = cross(lam, c_next) / det
    beta = cross(c_this, lam) / det
    sector = torch.minimum(alpha, beta).argmax(dim=-1, keepdim=True)
    alpha = alpha.gather(-1, sector).clamp(min=0.0)
    beta = beta.gather(-1, sector).clamp(min=0.0)
    pt = torch.zeros_like(Jt[..., 0])
    pt = pt.scatter_add(-1, sector, alpha)
    pt = pt.scatter_add(-1, (sector + 1) % D, beta)
    return torch.where(sticking.unsqueeze(-1), pt, zero)


def _basis_coordinates(Jt: Tensor, where: Tensor) -> Tensor:
    """Least-squares coordinates of every friction row in the tangent basis (rows 0 and 1).

    ``(Bᵀ B)⁻¹ Bᵀ Jt_d`` for the basis ``B = [Jt_0, Jt_1]``, by the closed-form inverse of the
    2 × 2 Gram matrix (regularised by eps on its diagonal, so that it stays invertible).

    Args:
        Jt: ``(*B, K, D, n)`` friction-direction rows, ``D >= 4``.
        where: ``(*B, K)`` bool, the slots whose coordinates are needed; the others get the
            coordinates of an identity Gram matrix (finite, and without gradient trouble).

    Returns:
        ``(*B, K, 2, D)`` coordinates.
    """
    eps = torch.finfo(Jt.dtype).eps
    first, second = Jt[..., 0, :], Jt[..., 1, :]
    g00 = (first * first).sum(-1) + eps
    g01 = (first * second).sum(-1)
    g11 = (second * second).sum(-1) + eps
    det = g00 * g11 - g01 * g01
    one, zero = torch.ones_like(det), torch.zeros_like(det)
    g00, g01 = torch.where(where, g00, one), torch.where(where, g01, zero)
    g11, det = torch.where(where, g11, one), torch.where(where, det, one)
    projections = Jt[..., :2, :] @ Jt.transpose(-1, -2)  # (*B, K, 2, D): Bᵀ Jt_d
    p0, p1 = projections[..., 0, :], projections[..., 1, :]
    inverse_det = det.reciprocal().unsqueeze(-1)
    c0 = (g11.unsqueeze(-1) * p0 - g01.unsqueeze(-1) * p1) * inverse_det
    c1 = (g00.unsqueeze(-1) * p1 - g01.unsqueeze(-1) * p0) * inverse_det
    return torch.stack([c0, c1], dim=-2)
