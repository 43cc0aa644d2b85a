"""Tracking a triangle grasped by a parallel-jaw gripper: the contact RBPF against baselines.

A triangle (8 cm sides, 0.2 kg) rests on a table in a vertical plane; two kinematic fingers
close on it from both sides (their twists are the control), push it into the middle of the
gripper, hold it and open again. A camera sees the triangle's pose with Gaussian noise except
while the fingers are close (occlusion: the measurement is NaN); a tactile array on the
triangle's edges reads contacts with false positives and negatives; the finger poses are known.

Estimators, all batched over the trials:

1. ``rbpf``: :class:`~torchcontact.filters.PlanarContactModel` + :class:`~torchcontact.filters.RBPF`
   over contact modes (table and transition from training rollouts), tactile likelihood as the
   extra per-mode evidence; after every step each particle's Gaussian is projected out of
   the bodies its mean penetrates (:func:`project_out_of_contact`);
2. ``pf``: a bootstrap particle filter over pose and twist that propagates particles through the
   :class:`~torchcontact.sim.Simulator` with process noise, weighted by vision and tactile, with
   as many particles as fit in the RBPF's measured (CPU) time per step (:func:`calibrate_pf`);
3. ``pf_same_n``: the same particle filter with the RBPF's particle count (slower; reference);
4. ``ekf``: an EKF with constant-velocity dynamics (contact ignored), vision updates;
5. ``vision``: the last measurement, held during the occlusion.

Ground truth is the simulator (exact LCP fallback), with per-trial friction and initial pose.

Usage::

    python train/triangle_grasp.py --trials 64 --name triangle_grasp

writes TensorBoard logs, ``results.md``, ``metrics.json`` and the plots to a new run folder,
``runs/triangle_grasp__<seed>__<unix time>``.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import torch
import tyro
from matplotlib.figure import Figure
from torch import Tensor
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from torchcontact.experiments import check_int, check_name, check_real, new_run_dir
from torchcontact.filters import (
    RBPF,
    Gaussian,
    KinematicControl,
    PlanarContactModel,
    RBPFBelief,
    collect_modes,
    ekf_predict,
    ekf_update,
    empirical_transition,
    kf_update,
    resample,
    wrap_angle,
)
from torchcontact.geometry import (
    HalfPlane,
    Polygon,
)
from torchcontact.sim import (
    UNSOLVED,
    Body,
    Rollout,
    Scene,
    Simulator,
    draw_scene,
    penetration,
)
from torchcontact.states import TactileArray, object_contacts

F64 = torch.float64
SIDE = 0.08  # triangle side, metres
HEIGHT = SIDE * math.sqrt(3.0) / 2.0
FINGER = (0.01, 0.03)  # finger width, height
FINGER_Y = 0.03  # finger centre above the table
H = 0.01  # time step, seconds
FINGER_OPEN = 0.07  # |x| of the open fingers, metres
METHODS = ("rbpf", "pf", "pf_same_n", "ekf", "vision")
BASELINES = ("pf", "ekf", "vision")  # the targets' baselines (pf gets the RBPF's time per step)
PF_NOISE_STD = (2e-4, 2e-4, 2e-3, 0.02, 0.02, 0.2)  # per step: x, y, θ, vx, vy, ω
CALIBRATION_PARTICLES = (8, 64)  # plain-PF particle counts timed to fit time(N) = a + b N
CALIBRATION_ROUNDS = 2  # PF runs at fitted particle counts, at most
CALIBRATION_TOLERANCE = 0.1  # relative miss of the RBPF's CPU time that ends the calibration
MIN_STEPS = 8  # time steps that give every phase of schedule() at least one step


@dataclass
class Args:
    """Arguments of the triangle-grasp tracking experiment."""

    name: str = "triangle_grasp"
    """experiment name: the run writes to <out-dir>/<name>__<seed>__<unix time>"""
    out_dir: str = "runs"
    """parent of the run folders"""
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
    fast: bool = False
    """tiny budget (tests)"""


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


def tactile_array(args: Args) -> TactileArray:
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
        false_positive=args.false_positive,
        false_negative=args.false_negative,
    )


def schedule(steps: int) -> tuple[slice, slice, Tensor]:
    """Closing and opening step ranges and the ``(T,)`` bool occlusion mask.

    Every phase (approach, closing, hold, opening, occlusion) has a step from
    ``steps >= MIN_STEPS`` on.
    """
    close = slice(steps // 8, steps // 2)
    opening = slice(int(0.78 * steps), steps)
    occluded = torch.zeros(steps, dtype=torch.bool)
    occluded[steps // 4 : int(0.85 * steps)] = True
    return close, opening, occluded


def make_trials(args: Args, batch: int, seed: int) -> tuple[Scene, Rollout, Tensor, Tensor]:
    """Simulate ``batch`` grasps with random pose, tilt and friction.

    The triangle is dropped from 0.1 mm with a random tilt (``args.tilt``) and offset
    (``args.x_offset``), falls flat and is pushed towards the middle by the closing fingers.

    Returns:
        The batched scene, the rollout (batch ``B``), the controls ``(T, B, 2, 3)`` and the
        friction ``(B,)``.

    Raises:
        RuntimeError: a trial had a step that no LCP solver could solve.
    """
    gen = torch.Generator().manual_seed(seed)
    T = args.steps
    x0 = (2 * torch.rand(batch, generator=gen, dtype=F64) - 1) * args.x_offset
    theta = (2 * torch.rand(batch, generator=gen, dtype=F64) - 1) * args.tilt
    mu = args.friction_low + (args.friction_high - args.friction_low) * torch.rand(
        batch, generator=gen, dtype=F64
    )
    vertices = Polygon.triangle(SIDE, HEIGHT).vertices
    cos, sin = torch.cos(theta), torch.sin(theta)
    lowest = (sin[:, None] * vertices[:, 0] + cos[:, None] * vertices[:, 1]).min(-1).values
    q = torch.stack([x0, 1e-4 - lowest, theta], -1)[:, None]
    # Close to a width 1.5 mm above the triangle's width at the fingers' lower corners.
    bottom = FINGER_Y - FINGER[1] / 2
    target = SIDE / 2 * (1 - bottom / HEIGHT) + 0.0015 + FINGER[0] / 2
    q_kin = torch.tensor([[-FINGER_OPEN, FINGER_Y, 0.0], [FINGER_OPEN, FINGER_Y, 0.0]], dtype=F64)
    q_kin = q_kin.expand(batch, 2, 3).clone()
    close, opening, _ = schedule(T)
    n_close = close.stop - close.start
    speed = (FINGER_OPEN - target) / (n_close * H)
    controls = torch.zeros(T, batch, 2, 3, dtype=F64)
    controls[close, :, 0, 0], controls[close, :, 1, 0] = speed, -speed
    controls[opening, :, 0, 0], controls[opening, :, 1, 0] = -0.1, 0.1
    scene = triangle_scene(mu)
    simulator = Simulator(scene)
    state = simulator.initial_state(q=q, q_kinematic=q_kin)
    rollout = simulator.rollout(state, steps=T, controls=controls, strict=False)
    failed = (rollout.solver == UNSOLVED).any(0)
    if bool(failed.any()):
        raise RuntimeError(f"{int(failed.sum())} trials had unsolved LCP steps (seed {seed})")
    return scene, rollout, controls, mu


def tactile_readings(
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
class Trials:
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


def simulate(args: Args) -> Trials:
    """Training rollouts (mode table, transition), evaluation trials and their measurements."""
    _, train, _, _ = make_trials(args, args.train_trials, seed=10_000 + args.seed)
    table, train_ids, _ = collect_modes(train.mode)
    transition = empirical_transition(train_ids.T.contiguous(), table.shape[0], smoothing=0.1)
    scene, truth, controls, _ = make_trials(args, args.trials, seed=args.seed)
    T, B = args.steps, args.trials
    gen = torch.Generator().manual_seed(args.seed + 1)
    _, _, occluded = schedule(T)
    y = truth.q[1:, :, 0] + vision_sigma(args) * torch.randn(T, B, 3, generator=gen, dtype=F64)
    y[occluded] = math.nan
    tactile = tactile_array(args)
    readings = tactile_readings(scene, truth, tactile, gen)
    prior_std = torch.tensor([0.005, 0.005, 0.05, 0.01, 0.01, 0.1], dtype=F64)
    noisy = truth.q[0, :, 0] + prior_std[:3] * torch.randn(B, 3, generator=gen, dtype=F64)
    prior_mean = torch.cat([noisy, torch.zeros(B, 3, dtype=F64)], -1)
    prior = Gaussian(prior_mean, torch.diag(prior_std.pow(2)).expand(B, 6, 6).contiguous())
    return Trials(
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


def vision_sigma(args: Args) -> Tensor:
    """``(3,)`` vision noise std of ``(x, y, θ)``."""
    return torch.tensor([args.vision_sigma] * 2 + [args.vision_sigma_theta], dtype=F64)


def mode_ids(mode: Tensor, table: Tensor) -> Tensor:
    """Row of ``table (K, L)`` of each ``(*B, L)`` mode vector; ``K`` where it is absent."""
    match = (mode[..., None, :] == table).all(-1)  # (*B, K)
    found = match.any(-1)
    return torch.where(found, match.to(torch.long).argmax(-1), table.shape[0])


def touch_codes(scene: Scene, mode: Tensor) -> Tensor:
    """Which bodies touch the triangle: ``(*B,)`` long bit code of ``(*B, L)`` per-slot modes.

    Bit ``i`` is set where a slot shared with ``scene.bodies[i]`` is in contact (mode >= 1).
    """
    triangle = scene.index("triangle")
    code = torch.zeros(mode.shape[:-1], dtype=torch.long)
    for group in scene.slot_groups:
        partner = group.other if group.receiver == triangle else group.receiver
        touching = (mode[..., group.start : group.start + group.count] > 0).any(-1)
        code = code | (touching.to(torch.long) << partner)
    return code


def mode_label(scene: Scene, mode: Tensor) -> str:
    """Readable contact state of one ``(L,)`` per-slot mode vector, e.g. ``"table 2 stick"``.

    Each touching body is named with its contacts' states: ``stick`` or ``slide``, the
    latter with the slip direction (``→`` or ``←``) on a static half-plane such as the table
    (its tangent is known; a finger's depends on the geometry). Equal states are counted
    (``table 2 slide→``), different ones joined (``table stick+slide←``); ``"free"`` when
    nothing touches.
    """
    triangle = scene.index("triangle")
    states: dict[int, list[str]] = {}
    for group in scene.slot_groups:
        partner = group.other if group.receiver == triangle else group.receiver
        body = scene.bodies[partner]
        slots = mode[group.start : group.start + group.count]
        for slot in slots.tolist():
            if slot == 0:
                continue
            state = "stick" if slot == 1 else "slide"
            if slot > 1 and isinstance(body.shape, HalfPlane):
                # Friction along +t (mode 2) or -t (mode 3), t = normal turned by +90°; the
                # slip opposes it.
                tangent_x = -float(body.shape.normal[1])
                slip_x = -tangent_x if slot == 2 else tangent_x
                state += "→" if slip_x > 0 else "←"
            states.setdefault(partner, []).append(state)
    parts = []
    for partner, names in sorted(states.items()):
        kinds = sorted(set(names))
        text = f"{len(names)} {kinds[0]}" if len(kinds) == 1 else "+".join(sorted(names))
        parts.append(f"{scene.bodies[partner].name} {text}")
    return ", ".join(parts) if parts else "free"


def contact_model(args: Args, trials: Trials) -> PlanarContactModel:
    """The RBPF's switching model: assumed friction, process noise, vision, learned modes."""
    K = trials.table.shape[0]
    pose, twist = args.rbpf_pose_noise, args.rbpf_twist_noise
    noise_std = torch.tensor([pose] * 3 + [twist, twist, 10 * twist], dtype=F64)
    return PlanarContactModel(
        scene=triangle_scene(args.friction_model),
        modes=trials.table,
        Q=torch.diag(noise_std.pow(2)),
        R=torch.diag(vision_sigma(args).pow(2)),
        transition=trials.transition,
        initial=torch.full((K,), 1.0 / K, dtype=F64),
    )


# ----------------------------------------------------------------------------------------------
# estimators


def project_out_of_contact(
    belief: RBPFBelief, scene: Scene, q_kinematic: Tensor, gap_sigma: float
) -> RBPFBelief:
    r"""Project every particle's Gaussian out of the bodies its mean penetrates.

    The RBPF linearizes each mode's step at the belief's mixture mean, so a particle away from
    the mean (or one whose mode keeps a slot separated while the finger moves into it) can end
    the step inside a finger or the table. For every slot whose gap :math:`\phi_s` at the
    particle's mean is negative, the zero-gap constraint enters as a pseudo-measurement
    :math:`0 = \phi_s(\mu) + J_s (x - \mu) + e`, :math:`e \sim N(0, \sigma^2)` (estimate
    projection, Simon and Chia 2002), with :math:`J_s` the slot's normal row (the gradient of
    its gap w.r.t. the pose). Weights and modes are unchanged.

    Args:
        belief: the RBPF belief after a step, batch ``(B,)`` with ``N`` particles.
        scene: the filter's scene (one dynamic body).
        q_kinematic: ``(B, Nk, 3)`` kinematic-body poses at the end of the step.
        gap_sigma: ``σ``, metres, ``> 0``.

    Returns:
        The belief with projected Gaussians.

    Raises:
        ValueError: ``gap_sigma`` is not positive, or the shapes disagree.
    """
    if not gap_sigma > 0:
        raise ValueError(f"gap_sigma: expected > 0, got {gap_sigma!r}")
    g = belief.gaussians
    B, N = belief.modes.shape
    if q_kinematic.shape != (B, len(scene.kinematic), 3):
        raise ValueError(
            f"q_kinematic: expected shape {(B, len(scene.kinematic), 3)}, got "
            f"{tuple(q_kinematic.shape)}"
        )
    phi, Jn, penetrating = penetration(
        scene,
        q=g.mean[..., None, :3],
        q_kinematic=q_kinematic[:, None].expand(B, N, *q_kinematic.shape[1:]),
    )  # (B, N, K), (B, N, K, 3), (B, N, K)
    slots = penetrating.flatten(0, 1).any(0).nonzero().squeeze(-1)
    if slots.numel() == 0:
        return belief
    m = int(slots.numel())
    Hm = g.mean.new_zeros(B, N, m, 6)
    Hm[..., :3] = Jn[..., slots, :]
    d = phi[..., slots] - (Hm @ g.mean[..., None]).squeeze(-1)
    R = torch.diag(g.mean.new_full((m,), gap_sigma**2))
    projected, _ = kf_update(
        g, g.mean.new_zeros(B, N, m), H=Hm, d=d, R=R, mask=penetrating[..., slots]
    )
    return dataclasses.replace(belief, gaussians=projected)


def run_rbpf(
    model: PlanarContactModel,
    trials: Trials,
    args: Args,
    gen: torch.Generator,
    trial: int = 0,
) -> dict[str, Tensor]:
    """RBPF over contact modes with tactile evidence and the zero-gap projection.

    Returns:
        ``pose (T, B, 3)`` mixture-mean poses, ``marginals (T, B, K)`` filtered mode
        marginals, ``cloud (T, N, 3)`` and ``cloud_weight (T, N)`` particle means and weights
        of trial ``trial``.
    """
    rbpf = RBPF(model, args.rbpf_particles, proposal="all_modes")
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
        if args.gap_sigma > 0:
            belief = project_out_of_contact(belief, model.scene, q_kinematic[t + 1], args.gap_sigma)
        poses.append(belief.mean()[..., :3])
        marginals.append(belief.mode_marginals())
        clouds.append(belief.gaussians.mean[trial, :, :3].clone())
        cloud_weights.append(belief.log_weights[trial].exp())
    return {
        "pose": torch.stack(poses),
        "marginals": torch.stack(marginals),
        "cloud": torch.stack(clouds),
        "cloud_weight": torch.stack(cloud_weights),
    }


def run_pf(
    trials: Trials,
    args: Args,
    num_particles: int,
    gen: torch.Generator,
    trial: int = 0,
) -> dict[str, Tensor]:
    """Bootstrap PF over pose and twist through the simulator (batch ``B × N``).

    Particles are stepped by the simulator with the assumed friction, perturbed by
    :data:`PF_NOISE_STD`, weighted by the tactile readings of their simulated contacts and by
    vision, and resampled (systematic) every step.

    Returns:
        Like :func:`run_rbpf`; the marginals are the weighted histogram of the particles'
        simulated modes over the mode table.
    """
    T, B, N = trials.steps, trials.batch, num_particles
    scene = triangle_scene(args.friction_model)
    simulator = Simulator(scene)
    prior, tactile, table = trials.prior, trials.tactile, trials.table
    chol = torch.linalg.cholesky(prior.cov)
    x = prior.mean[:, None] + (
        chol[:, None] @ torch.randn(B, N, 6, 1, generator=gen, dtype=F64)
    ).squeeze(-1)
    mode = torch.zeros(B, N, scene.num_slots, dtype=torch.long)
    noise = torch.tensor(PF_NOISE_STD, dtype=F64)
    R_std = vision_sigma(args)
    poses, marginals, clouds, cloud_weights = [], [], [], []
    for t in range(T):
        q_kin = trials.truth.q_kinematic[t][:, None].expand(B, N, 2, 3)
        u = trials.controls[t][:, None].expand(B, N, 2, 3)
        state = simulator.initial_state(
            q=x[..., None, :3], v=x[..., None, 3:], q_kinematic=q_kin.contiguous()
        )
        state = dataclasses.replace(state, mode=mode)
        result = simulator.step(state, u.contiguous())
        # A particle whose step no solver solved gets weight zero; its numbers are replaced
        # by finite ones so that they cannot poison the weighted sums.
        unsolved = result.solver == UNSOLVED
        stepped = torch.cat([result.state.q[..., 0, :], result.state.v[..., 0, :]], -1)
        x = torch.where(unsolved[..., None], x, stepped)
        x = x + noise * torch.randn(B, N, 6, generator=gen, dtype=F64)
        mode = torch.where(unsolved[..., None], 0, result.mode)
        log_w = torch.where(unsolved, -math.inf, 0.0).to(F64)
        contacts = object_contacts(
            scene,
            body="triangle",
            q=state.q,
            points=result.geometry.points,
            normals=result.geometry.normals,
            pn=torch.where(unsolved[..., None], 0.0, result.pn).clamp_min(0.0),
            mode=mode,
            active=result.geometry.active,
        )
        on = tactile.reading_probability(tactile.triggered(contacts))
        r = trials.readings[t][:, None]
        log_w = log_w + torch.where(r, torch.log(on), torch.log1p(-on)).sum(-1)
        seen = torch.isfinite(trials.y[t]).all(-1)
        residual = x[..., :3] - trials.y[t][:, None]
        residual[..., 2] = wrap_angle(residual[..., 2])
        vision = -0.5 * (residual / R_std).pow(2).sum(-1)
        log_w = log_w + torch.where(seen[:, None], vision.nan_to_num(0.0), 0.0)
        log_w = torch.where(torch.isneginf(log_w).all(-1, keepdim=True), 0.0, log_w)
        weights = torch.softmax(log_w, -1)
        poses.append((weights[..., None] * x[..., :3]).sum(1))
        ids = mode_ids(mode, table)
        hist = torch.zeros(B, table.shape[0] + 1, dtype=F64).scatter_add_(1, ids, weights)
        marginals.append(hist[:, :-1])
        clouds.append(x[trial, :, :3].clone())
        cloud_weights.append(weights[trial].clone())
        index = resample(log_w, generator=gen)
        x = torch.gather(x, 1, index[..., None].expand(B, N, 6))
        mode = torch.gather(mode, 1, index[..., None].expand(B, N, mode.shape[-1]))
    return {
        "pose": torch.stack(poses),
        "marginals": torch.stack(marginals),
        "cloud": torch.stack(clouds),
        "cloud_weight": torch.stack(cloud_weights),
    }


def run_ekf(args: Args, trials: Trials) -> dict[str, Tensor]:
    """Constant-velocity EKF (contact ignored); vision updates only."""

    def f(x: Tensor) -> Tensor:
        return torch.cat([x[:3] + H * x[3:], x[3:]])

    def measure(x: Tensor) -> Tensor:
        return x[:3]

    Q = torch.diag(torch.tensor([1e-7, 1e-7, 1e-5, 1e-3, 1e-3, 1e-1], dtype=F64))
    R = torch.diag(vision_sigma(args).pow(2))
    g = trials.prior
    poses = []
    for t in range(trials.steps):
        g = ekf_predict(g, f, Q=Q)
        g, _ = ekf_update(g, trials.y[t], measure, R=R)
        poses.append(g.mean[..., :3])
    return {"pose": torch.stack(poses)}


def run_vision(trials: Trials) -> dict[str, Tensor]:
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
    trials: Trials, args: Args, target: float, seed: int
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
        runs[n] = timed(lambda: run_pf(trials, args, n, torch.Generator().manual_seed(seed)))
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


# ----------------------------------------------------------------------------------------------
# evaluation


def evaluate(
    trials: Trials, outputs: dict[str, dict[str, Tensor]]
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
    table_codes = touch_codes(trials.scene, trials.table)  # (K,)
    true_codes = touch_codes(trials.scene, trials.truth.mode)  # (T, B)
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


# ----------------------------------------------------------------------------------------------
# the experiment


def check_args(args: Args) -> None:
    """Check every argument before any work (``rbpf_particles >= K`` is checked once the
    training rollouts have given the number of modes K).

    Raises:
        ValueError: an argument is out of range; the message names it and its range.
    """
    check_name("name", args.name)
    for name in ("trials", "train_trials", "rbpf_particles"):
        check_int(name, getattr(args, name), low=1)
    check_int("seed", args.seed, low=0)
    check_int("steps", args.steps, low=MIN_STEPS, why="every phase of the grasp schedule")
    check_int("pf_particles", args.pf_particles, low=0)
    for name in ("rbpf_pose_noise", "rbpf_twist_noise", "vision_sigma", "vision_sigma_theta"):
        check_real(name, getattr(args, name), low=0.0, low_open=True)
    for name in ("gap_sigma", "friction_model", "x_offset", "tilt"):
        check_real(name, getattr(args, name), low=0.0)
    for name in ("false_positive", "false_negative"):
        check_real(name, getattr(args, name), low=0.0, high=1.0, high_open=True)
    check_real("friction_low", args.friction_low, low=0.0)
    check_real("friction_high", args.friction_high, low=args.friction_low)


def run(args: Args) -> dict[str, Any]:
    """Simulate the trials, run every estimator, write logs, table and plots.

    The run writes to a new folder, :func:`~torchcontact.experiments.new_run_dir`.

    Returns:
        ``{"metrics": {method: {metric: float}}, "run_dir": str, "pf_particles": int,
        "calibration": {particles: seconds}, "ratio_pos_occ": float, ...}`` (see
        :func:`summarize`).

    Raises:
        ValueError: an argument is out of range (before the training rollouts; the RBPF's
            particle count right after them).
    """
    if args.fast:
        args = dataclasses.replace(
            args,
            trials=min(args.trials, 2),
            train_trials=min(args.train_trials, 8),
            steps=min(args.steps, 48),
            rbpf_particles=min(args.rbpf_particles, 20),
        )
    check_args(args)
    torch.manual_seed(args.seed)
    progress = tqdm(total=len(METHODS) + 3, desc="triangle grasp")
    trials = simulate(args)
    model = contact_model(args, trials)
    check_int(
        "rbpf_particles",
        args.rbpf_particles,
        low=model.num_modes,
        why="the number of modes K the training rollouts gave the RBPF",
    )
    progress.update()
    run_dir = new_run_dir(out_dir=args.out_dir, name=args.name, seed=args.seed)
    writer = SummaryWriter(str(run_dir))

    def generator(offset: int) -> torch.Generator:
        return torch.Generator().manual_seed(args.seed + offset)

    outputs: dict[str, dict[str, Tensor]] = {}
    timings: dict[str, Timing] = {}
    particles = {"rbpf": args.rbpf_particles}
    outputs["rbpf"], timings["rbpf"] = timed(lambda: run_rbpf(model, trials, args, generator(2)))
    progress.update()
    calibration: dict[int, float] = {}
    if args.pf_particles == 0:
        particles["pf"], outputs["pf"], timings["pf"], calibration = calibrate_pf(
            trials, args, timings["rbpf"].cpu, args.seed + 3
        )
    else:
        particles["pf"] = args.pf_particles
        outputs["pf"], timings["pf"] = timed(
            lambda: run_pf(trials, args, args.pf_particles, generator(3))
        )
    progress.update()
    if args.reference_pf:
        particles["pf_same_n"] = args.rbpf_particles
        outputs["pf_same_n"], timings["pf_same_n"] = timed(
            lambda: run_pf(trials, args, args.rbpf_particles, generator(4))
        )
    progress.update()
    outputs["ekf"], timings["ekf"] = timed(lambda: run_ekf(args, trials))
    outputs["vision"], timings["vision"] = timed(lambda: run_vision(trials))
    progress.update()

    metrics, errors = evaluate(trials, outputs)
    for method, row in metrics.items():
        row["particles"] = float(particles.get(method, 0))
        row["ms_per_step"] = 1e3 * timings[method].wall / trials.steps
        row["cpu_ms_per_step"] = 1e3 * timings[method].cpu / trials.steps
        row["cpu_ms_per_step_per_trial"] = row["cpu_ms_per_step"] / trials.batch
        for key, value in row.items():
            writer.add_scalar(f"charts/{method}_{key}", value, 0)
        pos, ang = errors[method]
        for t in range(trials.steps):
            writer.add_scalar(
                f"eval/{method}_pos_err_mm", 1e3 * float(pos[t].pow(2).mean().sqrt()), t
            )
            writer.add_scalar(
                f"eval/{method}_theta_err_deg", math.degrees(float(ang[t].pow(2).mean().sqrt())), t
            )
    summary = summarize(trials, metrics)
    summary["calibration"] = calibration
    summary["pf_particles"] = particles["pf"]
    for key in ("ratio_pos_occ", "ratio_theta_occ"):
        writer.add_scalar(f"charts/{key}", summary[key], 0)
    progress.update()

    (run_dir / "metrics.json").write_text(json.dumps({"metrics": metrics, **summary}, indent=2))
    write_table(run_dir / "results.md", args, metrics, summary)
    save_plots(run_dir, trials, outputs, errors, metrics)
    writer.close()
    progress.update()
    progress.close()
    return {"metrics": metrics, "run_dir": str(run_dir), **summary}


def summarize(trials: Trials, metrics: dict[str, dict[str, float]]) -> dict[str, Any]:
    """The issue's targets and sanity checks of the ground truth.

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
        "min_vertex_height": _min_vertex_height(trials.truth),
    }
    for key, metric in (("pos_occ", "pos_rmse_occ_mm"), ("theta_occ", "theta_rmse_occ_deg")):
        best = min(metrics[m][metric] for m in BASELINES if m in metrics)
        summary[f"ratio_{key}"] = rbpf[metric] / best
        if "pf_same_n" in metrics:
            summary[f"ratio_{key}_same_n"] = rbpf[metric] / metrics["pf_same_n"][metric]
    return summary


def _min_vertex_height(truth: Rollout) -> float:
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


def results_table(metrics: dict[str, dict[str, float]]) -> str:
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


def write_table(
    path: Path, args: Args, metrics: dict[str, dict[str, float]], summary: dict[str, Any]
) -> None:
    """``results.md``: settings, the table, the calibration and the issue's targets."""
    calibration = ", ".join(
        f"{n} → {1e3 * seconds / args.steps:.1f}" for n, seconds in summary["calibration"].items()
    )
    rbpf = metrics["rbpf"]
    lines = [
        f"# Triangle grasp tracking ({args.trials} trials, {args.steps} steps, seed {args.seed})",
        "",
        f"Mode table: {summary['table_size']} modes from {args.train_trials} training rollouts; "
        f"true mode in the table at {100 * summary['true_mode_in_table']:.1f} % of the steps. "
        "Times are for all trials batched together on one thread: wall clock and this "
        "process's CPU time (the steadier of the two on a shared machine).",
        "",
        f"Plain PF (`pf`) particles fitting in the RBPF's CPU time per step: "
        f"{summary['pf_particles']}"
        + (
            f" (calibration runs, particles → CPU ms per step: {calibration})."
            if calibration
            else " (given)."
        ),
        "",
        results_table(metrics),
        "",
        "Targets (RBPF against the best of pf, which gets the RBPF's time, ekf and vision):",
        "",
        f"- position RMSE during occlusion: ratio {summary['ratio_pos_occ']:.3f} (target <= 0.5)",
        f"- angle RMSE during occlusion: ratio {summary['ratio_theta_occ']:.3f} (target <= 0.5)",
        f"- contact-state (mode) accuracy: {rbpf['mode_accuracy']:.3f} (target >= 0.9)",
    ]
    if "ratio_pos_occ_same_n" in summary:
        lines.append(
            f"- against pf_same_n (same particle count, slower): position ratio "
            f"{summary['ratio_pos_occ_same_n']:.3f}, angle ratio "
            f"{summary['ratio_theta_occ_same_n']:.3f}"
        )
    lines += [
        "",
        f"Lowest triangle vertex height over all ground-truth steps: "
        f"{1e3 * summary['min_vertex_height']:.3f} mm",
    ]
    path.write_text("\n".join(lines) + "\n")


# ----------------------------------------------------------------------------------------------
# plots


def _shade_occlusion(ax: Any, trials: Trials, time_s: Tensor) -> None:
    occ = time_s[trials.occluded]
    ax.axvspan(float(occ[0]) - H / 2, float(occ[-1]) + H / 2, color="0.88", zorder=0)


def plot_snapshots(
    trials: Trials, outputs: dict[str, dict[str, Tensor]], steps: list[int], trial: int = 0
) -> Figure:
    """Trial ``trial`` after the given steps: the scene (top) and the particles (bottom).

    Top: truth with the fingers and the RBPF's particle means. Bottom: a 12 mm window around
    the true position with the RBPF's and the PF's particles (size ∝ weight) and the estimates.
    """
    truth = trials.truth
    fig, axes = plt.subplots(2, len(steps), figsize=(3.6 * len(steps), 4.4), squeeze=False)
    for column, t in enumerate(steps):
        top, bottom = axes[0, column], axes[1, column]
        draw_scene(
            top, trials.scene, q=truth.q[t + 1, trial], q_kinematic=truth.q_kinematic[t + 1, trial]
        )
        top.set_xlim(-0.08, 0.08)
        top.set_ylim(-0.005, 0.075)
        top.set_xticks([-0.05, 0.0, 0.05])
        top.set_yticks([0.0, 0.05])
        occluded = " (occluded)" if trials.occluded[t] else ""
        top.set_title(f"t = {H * (t + 1):.2f} s{occluded}", fontsize=9)
        true_xy = 1e3 * truth.q[t + 1, trial, 0, :2]
        for method, color in (("pf", "C2"), ("rbpf", "C3")):
            if method not in outputs:
                continue
            cloud = outputs[method]["cloud"][t]
            weight = outputs[method]["cloud_weight"][t]
            size = 4 + 60 * weight / weight.max()
            xy = 1e3 * cloud[:, :2] - true_xy
            bottom.scatter(
                xy[:, 0],
                xy[:, 1],
                s=size,
                color=color,
                alpha=0.4,
                lw=0,
                label=f"{method} particles",
            )
            if method == "rbpf":
                top.plot(cloud[:, 0], cloud[:, 1], ".", color=color, ms=2)
        for method, marker in (("rbpf", "x"), ("pf", "+"), ("vision", "s")):
            if method in outputs:
                xy = 1e3 * outputs[method]["pose"][t, trial, :2] - true_xy
                bottom.plot(
                    xy[0], xy[1], marker, color="k", ms=7, mfc="none", label=f"{method} estimate"
                )
        bottom.plot(0, 0, "*", color="C0", ms=10, label="truth")
        bottom.set_xlim(-6, 6)
        bottom.set_ylim(-3, 3)
        bottom.set_aspect("equal")
        bottom.set_xlabel("x error (mm)")
    axes[1, 0].set_ylabel("y error (mm)")
    axes[1, 0].legend(fontsize=6, loc="lower left")
    fig.tight_layout()
    return fig


def plot_errors(
    trials: Trials,
    errors: dict[str, tuple[Tensor, Tensor]],
    labels: dict[str, str] | None = None,
) -> Figure:
    """Position and angle RMSE over the trials against time, the occlusion shaded.

    Args:
        trials: the trials.
        errors: ``{method: (position error (T, B), angle error (T, B))}`` from :func:`evaluate`.
        labels: legend text per method (default: the method's name).
    """
    labels = labels or {}
    time_s = H * torch.arange(1, trials.steps + 1)
    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    for method, (pos, ang) in errors.items():
        label = labels.get(method, method)
        axes[0].plot(time_s, 1e3 * pos.pow(2).mean(-1).sqrt(), label=label)
        axes[1].plot(time_s, torch.rad2deg(ang.pow(2).mean(-1).sqrt()), label=label)
    for ax in axes:
        _shade_occlusion(ax, trials, time_s)
        ax.set_yscale("log")
    axes[0].set_ylabel("position RMSE (mm)")
    axes[1].set_ylabel("angle RMSE (deg)")
    axes[1].set_xlabel("time (s); shaded: camera occluded")
    axes[0].legend(fontsize=7, ncol=3, loc="lower center", bbox_to_anchor=(0.5, 1.0), frameon=False)
    fig.tight_layout()
    return fig


def plot_contact_timeline(trials: Trials, marginals: Tensor, trial: int = 0) -> Figure:
    """Mode marginals of one trial over time (shade), the true mode and the MAP mode.

    Args:
        trials: the trials.
        marginals: ``(T, B, K)`` filtered mode marginals.
        trial: which trial.
    """
    K = trials.table.shape[0]
    time_s = H * torch.arange(1, trials.steps + 1)
    marg = marginals[:, trial]
    labels = [f"{k}: {mode_label(trials.scene, trials.table[k])}" for k in range(K)]
    fig, ax = plt.subplots(figsize=(9, 0.28 * K + 1.6))
    ax.imshow(
        marg.T,
        aspect="auto",
        origin="lower",
        cmap="Blues",
        vmin=0.0,
        vmax=1.0,
        extent=(float(time_s[0]) - H / 2, float(time_s[-1]) + H / 2, -0.5, K - 0.5),
    )
    true_ids = trials.true_ids[:, trial]
    ax.plot(time_s, true_ids.clamp(max=K - 1), "o", mfc="none", color="C3", ms=6, label="true mode")
    ax.plot(time_s, marg.argmax(-1), "k.", ms=3, label="RBPF MAP mode")
    occ = time_s[trials.occluded]
    ax.axvspan(float(occ[0]) - H / 2, float(occ[-1]) + H / 2, color="0.5", alpha=0.12)
    ax.set_yticks(range(K), labels, fontsize=7)
    ax.set_xlabel("time (s); shaded: camera occluded")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    return fig


def save_plots(
    run_dir: Path,
    trials: Trials,
    outputs: dict[str, dict[str, Tensor]],
    errors: dict[str, tuple[Tensor, Tensor]],
    metrics: dict[str, dict[str, float]],
) -> None:
    """``snapshots.png``, ``errors.png`` and ``modes.png`` of the run."""
    T = trials.steps
    labels = {
        method: f"{method} ({row['particles']:.0f} particles)"
        for method, row in metrics.items()
        if row.get("particles")
    }
    figures = {
        "snapshots": plot_snapshots(trials, outputs, [T // 5, int(0.45 * T), int(0.8 * T)]),
        "errors": plot_errors(trials, errors, labels),
        "modes": plot_contact_timeline(trials, outputs["rbpf"]["marginals"]),
    }
    for name, fig in figures.items():
        fig.savefig(run_dir / f"{name}.png", dpi=90)
        plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    """Parse the command line and run (on one thread: the timings compare single-threaded work)."""
    torch.set_num_threads(1)
    result = run(tyro.cli(Args, args=argv, description=__doc__.splitlines()[0]))
    print(Path(result["run_dir"], "results.md").read_text())


if __name__ == "__main__":
    main()
