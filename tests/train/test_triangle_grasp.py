"""The triangle-grasp tracking experiment runs end to end on a tiny budget."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from tests.train import load_script


def _load():
    return load_script("triangle_grasp")


@pytest.fixture(scope="module")
def result(tmp_path_factory: pytest.TempPathFactory) -> dict:
    module = _load()
    out = tmp_path_factory.mktemp("runs")
    args = module.Args(name="tiny", out_dir=str(out), fast=True, seed=0)
    return module.run(args)


def test_outputs_exist(result: dict) -> None:
    run_dir = Path(result["run_dir"])
    for name in ("results.md", "trajectory.png", "errors.png", "modes.png"):
        assert (run_dir / name).is_file(), name
    assert any(p.name.startswith("events.out.tfevents") for p in run_dir.iterdir())
    assert "| rbpf |" in (run_dir / "results.md").read_text()


def test_metrics_are_sane(result: dict) -> None:
    metrics = result["metrics"]
    assert set(metrics) == {"rbpf", "pf", "ekf", "vision"}
    for row in metrics.values():
        assert all(math.isfinite(v) for v in row.values()), row
    assert 0.0 <= metrics["rbpf"]["mode_accuracy"] <= 1.0
    assert metrics["rbpf"]["mode_logprob"] <= 0.0
    # The contact model tracks the pushed triangle through the occlusion; held vision does not.
    assert metrics["rbpf"]["pos_rmse_occ_mm"] < metrics["vision"]["pos_rmse_occ_mm"]


def test_ground_truth_stays_above_the_table(result: dict) -> None:
    assert result["min_height"] > 0.0
    assert result["min_vertex_height"] > -1e-3  # at most the LCP's sub-millimetre slack


def test_help_lists_the_arguments(capsys: pytest.CaptureFixture[str]) -> None:
    module = _load()
    with pytest.raises(SystemExit):
        module.main(["--help"])
    text = capsys.readouterr().out
    assert "--rbpf-particles" in text
    assert "--trials" in text
