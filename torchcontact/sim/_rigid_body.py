r"""Spatial rigid-body dynamics: world-frame mass matrices, the free step and pose integration.

A spatial body's pose is its centroid's position and a unit quaternion ``(w, x, y, z)``,
``q = (x, y, z, qw, qx, qy, qz)``; its twist is the centroid's velocity and the angular
velocity, both in the world frame, ``v = (v, ω)``. The Newton–Euler equations in these
coordinates are

.. math::

    m \dot v = f, \qquad I_w \dot\omega + \omega \times I_w \omega = \tau,
    \qquad I_w = R I_b R^\top,

with ``I_b`` the inertia about the centroid in the body frame and ``R`` the body's rotation.
The mass matrix ``diag(m 1₃, I_w)`` depends on the pose; the gyroscopic term
``ω × I_w ω`` is what makes a body spinning about its intermediate axis tumble.

Time stepping (semi-implicit, as the planar engine): the contact-free velocity ``v_free``
of a step, then the contact impulses, then ``q⁺ = (x + h v⁺, exp(h ω⁺) ⊗ quat)``. An explicit
gyroscopic term gains energy on tumbling bodies; the free angular velocity here solves the
implicit torque-free equation ``I_b (ω⁺ − ω)/h + ω⁺ × I_b ω⁺ = 0`` in the body frame by one
Newton step from ``ω`` (exact for a body spinning about a principal axis, where the term
vanishes), which dissipates a little of the rotational energy of a tumbling body instead of
creating it.

References:
    E. Catto, "Numerical methods", Game Developers Conference 2015 (the implicit gyroscopic
    step); T. Duff, J. Burgess, P. Christensen, C. Hery, A. Kensler, M. Liani and R. Villemin,
    "Building an orthonormal basis, revisited", Journal of Computer Graphics Techniques 6(1),
    2017 (the tangent basis).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcontact.geometry import quat_exp, quat_mul, quat_to_matrix


def world_inertia(inertia_body: Tensor, quaternion: Tensor) -> Tensor:
    """Inertia tensors about the centroids in the world frame, ``R I_b Rᵀ``.

    Args:
        inertia_body: ``(*B, 3, 3)`` inertia about the centroid, body frame.
        quaternion: ``(*B, 4)`` unit quaternions ``(w, x, y, z)`` (body to world).

    Returns:
        ``(*B, 3, 3)`` world-frame inertia tensors.
    """
    R = quat_to_matrix(quaternion)
    return R @ inertia_body @ R.transpose(-1, -2)


def spatial_mass_matrix(masses: Tensor, inertia_body: Tensor, quaternion: Tensor) -> Tensor:
    """The block-diagonal mass matrix ``diag(m₁ 1₃, I_w,1, m₂ 1₃, I_w,2, …)``.

    Args:
        masses: ``(N,)`` masses in kg.
        inertia_body: ``(N, 3, 3)`` inertias about the centroids, body frames.
        quaternion: ``(*B, N, 4)`` the bodies' orientations.

    Returns:
        ``(*B, 6N, 6N)`` mass matrix in twist coordinates ``(v, ω)`` per body, world frame.
    """
    batch, N = quaternion.shape[:-2], quaternion.shape[-2]
    inertia = world_inertia(inertia_body, quaternion)  # (*B, N, 3, 3)
    eye = torch.eye(3, dtype=inertia.dtype, device=inertia.device)
    translational = masses.to(inertia)[:, None, None] * eye  # (N, 3, 3)
    zero = torch.zeros_like(inertia)
    blocks = torch.cat(
        [
            torch.cat([translational.expand_as(inertia), zero], dim=-1),
            torch.cat([zero, inertia], dim=-1),
        ],
        dim=-2,
    )  # (*B, N, 6, 6)
    M = inertia.new_zeros(*batch, N, 6, N, 6)
    index = torch.arange(N, device=inertia.device)
    M[..., index, :, index, :] = blocks.movedim(-3, 0)
    return M.reshape(*batch, 6 * N, 6 * N)


def free_angular_velocity(
    inertia_body: Tensor, quaternion: Tensor, omega: Tensor, h: float
) -> Tensor:
    """The torque-free angular velocity after one implicit gyroscopic step.

    One Newton step from ``ω`` on ``g(ω⁺) = I_b (ω⁺ − ω) + h ω⁺ × I_b ω⁺ = 0`` in the body
    frame: ``ω⁺ = ω − J⁻¹ h (ω × I_b ω)`` with ``J = I_b + h ([ω]× I_b − [I_b ω]×)``.

    Args:
        inertia_body: ``(*B, 3, 3)`` inertias about the centroids, body frames.
        quaternion: ``(*B, 4)`` orientations.
        omega: ``(*B, 3)`` angular velocities, world frame.
        h: time step in seconds.

    Returns:
        ``(*B, 3)`` angular velocities, world frame.
    """
    R = quat_to_matrix(quaternion)
    w_body = (R.transpose(-1, -2) @ omega.unsqueeze(-1)).squeeze(-1)
    momentum = (inertia_body @ w_body.unsqueeze(-1)).squeeze(-1)
    residual = h * torch.linalg.cross(w_body, momentum)
    jacobian = inertia_body + h * (skew(w_body) @ inertia_body - skew(momentum))
    step = torch.linalg.solve(jacobian, residual.unsqueeze(-1)).squeeze(-1)
    omega_next: Tensor = (R @ (w_body - step).unsqueeze(-1)).squeeze(-1)
    return omega_next


def skew(u: Tensor) -> Tensor:
    """``(*B, 3, 3)`` cross-product matrices ``[u]×`` (``[u]× w = u × w``) of ``u (*B, 3)``."""
    x, y, z = u.unbind(-1)
    zero = torch.zeros_like(x)
    return torch.stack(
        [
            torch.stack([zero, -z, y], dim=-1),
            torch.stack([z, zero, -x], dim=-1),
            torch.stack([-y, x, zero], dim=-1),
        ],
        dim=-2,
    )


def integrate_poses(q: Tensor, v: Tensor, h: float) -> Tensor:
    """Poses after a step at constant twist: ``x + h v`` and ``exp(h ω) ⊗ quat``, renormalized.

    Args:
        q: ``(*B, N, 7)`` poses ``(x, y, z, qw, qx, qy, qz)``.
        v: ``(*B, N, 6)`` twists ``(v, ω)``, world frame.
        h: time step in seconds.

    Returns:
        ``(*B, N, 7)`` poses with unit quaternions.
    """
    position = q[..., :3] + h * v[..., :3]
    quaternion = quat_mul(quat_exp(h * v[..., 3:]), q[..., 3:])
    quaternion = quaternion / torch.linalg.vector_norm(quaternion, dim=-1, keepdim=True)
    return torch.cat([position, quaternion], dim=-1)


def tangent_basis(normal: Tensor) -> Tensor:
    """Two unit tangents ``t₁, t₂`` with ``(t₁, t₂, n)`` a right-handed orthonormal frame.

    The branchless construction of Duff et al. (2017): smooth in ``n`` everywhere except
    across ``n_z = 0`` where it switches hemispheres (``n`` near ``+z``, ground contacts,
    is in the interior of one branch).

    Args:
        normal: ``(*B, 3)`` unit normals.

    Returns:
        ``(*B, 2, 3)`` the tangents ``t₁`` and ``t₂ = n × t₁``.
    """
    x, y, z = normal.unbind(-1)
    sign = torch.where(z >= 0, 1.0, -1.0).to(normal)
    a = -1.0 / (sign + z)
    b = x * y * a
    t1 = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], dim=-1)
    t2 = torch.stack([b, sign + y * y * a, -y], dim=-1)
    return torch.stack([t1, t2], dim=-2)


def tangent_directions(normal: Tensor, num_directions: int) -> Tensor:
    """``D`` unit friction directions per normal, evenly spaced in the tangent plane.

    Direction ``d`` is ``cos(2πd/D) t₁ + sin(2πd/D) t₂`` (:func:`tangent_basis`): ordered by
    angle around the normal, direction ``d + D/2`` opposite of ``d``, as
    :class:`~torchcontact.contact.ContactProblem` requires.

    Args:
        normal: ``(*B, 3)`` unit normals.
        num_directions: ``D``, even and ``>= 4``.

    Returns:
        ``(*B, D, 3)`` directions.
    """
    if num_directions < 4 or num_directions % 2:
        raise ValueError(f"num_directions must be even and >= 4, got {num_directions}")
    half = num_directions // 2
    angles = torch.arange(half, dtype=normal.dtype, device=normal.device)
    angles = angles * (2.0 * math.pi / num_directions)
    weights = torch.stack([torch.cos(angles), torch.sin(angles)], dim=-1)  # (D/2, 2)
    basis = tangent_basis(normal)
    # cos t₁ + sin t₂ as two broadcast products (a batched product of 2-column matrices
    # costs several times more on a CPU).
    first = weights[:, :1] * basis[..., :1, :] + weights[:, 1:] * basis[..., 1:, :]
    # The opposite half negated exactly, not from cos(θ + π) (which rounds differently).
    return torch.cat([first, -first], dim=-2)
