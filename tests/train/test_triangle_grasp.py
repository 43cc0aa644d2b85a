"""The triangle-grasp script: end to end on a tiny budget, its command line and its argument
checks (the pipeline's pieces are tested in tests/experiments, tests/filters and tests/states)."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import time
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

import pytest
import torch

from tests.train import assert_logged, load_script
from torchcontact.logs import read_run


@pytest.fixture(scope="module")
def module() -> ModuleType:
    return load_script("triangle_grasp")


@pytest.fixture(scope="module")
def result(module: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict]:
    out = tmp_path_factory.mktemp("runs")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the script's timings are single-threaded
    try:
        args = module.Args(name="tiny", out_dir=str(out), fast=True, seed=0, write_logs=True)
        yield module.run(args)
    finally:
        torch.set_num_threads(threads)


def test_outputs_exist(module: ModuleType, result: dict) -> None:
    run_dir = Path(result["run_dir"])
    ran = {"name": "tiny", "out_dir": str(run_dir.parent), "seed": 0, "fast": True, "trials": 2}
    assert_logged(run_dir, [f.name for f in dataclasses.fields(module.Args)], ran)
    assert re.fullmatch(r"tiny__0__\d+", run_dir.name)
    for name in ("results.md", "metrics.json", "snapshots.png", "errors.png", "modes.png"):
        assert (run_dir / name).is_file(), name
    assert any(p.name.startswith("events.out.tfevents") for p in run_dir.iterdir())
    text = (run_dir / "results.md").read_text()
    for method in ("rbpf", "pf", "pf_same_n", "ekf", "vision"):
        assert f"| {method} |" in text
    saved = json.loads((run_dir / "metrics.json").read_text())
    assert (
        saved["metrics"]["rbpf"]["pos_rmse_occ_mm"] == result["metrics"]["rbpf"]["pos_rmse_occ_mm"]
    )


def test_metrics_are_sane(result: dict) -> None:
    metrics = result["metrics"]
    assert set(metrics) == {"rbpf", "pf", "pf_same_n", "ekf", "vision"}
    for row in metrics.values():
        assert all(math.isfinite(v) for v in row.values()), row
    rbpf = metrics["rbpf"]
    for method in ("rbpf", "pf", "pf_same_n"):
        assert 0.0 <= metrics[method]["mode_accuracy"] <= 1.0
        assert 0.0 <= metrics[method]["touch_accuracy"] <= 1.0
        assert metrics[method]["mode_logprob"] <= 0.0
    # The contact model tracks the pushed triangle through the occlusion; held vision does not.
    assert rbpf["pos_rmse_occ_mm"] < 2.0 < metrics["vision"]["pos_rmse_occ_mm"]
    assert rbpf["theta_rmse_occ_deg"] < 0.2 < metrics["vision"]["theta_rmse_occ_deg"]
    assert rbpf["mode_accuracy"] > 0.85
    assert result["ratio_pos_occ"] == pytest.approx(
        rbpf["pos_rmse_occ_mm"]
        / min(metrics[m]["pos_rmse_occ_mm"] for m in ("pf", "ekf", "vision"))
    )


def test_plain_pf_is_calibrated_to_the_rbpf_time(result: dict) -> None:
    metrics = result["metrics"]
    assert metrics["rbpf"]["particles"] == 20  # fast mode
    assert metrics["pf_same_n"]["particles"] == 20
    assert metrics["pf"]["particles"] == result["pf_particles"] >= 2
    calibration = result["calibration"]  # particles -> CPU seconds of a PF run
    assert {8, 64, result["pf_particles"]} <= set(calibration)
    assert calibration[8] < calibration[64]
    assert metrics["pf"]["cpu_ms_per_step"] == pytest.approx(
        1e3 * calibration[result["pf_particles"]] / 48
    )


def test_ground_truth_stays_above_the_table(result: dict) -> None:
    assert result["min_height"] > 0.0
    assert result["min_vertex_height"] > -1e-3  # at most the LCP's sub-millimetre slack


def test_write_logs_writes_each_trial_as_a_run_log(result: dict) -> None:
    paths = sorted((Path(result["run_dir"]) / "logs").glob("*.mcap"))
    assert [p.name for p in paths] == ["trial_000.mcap", "trial_001.mcap"]  # --fast: 2 trials
    log = read_run(paths[1])
    assert log.steps == 48
    assert log.source["trial"] == 1
    assert log.source["settings"]["rbpf_particles"] == 20  # the --fast budget's settings


def test_help_lists_the_arguments(module: ModuleType, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        module.main(["--help"])
    text = capsys.readouterr().out
    for flag in ("--rbpf-particles", "--pf-particles", "--trials", "--gap-sigma", "--write-logs"):
        assert flag in text


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"trials": 0}, r"trials: expected an int >= 1, got 0"),
        ({"steps": 4}, r"steps: expected an int >= 8 \(every phase of the grasp schedule\)"),
        ({"pf_particles": -1}, r"pf_particles: expected an int >= 0"),
        ({"vision_sigma": 0.0}, r"vision_sigma: expected a finite number > 0"),
        ({"false_positive": 1.0}, r"false_positive: expected a finite number in \[0.0, 1.0\)"),
        ({"friction_high": 0.3}, r"friction_high: expected a finite number >= 0.4"),
        ({"gap_sigma": -1.0}, r"gap_sigma: expected a finite number"),
        ({"name": "a/b"}, r"name: expected a non-empty name"),
    ],
)
def test_bad_arguments_fail_before_any_work(
    module: ModuleType, tmp_path: Path, change: dict[str, object], message: str
) -> None:
    args = module.Args(out_dir=str(tmp_path / "runs"), fast=True, **change)
    clock = time.perf_counter()
    with pytest.raises(ValueError, match=message):
        module.run(args)
    assert time.perf_counter() - clock < 5.0
    assert not (tmp_path / "runs").exists()  # no run folder


def test_too_few_rbpf_particles_for_the_learned_modes_are_refused(
    module: ModuleType, tmp_path: Path
) -> None:
    args = module.Args(out_dir=str(tmp_path / "runs"), fast=True, rbpf_particles=2)
    with pytest.raises(ValueError, match=r"rbpf_particles: expected an int >= \d+ \(the number"):
        module.run(args)
    assert not (tmp_path / "runs").exists()  # refused before any filter ran
