"""Fitting the ground friction and the camera noise of the triangle grasp from the RBPF's evidence.

Every trial is one set-up with its own true parameters (the friction of the triangle on the
table ``μ``, the friction of the fingers on the triangle ``μ_f`` and the camera noise ``σ``),
recorded over a few grasps: the triangle is launched along the table towards the middle of
the open gripper at 0.4–0.5 m/s, slides to a stop in view of the camera, and the fingers close
on it, hold it and open again (the grasp of :func:`~torchcontact.experiments.grasp_trials`,
with its occlusion, tactile array and RBPF). The filter's evidence ``log p(y, readings | μ,
σ)``, summed over the trial's grasps, is maximized by the same three methods as the sliding box
(:data:`~torchcontact.experiments.FITTERS`).

Identifiability: the fingers are driven kinematically (their motion is given, the forces they
apply are not known), so a mass scales gravity, friction and the fingers' impulses alike and
is not identified; the triangle does not rotate once it lies flat, so neither is the ratio of
its inertia to its mass. The triangle's slide identifies ``μ`` (its deceleration is ``μ g``)
and the scatter of the measurements identifies ``σ``. ``μ_f`` is not identified: a finger
that pushes the triangle along the table, or holds it, sticks to it (their relative velocity
is zero), so ``μ_f`` only bounds contact forces that nothing measures. It is drawn per trial
(a nuisance that the fit must be insensitive to) and the filter keeps its nominal value.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from torchcontact.experiments._triangle_grasp import (
    F64,
    HEIGHT,
    SIDE,
    GraspTrials,
    TriangleGrasp,
    grasp_contact_model,
    grasp_controls,
    grasp_schedule,
    grasp_tactile_readings,
    run_rbpf,
    triangle_scene,
    triangle_tactile_array,
)
from torchcontact.filters import (
    Gaussian,
    PlanarContactModel,
    collect_modes,
    empirical_transition,
)
from torchcontact.geometry import Polygon
from torchcontact.sim import UNSOLVED, Rollout, Scene, Simulator
from torchcontact.states import mode_ids

#: Camera noise of the angle (rad) per metre of the position's (that of the grasp experiment:
#: 0.03 rad with 4 mm).
ANGLE_PER_POSITION = 7.5
#: Filter seed offset of a trial's evidence (common random numbers for every method).
EVIDENCE_SEED = 2


@dataclass(frozen=True)
class GraspFit:
    """Settings of the triangle-grasp fitting experiment.

    Attributes:
        seed: seed of the trials' true parameters and logs.
        rounds: number of trials (true parameters drawn per trial; a run resumed with more
            rounds adds trials).
        grasps: grasps recorded per trial (the evidence sums over them).
        steps: time steps per grasp (10 ms).
        particles: RBPF particles (all-modes proposal).
        train_trials: simulated grasps (nominal parameters) for the filter's mode table and
            transition.
        fit_steps: the filter reads the first ``fit_steps`` steps of every grasp (the launch,
            the slide and the fingers' approach, in view of the camera: what depends on the
            ground friction and the camera noise).
        mu_range: range of the true ground friction and of the grid and CMA-ES search.
        finger_mu_range: range of the true finger friction (not fitted).
        finger_mu_model: finger friction assumed by the filter.
        sigma_mm_range: range of the true camera noise (position, mm; the angle's is
            7.5 mrad per mm) and of the searches.
        speed_range: range of the triangle's launch speed, m/s.
        start_offset: distance of the triangle from the middle of the gripper at the launch,
            metres.
        speed_std: standard deviation of the filter's prior of the launch speed (the
            launcher's), m/s.
        pose_noise: the filter's process noise std of ``x``, ``y`` (m) and ``θ`` (rad) per
            step.
        twist_noise: the filter's process noise std of ``vx``, ``vy`` (m/s) per step; ``ω``
            gets 10 times it (rad/s).
        inconsistency_penalty: the model's penalty of modes inconsistent at the
            linearization point (that of the grasp experiment; 0: off).
        grid_points: grid points per parameter.
        cma_evaluations: evidence evaluations allowed to CMA-ES.
    """

    seed: int = 0
    rounds: int = 16
    grasps: int = 8
    steps: int = 80
    particles: int = 16
    train_trials: int = 16
    fit_steps: int = 24
    mu_range: tuple[float, float] = (0.25, 0.6)
    finger_mu_range: tuple[float, float] = (0.3, 0.7)
    finger_mu_model: float = 0.5
    sigma_mm_range: tuple[float, float] = (1.0, 4.0)
    speed_range: tuple[float, float] = (0.4, 0.5)
    start_offset: float = 0.025
    speed_std: float = 0.005
    pose_noise: float = 1e-4
    twist_noise: float = 1e-3
    inconsistency_penalty: float = 5.0
    grid_points: int = 7
    cma_evaluations: int = 40


@dataclass(frozen=True, eq=False)
class GraspFitLogs:
    """One trial's simulated grasps and the filter that reads them.

    Attributes:
        mu: the true ground friction.
        finger_mu: the true finger friction.
        sigma_mm: the true camera noise (position, mm).
        trials: the grasps (batch ``B = grasps``) with their measurements, prior and the
            filter's mode table and transition.
        model: the RBPF's contact model (:func:`grasp_contact_model`, nominal friction and
            noise; the fit replaces the ground friction and the camera noise).
        grasp: the grasp experiment's settings the filter runs with.
    """

    mu: float
    finger_mu: float
    sigma_mm: float
    trials: GraspTrials
    model: PlanarContactModel
    grasp: TriangleGrasp


def grasp_fit_scene(mu: float | Tensor, finger_mu: float | Tensor) -> Scene:
    """The triangle-grasp scene with ground friction ``mu`` (triangle–table) and finger
    friction ``finger_mu`` (both fingers–triangle)."""
    return replace(triangle_scene(finger_mu), pair_friction={("triangle", "table"): mu})


def camera_std(sigma_mm: float | Tensor) -> Tensor:
    """``(3,)`` camera standard deviations: position ``σ`` mm, angle ``7.5 σ`` mrad."""
    scale = torch.tensor([1.0, 1.0, ANGLE_PER_POSITION], dtype=F64)
    return 1e-3 * torch.as_tensor(sigma_mm, dtype=F64) * scale


def launched_grasps(
    settings: GraspFit, scene: Scene, batch: int, generator: torch.Generator
) -> tuple[Rollout, Tensor, Tensor]:
    """Simulate ``batch`` grasps of a launched triangle in ``scene``.

    The triangle rests flat on the table ``settings.start_offset`` off the middle, on a random
    side, and is launched towards the middle at a speed drawn in ``settings.speed_range``;
    the fingers follow :func:`~torchcontact.experiments.grasp_schedule`.

    Returns:
        The rollout (batch ``B``), the controls ``(T, B, 2, 3)`` and the launch twists
        ``(B, 3)``.

    Raises:
        RuntimeError: a grasp had a step that no LCP solver could solve.
    """
    side = torch.where(torch.rand(batch, generator=generator, dtype=F64) < 0.5, -1.0, 1.0)
    low, high = settings.speed_range
    speed = low + (high - low) * torch.rand(batch, generator=generator, dtype=F64)
    lowest = float(Polygon.triangle(SIDE, HEIGHT).vertices[:, 1].min())
    zeros = torch.zeros(batch, dtype=F64)
    q = torch.stack([settings.start_offset * side, zeros - lowest, zeros], -1)[:, None]
    v = torch.stack([-side * speed, zeros, zeros], -1)
    q_kin, controls = grasp_controls(settings.steps, batch)
    simulator = Simulator(scene)
    state = simulator.initial_state(q=q, v=v[:, None], q_kinematic=q_kin)
    rollout = simulator.rollout(state, steps=settings.steps, controls=controls, strict=False)
    if bool((rollout.solver == UNSOLVED).any()):
        raise RuntimeError("a grasp had unsolved LCP steps")
    return rollout, controls, v


def grasp_fit_logs(settings: GraspFit, trial: int) -> GraspFitLogs:
    """Simulate one trial: ``μ``, ``μ_f`` and ``σ`` drawn uniformly in their ranges (seed
    ``1000 seed + trial``), ``settings.grasps`` grasps of a launched triangle, noisy camera
    poses (NaN while occluded) and tactile readings; the filter's mode table and transition
    from ``settings.train_trials`` grasps with the nominal parameters (seed ``10_000 + seed``,
    the same for every trial)."""
    generator = torch.Generator().manual_seed(1000 * settings.seed + trial)
    draw = torch.rand(3, generator=generator, dtype=F64)

    def uniform(bounds: tuple[float, float], u: Tensor) -> float:
        return bounds[0] + float(u) * (bounds[1] - bounds[0])

    mu = uniform(settings.mu_range, draw[0])
    finger_mu = uniform(settings.finger_mu_range, draw[1])
    sigma_mm = uniform(settings.sigma_mm_range, draw[2])
    grasp = TriangleGrasp(
        seed=settings.seed,
        trials=settings.grasps,
        steps=settings.steps,
        rbpf_particles=settings.particles,
        vision_sigma=1e-3 * sum(settings.sigma_mm_range) / 2,
        vision_sigma_theta=ANGLE_PER_POSITION * 1e-3 * sum(settings.sigma_mm_range) / 2,
        friction_model=settings.finger_mu_model,
        rbpf_pose_noise=settings.pose_noise,
        rbpf_twist_noise=settings.twist_noise,
    )
    nominal = grasp_fit_scene(sum(settings.mu_range) / 2, settings.finger_mu_model)
    table, transition = _mode_table(settings)
    scene = grasp_fit_scene(mu, finger_mu)
    truth, controls, launch = launched_grasps(settings, scene, settings.grasps, generator)
    T, B = settings.steps, settings.grasps
    _, _, occluded = grasp_schedule(T)
    noise = camera_std(sigma_mm) * torch.randn(T, B, 3, generator=generator, dtype=F64)
    y = truth.q[1:, :, 0] + noise
    y[occluded] = math.nan
    tactile = triangle_tactile_array(grasp)
    readings = grasp_tactile_readings(scene, truth, tactile, generator)
    # The filter knows the launch pose to a few mm and the launch twist (the launcher's) to
    # ``speed_std``.
    pose_std = torch.tensor([0.003, 0.001, 0.01], dtype=F64)
    twist_std = torch.tensor([settings.speed_std, 0.01, 0.1], dtype=F64)
    prior_pose = truth.q[0, :, 0] + pose_std * torch.randn(B, 3, generator=generator, dtype=F64)
    prior_twist = launch + twist_std * torch.randn(B, 3, generator=generator, dtype=F64)
    prior_std = torch.cat([pose_std, twist_std])
    prior = Gaussian(
        torch.cat([prior_pose, prior_twist], -1),
        torch.diag(prior_std.pow(2)).expand(B, 6, 6).contiguous(),
    )
    window = slice(0, min(settings.fit_steps, T))
    trials = GraspTrials(
        scene=scene,
        truth=truth,
        controls=controls[window],
        y=y[window],
        readings=readings[window],
        tactile=tactile,
        prior=prior,
        occluded=occluded[window],
        table=table,
        transition=transition,
        true_ids=mode_ids(truth.mode, table)[window],
    )
    model = replace(
        grasp_contact_model(grasp, trials),
        scene=nominal,
        inconsistency_penalty=settings.inconsistency_penalty,
    )
    return GraspFitLogs(
        mu=mu,
        finger_mu=finger_mu,
        sigma_mm=sigma_mm,
        trials=trials,
        model=model,
        grasp=grasp,
    )


@functools.lru_cache(maxsize=4)
def _mode_table(settings: GraspFit) -> tuple[Tensor, Tensor]:
    """The filter's ``(K, S)`` mode table and ``(K, K)`` transition from
    ``settings.train_trials`` launched grasps with the nominal parameters (seed
    ``10_000 + settings.seed``; kept for the next trial of the same settings)."""
    nominal = grasp_fit_scene(sum(settings.mu_range) / 2, settings.finger_mu_model)
    generator = torch.Generator().manual_seed(10_000 + settings.seed)
    train, _, _ = launched_grasps(settings, nominal, settings.train_trials, generator)
    table, train_ids, _ = collect_modes(train.mode)
    return table, empirical_transition(train_ids, table.shape[0], smoothing=0.1)


def grasp_fit_evidence(logs: GraspFitLogs) -> Callable[[dict[str, Tensor]], Tensor]:
    """``{"mu", "sigma_mm"} ↦ log p(y, readings | μ, σ)`` summed over the trial's grasps: the
    grasp experiment's RBPF (:func:`~torchcontact.experiments.run_rbpf`: all-modes proposal,
    tactile evidence, zero-gap projection) with a fixed generator, differentiable in both.
    ``"finger_mu"`` may be given too (else the model's nominal value)."""
    nominal_finger = logs.grasp.friction_model

    def log_evidence(theta: dict[str, Tensor]) -> Tensor:
        finger_mu = theta.get("finger_mu", nominal_finger)
        model = replace(
            logs.model,
            scene=grasp_fit_scene(theta["mu"], finger_mu),
            R=torch.diag(camera_std(theta["sigma_mm"]).pow(2)),
        )
        generator = torch.Generator().manual_seed(logs.grasp.seed + EVIDENCE_SEED)
        return run_rbpf(model, logs.trials, logs.grasp, generator)["log_evidence"].sum()

    return log_evidence
