"""Sweep a train/ script over seeds and settings on Ray: one single-thread task per run.

    python train/sweep.py --script fit_params --seeds 0 1 2 3 --grid particles=8,16 rounds=2
    RAY_ADDRESS=<head>:6379 python train/sweep.py --script dyna_q_peg --seeds 0 1 2 3 4 5 6 7

Runs the script's ``run(args)`` once per seed × setting, each as a Ray task that holds one CPU
and runs torch on one thread. A setting is one combination of the ``--grid`` entries: each
``FIELD=V1,V2,...`` names a field of the script's ``Args`` and its values as they would be
typed on the script's command line (``true``/``false`` for a flag, spaces between a tuple's
items); an entry with one value fixes that field for every task. Ray starts on this machine
(``ray.init()``) unless ``RAY_ADDRESS`` names a cluster to join; the script's source travels
with the tasks, so a cluster's nodes need only torchcontact installed.

Writes ``tasks.json`` (every task's scalar results), the table of means, ranges and Student-t
intervals over the seeds of every setting and metric (``statistics.md``, ``.json``, ``.csv``,
:func:`~torchcontact.experiments.aggregate_seeds`), ``results.md`` and a checkpoint after
every finished task to a new run folder, ``runs/sweep__<first seed>__<unix time>``; each
task writes its own run folder under ``tasks/`` there (or ``--task-out-dir``). A killed sweep
continues with ``--resume <run folder>`` (the same arguments), running only the tasks it
lacks.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import itertools
import json
import os
import sys
import time
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import ray
import torch
import tyro
from tqdm import tqdm

from torchcontact.experiments import (
    CHECKPOINT,
    LOCATION,
    aggregate_seeds,
    check_int,
    check_name,
    check_real,
    new_run_dir,
    read_checkpoint,
    save_checkpoint,
    scalar_metrics,
    statistics_table,
    write_statistics,
)

TRAIN = Path(__file__).resolve().parent
#: Fields of a script's ``Args`` that the sweep sets itself: not allowed in ``--grid``.
_RESERVED = ("seed", "resume", "name", "out_dir")
#: Arguments that may differ when resuming a sweep (they do not change any task's result).
_FREE = (*LOCATION, "num_cpus")
_TRUE, _FALSE = ("true", "yes", "1"), ("false", "no", "0")


@dataclass(frozen=True)
class Args:
    """Arguments of a sweep."""

    script: str = "fit_params"
    """the train/ script to sweep: a name (train/<script>.py) or a path to a .py file with a
    dataclass Args (an int field seed) and run(args) returning a dict"""
    seeds: tuple[int, ...] = (0, 1, 2)
    """seeds of every setting"""
    grid: tuple[str, ...] = ()
    """settings: FIELD=V1,V2,... per field of the script's Args (every combination runs; one
    value fixes the field), e.g. particles=8,16 fast=true"""
    metrics: tuple[str, ...] = ()
    """results to tabulate: glob patterns over the /-joined keys of run()'s scalar results,
    e.g. 'summary/*/mu_abs_error' (empty: every scalar)"""
    confidence: float = 0.95
    """confidence of the Student-t intervals over seeds"""
    num_cpus: int | None = None
    """CPUs of the local Ray (default: all of this machine's); not with RAY_ADDRESS"""
    name: str = "sweep"
    """sweep name: the sweep writes to <out-dir>/<name>__<first seed>__<unix time>"""
    out_dir: str = "runs"
    """parent of the sweep's run folder"""
    task_out_dir: str | None = None
    """parent of the tasks' run folders (default: <run folder>/tasks; on a cluster, a folder
    every node can write)"""
    resume: str | None = None
    """a sweep's run folder to complete (same arguments): runs only the tasks it lacks"""


@dataclass(frozen=True)
class Task:
    """One run of the swept script: a setting's label, a seed and the script's arguments."""

    setting: str
    seed: int
    fields: dict[str, Any]


def script_path(script: str) -> Path:
    """The file of ``--script``: ``train/<script>.py`` for a name, else the path given.

    Raises:
        ValueError: naming ``script``, when no such file exists.
    """
    path = Path(script) if script.endswith(".py") else TRAIN / f"{script}.py"
    if not path.is_file():
        known = sorted(p.stem for p in TRAIN.glob("*.py") if p.stem != "sweep")
        raise ValueError(f"script: no file {path} (train/ has {known})")
    return path


def load_module(name: str, source: str, filename: str) -> types.ModuleType:
    """Execute a script's source as the module ``name`` (registered in ``sys.modules``, which
    dataclasses need) and return it."""
    module = types.ModuleType(name)
    module.__file__ = filename
    sys.modules[name] = module
    exec(compile(source, filename, "exec"), module.__dict__)
    return module


def _parse_grid(grid: tuple[str, ...], fields: dict[str, Any]) -> list[tuple[str, list[str]]]:
    """``[(field, values)]`` from the ``--grid`` entries, each field checked."""
    entries: list[tuple[str, list[str]]] = []
    for entry in grid:
        field, sep, text = entry.partition("=")
        field = field.strip().replace("-", "_")
        values = [value.strip() for value in text.split(",")]
        if not sep or not field or not all(values):
            raise ValueError(f"grid: expected FIELD=V1,V2,..., got {entry!r}")
        if field in _RESERVED:
            raise ValueError(f"grid: {field} is set by the sweep (seeds: --seeds), got {entry!r}")
        if field not in fields:
            raise ValueError(
                f"grid: the script's Args has no field {field!r} (it has {sorted(fields)})"
            )
        if field in (name for name, _ in entries):
            raise ValueError(f"grid: {field} given twice")
        entries.append((field, values))
    return entries


def _tokens(field: str, value: str, kind: Any) -> list[str]:
    """The script's command-line tokens setting ``field`` to ``value``."""
    flag = field.replace("_", "-")
    if kind is bool:
        if value.lower() in _TRUE:
            return [f"--{flag}"]
        if value.lower() in _FALSE:
            return [f"--no-{flag}"]
        raise ValueError(f"grid: {field} is a flag: expected true or false, got {value!r}")
    return [f"--{flag}", *value.split()]


def make_tasks(args: Args, module: types.ModuleType) -> list[Task]:
    """Every seed × setting's arguments, parsed by the script's own command line (tyro) and
    checked by its ``check_args`` when it has one: a bad value fails here, before any run.
    Each task's ``name`` is ``<script>-<setting index>``; :func:`run` sets its ``out_dir``.

    Raises:
        ValueError: naming ``script`` (no dataclass ``Args`` with a ``seed`` field, or no
            ``run``) or ``grid`` (a malformed entry, an unknown or reserved field, a value
            the script refuses).
    """
    Script = getattr(module, "Args", None)
    if not (dataclasses.is_dataclass(Script) and isinstance(Script, type)) or not callable(
        getattr(module, "run", None)
    ):
        raise ValueError(f"script: {args.script} has no dataclass Args and run(args)")
    hints = typing.get_type_hints(Script)
    if hints.get("seed") is not int:
        raise ValueError(f"script: {args.script}'s Args has no int field seed")
    entries = _parse_grid(args.grid, hints)
    varying = [field for field, values in entries if len(values) > 1]
    stem = script_path(args.script).stem
    tasks = []
    for index, combination in enumerate(itertools.product(*(values for _, values in entries))):
        setting = dict(zip((field for field, _ in entries), combination, strict=True))
        label = " ".join(f"{field}={setting[field]}" for field in varying)
        tokens = [
            t for field, value in setting.items() for t in _tokens(field, value, hints[field])
        ]
        for seed in args.seeds:
            try:
                parsed = tyro.cli(
                    Script, args=[*tokens, "--seed", str(seed)], console_outputs=False
                )
            except SystemExit:
                shown = " ".join(tokens) or "of its defaults"
                raise ValueError(
                    f"grid: {args.script} refuses the setting {shown!r} (a value it cannot "
                    "parse, or a required field not given; its message is above)"
                ) from None
            if "name" in hints:
                parsed = dataclasses.replace(parsed, name=f"{stem}-{index}")
            check = getattr(module, "check_args", None)
            if callable(check):
                try:
                    check(parsed)
                except ValueError as error:
                    raise ValueError(f"grid: setting {label or '(default)'!r}: {error}") from None
            fields = {f.name: getattr(parsed, f.name) for f in dataclasses.fields(parsed)}
            tasks.append(Task(setting=label, seed=seed, fields=fields))
    return tasks


def run_task(name: str, source: str, filename: str, fields: dict[str, Any]) -> dict[str, Any]:
    """One task, on a Ray worker: the script's ``run`` on one thread; its scalar results.

    Returns:
        ``{"run_dir": str, "metrics": {key: float}, "seconds": float, "threads": int}``
        (``threads``: torch's intra-op threads when the run ended).
    """
    torch.set_num_threads(1)
    module = load_module(name, source, filename)
    clock = time.perf_counter()
    result = module.run(module.Args(**fields))
    return {
        "run_dir": str(result.get("run_dir", "")),
        "metrics": scalar_metrics(result),
        "seconds": time.perf_counter() - clock,
        "threads": torch.get_num_threads(),
    }


def check_args(args: Args) -> None:
    """Check the sweep's own arguments before any work.

    Raises:
        ValueError: naming the argument.
    """
    script_path(args.script)
    if not args.seeds:
        raise ValueError("seeds: expected at least one seed")
    for seed in args.seeds:
        check_int("seeds", seed, low=0)
    if len(set(args.seeds)) != len(args.seeds):
        raise ValueError(f"seeds: expected distinct seeds, got {args.seeds}")
    check_real("confidence", args.confidence, low=0.0, high=1.0, low_open=True, high_open=True)
    if args.num_cpus is not None:
        check_int("num_cpus", args.num_cpus, low=1)
        if os.environ.get("RAY_ADDRESS"):
            raise ValueError(
                "num_cpus: sets the CPUs of a local Ray; RAY_ADDRESS joins a cluster, whose "
                "nodes have their own"
            )
    check_name("name", args.name)


def _open_sweep(args: Args) -> tuple[Path, list[dict[str, Any]]]:
    """The sweep's run folder and the tasks it has finished (none for a new sweep)."""
    if args.resume is None:
        return new_run_dir(out_dir=args.out_dir, name=args.name, seed=args.seeds[0]), []
    run_dir = Path(args.resume)
    if not (run_dir / CHECKPOINT).is_file():
        raise ValueError(f"resume: {str(run_dir)!r} is not a sweep folder with a {CHECKPOINT}")
    saved = read_checkpoint(run_dir / CHECKPOINT, keys=("args", "tasks"))
    now = dataclasses.asdict(args)
    differences = [
        f"{key}: checkpoint {saved['args'].get(key)!r}, now {value!r}"
        for key, value in now.items()
        if key not in _FREE and saved["args"].get(key) != value
    ]
    if differences:
        raise ValueError(
            f"{run_dir / CHECKPOINT} was written with other arguments: " + "; ".join(differences)
        )
    return run_dir, list(saved["tasks"])


def run(args: Args) -> dict[str, Any]:
    """Run (or complete) the sweep on Ray; write the task results and the tables.

    Uses the Ray this process has already started, else starts one: ``ray.init()`` joins the
    cluster named by ``RAY_ADDRESS`` or starts a local one (shut down at the end).

    Returns:
        ``{"run_dir": str, "tasks": [{"setting", "seed", "run_dir", "metrics", "seconds",
        "threads"}],
        "statistics": [record per setting and metric]}``.

    Raises:
        ValueError: an argument, or a setting of the swept script, is refused (before any
            task starts); a metric pattern matches no result.
    """
    check_args(args)
    path = script_path(args.script)
    source = path.read_text()
    name = f"_swept_{path.stem}"
    module = load_module(name, source, str(path))
    tasks = make_tasks(args, module)
    run_dir, finished = _open_sweep(args)
    task_out_dir = str(Path(args.task_out_dir or run_dir / "tasks").resolve())
    tasks = [
        dataclasses.replace(task, fields=task.fields | {"out_dir": task_out_dir})
        if "out_dir" in task.fields
        else task
        for task in tasks
    ]
    done = {(record["setting"], record["seed"]) for record in finished}
    todo = [task for task in tasks if (task.setting, task.seed) not in done]
    started = not ray.is_initialized()
    if started:
        ray.init(**({} if args.num_cpus is None else {"num_cpus": args.num_cpus}))
    if __name__ != "__main__":  # imported (tests): ship run_task by value, as __main__'s are
        ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    save_checkpoint(run_dir / CHECKPOINT, {"args": dataclasses.asdict(args), "tasks": finished})
    clock = time.perf_counter()
    pending: dict[Any, Task] = {}
    try:
        remote = ray.remote(num_cpus=1)(run_task).options(
            runtime_env={"env_vars": {"TQDM_DISABLE": "1", "OMP_NUM_THREADS": "1"}}
        )
        pending = {remote.remote(name, source, str(path), task.fields): task for task in todo}
        with tqdm(total=len(tasks), initial=len(finished), desc=f"sweep {path.stem}") as bar:
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                task = pending.pop(ready[0])
                outcome = ray.get(ready[0])
                finished.append({"setting": task.setting, "seed": task.seed, **outcome})
                save_checkpoint(
                    run_dir / CHECKPOINT, {"args": dataclasses.asdict(args), "tasks": finished}
                )
                bar.update()
    except BaseException:  # a task failed, or the driver was interrupted: stop the others
        for ref in pending:
            ray.cancel(ref)
        raise
    finally:
        if started:
            ray.shutdown()
    seconds = time.perf_counter() - clock
    order = {(task.setting, task.seed): i for i, task in enumerate(tasks)}
    finished.sort(key=lambda record: order[record["setting"], record["seed"]])
    (run_dir / "tasks.json").write_text(json.dumps(finished, indent=2) + "\n")
    results: dict[str, list[dict[str, float]]] = {}
    for record in finished:
        metrics = record["metrics"] | {"task_seconds": record["seconds"]}
        results.setdefault(record["setting"], []).append(metrics)
    rows = aggregate_seeds(
        results, confidence=args.confidence, metrics=_chosen(args.metrics, results)
    )
    write_statistics(rows, run_dir)
    header = (
        f"# Sweep of {path.stem}: {len(tasks) // len(args.seeds)} setting(s) × "
        f"{len(args.seeds)} seeds\n\n"
        f"Seeds {', '.join(map(str, args.seeds))}; {len(todo)} tasks ran in {seconds:.1f} s "
        f"on Ray ({len(finished) - len(todo)} from the checkpoint).\n\n"
    )
    (run_dir / "results.md").write_text(header + statistics_table(rows))
    records = json.loads((run_dir / "statistics.json").read_text())
    return {"run_dir": str(run_dir), "tasks": finished, "statistics": records}


def _chosen(patterns: tuple[str, ...], results: dict[str, list[dict[str, float]]]) -> list[str]:
    """The metrics that match ``patterns`` (all when none), in the order first seen."""
    names = list(dict.fromkeys(key for runs in results.values() for run in runs for key in run))
    if not patterns:
        return names
    for pattern in patterns:
        if not any(fnmatch.fnmatchcase(key, pattern) for key in names):
            raise ValueError(f"metrics: {pattern!r} matches no result (they are {names})")
    return [key for key in names if any(fnmatch.fnmatchcase(key, p) for p in patterns)]


def main(argv: list[str] | None = None) -> None:
    """Parse the command line and run; print the table."""
    result = run(tyro.cli(Args, args=argv, description=(__doc__ or "").splitlines()[0]))
    print(Path(result["run_dir"], "results.md").read_text())


if __name__ == "__main__":
    main()
