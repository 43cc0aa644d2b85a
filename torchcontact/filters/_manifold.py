"""State manifolds for error-state (tangent-space) filtering: Euclidean, SE(2) and SE(3) poses."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final, Protocol, runtime_checkable

import torch
from torch import Tensor

from torchcontact._checks import check_float_shape, check_int
from torchcontact.geometry import quat_conj, quat_exp, quat_log, quat_mul, wrap_angle


@runtime_checkable
class Manifold(Protocol):
    r"""A state space with a retraction, for filters that keep covariances in a tangent space.

    ``retract(x, δ)`` moves the point ``x`` by the tangent vector ``δ``; ``local(x, y)`` is its
    inverse, the tangent vector at ``x`` pointing to ``y``:
    ``local(x, retract(x, δ)) == δ`` for small ``δ``. A Gaussian on the manifold has its mean
    ``x`` on the manifold and its covariance over ``δ`` (error-state form; Solà, "Quaternion
    kinematics for the error-state Kalman filter", 2017).

    Both maps take batched points ``(*B, n)`` and tangent vectors ``(*B, d)`` and must be
    differentiable with ``torch.func`` (the EKF differentiates them with ``jacfwd``).
    """

    def tangent_dim(self, dim: int) -> int:
        """Tangent dimension ``d`` of points of size ``dim`` (``ValueError`` if invalid)."""
        ...

    def retract(self, x: Tensor, delta: Tensor) -> Tensor:
        """``(*B, n)``, ``(*B, d)`` → ``(*B, n)``: the point reached from ``x`` along ``delta``."""
        ...

    def local(self, x: Tensor, y: Tensor) -> Tensor:
        """``(*B, n)``, ``(*B, n)`` → ``(*B, d)``: the tangent vector at ``x`` pointing to ``y``."""
        ...


def _sizes(manifold: Manifold, x: object) -> tuple[int, int]:
    """The sizes ``(n, d)`` of a point ``x`` ``(*B, n)`` of ``manifold`` and of its tangent
    (shapes only: usable under ``torch.func`` transforms).

    Raises:
        ValueError: ``x`` is not a float32/float64 tensor or ``n`` does not fit the manifold.
    """
    n = int(check_float_shape("x", x, trailing=(-1,), what="(*B, n)").shape[-1])
    try:
        return n, manifold.tangent_dim(n)
    except ValueError as err:
        raise ValueError(f"x: {err}") from err


@dataclass(frozen=True)
class Euclidean:
    """Flat space ``R^n``: ``retract(x, δ) = x + δ``, ``local(x, y) = y - x``."""

    def tangent_dim(self, dim: int) -> int:
        """``d = n``."""
        return check_int("dim", dim, low=1)

    def retract(self, x: Tensor, delta: Tensor) -> Tensor:
        """``x + δ``."""
        _, d = _sizes(self, x)
        return x + check_float_shape("delta", delta, trailing=(d,), what=f"(*B, {d})")

    def local(self, x: Tensor, y: Tensor) -> Tensor:
        """``y - x``."""
        n, _ = _sizes(self, x)
        return check_float_shape("y", y, trailing=(n,), what=f"(*B, {n})") - x


@dataclass(frozen=True)
class SE2Pose:
    """Planar pose ``(x, y, θ)`` in the world frame, optionally followed by Euclidean components.

    A point is ``(*B, 3 + r)``: position, heading θ (radians), then ``r`` Euclidean components
    (e.g. the twist ``(vx, vy, ω)``); the tangent has the same size. Perturbations are in the
    world frame and the heading is wrapped to ``(-π, π]``:
    ``retract(x, δ) = (p + δp, wrap(θ + δθ), v + δv)``, ``local(x, y) = (p_y - p_x,
    wrap(θ_y - θ_x), v_y - v_x)``.
    """

    def tangent_dim(self, dim: int) -> int:
        """``d = n`` (``n >= 3``)."""
        if check_int("dim", dim, low=1) < 3:
            raise ValueError(f"dim: an SE(2) pose needs n >= 3 (x, y, θ, ...), got {dim}")
        return dim

    def retract(self, x: Tensor, delta: Tensor) -> Tensor:
        """Add ``δ`` and wrap the heading."""
        _, d = _sizes(self, x)
        out = x + check_float_shape("delta", delta, trailing=(d,), what=f"(*B, {d})")
        return torch.cat([out[..., :2], wrap_angle(out[..., 2:3]), out[..., 3:]], dim=-1)

    def local(self, x: Tensor, y: Tensor) -> Tensor:
        """Subtract and wrap the heading difference."""
        n, _ = _sizes(self, x)
        diff = check_float_shape("y", y, trailing=(n,), what=f"(*B, {n})") - x
        return torch.cat([diff[..., :2], wrap_angle(diff[..., 2:3]), diff[..., 3:]], dim=-1)


@dataclass(frozen=True)
class SE3Pose:
    """Spatial pose: position + unit quaternion ``(w, x, y, z)``, optionally followed by
    Euclidean components.

    A point is ``(*B, 7 + r)``: world-frame position ``p``, orientation ``q`` (body to world),
    then ``r`` Euclidean components (e.g. the twist); the tangent is ``(*B, 6 + r)``:
    ``(δp, δθ, δv)`` with ``δp`` in the world frame and ``δθ`` a rotation vector in the body
    frame (right perturbation):

        retract(x, δ) = (p + δp, q ⊗ Exp(δθ), v + δv),
        local(x, y) = (p_y - p_x, Log(q_x⁻¹ ⊗ q_y), v_y - v_x).

    ``Log`` takes the shortest rotation (``q`` and ``-q`` are the same pose); ``retract``
    re-normalizes the quaternion.
    """

    def tangent_dim(self, dim: int) -> int:
        """``d = n - 1`` (``n >= 7``)."""
        if check_int("dim", dim, low=1) < 7:
            raise ValueError(f"dim: an SE(3) pose needs n >= 7 (position, quaternion), got {dim}")
        return dim - 1

    def retract(self, x: Tensor, delta: Tensor) -> Tensor:
        """``(p + δp, q ⊗ Exp(δθ), v + δv)``."""
        _, d = _sizes(self, x)
        check_float_shape("delta", delta, trailing=(d,), what=f"(*B, {d})")
        q = quat_mul(x[..., 3:7], quat_exp(delta[..., 3:6]))
        q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
        return torch.cat([x[..., :3] + delta[..., :3], q, x[..., 7:] + delta[..., 6:]], dim=-1)

    def local(self, x: Tensor, y: Tensor) -> Tensor:
        """``(p_y - p_x, Log(q_x⁻¹ ⊗ q_y), v_y - v_x)``."""
        n, _ = _sizes(self, x)
        check_float_shape("y", y, trailing=(n,), what=f"(*B, {n})")
        rot = quat_log(quat_mul(quat_conj(x[..., 3:7]), y[..., 3:7]))
        return torch.cat([y[..., :3] - x[..., :3], rot, y[..., 7:] - x[..., 7:]], dim=-1)


EUCLIDEAN: Final = Euclidean()
"""Flat state space (the default of every filter)."""
SE2: Final = SE2Pose()
"""Planar pose ``(x, y, θ, *extra)``."""
SE3: Final = SE3Pose()
"""Spatial pose ``(p, q_wxyz, *extra)`` with a 6-dim (+extra) tangent."""
