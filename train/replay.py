"""Replay an estimator of the triangle-grasp experiment over recorded run logs.

The logs are MCAP files of :mod:`torchcontact.logs`, one per trial: those that
``train/triangle_grasp.py --write-logs`` writes, or recorded runs in the same format. The
estimator (``rbpf``, ``pf``, ``pf_same_n``, ``ekf`` or ``vision``) runs over all of them
batched, with the experiment's code and seeds, and is scored as in the experiment
(:func:`~torchcontact.experiments.replay`): over the logs of an experiment's run, with its
settings, the estimates are the experiment's.

Usage::

    python train/triangle_grasp.py --trials 64 --write-logs   # logs in <run folder>/logs/
    python train/replay.py --logs runs/triangle_grasp__0__<unix time>/logs --filter rbpf

writes ``results.md``, ``metrics.json``, ``estimates.pt`` (the per-step estimates and errors)
and TensorBoard logs to a new run folder, ``runs/replay__<seed>__<unix time>``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
import tyro
from torch.utils.tensorboard import SummaryWriter

from torchcontact.experiments import (
    GRASP_METHODS,
    TriangleGrasp,
    check_choice,
    check_name,
    logged_settings,
    new_run_dir,
    replay,
    tracking_table,
)
from torchcontact.logs import read_run


@dataclass(frozen=True)
class Args(TriangleGrasp):
    """Arguments of the replay (the settings apply with ``--settings args``)."""

    logs: tuple[str, ...] = ()
    """the run logs: .mcap files, or folders whose .mcap files are all read (by name)"""
    filter: str = "rbpf"
    """the estimator: rbpf, pf, pf_same_n, ekf or vision"""
    settings: Literal["log", "args"] = "log"
    """'log': the settings the logs record (with --pf-particles if > 0); 'args': these"""
    name: str = "replay"
    """run name: the run writes to <out-dir>/<name>__<seed>__<unix time>"""
    out_dir: str = "runs"
    """parent of the run folders"""


def log_paths(logs: tuple[str, ...]) -> list[Path]:
    """The log files: each file given, and each folder's ``*.mcap`` files sorted by name.

    Raises:
        ValueError: no logs given, a path is neither a file nor a folder, or a folder holds
            no ``.mcap`` file.
    """
    if not logs:
        raise ValueError("logs: expected at least one .mcap file or folder, got none")
    paths: list[Path] = []
    for entry in map(Path, logs):
        if entry.is_dir():
            found = sorted(entry.glob("*.mcap"))
            if not found:
                raise ValueError(f"logs: the folder {str(entry)!r} holds no .mcap file")
            paths += found
        elif entry.is_file():
            paths.append(entry)
        else:
            raise ValueError(f"logs: {str(entry)!r} is neither a file nor a folder")
    return paths


def check_args(args: Args) -> list[Path]:
    """Check the arguments before any work and return the log files.

    Raises:
        ValueError: an argument is out of range; the message names it.
    """
    check_name("name", args.name)
    check_choice("filter", args.filter, GRASP_METHODS)
    check_choice("settings", args.settings, ("log", "args"))
    if args.settings == "args":
        args.check()
    return log_paths(args.logs)


def run(args: Args) -> dict[str, Any]:
    """Read the logs, replay the estimator, write the results.

    Returns:
        ``{"metrics": {filter: {metric: float}}, "run_dir": str, "logs": [str]}``.

    Raises:
        ValueError: an argument is out of range, or a log is not readable or does not fit the
            triangle grasp.
    """
    paths = check_args(args)
    logs = [read_run(path) for path in paths]
    if args.settings == "log":
        settings = logged_settings(logs)
        if args.pf_particles > 0:
            settings = dataclasses.replace(settings, pf_particles=args.pf_particles)
    else:
        names = [f.name for f in dataclasses.fields(TriangleGrasp)]
        settings = TriangleGrasp(**{name: getattr(args, name) for name in names})
    result = replay(logs, filter=args.filter, settings=settings)
    method, steps, batch = result.method, result.trials.steps, result.trials.batch

    run_dir = new_run_dir(out_dir=args.out_dir, name=args.name, seed=settings.seed)
    writer = SummaryWriter(str(run_dir))
    row = dict(result.metrics)
    row["particles"] = float(result.particles)
    row["ms_per_step"] = 1e3 * result.timing.wall / steps
    row["cpu_ms_per_step"] = 1e3 * result.timing.cpu / steps
    row["cpu_ms_per_step_per_trial"] = row["cpu_ms_per_step"] / batch
    for key, value in row.items():
        writer.add_scalar(f"charts/{method}_{key}", value, 0)
    pos, ang = result.errors
    for t in range(steps):
        writer.add_scalar(f"eval/{method}_pos_err_mm", 1e3 * float(pos[t].pow(2).mean().sqrt()), t)
        writer.add_scalar(
            f"eval/{method}_theta_err_deg", math.degrees(float(ang[t].pow(2).mean().sqrt())), t
        )
    writer.close()
    metrics = {method: row}
    saved = {
        "filter": method,
        "metrics": metrics,
        "logs": [str(path) for path in paths],
        "settings": dataclasses.asdict(settings),
    }
    (run_dir / "metrics.json").write_text(json.dumps(saved, indent=2))
    torch.save({**result.output, "pos_err": pos, "theta_err": ang}, run_dir / "estimates.pt")
    (run_dir / "results.md").write_text(
        f"# Replay of {method} over {batch} logs ({steps} steps, seed {settings.seed})\n\n"
        + tracking_table(metrics)
        + "\n"
    )
    return {"metrics": metrics, "run_dir": str(run_dir), "logs": saved["logs"]}


def main(argv: list[str] | None = None) -> None:
    """Parse the command line and run (on one thread, as the experiment's timings)."""
    torch.set_num_threads(1)
    result = run(tyro.cli(Args, args=argv, description=__doc__.splitlines()[0]))
    print(Path(result["run_dir"], "results.md").read_text())


if __name__ == "__main__":
    main()
