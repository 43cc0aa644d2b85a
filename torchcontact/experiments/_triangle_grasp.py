"""The triangle-grasp tracking experiment: a parallel-jaw gripper grasps a triangle that a
camera loses sight of; the contact RBPF is compared with a particle filter through the
simulator, an EKF and held vision.

A triangle (8 cm sides, 0.2 kg) rests on a table in a vertical plane; two kinematic fingers
close on it from both sides (their twists are the control), push it into the middle of the
gripper, hold it and open again. A camera sees the triangle's pose with Gaussian noise except
while the fingers are close (occlusion: the measurement is NaN); a tactile array on the
triangle's edges reads contacts with false positives and negatives; the finger poses are known.

Estimators (:func:`run_estimators`), all batched over the trials:

1. ``rbpf``: :class:`~torchcontact.filters.PlanarContactModel` + :class:`~torchcontact.filters.RBPF`
   over contact modes (table and transition from training rollouts), tactile likelihood as the
   extra per-mode evidence; after every step each particle's Gaussian is projected out of the
   bodies its mean penetrates (:func:`~torchcontact.filters.project_out_of_contact`);
2. ``pf``: :class:`~torchcontact.filters.SimulatorParticleFilter` over pose and twist with
   process noise, weighted by vision and tactile, with as many particles as fit in the RBPF's
   measured (CPU) time per step (:func:`calibrate_pf`);
3. ``pf_same_n``: the same particle filter with the RBPF's particle count (slower; reference);
4. ``ekf``: an EKF with constant-velocity dynamics (contact ignored), vision updates;
5. ``vision``: the last measurement, held during the occlusion.

Ground truth is the simulator (exact LCP fallback), with per-trial friction and initial pose.
``train/triangle_grasp.py`` runs it from the command line and writes the results.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from torchcontact._checks import check_int, check_real
from torchcontact.filters import (
    RBPF,
    Gaussian,
    KinematicControl,
    PlanarContactModel,
    SimulatorParticleFilter,
    collect_modes,
    ekf_predict,
    ekf_update,
    empirical_transition,
    project_out_of_contact,
    wrap_angle,
)
from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import UNSOLVED, Body, Rollout, Scene, SceneState, Simulator, StepResult
from torchcontact.states import TactileArray, mode_ids, object_contacts, touch_codes

F64 = torch.float64
SIDE = 0.08  # triangle side, metres
HEIGHT = SIDE * math.sqrt(3.0) / 2.0
FINGER = (0.01, 0.03)  # finger width, height
FINGER_Y = 0.03  # finger centre above the table
H = 0.01  # time step, seconds
FINGER_OPEN = 0.07  # |x| of the open fingers, metres
#: The estimators, in the order :func:`run_estimators` runs them.
GRASP_METHODS = ("rbpf", "pf", "pf_same_n", "ekf", "vision")
BASELINES = ("pf", "ekf", "vision")  # the targets' baselines (pf gets the RBPF's time per step)
PF_NOISE_STD = (2e-4, 2e-4, 2e-3, 0.02, 0.02, 0.2)  # per step: x, y, θ, vx, vy, ω
CALIBRATION_PARTICLES = (8, 64)  # plain-PF particle counts timed to fit time(N) = a + b N
CALIBRATION_ROUNDS = 2  # PF runs at fitted particle counts, at most
CALIBRATION_TOLERANCE = 0.1  # relative miss of the RBPF's CPU time that ends the calibration
MIN_STEPS = 8  # time steps that give every phase of grasp_schedule() at least one step
#: Each particle filter draws from the seed ``settings.seed`` plus its offset.
FILTER_SEED_OFFSETS = {"rbpf": 2, "pf": 3, "pf_same_n": 4}


@dataclass(frozen=True)
class TriangleGrasp:
    """Settings of the triangle-grasp tracking experiment."""

    seed: int = 0
    """seed of the evaluation trials"""
    trials: int = 64
    """evaluation trials"""
    train_trials: int = 64
    """training rollouts for the mode table and transition"""
    steps: int = 80
    """time steps per trial (h=0.01)"""
    rbpf_particles: int = 200
    """RBPF particles"""
    pf_particles: int = 0
    """plain PF particles; 0: as many as fit in the RBPF's time per step"""
    reference_pf: bool = True
    """also run the plain PF with the RBPF's particle count"""
    rbpf_pose_noise: float = 1e-4
    """RBPF process noise std of x, y (m) and θ (rad) per step"""
    rbpf_twist_noise: float = 3e-3
    """RBPF process noise std of vx, vy (m/s) per step; ω gets 10x (rad/s)"""
    gap_sigma: float = 1e-4
    """std (m) of the RBPF's zero-gap projection; 0 disables the projection"""
    vision_sigma: float = 0.004
    """vision position noise std, metres"""
    vision_sigma_theta: float = 0.03
    """vision angle noise std, radians"""
    false_positive: float = 0.05
    """tactile FP rate"""
    false_negative: float = 0.1
    """tactile FN rate"""
    friction_low: float = 0.4
    """min true friction"""
    friction_high: float = 0.6
    """max true friction"""
    friction_model: float = 0.5
    """friction assumed by the filters"""
    x_offset: float = 0.012
    """max |initial x offset| of the triangle, metres"""
    tilt: float = 0.15
    """max |initial rotation| of the triangle, radians"""

    def check(self) -> None:
        """Check every setting before any work (``rbpf_particles >= K`` can only be checked
        once the training rollouts have given the number of modes K).

        Raises:
            ValueError: a setting is out of range; the message names it and its range.
        """
        for name in ("trials", "train_trials", "rbpf_particles"):
            check_int(name, getattr(self, name), low=1)
        check_int("seed", self.seed, low=0)
        check_int("steps", self.steps, low=MIN_STEPS, why="every phase of the grasp schedule")
        check_int("pf_particles", self.pf_particles, low=0)
        for name in ("rbpf_pose_noise", "rbpf_twist_noise", "vision_sigma", "vision_sigma_theta"):
            check_real(name, getattr(self, name), low=0.0, low_open=True)
        for name in ("gap_sigma", "friction_model", "x_offset", "tilt"):
            check_real(name, getattr(self, name), low=0.0)
        for name in ("false_positive", "false_negative"):
            check_real(name, getattr(self, name), low=0.0, high=1.0, high_open=True)
        check_real("friction_low", self.friction_low, low=0.0)
        check_real("friction_high", self.friction_high, low=self.friction_low)

    def vision_std(self) -> Tensor:
        """``(3,)`` float64 vision noise std of ``(x, y, θ)``."""
        return torch.tensor([self.vision_sigma] * 2 + [self.vision_sigma_theta], dtype=F64)


# ----------------------------------------------------------------------------------------------
# scene and data


def triangle_scene(friction: float | Tensor) -> Scene:
    """Table, triangle (dynamic) and two kinematic fingers; ``friction`` float or ``(B,)``."""
    return Scene(
        bodies=(
            Body("table", HalfPlane.ground(), kind="static"),
            Body("triangle", Polygon.triangle(SIDE, HEIGHT), mass=0.2),
            Body("left", Polygon.box(*FINGER), kind="kinematic"),
            Body("right", Polygon.box(*FINGER), kind="kinematic"),
        ),
        friction=friction,
        h=H,
    )


def triangle_tactile_array(settings: TriangleGrasp) -> TactileArray:
    """Three sensors per edge of the triangle (body frame), 9 in all."""
    vertices = Polygon.triangle(SIDE, HEIGHT).vertices
    positions, normals = [], []
    for i in range(3):
        a, b = vertices[i], vertices[(i + 1) % 3]
        edge = b - a
        normal = torch.stack([edge[1], -edge[0]]) / edge.norm()
        for s in (0.2, 0.5, 0.8):
            positions.append(a + s * edge)
            normals.append(normal)
    return TactileArray(
        positions=torch.stack(positions),
        normals=torch.stack(normals),
        radius=0.02,
        half_angle=0.6,
        false_positive=settings.false_positive,
        false_negative=settings.false_negative,
    )


def grasp_schedule(steps: int) -> tuple[slice, slice, Tensor]:
    """Closing and opening step ranges and the ``(T,)`` bool occlusion mask.

    Every phase (approach, closing, hold, opening, occlusion) has a step from
    ``steps >= MIN_STEPS`` on.
    """
    close = slice(steps // 8, steps // 2)
    opening = slice(int(0.78 * steps), steps)
    occluded = torch.zeros(steps, dtype=torch.bool)
    occluded[steps // 4 : int(0.85 * steps)] = True
    return close, opening, occluded


def grasp_controls(steps: int, batch: int) -> tuple[Tensor, Tensor]:
    """The fingers' open poses ``(B, 2, 3)`` and their twists ``(T, B, 2, 3)`` (world frame)
    over :func:`grasp_schedule`: they close at constant speed to a width 1.5 mm above the
    triangle's width at their lower corners, hold, and open at 0.1 m/s."""
    bottom = FINGER_Y - FINGER[1] / 2
    target = SIDE / 2 * (1 - bottom / HEIGHT) + 0.0015 + FINGER[0] / 2
    q_kin = torch.tensor([[-FINGER_OPEN, FINGER_Y, 0.0], [FINGER_OPEN, FINGER_Y, 0.0]], dtype=F64)
    q_kin = q_kin.expand(batch, 2, 3).clone()
    close, opening, _ = grasp_schedule(steps)
    n_close = close.stop - close.start
    speed = (FINGER_OPEN - target) / (n_close * H)
    controls = torch.zeros(steps, batch, 2, 3, dtype=F64)
    controls[close, :, 0, 0], controls[close, :, 1, 0] = speed, -speed
    controls[opening, :, 0, 0], controls[opening, :, 1, 0] = -0.1, 0.1
    return q_kin, controls


def simulate_grasps(
    settings: TriangleGrasp, batch: int, seed: int
) -> tuple[Scene, Rollout, Tensor, Tensor]:
    """Simulate ``batch`` grasps with random pose, tilt and friction.

    The triangle is dropped from 0.1 mm with a random tilt (``settings.tilt``) and offset
    (``settings.x_offset``), falls flat and is pushed towards the middle by the closing fingers.

    Returns:
        The batched scene, the rollout (batch ``B``), the controls ``(T, B, 2, 3)`` and the
        friction ``(B,)``.

    Raises:
        RuntimeError: a trial had a step that no LCP solver could solve.
    """
    gen = torch.Generator().manual_seed(seed)
    T = settings.steps
    x0 = (2 * torch.rand(batch, generator=gen, dtype=F64) - 1) * settings.x_offset
    theta = (2 * torch.rand(batch, generator=gen, dtype=F64) - 1) * settings.tilt
    mu = settings.friction_low + (settings.friction_high - settings.friction_low) * torch.rand(
        batch, generator=gen, dtype=F64
    )
    vertices = Polygon.triangle(SIDE, HEIGHT).vertices
    cos, sin = torch.cos(theta), torch.sin(theta)
    lowest = (sin[:, None] * vertices[:, 0] + cos[:, None] * vertices[:, 1]).min(-1).values
    q = torch.stack([x0, 1e-4 - lowest, theta], -1)[:, None]
    q_kin, controls = grasp_controls(T, batch)
    scene = triangle_scene(mu)
    simulator = Simulator(scene)
    state = simulator.initial_state(q=q, q_kinematic=q_kin)
    rollout = simulator.rollout(state, steps=T, controls=controls, strict=False)
    failed = (rollout.solver == UNSOLVED).any(0)
    if bool(failed.any()):
        raise RuntimeError(f"{int(failed.sum())} trials had unsolved LCP steps (seed {seed})")
    return scene, rollout, controls, mu


def grasp_tactile_readings(
    scene: Scene, rollout: Rollout, tactile: TactileArray, gen: torch.Generator
) -> Tensor:
    """``(T, B, S)`` noisy tactile readings of the true contacts at the start of each step."""
    contacts = object_contacts(
        scene,
        body="triangle",
        q=rollout.q[:-1],
        points=rollout.points,
        normals=rollout.normals,
        pn=rollout.pn,
        mode=rollout.mode,
        active=rollout.active,
    )
    return tactile.sample(tactile.triggered(contacts), generator=gen)


@dataclass(frozen=True, eq=False)
class GraspTrials:
    """Simulated evaluation trials, their measurements and what the filters learn beforehand.

    Attributes:
        scene: the true scene (per-trial friction, batch ``B``).
        truth: the ground-truth rollout, ``T`` steps of batch ``B``.
        controls: ``(T, B, 2, 3)`` finger twists.
        y: ``(T, B, 3)`` vision poses after each step, NaN while occluded.
        readings: ``(T, B, S)`` bool tactile readings at the start of each step.
        tactile: the tactile array.
        prior: the filters' initial belief over pose and twist, batch ``B``.
        occluded: ``(T,)`` bool occlusion mask.
        table: ``(K, L)`` long mode table (per-slot modes) from the training rollouts.
        transition: ``(K, K)`` empirical mode transition from the training rollouts.
        true_ids: ``(T, B)`` long row of each true mode in ``table``; ``K`` where absent.
    """

    scene: Scene
    truth: Rollout
    controls: Tensor
    y: Tensor
    readings: Tensor
    tactile: TactileArray
    prior: Gaussian
    occluded: Tensor
    table: Tensor
    transition: Tensor
    true_ids: Tensor

    @property
    def steps(self) -> int:
        """``T``."""
        return int(self.y.shape[0])

    @property
    def batch(self) -> int:
        """``B``."""
        return int(self.y.shape[1])


def grasp_mode_table(settings: TriangleGrasp) -> tuple[Tensor, Tensor]:
    """The ``(K, L)`` mode table and the ``(K, K)`` mode transition of the filters, from
    ``settings.train_trials`` training rollouts (seed ``10_000 + settings.seed``)."""
    _, train, _, _ = simulate_grasps(settings, settings.train_trials, seed=10_000 + settings.seed)
    table, train_ids, _ = collect_modes(train.mode)
    transition = empirical_transition(train_ids, table.shape[0], smoothing=0.1)
    return table, transition


def grasp_trials(settings: TriangleGrasp) -> GraspTrials:
    """Training rollouts (mode table, transition), evaluation trials and their measurements."""
    table, transition = grasp_mode_table(settings)
    scene, truth, controls, _ = simulate_grasps(settings, settings.trials, seed=settings.seed)
    T, B = settings.steps, settings.trials
    gen = torch.Generator().manual_seed(settings.seed + 1)
    _, _, occluded = grasp_schedule(T)
    y = truth.q[1:, :, 0] + settings.vision_std() * torch.randn(T, B, 3, generator=gen, dtype=F64)
    y[occluded] = math.nan
    tactile = triangle_tactile_array(settings)
    readings = grasp_tactile_readings(scene, truth, tactile, gen)
    prior_std = torch.tensor([0.005, 0.005, 0.05, 0.01, 0.01, 0.1], dtype=F64)
    noisy = truth.q[0, :, 0] + prior_std[:3] * torch.randn(B, 3, generator=gen, dtype=F64)
    prior_mean = torch.cat([noisy, torch.zeros(B, 3, dtype=F64)], -1)
    prior = Gaussian(prior_mean, torch.diag(prior_std.pow(2)).expand(B, 6, 6).contiguous())
    return GraspTrials(
        scene=scene,
        truth=truth,
        controls=controls,
        y=y,
        readings=readings,
        tactile=tactile,
        prior=prior,
        occluded=occluded,
        table=table,
        transition=transition,
        true_ids=mode_ids(truth.mode, table),
    )


def grasp_contact_model(settings: TriangleGrasp, trials: GraspTrials) -> PlanarContactModel:
    """The RBPF's switching model: assumed friction, process noise, vision, learned modes."""
    K = trials.table.shape[0]
    pose, twist = settings.rbpf_pose_noise, settings.rbpf_twist_noise
    noise_std = torch.tensor([pose] * 3 + [twist, twist, 10 * twist], dtype=F64)
    return PlanarContactModel(
        scene=triangle_scene(settings.friction_model),
        modes=trials.table,
        Q=torch.diag(noise_std.pow(2)),
        R=torch.diag(settings.vision_std().pow(2)),
        transition=trials.transition,
        initial=torch.full((K,), 1.0 / K, dtype=F64),
    )


# ----------------------------------------------------------------------------------------------
# estimators


def run_rbpf(
    model: PlanarContactModel,
    trials: GraspTrials,
    settings: TriangleGrasp,
    gen: torch.Generator,
    trial: int = 0,
) -> dict[str, Tensor]:
    """RBPF over contact modes with tactile evidence and the zero-gap projection.

    Returns:
        ``pose (T, B, 3)`` mixture-mean poses, ``marginals (T, B, K)`` filtered mode
        marginals, ``cloud (T, N, 3)`` and ``cloud_weight (T, N)`` particle means and weights
        of trial ``trial``, and ``log_evidence (B,)`` the filter's ``log p(y, readings)``
        (differentiable in the model's parameters).
    """
    rbpf = RBPF(model, settings.rbpf_particles, proposal="all_modes")
    belief = rbpf.init(trials.prior)
    q_kinematic = trials.truth.q_kinematic
    poses, marginals, clouds, cloud_weights = [], [], [], []
    for t in range(trials.steps):
        control = KinematicControl(q=q_kinematic[t], v=trials.controls[t])
        extra = model.tactile_log_likelihood(
            trials.tactile, trials.readings[t], pose=belief.mean()[..., :3], control=control
        )
        belief = rbpf.step(
            belief, trials.y[t], extra_log_likelihood=extra, control=control, generator=gen
        )
        if settings.gap_sigma > 0:
            belief = project_out_of_contact(
                belief, model.scene, q_kinematic[t + 1], gap_sigma=settings.gap_sigma
            )
        poses.append(belief.mean()[..., :3])
        marginals.append(belief.mode_marginals())
        clouds.append(belief.gaussians.mean[trial, :, :3].clone())
        cloud_weights.append(belief.log_weights[trial].exp())
    return {
        "pose": torch.stack(poses),
        "marginals": torch.stack(marginals),
        "cloud": torch.stack(clouds),
        "cloud_weight": torch.stack(cloud_weights),
        "log_evidence": belief.log_evidence,
    }


def _tactile_term(
    scene: Scene, tactile: TactileArray, readings: Tensor
) -> Callable[[SceneState, StepResult], Tensor]:
    """The PF's ``extra_log_likelihood``: ``log p(readings)`` ``(B, N)`` of the ``(B, S)``
    tactile readings given each particle's simulated contacts."""

    def log_likelihood(state: SceneState, result: StepResult) -> Tensor:
        contacts = object_contacts(
            scene,
            body="triangle",
            q=state.q,
            points=result.geometry.points,
            normals=result.geometry.normals,
            pn=result.pn,
            mode=result.mode,
            active=result.geometry.active,
        )
        return tactile.reading_log_likelihood(readings[:, None], tactile.triggered(contacts))

    return log_likelihood


def run_pf(
    trials: GraspTrials,
    settings: TriangleGrasp,
    num_particles: int,
    gen: torch.Generator,
    trial: int = 0,
) -> dict[str, Tensor]:
    """:class:`~torchcontact.filters.SimulatorParticleFilter` over pose and twist (batch
    ``B × N``).

    Particles are stepped by the simulator with the assumed friction, perturbed by
    :data:`PF_NOISE_STD`, weighted by the tactile readings of their simulated contacts and by
    vision, and resampled (systematic) every step.

    Returns:
        Like :func:`run_rbpf`; the marginals are the weighted histogram of the particles'
        simulated modes over the mode table.
    """
    scene = triangle_scene(settings.friction_model)
    pf = SimulatorParticleFilter(
        scene,
        num_particles,
        process_std=torch.tensor(PF_NOISE_STD, dtype=F64),
        measurement_std=settings.vision_std(),
    )
    tactile, table = trials.tactile, trials.table
    belief = pf.init(trials.prior, generator=gen)
    poses, marginals, clouds, cloud_weights = [], [], [], []
    for t in range(trials.steps):
        control = KinematicControl(q=trials.truth.q_kinematic[t], v=trials.controls[t])
        belief = pf.step(
            belief,
            trials.y[t],
            control=control,
            extra_log_likelihood=_tactile_term(scene, tactile, trials.readings[t]),
            generator=gen,
        )
        weights = belief.weights()
        poses.append(belief.mean()[..., :3])
        ids = mode_ids(belief.modes, table)
        hist = torch.zeros(trials.batch, table.shape[0] + 1, dtype=F64)
        marginals.append(hist.scatter_add_(1, ids, weights)[:, :-1])
        clouds.append(belief.particles[trial, :, :3].clone())
        cloud_weights.append(weights[trial].clone())
    return {
        "pose": torch.stack(poses),
        "marginals": torch.stack(marginals),
        "cloud": torch.stack(clouds),
        "cloud_weight": torch.stack(cloud_weights),
    }


def run_ekf(settings: TriangleGrasp, trials: GraspTrials) -> dict[str, Tensor]:
    """Constant-velocity EKF (contact ignored); vision updates only."""

    def f(x: Tensor) -> Tensor:
        return torch.cat([x[:3] + H * x[3:], x[3:]])

    def measure(x: Tensor) -> Tensor:
        return x[:3]

    Q = torch.diag(torch.tensor([1e-7, 1e-7, 1e-5, 1e-3, 1e-3, 1e-1], dtype=F64))
    R = torch.diag(settings.vision_std().pow(2))
    g = trials.prior
    poses = []
    for t in range(trials.steps):
        g = ekf_predict(g, f, Q=Q)
        g, _ = ekf_update(g, trials.y[t], measure, R=R)
        poses.append(g.mean[..., :3])
    return {"pose": torch.stack(poses)}


def run_vision(trials: GraspTrials) -> dict[str, Tensor]:
    """Last seen measurement (the prior mean before the first)."""
    last = trials.prior.mean[..., :3]
    poses = []
    for t in range(trials.steps):
        seen = torch.isfinite(trials.y[t]).all(-1, keepdim=True)
        last = torch.where(seen, trials.y[t], last)
        poses.append(last)
    return {"pose": torch.stack(poses)}


@dataclass(frozen=True)
class Timing:
    """Seconds one estimator took: ``wall`` (elapsed) and ``cpu`` (this process's CPU time).

    On an idle machine with one torch thread the two agree; on a shared one the wall time also
    counts the waits for a core, so the CPU time is the steadier measure of the work done.
    """

    wall: float
    cpu: float


def timed(fn: Callable[[], dict[str, Tensor]]) -> tuple[dict[str, Tensor], Timing]:
    """``fn()`` and the time it took."""
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, Timing(time.perf_counter() - wall, time.process_time() - cpu)


def calibrate_pf(
    trials: GraspTrials, settings: TriangleGrasp, target: float, seed: int
) -> tuple[int, dict[str, Tensor], Timing, dict[int, float]]:
    """Run the plain PF with as many particles as fit in ``target`` CPU seconds.

    Times the PF on all trials with each of :data:`CALIBRATION_PARTICLES` particles, fits
    ``time(N) = a + b N`` through the two measured counts whose times are closest to the
    target, runs the PF with the solution (at least 2 particles) and, while that run misses
    the target by more than :data:`CALIBRATION_TOLERANCE`, refits and runs once more (at
    most :data:`CALIBRATION_ROUNDS` runs). The run closest to the target is kept.

    Returns:
        The particle count, the PF's output and timing with it, and every measured
        ``{particles: CPU seconds}``.
    """
    measured: dict[int, float] = {}
    runs: dict[int, tuple[dict[str, Tensor], Timing]] = {}

    def measure(n: int) -> None:
        runs[n] = timed(lambda: run_pf(trials, settings, n, torch.Generator().manual_seed(seed)))
        measured[n] = runs[n][1].cpu

    def solve() -> int:
        (n0, t0), (n1, t1) = sorted(measured.items(), key=lambda item: abs(item[1] - target))[:2]
        slope = max((t1 - t0) / (n1 - n0), 1e-9)
        return max(2, round(n0 + (target - t0) / slope))

    for n in CALIBRATION_PARTICLES:
        measure(n)
    for _ in range(CALIBRATION_ROUNDS):
        n = solve()
        if n in measured:
            break
        measure(n)
        if abs(measured[n] - target) <= CALIBRATION_TOLERANCE * target:
            break
    candidates = [n for n in measured if n not in CALIBRATION_PARTICLES] or list(measured)
    best = min(candidates, key=lambda n: abs(measured[n] - target))
    return best, *runs[best], measured


@dataclass(frozen=True, eq=False)
class EstimatorRuns:
    """What :func:`run_estimators` gives.

    Attributes:
        outputs: ``{method: output of run_rbpf / run_pf / run_ekf / run_vision}``.
        timings: ``{method: Timing}``.
        particles: ``{method: particle count}`` of the particle filters.
        calibration: ``{particles: CPU seconds}`` of :func:`calibrate_pf` (empty when
            ``settings.pf_particles`` was given).
    """

    outputs: dict[str, dict[str, Tensor]]
    timings: dict[str, Timing]
    particles: dict[str, int]
    calibration: dict[int, float]


def run_estimators(
    settings: TriangleGrasp,
    trials: GraspTrials,
    model: PlanarContactModel,
    *,
    done: Callable[[str], None] | None = None,
) -> EstimatorRuns:
    """Run every estimator of :data:`GRASP_METHODS` on the trials, timed.

    The RBPF draws from the seed ``settings.seed + 2``, the plain PF from ``+ 3`` (also its
    calibration runs), ``pf_same_n`` (when ``settings.reference_pf``) from ``+ 4``
    (:data:`FILTER_SEED_OFFSETS`).

    Args:
        settings: the settings.
        trials: the trials of :func:`grasp_trials`.
        model: the RBPF's model, :func:`grasp_contact_model`.
        done: called with ``"rbpf"``, ``"pf"``, ``"pf_same_n"`` (also when skipped) and
            ``"ekf+vision"`` as each finishes (e.g. a progress bar).

    Returns:
        The outputs, timings, particle counts and the PF's calibration.
    """

    def generator(method: str) -> torch.Generator:
        return torch.Generator().manual_seed(settings.seed + FILTER_SEED_OFFSETS[method])

    def report(stage: str) -> None:
        if done is not None:
            done(stage)

    outputs: dict[str, dict[str, Tensor]] = {}
    timings: dict[str, Timing] = {}
    particles = {"rbpf": settings.rbpf_particles}
    outputs["rbpf"], timings["rbpf"] = timed(
        lambda: run_rbpf(model, trials, settings, generator("rbpf"))
    )
    report("rbpf")
    calibration: dict[int, float] = {}
    if settings.pf_particles == 0:
        particles["pf"], outputs["pf"], timings["pf"], calibration = calibrate_pf(
            trials, settings, timings["rbpf"].cpu, settings.seed + FILTER_SEED_OFFSETS["pf"]
        )
    else:
        particles["pf"] = settings.pf_particles
        outputs["pf"], timings["pf"] = timed(
            lambda: run_pf(trials, settings, settings.pf_particles, generator("pf"))
        )
    report("pf")
    if settings.reference_pf:
        particles["pf_same_n"] = settings.rbpf_particles
        outputs["pf_same_n"], timings["pf_same_n"] = timed(
            lambda: run_pf(trials, settings, settings.rbpf_particles, generator("pf_same_n"))
        )
    report("pf_same_n")
    outputs["ekf"], timings["ekf"] = timed(lambda: run_ekf(settings, trials))
    outputs["vision"], timings["vision"] = timed(lambda: run_vision(trials))
    report("ekf+vision")
    return EstimatorRuns(outputs, timings, particles, calibration)


# ----------------------------------------------------------------------------------------------
# evaluation


def evaluate_tracking(
    trials: GraspTrials, outputs: dict[str, dict[str, Tensor]]
) -> tuple[dict[str, dict[str, float]], dict[str, tuple[Tensor, Tensor]]]:
    """Pose errors and contact-state scores of every method.

    Returns:
        ``{method: {metric: value}}`` (RMSE over all steps and trials and over the occluded
        steps; for the particle filters the MAP mode accuracy, the MAP accuracy of the set of
        touching bodies and the mean log-probability of the true mode) and ``{method: (position
        error (T, B), angle error (T, B))}``.
    """
    true_pose = trials.truth.q[1:, :, 0]
    occluded = trials.occluded
    table_codes = touch_codes(trials.scene, trials.table, body="triangle")  # (K,)
    true_codes = touch_codes(trials.scene, trials.truth.mode, body="triangle")  # (T, B)
    metrics: dict[str, dict[str, float]] = {}
    errors: dict[str, tuple[Tensor, Tensor]] = {}
    for method, out in outputs.items():
        diff = out["pose"] - true_pose
        pos = diff[..., :2].pow(2).sum(-1)
        ang = wrap_angle(diff[..., 2]).pow(2)
        errors[method] = (pos.sqrt(), ang.sqrt())
        row = {
            "pos_rmse_mm": 1e3 * float(pos.mean().sqrt()),
            "pos_rmse_occ_mm": 1e3 * float(pos[occluded].mean().sqrt()),
            "theta_rmse_deg": math.degrees(float(ang.mean().sqrt())),
            "theta_rmse_occ_deg": math.degrees(float(ang[occluded].mean().sqrt())),
        }
        if "marginals" in out:
            marg = out["marginals"]
            row["mode_accuracy"] = float((marg.argmax(-1) == trials.true_ids).double().mean())
            by_code = marg.new_zeros(*marg.shape[:-1], int(table_codes.max()) + 1)
            by_code.scatter_add_(-1, table_codes.expand_as(marg), marg)
            row["touch_accuracy"] = float((by_code.argmax(-1) == true_codes).double().mean())
            padded = torch.cat([marg, marg.new_zeros(*marg.shape[:-1], 1)], -1)
            p_true = padded.gather(-1, trials.true_ids[..., None]).squeeze(-1)
            row["mode_logprob"] = float(p_true.clamp_min(1e-12).log().mean())
        metrics[method] = row
    return metrics, errors


def grasp_summary(trials: GraspTrials, metrics: dict[str, dict[str, float]]) -> dict[str, Any]:
    """The RBPF's error ratios against the baselines, and sanity checks of the ground truth.

    Returns:
        ``ratio_pos_occ`` and ``ratio_theta_occ`` (RBPF RMSE during the occlusion over the
        best of :data:`BASELINES`), ``ratio_pos_occ_same_n`` and ``ratio_theta_occ_same_n``
        (over the PF with the RBPF's particle count, when it ran), ``table_size``,
        ``true_mode_in_table`` (fraction of steps), ``min_height`` and ``min_vertex_height``
        (metres, over all ground-truth steps).
    """
    K = trials.table.shape[0]
    rbpf = metrics["rbpf"]
    summary: dict[str, Any] = {
        "table_size": K,
        "true_mode_in_table": float((trials.true_ids < K).double().mean()),
        "min_height": float(trials.truth.q[..., 0, 1].min()),
        "min_vertex_height": min_vertex_height(trials.truth),
    }
    for key, metric in (("pos_occ", "pos_rmse_occ_mm"), ("theta_occ", "theta_rmse_occ_deg")):
        best = min(metrics[m][metric] for m in BASELINES if m in metrics)
        summary[f"ratio_{key}"] = rbpf[metric] / best
        if "pf_same_n" in metrics:
            summary[f"ratio_{key}_same_n"] = rbpf[metric] / metrics["pf_same_n"][metric]
    return summary


def min_vertex_height(truth: Rollout) -> float:
    """Lowest height of any triangle vertex over all trials and steps (penetration check)."""
    vertices = Polygon.triangle(SIDE, HEIGHT).vertices
    q = truth.q[..., 0, :]
    height = (
        q[..., 1:2]
        + torch.sin(q[..., 2:3]) * vertices[:, 0]
        + torch.cos(q[..., 2:3]) * vertices[:, 1]
    )
    return float(height.min())


TABLE_COLUMNS = (
    ("particles", "particles", "{:.0f}"),
    ("pos_rmse_mm", "pos RMSE (mm)", "{:.3f}"),
    ("pos_rmse_occ_mm", "pos RMSE occl. (mm)", "{:.3f}"),
    ("theta_rmse_deg", "θ RMSE (deg)", "{:.3f}"),
    ("theta_rmse_occ_deg", "θ RMSE occl. (deg)", "{:.4f}"),
    ("mode_accuracy", "mode acc.", "{:.3f}"),
    ("touch_accuracy", "touch acc.", "{:.3f}"),
    ("mode_logprob", "log p(true mode)", "{:.3f}"),
    ("ms_per_step", "wall ms / step", "{:.1f}"),
    ("cpu_ms_per_step", "CPU ms / step", "{:.1f}"),
    ("cpu_ms_per_step_per_trial", "CPU ms / step / trial", "{:.2f}"),
)


def tracking_table(metrics: dict[str, dict[str, float]]) -> str:
    """The metrics as a markdown table, one row per method (columns that no row has are left
    out; a cell a row lacks reads ``–``)."""
    columns = [c for c in TABLE_COLUMNS if any(c[0] in row for row in metrics.values())]
    lines = [
        "| method | " + " | ".join(title for _, title, _ in columns) + " |",
        "|---" + "|--:" * len(columns) + "|",
    ]
    for method, row in metrics.items():
        cells = [
            fmt.format(row[key]) if key in row and (key != "particles" or row[key]) else "–"
            for key, _, fmt in columns
        ]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
