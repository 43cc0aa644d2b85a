"""Constrained Kalman update: every particle's Gaussian projected out of the bodies it enters."""

from __future__ import annotations

import dataclasses

from torch import Tensor

from torchcontact._checks import check_batched, check_real
from torchcontact.filters._kalman import kf_update
from torchcontact.filters._rbpf_belief import RBPFBelief
from torchcontact.sim import Scene, penetration


def project_out_of_contact(
    belief: RBPFBelief, scene: Scene, q_kinematic: Tensor, *, gap_sigma: float
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

    Args:
        belief: an RBPF belief, batch ``(*B,)`` with ``N`` particles whose state begins with
            the pose ``(x, y, θ)`` (world frame) of ``scene``'s one dynamic body.
        scene: the filter's scene (one dynamic body).
        q_kinematic: ``(*B, Nk, 3)`` kinematic-body poses (world frame) at the belief's time.
        gap_sigma: ``σ``, the pseudo-measurement's noise std, metres, ``> 0``.

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
