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
