"""The sweep script: a two-task sweep on a local Ray against the script run directly, the
settings it builds, and its argument checks."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest
import ray
import torch

from tests.train import load_script
from torchcontact.experiments import scalar_metrics

#: The fitting script's results compared (its timings are not: they differ from run to run).
METRICS = ("summary/*/mu_abs_error", "summary/*/sigma_abs_error_mm", "summary/*/evaluations")


@pytest.fixture(scope="module")
def module() -> ModuleType:
    return load_script("sweep")


@pytest.fixture(scope="module")
def fit_params() -> ModuleType:
    return load_script("fit_params")


@pytest.fixture
def local_ray() -> Iterator[None]:
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.mark.usefixtures("local_ray")
def test_two_seeds_on_ray_match_the_script_run_directly(
    module: ModuleType, fit_params: ModuleType, tmp_path: Path
) -> None:
    args = module.Args(
        script="fit_params",
        seeds=(0, 1),
        grid=("fast=true",),
        metrics=METRICS,
        out_dir=str(tmp_path / "sweeps"),
    )
    result = module.run(args)
    run_dir = Path(result["run_dir"])
    assert run_dir.name.startswith("sweep__0__")
    for name in ("tasks.json", "statistics.json", "statistics.csv", "statistics.md", "results.md"):
        assert (run_dir / name).is_file(), name
    assert [(t["setting"], t["seed"]) for t in result["tasks"]] == [("", 0), ("", 1)]
    assert [t["threads"] for t in result["tasks"]] == [1, 1]  # each task pinned to one thread
    for task in result["tasks"]:  # each task's own run folder, under the sweep's
        assert Path(task["run_dir"]).parent == (run_dir / "tasks").resolve()
        assert Path(task["run_dir"]).name.startswith(f"fit_params-0__{task['seed']}__")

    # The same runs in this process, on one thread as the tasks: the same fits up to the
    # rounding of another process (L-BFGS stops at a relative gradient of 1e-6 or so).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        direct = [
            scalar_metrics(
                fit_params.run(
                    fit_params.Args(fast=True, seed=seed, out_dir=str(tmp_path / "direct"))
                )
            )
            for seed in (0, 1)
        ]
    finally:
        torch.set_num_threads(threads)
    statistics = {row["metric"]: row for row in result["statistics"]}
    assert set(statistics) == {
        f"summary/{method}/{metric}"
        for method in ("gradient", "grid", "cma")
        for metric in ("mu_abs_error", "sigma_abs_error_mm", "evaluations")
    }
    for metric, row in statistics.items():
        a, b = direct[0][metric], direct[1][metric]
        for task, value in zip(result["tasks"], (a, b), strict=True):
            assert task["metrics"][metric] == pytest.approx(value, rel=1e-5, abs=1e-9), metric
        # Two seeds: mean (a + b)/2, s/√2 = |a − b|/2 and the 97.5 % quantile of t with one
        # degree of freedom, tan(0.475 π).
        half = math.tan(0.475 * math.pi) * abs(a - b) / 2
        assert row["n"] == 2
        assert row["setting"] == ""
        assert row["mean"] == pytest.approx((a + b) / 2, rel=1e-5, abs=1e-9), metric
        assert (row["min"], row["max"]) == pytest.approx((min(a, b), max(a, b)), rel=1e-5, abs=1e-9)
        assert row["ci_low"] == pytest.approx((a + b) / 2 - half, rel=1e-4, abs=1e-8), metric
        assert row["ci_high"] == pytest.approx((a + b) / 2 + half, rel=1e-4, abs=1e-8), metric
    table = (run_dir / "results.md").read_text()
    assert "| – | summary/gradient/mu_abs_error | 2 |" in table

    # Resuming the finished sweep runs no task and rebuilds the same tables.
    again = module.run(dataclasses.replace(args, resume=str(run_dir)))
    assert again["tasks"] == result["tasks"]
    assert again["statistics"] == result["statistics"]
    with pytest.raises(ValueError, match=r"other arguments: seeds: checkpoint \[?\(?0, 1"):
        module.run(dataclasses.replace(args, seeds=(0, 2), resume=str(run_dir)))


SCRIPT = """
from dataclasses import dataclass


@dataclass(frozen=True)
class Args:
    seed: int = 0
    scale: float = 1.0


def run(args):
    if args.seed == FAILING:
        raise ValueError(f"seed {args.seed} fails")
    return {"value": args.scale * args.seed, "nested": {"square": float(args.seed**2)}}
"""


@pytest.mark.usefixtures("local_ray")
def test_a_failed_task_stops_the_sweep_and_resuming_completes_it(
    module: ModuleType, tmp_path: Path
) -> None:
    """Any script with a dataclass Args and run(args); a failing task fails the sweep, whose
    checkpoint keeps what finished; resumed (the script fixed), it runs the rest."""
    script = tmp_path / "toy.py"
    script.write_text(SCRIPT.replace("FAILING", "2"))
    args = module.Args(
        script=str(script), seeds=(0, 1, 2), grid=("scale=0.5,3",), out_dir=str(tmp_path / "r")
    )
    with pytest.raises(ValueError, match="seed 2 fails"):
        module.run(args)
    (run_dir,) = (tmp_path / "r").iterdir()
    assert not (run_dir / "tasks.json").exists()
    script.write_text(SCRIPT.replace("FAILING", "-1"))
    result = module.run(dataclasses.replace(args, resume=str(run_dir)))
    assert [(t["setting"], t["seed"]) for t in result["tasks"]] == [
        (f"scale={scale}", seed) for scale in ("0.5", "3") for seed in (0, 1, 2)
    ]
    for task in result["tasks"]:  # exact: products of small integers and 0.5
        scale = float(task["setting"].split("=")[1])
        assert task["metrics"] == {
            "value": scale * task["seed"],
            "nested/square": task["seed"] ** 2,
        }
    rows = {(r["setting"], r["metric"]): r for r in result["statistics"]}
    # 0, 3, 6: mean 3, s = 3, interval 3 ± t √3 with t = 0.95 / √(0.0975 / 2), the 97.5 %
    # quantile of t with two degrees of freedom in closed form
    row = rows["scale=3", "value"]
    assert (row["n"], row["min"], row["max"]) == (3, 0.0, 6.0)
    assert row["ci_high"] == pytest.approx(
        3 + 0.95 / math.sqrt(0.0975 / 2) * math.sqrt(3), rel=1e-9
    )
    assert rows["scale=0.5", "nested/square"]["mean"] == pytest.approx(5 / 3, rel=1e-15)


def test_settings_are_the_scripts_own_arguments(module: ModuleType) -> None:
    """Every seed × setting of the grid, as the Dyna-Q script's Args built directly."""
    dyna_q = load_script("dyna_q_peg")
    args = module.Args(
        script="dyna_q_peg",
        seeds=(0, 3),
        grid=("planning-steps=0,10", "sweep=false", "exploration=uniform,least_tried"),
    )
    tasks = module.make_tasks(args, module.load_module("dq", *_source("dyna_q_peg")))
    expected = [
        (f"planning_steps={steps} exploration={exploration}", seed, index)
        for index, (steps, exploration) in enumerate(
            (s, e) for s in (0, 10) for e in ("uniform", "least_tried")
        )
        for seed in (0, 3)
    ]
    assert [(t.setting, t.seed) for t in tasks] == [(label, seed) for label, seed, _ in expected]
    for task, (label, seed, index) in zip(tasks, expected, strict=True):
        steps, exploration = label.split()
        direct = dyna_q.Args(
            seed=seed,
            planning_steps=int(steps.split("=")[1]),
            exploration=exploration.split("=")[1],
            sweep=False,
            name=f"dyna_q_peg-{index}",
        )
        assert task.fields == dataclasses.asdict(direct)
    fit = module.make_tasks(
        module.Args(seeds=(1,), grid=("mu_range=0.3 0.5", "fast=true")),
        module.load_module("fp", *_source("fit_params")),
    )
    assert [(t.setting, t.fields["mu_range"], t.fields["fast"]) for t in fit] == [
        ("", (0.3, 0.5), True)
    ]


def _source(name: str) -> tuple[str, str]:
    path = Path(__file__).resolve().parents[2] / "train" / f"{name}.py"
    return path.read_text(), str(path)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"script": "nothing"}, r"script: no file .*nothing\.py \(train/ has \[.*'fit_params'"),
        ({"seeds": ()}, "seeds: expected at least one seed"),
        ({"seeds": (0, 0)}, r"seeds: expected distinct seeds, got \(0, 0\)"),
        ({"seeds": (-1,)}, "seeds: expected an int >= 0"),
        ({"confidence": 1.0}, "confidence: expected a finite number in"),
        ({"num_cpus": 0}, "num_cpus: expected an int >= 1"),
        ({"name": "a/b"}, "name: expected a non-empty name"),
        ({"grid": ("particles",)}, "grid: expected FIELD=V1,V2,..., got 'particles'"),
        ({"grid": ("particles=8,",)}, "grid: expected FIELD=V1,V2"),
        ({"grid": ("seed=1,2",)}, r"grid: seed is set by the sweep \(seeds: --seeds\)"),
        ({"grid": ("out_dir=x",)}, "grid: out_dir is set by the sweep"),
        ({"grid": ("fitter=gradient",)}, r"grid: the script's Args has no field 'fitter'"),
        ({"grid": ("rounds=1", "rounds=2")}, "grid: rounds given twice"),
        ({"grid": ("fast=maybe",)}, "grid: fast is a flag: expected true or false"),
        ({"grid": ("particles=x",)}, "grid: fit_params refuses the setting '--particles x'"),
        ({"grid": ("particles=8,1",)}, "grid: setting 'particles=1': particles: expected an int"),
        ({"resume": "nowhere"}, "resume: 'nowhere' is not a sweep folder"),
    ],
)
def test_bad_arguments_fail_before_any_work(
    module: ModuleType, tmp_path: Path, change: dict[str, object], message: str
) -> None:
    out = tmp_path / "runs"
    with pytest.raises(ValueError, match=message):
        module.run(dataclasses.replace(module.Args(out_dir=str(out)), **change))
    assert not out.exists()  # no run folder
    assert not ray.is_initialized()


def test_num_cpus_is_refused_with_a_cluster_address(
    module: ModuleType, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("RAY_ADDRESS", "10.0.0.1:6379")
    with pytest.raises(ValueError, match="num_cpus: sets the CPUs of a local Ray; RAY_ADDRESS"):
        module.check_args(module.Args(num_cpus=4))
    module.check_args(module.Args())


def test_metric_patterns(module: ModuleType) -> None:
    results = {"": [{"summary/grid/mu": 1.0, "summary/cma/mu": 2.0, "task_seconds": 3.0}]}
    assert module._chosen(("summary/*",), results) == ["summary/grid/mu", "summary/cma/mu"]
    assert module._chosen((), results) == ["summary/grid/mu", "summary/cma/mu", "task_seconds"]
    with pytest.raises(ValueError, match=r"metrics: 'loss' matches no result \(they are \["):
        module._chosen(("loss",), results)


def test_main_parses_the_command_line(module: ModuleType, monkeypatch: pytest.MonkeyPatch) -> None:
    received: list[object] = []
    monkeypatch.setattr(module, "run", lambda args: received.append(args) or {"run_dir": ""})
    monkeypatch.setattr(Path, "read_text", lambda self: "")
    module.main(["--script", "dyna_q_peg", "--seeds", "1", "2", "--grid", "rounds=2", "alpha=1"])
    assert received == [
        module.Args(script="dyna_q_peg", seeds=(1, 2), grid=("rounds=2", "alpha=1"))
    ]
