"""Rao-Blackwellized particle filter over the modes of a linear switching model."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import KW_ONLY, dataclass
from typing import Any, Literal, Protocol, get_args, runtime_checkable

import torch
from torch import Tensor

from torchcontact._checks import broadcast_batch, check_mask, check_tensor, describe
from torchcontact.filters import _linalg as la
from torchcontact.filters._compiled import kernel
from torchcontact.filters._gaussian import Gaussian, check_gaussian, unchecked_gaussian
from torchcontact.filters._kalman import (
    observed_components,
    predict_core,
    update_core,
    update_log_likelihood,
)
from torchcontact.filters._resampling import (
    RESAMPLING_METHODS,
    ResamplingMethod,
    normalized_cdf,
    optimal_resample_core,
    resample_indices,
    search_cdf,
)
from torchcontact.filters._switching import ModeDynamics

Proposal = Literal["bootstrap", "all_modes"]
PROPOSALS: tuple[str, ...] = get_args(Proposal)
#: Fields of :class:`ModeDynamics` that the particles need no copy of when all modes share them.
_SHAREABLE = ("Q", "H", "d", "R")
_INVALID_WEIGHTS = "belief: a Kalman update produced NaN (a particle covariance is not PSD)"


@runtime_checkable
class SwitchingModel(Protocol):
    """What the :class:`RBPF` needs of a model: ``K`` modes, a mode transition, and per-mode
    linear-Gaussian dynamics for each step.

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
    r"""The belief of an :class:`RBPF`: ``N`` weighted particles per batch entry, each a mode
    with a Gaussian over the continuous state,
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
        prior: the prior of :meth:`RBPF.init` (batch ``*B``), the reset target.
        num_modes: ``K``.
    """

    modes: Tensor
    log_weights: Tensor
    gaussians: Gaussian
    log_evidence: Tensor
    history: Tensor
    degenerate: Tensor
    prior: Gaussian
    num_modes: int

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
        r"""Mixture mean :math:`\sum_i w_i \mu_i`, ``(*B, n)``."""
        w = torch.exp(self.log_weights).unsqueeze(-1)
        return (w * self.gaussians.mean).sum(-2)

    def cov(self) -> Tensor:
        r"""Moment-matched mixture covariance
        :math:`\sum_i w_i (P_i + (\mu_i - \bar\mu)(\mu_i - \bar\mu)^\top)`, ``(*B, n, n)``."""
        w = torch.exp(self.log_weights)[..., None, None]
        dev = self.gaussians.mean - self.mean().unsqueeze(-2)
        spread = dev.unsqueeze(-1) * dev.unsqueeze(-2)
        return (w * (self.gaussians.cov + spread)).sum(-3)

    def ess(self) -> Tensor:
        r"""Effective sample size :math:`1 / \sum_i w_i^2`, ``(*B,)``."""
        return torch.exp(-torch.logsumexp(2.0 * self.log_weights, -1))


@dataclass(frozen=True, eq=False)
class RBPF:
    r"""Rao-Blackwellized particle filter for a switching model (:class:`SwitchingModel`: a
    :class:`LinearSwitchingModel`, or a nonlinear model linearized at every step such as
    :class:`~torchcontact.filters.PlanarContactModel`).

    Each particle samples the discrete mode path and carries the exact Kalman belief of the
    continuous state given that path (Doucet, de Freitas, Murphy and Russell 2000), so only
    the mode is sampled:

    .. math::

        w^i_t \propto w^i_{t-1}\,
            \frac{p(m^i_t \mid m^i_{t-1})}{q(m^i_t \mid m^i_{t-1}, y_t)}\,
            p(y_t \mid m^i_t, y_{1:t-1}, m^i_{1:t-1})\, e^{\ell_t(m^i_t)}

    where the predictive likelihood :math:`p(y_t \mid \cdot) = N(y_t; H \mu^- + d, H P^- H^\top
    + R)` comes from the particle's Kalman update and :math:`\ell_t` is an optional per-mode
    log-likelihood term (e.g. tactile evidence). The evidence increment is
    :math:`\hat p(y_t \mid y_{1:t-1}) = \sum_i w^i_{t-1} \cdot (\text{incremental weight})`,
    so :math:`\hat p(y_{1:t})` is unbiased.

    Proposals:

    * ``"bootstrap"``: :math:`q = p(m_t \mid m_{t-1})` (sample the next mode from the
      transition, weight by the predictive likelihood), then resample with ``resampling``
      when the ESS falls below ``ess_threshold · N``.
    * ``"all_modes"``: every particle expands into all ``K`` children, weighted by
      transition × predictive likelihood, and the ``N · K`` children are reduced back to ``N``
      with Fearnhead–Clifford optimal resampling (2003; see
      :func:`~torchcontact.filters.optimal_resample`): every child of weight above the
      threshold :math:`1/c` is kept deterministically with its weight, each other child is
      drawn with probability :math:`c\,w`, at most once (systematic sampling over a random
      permutation of those children, never over the particle-major layout, where equal
      weights would hand every survivor the same mode). Every mode is evaluated at every
      step, so low-prior modes survive whenever their weight is competitive: this is the
      proposal of choice when rare modes (contact onset) matter. With at most ``N``
      children of positive weight nothing is sampled and the filter is exact.
      ``resampling`` and ``ess_threshold`` are not used. The children's weights need their
      predictive likelihoods only (of a measurement that reads part of the state, only that
      part of their prediction): the full Kalman update runs on the ``N`` survivors.

    Initialization: :meth:`init` represents :math:`p(m_0)` exactly. ``bootstrap`` spreads
    the ``N >= K`` particles evenly over the modes (particle ``i`` has mode ``i mod K`` and
    weight ``initial[k] / count_k``), so no mode with positive prior starts without
    particles; ``all_modes`` gives particle ``k < K`` the mode ``k`` with weight
    ``initial[k]`` and the other particles weight zero (they are replaced at the first step).

    Degeneracy: if every particle of a batch entry gets weight zero (e.g. the extra
    log-likelihood rules out every reachable mode), that entry is reset to the prior of
    :meth:`init`, flagged in :attr:`RBPFBelief.degenerate`, and its ``log_evidence`` becomes
    ``-inf`` (the model gives the data probability zero). No NaN is produced.

    Differentiability: ``log_evidence``, the weights and the Gaussians are differentiable
    w.r.t. every model tensor (``F, c, Q, H, d, R``, and ``transition`` with ``all_modes``;
    the bootstrap proposal samples from the transition, so its weights do not depend on it)
    and w.r.t. ``y``. Resampling is a stop-gradient: gradients flow through the Kalman
    log-likelihoods and the weights but not through the (discrete) resampling indices, and
    bootstrap resampling resets the weights to the constant ``1/N``. This is the usual
    biased but low-variance estimator of :math:`\nabla \log p(y_{1:T})` (e.g. Naesseth,
    Linderman, Ranganath and Blei, "Variational sequential Monte Carlo", AISTATS 2018). A step
    none of whose inputs needs a gradient records nothing for autograd (it runs in inference
    mode) and returns ordinary tensors, with the same values.

    Time-varying models: every step asks the model for its per-mode dynamics
    (:meth:`SwitchingModel.mode_dynamics`, given the belief and the step's ``control``), so a
    nonlinear model is linearized once per mode and batch entry at the belief's mean (an
    extended Kalman filter per particle that shares the linearization point; exact for a
    linear model). A ``Q``, ``H``, ``d`` or ``R`` that every mode shares, given as a
    ``(K, ...)`` view of one matrix (``expand``), is not copied to the particles.

    Args:
        model: the switching model.
        num_particles: ``N >= K``.
        proposal: ``"bootstrap"`` or ``"all_modes"``.
        resampling: scheme of the bootstrap's ESS-triggered resampling (see
            :func:`~torchcontact.filters.resample`).
        ess_threshold: resample when ``ESS < ess_threshold · N`` (``0``: never; ``1``:
            whenever the weights are not uniform).
        max_lag: ``L``, the longest lag of :meth:`RBPFBelief.fixed_lag_marginals`.
        compiled: run the particles' Kalman kernels through :func:`torch.compile` (see
            ``torchcontact.filters._compiled``: the first steps compile, tens of seconds;
            then a step at ``N = 1,000`` takes about half the eager time, with a
            :class:`~torchcontact.filters.PlanarContactModel` that is compiled too; the results
            agree to rounding, not to the bit).

    References:
        A. Doucet, N. de Freitas, K. Murphy and S. Russell, "Rao-Blackwellised particle
        filtering for dynamic Bayesian networks", UAI 2000.
        P. Fearnhead and P. Clifford, "On-line inference for hidden Markov models via particle
        filters", J. R. Statist. Soc. B 65(4), 2003.
    """

    model: SwitchingModel
    num_particles: int
    _: KW_ONLY
    proposal: Proposal = "bootstrap"
    resampling: ResamplingMethod = "systematic"
    ess_threshold: float = 0.5
    max_lag: int = 2
    compiled: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.model, SwitchingModel):
            raise ValueError(
                f"model: expected a switching model (e.g. LinearSwitchingModel), got "
                f"{type(self.model).__name__}"
            )
        K = self.model.num_modes
        if not isinstance(self.num_particles, int) or self.num_particles < K:
            raise ValueError(
                f"num_particles: expected an int >= K = {K}, got {self.num_particles!r}"
            )
        if self.proposal not in PROPOSALS:
            raise ValueError(f"proposal: expected one of {PROPOSALS}, got {self.proposal!r}")
        if self.resampling not in RESAMPLING_METHODS:
            raise ValueError(
                f"resampling: expected one of {RESAMPLING_METHODS}, got {self.resampling!r}"
            )
        threshold = self.ess_threshold
        if not isinstance(threshold, int | float) or not 0.0 <= threshold <= 1.0:
            raise ValueError(
                f"ess_threshold: expected a number in [0, 1], got {self.ess_threshold}"
            )
        if not isinstance(self.max_lag, int) or self.max_lag < 0:
            raise ValueError(f"max_lag: expected an int >= 0, got {self.max_lag!r}")
        if not isinstance(self.compiled, bool):
            raise ValueError(f"compiled: expected a bool, got {self.compiled!r}")

    # ------------------------------------------------------------------------------------------
    # initialization

    def _initial_particles(self, batch: torch.Size) -> tuple[Tensor, Tensor, Tensor]:
        """Modes ``(*B, N)``, normalized log-weights ``(*B, N)`` and history ``(*B, N, L+1)``
        representing ``p(m_0) = initial`` exactly."""
        K, N = self.model.num_modes, self.num_particles
        device = self.model.device
        modes = torch.arange(N, device=device) % K
        log_prior = torch.log(self.model.initial)[modes]
        if self.proposal == "bootstrap":
            counts = torch.bincount(modes, minlength=K).to(self.model.dtype)
            log_w = log_prior - torch.log(counts)[modes]
        else:
            log_w = torch.where(torch.arange(N, device=device) < K, log_prior, -math.inf)
        log_w = log_w - torch.logsumexp(log_w, -1)
        history = torch.full((N, self.max_lag + 1), -1, dtype=torch.long, device=device)
        history[:, 0] = modes
        return (
            modes.expand(*batch, N),
            log_w.expand(*batch, N),
            history.expand(*batch, N, self.max_lag + 1),
        )

    def init(self, prior: Gaussian, batch_shape: Sequence[int] = ()) -> RBPFBelief:
        """The belief before the first step: ``m_0 ~ initial``, ``x_0 ~ prior``.

        Args:
            prior: ``(*B', n)`` Gaussian over ``x_0`` (Euclidean), dtype of the model.
            batch_shape: extra batch shape; the belief's batch ``*B`` is the broadcast of
                ``prior.batch_shape`` and ``batch_shape`` (e.g. independent replicas).

        Returns:
            The initial :class:`RBPFBelief` (``log_evidence == 0``).
        """
        prior = check_gaussian(prior, "prior", euclidean=True)
        model = self.model
        if prior.dim != model.state_dim or prior.dtype != model.dtype:
            raise ValueError(
                f"prior: expected n = {model.state_dim} and dtype {model.dtype}, got "
                f"n = {prior.dim} and {prior.dtype}"
            )
        try:
            batch = torch.broadcast_shapes(prior.batch_shape, tuple(batch_shape))
        except (RuntimeError, TypeError) as err:
            raise ValueError(
                f"batch_shape: {batch_shape!r} does not broadcast with the prior's batch "
                f"{tuple(prior.batch_shape)}"
            ) from err
        n, nb = model.state_dim, len(batch)
        prior = unchecked_gaussian(prior.mean.expand(*batch, n), prior.cov.expand(*batch, n, n))
        modes, log_w, history = self._initial_particles(batch)
        mean, cov = self._prior_particles(prior, nb)
        return RBPFBelief(
            modes=modes,
            log_weights=log_w,
            gaussians=unchecked_gaussian(la.to_batch_first(mean, 1), la.to_batch_first(cov, 2)),
            log_evidence=torch.zeros(batch, dtype=model.dtype, device=model.device),
            history=history,
            degenerate=torch.zeros(batch, dtype=torch.bool, device=model.device),
            prior=prior,
            num_modes=model.num_modes,
        )

    def _prior_particles(self, prior: Gaussian, nb: int) -> tuple[Tensor, Tensor]:
        """The prior copied to every particle, batch-last: ``(n, *B, N)``, ``(n, n, *B, N)``."""
        N = self.num_particles
        mean = la.to_batch_last(prior.mean.unsqueeze(-2), 1, nb + 1)
        cov = la.to_batch_last(prior.cov.unsqueeze(-3), 2, nb + 1)
        return (
            mean.expand(*mean.shape[:-1], N).contiguous(),
            cov.expand(*cov.shape[:-1], N).contiguous(),
        )

    # ------------------------------------------------------------------------------------------
    # one step

    def step(
        self,
        belief: RBPFBelief,
        y: Tensor,
        *,
        action: Tensor | int | None = None,
        extra_log_likelihood: Tensor | None = None,
        control: Any = None,
        mask: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> RBPFBelief:
        """Advance the belief by one step: propose modes, Kalman predict/update, reweight,
        resample.

        Args:
            belief: the belief at ``t - 1`` (from :meth:`init` or :meth:`step`).
            y: ``(*B', m)`` measurement at ``t``, broadcast to the batch ``*B``. NaN in every
                component means "no measurement" (likelihood 1 for every particle).
            action: the action that selects the transition matrix of an action-dependent model:
                an int or a ``(*B',)`` long tensor in ``[0, A)``; must be None for a ``(K, K)``
                transition.
            extra_log_likelihood: ``(*B', K)`` per-mode log-likelihood added to each particle's
                log-weight by its new mode (``-inf`` rules a mode out; NaN and ``+inf`` are
                errors).
            control: the model's control input of this step (e.g. the finger poses and
                twists of a :class:`~torchcontact.filters.PlanarContactModel`); None for a
                :class:`LinearSwitchingModel`.
            mask: ``(*B', m)`` bool, the measurement components used (see ``kf_update``).
            generator: random source, for reproducible runs; torch's default if None.

        Returns:
            The belief at ``t``.
        """
        model = self.model
        K, m = model.num_modes, model.obs_dim
        belief = self._check_belief(belief)
        batch = belief.batch_shape
        like = model.initial
        if not isinstance(y, Tensor) or y.ndim < 1:
            raise ValueError(f"y: expected a (*B, {m}) tensor, got {getattr(y, 'shape', y)!r}")
        y = check_tensor("y", y, event_shape=(m,), like=like, allow_nan=True)
        shapes: list[tuple[str, Sequence[int]]] = [("belief", batch), ("y", y.shape[:-1])]
        if mask is not None:
            mask = check_mask("mask", mask, size=m)
            shapes.append(("mask", mask.shape[:-1]))
        extra = None
        if extra_log_likelihood is not None:
            extra = check_tensor(
                "extra_log_likelihood",
                extra_log_likelihood,
                event_shape=(K,),
                like=like,
                allow_neginf=True,
            )
            shapes.append(("extra_log_likelihood", extra.shape[:-1]))
        transition = self._transition(action, shapes)
        if broadcast_batch(shapes) != batch:
            raise ValueError(
                f"y: inputs must broadcast to the belief's batch {tuple(batch)}, got "
                + ", ".join(f"{name} {tuple(s)}" for name, s in shapes[1:])
            )
        observed = observed_components(y, mask)
        dynamics = self.model.mode_dynamics(belief, control)
        if not isinstance(dynamics, ModeDynamics):
            raise ValueError(
                f"model: mode_dynamics returned {type(dynamics).__name__}, not ModeDynamics"
            )
        packed, shared, mode_log_weight = self._packed_dynamics(belief, dynamics)
        rows = self._transition_rows(belief, transition, dynamics.transition_rows)
        # Without gradients to carry, the step runs without autograd's bookkeeping. (Not in
        # inference mode: its tensors would reach the next step's compiled kernels as
        # variants of their inputs that compile anew, up to torch's recompile limit.)
        g, prior = belief.gaussians, belief.prior
        inputs = (packed, *shared.values(), mode_log_weight, y, rows, extra, belief.log_weights)
        inputs += (g.mean, g.cov, belief.log_evidence, prior.mean, prior.cov)
        tracked = torch.is_grad_enabled() and any(
            value is not None and value.requires_grad for value in inputs
        )
        with torch.set_grad_enabled(tracked):
            step = self._step_bootstrap if self.proposal == "bootstrap" else self._step_all_modes
            new = step(belief, packed, shared, mode_log_weight, y, observed, rows, extra, generator)
        return new

    def _transition_rows(
        self, belief: RBPFBelief, transition: Tensor, rows: Tensor | None
    ) -> Tensor:
        """``(*B, N, K)`` transition probabilities of every particle's next mode: the model's
        per-particle ``rows`` if given (checked), else the rows of ``transition`` (``(K, K)``
        or ``(*B', K, K)``) selected by the particles' modes."""
        model, N, K = self.model, self.num_particles, self.model.num_modes
        batch = belief.batch_shape
        if rows is None:
            # Modes out of [0, K) are flagged by the step (:func:`_belief_flags`); clamped here
            # so that the step reaches its one flag read.
            modes = belief.modes.clamp(0, K - 1)
            return transition.expand(*batch, K, K).gather(
                -2, modes.unsqueeze(-1).expand(*batch, N, K)
            )
        rows = check_tensor(
            "model: mode_dynamics().transition_rows", rows, event_shape=(N, K), like=model.initial
        )
        shapes = [("belief", batch), ("transition_rows", rows.shape[:-2])]
        if broadcast_batch(shapes) != batch:
            raise ValueError(
                f"model: mode_dynamics().transition_rows batch {tuple(rows.shape[:-2])} does "
                f"not broadcast to the belief's batch {tuple(batch)}"
            )
        tol = 1e3 * torch.finfo(rows.dtype).eps * K
        if bool((rows < 0).any()) or not bool(((rows.sum(-1) - 1).abs() <= tol).all()):
            raise ValueError(
                "model: mode_dynamics().transition_rows must be non-negative rows summing to 1"
            )
        return rows.expand(*batch, N, K)

    def _packed_dynamics(
        self, belief: RBPFBelief, dynamics: ModeDynamics
    ) -> tuple[Tensor, dict[str, Tensor], Tensor | None]:
        """The model's per-mode dynamics of this step, checked and packed.

        Returns:
            The fields that differ between modes packed into ``(*B', K, P)`` (``*B'`` empty or
            broadcastable to the belief's batch): ``F`` and ``c``, and each of ``Q, H, d, R``
            unless every mode shares it; the shared ones (a model's constant noise and
            measurement, given as ``(K, ...)`` views of one matrix) by name, without the mode
            dim (the particles need no copy of them); and the optional
            ``mode_log_weight (*B', K)``. Shapes and dtypes are checked here, values by the
            step (:func:`_dynamics_flags`).
        """
        model = self.model
        K, n, m = model.num_modes, model.state_dim, model.obs_dim
        events = {
            "F": (K, n, n),
            "c": (K, n),
            "Q": (K, n, n),
            "H": (K, m, n),
            "d": (K, m),
            "R": (K, m, m),
        }
        values: dict[str, Tensor] = {}
        shapes: list[tuple[str, Sequence[int]]] = [("belief", belief.batch_shape)]
        for name, event in events.items():
            value = getattr(dynamics, name)
            lead = value.ndim - len(event) if isinstance(value, Tensor) else -1
            if lead < 0 or tuple(value.shape[lead:]) != event or value.dtype != model.dtype:
                raise ValueError(
                    f"model: mode_dynamics().{name} must be a {model.dtype} tensor of shape "
                    f"(*B, {', '.join(map(str, event))}), got {describe(value)}"
                )
            values[name] = value
            shapes.append((f"mode_dynamics().{name}", value.shape[:lead]))
        if broadcast_batch(shapes) != belief.batch_shape:
            raise ValueError(
                f"model: mode_dynamics() batch shapes {[tuple(s) for _, s in shapes[1:]]} do "
                f"not broadcast to the belief's batch {tuple(belief.batch_shape)}"
            )
        batch = broadcast_batch(shapes[1:])
        shared = {
            name: values[name][0]
            for name in _SHAREABLE
            if values[name].ndim == len(events[name]) and values[name].stride(0) == 0
        }
        packed = torch.cat(
            [
                value.expand(*batch, *events[name]).reshape(*batch, K, -1)
                for name, value in values.items()
                if name not in shared
            ],
            dim=-1,
        )
        log_weight, field = dynamics.mode_log_weight, "model: mode_dynamics().mode_log_weight"
        if log_weight is not None:
            if not isinstance(log_weight, Tensor):
                raise ValueError(f"{field}: expected a torch.Tensor, got {describe(log_weight)}")
            if log_weight.dtype != model.dtype or log_weight.device != model.device:
                raise ValueError(
                    f"{field}: expected dtype {model.dtype} on {model.device}, got "
                    f"{log_weight.dtype} on {log_weight.device}"
                )
            if log_weight.ndim < 1 or log_weight.shape[-1] != K:
                raise ValueError(
                    f"{field}: expected shape (*B, {K}), got {tuple(log_weight.shape)}"
                )
            weight_batch = [
                ("belief", belief.batch_shape),
                ("mode_log_weight", log_weight.shape[:-1]),
            ]
            if broadcast_batch(weight_batch) != belief.batch_shape:
                raise ValueError(
                    f"{field} batch {tuple(log_weight.shape[:-1])} does not broadcast to the "
                    f"belief's batch {tuple(belief.batch_shape)}"
                )
        # Their values (finite; a log-weight may be -inf) are tested by the step's kernels,
        # whose flags are read with one host synchronization (:func:`_read_flags`).
        return packed, shared, log_weight

    def _measured(self, observed: Tensor | None) -> bool:
        """Whether a step's kernels run the Kalman update: a compiled step always does (no
        host synchronization to learn whether anything was measured; the update returns the
        prediction and likelihood 1 where nothing was), an eager one only if something was
        measured."""
        return self.compiled or observed is None or bool(observed.any())

    def _step_bootstrap(
        self,
        belief: RBPFBelief,
        packed: Tensor,
        shared: dict[str, Tensor],
        mode_log_weight: Tensor | None,
        y: Tensor,
        observed: Tensor | None,
        rows: Tensor,
        extra: Tensor | None,
        generator: torch.Generator | None,
    ) -> RBPFBelief:
        model, N = self.model, self.num_particles
        batch, nb = belief.batch_shape, len(belief.batch_shape)
        # Sample m_t ~ p(m_t | particle) by inverse CDF (no gradient through the draw).
        cdf = normalized_cdf(rows.detach())  # (*B, N, K)
        draw = torch.rand(
            (*batch, N, 1), dtype=torch.float64, device=model.device, generator=generator
        )
        modes = search_cdf(cdf, draw).squeeze(-1)
        y_bl, obs_bl = _measurement(y, observed, nb + 1)
        g = belief.gaussians
        core = kernel(_bootstrap_core, compiled=self.compiled)
        log_w, mean, cov, log_evidence, history, dead, resample, flags = core(
            modes,
            packed,
            _select(packed, modes),
            shared,
            mode_log_weight,
            la.to_batch_last(g.mean, 1, nb + 1),
            la.to_batch_last(g.cov, 2, nb + 1),
            y_bl,
            obs_bl,
            extra,
            belief.log_weights,
            belief.log_evidence,
            belief.history,
            belief.modes,
            n=model.state_dim,
            m=model.obs_dim,
            measured=self._measured(observed),
            entrywise=self.compiled,
            log_ess_bound=-math.log(max(self.ess_threshold * N, 1e-300)),
        )
        read = _read_flags(flags)
        any_dead, any_resample = read[_DEAD], read[_RESAMPLE]
        if any_resample:
            index = resample_indices(log_w, N, self.resampling, generator)
            identity = torch.arange(N, device=index.device)
            index = torch.where(resample.unsqueeze(-1), index, identity)
            modes, history, mean, cov = _gather(index, modes, history, mean, cov)
            log_w = torch.where(resample.unsqueeze(-1), -math.log(N), log_w)
        return self._belief(belief, modes, log_w, mean, cov, log_evidence, history, dead, any_dead)

    def _step_all_modes(
        self,
        belief: RBPFBelief,
        packed: Tensor,
        shared: dict[str, Tensor],
        mode_log_weight: Tensor | None,
        y: Tensor,
        observed: Tensor | None,
        rows: Tensor,
        extra: Tensor | None,
        generator: torch.Generator | None,
    ) -> RBPFBelief:
        N, K = self.num_particles, self.model.num_modes
        batch, nb = belief.batch_shape, len(belief.batch_shape)
        # The children (particle i, mode k), particle-major once flattened: their weights need
        # their predictive likelihoods only, not their posteriors.
        mean = la.to_batch_last(belief.gaussians.mean, 1, nb + 1)  # (n, *B, N)
        cov = la.to_batch_last(belief.gaussians.cov, 2, nb + 1)
        measured = self._measured(observed)
        log_lik = self._children_log_likelihood(
            mean, cov, packed, shared, y, observed, measured=measured
        )
        log_trans = torch.log(rows)  # (*B, N, K): log p(m_t = k | particle i)
        log_w = belief.log_weights.unsqueeze(-1) + log_trans + log_lik
        for weight in (extra, mode_log_weight):
            if weight is not None:
                log_w = log_w + weight.unsqueeze(-2)
        log_w, log_evidence, dead, invalid = _normalized(log_w.flatten(-2), belief.log_evidence)
        flags = _flags(
            invalid,
            dead,
            *_dynamics_flags(packed, shared, mode_log_weight),
            _belief_flags(belief.modes, belief.log_weights, belief.log_evidence, K),
        )
        any_dead = _read_flags(flags)[_DEAD]
        index, log_w = optimal_resample_core(log_w, N, generator)
        modes = index % K
        parents = torch.div(index, K, rounding_mode="floor")
        history = belief.history.gather(
            -2, parents.unsqueeze(-1).expand(*batch, N, self.max_lag + 1)
        )
        history = torch.cat([modes.unsqueeze(-1), history[..., :-1]], -1)
        # Only the N survivors need the Kalman update: the same operations on the same
        # numbers (in the same memory layouts) as a step of all N·K children does for them.
        mean, cov = _gather_states(parents, mean, cov)
        y_bl, obs_bl = _measurement(y, observed, nb + 1)
        kalman = kernel(_predict_update, compiled=self.compiled)
        mean, cov, _ = kalman(
            mean,
            cov,
            _select(packed, modes),
            shared,
            y_bl,
            obs_bl,
            n=self.model.state_dim,
            m=self.model.obs_dim,
            measured=measured,
            entrywise=self.compiled,
        )
        return self._belief(belief, modes, log_w, mean, cov, log_evidence, history, dead, any_dead)

    def _children_log_likelihood(
        self,
        mean: Tensor,
        cov: Tensor,
        packed: Tensor,
        shared: dict[str, Tensor],
        y: Tensor,
        observed: Tensor | None,
        *,
        measured: bool,
    ) -> Tensor:
        """``(*B, N, K)`` predictive log-likelihoods of every particle's ``K`` children.

        The log-likelihood of :func:`_predict_update` on every child without the posterior, from the
        leading ``r`` components of the predicted mean and covariance: those that ``H`` reads
        when every mode shares it (the pose of a
        :class:`~torchcontact.filters.PlanarContactModel`), else all. The operations are
        those of :func:`_predict_update` on the same numbers, so the values are the same (to the bit
        when ``H`` selects components; see :func:`update_log_likelihood` for the exception).

        Args:
            mean: ``(n, *B, N)``; cov: ``(n, n, *B, N)``: the particles, batch-last.
            packed: ``(K, D)`` or ``(*B', K, D)`` the modes' packed dynamics.
            shared: as in :func:`_predict_update`.
            y: ``(*B', m)`` measurement; observed: ``(*B', m)`` bool or None.
            measured: :meth:`_measured` of ``observed``; ``False``: likelihood 1.
        """
        model = self.model
        n, m, K = model.state_dim, model.obs_dim, model.num_modes
        if not measured:
            return mean.new_zeros(*mean.shape[1:], K)  # no measurement: likelihood 1
        nb, lead = mean.ndim - 2, packed.ndim - 2
        r = n
        if "H" in shared:
            read = shared["H"].detach().ne(0).any(0).nonzero()
            r = int(read.max()) + 1 if read.numel() else 1
        # The children span the trailing dims (K, N): the particles' numbers vary along the
        # innermost N, the modes' dynamics are constant there (vectorized kernels), and
        # neither is copied K or N times.
        params = packed.movedim(-1, 0).reshape(
            packed.shape[-1], *(1,) * (nb - lead), *packed.shape[:-2], K, 1
        )  # (D, *B', K, 1)
        F, c, Q, H, d, R = _unpack(params, shared, n, m)
        # F x + c as a step of all children computes it, whose sums over x round as they do in
        # its layouts: per-batch dynamics are gathered with the fields last (each row's
        # products F_ij x_j summed over the innermost j), shared ones are contiguous.
        if lead:
            F_bf = packed[..., : r * n].unflatten(-1, (r, n)).unsqueeze(-3)  # (*B', K, 1, r, n)
            x_bf = la.to_batch_first(mean, 1).contiguous()[..., None, :, None, :]  # (*B,1,N,1,n)
            predicted = (F_bf * x_bf).sum(-1).movedim(-1, 0) + c[:r]  # (r, *B, K, N)
        else:
            predicted = la.mv(F[:r].contiguous(), mean.unsqueeze(-2)) + c[:r]
        size = n * n * n * math.prod(predicted.shape[1:])
        y_bl, obs_bl = _measurement(y, observed, predicted.ndim - 1)
        likelihood = kernel(_predicted_log_likelihood, compiled=self.compiled)
        log_lik = likelihood(
            predicted,
            F[:r],
            cov.unsqueeze(-2),
            Q[:r, :r],
            y_bl,
            H,
            d,
            R,
            obs_bl,
            size=size,
            entrywise=self.compiled,
        )
        return log_lik.transpose(-1, -2)  # (*B, N, K)

    def _belief(
        self,
        previous: RBPFBelief,
        modes: Tensor,
        log_w: Tensor,
        mean: Tensor,
        cov: Tensor,
        log_evidence: Tensor,
        history: Tensor,
        dead: Tensor,
        any_dead: bool,
    ) -> RBPFBelief:
        """Assemble the new belief, resetting the entries flagged ``dead`` to the prior."""
        if any_dead:
            batch = previous.batch_shape
            modes0, log_w0, history0 = self._initial_particles(batch)
            mean0, cov0 = self._prior_particles(previous.prior, len(batch))
            keep = ~dead
            modes = torch.where(keep.unsqueeze(-1), modes, modes0)
            log_w = torch.where(keep.unsqueeze(-1), log_w, log_w0)
            history = torch.where(keep[..., None, None], history, history0)
            mean = torch.where(keep.unsqueeze(-1), mean, mean0)
            cov = torch.where(keep.unsqueeze(-1), cov, cov0)
        return RBPFBelief(
            modes=modes,
            log_weights=log_w,
            gaussians=unchecked_gaussian(la.to_batch_first(mean, 1), la.to_batch_first(cov, 2)),
            log_evidence=log_evidence,
            history=history,
            degenerate=dead,
            prior=previous.prior,
            num_modes=self.model.num_modes,
        )

    def _check_belief(self, belief: object) -> RBPFBelief:
        model = self.model
        if not isinstance(belief, RBPFBelief):
            raise ValueError(f"belief: expected an RBPFBelief, got {type(belief).__name__}")
        g = belief.gaussians
        if not isinstance(belief.modes, Tensor) or belief.modes.dtype != torch.long:
            raise ValueError(f"belief: modes must be a long tensor, got {describe(belief.modes)}")
        if (
            belief.num_modes != model.num_modes
            or belief.num_particles != self.num_particles
            or belief.max_lag != self.max_lag
            or g.dim != model.state_dim
            or g.dtype != model.dtype
        ):
            raise ValueError(
                f"belief: does not match this filter (K = {model.num_modes}, "
                f"N = {self.num_particles}, L = {self.max_lag}, n = {model.state_dim}, "
                f"{model.dtype}); build it with RBPF.init"
            )
        return belief

    def _transition(
        self, action: Tensor | int | None, shapes: list[tuple[str, Sequence[int]]]
    ) -> Tensor:
        """The transition matrix for ``action``: ``(K, K)`` or ``(*B', K, K)``."""
        model = self.model
        actions = model.num_actions
        if actions is None:
            if action is not None:
                raise ValueError(
                    "action: this model's transition is not action-dependent; pass None"
                )
            return model.transition
        if action is None:
            raise ValueError(
                f"action: required for an action-dependent transition ({actions} actions)"
            )
        if isinstance(action, int) and not isinstance(action, bool):
            action = torch.tensor(action, device=model.device)
        if not isinstance(action, Tensor) or action.dtype != torch.long:
            raise ValueError(f"action: expected an int or a long tensor, got {action!r}")
        if bool(((action < 0) | (action >= actions)).any()):
            raise ValueError(f"action: values must lie in [0, {actions})")
        shapes.append(("action", action.shape))
        return model.transition[action]


def _unpack(params: Tensor, shared: dict[str, Tensor], n: int, m: int) -> list[Tensor]:
    """Batch-last ``F, c, Q, H, d, R`` views: the packed ones split from ``(D, *P)`` params,
    the shared ones with ``len(P)`` batch dims of size 1."""
    batch = params.shape[1:]
    shapes = {"F": (n, n), "c": (n,), "Q": (n, n), "H": (m, n), "d": (m,), "R": (m, m)}
    names = [name for name in shapes if name not in shared]
    parts = torch.split(params, [math.prod(shapes[name]) for name in names])
    fields = {
        name: part.reshape(*shapes[name], *batch) for name, part in zip(names, parts, strict=True)
    }
    ones = (1,) * len(batch)
    fields.update({name: value.reshape(*value.shape, *ones) for name, value in shared.items()})
    return [fields[name] for name in shapes]


def _predict_update(
    mean: Tensor,
    cov: Tensor,
    params: Tensor,
    shared: dict[str, Tensor],
    y: Tensor,
    observed: Tensor | None,
    *,
    n: int,
    m: int,
    measured: bool = True,
    entrywise: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """Kalman predict + update of batch-last particles under per-particle model parameters.

    Args:
        mean: ``(n, *P)``; cov: ``(n, n, *P)`` (``*P`` = the particle batch dims).
        params: ``(D, *P')`` packed per-mode fields (see :meth:`RBPF._packed_dynamics`).
        shared: the fields every mode shares, without batch dims.
        y, observed: the measurement and its used components, batch-last
            (:func:`_measurement`).
        n, m: state and measurement sizes.
        measured: ``False`` predicts only (likelihood 1: nothing was measured).
        entrywise: factor the predicted covariances per particle: no host synchronization,
            so the compiled form is one kernel (see :func:`update_core`).

    Returns:
        ``(mean⁺ (n, *P), cov⁺ (n, n, *P), log_likelihood (*P))``.
    """
    F, c, Q, H, d, R = _unpack(params, shared, n, m)
    if not measured:
        mean, cov = predict_core(mean, cov, F, c, Q)
        return mean, cov, mean.new_zeros(mean.shape[1:])
    # update_core reads the lower triangle only, except that entries without a measurement
    # keep the predicted covariance as it is: symmetrize only then.
    mean, cov = predict_core(mean, cov, F, c, Q, symmetric=observed is not None)
    return update_core(mean, cov, y, H, d, R, observed, entrywise=entrywise)


def _bootstrap_core(
    modes: Tensor,
    packed: Tensor,
    params: Tensor,
    shared: dict[str, Tensor],
    mode_log_weight: Tensor | None,
    mean: Tensor,
    cov: Tensor,
    y: Tensor,
    observed: Tensor | None,
    extra: Tensor | None,
    log_weights: Tensor,
    log_evidence: Tensor,
    history: Tensor,
    previous_modes: Tensor,
    *,
    n: int,
    m: int,
    measured: bool,
    entrywise: bool,
    log_ess_bound: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """A bootstrap step from the sampled modes up to resampling, without host
    synchronization (compiled: one kernel).

    Args:
        modes: ``(*B, N)`` the particles' new modes; packed: ``(*B', K, D)`` every mode's
            packed dynamics (tested for finite values only); params: ``(D, *B, N)`` the
            particles' (:func:`_select`, given rather than gathered here: the compiled loops
            vectorize over contiguous parameters, not over indirect loads); shared: the
            fields every mode shares; mode_log_weight: ``(*B', K)`` or None, the model's.
        mean: ``(n, *B, N)``; cov: ``(n, n, *B, N)``: the particles, batch-last.
        y, observed: batch-last (:func:`_measurement`); extra: ``(*B', K)`` or None.
        log_weights: ``(*B, N)``; log_evidence: ``(*B,)``; history: ``(*B, N, L + 1)``;
            previous_modes: ``(*B, N)``: the given belief's (tested by :func:`_belief_flags`).
        n, m, measured, entrywise: as in :func:`_predict_update`.
        log_ess_bound: resample where ``log Σ w² >`` this (``-log(threshold · N)``).

    Returns:
        The normalized log-weights, batch-last mean and covariance, evidence and history,
        ``dead (*B)`` (every weight zero: placeholders, see :func:`_normalized`), ``resample
        (*B)`` (ESS below the threshold, not dead) and the :func:`_flags`.
    """
    mean, cov, log_lik = _predict_update(
        mean,
        cov,
        params,
        shared,
        y,
        observed,
        n=n,
        m=m,
        measured=measured,
        entrywise=entrywise,
    )
    belief_flags = _belief_flags(previous_modes, log_weights, log_evidence, packed.shape[-2])
    log_w = log_weights + log_lik
    for weight in (extra, mode_log_weight):
        if weight is not None:
            log_w = log_w + weight.expand(*log_w.shape[:-1], weight.shape[-1]).gather(-1, modes)
    log_w, log_evidence, dead, invalid = _normalized(log_w, log_evidence)
    history = torch.cat([modes.unsqueeze(-1), history[..., :-1]], -1)
    # ESS = 1 / Σ w² < threshold · N, in log space
    resample = (torch.logsumexp(2.0 * log_w, -1) > log_ess_bound) & ~dead
    flags = _flags(
        invalid,
        dead,
        *_dynamics_flags(packed, shared, mode_log_weight),
        belief_flags,
        resample,
    )
    return log_w, mean, cov, log_evidence, history, dead, resample, flags


def _select(packed: Tensor, modes: Tensor) -> Tensor:
    """Batch-last ``(D, *B, N)`` packed dynamics of the particles' ``modes (*B, N)``, from
    ``packed (K, D)`` (one set for the whole batch: one index_select) or ``(*B', K, D)``."""
    batch, N = modes.shape[:-1], modes.shape[-1]
    if packed.ndim == 2:
        return packed.T.index_select(1, modes.reshape(-1)).reshape(packed.shape[-1], *batch, N)
    params = packed.expand(*batch, *packed.shape[-2:]).gather(
        -2, modes.unsqueeze(-1).expand(*batch, N, packed.shape[-1])
    )
    return params.movedim(-1, 0)


def _predicted_log_likelihood(
    predicted: Tensor,
    F: Tensor,
    cov: Tensor,
    Q: Tensor,
    y: Tensor,
    H: Tensor,
    d: Tensor | None,
    R: Tensor,
    observed: Tensor | None,
    *,
    size: int,
    entrywise: bool,
) -> Tensor:
    """The children's predictive log-likelihoods from the leading ``(r, r)`` block of
    :func:`~torchcontact.filters._kalman.predict_core`'s ``F P Fᵀ + Q``, computed by the same
    operations (products sized as the full step's, ``size``).

    Args:
        predicted: ``(r, *B)`` the leading components of the predicted means.
        F: ``(r, n, *B)`` the leading rows of the children's ``F``; cov: ``(n, n, *B)``;
            Q: ``(r, r, *B)``.
        y, H, d, R, observed: batch-last, as in :func:`update_log_likelihood`.
        entrywise: see :func:`update_core`.

    Returns:
        ``(*B)`` log-likelihoods.
    """
    block = la.add_(la.mm_t(la.mm(F, cov, size=size), F, size=size), Q)
    if observed is not None:  # as _predict_update symmetrizes
        block = la.symmetrize(block)
    return update_log_likelihood(predicted, block, y, H, d, R, observed, entrywise=entrywise)


def _measurement(
    y: Tensor, observed: Tensor | None, batch_ndim: int
) -> tuple[Tensor, Tensor | None]:
    """``y (*B', m)`` and ``observed`` batch-last with ``batch_ndim`` batch dims: the particle
    dims that they lack are added as 1s on the right."""
    m = y.shape[-1]
    extra_dims = batch_ndim - (y.ndim - 1)  # particle dims that y does not have
    y_bl = la.to_batch_last(y.reshape(*y.shape[:-1], *(1,) * extra_dims, m), 1, batch_ndim)
    if observed is None:
        return y_bl, None
    observed = observed.reshape(*observed.shape[:-1], *(1,) * extra_dims, m)
    return y_bl, la.to_batch_last(observed, 1, batch_ndim)


def _normalized(log_w: Tensor, log_evidence: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Normalize incremental log-weights ``(*B, M)`` and accumulate the evidence ``(*B,)``,
    without host synchronization.

    Returns ``(log_w, log_evidence, dead, invalid)``: where every weight is zero (``dead``),
    the log-weights are a uniform placeholder (the caller resets the entry) and the evidence
    is ``-inf``, gradients staying finite everywhere; ``invalid`` flags a NaN or ``+inf`` sum
    (the caller raises).
    """
    increment = torch.logsumexp(log_w, -1)
    dead = torch.isneginf(increment)
    invalid = torch.isnan(increment) | torch.isposinf(increment)
    # Summed again without the dead entries' -inf (the same numbers elsewhere), so that the
    # gradient of the logsumexp is finite.
    log_w = torch.where(dead.unsqueeze(-1), 0.0, log_w)
    increment = torch.logsumexp(log_w, -1)
    log_evidence = torch.where(dead, -math.inf, log_evidence + increment)
    return log_w - increment.unsqueeze(-1), log_evidence, dead, invalid


# Entries of a step's flags (:func:`_flags`).
_INVALID, _DEAD, _BAD_DYNAMICS, _BAD_MODE_WEIGHT, _BAD_WEIGHTS, _BAD_MODES, _RESAMPLE = range(7)


def _belief_flags(modes: Tensor, log_weights: Tensor, log_evidence: Tensor, K: int) -> Tensor:
    """Whether the belief given to a step holds NaN or ``+inf`` log-weights or evidence, and
    whether its modes leave ``[0, K)``: ``(2,)`` bool, no synchronization (the step reads it
    with its other flags).

    Args:
        modes: ``(*B, N)`` long; log_weights: ``(*B, N)``; log_evidence: ``(*B,)``.
        K: the number of modes.
    """
    # x < inf is False exactly for NaN and +inf
    bad_weights = ~((log_weights < math.inf).all() & (log_evidence < math.inf).all())
    return torch.stack([bad_weights, ((modes < 0) | (modes >= K)).any()])


def _dynamics_flags(
    packed: Tensor, shared: dict[str, Tensor], mode_log_weight: Tensor | None
) -> tuple[Tensor, Tensor]:
    """Whether the model's dynamics of a step hold NaN or inf, and whether its
    ``mode_log_weight`` holds NaN or ``+inf``: two ``()`` bool tensors, no synchronization."""
    finite = torch.isfinite(packed).all()
    for value in shared.values():
        finite = finite & torch.isfinite(value).all()
    if mode_log_weight is None:
        return ~finite, torch.zeros_like(finite)
    return ~finite, (torch.isnan(mode_log_weight) | torch.isposinf(mode_log_weight)).any()


def _flags(
    invalid: Tensor,
    dead: Tensor,
    bad_dynamics: Tensor,
    bad_mode_weight: Tensor,
    belief_flags: Tensor,
    resample: Tensor | None = None,
) -> Tensor:
    """A step's ``(7,)`` bool flags (indexed by ``_INVALID`` …): any NaN/+inf weight
    increment, any dead entry, the model's dynamics and mode log-weights bad, the given
    belief's :func:`_belief_flags`, any entry to resample (False if ``resample`` is None)."""
    wanted = resample.any() if resample is not None else torch.zeros_like(bad_dynamics)
    head = torch.stack([invalid.any(), dead.any(), bad_dynamics, bad_mode_weight])
    return torch.cat([head, belief_flags, wanted.unsqueeze(0)])


def _read_flags(flags: Tensor) -> list[bool]:
    """A step's :func:`_flags` read (one host synchronization), raising the error they call
    for."""
    read: list[bool] = flags.tolist()
    # The given belief's and the model's faults come first: they make the weights NaN too.
    if read[_BAD_WEIGHTS]:
        raise ValueError("belief: log_weights and log_evidence must not hold NaN or +inf")
    if read[_BAD_MODES]:
        raise ValueError("belief: modes must lie in [0, K), the model's modes")
    if read[_BAD_MODE_WEIGHT]:
        raise ValueError("model: mode_dynamics().mode_log_weight: contains NaN or +inf")
    if read[_BAD_DYNAMICS]:
        raise ValueError("model: mode_dynamics() returned NaN or inf")
    if read[_INVALID]:
        raise ValueError(_INVALID_WEIGHTS)
    return read


def _gather_states(index: Tensor, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
    """Select particles along the last dim of batch-last states: ``index (*B, N)``."""
    mean = mean.gather(-1, index.expand(mean.shape[0], *index.shape))
    cov = cov.gather(-1, index.expand(cov.shape[0], cov.shape[1], *index.shape))
    return mean, cov


def _gather(
    index: Tensor, modes: Tensor, history: Tensor, mean: Tensor, cov: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Resample modes ``(*B, N)``, history ``(*B, N, L+1)`` and batch-last states by ``index``."""
    modes = modes.gather(-1, index)
    history = history.gather(-2, index.unsqueeze(-1).expand(*history.shape))
    mean, cov = _gather_states(index, mean, cov)
    return modes, history, mean, cov
