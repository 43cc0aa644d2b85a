"""The per-mode linearization of :class:`~torchcontact.filters.PlanarContactModel`, fast.

It computes what the model's definition asks for: the exact Jacobian of the mode-fixed step
(:func:`~torchcontact.sim.contact_problem`, :func:`~torchcontact.contact.solve_mode`,
semi-implicit Euler) at the linearization point, and
:func:`~torchcontact.contact.is_consistent` there with the mode's gaps closed. The tensors
are small (a few modes, a dozen slots), so the time goes into the number of tensor
operations (a few microseconds each), not their size; this module uses a fixed number of
them per call, whatever the batch:

* the slot rows of every slot group at once (:func:`slot_rows`), from body-frame tables built
  once per scene: each shape's vertices, edge normals and edge directions (its contact
  tangents) rotate together, and a half-plane is a polygon of one unbounded edge; with them
  their derivatives along the tracked body's pose (``x``, ``y``, ``θ``), in closed form by
  the same operations (a rotated row's derivative along ``θ`` is the row turned by +90°, the
  gap ``φ`` takes that of its closest edge), stacked behind the rows;
* each mode's system holds only the slots that the mode activates and that are candidates at
  the point (sorted from a table of each mode's slots built once per model);
  ``solve_mode``'s system is the identity on every other row. The mode fixes the constraint
  rows ``C`` (active normals, sticking tangents), the impulse rows ``G`` (``C`` with
  ``μ Jt_d`` added to the normals of sliding slots), ``U = M⁻¹ Gᵀ``, ``A = C U`` and
  ``b = −(C v_free + target)``, ``target = (bn + φ/h, bt)``; all linear in the slot rows, so
  their derivatives along the pose follow from the rows' by the same operations;
* ``solve_mode``'s two iterated Tikhonov passes for the impulses ``x`` (``A x = b``), at the
  point and at the point with the mode's gaps closed (the consistency check's); the second
  pass (the friction split among redundant sticking contacts) runs on every mode and is kept
  for those with sticking slots, as ``solve_mode`` on one mode: it leaves the step unchanged
  where the mode's system is solvable, and decides the regularised answer where it is not.
  Each pass factors its matrices once (:class:`~torchcontact.contact.TikhonovSystem`, the
  solve ``solve_mode`` runs) and iterates with products;
* the derivative along each of the six coordinates at once: ``dx = P(db − dA x)`` with
  ``dA = dC U + C dU`` and ``P`` the iterated Tikhonov solve of the pass kept (its factors
  and weights held), ``dv⁺ = dU x + U dx + dv_free`` (``dv_free`` the unit twists along
  ``v``, zero along the pose), so that ``F = [[I + h ∂v⁺/∂q, h ∂v⁺/∂v], [∂v⁺/∂q, ∂v⁺/∂v]]``;
* ``is_consistent``'s tests on every slot, knowing which carry impulses;
* one host synchronisation (the size of the systems) and no validation: the model checks its
  inputs at its public methods.

With ``for_compile`` (the model's ``compiled=True``) the systems are sized by the mode table
instead: no host synchronisation, shapes that do not depend on the data, as
:func:`torch.compile` wants them.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact.contact import (
    SOLVE_MODE_REFINEMENTS,
    SOLVE_MODE_WEIGHTED_REFINEMENTS,
    ContactProblem,
    consistent_with_mode,
    friction_split_weights,
    iterated_tikhonov,
    tikhonov_system,
)
from torchcontact.filters._planar_slots import SlotLayout, slot_rows

#: Tikhonov shift of ``solve_mode`` relative to the largest diagonal entry of the system.
_SQRT_EPS = torch.finfo(torch.float64).eps ** 0.5


@dataclass(frozen=True, eq=False)
class ModeTable:
    """A model's per-slot modes as the linearization uses them, built once.

    Each mode's constraint system is laid out over ``W`` slots (``W`` the most slots any mode
    activates among the candidates of the call): the slots it activates that are candidates,
    in slot order, then others, whose rows are unused (the identity): ``W`` normal rows, then
    ``W`` tangent rows. The table keeps each mode's first ``W_max`` slots in that order
    without the candidates (those it activates, then the others), so a call only sorts them.

    Attributes:
        modes: ``(K, S)`` long per-slot modes.
        slots: ``(K, W_max)`` long, the slots each mode activates in slot order, then the
            first slots it does not (``W_max`` the most slots any mode activates).
        activates: ``(K, W_max)`` bool, the mode activates the slot (mode ≥ 1).
        sticks: ``(K, W_max)`` bool, the slot sticks in the mode (mode 1).
        sliding_sign: ``(K, W_max)`` float64 ``±1`` where the slot slides with friction
            along ``±t``, else 0.
        acting: ``(K, S)`` bool, the slot carries an impulse in the mode (mode ≥ 1).
        sticking: ``(K, S)`` bool, mode 1.
        slide_sign: ``(K, S)`` float64 ``+1`` where the slot slides with friction along
            ``+t`` (mode 2), ``-1`` along ``−t`` (mode 3), else 0.
    """

    modes: Tensor
    slots: Tensor
    activates: Tensor
    sticks: Tensor
    sliding_sign: Tensor
    acting: Tensor
    sticking: Tensor
    slide_sign: Tensor


def mode_table(layout: SlotLayout, modes: Tensor) -> ModeTable:
    """The :class:`ModeTable` of ``(K, S)`` long per-slot modes."""
    f64 = torch.float64
    modes = modes.to(layout.gravity_step.device)
    acting = modes >= 1
    W = max(1, int(acting.sum(-1).max()))
    slots = torch.argsort(acting.to(torch.uint8), dim=-1, descending=True, stable=True)[:, :W]
    sign = (modes == 2).to(f64) - (modes == 3).to(f64)
    return ModeTable(
        modes=modes,
        slots=slots,
        activates=acting.gather(-1, slots),
        sticks=(modes == 1).gather(-1, slots),
        sliding_sign=sign.gather(-1, slots),
        acting=acting,
        sticking=modes == 1,
        slide_sign=sign,
    )


def linearize_modes(
    layout: SlotLayout,
    table: ModeTable,
    x: Tensor,
    q_kinematic: Tensor,
    v_kinematic: Tensor,
    *,
    mu: Tensor,
    inverse_mass: Tensor,
    consistency_gap: float,
    consistency_tolerance: float,
    for_compile: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """Every mode's step linearized at ``x`` (its exact Jacobian), and its consistency.

    Args:
        layout: the scene's layout.
        table: the ``K`` modes.
        x: ``(B, 6)`` float64 linearization points.
        q_kinematic: ``(B, Nk, 3)`` float64 kinematic poses.
        v_kinematic: ``(B, Nk, 3)`` float64 kinematic twists.
        mu: ``(S,)`` float64 friction coefficient of every slot (may require grad).
        inverse_mass: ``(3,)`` float64 ``(1/m, 1/m, 1/I)`` of the tracked body (may require
            grad).
        consistency_gap: gaps of a mode's slots within ``±consistency_gap`` are taken as
            closed by the check: a mean a millimetre off a contact (whose ``φ/h`` correction
            would turn its impulse around) does not count against the mode, while a contact
            held across a wider gap (a box "stuck" to a finger it has left) does.
        consistency_tolerance: relative tolerance of the check.
        for_compile: lay every system out over ``W_max`` slots (the most any mode of the
            table activates) instead of the most the modes activate among this call's
            candidates (the extra rows are the identity, decoupled): larger systems, the same
            results to rounding, no host synchronisation and shapes that do not depend on the
            data, as :func:`torch.compile` wants them.

    Returns:
        ``F (B, K, 6, 6)``, ``c (B, K, 6)`` and ``(B, K)`` bool: the mode is consistent.
    """
    B, (K, S), h, gap = x.shape[0], table.modes.shape, layout.h, consistency_gap
    features, candidate = slot_rows(layout, x[:, :3], q_kinematic, v_kinematic, tangents=True)
    centre = features[:, 0]  # (B, S, 9); features (B, 4, S, 9): value, d/dx, d/dy, d/dθ

    # Each mode's slots: those it activates among the candidates, in slot order, then others.
    slots = table.slots.expand(B, K, -1)
    acting = candidate.gather(-1, slots.flatten(1)).view_as(slots) & table.activates
    W = table.slots.shape[-1] if for_compile else max(1, int(acting.sum(-1).max()))
    order = torch.argsort(acting.to(torch.uint8), dim=-1, descending=True, stable=True)[..., :W]
    keep = slots.gather(-1, order)  # (B, K, W)
    acting = acting.gather(-1, order)
    sticks = acting & table.sticks.expand(B, K, -1).gather(-1, order)
    slide = (table.sliding_sign * mu[table.slots]).expand(B, K, -1).gather(-1, order)
    slide = slide[:, :, None, :, None]  # ±μ of the sliding slots

    # solve_mode on those slots: constraint rows C (normals, then tangents) and impulse rows
    # G (the same with μ Jt_d added to the normals of sliding slots); the rows of acting
    # normals and sticking tangents make the Schur system A = C U, U = M⁻¹ Gᵀ, for the
    # impulses; the other rows are the identity, with a zero right side. All of it is linear
    # in the slot rows, so their derivatives along the pose (stacked behind them) give dC,
    # dU and the derivative of the target (bn + φ/h, bt) by the same operations.
    index = (torch.arange(4, device=x.device)[:, None] * S + keep.unsqueeze(2)).view(B, -1, 1)
    rows = features.flatten(1, 2).gather(1, index.expand(-1, -1, 9)).view(B, K, 4, W, 9)
    phi, Jn, Jt, bn, bt = rows.split([1, 3, 3, 1, 1], dim=-1)
    on = torch.cat([acting, sticks, acting, sticks], dim=-1).to(torch.float64)  # (B, K, 4W)
    rows_on = on[:, :, None, :, None]
    on_c = rows_on[..., : 2 * W, :]
    CG = torch.cat([Jn, Jt, Jn + slide * Jt, Jt], dim=-2) * rows_on
    C, U = CG[..., : 2 * W, :], (CG[..., 2 * W :, :] * inverse_mass).mT  # (B, K, 4, ·, ·)
    target = torch.cat([bn + phi / h, bt], dim=-2)  # (B, K, 4, 2W, 1)
    C0, U0 = C[:, :, :1], U[:, :, :1]
    system = C0 @ U0  # (B, K, 1, 2W, 2W)
    v_free = (x[:, 3:] + layout.gravity_step)[:, None, None, :, None]  # (B, 1, 1, 3, 1)
    # Two points: x, and x with the mode's gaps closed up to the dead zone (the consistency
    # check's).
    closed = torch.nn.functional.pad(phi[:, :, :1].clamp(-gap, gap), (0, 0, 0, W))
    target_points = torch.addcmul(target[:, :, :1], closed, layout.closing, value=-1.0 / h)
    b = torch.addcmul(C0 @ v_free, target_points, on_c).neg()  # (B, K, 2, 2W, 1)
    off = 1.0 - on[:, :, None, : 2 * W]  # (B, K, 1, 2W): the identity rows
    scale = system.diagonal(dim1=-2, dim2=-1).abs().amax(dim=-1, keepdim=True).clamp_min(1.0)
    shift = (_SQRT_EPS * scale).unsqueeze(-1)  # (B, K, 1, 1, 1)
    A = system + torch.diag_embed(off)
    # Few systems, many iterations and right-hand sides: iterations as products.
    first = tikhonov_system(A, shift[..., 0].expand_as(off), products=True)
    impulses = iterated_tikhonov(first, b, refinements=SOLVE_MODE_REFINEMENTS)
    # Redundant sticking rows leave the impulse split free: solve_mode prefers normal support
    # and shares friction in proportion to the normal loads (kept for modes that stick).
    friction = friction_split_weights(impulses[..., :W, :], dim=-2)
    weighted = torch.cat([shift.expand_as(friction), shift * friction], dim=-2)  # (..., 2W, 1)
    second = tikhonov_system(A, weighted[..., 0], products=True)
    split = iterated_tikhonov(second, b, refinements=SOLVE_MODE_WEIGHTED_REFINEMENTS)
    sticky = sticks.any(dim=-1)[:, :, None, None, None]
    impulses = torch.where(sticky, split, impulses)
    v_next = v_free + U0 @ impulses  # (B, K, 2, 3, 1)

    # The exact derivative of the step at x along the six coordinates j (the discrete choices
    # held): with w_j = dv_free + dU x (dv_free = e_j along the twist, dU along the pose),
    # dx = P(db − dA x) = −P(dC v⁺ + C w_j + dtarget), P the solve above (its weights held),
    # and dv⁺ = w_j + U dx.
    v_plus = v_next[:, :, :1]
    w = torch.cat(
        [U[:, :, 1:] @ impulses[:, :, :1], layout.twist_tangents.expand(B, K, 3, 3, 1)], 2
    )
    moving = torch.addcmul(C[:, :, 1:] @ v_plus, target[:, :, 1:], on_c)  # (B, K, 3, 2W, 1)
    rhs = (C0 @ w + torch.nn.functional.pad(moving, (0, 0, 0, 0, 0, 3))).neg()  # (B, K, 6, ·)
    # The kept pass's system at x, factored once more (selecting factors instead would feed
    # computed pivots to lu_solve, which crashes torch 2.13's compiled C++ wrapper).
    held = tikhonov_system(A, torch.where(sticky, weighted[:, :, :1], shift)[..., 0], products=True)
    # The six directions as the columns of one right-hand side (B, K, 1, 2W, 6).
    columns = iterated_tikhonov(
        held, rhs.squeeze(-1).mT.unsqueeze(2), refinements=SOLVE_MODE_WEIGHTED_REFINEMENTS
    )
    derivative = columns.squeeze(2).mT.unsqueeze(-1)  # (B, K, 6, 2W, 1)
    dv = (w + U0 @ derivative).squeeze(-1).mT  # (B, K, 3, 6): ∂v⁺/∂x
    F = torch.cat([torch.add(layout.embed, dv, alpha=h), dv], dim=-2)  # (B, K, 6, 6)
    v_step = v_plus[:, :, 0, :, 0]  # (B, K, 3)
    f = torch.cat([x[:, None, :3] + h * v_step, v_step], dim=-1)  # (B, K, 6)
    c = f - (F @ x[:, None, :, None]).squeeze(-1)

    # is_consistent at the last point (the mode's gaps closed), on every slot: the impulses
    # placed back on their slots, a sliding slot's friction μ pn along its direction.
    impulse = impulses[:, :, -1, :, 0].unflatten(-1, (2, W))  # (B, K, 2, W): normal, tangent
    placed = impulse.new_zeros(B, K, 2, S).scatter(
        -1, keep.unsqueeze(2).expand_as(impulse), impulse
    )
    pn, tangential = placed.unbind(2)
    friction = torch.where(table.sticking, tangential, table.slide_sign * mu * pn)
    pt = torch.stack([friction.clamp(min=0.0), (-friction).clamp(min=0.0)], dim=-1)
    phi_all = centre[:, None, :, 0]  # (B, 1, S)
    rows_centre = centre[:, None, :, 1:7].unflatten(-1, (2, 3))  # (B, 1, S, 2, 3): Jn, Jt
    known = centre[:, None, :, 7:9]  # (B, 1, S, 2): bn, bt
    problem = ContactProblem.unchecked(
        M=torch.diag(inverse_mass.reciprocal()),
        v=x[:, None, 3:],
        f=layout.gravity_step / (h * inverse_mass),
        Jn=rows_centre[..., 0, :],
        Jt=torch.stack([rows_centre[..., 1, :], -rows_centre[..., 1, :]], dim=-2),
        phi=torch.where(table.acting, phi_all - phi_all.clamp(-gap, gap), phi_all),
        mu=mu,
        h=h,
        mask=candidate.unsqueeze(1),
        bn=known[..., 0],
        bt=torch.stack([known[..., 1], -known[..., 1]], dim=-1),
    )
    consistent = consistent_with_mode(
        problem,
        v_next=v_next[:, :, -1, :, 0],
        pn=pn,
        pt=pt,
        mode=table.modes,
        atol=consistency_tolerance,
        v_free=v_free[:, :, 0, :, 0].expand(B, K, 3),
    )
    return F, c, consistent
