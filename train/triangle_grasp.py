"""Tracking a triangle grasped by a parallel-jaw gripper: the contact RBPF against baselines.

A triangle (8 cm sides, 0.2 kg) rests on a table in a vertical plane; two kinematic fingers
close on it from both sides (their twists are the control), push it into the middle of the
gripper, hold it and open again. A camera sees the triangle's pose with Gaussian noise except
while the fingers are close (occlusion: the measurement is NaN); a tactile array on the
triangle's edges reads contacts with false positives and negatives; the finger poses are known.

Estimators, all batched over the trials:

1. ``rbpf``: :class:`~torchcontact.filters.PlanarContactModel` + :class:`~torchcontact.filters.RBPF`
   over contact modes (table and transition from training rollouts), tactile likelihood as the
   extra per-mode evidence;
2. ``pf``: a bootstrap particle filter over pose and twist that propagates particles through the
   :class:`~torchcontact.sim.Simulator` with process noise, weighted by vision and tactile;
3. ``ekf``: an EKF with constant-velocity dynamics (contact ignored), vision updates;
4. ``vision``: the last measurement, held during the occlusion.

Ground truth is the simulator (exact LCP fallback), with per-trial friction and initial pose.

Usage::

    python train/triangle_grasp.py --trials 50 --name triangle_grasp
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import torch
from torch import Tensor
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from torchcontact.experiments import parse_dataclass
from torchcontact.filters import (
    RBPF,
    Gaussian,
    KinematicControl,
    PlanarContactModel,
    collect_modes,
    ekf_predict,
    ekf_update,
    empirical_transition,
    resample,
    wrap_angle,
)
from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import UNSOLVED, Body, Rollout, Scene, Simulator, draw_scene
from torchcontact.states import TactileArray, object_contacts

F64 = torch.float64
SIDE = 0.08  # triangle side, metres
HEIGHT = SIDE * math.sqrt(3.0) / 2.0
FINGER = (0.01, 0.03)  # finger width, height
FINGER_Y = 0.03  # finger centre above the table
METHODS = ("rbpf", "pf", "ekf", "vision")


@dataclass
class Args:
    """Arguments of the triangle-grasp tracking experiment."""

    name: str = dataclasses.field(default="triangle_grasp", metadata={"help": "run name"})
    out_dir: str = dataclasses.field(default="runs", metadata={"help": "parent of the run folder"})
    seed: int = dataclasses.field(default=0, metadata={"help": "seed of the evaluation trials"})
    trials: int = dataclasses.field(default=50, metadata={"help": "evaluation trials"})
    train_trials: int = dataclasses.field(
        default=64, metadata={"help": "training rollouts for the mode table and transition"}
    )
    steps: int = dataclasses.field(default=80, metadata={"help": "time steps per trial (h=0.01)"})
    rbpf_particles: int = dataclasses.field(default=200, metadata={"help": "RBPF particles"})
    pf_particles: int = dataclasses.field(default=200, metadata={"help": "plain PF particles"})
    vision_sigma: float = dataclasses.field(
        default=0.004, metadata={"help": "vision position noise std, metres"}
    )
    vision_sigma_theta: float = dataclasses.field(
        default=0.03, metadata={"help": "vision angle noise std, radians"}
    )
    false_positive: float = dataclasses.field(default=0.05, metadata={"help": "tactile FP rate"})
    false_negative: float = dataclasses.field(default=0.1, metadata={"help": "tactile FN rate"})
    friction_low: float = dataclasses.field(default=0.4, metadata={"help": "min true friction"})
    friction_high: float = dataclasses.field(default=0.6, metadata={"help": "max true friction"})
    friction_model: float = dataclasses.field(
        default=0.5, metadata={"help": "friction assumed by the filters"}
    )
    x_offset: float = dataclasses.field(
        default=0.012, metadata={"help": "max |initial x offset| of the triangle, metres"}
    )
    tilt: float = dataclasses.field(
        default=0.15, metadata={"help": "max |initial rotation| of the triangle, radians"}
    )
    fast: bool = dataclasses.field(default=False, metadata={"help": "tiny budget (tests)"})


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
        h=0.01,
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
    """Closing and opening step ranges and the ``(T,)`` bool occlusion mask."""
    close = slice(steps // 8, steps // 2)
    opening = slice(int(0.78 * steps), steps)
    occluded = torch.zeros(steps, dtype=torch.bool)
    occluded[steps // 4 : int(0.85 * steps)] = True
    return close, opening, occluded


def make_trials(args: Args, batch: int, seed: int) -> tuple[Scene, Rollout, Tensor, Tensor]:
    """Simulate ``batch`` grasps with random pose, tilt and friction.

    Returns:
        The batched scene, the rollout (batch ``B``), the controls ``(T, B, 2, 3)`` and the
        friction ``(B,)``. Trials that the LCP could not solve are re-drawn.
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
    start = 0.07
    q_kin = torch.tensor([[-start, FINGER_Y, 0.0], [start, FINGER_Y, 0.0]], dtype=F64)
    q_kin = q_kin.expand(batch, 2, 3).clone()
    close, opening, _ = schedule(T)
    n_close = close.stop - close.start
    speed = (start - target) / (n_close * 0.01)
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


# ----------------------------------------------------------------------------------------------
# estimators


def run_rbpf(
    model: PlanarContactModel,
    args: Args,
    prior: Gaussian,
    y: Tensor,
    readings: Tensor,
    tactile: TactileArray,
    rollout: Rollout,
    controls: Tensor,
    gen: torch.Generator,
) -> dict[str, Tensor]:
    """RBPF over contact modes; returns ``pose (T, B, 3)``, ``marginals (T, B, K)``, ``cloud``."""
    rbpf = RBPF(model, args.rbpf_particles, proposal="all_modes")
    belief = rbpf.init(prior)
    poses, marginals, clouds = [], [], []
    for t in range(y.shape[0]):
        control = KinematicControl(q=rollout.q_kinematic[t], v=controls[t])
        extra = model.tactile_log_likelihood(
            tactile, readings[t], pose=belief.mean()[..., :3], control=control
        )
        belief = rbpf.step(belief, y[t], extra_log_likelihood=extra, control=control, generator=gen)
        poses.append(belief.mean()[..., :3])
        marginals.append(belief.mode_marginals())
        clouds.append(belief.gaussians.mean[0, :, :3].clone())
    return {
        "pose": torch.stack(poses),
        "marginals": torch.stack(marginals),
        "cloud": torch.stack(clouds),
    }


def run_pf(
    scene: Scene,
    table: Tensor,
    args: Args,
    prior: Gaussian,
    y: Tensor,
    readings: Tensor,
    tactile: TactileArray,
    rollout: Rollout,
    controls: Tensor,
    gen: torch.Generator,
) -> dict[str, Tensor]:
    """Bootstrap PF over pose and twist through the simulator (batch ``B × N``)."""
    T, B = y.shape[:2]
    N = args.pf_particles
    simulator = Simulator(scene)
    chol = torch.linalg.cholesky(prior.cov)
    x = prior.mean[:, None] + (
        chol[:, None] @ torch.randn(B, N, 6, 1, generator=gen, dtype=F64)
    ).squeeze(-1)
    mode = torch.zeros(B, N, scene.num_slots, dtype=torch.long)
    noise = torch.tensor([2e-4, 2e-4, 2e-3, 0.02, 0.02, 0.2], dtype=F64)
    R_std = torch.tensor([args.vision_sigma] * 2 + [args.vision_sigma_theta], dtype=F64)
    poses, marginals, clouds = [], [], []
    for t in range(T):
        q_kin = rollout.q_kinematic[t][:, None].expand(B, N, 2, 3)
        u = controls[t][:, None].expand(B, N, 2, 3)
        state = simulator.initial_state(
            q=x[..., None, :3], v=x[..., None, 3:], q_kinematic=q_kin.contiguous()
        )
        state = dataclasses.replace(state, mode=mode)
        result = simulator.step(state, u.contiguous())
        x = torch.cat([result.state.q[..., 0, :], result.state.v[..., 0, :]], -1)
        x = x + noise * torch.randn(B, N, 6, generator=gen, dtype=F64)
        mode = result.mode
        log_w = torch.where(result.solver == UNSOLVED, -math.inf, 0.0).to(F64)
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
        on = tactile.reading_probability(tactile.triggered(contacts))
        r = readings[t][:, None]
        log_w = log_w + torch.where(r, torch.log(on), torch.log1p(-on)).sum(-1)
        seen = torch.isfinite(y[t]).all(-1)
        residual = x[..., :3] - y[t][:, None]
        residual[..., 2] = wrap_angle(residual[..., 2])
        vision = -0.5 * (residual / R_std).pow(2).sum(-1)
        log_w = log_w + torch.where(seen[:, None], vision.nan_to_num(0.0), 0.0)
        weights = torch.softmax(log_w, -1)
        pose = (weights[..., None] * x[..., :3]).sum(1)
        poses.append(pose)
        ids = _mode_ids(mode, table)
        hist = torch.zeros(B, table.shape[0] + 1, dtype=F64).scatter_add_(1, ids, weights)
        marginals.append(hist[:, :-1])
        index = resample(log_w, generator=gen)
        x = torch.gather(x, 1, index[..., None].expand(B, N, 6))
        mode = torch.gather(mode, 1, index[..., None].expand(B, N, mode.shape[-1]))
        clouds.append(x[0, :, :3].clone())
    return {
        "pose": torch.stack(poses),
        "marginals": torch.stack(marginals),
        "cloud": torch.stack(clouds),
    }


def _mode_ids(mode: Tensor, table: Tensor) -> Tensor:
    """Row of ``table (K, S)`` of each ``(*B, S)`` mode vector; ``K`` where it is absent."""
    match = (mode[..., None, :] == table).all(-1)  # (*B, K)
    found = match.any(-1)
    return torch.where(found, match.to(torch.long).argmax(-1), table.shape[0])


def run_ekf(args: Args, prior: Gaussian, y: Tensor) -> dict[str, Tensor]:
    """Constant-velocity EKF (contact ignored); vision updates only."""
    h = 0.01

    def f(x: Tensor) -> Tensor:
        return torch.cat([x[:3] + h * x[3:], x[3:]])

    def measure(x: Tensor) -> Tensor:
        return x[:3]

    Q = torch.diag(torch.tensor([1e-7, 1e-7, 1e-5, 1e-3, 1e-3, 1e-1], dtype=F64))
    R = torch.diag(torch.tensor([args.vision_sigma] * 2 + [args.vision_sigma_theta], dtype=F64))
    R = R.pow(2)
    g = prior
    poses = []
    for t in range(y.shape[0]):
        g = ekf_predict(g, f, Q=Q)
        g, _ = ekf_update(g, y[t], measure, R=R)
        poses.append(g.mean[..., :3])
    return {"pose": torch.stack(poses)}


def run_vision(prior: Gaussian, y: Tensor) -> dict[str, Tensor]:
    """Last seen measurement (the prior mean before the first)."""
    last = prior.mean[..., :3]
    poses = []
    for t in range(y.shape[0]):
        seen = torch.isfinite(y[t]).all(-1, keepdim=True)
        last = torch.where(seen, y[t], last)
        poses.append(last)
    return {"pose": torch.stack(poses)}


# ----------------------------------------------------------------------------------------------
# the experiment


def run(args: Args) -> dict[str, Any]:
    """Simulate the trials, run every estimator, write logs, table and plots.

    Returns:
        ``{"metrics": {method: {metric: float}}, "run_dir": str, "min_height": float, ...}``.
    """
    if args.fast:
        args = dataclasses.replace(
            args,
            trials=min(args.trials, 2),
            train_trials=min(args.train_trials, 8),
            steps=min(args.steps, 48),
            rbpf_particles=min(args.rbpf_particles, 20),
            pf_particles=min(args.pf_particles, 20),
        )
    torch.manual_seed(args.seed)
    run_dir = Path(args.out_dir) / args.name
    run_dir.mkdir(parents=True, exist_ok=True)
    writer = SummaryWriter(str(run_dir))
    progress = tqdm(total=8, desc="triangle grasp")

    # training rollouts: mode table and transition
    _, train, _, _ = make_trials(args, args.train_trials, seed=10_000 + args.seed)
    table, train_ids, _ = collect_modes(train.mode)
    K = table.shape[0]
    transition = empirical_transition(train_ids.T.contiguous(), K, smoothing=0.1)
    progress.update()

    # evaluation trials (ground truth), measurements
    true_scene, truth, controls, _ = make_trials(args, args.trials, seed=args.seed)
    T, B = args.steps, args.trials
    gen = torch.Generator().manual_seed(args.seed + 1)
    _, _, occluded = schedule(T)
    sigma = torch.tensor([args.vision_sigma] * 2 + [args.vision_sigma_theta], dtype=F64)
    y = truth.q[1:, :, 0] + sigma * torch.randn(T, B, 3, generator=gen, dtype=F64)
    y[occluded] = math.nan
    tactile = tactile_array(args)
    readings = tactile_readings(true_scene, truth, tactile, gen)
    q0 = truth.q[0, :, 0]
    prior_std = torch.tensor([0.005, 0.005, 0.05, 0.01, 0.01, 0.1], dtype=F64)
    noisy = q0 + prior_std[:3] * torch.randn(B, 3, generator=gen, dtype=F64)
    prior_mean = torch.cat([noisy, torch.zeros(B, 3, dtype=F64)], -1)
    prior = Gaussian(prior_mean, torch.diag(prior_std.pow(2)).expand(B, 6, 6).contiguous())
    progress.update()

    model_scene = triangle_scene(args.friction_model)
    model = PlanarContactModel(
        scene=model_scene,
        modes=table,
        Q=torch.diag(torch.tensor([1e-7] * 3 + [1e-4, 1e-4, 1e-2], dtype=F64)),
        R=torch.diag(sigma.pow(2)),
        transition=transition,
        initial=torch.full((K,), 1.0 / K, dtype=F64),
    )
    outputs: dict[str, dict[str, Tensor]] = {}
    seconds: dict[str, float] = {}
    runners = {
        "rbpf": lambda: run_rbpf(model, args, prior, y, readings, tactile, truth, controls, gen),
        "pf": lambda: run_pf(
            model_scene, table, args, prior, y, readings, tactile, truth, controls, gen
        ),
        "ekf": lambda: run_ekf(args, prior, y),
        "vision": lambda: run_vision(prior, y),
    }
    for method, runner in runners.items():
        start = time.perf_counter()
        outputs[method] = runner()
        seconds[method] = time.perf_counter() - start
        progress.update()

    # metrics
    true_pose = truth.q[1:, :, 0]
    true_ids = _mode_ids(truth.mode, table)  # (T, B), K when unseen in training
    metrics: dict[str, dict[str, float]] = {}
    errors: dict[str, tuple[Tensor, Tensor]] = {}
    for method, out in outputs.items():
        diff = out["pose"] - true_pose
        pos = diff[..., :2].pow(2).sum(-1)  # (T, B)
        ang = wrap_angle(diff[..., 2]).pow(2)
        errors[method] = (pos.sqrt(), ang.sqrt())
        row = {
            "pos_rmse_mm": 1e3 * float(pos.mean().sqrt()),
            "theta_rmse_deg": math.degrees(float(ang.mean().sqrt())),
            "pos_rmse_occ_mm": 1e3 * float(pos[occluded].mean().sqrt()),
            "theta_rmse_occ_deg": math.degrees(float(ang[occluded].mean().sqrt())),
            "ms_per_step": 1e3 * seconds[method] / T,
            "ms_per_step_per_trial": 1e3 * seconds[method] / (T * B),
        }
        if "marginals" in out:
            marg = out["marginals"]
            padded = torch.cat([marg, torch.zeros(T, B, 1, dtype=F64)], -1)
            row["mode_accuracy"] = float((marg.argmax(-1) == true_ids).double().mean())
            p_true = padded.gather(-1, true_ids[..., None]).squeeze(-1)
            row["mode_logprob"] = float(p_true.clamp_min(1e-12).log().mean())
        metrics[method] = row
        for t in range(T):
            writer.add_scalar(f"eval/{method}_pos_err_mm", 1e3 * float(pos[t].mean().sqrt()), t)
            writer.add_scalar(
                f"eval/{method}_theta_err_deg", math.degrees(float(ang[t].mean().sqrt())), t
            )
        for key, value in row.items():
            writer.add_scalar(f"charts/{method}_{key}", value, 0)
    best_baseline = min(metrics[m]["pos_rmse_occ_mm"] for m in ("pf", "ekf", "vision"))
    summary = {
        "table_size": K,
        "true_mode_in_table": float((true_ids < K).double().mean()),
        "occlusion_ratio_vs_best_baseline": metrics["rbpf"]["pos_rmse_occ_mm"] / best_baseline,
        "min_height": float(truth.q[..., 0, 1].min()),
        "min_vertex_height": _min_vertex_height(truth),
    }
    ratio = summary["occlusion_ratio_vs_best_baseline"]
    writer.add_scalar("charts/occlusion_ratio_vs_best_baseline", ratio, 0)
    progress.update()

    _write_table(run_dir / "results.md", args, metrics, summary)
    _plots(run_dir, true_scene, truth, outputs, errors, occluded, true_ids, K)
    writer.close()
    progress.update()
    progress.close()
    return {"metrics": metrics, "run_dir": str(run_dir), **summary}


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


def _write_table(
    path: Path, args: Args, metrics: dict[str, dict[str, float]], summary: dict[str, float]
) -> None:
    keys = [
        "pos_rmse_mm",
        "pos_rmse_occ_mm",
        "theta_rmse_deg",
        "theta_rmse_occ_deg",
        "mode_accuracy",
        "mode_logprob",
        "ms_per_step",
        "ms_per_step_per_trial",
    ]
    lines = [
        f"# Triangle grasp tracking ({args.trials} trials, {args.steps} steps)",
        "",
        f"RBPF {args.rbpf_particles} particles, PF {args.pf_particles} particles; "
        f"mode table {summary['table_size']} modes from {args.train_trials} training rollouts; "
        f"true mode in table {100 * summary['true_mode_in_table']:.1f} % of steps.",
        "Times are for all trials batched together (per step, and per step per trial).",
        "",
        "| method | " + " | ".join(keys) + " |",
        "|---" * (len(keys) + 1) + "|",
    ]
    for method, row in metrics.items():
        cells = [f"{row[k]:.3f}" if k in row else "–" for k in keys]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    lines += [
        "",
        f"RBPF occlusion position RMSE / best baseline: "
        f"{summary['occlusion_ratio_vs_best_baseline']:.3f} (target <= 0.5)",
        f"Lowest triangle vertex height over all ground-truth steps: "
        f"{1e3 * summary['min_vertex_height']:.3f} mm",
    ]
    path.write_text("\n".join(lines) + "\n")


def _plots(
    run_dir: Path,
    scene: Scene,
    truth: Rollout,
    outputs: dict[str, dict[str, Tensor]],
    errors: dict[str, tuple[Tensor, Tensor]],
    occluded: Tensor,
    true_ids: Tensor,
    K: int,
) -> None:
    T = occluded.shape[0]
    time_s = 0.01 * torch.arange(1, T + 1)
    occ = time_s[occluded]
    # trajectory of trial 0 with the RBPF cloud
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.5))
    for ax, t in zip(axes, (T // 4, T // 2, int(0.75 * T)), strict=True):
        draw_scene(ax, scene, q=truth.q[t + 1, 0], q_kinematic=truth.q_kinematic[t + 1, 0])
        cloud = outputs["rbpf"]["cloud"][t]
        ax.plot(cloud[:, 0], cloud[:, 1], ".", color="C3", ms=2, label="RBPF particles")
        pf = outputs["pf"]["cloud"][t]
        ax.plot(pf[:, 0], pf[:, 1], ".", color="C2", ms=2, alpha=0.5, label="PF particles")
        for method, marker in (("rbpf", "x"), ("ekf", "+"), ("vision", "s")):
            p = outputs[method]["pose"][t, 0]
            ax.plot(p[0], p[1], marker, color="k", ms=6, mfc="none", label=method)
        ax.set_xlim(-0.08, 0.08)
        ax.set_ylim(-0.01, 0.08)
        ax.set_title(f"t = {float(time_s[t]):.2f} s" + (" (occluded)" if occluded[t] else ""))
    axes[0].legend(fontsize=6, loc="upper left")
    fig.tight_layout()
    fig.savefig(run_dir / "trajectory.png", dpi=90)
    plt.close(fig)
    # errors over time
    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    for method, (pos, ang) in errors.items():
        axes[0].plot(time_s, 1e3 * pos.pow(2).mean(-1).sqrt(), label=method)
        axes[1].plot(time_s, torch.rad2deg(ang.pow(2).mean(-1).sqrt()), label=method)
    for ax in axes:
        ax.axvspan(float(occ[0]), float(occ[-1]), color="0.85", label="occluded")
    axes[0].set_ylabel("position RMSE (mm)")
    axes[1].set_ylabel("angle RMSE (deg)")
    axes[1].set_xlabel("time (s)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(run_dir / "errors.png", dpi=90)
    plt.close(fig)
    # mode timeline of trial 0
    fig, ax = plt.subplots(figsize=(8, 3))
    marg = outputs["rbpf"]["marginals"][:, 0]
    ax.imshow(
        marg.T,
        aspect="auto",
        origin="lower",
        cmap="Blues",
        extent=(float(time_s[0]) - 0.005, float(time_s[-1]) + 0.005, -0.5, K - 0.5),
    )
    ax.plot(time_s, true_ids[:, 0], "r.", ms=4, label=f"true mode ({K} = not in table)")
    ax.plot(time_s, marg.argmax(-1), "k+", ms=4, label="RBPF MAP")
    ax.axvspan(float(occ[0]), float(occ[-1]), color="0.5", alpha=0.15)
    ax.set_ylabel("mode id")
    ax.set_xlabel("time (s)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(run_dir / "modes.png", dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    """Parse the command line and run."""
    result = run(parse_dataclass(Args, argv, __doc__.splitlines()[0]))
    print(Path(result["run_dir"], "results.md").read_text())


if __name__ == "__main__":
    main()
