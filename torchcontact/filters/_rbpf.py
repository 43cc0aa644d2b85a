"""Rao-Blackwellized particle filter over the modes of a linear switching model: the filter's
settings, its initialization, the checks of a step's inputs and the two proposals' steps (whose
kernels are in ``_rbpf_kernels``)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import KW_ONLY, dataclass
from functools import cached_property
from typing import Any, Literal, get_args

import torch
from torch import Tensor

from torchcontact._checks import broadcast_batch, check_mask, check_tensor, describe
from torchcontact._compiled import kernel
from torchcontact.filters import _linalg as la
from torchcontact.filters._gaussian import Gaussian, check_gaussian, unchecked_gaussian
from torchcontact.filters._kalman import observed_components
from torchcontact.filters._manifold import EUCLIDEAN, Euclidean, Manifold
from torchcontact.filters._rbpf_belief import RBPFBelief, SwitchingModel
from torchcontact.filters._rbpf_kernels import (
    DEAD,
    RESAMPLE,
    batch_last_measurement,
    belief_flags,
    bootstrap_core,
    dynamics_flags,
    gather_particles,
    gather_states,
    normalize_log_weights,
    particle_params,
    predict_update,
    predicted_log_likelihood,
    read_flags,
    step_flags,
    unpack_dynamics,
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
    none of whose inputs needs a gradient records nothing for autograd (it runs with gradients
    disabled) and returns tensors that need none, with the same values.

    Time-varying models: every step asks the model for its per-mode dynamics
    (:meth:`SwitchingModel.mode_dynamics`, given the belief and the step's ``control``), so a
    nonlinear model is linearized once per mode and batch entry at the belief's mean (an
    extended Kalman filter per particle that shares the linearization point; exact for a
    linear model). A ``Q``, ``H``, ``d`` or ``R`` that every mode shares, given as a
    ``(K, ...)`` view of one matrix (``expand``), is not copied to the particles.

    States on a manifold: a model with a ``manifold`` attribute (e.g.
    :data:`~torchcontact.filters.SE3` for :class:`~torchcontact.filters.SpatialContactModel`)
    keeps each particle's mean on the manifold and its covariance in the ``d``-dim tangent
    there (error-state form). Its :class:`ModeDynamics` act on tangent coordinates: a
    particle enters the step as :math:`\delta_i = \mathrm{local}(\mathrm{origin},
    \mu_i)` (its covariance taken as it is, first order), the Kalman predict and update run
    on :math:`\delta` as above, and the posterior mean leaves as
    :math:`\mathrm{retract}(\mathrm{chart}, \delta_i^+)`. A measurement on a manifold (the
    model's ``measurement_manifold``) enters as :math:`\mathrm{local}(\mathrm{measurement
    \_chart}, y)`. The belief's :meth:`RBPFBelief.mean` is then the weighted Karcher mean.
    Models without these attributes are Euclidean, and their steps are unchanged.

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
            ``torchcontact._compiled``: the first steps compile, tens of seconds;
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

    @cached_property
    def manifold(self) -> Manifold:
        """The state's manifold: the model's ``manifold`` attribute, else
        :data:`~torchcontact.filters.EUCLIDEAN`."""
        return _manifold_of(self.model, "manifold")

    @cached_property
    def measurement_manifold(self) -> Manifold:
        """The measurement's manifold: the model's ``measurement_manifold`` attribute, else
        :data:`~torchcontact.filters.EUCLIDEAN`."""
        return _manifold_of(self.model, "measurement_manifold")

    @cached_property
    def _dims(self) -> tuple[int, int]:
        """The Kalman filters' sizes: the state's and the measurement's tangent dimensions."""
        model = self.model
        return (
            self.manifold.tangent_dim(model.state_dim),
            self.measurement_manifold.tangent_dim(model.obs_dim),
        )

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
            prior: ``(*B', n)`` Gaussian over ``x_0`` (covariance ``(d, d)`` in the tangent
                for a model on a manifold), dtype of the model.
            batch_shape: extra batch shape; the belief's batch ``*B`` is the broadcast of
                ``prior.batch_shape`` and ``batch_shape`` (e.g. independent replicas).

        Returns:
            The initial :class:`RBPFBelief` (``log_evidence == 0``).
        """
        euclidean = isinstance(self.manifold, Euclidean)
        prior = check_gaussian(prior, "prior", euclidean=euclidean)
        model = self.model
        d = self._dims[0]
        if prior.dim != model.state_dim or prior.tangent_dim != d or prior.dtype != model.dtype:
            raise ValueError(
                f"prior: expected n = {model.state_dim}, covariance ({d}, {d}) and dtype "
                f"{model.dtype}, got n = {prior.dim}, covariance {tuple(prior.cov.shape[-2:])} "
                f"and {prior.dtype}"
            )
        try:
            batch = torch.broadcast_shapes(prior.batch_shape, tuple(batch_shape))
        except (RuntimeError, TypeError) as err:
            raise ValueError(
                f"batch_shape: {batch_shape!r} does not broadcast with the prior's batch "
                f"{tuple(prior.batch_shape)}"
            ) from err
        n, nb = model.state_dim, len(batch)
        prior = unchecked_gaussian(prior.mean.expand(*batch, n), prior.cov.expand(*batch, d, d))
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
            manifold=self.manifold,
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
                component means "no measurement" (likelihood 1 for every particle); for a
                measurement on a manifold (the model's ``measurement_manifold``), NaN in any.
            action: the action that selects the transition matrix of an action-dependent model:
                an int or a ``(*B',)`` long tensor in ``[0, A)``; must be None for a ``(K, K)``
                transition.
            extra_log_likelihood: ``(*B', K)`` per-mode log-likelihood added to each particle's
                log-weight by its new mode (``-inf`` rules a mode out; NaN and ``+inf`` are
                errors).
            control: the model's control input of this step (e.g. the finger poses and
                twists of a :class:`~torchcontact.filters.PlanarContactModel`); None for a
                :class:`LinearSwitchingModel`.
            mask: ``(*B', m)`` bool, the measurement components used (see ``kf_update``); for
                a measurement on a manifold, ``(*B', k)`` over its tangent components.
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
            mask = check_mask("mask", mask, size=self._dims[1])
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
        euclidean_y = isinstance(self.measurement_manifold, Euclidean)
        observed = observed_components(y, mask) if euclidean_y else None
        dynamics = self.model.mode_dynamics(belief, control)
        if not isinstance(dynamics, ModeDynamics):
            raise ValueError(
                f"model: mode_dynamics returned {type(dynamics).__name__}, not ModeDynamics"
            )
        if not euclidean_y:
            y = self._measurement_in_chart(y, dynamics.measurement_chart)
            observed = observed_components(y, mask)
        chart = None
        if not isinstance(self.manifold, Euclidean):
            belief, chart = self._belief_in_chart(belief, dynamics)
        packed, shared, mode_log_weight = self._packed_dynamics(belief, dynamics)
        mode_log_weight = self._child_log_weight(belief, mode_log_weight, dynamics)
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
            new = step(
                belief, packed, shared, mode_log_weight, y, observed, rows, extra, generator, chart
            )
        return new

    def _measurement_in_chart(self, y: Tensor, chart: Tensor | None) -> Tensor:
        """``local(chart, y)`` ``(*B, k)``: a measurement on the measurement manifold in the
        tangent at the model's ``measurement_chart``; a measurement with a NaN is NaN in every
        component (missing)."""
        m = self.model.obs_dim
        if not isinstance(chart, Tensor) or chart.shape[-1:] != (m,):
            raise ValueError(
                f"model: mode_dynamics().measurement_chart must be a (*B, {m}) tensor for a "
                f"measurement on a manifold, got {describe(chart)}"
            )
        batch = torch.broadcast_shapes(y.shape[:-1], chart.shape[:-1])
        missing = torch.isnan(y).any(-1, keepdim=True)
        local = self.measurement_manifold.local(
            chart.expand(*batch, m), torch.where(missing, chart, y).expand(*batch, m)
        )
        return torch.where(missing, math.nan, local)

    def _belief_in_chart(
        self, belief: RBPFBelief, dynamics: ModeDynamics
    ) -> tuple[RBPFBelief, Tensor]:
        """The belief with its particles' means in the tangent at ``dynamics.origin``
        (``local(origin, μ_i)``), and the ``(*B, n)`` chart its predictions are retracted
        from."""
        n = self.model.state_dim
        batch, N = belief.batch_shape, self.num_particles
        for name in ("origin", "chart"):
            value = getattr(dynamics, name)
            if not isinstance(value, Tensor) or value.shape[-1:] != (n,):
                raise ValueError(
                    f"model: mode_dynamics().{name} must be a (*B, {n}) tensor for a state on "
                    f"a manifold, got {describe(value)}"
                )
        assert dynamics.origin is not None
        assert dynamics.chart is not None
        g = belief.gaussians
        origin = dynamics.origin.unsqueeze(-2).expand(*batch, N, n)
        delta = self.manifold.local(origin, g.mean)
        local = dataclasses.replace(belief, gaussians=unchecked_gaussian(delta, g.cov))
        return local, dynamics.chart.expand(*batch, n)

    def _child_log_weight(
        self, belief: RBPFBelief, mode_log_weight: Tensor | None, dynamics: ModeDynamics
    ) -> Tensor | None:
        """The model's log-weight of every particle's children, ``(*B', N, K)`` (or with
        ``N`` of size 1 where it is the same for every particle): ``mode_log_weight
        (*B', K)`` plus the checked ``particle_log_weight (*B', N, K)``; None if neither is
        given."""
        weight = dynamics.particle_log_weight
        if weight is None:
            return None if mode_log_weight is None else mode_log_weight.unsqueeze(-2)
        model, N, K = self.model, self.num_particles, self.model.num_modes
        field = "model: mode_dynamics().particle_log_weight"
        weight = check_tensor(
            field, weight, event_shape=(N, K), like=model.initial, allow_neginf=True
        )
        shapes = [("belief", belief.batch_shape), ("particle_log_weight", weight.shape[:-2])]
        if broadcast_batch(shapes) != belief.batch_shape:
            raise ValueError(
                f"{field} batch {tuple(weight.shape[:-2])} does not broadcast to the belief's "
                f"batch {tuple(belief.batch_shape)}"
            )
        return weight if mode_log_weight is None else weight + mode_log_weight.unsqueeze(-2)

    def _transition_rows(
        self, belief: RBPFBelief, transition: Tensor, rows: Tensor | None
    ) -> Tensor:
        """``(*B, N, K)`` transition probabilities of every particle's next mode: the model's
        per-particle ``rows`` if given (checked), else the rows of ``transition`` (``(K, K)``
        or ``(*B', K, K)``) selected by the particles' modes."""
        model, N, K = self.model, self.num_particles, self.model.num_modes
        batch = belief.batch_shape
        if rows is None:
            # Modes out of [0, K) are flagged by the step (:func:`belief_flags`); clamped here
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
            step (:func:`dynamics_flags`).
        """
        model = self.model
        K, (n, m) = model.num_modes, self._dims
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
        # whose flags are read with one host synchronization (:func:`read_flags`).
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
        chart: Tensor | None,
    ) -> RBPFBelief:
        model, N = self.model, self.num_particles
        batch, nb = belief.batch_shape, len(belief.batch_shape)
        # Sample m_t ~ p(m_t | particle) by inverse CDF (no gradient through the draw).
        cdf = normalized_cdf(rows.detach())  # (*B, N, K)
        draw = torch.rand(
            (*batch, N, 1), dtype=torch.float64, device=model.device, generator=generator
        )
        modes = search_cdf(cdf, draw).squeeze(-1)
        y_bl, obs_bl = batch_last_measurement(y, observed, nb + 1)
        g = belief.gaussians
        core = kernel(bootstrap_core, compiled=self.compiled)
        log_w, mean, cov, log_evidence, history, dead, resample, flags = core(
            modes,
            packed,
            particle_params(packed, modes),
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
            n=self._dims[0],
            m=self._dims[1],
            measured=self._measured(observed),
            entrywise=self.compiled,
            log_ess_bound=-math.log(max(self.ess_threshold * N, 1e-300)),
        )
        read = read_flags(flags)
        any_dead, any_resample = read[DEAD], read[RESAMPLE]
        if any_resample:
            index = resample_indices(log_w, N, self.resampling, generator)
            identity = torch.arange(N, device=index.device)
            index = torch.where(resample.unsqueeze(-1), index, identity)
            modes, history, mean, cov = gather_particles(index, modes, history, mean, cov)
            log_w = torch.where(resample.unsqueeze(-1), -math.log(N), log_w)
        return self._belief(
            belief, modes, log_w, mean, cov, log_evidence, history, dead, any_dead, chart
        )

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
        chart: Tensor | None,
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
        if extra is not None:
            log_w = log_w + extra.unsqueeze(-2)
        if mode_log_weight is not None:  # (*B', N or 1, K)
            log_w = log_w + mode_log_weight
        log_w, log_evidence, dead, invalid = normalize_log_weights(
            log_w.flatten(-2), belief.log_evidence
        )
        flags = step_flags(
            invalid,
            dead,
            *dynamics_flags(packed, shared, mode_log_weight),
            belief_flags(belief.modes, belief.log_weights, belief.log_evidence, K),
        )
        any_dead = read_flags(flags)[DEAD]
        index, log_w = optimal_resample_core(log_w, N, generator)
        modes = index % K
        parents = torch.div(index, K, rounding_mode="floor")
        history = belief.history.gather(
            -2, parents.unsqueeze(-1).expand(*batch, N, self.max_lag + 1)
        )
        history = torch.cat([modes.unsqueeze(-1), history[..., :-1]], -1)
        # Only the N survivors need the Kalman update: the same operations on the same
        # numbers (in the same memory layouts) as a step of all N·K children does for them.
        mean, cov = gather_states(parents, mean, cov)
        y_bl, obs_bl = batch_last_measurement(y, observed, nb + 1)
        kalman = kernel(predict_update, compiled=self.compiled)
        mean, cov, _ = kalman(
            mean,
            cov,
            particle_params(packed, modes),
            shared,
            y_bl,
            obs_bl,
            n=self._dims[0],
            m=self._dims[1],
            measured=measured,
            entrywise=self.compiled,
        )
        return self._belief(
            belief, modes, log_w, mean, cov, log_evidence, history, dead, any_dead, chart
        )

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

        The log-likelihood of :func:`predict_update` on every child without the posterior, from the
        leading ``r`` components of the predicted mean and covariance: those that ``H`` reads
        when every mode shares it (the pose of a
        :class:`~torchcontact.filters.PlanarContactModel`), else all. The operations are
        those of :func:`predict_update` on the same numbers, so the values are the same (to the bit
        when ``H`` selects components; see :func:`update_log_likelihood` for the exception).

        Args:
            mean: ``(n, *B, N)``; cov: ``(n, n, *B, N)``: the particles, batch-last.
            packed: ``(K, D)`` or ``(*B', K, D)`` the modes' packed dynamics.
            shared: as in :func:`predict_update`.
            y: ``(*B', m)`` measurement; observed: ``(*B', m)`` bool or None.
            measured: :meth:`_measured` of ``observed``; ``False``: likelihood 1.
        """
        model = self.model
        (n, m), K = self._dims, model.num_modes
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
        F, c, Q, H, d, R = unpack_dynamics(params, shared, n, m)
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
        y_bl, obs_bl = batch_last_measurement(y, observed, predicted.ndim - 1)
        likelihood = kernel(predicted_log_likelihood, compiled=self.compiled)
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
        chart: Tensor | None = None,
    ) -> RBPFBelief:
        """Assemble the new belief, resetting the entries flagged ``dead`` to the prior; with
        a ``chart`` ``(*B, n)``, the means ``(d, *B, N)`` are tangent vectors there."""
        if chart is not None:
            batch, N = previous.batch_shape, self.num_particles
            delta = la.to_batch_first(mean, 1)
            point = chart.unsqueeze(-2).expand(*batch, N, chart.shape[-1])
            mean = la.to_batch_last(self.manifold.retract(point, delta), 1, len(batch) + 1)
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
            manifold=self.manifold,
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
            or g.tangent_dim != self._dims[0]
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


def _manifold_of(model: object, name: str) -> Manifold:
    """A model's optional manifold attribute ``name`` (default Euclidean), checked."""
    manifold = getattr(model, name, EUCLIDEAN)
    if not isinstance(manifold, Manifold):
        raise ValueError(f"model: its {name} must be a Manifold, got {describe(manifold)}")
    return manifold
