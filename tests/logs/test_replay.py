"""The triangle grasp's trials as run logs, and estimators replayed over them: the logs hold
the simulated trials tensor for tensor, and every estimator replayed over the logs gives what
it gives in the experiment (:func:`run_estimators`) on the trials in memory."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import ModuleType

import pytest
import torch

from tests.train import load_script
from torchcontact.experiments import (
    FINGER_JOINTS,
    EstimatorRuns,
    GraspTrials,
    TriangleGrasp,
    evaluate_tracking,
    grasp_contact_model,
    grasp_trials,
    grasp_trials_from_logs,
    logged_settings,
    replay,
    run_estimators,
    write_grasp_logs,
)
from torchcontact.logs import RunLog, read_run

SETTINGS = TriangleGrasp(
    trials=2, train_trials=8, steps=48, rbpf_particles=20, pf_particles=8, reference_pf=False
)
SAME = (
    "the same code on the same inputs in the same process: the logs hand the filters the "
    "tensors of the trials unchanged (the format is lossless)"
)


@pytest.fixture(scope="module")
def trials() -> GraspTrials:
    return grasp_trials(SETTINGS)


@pytest.fixture(scope="module")
def runs(trials: GraspTrials) -> EstimatorRuns:
    return run_estimators(SETTINGS, trials, grasp_contact_model(SETTINGS, trials))


@pytest.fixture(scope="module")
def folder(trials: GraspTrials, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("grasp") / "logs"
    paths = write_grasp_logs(out, SETTINGS, trials)
    assert [p.name for p in paths] == ["trial_000.mcap", "trial_001.mcap"]
    return out


@pytest.fixture(scope="module")
def logs(folder: Path) -> list[RunLog]:
    return [read_run(path) for path in sorted(folder.glob("*.mcap"))]


@pytest.mark.bitwise("values passed through the lossless format untouched")
def test_the_logs_hold_the_trials(trials: GraspTrials, logs: list[RunLog]) -> None:
    T = SETTINGS.steps
    truth = trials.truth
    for b, log in enumerate(logs):
        assert log.name == f"triangle_grasp__0__trial{b:03d}"
        assert (log.h, log.body, log.joints, log.bodies) == (
            0.01,
            "triangle",
            FINGER_JOINTS,
            ("triangle",),
        )
        assert log.joints[:3] == ("left.x", "left.y", "left.theta")
        assert log.time_ns.tolist() == [10_000_000 * k for k in range(T + 1)]
        assert bool((log.robot_position == truth.q_kinematic[:, b].flatten(1)).all())
        assert bool((log.robot_velocity == trials.controls[:, b].flatten(1)).all())
        seen = torch.isfinite(trials.y[:, b, 0])
        assert bool(log.vision[0].isnan().all())  # no measurement before the first step
        assert bool((log.vision[1:, 0].isfinite() == seen).all())
        assert bool((log.vision[1:][seen] == trials.y[:, b][seen]).all())
        assert bool((log.tactile == trials.readings[:, b]).all())
        assert log.prior_mean is not None
        assert bool((log.prior_mean == trials.prior.mean[b]).all())
        assert log.truth_pose is not None
        assert bool((log.truth_pose == truth.q[:, b]).all())
        assert log.truth_contacts is not None
        assert bool((log.truth_contacts.mode == truth.mode[:, b]).all())
        assert bool((log.truth_contacts.normal_impulse == truth.pn[:, b]).all())
        assert log.parameters == {"friction": float(trials.scene.friction[b])}
        assert log.source["trial"] == b
    assert logged_settings(logs) == SETTINGS


@pytest.mark.bitwise(SAME)
def test_the_trials_rebuilt_from_the_logs_are_the_trials(
    trials: GraspTrials, logs: list[RunLog]
) -> None:
    rebuilt = grasp_trials_from_logs(logs, SETTINGS)
    for name in ("controls", "readings", "occluded", "table", "transition", "true_ids"):
        a, b = getattr(trials, name), getattr(rebuilt, name)
        assert (a.dtype, a.shape) == (b.dtype, b.shape), name
        assert bool((a == b).all()), name
    assert bool(((trials.y == rebuilt.y) | (trials.y.isnan() & rebuilt.y.isnan())).all())
    for field in dataclasses.fields(trials.truth):
        a, b = getattr(trials.truth, field.name), getattr(rebuilt.truth, field.name)
        if a is None or b is None:  # robot fields: empty in a scene without robots
            assert all(t is None or t.numel() == 0 for t in (a, b)), field.name
            continue
        assert (a.dtype, a.shape) == (b.dtype, b.shape), field.name
        assert bool((a == b).all()), field.name
    assert bool((trials.prior.mean == rebuilt.prior.mean).all())
    assert bool((trials.prior.cov == rebuilt.prior.cov).all())
    assert bool((trials.scene.friction == rebuilt.scene.friction).all())
    assert bool((trials.tactile.positions == rebuilt.tactile.positions).all())


@pytest.mark.bitwise(SAME)
@pytest.mark.parametrize("method", ["rbpf", "pf", "ekf", "vision"])
def test_replaying_the_logs_gives_the_experiments_estimates(
    method: str, trials: GraspTrials, runs: EstimatorRuns, folder: Path
) -> None:
    result = replay(sorted(folder.glob("*.mcap")), filter=method)
    expected = runs.outputs[method]
    assert set(result.output) == set(expected)
    for key, value in expected.items():
        assert result.output[key].shape == value.shape, key
        assert bool((result.output[key] == value).all()), key
    metrics, errors = evaluate_tracking(trials, runs.outputs)
    assert result.metrics == metrics[method]
    assert bool((result.errors[0] == errors[method][0]).all())
    assert result.particles == runs.particles.get(method, 0)


def test_replay_names_what_is_wrong(logs: list[RunLog]) -> None:
    with pytest.raises(ValueError, match="filter: expected one of"):
        replay(logs, filter="kalman")
    with pytest.raises(ValueError, match="pf_particles: expected an int >= 1"):
        replay(logs, filter="pf", settings=dataclasses.replace(SETTINGS, pf_particles=0))
    with pytest.raises(ValueError, match="logs: expected at least one run log"):
        replay([], filter="ekf")
    with pytest.raises(ValueError, match="logs: expected a sequence"):
        replay("trial_000.mcap", filter="ekf")  # type: ignore[arg-type]
    blind = dataclasses.replace(logs[0], truth_pose=None, truth_twist=None, bodies=())
    with pytest.raises(ValueError, match=r"needs the true states \(/ground_truth/state\)"):
        replay([blind], filter="ekf", settings=SETTINGS)
    other = dataclasses.replace(logs[1], source={**logs[1].source, "settings": {"seed": 1}})
    with pytest.raises(ValueError, match="the logs record different settings"):
        replay([logs[0], other], filter="ekf")
    short = dataclasses.replace(logs[0], h=0.02)
    with pytest.raises(ValueError, match="expected a triangle-grasp run"):
        replay([short], filter="ekf", settings=SETTINGS)


@pytest.fixture(scope="module")
def script() -> ModuleType:
    return load_script("replay")


@pytest.mark.bitwise(SAME)
def test_the_replay_script_writes_the_experiments_results(
    script: ModuleType,
    trials: GraspTrials,
    runs: EstimatorRuns,
    folder: Path,
    tmp_path: Path,
) -> None:
    result = script.run(script.Args(logs=(str(folder),), filter="rbpf", out_dir=str(tmp_path)))
    run_dir = Path(result["run_dir"])
    assert run_dir.name.startswith("replay__0__")
    saved = json.loads((run_dir / "metrics.json").read_text())
    expected = evaluate_tracking(trials, runs.outputs)[0]["rbpf"]
    for key, value in expected.items():
        assert saved["metrics"]["rbpf"][key] == value, key
    assert saved["metrics"]["rbpf"]["particles"] == SETTINGS.rbpf_particles
    estimates = torch.load(run_dir / "estimates.pt")
    assert bool((estimates["pose"] == runs.outputs["rbpf"]["pose"]).all())
    assert estimates["pos_err"].shape == (SETTINGS.steps, SETTINGS.trials)
    assert "| rbpf |" in (run_dir / "results.md").read_text()
    assert any(p.name.startswith("events.out.tfevents") for p in run_dir.iterdir())


def test_the_replay_script_checks_its_arguments(script: ModuleType, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="logs: expected at least one"):
        script.run(script.Args(out_dir=str(tmp_path)))
    with pytest.raises(ValueError, match=r"holds no \.mcap file"):
        script.run(script.Args(logs=(str(tmp_path),), out_dir=str(tmp_path)))
    with pytest.raises(ValueError, match="filter: expected one of"):
        script.run(script.Args(logs=(str(tmp_path),), filter="kf", out_dir=str(tmp_path)))
    with pytest.raises(ValueError, match="is neither a file nor a folder"):
        script.run(script.Args(logs=(str(tmp_path / "none.mcap"),), out_dir=str(tmp_path)))
