"""The Stewart–Trinkle LCP of a contact problem: assembly, residual, mode and consistency."""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from torchcontact._checks import check_positive, check_tensor, describe
from torchcontact.contact._problem import ContactProblem
from torchcontact.contact._solution import Solution

#: Mode of a slot that carries no impulse.
SEPARATED = 0
#: Mode of a slot whose contact point does not slide.
STICKING = 1
#: First sliding code. Mode ``SLIDING + d`` slides with the friction impulse along direction
#: ``d`` (an edge of the friction cone); when spatial (``D >= 4``), mode ``SLIDING + D + d``
#: slides with it on the face between directions ``d`` and ``(d + 1) mod D``. Every mode
#: ``>= SLIDING`` slides: test with :func:`is_sliding`, not ``== SLIDING``.
SLIDING = 2


def num_modes(num_directions: int) -> int:
    """Number of slot modes of a problem with ``D = num_directions`` friction directions.

    ``2 + D`` when planar (``D == 2``: separated, sticking, sliding along ``+t`` or ``−t``) and
    ``2 + 2D`` when spatial (``D >= 4``: separated, sticking, ``D`` edges and ``D`` faces of the
    friction cone); the modes are the integers ``0 … num_modes − 1``.
    """
    return SLIDING + (num_directions if num_directions == 2 else 2 * num_directions)


def is_sliding(mode: Tensor) -> Tensor:
    """``mode``'s slots that slide, along an edge or a face (``mode >= SLIDING``), as bool."""
    return mode >= SLIDING


def is_face_sliding(mode: Tensor, *, num_directions: int) -> Tensor:
    """``mode``'s slots that slide on a face of the friction cone (``mode >= SLIDING + D``).

    Always ``False`` when planar (``D == 2``), where no such mode exists.

    Args:
        mode: ``(*B, K)`` long modes.
        num_directions: ``D``, the problem's number of friction directions.
    """
    return mode >= SLIDING + num_directions


def friction_direction(mode: Tensor, *, num_directions: int) -> Tensor:
    """The first friction direction that carries a sliding slot's friction, ``-1`` elsewhere.

    ``d`` for an edge mode ``SLIDING + d`` and for a face mode ``SLIDING + D + d``, whose
    friction impulse lies between directions ``d`` and ``(d + 1) mod D`` (tell the two apart
    with :func:`is_face_sliding`). The friction impulse acts against the slip: a planar slot in
    mode ``SLIDING + 1`` has its friction along ``−t`` and slides along ``+t``.

    Args:
        mode: ``(*B, K)`` long modes.
        num_directions: ``D``, the problem's number of friction directions.

    Returns:
        ``(*B, K)`` long directions in ``[0, D)``, or ``-1`` where the slot does not slide.
    """
    return torch.where(is_sliding(mode), (mode - SLIDING) % num_directions, -1)


def friction_pair(mode: Tensor, *, num_directions: int) -> tuple[Tensor, Tensor]:
    """The two friction directions that carry each slot's sliding friction (clamped at 0).

    Returns:
        ``first, second (*B, K)`` long: ``d`` and ``(d + 1) mod D`` for a face mode, ``d``
        twice for an edge mode, ``0`` twice where the slot does not slide.
    """
    first = friction_direction(mode, num_directions=num_directions).clamp(min=0)
    face = is_face_sliding(mode, num_directions=num_directions)
    second = torch.where(face, (first + 1) % num_directions, first)
    return first, second


def default_tolerance(dtype: torch.dtype) -> float:
    """Absolute tolerance used by the residual tests of solvers for ``dtype``."""
    return 1e-9 if dtype == torch.float64 else 1e-4


def contact_jacobian(problem: ContactProblem) -> Tensor:
    """Stack normal and friction rows into ``J (*B, K + K·D, n)``: ``[Jn; Jt]``."""
    Jt_flat = problem.Jt.flatten(-3, -2)
    return torch.cat([problem.Jn, Jt_flat], dim=-2)


def delassus(problem: ContactProblem) -> tuple[Tensor, Tensor]:
    """Delassus operator of the stacked rows and the mobility of each row.

    Returns:
        ``W (*B, K + K·D, K + K·D) = J M⁻¹ Jᵀ`` and ``M⁻¹ Jᵀ (*B, n, K + K·D)``, computed by
        Cholesky solves.
    """
    J = contact_jacobian(problem)
    Minv_JT = problem.mass_solve(J.transpose(-1, -2))
    return J @ Minv_JT, Minv_JT


def free_constraint_velocity(problem: ContactProblem, *, v_free: Tensor) -> Tensor:
    """``(*B, K + K·D)`` constraint velocities at ``v_free``: ``J v_free + [bn + φ/h; bt]``.

    With ``W`` from :func:`delassus` this is the LCP data: the constraint velocities at the end
    of the step are ``W p + q`` for stacked impulses ``p = [pn; pt]``.

    Args:
        problem: the contact problem.
        v_free: ``(*B, n)`` its contact-free velocity, ``problem.v_free()`` (passed in so
            callers that need it too factor ``M`` once).
    """
    return _rows_times(problem, v_free) + _bias(problem)


def velocity_terms(problem: ContactProblem, v_next: Tensor) -> tuple[Tensor, Tensor]:
    """Constraint velocities at ``v_next``.

    Args:
        problem: the contact problem.
        v_next: ``(*B, n)`` generalized velocity at the end of the step.

    Returns:
        ``gap_rate (*B, K) = Jn v⁺ + bn + φ/h`` and ``slip (*B, K, D) = Jt v⁺ + bt``.
    """
    return problem.cached_at(
        "velocity_terms",
        (v_next,),
        lambda: _split_rows(problem, _rows_times(problem, v_next) + _bias(problem)),
    )


def _rows_times(problem: ContactProblem, v: Tensor) -> Tensor:
    """``(*B, K + K·D)`` the stacked rows times ``v (*B, n)``: ``J v``.

    One batched product with the stacked rows (:func:`contact_jacobian`, kept on the problem)
    instead of one per block: a product with ``Jt (*B, K, D, n)`` broadcast against ``v``
    copies ``v`` once per slot first.
    """
    J = problem.cached("contact_jacobian", lambda: contact_jacobian(problem))
    return (J @ v.unsqueeze(-1)).squeeze(-1)


def _bias(problem: ContactProblem) -> Tensor:
    """``(*B, K + K·D)`` the constant terms of the constraint velocities, ``[bn + φ/h; bt]``."""
    return problem.cached(
        "bias",
        lambda: torch.cat(
            [problem.b_normal + problem.phi / problem.h, problem.b_tangent.flatten(-2, -1)],
            dim=-1,
        ),
    )


def _split_rows(problem: ContactProblem, stacked: Tensor) -> tuple[Tensor, Tensor]:
    """``(*B, K)`` normal and ``(*B, K, D)`` friction parts of stacked row values."""
    K, D = problem.num_slots, problem.num_directions
    return stacked[..., :K], stacked[..., K:].unflatten(-1, (K, D))


def lcp_residual(problem: ContactProblem, *, v_next: Tensor, pn: Tensor, pt: Tensor) -> Tensor:
    """Natural-map residual ``max |min(z, w)|`` of the Stewart–Trinkle LCP.

    The sliding speed of each contact is taken as the least value that satisfies the friction
    rows, ``σ = max(0, −min_d (Jt_d v⁺ + bt_d))``, so the residual measures a candidate
    ``(v⁺, pn, pt)`` alone. Padding slots contribute ``|pn|`` and ``|pt|`` (they must be zero).
    Velocities and impulses are mixed in one number, as in the LCP itself.

    Args:
        problem: the contact problem.
        v_next: ``(*B, n)`` end-of-step velocity, assumed to satisfy the Newton–Euler row.
        pn: ``(*B, K)`` normal impulses.
        pt: ``(*B, K, D)`` friction impulses.

    Returns:
        ``(*B,)`` residual, zero exactly at a solution.
    """
    gap_rate, slip = velocity_terms(problem, v_next)
    sigma = (-slip.amin(dim=-1)).clamp(min=0.0)
    normal = torch.minimum(pn, gap_rate).abs()
    friction = torch.minimum(pt, slip + sigma.unsqueeze(-1)).abs().amax(dim=-1)
    cone = torch.minimum(sigma, problem.mu * pn - pt.sum(dim=-1)).abs()
    per_slot = torch.stack([normal, friction, cone], dim=-1).amax(dim=-1)
    padding = torch.maximum(pn.abs(), pt.abs().amax(dim=-1))
    per_slot = torch.where(problem.slot_mask, per_slot, padding)
    return per_slot.amax(dim=-1) if per_slot.shape[-1] else per_slot.sum(dim=-1)


def problem_scales(
    problem: ContactProblem,
    *,
    v_next: Tensor,
    pn: Tensor,
    pt: Tensor,
    v_free: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Velocity and impulse scales ``(*B, 1)`` of a candidate solution, for relative tests.

    Both follow the problem's own units, so a test against them is invariant under a change
    of units of time, mass or length (``h``, ``M``, ``v`` scaled together or apart):

    * velocity: the largest constraint velocity the step starts from or the impulses cause
      over the real slots, ``|J v_free|``, ``|b|``, ``|J (v⁺ − v_free)|``, and the
      penetration-recovery rate ``−φ/h`` of penetrating slots (a positive ``φ/h``, a slot far
      away, sets no scale for the others);
    * impulse: the largest generalized momentum ``|M v|``, ``|h f|``, ``|M (v⁺ − v_free)|``
      (``= |Jᵀ p|``), or impulse.

    Both are floored at the dtype's ``tiny`` (a problem at rest with no force has scale 0).
    ``v_free`` (``(*B, n)``, :meth:`ContactProblem.v_free`) is computed when not given.
    """
    gap_rate, slip = velocity_terms(problem, v_next)
    return _scales(
        problem, v_next=v_next, pn=pn, pt=pt, gap_rate=gap_rate, slip=slip, v_free=v_free
    )


def _scales(
    problem: ContactProblem,
    *,
    v_next: Tensor,
    pn: Tensor,
    pt: Tensor,
    gap_rate: Tensor,
    slip: Tensor,
    v_free: Tensor | None,
) -> tuple[Tensor, Tensor]:
    """:func:`problem_scales` from the constraint velocities at ``v_next``
    (:func:`velocity_terms`), which the tests against the scales need too.

    The constraint velocities the impulses cause are those at ``v_next`` less those at
    ``v_free``; every term that depends on the problem alone is computed once per problem
    (:meth:`ContactProblem.cached`) unless the caller passes its own ``v_free``, and so are
    the scales of the last solution checked (:meth:`ContactProblem.cached_at`: the
    simulator's consistency check and its canonical modes read the same solution).
    """
    scales = functools.partial(
        _scales_from, problem, v_next=v_next, pn=pn, pt=pt, gap_rate=gap_rate, slip=slip
    )
    if v_free is not None:
        return scales(v_free=v_free, free=_free_terms(problem, v_free))

    def from_problem() -> tuple[Tensor, Tensor]:
        # One contact-free velocity: where the problem keeps nothing (a field requires grad,
        # under tracing) each call of v_free() would solve with M again.
        free_velocity = problem.v_free()
        free = problem.cached("free_terms", lambda: _free_terms(problem, free_velocity))
        return scales(v_free=free_velocity, free=free)

    return problem.cached_at("scales", (v_next, pn, pt), from_problem)


def _scales_from(
    problem: ContactProblem,
    *,
    v_next: Tensor,
    pn: Tensor,
    pt: Tensor,
    gap_rate: Tensor,
    slip: Tensor,
    v_free: Tensor,
    free: tuple[Tensor, Tensor, Tensor, Tensor],
) -> tuple[Tensor, Tensor]:
    """:func:`_scales` from the contact-free velocity and its :func:`_free_terms`."""
    tiny = torch.finfo(problem.dtype).tiny
    free_gap, free_slip, slot_scale, impulse_floor = free
    caused = torch.maximum((gap_rate - free_gap).abs(), (slip - free_slip).abs().amax(dim=-1))
    per_slot = torch.maximum(slot_scale, caused)
    per_slot = torch.where(problem.slot_mask, per_slot, torch.zeros((), dtype=per_slot.dtype))
    velocity = torch.nn.functional.pad(per_slot, (0, 1)).amax(dim=-1, keepdim=True)
    # |M (v⁺ − v_free)| (= |Jᵀ p| by the Newton–Euler row).
    momentum = (problem.M @ (v_next - v_free).unsqueeze(-1)).squeeze(-1)
    impulse = torch.cat([momentum.abs(), pn.abs(), pt.flatten(-2).abs()], dim=-1)
    impulse = torch.maximum(impulse.amax(dim=-1, keepdim=True), impulse_floor)
    return velocity.clamp(min=tiny), impulse.clamp(min=tiny)


def _free_terms(problem: ContactProblem, v_free: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The terms of :func:`problem_scales` that do not depend on the candidate solution.

    Returns:
        The constraint velocities at ``v_free``, ``(*B, K)`` ``Jn v_free + bn + φ/h`` and
        ``(*B, K, D)`` ``Jt v_free + bt``; the ``(*B, K)`` per-slot velocity scale without the
        impulses' share (``|J v_free|``, ``|b|``, ``−φ/h`` where penetrating); the
        ``(*B, 1)`` impulse scale without the solution's share (``|M v|``, ``|h f|``).
    """
    Jn_v, Jt_v = _split_rows(problem, _rows_times(problem, v_free))
    known = torch.maximum(problem.b_normal.abs(), problem.b_tangent.abs().amax(dim=-1))
    slot_scale = torch.maximum(Jn_v.abs(), Jt_v.abs().amax(dim=-1))
    slot_scale = torch.maximum(slot_scale, known)
    slot_scale = torch.maximum(slot_scale, (-problem.phi / problem.h).clamp(min=0.0))
    momentum = (problem.M @ problem.v.unsqueeze(-1)).squeeze(-1)
    impulse_floor = torch.cat([momentum.abs(), (problem.h * problem.f).abs()], dim=-1)
    return (
        Jn_v + problem.b_normal + problem.phi / problem.h,
        Jt_v + problem.b_tangent,
        slot_scale,
        impulse_floor.amax(dim=-1, keepdim=True),
    )


def relative_residual(
    problem: ContactProblem,
    *,
    v_next: Tensor,
    pn: Tensor,
    pt: Tensor,
    v_free: Tensor | None = None,
) -> Tensor:
    """Scale-invariant natural-map residual of the Stewart–Trinkle LCP.

    :func:`lcp_residual` with every impulse divided by the impulse scale and every velocity by
    the velocity scale of :func:`problem_scales`: the same number whatever the units of time,
    mass and length, so one tolerance decides convergence at every scale of ``h``, ``M`` and
    ``v``. Padding slots contribute their impulses relative to the impulse scale.

    Args:
        problem: the contact problem.
        v_next: ``(*B, n)`` end-of-step velocity, assumed to satisfy the Newton–Euler row.
        pn: ``(*B, K)`` normal impulses.
        pt: ``(*B, K, D)`` friction impulses.
        v_free: ``(*B, n)`` the contact-free velocity if the caller has it (else computed).

    Returns:
        ``(*B,)`` relative residual, zero exactly at a solution.
    """
    gap_rate, slip = velocity_terms(problem, v_next)
    velocity_scale, impulse_scale = _scales(
        problem, v_next=v_next, pn=pn, pt=pt, gap_rate=gap_rate, slip=slip, v_free=v_free
    )
    gap_rate, slip = gap_rate / velocity_scale, slip / velocity_scale.unsqueeze(-1)
    pn, pt = pn / impulse_scale, pt / impulse_scale.unsqueeze(-1)
    sigma = (-slip.amin(dim=-1)).clamp(min=0.0)
    normal = torch.minimum(pn, gap_rate).abs()
    friction = torch.minimum(pt, slip + sigma.unsqueeze(-1)).abs().amax(dim=-1)
    cone = torch.minimum(sigma, problem.mu * pn - pt.sum(dim=-1)).abs()
    per_slot = torch.maximum(torch.maximum(normal, friction), cone)
    padding = torch.maximum(pn.abs(), pt.abs().amax(dim=-1))
    per_slot = torch.where(problem.slot_mask, per_slot, padding)
    return per_slot.amax(dim=-1) if per_slot.shape[-1] else per_slot.sum(dim=-1)


def contact_mode(
    problem: ContactProblem,
    *,
    v_next: Tensor,
    pn: Tensor,
    pt: Tensor | None = None,
    atol: float | None = None,
) -> Tensor:
    """Read the contact mode of each slot off a solution.

    A slot is separated when its normal impulse is zero (within tolerance), sticking when it
    carries an impulse and its contact point does not slide, and otherwise sliding: along the
    friction direction ``d`` most opposed to its slip (the direction that carries its
    friction), or, when spatial and a direction adjacent to ``d`` carries friction too, on the
    face between the two (at a solution, the slip is then equally opposed to both).

    Args:
        problem: the contact problem.
        v_next: ``(*B, n)`` end-of-step velocity.
        pn: ``(*B, K)`` normal impulses.
        pt: ``(*B, K, D)`` friction impulses (their size enters the impulse scale of
            :func:`problem_scales`, and they tell faces from edges); default zeros.
        atol: relative tolerance; default :func:`default_tolerance` of the dtype times 10.

    Returns:
        ``(*B, K)`` long modes (0 separated, 1 sticking, ``2 + d`` sliding along ``d``,
        ``2 + D + d`` sliding on the face between ``d`` and ``(d + 1) mod D``).
    """
    tol = 10 * default_tolerance(problem.dtype) if atol is None else atol
    pt = torch.zeros_like(problem.b_tangent) if pt is None else pt
    D = problem.num_directions
    gap_rate, slip = velocity_terms(problem, v_next)
    velocity_scale, impulse_scale = _scales(
        problem, v_next=v_next, pn=pn, pt=pt, gap_rate=gap_rate, slip=slip, v_free=None
    )
    active = problem.slot_mask & (pn > tol * impulse_scale)
    sticking = slip.abs().amax(dim=-1) <= tol * velocity_scale
    direction = slip.argmin(dim=-1)
    sliding_mode = SLIDING + direction
    if D > 2:
        # A neighbour of the most opposed direction that carries friction makes it a face.
        previous = (direction - 1) % D
        pt_next = pt.gather(-1, ((direction + 1) % D).unsqueeze(-1)).squeeze(-1)
        pt_previous = pt.gather(-1, previous.unsqueeze(-1)).squeeze(-1)
        carried = tol * impulse_scale
        next_face = (pt_next > carried) & (pt_next >= pt_previous)
        previous_face = (pt_previous > carried) & ~next_face
        sliding_mode = torch.where(next_face, SLIDING + D + direction, sliding_mode)
        sliding_mode = torch.where(previous_face, SLIDING + D + previous, sliding_mode)
    mode = torch.where(sticking, torch.full_like(sliding_mode, STICKING), sliding_mode)
    return torch.where(active, mode, torch.zeros_like(mode))


def is_consistent(
    problem: ContactProblem, solution: Solution, *, atol: float | None = None
) -> Tensor:
    """Check that a solution's impulses and velocities agree with its own contact modes.

    For every real slot: impulses are non-negative; a separated slot carries no impulse and
    does not penetrate (gap rate ≥ 0); an active slot has zero gap rate; a sticking slot has
    zero slip and its friction inside the polyhedral cone (Σ_d pt_d ≤ μ pn); a sliding slot
    has Σ_d pt_d = μ pn carried by its direction ``d`` (edge mode) or by ``d`` and
    ``(d + 1) mod D`` (face mode), and slips against them (``Jt_d v⁺ + bt_d ≤ 0``) at least as
    fast as along any other direction (on a face, equally fast against both). Padding slots
    carry no impulse. Tolerances are relative to the problem's velocity and impulse scales.

    Args:
        problem: the contact problem.
        solution: the solution to check (its ``v_next``, ``pn``, ``pt`` and ``mode``).
        atol: relative tolerance; default 10 × :func:`default_tolerance` of the dtype.

    Returns:
        ``(*B,)`` bool, ``True`` where the solution is consistent with its modes.

    Raises:
        ValueError: ``problem`` or ``solution`` is not one, or their shapes or dtypes differ.
    """
    check_solution(problem, solution)
    tol = 10 * default_tolerance(problem.dtype) if atol is None else check_positive("atol", atol)
    v_next, pn, pt, mode = solution.v_next, solution.pn, solution.pt, solution.mode
    return consistent_with_mode(problem, v_next=v_next, pn=pn, pt=pt, mode=mode, atol=tol)


def consistent_with_mode(
    problem: ContactProblem,
    *,
    v_next: Tensor,
    pn: Tensor,
    pt: Tensor,
    mode: Tensor,
    atol: float,
    v_free: Tensor | None = None,
) -> Tensor:
    """:func:`is_consistent` on arrays, without validation: the one consistency check.

    For code that holds a candidate solution as arrays on its hot path (the simulator's mode
    iterations, the filters' per-mode linearization), with shapes and dtypes right by
    construction.

    Args:
        problem: the contact problem, batch ``*B``.
        v_next: ``(*B, n)`` end-of-step velocity.
        pn: ``(*B, K)`` normal impulses.
        pt: ``(*B, K, D)`` friction impulses.
        mode: ``(*B, K)`` long contact modes (broadcastable).
        atol: relative tolerance.
        v_free: ``(*B, n)`` the contact-free velocity if the caller has it (else computed).

    Returns:
        ``(*B,)`` bool, ``True`` where the solution is consistent with its modes.
    """
    velocity_ok, impulse_ok = mode_conditions(
        problem, v_next=v_next, pn=pn, pt=pt, mode=mode, atol=atol, v_free=v_free
    )
    return (velocity_ok & impulse_ok).all(dim=-1)


def mode_conditions(
    problem: ContactProblem,
    *,
    v_next: Tensor,
    pn: Tensor,
    pt: Tensor,
    mode: Tensor,
    atol: float,
    v_free: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """The conditions of :func:`consistent_with_mode`, per slot, in two parts: those on the
    velocities (a separated slot does not penetrate; an active slot's gap rate is zero; a
    sticking slot does not slip; a sliding slot slips against its friction) and those on
    the impulses (non-negative; none at a separated or padding slot; friction inside the cone
    when sticking, on its boundary along the slot's directions when sliding). The arguments
    are those of :func:`consistent_with_mode`.

    Returns:
        ``velocity_ok, impulse_ok``: ``(*B, K)`` bool each (``True`` at padding slots'
        velocity conditions).
    """
    gap_rate, slip = velocity_terms(problem, v_next)
    velocity_scale, impulse_scale = _scales(
        problem, v_next=v_next, pn=pn, pt=pt, gap_rate=gap_rate, slip=slip, v_free=v_free
    )
    v_tol, p_tol = atol * velocity_scale, atol * impulse_scale
    p_tol_d = p_tol.unsqueeze(-1)
    friction_total = pt.sum(dim=-1)
    mu_pn = problem.mu * pn
    mode = mode.expand(pn.shape)
    # The directions that carry a sliding slot's friction: d twice (edge) or d, d + 1 (face).
    pair = torch.stack(friction_pair(mode, num_directions=problem.num_directions), dim=-1)
    face = is_face_sliding(mode, num_directions=problem.num_directions)
    slip_pair = slip.gather(-1, pair)
    pt_pair = pt.gather(-1, pair)
    pt_carried = pt_pair[..., 0] + torch.where(face, pt_pair[..., 1], 0.0)

    nonnegative = (pn >= -p_tol) & (pt >= -p_tol_d).all(dim=-1)
    no_impulse = (pn.abs() <= p_tol) & (pt.abs() <= p_tol_d).all(dim=-1)
    closed = gap_rate.abs() <= v_tol
    sticking_slip = closed & (slip.abs() <= v_tol.unsqueeze(-1)).all(dim=-1)
    sticking_cone = friction_total <= mu_pn + p_tol
    sliding_cone = (friction_total - mu_pn).abs() <= p_tol
    sliding_cone = sliding_cone & ((pt_carried - friction_total).abs() <= p_tol)
    least_slip = slip.amin(dim=-1, keepdim=True) + v_tol.unsqueeze(-1)
    against = (slip_pair <= v_tol.unsqueeze(-1)) & (slip_pair <= least_slip)
    sliding_slip = closed & against.all(dim=-1)
    velocity_ok = torch.where(
        mode == SEPARATED,
        gap_rate >= -v_tol,
        torch.where(mode == STICKING, sticking_slip, sliding_slip),
    )
    impulse_ok = torch.where(
        mode == SEPARATED,
        no_impulse,
        torch.where(mode == STICKING, sticking_cone, sliding_cone) & nonnegative,
    )
    velocity_ok = velocity_ok | ~problem.slot_mask
    impulse_ok = torch.where(problem.slot_mask, impulse_ok, no_impulse)
    return velocity_ok, impulse_ok


def check_solution(problem: object, solution: object) -> None:
    """Check that ``solution`` is a :class:`Solution` shaped like ``problem``'s.

    Raises:
        ValueError: naming ``problem`` or ``solution`` (and the field at fault).
    """
    if not isinstance(problem, ContactProblem):
        raise ValueError(f"problem must be a ContactProblem, got {type(problem).__name__}")
    if not isinstance(solution, Solution):
        raise ValueError(f"solution must be a Solution, got {type(solution).__name__}")
    batch, K, D = problem.batch_shape, problem.num_slots, problem.num_directions
    for name, event in (("v_next", (problem.num_dofs,)), ("pn", (K,)), ("pt", (K, D))):
        value = check_tensor(
            f"solution.{name}", getattr(solution, name), event_shape=event, like=problem.M
        )
        if value.shape[: value.dim() - len(event)] != batch:
            raise ValueError(
                f"solution.{name}: expected batch shape {tuple(batch)}, got {tuple(value.shape)}"
            )
    mode = solution.mode
    if not isinstance(mode, Tensor) or mode.dtype != torch.long or mode.shape != (*batch, K):
        raise ValueError(
            f"solution.mode must be a long tensor of shape {(*batch, K)}, got {describe(mode)}"
        )
    if mode.numel() and (int(mode.min()) < 0 or int(mode.max()) >= num_modes(D)):
        raise ValueError(f"solution.mode values must lie in [0, {num_modes(D)}) for D = {D}")
