"""Fitting friction and camera noise from the contact RBPF's evidence: gradient, grid, CMA-ES.

Each experiment draws a true friction coefficient μ and camera noise σ, simulates boxes
sliding to a stop under that camera, and maximizes the contact RBPF's evidence
``log p(y | μ, σ)`` three ways on the same logs: by gradient (L-BFGS through the filter,
``torchcontact.filters.fit_parameters``, with standard errors), over a grid, and by CMA-ES.
The pipeline is :mod:`torchcontact.experiments`'s (``sliding_logs``, ``sliding_evidence``,
``FITTERS``); this script is its command line.

Usage::

    python train/fit_params.py --rounds 8

writes TensorBoard logs, ``results.md``, ``metrics.json`` and a checkpoint after every
experiment to ``runs/fit_params__<seed>__<unix time>``; ``--resume <run folder>`` continues a
killed run (or adds experiments with a larger ``--rounds``).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tyro
from tqdm import tqdm

from torchcontact.experiments import (
    CHECKPOINT,
    FIT_METHODS,
    FITTERS,
    RunLog,
    SlidingFit,
    check_int,
    check_name,
    check_real,
    open_run,
    save_checkpoint,
    sliding_evidence,
    sliding_logs,
)


@dataclass(frozen=True)
class Args(SlidingFit):
    """Arguments of the fitting experiment."""

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
    check_name("name", args.name)


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
        )
    check_args(args)
    run_dir, saved = open_run(args, keys=("experiments",))
    experiments: list[dict[str, Any]] = [] if saved is None else list(saved["experiments"])
    log = RunLog(run_dir, args)
    writer = log.writer
    first = len(experiments)
    for index in tqdm(range(first, args.rounds), desc="fit experiments"):
        logs = sliding_logs(args, index)
        evidence = sliding_evidence(logs, args.particles)
        row: dict[str, Any] = {"mu": logs.mu, "sigma_mm": logs.sigma_mm}
        for method in FIT_METHODS:
            outcome = FITTERS[method](evidence, args)
            row[method] = dataclasses.asdict(outcome)
            writer.add_scalar(f"charts/{method}_mu_abs_error", abs(outcome.mu - logs.mu), index)
            writer.add_scalar(
                f"charts/{method}_sigma_abs_error_mm", abs(outcome.sigma_mm - logs.sigma_mm), index
            )
            writer.add_scalar(f"charts/{method}_seconds", outcome.seconds, index)
            writer.add_scalar(f"losses/{method}_neg_log_evidence", -outcome.log_evidence, index)
        experiments.append(row)
        # SPS: camera frames fitted (every box's steps, once per experiment) per second.
        log.steps_per_second((index + 1 - first) * args.trials * args.steps, index)
        save_checkpoint(
            run_dir / CHECKPOINT, {"args": dataclasses.asdict(args), "experiments": experiments}
        )
    summary = summarize(experiments)
    for method, values in summary.items():
        for key, value in values.items():
            writer.add_scalar(f"eval/{method}_{key}", value, len(experiments))
    log.close()
    (run_dir / "metrics.json").write_text(
        json.dumps({"experiments": experiments, "summary": summary}, indent=2)
    )
    write_table(run_dir / "results.md", args, experiments, summary)
    return {"run_dir": str(run_dir), "experiments": experiments, "summary": summary}


def summarize(experiments: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Per method: mean absolute errors of μ and σ, mean evaluations and seconds, and the mean
    shortfall of its evidence from the best of the three methods on the same experiment."""
    summary = {}
    for method in FIT_METHODS:
        rows = [experiment[method] for experiment in experiments]
        best = [max(e[m]["log_evidence"] for m in FIT_METHODS) for e in experiments]
        summary[method] = {
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
    lines = [
        f"# Fitting friction and camera noise ({len(experiments)} experiments, "
        f"{args.trials} boxes × {args.steps} steps each, RBPF {args.particles} particles)",
        "",
        "| method | mean abs. error μ | mean abs. error σ (mm) | evidence below best (nats) "
        "| evaluations | seconds |",
        "|---|--:|--:|--:|--:|--:|",
    ]
    for method, row in summary.items():
        lines.append(
            f"| {method} | {row['mu_abs_error']:.4f} | {row['sigma_abs_error_mm']:.3f} "
            f"| {row['evidence_shortfall']:.2f} | {row['evaluations']:.0f} | {row['seconds']:.1f} |"
        )
    lines += [
        "",
        "| experiment | true μ | true σ (mm) | gradient μ ± s.e. | grid μ | CMA-ES μ |",
        "|--:|--:|--:|--:|--:|--:|",
    ]
    for index, e in enumerate(experiments):
        gradient = e["gradient"]
        lines.append(
            f"| {index} | {e['mu']:.4f} | {e['sigma_mm']:.3f} "
            f"| {gradient['mu']:.4f} ± {gradient['mu_error']:.4f} | {e['grid']['mu']:.4f} "
            f"| {e['cma']['mu']:.4f} |"
        )
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> None:
    """Parse the arguments (``tyro``), run, print the table."""
    doc = __doc__ or ""
    result = run(tyro.cli(Args, args=argv, description=doc.splitlines()[0]))
    print((Path(result["run_dir"]) / "results.md").read_text())


if __name__ == "__main__":
    main()
