"""Bootstrap particle filter that steps every particle through the contact simulator."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import KW_ONLY, dataclass, field

import torch
from torch import Tensor

from torchcontact._checks import check_batched, check_float, check_int, check_tensor
from torchcontact.contact import Method
from torchcontact.filters._contact_model import KinematicControl
from torchcontact.filters._gaussian import Gaussian, check_gaussian
from torchcontact.filters._manifold import SE3
from torchcontact.filters._resampling import RESAMPLING_METHODS, ResamplingMethod, resample
from torchcontact.filters._spatial_contact_model import RobotControl
from torchcontact.geometry import wrap_angle
from torchcontact.sim import UNSOLVED, Scene, SceneState, Simulator, StepResult

#: ``extra_log_likelihood(state, result) -> (*B, N)``: a per-particle log-likelihood term of
#: the step from the particles' ``state`` (batch ``(*B, N)``) and the simulator's ``result``.
ParticleLogLikelihood = Callable[[SceneState, StepResult], Tensor]
#: Sizes by scene dimension: state (pose + twist), its tangent, the pose measurement's tangent.
_STATE_SIZE = {2: 6, 3: 13}
_TANGENT_SIZE = {2: 6, 3: 12}
_MEASUREMENT_SIZE = {2: 3, 3: 6}


@dataclass(frozen=True, eq=False)
class SimulatorPFBelief:
    """The belief of a :class:`SimulatorParticleFilter`: ``N`` weighted particles per batch
    entry.

    Attributes:
        particles: ``(*B, N, 6)`` pose ``(x, y, θ)`` and twist ``(vx, vy, ω)`` of the dynamic
            body, world frame; spatial: ``(*B, N, 13)`` position, unit quaternion
            ``(w, x, y, z)`` and twist ``(v, ω)``.
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
        r"""Weighted mean :math:`\sum_i w_i x_i`, ``(*B, 6)`` (the angle averaged as a number).

        Spatial, ``(*B, 13)``: the quaternions are first given the sign of the heaviest
        particle's (``q`` and ``-q`` are one rotation), and their weighted sum is normalized
        (the chordal mean of the rotations).
        """
        w = self.weights()[..., None]
        x = self.particles
        if x.shape[-1] == _STATE_SIZE[2]:
            return (w * x).sum(-2)
        heaviest = self.log_weights.argmax(-1)[..., None, None].expand(*x.shape[:-2], 1, 4)
        reference = torch.gather(x[..., 3:7], -2, heaviest)
        sign = torch.where((x[..., 3:7] * reference).sum(-1, keepdim=True) < 0, -1.0, 1.0)
        quaternion = (w * sign * x[..., 3:7]).sum(-2)
        quaternion = quaternion / torch.linalg.vector_norm(quaternion, dim=-1, keepdim=True)
        rest = (w * x).sum(-2)
        return torch.cat([rest[..., :3], quaternion, rest[..., 7:]], -1)


@dataclass(frozen=True, eq=False)
class SimulatorParticleFilter:
    r"""Bootstrap particle filter over the pose and twist of a scene's one dynamic body, each
    particle propagated by the :class:`~torchcontact.sim.Simulator` (the baseline that a
    contact-mode :class:`~torchcontact.filters.RBPF` is compared against).

    Planar scenes: the state is ``(x, y, θ, vx, vy, ω)``, the kinematic bodies' motion the
    control (:class:`~torchcontact.filters.KinematicControl`). Spatial scenes: the state is
    the 13 numbers of :data:`~torchcontact.filters.SE3` with a twist (position, unit
    quaternion, ``(v, ω)``), noise and measurement residuals live in its tangent
    (``retract``/``local``), and the control is the measured motion of the scene's robots
    (:class:`~torchcontact.filters.RobotControl`: joint angles and velocities, base poses and
    twists, and for servo joints their commands: they are simulated with each particle).

    One :meth:`step` (Gordon, Salmond and Smith 1993):

    1. resample the particles with ``resampling`` (:func:`~torchcontact.filters.resample`),
       except the prior's draws of :meth:`init` (independent and equally weighted);
    2. step every particle through the simulator under the step's ``control``
       (its per-slot modes are the simulator's first guess), then add process noise
       :math:`w \sim N(0, \mathrm{diag}(\sigma_w^2))`;
    3. weight it by :math:`\log p(y \mid x) = \log N(y; x_{0:3}, \mathrm{diag}(\sigma_y^2))`
       (the angle residual wrapped to :math:`[-\pi, \pi)`; spatial: ``y`` is a ``(7,)`` pose
       and the residual ``local(x, y)`` its 6-dim tangent; an entry whose ``y`` has a NaN is
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
            ``>= 0`` (float64 or the filter's dtype); spatial ``(12,)``, of the tangent
            ``(δp, δθ, δv, δω)`` (``δθ`` in the body frame).
        measurement_std: ``(3,)`` std ``σ_y`` of the pose measurement, ``> 0``; spatial
            ``(6,)``, of position and rotation vector.
        resampling: the resampling scheme.
        fallback: the simulator's exact solvers for the particles whose guessed modes fail
            (:attr:`Simulator.fallback <torchcontact.sim.Simulator.fallback>`): dropping the
            QP fallback, slow on a grasp's redundant rows, bounds the cost of a step; the
            particles that Lemke leaves unsolved then get weight zero.

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
    fallback: tuple[Method, ...] = ("lemke", "qp")
    _simulator: Simulator = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.scene, Scene) or len(self.scene.dynamic) != 1:
            raise ValueError("scene: expected a Scene with one dynamic body")
        check_int("num_particles", self.num_particles, low=1)
        dimension = self.scene.dimension
        sizes = (_TANGENT_SIZE[dimension], _MEASUREMENT_SIZE[dimension])
        for name, size in zip(("process_std", "measurement_std"), sizes, strict=True):
            value = check_float(name, getattr(self, name), trailing=(size,), what=f"({size},)")
            if value.ndim != 1 or bool((value < 0).any()):
                raise ValueError(f"{name}: expected a ({size},) tensor >= 0, got {value}")
        if bool((self.measurement_std == 0).any()):
            raise ValueError(f"measurement_std: expected > 0, got {self.measurement_std}")
        # the simulator every step runs (it validates ``fallback``)
        object.__setattr__(self, "_simulator", Simulator(self.scene, fallback=self.fallback))
        if self.resampling not in RESAMPLING_METHODS:
            raise ValueError(
                f"resampling: expected one of {RESAMPLING_METHODS}, got {self.resampling!r}"
            )

    def init(
        self, prior: Gaussian, *, generator: torch.Generator | None = None
    ) -> SimulatorPFBelief:
        """``N`` equally weighted particles drawn from ``prior``, in separated modes.

        Args:
            prior: ``(*B, 6)`` Gaussian over pose and twist (Euclidean, positive definite);
                spatial: mean ``(*B, 13)`` and covariance ``(*B, 12, 12)`` in the tangent
                (:data:`~torchcontact.filters.SE3`, positive definite).
            generator: random source (reproducible runs); torch's default if None.

        Returns:
            The initial belief (``log_evidence == 0``).
        """
        spatial = self.scene.dimension == 3
        prior = check_gaussian(prior, "prior", euclidean=not spatial)
        size, tangent = _STATE_SIZE[self.scene.dimension], _TANGENT_SIZE[self.scene.dimension]
        if prior.dim != size or prior.tangent_dim != tangent:
            raise ValueError(
                f"prior: expected a Gaussian over {size} components ({tangent} in the tangent), "
                f"got {prior.dim} ({prior.tangent_dim})"
            )
        batch, N = prior.batch_shape, self.num_particles
        chol = torch.linalg.cholesky(prior.cov)
        dtype, device = prior.dtype, prior.mean.device
        noise = torch.randn(*batch, N, tangent, 1, generator=generator, dtype=dtype, device=device)
        delta = (chol.unsqueeze(-3) @ noise).squeeze(-1)
        mean = prior.mean.unsqueeze(-2).expand(*batch, N, size)
        particles = SE3.retract(mean, delta) if spatial else mean + delta
        return SimulatorPFBelief(
            particles=particles,
            modes=torch.zeros(*batch, N, self.scene.num_slots, dtype=torch.long, device=device),
            log_weights=torch.full((*batch, N), -math.log(N), dtype=dtype, device=device),
            log_evidence=torch.zeros(batch, dtype=dtype, device=device),
            stepped=False,
        )

    def step(
        self,
        belief: SimulatorPFBelief,
        y: Tensor,
        *,
        control: KinematicControl | RobotControl,
        extra_log_likelihood: ParticleLogLikelihood | None = None,
        generator: torch.Generator | None = None,
    ) -> SimulatorPFBelief:
        """Resample, simulate, perturb and weight the particles (see the class docstring).

        Args:
            belief: the belief at the start of the step, batch ``*B``.
            y: ``(*B, 3)`` pose measurement after the step (world frame); spatial ``(*B, 7)``
                (position, unit quaternion); NaN: none.
            control: planar: a :class:`~torchcontact.filters.KinematicControl`, the kinematic
                bodies' ``(*B, Nk, 3)`` poses at the start of the step and twists during it;
                spatial: a :class:`~torchcontact.filters.RobotControl`, the measured motion
                of the scene's kinematic robots.
            extra_log_likelihood: optional per-particle log-likelihood of the simulated step.
            generator: random source (reproducible runs); torch's default if None.

        Returns:
            The belief after the step.
        """
        if not isinstance(belief, SimulatorPFBelief):
            raise ValueError(f"belief: expected a SimulatorPFBelief, got {type(belief).__name__}")
        x, like = belief.particles, belief.particles
        batch, N = belief.batch_shape, belief.num_particles
        spatial = self.scene.dimension == 3
        size = 7 if spatial else 3
        y = check_tensor("y", y, event_shape=(size,), like=like, allow_nan=True)
        if y.shape[:-1] != batch:
            raise ValueError(f"y: expected shape {(*batch, size)}, got {tuple(y.shape)}")
        mode = belief.modes
        if belief.stepped:
            index = resample(belief.log_weights, method=self.resampling, generator=generator)
            x = torch.gather(x, -2, index[..., None].expand(*batch, N, x.shape[-1]))
            mode = torch.gather(mode, -2, index[..., None].expand(*batch, N, mode.shape[-1]))
        simulator = self._simulator
        if spatial:
            state, result = self._simulate_spatial(simulator, x, mode, control, like)
        else:
            state, result = self._simulate_planar(simulator, x, mode, control, like)
        # A particle whose step no solver solved gets weight zero; its numbers are replaced
        # by finite ones so that they cannot poison the weighted sums.
        unsolved = result.solver == UNSOLVED
        simulated = torch.cat([result.state.q[..., 0, :], result.state.v[..., 0, :]], -1)
        x = torch.where(unsolved[..., None], x, simulated)
        noise = self.process_std.to(x)
        delta = noise * torch.randn(
            *batch, N, noise.shape[-1], generator=generator, dtype=x.dtype, device=x.device
        )
        x = SE3.retract(x, delta) if spatial else x + delta
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
        if spatial:
            # Unmeasured entries get a placeholder pose (their residual is discarded).
            placeholder = torch.tensor(
                [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], dtype=x.dtype, device=x.device
            )
            measured = torch.where(seen[..., None], y, placeholder)
            residual = SE3.local(x[..., :7], measured.unsqueeze(-2).expand(*batch, N, 7))
        else:
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

    def _simulate_planar(
        self, simulator: Simulator, x: Tensor, mode: Tensor, control: object, like: Tensor
    ) -> tuple[SceneState, StepResult]:
        """Step ``(*B, N, 6)`` planar particles under a :class:`KinematicControl`."""
        *batch, N, _ = x.shape
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
        state = simulator.initial_state(
            q=x[..., None, :3],
            v=x[..., None, 3:],
            q_kinematic=control.q.unsqueeze(-3).expand(*batch, N, Nk, 3).contiguous(),
        )
        state = dataclasses.replace(state, mode=mode)
        result = simulator.step(
            state, control.v.unsqueeze(-3).expand(*batch, N, Nk, 3).contiguous()
        )
        return state, result

    def _simulate_spatial(
        self, simulator: Simulator, x: Tensor, mode: Tensor, control: object, like: Tensor
    ) -> tuple[SceneState, StepResult]:
        """Step ``(*B, N, 13)`` spatial particles under the robots' measured motion."""
        *batch, N, _ = x.shape
        scene = self.scene
        joints, robots = scene.num_robot_joints, len(scene.robots)
        if scene.kinematic:
            raise ValueError("scene: a spatial filter scene moves robots, not kinematic bodies")
        if not isinstance(control, RobotControl):
            raise ValueError(f"control: expected a RobotControl, got {type(control).__name__}")
        values = {}
        for name, shape in (
            ("q_robot", (*batch, joints)),
            ("v_robot", (*batch, joints)),
            ("robot_base", (*batch, robots, 7)),
            ("base_twist", (*batch, robots, 6)),
            ("joint_command", (*batch, joints)),
        ):
            value = getattr(control, name)
            if value is not None:
                check_batched(f"control.{name}", value, shape=shape, like=like, like_name="belief")
                value = value.unsqueeze(len(batch)).expand(*batch, N, *shape[len(batch) :])
            values[name] = value
        # Kinematic robots move as measured over the step; servo joints start from their
        # measured velocities under the commands (see RobotControl).
        servo = scene.num_servo_joints > 0
        command = values["joint_command"] if servo else values["v_robot"]
        if command is None:
            raise ValueError("control.joint_command: required for a scene with servo joints")
        state = simulator.initial_state(
            q=x[..., None, :7],
            v=x[..., None, 7:],
            q_robot=values["q_robot"].contiguous(),
            v_robot=values["v_robot"].contiguous() if servo else None,
            robot_base=values["robot_base"],
        )
        state = dataclasses.replace(state, mode=mode)
        result = simulator.step(
            state, joint_command=command.contiguous(), base_twist=values["base_twist"]
        )
        return state, result
