"""The batched Gaussian belief shared by every filter."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from torchcontact._checks import FLOAT_DTYPES, all_finite, check_symmetric_psd


@dataclass(frozen=True, eq=False)
class Gaussian:
    r"""A batch of Gaussian beliefs :math:`\mathcal N(\mu, P)` with leading batch dims ``*B``.

    For a Euclidean state the covariance is over the state itself (``d == n``). For a state on
    a manifold (a pose with a unit quaternion, see :class:`~torchcontact.filters.SE3Pose`) the
    mean is the point on the manifold and the covariance lives in the ``d``-dimensional
    tangent space at the mean (error-state form), so ``d <= n``; the Kalman functions
    (:func:`~torchcontact.filters.kf_predict`, :func:`~torchcontact.filters.kf_update`) need
    ``d == n``, the EKF functions take the manifold explicitly.

    Attributes:
        mean: ``(*B, n)`` mean, in the frame of the model that produced it.
        cov: ``(*B, d, d)`` covariance (symmetric positive semi-definite), same dtype/device.

    Construction validates shapes, dtype (float32 or float64, shared), finiteness, and that
    ``cov`` is symmetric positive semi-definite to a tolerance relative to its scale and the
    dtype's epsilon (:func:`~torchcontact._checks.check_symmetric_psd`), and raises
    ``ValueError`` naming the field at fault. Indexing ``g[idx]`` indexes the batch dims only
    (any torch index: ints, slices, ``...``, ``None``, bool or long tensors).
    """

    mean: Tensor
    cov: Tensor

    def __post_init__(self) -> None:
        mean, cov = self.mean, self.cov
        for name, value in (("mean", mean), ("cov", cov)):
            if not isinstance(value, Tensor):
                raise ValueError(f"{name}: expected a torch.Tensor, got {type(value).__name__}")
            if value.dtype not in FLOAT_DTYPES:
                raise ValueError(f"{name}: expected float32 or float64, got dtype {value.dtype}")
        if cov.dtype != mean.dtype or cov.device != mean.device:
            raise ValueError(
                f"cov: dtype/device {cov.dtype}/{cov.device} differ from mean's "
                f"{mean.dtype}/{mean.device}"
            )
        if mean.ndim < 1 or mean.shape[-1] < 1:
            raise ValueError(f"mean: expected shape (*B, n) with n >= 1, got {tuple(mean.shape)}")
        if (
            cov.ndim != mean.ndim + 1
            or cov.shape[-1] != cov.shape[-2]
            or cov.shape[:-2] != mean.shape[:-1]
            or not 1 <= cov.shape[-1] <= mean.shape[-1]
        ):
            raise ValueError(
                f"cov: expected shape (*B, d, d) with *B = {tuple(mean.shape[:-1])} and "
                f"1 <= d <= n = {mean.shape[-1]}, got {tuple(cov.shape)}"
            )
        for name, value in (("mean", mean), ("cov", cov)):
            if value.numel() and not all_finite(value.detach()):
                raise ValueError(f"{name}: contains NaN or inf")
        check_symmetric_psd("cov", cov)

    @property
    def batch_shape(self) -> torch.Size:
        """The batch dims ``*B``."""
        return self.mean.shape[:-1]

    @property
    def dim(self) -> int:
        """Size ``n`` of the mean (the ambient dimension for a manifold state)."""
        return int(self.mean.shape[-1])

    @property
    def tangent_dim(self) -> int:
        """Size ``d`` of the covariance (``n`` for a Euclidean state)."""
        return int(self.cov.shape[-1])

    @property
    def dtype(self) -> torch.dtype:
        """Floating-point dtype of mean and covariance."""
        return self.mean.dtype

    @property
    def device(self) -> torch.device:
        """Device of mean and covariance."""
        return self.mean.device

    def __getitem__(self, index: Any) -> Gaussian:
        """Index the batch dims: ``g[idx].mean == g.mean[idx]`` for any index over ``*B``."""
        batch = self.batch_shape
        flat = torch.arange(batch.numel(), device=self.device).reshape(batch)[index]
        n, d = self.dim, self.tangent_dim
        mean = self.mean.reshape(-1, n)[flat.reshape(-1)].reshape((*flat.shape, n))
        cov = self.cov.reshape(-1, d, d)[flat.reshape(-1)].reshape((*flat.shape, d, d))
        return unchecked_gaussian(mean, cov)

    def to(self, *args: Any, **kwargs: Any) -> Gaussian:
        """``Tensor.to`` applied to mean and covariance (dtype and/or device)."""
        return Gaussian(self.mean.to(*args, **kwargs), self.cov.to(*args, **kwargs))


def unchecked_gaussian(mean: Tensor, cov: Tensor) -> Gaussian:
    """Build a :class:`Gaussian` without validation, for filter internals on validated data."""
    g = object.__new__(Gaussian)
    object.__setattr__(g, "mean", mean)
    object.__setattr__(g, "cov", cov)
    return g


def check_gaussian(g: object, name: str, *, euclidean: bool) -> Gaussian:
    """Return ``g`` if it is a :class:`Gaussian` (with ``d == n`` if ``euclidean``), else raise."""
    if not isinstance(g, Gaussian):
        raise ValueError(f"{name}: expected a Gaussian, got {type(g).__name__}")
    if euclidean and g.tangent_dim != g.dim:
        raise ValueError(
            f"{name}: a Euclidean state needs cov (*B, n, n) matching mean (*B, n); got mean "
            f"{tuple(g.mean.shape)} and cov {tuple(g.cov.shape)} (use the EKF with a manifold)"
        )
    return g
