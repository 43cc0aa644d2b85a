"""The belief of the Rao-Blackwellized particle filter and the protocol of its models."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import torch
from torch import Tensor

from torchcontact.filters._gaussian import Gaussian
from torchcontact.filters._manifold import EUCLIDEAN, Euclidean, Manifold
from torchcontact.filters._switching import ModeDynamics

#: Gauss–Newton steps of :meth:`RBPFBelief.mean` on a manifold (enough for particles spread
#: over a few degrees: each step shrinks the error by orders of magnitude).
KARCHER_STEPS = 3


@runtime_checkable
class SwitchingModel(Protocol):
    """What the :class:`~torchcontact.filters.RBPF` needs of a model: ``K`` modes, a mode
    transition, and per-mode linear-Gaussian dynamics for each step.

    :class:`~torchcontact.filters.LinearSwitchingModel` (constant dynamics) and
    :class:`~torchcontact.filters.PlanarContactModel` (contact dynamics linearized at the
    belief's mean) implement it.
    """

    @property
    def num_modes(self) -> int:
        """``K``."""
        ...

    @property
    def state_dim(self) -> int:
        """``n``."""
        ...

    @property
    def obs_dim(self) -> int:
        """``m``."""
        ...

    @property
    def num_actions(self) -> int | None:
        """``A`` for an action-dependent ``(A, K, K)`` transition, else None."""
        ...

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the filter."""
        ...

    @property
    def device(self) -> torch.device:
        """Device of the filter."""
        ...

    @property
    def transition(self) -> Tensor:
        """``(K, K)`` or ``(A, K, K)`` row-stochastic mode transition (row = from)."""
        ...

    @property
    def initial(self) -> Tensor:
        """``(K,)`` distribution of the first mode."""
        ...

    def mode_dynamics(self, belief: RBPFBelief, control: Any) -> ModeDynamics:
        """Per-mode dynamics of the step that starts from ``belief`` under ``control``."""
        ...


@dataclass(frozen=True, eq=False)
class RBPFBelief:
    r"""The belief of an :class:`~torchcontact.filters.RBPF`: ``N`` weighted particles per batch
    entry, each a mode with a Gaussian over the continuous state,
    :math:`p(m_t, x_t \mid y_{1:t}) \approx \sum_i w_i\, \delta_{m^i_t}(m_t)\,
    N(x_t; \mu_i, P_i)`.

    Attributes:
        modes: ``(*B, N)`` long, the current mode :math:`m^i_t` of each particle.
        log_weights: ``(*B, N)`` normalized log-weights (``logsumexp == 0``; ``-inf`` = weight
            zero).
        gaussians: the per-particle Kalman beliefs, a :class:`Gaussian` with batch ``(*B, N)``.
        log_evidence: ``(*B,)`` running :math:`\log \hat p(y_{1:t})` (an unbiased estimate of
            :math:`p(y_{1:t})` in linear space); ``-inf`` once a step had zero likelihood.
        history: ``(*B, N, L + 1)`` long, the particle's mode path, newest first:
            ``history[..., l]`` is :math:`m^i_{t-l}` (``history[..., 0] == modes``); ``-1``
            before the first step (or a reset). Resampled with the particles.
        degenerate: ``(*B,)`` bool, ``True`` where the last step gave every particle weight
            zero and the entry was reset to the prior.
        prior: the prior of :meth:`~torchcontact.filters.RBPF.init` (batch ``*B``), the reset
            target.
        num_modes: ``K``.
        manifold: the state's manifold (the filter's): particle means are points of it and
            covariances live in its tangent at them.
    """

    modes: Tensor
    log_weights: Tensor
    gaussians: Gaussian
    log_evidence: Tensor
    history: Tensor
    degenerate: Tensor
    prior: Gaussian
    num_modes: int
    manifold: Manifold = EUCLIDEAN

    @property
    def batch_shape(self) -> torch.Size:
        """The batch dims ``*B``."""
        return self.modes.shape[:-1]

    @property
    def num_particles(self) -> int:
        """``N``."""
        return int(self.modes.shape[-1])

    @property
    def max_lag(self) -> int:
        """``L``, the longest lag of :meth:`fixed_lag_marginals`."""
        return int(self.history.shape[-1]) - 1

    def fixed_lag_marginals(self, lag: int) -> Tensor:
        r"""Fixed-lag smoothed mode marginals :math:`p(m_{t-\mathrm{lag}} = k \mid y_{1:t})`.

        Args:
            lag: ``0 <= lag <= L``.

        Returns:
            ``(*B, K)``; rows sum to 1, or less when ``lag`` reaches before the first step.
        """
        if not isinstance(lag, int) or not 0 <= lag <= self.max_lag:
            raise ValueError(f"lag: expected an int in [0, {self.max_lag}], got {lag!r}")
        modes = self.history[..., lag]
        weights = torch.exp(self.log_weights) * (modes >= 0)
        out = weights.new_zeros((*self.batch_shape, self.num_modes))
        return out.scatter_add(-1, modes.clamp(min=0), weights)

    def mode_marginals(self) -> Tensor:
        r"""Filtered mode marginals :math:`p(m_t = k \mid y_{1:t})`, ``(*B, K)``."""
        return self.fixed_lag_marginals(0)

    def mean(self) -> Tensor:
        r"""Mixture mean :math:`\sum_i w_i \mu_i`, ``(*B, n)``.

        On a manifold, the weighted Karcher mean: from the heaviest particle's mean
        :math:`\bar\mu`, ``KARCHER_STEPS`` Gauss–Newton steps
        :math:`\bar\mu \leftarrow \mathrm{retract}(\bar\mu, \sum_i w_i\,
        \mathrm{local}(\bar\mu, \mu_i))` (for unit quaternions: sign-invariant, normalized).
        """
        w = torch.exp(self.log_weights).unsqueeze(-1)
        if isinstance(self.manifold, Euclidean):
            return (w * self.gaussians.mean).sum(-2)
        means = self.gaussians.mean
        heaviest = self.log_weights.argmax(-1)[..., None, None].expand(
            *self.batch_shape, 1, means.shape[-1]
        )
        centre = means.gather(-2, heaviest).squeeze(-2)
        for _ in range(KARCHER_STEPS):
            step = (w * self.manifold.local(centre.unsqueeze(-2).expand_as(means), means)).sum(-2)
            centre = self.manifold.retract(centre, step)
        return centre

    def cov(self) -> Tensor:
        r"""Moment-matched mixture covariance
        :math:`\sum_i w_i (P_i + (\mu_i - \bar\mu)(\mu_i - \bar\mu)^\top)`, ``(*B, d, d)``
        (on a manifold with :math:`\mathrm{local}(\bar\mu, \mu_i)` for the deviations, in
        the tangent at the mean)."""
        w = torch.exp(self.log_weights)[..., None, None]
        means = self.gaussians.mean
        if isinstance(self.manifold, Euclidean):
            dev = means - self.mean().unsqueeze(-2)
        else:
            dev = self.manifold.local(self.mean().unsqueeze(-2).expand_as(means), means)
        spread = dev.unsqueeze(-1) * dev.unsqueeze(-2)
        return (w * (self.gaussians.cov + spread)).sum(-3)

    def ess(self) -> Tensor:
        r"""Effective sample size :math:`1 / \sum_i w_i^2`, ``(*B,)``."""
        return torch.exp(-torch.logsumexp(2.0 * self.log_weights, -1))
