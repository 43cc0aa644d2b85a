"""The fitting script: end to end on a tiny budget, resuming, and its argument checks."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path
from types import ModuleType

import pytest

from tests.train import assert_logged, load_script


@pytest.fixture(scope="module")
def module() -> ModuleType:
    return load_script("fit_params")


def test_tiny_run_writes_its_outputs_and_resumes(module: ModuleType, tmp_path: Path) -> None:
    result = module.run(module.Args(name="tiny", out_dir=str(tmp_path), fast=True, seed=3))
    run_dir = Path(result["run_dir"])
    # The arguments as run: fast mode shrinks the budget.
    ran = {"name": "tiny", "out_dir": str(tmp_path), "seed": 3, "fast": True, "rounds": 1}
    assert_logged(run_dir, [f.name for f in dataclasses.fields(module.Args)], ran)
    assert re.fullmatch(r"tiny__3__\d+", run_dir.name)
    for name in ("results.md", "metrics.json", "checkpoint.pt"):
        assert (run_dir / name).is_file(), name
    (experiment,) = result["experiments"]
    low, high = module.Args().mu_range
    assert low <= experiment["mu"] <= high
    for method in ("gradient", "grid", "cma"):
        outcome = experiment[method]
        assert math.isfinite(outcome["log_evidence"])
        assert low <= outcome["mu"] <= high or method == "gradient"
    # Gradient ascent from the middle ends at least as high as the best of a 3 × 3 grid.
    assert experiment["gradient"]["log_evidence"] >= experiment["grid"]["log_evidence"] - 1e-6
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert set(metrics["summary"]) == {"gradient", "grid", "cma"}
    # Resuming the finished run with the same arguments adds nothing and reproduces the table.
    again = module.run(
        module.Args(name="tiny", out_dir=str(tmp_path), fast=True, seed=3, resume=str(run_dir))
    )
    # (compared as JSON: a missing standard error is nan, unequal to itself)
    assert json.dumps(again["experiments"]) == json.dumps(result["experiments"])


@pytest.mark.parametrize(
    ("field", "value"),
    [("rounds", 0), ("particles", 1), ("grid_points", 1), ("mu_range", (0.5, 0.2))],
)
def test_bad_arguments_are_named(module: ModuleType, field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field):
        module.check_args(module.Args(**{field: value}))


def test_tiny_triangle_grasp_run(module: ModuleType, tmp_path: Path) -> None:
    """The triangle-grasp experiment end to end: the true parameters lie in their ranges,
    every method's estimate is finite, gradient ascent from the middle ends at least as high
    as the best point of a 3 × 3 grid, and the table reports the median relative errors."""
    args = module.Args(
        experiment="triangle-grasp", name="grasp", out_dir=str(tmp_path), fast=True, seed=1
    )
    result = module.run(args)
    (experiment,) = result["experiments"]
    grasp = module.GraspFit()
    for key, (low, high) in (
        ("mu", grasp.mu_range),
        ("finger_mu", grasp.finger_mu_range),
        ("sigma_mm", grasp.sigma_mm_range),
    ):
        assert low <= experiment[key] <= high, key
    for method in ("gradient", "grid", "cma"):
        outcome = experiment[method]
        assert math.isfinite(outcome["log_evidence"]), method
        assert outcome["mu"] > 0, method
        assert outcome["sigma_mm"] > 0, method
    assert experiment["gradient"]["log_evidence"] >= experiment["grid"]["log_evidence"] - 1e-6
    summary = result["summary"]["gradient"]
    assert summary["mu_median_rel_error"] == pytest.approx(
        abs(experiment["gradient"]["mu"] / experiment["mu"] - 1), rel=1e-12
    )
    table = (Path(result["run_dir"]) / "results.md").read_text()
    assert "triangle grasp" in table
    assert "median abs. rel. error μ" in table


def test_methods_can_be_chosen(module: ModuleType, tmp_path: Path) -> None:
    result = module.run(
        module.Args(name="grid", out_dir=str(tmp_path), fast=True, methods=("grid",))
    )
    assert set(result["summary"]) == {"grid"}
    assert set(result["experiments"][0]) == {"mu", "sigma_mm", "grid"}


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"experiment": "peg"}, "experiment"),
        ({"methods": ()}, "methods"),
        ({"methods": ("adam",)}, "methods"),
        ({"threads": 0}, "threads"),
    ],
)
def test_bad_experiment_arguments_are_named(
    module: ModuleType, changes: dict, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        module.check_args(module.Args(**changes))


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"grasps": 0}, "grasp.grasps"),
        ({"particles": 1}, "grasp.particles"),
        ({"mu_range": (0.6, 0.2)}, "grasp.mu_range"),
        ({"speed_std": 0.0}, "grasp.speed_std"),
    ],
)
def test_bad_grasp_arguments_are_named(module: ModuleType, changes: dict, message: str) -> None:
    args = module.Args(grasp=module.GraspFit(**changes))
    with pytest.raises(ValueError, match=message):
        module.check_args(args)
