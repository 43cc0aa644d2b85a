"""Fitting friction and camera noise from the contact RBPF's evidence: gradient, grid, CMA-ES.

Each experiment (trial) draws a true friction coefficient μ and camera noise σ, simulates its
logs under that camera, and maximizes the contact RBPF's evidence ``log p(y | μ, σ)`` three
ways on the same logs: by gradient (L-BFGS through the filter,
``torchcontact.filters.fit_parameters``, with standard errors), over a grid, and by CMA-ES.
``--experiment sliding-box``: boxes sliding to a stop (``sliding_logs``,
``sliding_evidence``); ``--experiment triangle-grasp``: grasps of a triangle launched along
the table, the grasp experiment's RBPF (``grasp_fit_logs``, ``grasp_fit_evidence``; its
settings are ``--grasp.*``, its seed and trials ``--seed`` and ``--rounds``). The pipeline is
:mod:`torchcontact.experiments`'s; this script is its command line.

Usage::

    python train/fit_params.py --rounds 8
    python train/fit_params.py --experiment triangle-grasp --rounds 16

writes TensorBoard logs, ``results.md``, ``metrics.json`` and a checkpoint after every
experiment to ``runs/fit_params__<seed>__<unix time>``; ``--resume <run folder>`` continues a
killed run (or adds experiments with a larger ``--rounds``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import statistics
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
import tyro
from tqdm import tqdm

from torchcontact.experiments import (
    CHECKPOINT,
    FIT_METHODS,
    FITTERS,
    FitSearch,
    GraspFit,
    RunLog,
    SlidingFit,
    check_choice,
    check_int,
    check_name,
    check_real,
    grasp_fit_evidence,
    grasp_fit_logs,
    open_run,
    save_checkpoint,
    sliding_evidence,
    sliding_logs,
)

EXPERIMENTS = ("sliding-box", "triangle-grasp")


@dataclass(frozen=True)
class Args(SlidingFit):
    """Arguments of the fitting experiment."""

    experiment: Literal["sliding-box", "triangle-grasp"] = "sliding-box"
    """the set-up whose logs are fitted"""
    grasp: GraspFit = field(default_factory=GraspFit)
    """settings of the triangle-grasp experiment (its seed and rounds are --seed and --rounds)"""
    methods: tuple[str, ...] = FIT_METHODS
    """fitting methods to run, of gradient, grid, cma"""
    threads: int = 1
    """torch threads (timings are per trial on this many)"""
    name: str = "fit_params"
    """experiment name: the run writes to <out-dir>/<name>__<seed>__<unix time>"""
    out_dir: str = "runs"
    """parent of the run folders"""
    resume: str | None = None
    """run folder to continue (same arguments; --rounds may grow)"""
    fast: bool = False
    """tiny budget (tests)"""


def check_args(args: Args) -> None:
    """Check every argument before any work.

    Raises:
        ValueError: naming the argument out of range.
    """
    check_choice("experiment", args.experiment, EXPERIMENTS)
    if not args.methods:
        raise ValueError("methods: expected at least one method")
    for method in args.methods:
        check_choice("methods", method, FIT_METHODS)
    check_int("threads", args.threads, low=1)
    check_int("seed", args.seed, low=0)
    check_int("rounds", args.rounds, low=1)
    check_int("trials", args.trials, low=1)
    check_int("steps", args.steps, low=2)
    check_int("particles", args.particles, low=2)
    check_int("grid_points", args.grid_points, low=2)
    check_int("cma_evaluations", args.cma_evaluations, low=4)
    for name, (low, high) in (("mu_range", args.mu_range), ("sigma_mm_range", args.sigma_mm_range)):
        check_real(name, low, low=0.0)
        if not high > low:
            raise ValueError(f"{name}: expected low < high, got ({low}, {high})")
    grasp = args.grasp
    check_int("grasp.grasps", grasp.grasps, low=1)
    check_int("grasp.steps", grasp.steps, low=8)
    check_int("grasp.particles", grasp.particles, low=2)
    check_int("grasp.train_trials", grasp.train_trials, low=1)
    check_int("grasp.grid_points", grasp.grid_points, low=2)
    check_int("grasp.cma_evaluations", grasp.cma_evaluations, low=4)
    for name, (low, high) in (
        ("grasp.mu_range", grasp.mu_range),
        ("grasp.finger_mu_range", grasp.finger_mu_range),
        ("grasp.sigma_mm_range", grasp.sigma_mm_range),
        ("grasp.speed_range", grasp.speed_range),
    ):
        check_real(name, low, low=0.0)
        if not high >= low:
            raise ValueError(f"{name}: expected low <= high, got ({low}, {high})")
    for name in ("speed_std", "pose_noise", "twist_noise"):
        check_real(f"grasp.{name}", getattr(grasp, name), low=0.0, low_open=True)
    check_name("name", args.name)


def experiment_settings(args: Args) -> FitSearch:
    """The settings of ``args.experiment`` (the grasp's with ``args``' seed and rounds)."""
    if args.experiment == "triangle-grasp":
        return dataclasses.replace(args.grasp, seed=args.seed, rounds=args.rounds)
    return args


def trial_evidence(
    args: Args, index: int
) -> tuple[dict[str, float], Callable[[dict[str, torch.Tensor]], torch.Tensor]]:
    """Trial ``index``'s true parameters and its evidence function."""
    if args.experiment == "triangle-grasp":
        grasp_logs = grasp_fit_logs(dataclasses.replace(args.grasp, seed=args.seed), index)
        truth = {
            "mu": grasp_logs.mu,
            "sigma_mm": grasp_logs.sigma_mm,
            "finger_mu": grasp_logs.finger_mu,
        }
        return truth, grasp_fit_evidence(grasp_logs)
    logs = sliding_logs(args, index)
    return {"mu": logs.mu, "sigma_mm": logs.sigma_mm}, sliding_evidence(logs, args.particles)


def run(args: Args) -> dict[str, Any]:
    """Run (or continue) the experiments; write logs, checkpoint, table and metrics.

    Returns:
        ``{"run_dir": str, "experiments": [{"mu": .., "sigma_mm": .., method: {...}}],
        "summary": {method: {metric: float}}}``.
    """
    if args.fast:
        args = dataclasses.replace(
            args,
            rounds=min(args.rounds, 1),
            trials=min(args.trials, 2),
            steps=min(args.steps, 12),
            grid_points=min(args.grid_points, 3),
            cma_evaluations=min(args.cma_evaluations, 12),
            grasp=dataclasses.replace(
                args.grasp,
                grasps=min(args.grasp.grasps, 1),
                steps=min(args.grasp.steps, 16),
                train_trials=min(args.grasp.train_trials, 4),
                grid_points=min(args.grasp.grid_points, 3),
                cma_evaluations=min(args.grasp.cma_evaluations, 8),
            ),
        )
    check_args(args)
    torch.set_num_threads(args.threads)
    settings = experiment_settings(args)
    run_dir, saved = open_run(args, keys=("experiments",))
    experiments: list[dict[str, Any]] = [] if saved is None else list(saved["experiments"])
    log = RunLog(run_dir, args)
    writer = log.writer
    first = len(experiments)
    for index in tqdm(range(first, args.rounds), desc="fit experiments"):
        truth, evidence = trial_evidence(args, index)
        row: dict[str, Any] = dict(truth)
        for method in args.methods:
            outcome = FITTERS[method](evidence, settings)
            row[method] = dataclasses.asdict(outcome)
            writer.add_scalar(f"charts/{method}_mu_abs_error", abs(outcome.mu - truth["mu"]), index)
            writer.add_scalar(
                f"charts/{method}_sigma_abs_error_mm",
                abs(outcome.sigma_mm - truth["sigma_mm"]),
                index,
            )
            writer.add_scalar(f"charts/{method}_seconds", outcome.seconds, index)
            writer.add_scalar(f"losses/{method}_neg_log_evidence", -outcome.log_evidence, index)
        experiments.append(row)
        # SPS: camera frames fitted (every recorded step, once per experiment) per second.
        frames = (
            args.grasp.grasps * args.grasp.steps
            if args.experiment == "triangle-grasp"
            else args.trials * args.steps
        )
        log.steps_per_second((index + 1 - first) * frames, index)
        save_checkpoint(
            run_dir / CHECKPOINT, {"args": dataclasses.asdict(args), "experiments": experiments}
        )
    summary = summarize(experiments, args.methods)
    for method, values in summary.items():
        for key, value in values.items():
            writer.add_scalar(f"eval/{method}_{key}", value, len(experiments))
    log.close()
    (run_dir / "metrics.json").write_text(
        json.dumps({"experiments": experiments, "summary": summary}, indent=2)
    )
    write_table(run_dir / "results.md", args, experiments, summary)
    return {"run_dir": str(run_dir), "experiments": experiments, "summary": summary}


def summarize(
    experiments: list[dict[str, Any]], methods: tuple[str, ...] = FIT_METHODS
) -> dict[str, dict[str, float]]:
    """Per method: mean absolute errors of μ and σ, median absolute relative errors of μ and
    σ, mean evaluations and seconds, and the mean shortfall of its evidence from the best of
    the methods on the same experiment."""
    summary = {}
    for method in methods:
        rows = [experiment[method] for experiment in experiments]
        best = [max(e[m]["log_evidence"] for m in methods) for e in experiments]
        summary[method] = {
            "mu_median_rel_error": statistics.median(
                abs(r["mu"] / e["mu"] - 1) for r, e in zip(rows, experiments, strict=True)
            ),
            "sigma_median_rel_error": statistics.median(
                abs(r["sigma_mm"] / e["sigma_mm"] - 1)
                for r, e in zip(rows, experiments, strict=True)
            ),
            "mu_abs_error": _mean(
                abs(r["mu"] - e["mu"]) for r, e in zip(rows, experiments, strict=True)
            ),
            "sigma_abs_error_mm": _mean(
                abs(r["sigma_mm"] - e["sigma_mm"]) for r, e in zip(rows, experiments, strict=True)
            ),
            "evidence_shortfall": _mean(
                b - r["log_evidence"] for r, b in zip(rows, best, strict=True)
            ),
            "evaluations": _mean(r["evaluations"] for r in rows),
            "seconds": _mean(r["seconds"] for r in rows),
            "cpu_seconds": _mean(r["cpu_seconds"] for r in rows),
        }
    return summary


def _mean(values: Any) -> float:
    items = list(values)
    return math.fsum(items) / len(items)


def write_table(
    path: Path,
    args: Args,
    experiments: list[dict[str, Any]],
    summary: dict[str, dict[str, float]],
) -> None:
    """The results as Markdown: the summary per method, then every experiment."""
    if args.experiment == "triangle-grasp":
        grasp = args.grasp
        what = (
            f"triangle grasp, {grasp.grasps} grasps × {grasp.steps} steps each, "
            f"RBPF {grasp.particles} particles"
        )
    else:
        what = f"{args.trials} boxes × {args.steps} steps each, RBPF {args.particles} particles"
    lines = [
        f"# Fitting friction and camera noise ({len(experiments)} experiments, {what}, "
        f"{args.threads} thread(s))",
        "",
        "| method | median abs. rel. error μ | median abs. rel. error σ | mean abs. error μ "
        "| mean abs. error σ (mm) | evidence below best (nats) | evaluations | wall s per trial "
        "| CPU s per trial |",
        "|---|--:|--:|--:|--:|--:|--:|--:|--:|",
    ]
    for method, row in summary.items():
        lines.append(
            f"| {method} | {row['mu_median_rel_error']:.2%} | {row['sigma_median_rel_error']:.2%} "
            f"| {row['mu_abs_error']:.4f} | {row['sigma_abs_error_mm']:.3f} "
            f"| {row['evidence_shortfall']:.2f} | {row['evaluations']:.0f} | {row['seconds']:.1f} "
            f"| {row['cpu_seconds']:.1f} |"
        )
    methods = list(summary)
    lines += [
        "",
        "| experiment | true μ | true σ (mm) | "
        + " | ".join(f"{m} μ | {m} σ (mm) | {m} CPU s" for m in methods)
        + " |",
        "|--:|--:|--:|" + "--:|" * (3 * len(methods)),
    ]
    for index, e in enumerate(experiments):
        cells = []
        for m in methods:
            mu = f"{e[m]['mu']:.4f}"
            if m == "gradient":
                mu += f" ± {e[m]['mu_error']:.4f}"
            cells += [mu, f"{e[m]['sigma_mm']:.3f}", f"{e[m]['cpu_seconds']:.1f}"]
        lines.append(
            f"| {index} | {e['mu']:.4f} | {e['sigma_mm']:.3f} | " + " | ".join(cells) + " |"
        )
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> None:
    """Parse the arguments (``tyro``), run, print the table."""
    doc = __doc__ or ""
    result = run(tyro.cli(Args, args=argv, description=doc.splitlines()[0]))
    print((Path(result["run_dir"]) / "results.md").read_text())


if __name__ == "__main__":
    main()
