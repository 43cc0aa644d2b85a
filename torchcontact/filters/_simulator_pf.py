"""Bootstrap particle filter that steps every particle through the contact simulator."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import KW_ONLY, dataclass

import torch
from torch import Tensor

from torchcontact._checks import check_batched, check_float, check_int, check_tensor
from torchcontact.filters._contact_model import KinematicControl
from torchcontact.filters._gaussian import Gaussian, check_gaussian
from torchcontact.filters._resampling import RESAMPLING_METHODS, ResamplingMethod, resample
from torchcontact.geometry import wrap_angle
from torchcontact.sim import UNSOLVED, Scene, SceneState, Simulator, StepResult

#: ``extra_log_likelihood(state, result) -> (*B, N)``: a per-particle log-likelihood term of
#: the step from the particles' ``state`` (batch ``(*B, N)``) and the simulator's ``result``.
ParticleLogLikelihood = Callable[[SceneState, StepResult], Tensor]


@dataclass(frozen=True, eq=False)
class SimulatorPFBelief:
    """The belief of a :class:`SimulatorParticleFilter`: ``N`` weighted particles per batch
    entry.

    Attributes:
        particles: ``(*B, N, 6)`` pose ``(x, y, θ)`` and twist ``(vx, vy, ω)`` of the dynamic
            body, world frame.
        modes: ``(*B, N, L)`` long per-slot contact modes of each particle's last simulated
            step (zeros before the first); the simulator's first guess for the next step.
        log_weights: ``(*B, N)`` normalized log-weights (``logsumexp == 0``).
        log_evidence: ``(*B,)`` running :math:`\\log \\hat p(y_{1:t})`; ``-inf`` once a step
            gave every particle weight zero.
        stepped: whether a step made the belief (its particles are then resampled by the
            next step); ``False`` for the prior's independent draws of
            :meth:`SimulatorParticleFilter.init`.
    """

    particles: Tensor
    modes: Tensor
    log_weights: Tensor
    log_evidence: Tensor
    stepped: bool

    @property
    def batch_shape(self) -> torch.Size:
        """The batch dims ``*B``."""
        return self.log_weights.shape[:-1]

    @property
    def num_particles(self) -> int:
        """``N``."""
        return int(self.log_weights.shape[-1])

    def weights(self) -> Tensor:
        """``(*B, N)`` normalized weights."""
        return torch.exp(self.log_weights)

    def mean(self) -> Tensor:
        r"""Weighted mean :math:`\sum_i w_i x_i`, ``(*B, 6)`` (the angle averaged as a number)."""
        return (self.weights()[..., None] * self.particles).sum(-2)


@dataclass(frozen=True, eq=False)
class SimulatorParticleFilter:
    r"""Bootstrap particle filter over the pose and twist of a scene's one dynamic body, each
    particle propagated by the :class:`~torchcontact.sim.Simulator` (the baseline that a
    contact-mode :class:`~torchcontact.filters.RBPF` is compared against).

    One :meth:`step` (Gordon, Salmond and Smith 1993):

    1. resample the particles with ``resampling`` (:func:`~torchcontact.filters.resample`),
       except the prior's draws of :meth:`init` (independent and equally weighted);
    2. step every particle through the simulator under the step's kinematic ``control``
       (its per-slot modes are the simulator's first guess), then add process noise
       :math:`w \sim N(0, \mathrm{diag}(\sigma_w^2))`;
    3. weight it by :math:`\log p(y \mid x) = \log N(y; x_{0:3}, \mathrm{diag}(\sigma_y^2))`
       (the angle residual wrapped to :math:`[-\pi, \pi)`; an entry whose ``y`` has a NaN is
       not measured) plus the optional ``extra_log_likelihood`` of the simulated step (e.g.
       tactile readings of the particle's contacts). The evidence increment is
       :math:`\log \frac1N \sum_i p(y \mid x_i)\, e^{\ell_i}`.

    A particle whose step no contact solver solved keeps its state, gets weight zero and the
    modes 0; an entry all of whose particles get weight zero is given uniform weights (its
    evidence becomes ``-inf``). Everything is functional: the belief holds the whole state.

    Args:
        scene: the filter's scene, one dynamic body (e.g. with an assumed friction).
        num_particles: ``N >= 1``.
        process_std: ``(6,)`` per-step process noise std ``σ_w`` of ``(x, y, θ, vx, vy, ω)``,
            ``>= 0`` (float64 or the filter's dtype).
        measurement_std: ``(3,)`` std ``σ_y`` of the pose measurement, ``> 0``.
        resampling: the resampling scheme.

    References:
        N. J. Gordon, D. J. Salmond and A. F. M. Smith, "Novel approach to nonlinear/non-Gaussian
        Bayesian state estimation", IEE Proceedings F 140(2), 1993.
    """

    scene: Scene
    num_particles: int
    _: KW_ONLY
    process_std: Tensor
    measurement_std: Tensor
    resampling: ResamplingMethod = "systematic"

    def __post_init__(self) -> None:
        if not isinstance(self.scene, Scene) or len(self.scene.dynamic) != 1:
            raise ValueError("scene: expected a Scene with one dynamic body")
        check_int("num_particles", self.num_particles, low=1)
        for name, size in (("process_std", 6), ("measurement_std", 3)):
            value = check_float(name, getattr(self, name), trailing=(size,), what=f"({size},)")
            if value.ndim != 1 or bool((value < 0).any()):
                raise ValueError(f"{name}: expected a ({size},) tensor >= 0, got {value}")
        if bool((self.measurement_std == 0).any()):
            raise ValueError(f"measurement_std: expected > 0, got {self.measurement_std}")
        if self.resampling not in RESAMPLING_METHODS:
            raise ValueError(
                f"resampling: expected one of {RESAMPLING_METHODS}, got {self.resampling!r}"
            )

    def init(
        self, prior: Gaussian, *, generator: torch.Generator | None = None
    ) -> SimulatorPFBelief:
        """``N`` equally weighted particles drawn from ``prior``, in separated modes.

        Args:
            prior: ``(*B, 6)`` Gaussian over pose and twist (Euclidean, positive definite).
            generator: random source (reproducible runs); torch's default if None.

        Returns:
            The initial belief (``log_evidence == 0``).
        """
        prior = check_gaussian(prior, "prior", euclidean=True)
        if prior.dim != 6:
            raise ValueError(f"prior: expected a Gaussian over 6 components, got {prior.dim}")
        batch, N = prior.batch_shape, self.num_particles
        chol = torch.linalg.cholesky(prior.cov)
        noise = torch.randn(*batch, N, 6, 1, generator=generator, dtype=prior.dtype)
        particles = prior.mean.unsqueeze(-2) + (chol.unsqueeze(-3) @ noise).squeeze(-1)
        return SimulatorPFBelief(
            particles=particles,
            modes=torch.zeros(*batch, N, self.scene.num_slots, dtype=torch.long),
            log_weights=torch.full((*batch, N), -math.log(N), dtype=prior.dtype),
            log_evidence=torch.zeros(batch, dtype=prior.dtype),
            stepped=False,
        )

    def step(
        self,
        belief: SimulatorPFBelief,
        y: Tensor,
        *,
        control: KinematicControl,
        extra_log_likelihood: ParticleLogLikelihood | None = None,
        generator: torch.Generator | None = None,
    ) -> SimulatorPFBelief:
        """Resample, simulate, perturb and weight the particles (see the class docstring).

        Args:
            belief: the belief at the start of the step, batch ``*B``.
            y: ``(*B, 3)`` pose measurement after the step (world frame); NaN: none.
            control: the kinematic bodies' ``(*B, Nk, 3)`` poses at the start of the step and
                twists during it.
            extra_log_likelihood: optional per-particle log-likelihood of the simulated step.
            generator: random source (reproducible runs); torch's default if None.

        Returns:
            The belief after the step.
        """
        if not isinstance(belief, SimulatorPFBelief):
            raise ValueError(f"belief: expected a SimulatorPFBelief, got {type(belief).__name__}")
        x, like = belief.particles, belief.particles
        batch, N = belief.batch_shape, belief.num_particles
        y = check_tensor("y", y, event_shape=(3,), like=like, allow_nan=True)
        if y.shape[:-1] != batch:
            raise ValueError(f"y: expected shape {(*batch, 3)}, got {tuple(y.shape)}")
        Nk = len(self.scene.kinematic)
        if not isinstance(control, KinematicControl):
            raise ValueError(f"control: expected a KinematicControl, got {type(control).__name__}")
        for name in ("q", "v"):
            check_batched(
                f"control.{name}",
                getattr(control, name),
                shape=(*batch, Nk, 3),
                like=like,
                like_name="belief",
            )
        mode = belief.modes
        if belief.stepped:
            index = resample(belief.log_weights, method=self.resampling, generator=generator)
            x = torch.gather(x, -2, index[..., None].expand(*batch, N, 6))
            mode = torch.gather(mode, -2, index[..., None].expand(*batch, N, mode.shape[-1]))
        simulator = Simulator(self.scene)
        state = simulator.initial_state(
            q=x[..., None, :3],
            v=x[..., None, 3:],
            q_kinematic=control.q.unsqueeze(-3).expand(*batch, N, Nk, 3).contiguous(),
        )
        state = dataclasses.replace(state, mode=mode)
        result = simulator.step(
            state, control.v.unsqueeze(-3).expand(*batch, N, Nk, 3).contiguous()
        )
        # A particle whose step no solver solved gets weight zero; its numbers are replaced
        # by finite ones so that they cannot poison the weighted sums.
        unsolved = result.solver == UNSOLVED
        simulated = torch.cat([result.state.q[..., 0, :], result.state.v[..., 0, :]], -1)
        x = torch.where(unsolved[..., None], x, simulated)
        noise = self.process_std.to(x)
        x = x + noise * torch.randn(*batch, N, 6, generator=generator, dtype=x.dtype)
        mode = torch.where(unsolved[..., None], 0, result.mode)
        log_w = torch.where(unsolved, -math.inf, 0.0).to(x.dtype)
        if extra_log_likelihood is not None:
            result = dataclasses.replace(
                result,
                pn=torch.where(unsolved[..., None], 0.0, result.pn).clamp_min(0.0),
                mode=mode,
            )
            extra = extra_log_likelihood(state, result)
            log_w = log_w + check_tensor(
                "extra_log_likelihood", extra, event_shape=(N,), like=like, allow_neginf=True
            )
        sigma = self.measurement_std.to(x)
        seen = torch.isfinite(y).all(-1)
        residual = x[..., :3] - y.unsqueeze(-2)
        residual[..., 2] = wrap_angle(residual[..., 2])
        vision = -0.5 * (residual / sigma).pow(2).sum(-1)
        log_w = log_w + torch.where(seen[..., None], vision.nan_to_num(0.0), 0.0)
        dead = torch.isneginf(log_w).all(-1)
        log_w = torch.where(dead[..., None], 0.0, log_w)
        # The Gaussian's normalizing constant: the same for every particle of an entry.
        constant = -0.5 * torch.log(2 * math.pi * sigma.pow(2)).sum()
        increment = torch.logsumexp(log_w, -1) - math.log(N) + torch.where(seen, constant, 0.0)
        increment = torch.where(dead, -math.inf, increment)
        return SimulatorPFBelief(
            particles=x,
            modes=mode,
            log_weights=torch.log_softmax(log_w, -1),
            log_evidence=belief.log_evidence + increment,
            stepped=True,
        )
