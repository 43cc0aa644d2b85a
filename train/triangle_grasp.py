"""Tracking a triangle grasped by a parallel-jaw gripper: the contact RBPF against baselines.

A triangle (8 cm sides, 0.2 kg) rests on a table in a vertical plane; two kinematic fingers
close on it from both sides (their twists are the control), push it into the middle of the
gripper, hold it and open again. A camera sees the triangle's pose with Gaussian noise except
while the fingers are close (occlusion: the measurement is NaN); a tactile array on the
triangle's edges reads contacts with false positives and negatives; the finger poses are known.

The pipeline is :mod:`torchcontact.experiments`'s (``grasp_trials``, ``run_estimators``,
``evaluate_tracking``; the estimators are described there: ``rbpf``, the contact RBPF with its
projection out of contact; ``pf`` and ``pf_same_n``, the simulator particle filter with as many
particles as fit in the RBPF's CPU time per step and with the RBPF's count; ``ekf``; held
``vision``). This script is its command line: it checks the arguments, opens a run folder and
writes TensorBoard logs, the table and the plots.

Ground truth is the simulator (exact LCP fallback), with per-trial friction and initial pose.

Usage::

    python train/triangle_grasp.py --trials 64 --name triangle_grasp

writes TensorBoard logs, ``results.md``, ``metrics.json`` and the plots to a new run folder,
``runs/triangle_grasp__<seed>__<unix time>``; with ``--write-logs`` also each trial as an
MCAP run log in its ``logs/`` folder (``train/replay.py`` replays an estimator over them).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import torch
import tyro
from torch import Tensor
from tqdm import tqdm

from torchcontact.experiments import (
    GRASP_METHODS,
    GraspTrials,
    RunLog,
    TriangleGrasp,
    check_int,
    check_name,
    evaluate_tracking,
    grasp_contact_model,
    grasp_summary,
    grasp_trials,
    new_run_dir,
    plot_grasp_snapshots,
    plot_mode_timeline,
    plot_tracking_errors,
    run_estimators,
    tracking_table,
    write_grasp_logs,
)


@dataclass(frozen=True)
class Args(TriangleGrasp):
    """Arguments of the triangle-grasp tracking experiment."""

    name: str = "triangle_grasp"
    """experiment name: the run writes to <out-dir>/<name>__<seed>__<unix time>"""
    out_dir: str = "runs"
    """parent of the run folders"""
    fast: bool = False
    """tiny budget (tests)"""
    write_logs: bool = False
    """also write each trial as an MCAP run log, <run folder>/logs/trial_<b>.mcap"""


def check_args(args: Args) -> None:
    """Check every argument before any work (``rbpf_particles >= K`` is checked once the
    training rollouts have given the number of modes K).

    Raises:
        ValueError: an argument is out of range; the message names it and its range.
    """
    check_name("name", args.name)
    args.check()


def run(args: Args) -> dict[str, Any]:
    """Simulate the trials, run every estimator, write logs, table and plots.

    The run writes to a new folder, :func:`~torchcontact.experiments.new_run_dir`.

    Returns:
        ``{"metrics": {method: {metric: float}}, "run_dir": str, "pf_particles": int,
        "calibration": {particles: seconds}, "ratio_pos_occ": float, ...}`` (see
        :func:`~torchcontact.experiments.grasp_summary`).

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
    progress = tqdm(total=len(GRASP_METHODS) + 3, desc="triangle grasp")
    trials = grasp_trials(args)
    model = grasp_contact_model(args, trials)
    check_int(
        "rbpf_particles",
        args.rbpf_particles,
        low=model.num_modes,
        why="the number of modes K the training rollouts gave the RBPF",
    )
    progress.update()
    run_dir = new_run_dir(out_dir=args.out_dir, name=args.name, seed=args.seed)
    if args.write_logs:
        write_grasp_logs(run_dir / "logs", args, trials)
    log = RunLog(run_dir, args)
    writer = log.writer
    runs = run_estimators(args, trials, model, done=lambda _: progress.update())
    outputs, timings, particles = runs.outputs, runs.timings, runs.particles

    metrics, errors = evaluate_tracking(trials, outputs)
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
    summary = grasp_summary(trials, metrics)
    summary["calibration"] = runs.calibration
    summary["pf_particles"] = particles["pf"]
    for key in ("ratio_pos_occ", "ratio_theta_occ"):
        writer.add_scalar(f"charts/{key}", summary[key], 0)
    progress.update()

    (run_dir / "metrics.json").write_text(json.dumps({"metrics": metrics, **summary}, indent=2))
    write_table(run_dir / "results.md", args, metrics, summary)
    save_plots(run_dir, trials, outputs, errors, metrics)
    # SPS: tracked steps (every trial's, through every estimator) per second of the run.
    log.steps_per_second(trials.batch * trials.steps * len(outputs), 0)
    log.close()
    progress.update()
    progress.close()
    return {"metrics": metrics, "run_dir": str(run_dir), **summary}


def write_table(
    path: Path, args: Args, metrics: dict[str, dict[str, float]], summary: dict[str, Any]
) -> None:
    """``results.md``: settings, the table, the calibration and the RBPF's error ratios."""
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
        tracking_table(metrics),
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


def save_plots(
    run_dir: Path,
    trials: GraspTrials,
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
        "snapshots": plot_grasp_snapshots(trials, outputs, [T // 5, int(0.45 * T), int(0.8 * T)]),
        "errors": plot_tracking_errors(trials, errors, labels),
        "modes": plot_mode_timeline(trials, outputs["rbpf"]["marginals"]),
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
