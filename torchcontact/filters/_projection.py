"""Constrained Kalman update: every particle's Gaussian projected out of the bodies it enters."""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from torchcontact._checks import check_batched, check_real, describe
from torchcontact.filters._gaussian import unchecked_gaussian
from torchcontact.filters._kalman import kf_update
from torchcontact.filters._manifold import SE3
from torchcontact.filters._rbpf_belief import RBPFBelief
from torchcontact.filters._spatial_contact_model import (
    STATE_DIM,
    TANGENT_DIM,
    RobotControl,
    check_control,
    robot_contact_problem,
    servo_velocities,
)
from torchcontact.geometry import quat_to_matrix
from torchcontact.sim import Scene, penetration


def project_out_of_contact(
    belief: RBPFBelief,
    scene: Scene,
    q_kinematic: Tensor | None = None,
    *,
    gap_sigma: float,
    control: RobotControl | None = None,
    mode_table: Tensor | None = None,
) -> RBPFBelief:
    r"""Project every particle's Gaussian out of the bodies its mean penetrates.

    An RBPF over contact modes linearizes each mode's step at the belief's mixture mean
    (:class:`~torchcontact.filters.PlanarContactModel`), so a particle away from the mean (or
    one whose mode keeps a slot separated while a finger moves into it) can end a step
    inside a finger or the table. This solves, per particle, the constrained Kalman update
    with the non-penetration constraints of the slots its mean violates taken as perfect-but-
    softened measurements (estimate projection; Simon and Chia 2002, Simon 2010): for every
    slot :math:`s` whose gap :math:`\phi_s(\mu)` at the particle's mean :math:`\mu` is
    negative, the pseudo-measurement

    .. math::

        0 = \phi_s(\mu) + J_s (x - \mu) + e_s, \qquad e_s \sim N(0, \sigma^2),

    with :math:`J_s` the slot's normal row (the gradient of its gap w.r.t. the body's pose
    ``x[:3]``; zero w.r.t. the twist), enters one joint Kalman update
    (:func:`~torchcontact.filters.kf_update`). As :math:`\sigma \to 0` the mean moves to the
    minimum-:math:`P^{-1}`-distance point of the linearized constraint surface
    :math:`\phi_s = 0` and the covariance collapses along the rows :math:`J_s`. Particles
    that penetrate nothing, the weights, the modes and the evidence are unchanged.

    Spatial scenes (a :class:`~torchcontact.filters.SpatialContactModel`'s belief on SE(3),
    the state ``(p, q, v, ω)``): the gaps and rows are those of
    :func:`~torchcontact.sim.contact_problem` at each particle's mean under the robots'
    ``control``, the update runs in the tangent at the mean (:math:`J_s = (n,\ (r \times
    n)^\top R)` along :math:`(\delta p, \delta\theta)`, ``R`` the body's rotation) and
    its result is retracted onto the manifold. With the model's ``mode_table``, each
    particle's Gaussian is also projected onto the contacts its mode closes: the slots
    in contact in its mode (sticking or sliding, code ``>= 1``) get the same pseudo-measurement
    whatever the sign of their gap, so a particle in a mode that sets the box on the table is
    set on the table (the mode is a contact state; its gaps are zero), and its twist is
    projected onto the mode's velocity constraints: the gap rates :math:`J_n v + b_n` of
    those slots and the slips :math:`J_t v + b_t` of its sticking ones are pseudo-measured
    zero with std :math:`\sigma / h` (the same softness over one step). Without that, a
    twist that no measurement sees while the camera is occluded keeps whatever the steps
    of other modes left in it, and a grasp's stiff modes amplify it.

    Args:
        belief: an RBPF belief, batch ``(*B,)`` with ``N`` particles whose state begins with
            the pose ``(x, y, θ)`` (world frame) of ``scene``'s one dynamic body (spatial:
            the 13-dim state on SE(3)).
        scene: the filter's scene (one dynamic body).
        q_kinematic: ``(*B, Nk, 3)`` kinematic-body poses (world frame) at the belief's time
            (planar scenes).
        gap_sigma: ``σ``, the pseudo-measurement's noise std, metres, ``> 0``.
        control: the robots' joint positions, velocities and base poses (and kinematic
            bodies' poses) at the belief's time, batch ``*B`` (spatial scenes; the joints'
            velocities, kinematic or servo, enter the gap rates and slips of the mode's
            contacts).
        mode_table: ``(K, S)`` long, the model's per-slot modes of its ``K`` modes
            (``S = scene.num_slots``; spatial scenes), or ``(*B, K, S)`` per batch entry
            (e.g. :meth:`~torchcontact.filters.SpatialContactModel.slot_modes` at the
            belief's mean: a table of slot-group states names every slot of a touching group,
            its resolution only the slots that touch), or None: penetrated slots only.

    Returns:
        The belief with projected Gaussians.

    Raises:
        ValueError: ``gap_sigma`` is not positive, ``scene`` has not one dynamic body, the
            state has fewer than 3 components, or ``q_kinematic`` has another shape.

    References:
        D. Simon and T. L. Chia, "Kalman filtering with state equality constraints", IEEE
        Trans. Aerospace and Electronic Systems 38(1), 2002.
        D. Simon, "Kalman filtering with state constraints: a survey of linear and nonlinear
        algorithms", IET Control Theory & Applications 4(8), 2010.
    """
    gap_sigma = check_real("gap_sigma", gap_sigma, low=0.0, low_open=True)
    if not isinstance(scene, Scene) or len(scene.dynamic) != 1:
        raise ValueError("scene: expected a Scene with one dynamic body")
    if scene.dimension == 3:
        return _project_spatial(belief, scene, control, gap_sigma, mode_table)
    if mode_table is not None:
        raise ValueError("mode_table: supported on spatial scenes only")
    if not isinstance(q_kinematic, Tensor):
        raise ValueError(f"q_kinematic: required for a planar scene, got {describe(q_kinematic)}")
    g = belief.gaussians
    batch, N, n = belief.batch_shape, belief.num_particles, g.dim
    if n < 3:
        raise ValueError(f"belief: expected a state that begins with a pose (n >= 3), got n = {n}")
    shape = (*batch, len(scene.kinematic), 3)
    check_batched("q_kinematic", q_kinematic, shape=shape, like=g.mean, like_name="belief")
    phi, Jn, penetrating = penetration(
        scene,
        q=g.mean[..., None, :3],
        q_kinematic=q_kinematic.unsqueeze(-3).expand(*batch, N, *shape[-2:]),
    )  # (*B, N, L), (*B, N, L, 3), (*B, N, L)
    slots = penetrating.flatten(0, -2).any(0).nonzero().squeeze(-1)
    if slots.numel() == 0:
        return belief
    m = int(slots.numel())
    H = g.mean.new_zeros(*batch, N, m, n)
    H[..., :3] = Jn[..., slots, :]
    d = phi[..., slots] - (H @ g.mean[..., None]).squeeze(-1)
    R = g.mean.new_full((m,), gap_sigma**2).diag()
    projected, _ = kf_update(
        g, g.mean.new_zeros(*batch, N, m), H=H, d=d, R=R, mask=penetrating[..., slots]
    )
    return dataclasses.replace(belief, gaussians=projected)


def _project_spatial(
    belief: RBPFBelief,
    scene: Scene,
    control: RobotControl | None,
    gap_sigma: float,
    mode_table: Tensor | None,
) -> RBPFBelief:
    """:func:`project_out_of_contact` of a belief on SE(3) (see there)."""
    g = belief.gaussians
    batch, N = belief.batch_shape, belief.num_particles
    if g.dim != STATE_DIM or g.tangent_dim != TANGENT_DIM:
        raise ValueError(
            f"belief: expected states (p, q, v, ω) on SE(3), n = {STATE_DIM} with a "
            f"{TANGENT_DIM}-dim tangent, got n = {g.dim}, d = {g.tangent_dim}"
        )
    flat = g.mean.reshape(-1, STATE_DIM)
    P = flat.shape[0]
    ctrl = check_control(scene, control, batch, flat.dtype, flat.device)
    # Every particle of a batch entry shares its control.
    problem, geometry = robot_contact_problem(scene, flat, ctrl.expand(N))
    phi, Jn = geometry.phi, problem.Jn[..., :6]  # (P, S) unclamped gaps, (P, S, 6)
    constrained = geometry.active & (phi < 0)  # penetrated
    closed = torch.zeros_like(constrained)
    sticking = torch.zeros_like(constrained)
    if mode_table is not None:
        K, S = belief.num_modes, scene.num_slots
        if (
            not isinstance(mode_table, Tensor)
            or mode_table.dtype != torch.long
            or tuple(mode_table.shape) not in ((K, S), (*batch, K, S))
        ):
            raise ValueError(
                f"mode_table: expected a long ({K}, {S}) or {(*batch, K, S)} tensor, got "
                f"{describe(mode_table)}"
            )
        table = mode_table.to(phi.device).expand(*batch, K, S)
        index = belief.modes.clamp(min=0)[..., None].expand(*batch, N, S)
        slot_modes = table.gather(-2, index).reshape(P, S)  # (P, S)
        closed = geometry.active & (slot_modes >= 1)
        sticking = geometry.active & (slot_modes == 1)
        constrained = constrained | closed
    slots = constrained.any(0).nonzero().squeeze(-1)
    if slots.numel() == 0:
        return belief
    # Rows: the gaps of the constrained slots (pose), then the gap rates of the closed slots
    # and the slips of the sticking ones along the first D/2 directions (twist; the other
    # half are their opposites).
    half = problem.num_directions // 2
    rotation = quat_to_matrix(flat[:, 3:7])  # (P, 3, 3): body to world
    gap_rows = flat.new_zeros(P, slots.numel(), TANGENT_DIM)
    gap_rows[..., :3] = Jn[:, slots, :3]
    gap_rows[..., 3:6] = Jn[:, slots, 3:] @ rotation  # ∂φ/∂δθ = (r × n)ᵀ R
    twist = flat[:, 7:13, None]
    Jt = problem.Jt[:, slots, :half, :6]  # (P, m, D/2, 6)
    bn = phi.new_zeros(phi.shape) if problem.bn is None else problem.bn
    bt = Jt.new_zeros(Jt.shape[:-1]) if problem.bt is None else problem.bt[:, slots, :half]
    rate_rows = flat.new_zeros(P, slots.numel(), 1 + half, TANGENT_DIM)
    rate_rows[..., 0, 6:] = Jn[:, slots]
    rate_rows[..., 1:, 6:] = Jt
    rates = (rate_rows[..., 6:] @ twist[:, None]).squeeze(-1)  # (P, m, 1 + D/2)
    rates = rates + torch.cat([bn[:, slots, None], bt], -1)
    if scene.num_servo_joints:
        # the servo joints' motion, columns after the body's twist (kinematic joints: in b)
        joints = servo_velocities(scene, ctrl.expand(N).v_robot)[:, None, :, None]
        rows = torch.cat([problem.Jn[:, slots, None, 6:], problem.Jt[:, slots, :half, 6:]], 2)
        rates = rates + (rows @ joints).squeeze(-1)
    rate_mask = torch.cat(
        [closed[:, slots, None], sticking[:, slots, None].expand(-1, -1, half)], -1
    )
    H = torch.cat([gap_rows, rate_rows.flatten(1, 2)], 1)
    d = torch.cat([phi[:, slots], rates.flatten(1)], 1)
    mask = torch.cat([constrained[:, slots], rate_mask.flatten(1)], 1)
    m = H.shape[1]
    sigma = torch.cat(
        [
            flat.new_full((slots.numel(),), gap_sigma),
            flat.new_full((m - slots.numel(),), gap_sigma / scene.h),
        ]
    )
    tangent = unchecked_gaussian(
        flat.new_zeros(P, TANGENT_DIM), g.cov.reshape(P, TANGENT_DIM, TANGENT_DIM)
    )
    projected, _ = kf_update(
        tangent, flat.new_zeros(P, m), H=H, d=d, R=sigma.pow(2).diag(), mask=mask
    )
    mean = SE3.retract(flat, projected.mean)
    gaussians = unchecked_gaussian(mean.reshape(g.mean.shape), projected.cov.reshape(g.cov.shape))
    return dataclasses.replace(belief, gaussians=gaussians)
