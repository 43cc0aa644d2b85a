"""Tracking a box that a BarrettHand grasps, pushes or tips over: the contact RBPF and baselines.

The WAM carries the BarrettHand palm down to a box lying on a table (WAM joints along a
planned approach, the hand's fingers servoed) and the hand closes. Per trial the box's size,
mass, friction and initial pose are drawn (:class:`~torchcontact.experiments.BarrettBoxGrasp`
states the ranges); the hand aims at the nominal position, so in some trials the first
finger to touch tips the box over about its bottom edge before the grasp closes, in others
it slides into the grasp or is grasped cleanly. A Kinect-like camera (5 mm, 2°) sees the box
until the fingers start closing (occluded from then on, by phase); the BarrettHand's tactile
pads read contacts with false positives and negatives; the robot's joint angles are known.
The filters assume the nominal mass and friction, and know each box's size (a camera measures
it before the grasp; ``--no-known-size``: the nominal size too).

Estimators (:func:`~torchcontact.experiments.run_box_estimators`), all batched over trials:
``rbpf`` (the spatial contact RBPF, all-modes proposal: with few modes every mode of every
particle is predicted exactly, no sampling noise in the mode; projection out of contact
after each step), ``rbpf_no_projection`` (ablation), ``rbpf_servo`` (the hand's fingers
servoed in the RBPF's model, its measured joint velocities evidence for the modes), ``pf``
(the simulator particle filter
with as many particles as fit in the RBPF's CPU time per step), ``pf_same_n`` (the RBPF's
particle count), ``ekf`` (constant velocity on SE(3), no contact) and ``camera`` (the last
pose seen).

Usage::

    python train/barrett_box_grasp.py --trials 32 --name barrett_box_grasp

writes TensorBoard scalars, ``results.md``, ``results.json`` (one record per method) and the
figures to a new run folder, ``runs/<name>__<seed>__<unix time>``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import torch
import tyro
from tqdm import tqdm

from torchcontact.experiments import (
    BOX_METHODS,
    RBPF_METHODS,
    BarrettBoxGrasp,
    BoxEstimatorRuns,
    BoxTrials,
    RunLog,
    box_contact_model,
    box_tracking_table,
    box_trials,
    check_int,
    check_name,
    new_run_dir,
    plot_box_errors,
    plot_box_snapshots,
    plot_box_states,
    run_box_estimators,
    score_box_estimators,
)

METHODS = BOX_METHODS


@dataclass(frozen=True)
class Args(BarrettBoxGrasp):
    """Arguments of the BarrettHand box-grasp experiment."""

    name: str = "barrett_box_grasp"
    """experiment name: the run writes to <out-dir>/<name>__<seed>__<unix time>"""
    out_dir: str = "runs"
    """parent of the run folders"""
    rbpf: bool = True
    """run the contact RBPF (and its ablation); without it pf gets rbpf_particles"""
    projection: bool = True
    """run the RBPFs with the projection out of contact (the rbpf and rbpf_servo rows); the
    ablation runs always"""
    proposal: Literal["all_modes", "bootstrap"] = "all_modes"
    """the RBPF's proposal"""
    known_size: bool = True
    """the filters know each box's size (measured by the camera before the grasp); mass and
    friction are nominal either way"""
    train_trials: int = 16
    """training trials whose rollouts give the RBPF's modes and transition"""
    rbpf_particles: int = 0
    """RBPF particles (and pf_same_n's); 0: the number of modes K (the RBPF needs N >= K)"""
    pf_particles: int = 0
    """plain PF particles; 0: as many as fit in the RBPF's CPU time per step"""
    fast: bool = False
    """tiny budget (tests)"""


def check_args(args: Args) -> None:
    """Check every argument before any work.

    Raises:
        ValueError: an argument is out of range; the message names it and its range.
    """
    check_name("name", args.name)
    check_int("train_trials", args.train_trials, low=1)
    check_int("rbpf_particles", args.rbpf_particles, low=0)
    check_int("pf_particles", args.pf_particles, low=0)
    args.check()


def run(args: Args) -> dict[str, Any]:
    """Simulate the trials, run every estimator, write the logs, tables and figures.

    Returns:
        ``{"metrics": {method: {metric: float}}, "run_dir": str, "tip_share": float,
        "particles": {method: int}, "calibration": {particles: CPU seconds}}``.

    Raises:
        ValueError: an argument is out of range.
    """
    if args.fast:
        args = dataclasses.replace(
            args,
            trials=1,
            trials_per_box=1,
            train_trials=1,
            steps=12,
            rbpf_particles=0,
            pf_particles=args.pf_particles or 2,
        )
    check_args(args)
    torch.manual_seed(args.seed)
    stages = 3 + len(METHODS)
    progress = tqdm(total=stages, desc="barrett box grasp")
    trials = box_trials(args)
    model = None
    if args.rbpf:
        train = box_trials(
            dataclasses.replace(args, trials=args.train_trials), seed=10_000 + args.seed
        )
        model = box_contact_model(args, train)
        if args.rbpf_particles:
            check_int(
                "rbpf_particles",
                args.rbpf_particles,
                low=model.num_modes,
                why="the number of modes K the training rollouts gave the RBPF",
            )
    progress.update()
    run_dir = new_run_dir(out_dir=args.out_dir, name=args.name, seed=args.seed)
    log = RunLog(run_dir, args)
    runs = run_box_estimators(
        args,
        trials,
        rbpf_particles=args.rbpf_particles,
        pf_particles=args.pf_particles,
        model=model,
        rbpf_methods=tuple(m for m in RBPF_METHODS if args.projection or m == "rbpf_no_projection"),
        proposal=args.proposal,
        known_size=args.known_size,
        seed=args.seed,
        done=lambda _: progress.update(),
    )
    metrics = score_box_estimators(trials, runs)
    writer = log.writer
    for method, row in metrics.items():
        for key, value in row.items():
            writer.add_scalar(f"charts/{method}_{key}", value, 0)
        pose = runs.outputs[method]["pose"]
        error = 1e3 * (pose[..., :3] - trials.pose[..., :3]).pow(2).sum(-1).mean(-1).sqrt()
        for t in range(trials.steps):
            writer.add_scalar(f"eval/{method}_pos_err_mm", float(error[t]), t)
    tip_share = float((trials.tip_step >= 0).double().mean())
    writer.add_scalar("charts/tip_share", tip_share, 0)
    progress.update()
    records = [{"method": method, **row} for method, row in metrics.items()]
    summary = {
        "tip_share": tip_share,
        "particles": runs.particles,
        "calibration": runs.calibration,
        "trials": trials.batch,
        "steps": trials.steps,
        "modes": 0 if model is None else model.num_modes,
    }
    (run_dir / "results.json").write_text(
        json.dumps({"methods": records, **summary}, indent=2, default=str)
    )
    write_results(run_dir / "results.md", args, trials, metrics, runs, summary["modes"])
    save_figures(run_dir, trials, runs)
    log.steps_per_second(trials.batch * trials.steps * len(metrics), 0)
    log.close()
    progress.update()
    progress.close()
    return {"metrics": metrics, "run_dir": str(run_dir), **summary}


def write_results(
    path: Path,
    args: Args,
    trials: BoxTrials,
    metrics: dict[str, dict[str, float]],
    runs: BoxEstimatorRuns,
    modes: int,
) -> None:
    """``results.md``: the setting, the table, the calibration and the targets."""
    tips = int((trials.tip_step >= 0).sum())
    lines = [
        f"# BarrettHand box grasp ({trials.batch} trials, {trials.steps} steps, seed {args.seed})",
        "",
        f"{tips} of {trials.batch} trials tip over (tilt > 5°). Occluded from step "
        f"{int(trials.occluded.nonzero()[0])} on. Times: all trials batched on one thread, "
        "wall clock and this process's CPU time. Tip-over detection: the first step at which "
        "the estimated tilt exceeds 5°, against the truth's."
        + (
            f" RBPF: {modes} modes from {args.train_trials} training trials, "
            f"{args.proposal} proposal."
            if modes
            else ""
        )
        + (
            " The filters know each box's size (nominal mass and friction)."
            if args.known_size
            else " The filters assume the nominal size, mass and friction."
        ),
        "",
        box_tracking_table(metrics),
    ]
    if runs.calibration:
        fitted = ", ".join(
            f"{n} → {1e3 * seconds / trials.steps:.0f}" for n, seconds in runs.calibration.items()
        )
        lines += ["", f"PF calibration (particles → CPU ms per step): {fitted}."]
    rbpf_method = next((m for m in RBPF_METHODS if m in metrics), None)
    if rbpf_method is not None:
        rbpf = metrics[rbpf_method]
        lines += ["", f"Targets ({rbpf_method}):", ""]
        # the baselines, each at no more CPU time per step than the RBPF's
        baselines = ("pf", "pf_same_n", "ekf", "camera")
        for key in ("pos_rmse_occ_mm", "rot_rmse_occ_deg"):
            best = min(metrics[m][key] for m in baselines if m in metrics)
            lines.append(f"- {key}: RBPF / best baseline = {rbpf[key] / best:.3f} (target <= 0.5)")
        lines.append(
            f"- contact-state accuracy: {rbpf.get('state_accuracy', math.nan):.3f} (target >= 0.95)"
        )
    else:
        lines += ["", "The RBPF did not run (`--no-rbpf`)."]
    if args.rbpf and not args.projection:
        lines += ["", "The RBPF with the projection (`rbpf`) did not run (`--no-projection`)."]
    path.write_text("\n".join(lines) + "\n")


def save_figures(run_dir: Path, trials: BoxTrials, runs: BoxEstimatorRuns) -> None:
    """``errors.png``, ``snapshots.png`` and ``states.png`` (of the RBPF, else the PF)."""
    T = trials.steps
    labels = {m: f"{m} ({n} particles)" for m, n in runs.particles.items()}
    tipping = (trials.tip_step >= 0).nonzero()
    trial = int(tipping[0]) if len(tipping) else 0
    state_method = "rbpf" if "rbpf" in runs.outputs else "pf"
    figures = {
        "errors": plot_box_errors(trials, runs.outputs, labels),
        "snapshots": plot_box_snapshots(trials, runs.outputs, [T // 5, T // 2, T - 1]),
        "states": plot_box_states(trials, runs.outputs[state_method]["state_probs"], trial=trial),
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
