"""The Dyna-Q peg-in-hole script runs end to end on a tiny budget and resumes exactly."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
import torch

from tests.train import assert_logged, load_script
from torchcontact.envs import PegInHole2DVector
from torchcontact.experiments import (
    PegLearning,
    PotentialShaping,
    aggregate_seeds,
    round_seed,
    statistics_table,
)


def _tiny(module: ModuleType, out: Path, **changes: object) -> object:
    args = module.Args(
        out_dir=str(out),
        num_envs=3,
        rounds=2,
        max_steps=12,
        eval_every=1,
        eval_episodes=2,
        final_episodes=3,
        particles=24,
        mode_episodes=8,  # the physics model's greedy episodes: no test judges its fit
    )
    return dataclasses.replace(args, **changes)


@pytest.fixture(scope="module")
def module() -> ModuleType:
    return load_script("dyna_q_peg")


@pytest.fixture(scope="module")
def straight(module: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The tiny run (two rounds) without interruption; the tests only read its folder."""
    result: dict[str, Any] = module.run(_tiny(module, tmp_path_factory.mktemp("straight")))
    return result


@pytest.fixture(scope="module")
def straight_three(module: ModuleType, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """Three rounds without interruption; the tests only read its folder."""
    out = tmp_path_factory.mktemp("straight_three")
    result: dict[str, Any] = module.run(_tiny(module, out, rounds=3))
    return result


def test_runs_and_writes_its_artefacts(module: ModuleType, straight: dict[str, Any]) -> None:
    result = straight
    run_dir = Path(result["run_dir"])
    args = _tiny(module, run_dir.parent)
    assert_logged(run_dir, [f.name for f in dataclasses.fields(args)], dataclasses.asdict(args))
    artefacts = ("results.md", "q_table.pt", "graph.json", "graph.png", "learning.png")
    for name in (*artefacts, "checkpoint.pt"):
        assert (run_dir / name).is_file(), name
    rows = {"oracle", "raw", "qmdp + fitted", "qmdp + physics"}
    assert set(result["evaluations"]) == rows
    assert set(result["execution"]) == rows
    for name, metrics in result["execution"].items():
        assert set(metrics) == {"success", "steps", "log_p_true_class", "ms_per_decision"}
        # Only the filters have a belief over the contact class; a probability is <= 1.
        assert math.isnan(metrics["log_p_true_class"]) == (name in ("oracle", "raw"))
        assert math.isnan(metrics["log_p_true_class"]) or metrics["log_p_true_class"] <= 0.0
    saved = json.loads((run_dir / "metrics.json").read_text())
    success = result["evaluations"]["qmdp + physics"]
    assert saved["execution/qmdp + physics/success"] == pytest.approx(success, abs=1e-12)
    assert set(result["learning"]) == {"greedy_success@3", "greedy_success@6"}
    assert (run_dir / "physics_model.pt").is_file()
    assert len(result["history"]) == 2
    assert "greedy_success" in result["history"][-1]
    assert list(run_dir.glob("events.out.tfevents.*"))
    text = (run_dir / "results.md").read_text()
    assert "| qmdp + fitted | 3 |" in text
    assert "| qmdp + physics | 3 |" in text
    greedy = [f"{100 * h['greedy_success']:.1f} %" for h in result["history"]]
    assert "| greedy success (true state) | " + " | ".join(greedy) + " |" in text


@pytest.mark.bitwise("the Q table is read back from the checkpoint")
def test_a_finished_run_is_evaluated_again_without_training(
    module: ModuleType, tmp_path: Path
) -> None:
    trained = module.run(_tiny(module, tmp_path, rounds=1, final_episodes=0))
    assert trained["evaluations"] == {}
    run_dir = Path(trained["run_dir"])
    assert "No final evaluation." in (run_dir / "results.md").read_text()
    q_table = torch.load(run_dir / "q_table.pt")
    again = module.run(
        _tiny(
            module,
            tmp_path,
            rounds=1,
            final_episodes=2,
            particles=30,
            vision_sigma=0.004,
            resume=str(run_dir),
        )
    )
    assert again["run_dir"] == str(run_dir)
    assert set(again["evaluations"]) == {"oracle", "raw", "qmdp + fitted", "qmdp + physics"}
    assert again["history"] == trained["history"]
    assert torch.equal(torch.load(run_dir / "q_table.pt"), q_table)
    refused = "other arguments .*: epsilon: checkpoint 0.1, now 0.2$"  # a training argument
    with pytest.raises(ValueError, match=refused):
        module.run(
            _tiny(module, tmp_path, rounds=1, final_episodes=0, epsilon=0.2, resume=str(run_dir))
        )


@pytest.mark.bitwise("a resumed run runs the same code on the same inputs in the same process")
def test_resuming_from_a_checkpoint_reproduces_the_uninterrupted_run(
    module: ModuleType, straight: dict[str, Any], tmp_path: Path
) -> None:
    stopped = module.run(_tiny(module, tmp_path, rounds=1))
    resumed = module.run(_tiny(module, tmp_path, resume=stopped["run_dir"]))
    assert resumed["run_dir"] == stopped["run_dir"] != straight["run_dir"]
    _assert_identical(straight, resumed)
    with pytest.raises(
        ValueError,
        match=r"mode_episodes may differ\): seed: checkpoint 0, now 3; "
        r"alpha: checkpoint 0\.1, now 0\.5$",
    ):
        module.run(_tiny(module, tmp_path, alpha=0.5, seed=3, resume=stopped["run_dir"]))


def _assert_identical(a: dict[str, Any], b: dict[str, Any]) -> None:
    """Two runs' results and final Q tables are bit-identical."""
    assert a["history"] == b["history"]
    assert a["evaluations"] == b["evaluations"]
    assert a["num_states"] == b["num_states"]
    q_a = torch.load(Path(a["run_dir"]) / "q_table.pt")
    q_b = torch.load(Path(b["run_dir"]) / "q_table.pt")
    assert torch.equal(q_a, q_b)
    graph = [(Path(r["run_dir"]) / "graph.json").read_text() for r in (a, b)]
    assert graph[0] == graph[1]  # (results.md differs: it holds timings)


class _KilledError(Exception):
    """Stands for a kill of the process."""


@pytest.mark.bitwise("a resumed run runs the same code on the same inputs in the same process")
def test_a_run_killed_after_any_checkpoint_resumes_to_an_identical_result(
    module: ModuleType,
    straight_three: dict[str, Any],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    save = module.save_checkpoint
    for killed_after in (1, 2):
        writes: list[Path] = []

        def save_then_kill(
            path: Path,
            payload: dict[str, Any],
            writes: list[Path] = writes,
            after: int = killed_after,
        ) -> None:
            save(path, payload)
            writes.append(path.parent)
            if len(writes) == after:
                raise _KilledError

        monkeypatch.setattr(module, "save_checkpoint", save_then_kill)
        with pytest.raises(_KilledError):
            module.run(_tiny(module, tmp_path, rounds=3))
        monkeypatch.setattr(module, "save_checkpoint", save)
        resumed = module.run(_tiny(module, tmp_path, rounds=3, resume=str(writes[0])))
        _assert_identical(straight_three, resumed)


def test_a_kill_during_the_checkpoint_write_keeps_the_previous_checkpoint(
    module: ModuleType,
    straight_three: dict[str, Any],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    stopped = module.run(_tiny(module, tmp_path, rounds=2))
    checkpoint = Path(stopped["run_dir"]) / "checkpoint.pt"
    before = checkpoint.read_bytes()

    def killed_mid_write(payload: object, file: Any) -> None:
        file.write(before[: len(before) // 2])
        raise _KilledError

    monkeypatch.setattr(torch, "save", killed_mid_write)
    with pytest.raises(_KilledError):  # round 3's checkpoint write is killed halfway
        module.run(_tiny(module, tmp_path, rounds=3, resume=stopped["run_dir"]))
    monkeypatch.undo()
    assert checkpoint.read_bytes() == before
    assert not [p for p in checkpoint.parent.iterdir() if p.suffix == ".tmp"]
    resumed = module.run(_tiny(module, tmp_path, rounds=3, resume=stopped["run_dir"]))
    _assert_identical(straight_three, resumed)


def test_a_damaged_checkpoint_is_named_when_resuming(module: ModuleType, tmp_path: Path) -> None:
    stopped = module.run(_tiny(module, tmp_path, rounds=1, final_episodes=0))
    checkpoint = Path(stopped["run_dir"]) / "checkpoint.pt"
    data = checkpoint.read_bytes()
    checkpoint.write_bytes(data[: len(data) // 3])
    with pytest.raises(ValueError, match=f"{checkpoint}: unreadable or damaged checkpoint"):
        module.run(_tiny(module, tmp_path, resume=stopped["run_dir"]))
    torch.save({"args": dataclasses.asdict(_tiny(module, tmp_path, rounds=1))}, checkpoint)
    with pytest.raises(ValueError, match=r"lacks the entries \['agent', 'round'"):
        module.run(_tiny(module, tmp_path, resume=stopped["run_dir"]))
    with pytest.raises(ValueError, match=r"resume: .* is not a run folder"):
        module.run(_tiny(module, tmp_path, resume=str(tmp_path / "nothing")))


def test_each_run_gets_its_own_folder(module: ModuleType, tmp_path: Path) -> None:
    args = _tiny(module, tmp_path, rounds=1, final_episodes=0, seed=4)
    first, second = module.run(args), module.run(args)  # most likely in the same second
    names = [Path(first["run_dir"]).name, Path(second["run_dir"]).name]
    assert names[0] != names[1]
    for name in names:
        assert re.fullmatch(r"dyna_q_peg__4__\d+(_1)?", name), name
    assert {p.name for p in tmp_path.iterdir()} == set(names)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"particles": 16}, r"particles: expected an int >= 24 \(the belief model's number of "),
        ({"exploration": "foo"}, r"exploration: expected one of \('uniform', 'least_tried'\)"),
        ({"step_size": "decay"}, r"step_size: expected one of \('constant', 'visits'\)"),
        ({"rounds": -1}, r"rounds: expected an int >= 1, got -1"),
        ({"rounds": 0}, r"rounds: expected an int >= 1, got 0"),
        ({"num_envs": 0}, r"num_envs: expected an int >= 1"),
        ({"eval_every": 0}, r"eval_every: expected an int >= 1"),
        ({"final_episodes": -1}, r"final_episodes: expected an int >= 0"),
        ({"alpha": 0.0}, r"alpha: expected a finite number in \(0.0, 1.0\]"),
        ({"gamma": 1.5}, r"gamma: expected a finite number in \[0.0, 1.0\]"),
        ({"epsilon": -0.1}, r"epsilon: expected a finite number"),
        ({"vision_sigma": 0.0}, r"vision_sigma: expected a finite number > 0"),
        ({"shaping": float("nan")}, r"shaping: expected a finite number"),
        ({"planning_steps": -1}, r"planning_steps: expected an int >= 0"),
        ({"name": "a/b"}, r"name: expected a non-empty name"),
        ({"y_edges": "0,a"}, r"y_edges must be comma-separated numbers"),
    ],
)
def test_bad_arguments_fail_before_any_work(
    module: ModuleType, tmp_path: Path, change: dict[str, object], message: str
) -> None:
    clock = time.perf_counter()
    with pytest.raises(ValueError, match=message):
        module.run(_tiny(module, tmp_path / "runs", **change))
    assert time.perf_counter() - clock < 5.0
    assert not (tmp_path / "runs").exists()  # no run folder


def test_help_lists_the_arguments(module: ModuleType, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        module.main(["--help"])
    text = capsys.readouterr().out
    for flag in ("--planning-steps", "--resume", "--step-size {constant,visits}", "--no-sweep"):
        assert flag in text
    assert "Dyna-Q planning n" in text  # the fields' help texts


def test_main_parses_the_command_line(
    module: ModuleType, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    received: list[object] = []
    monkeypatch.setattr(module, "run", lambda args: received.append(args) or {"run_dir": ""})
    monkeypatch.setattr(Path, "read_text", lambda self: "")
    module.main(["--rounds", "3", "--no-sweep", "--resume", str(tmp_path)])
    assert received == [module.Args(rounds=3, sweep=False, resume=str(tmp_path))]


def test_defaults_are_the_shared_peg_learning_settings(module: ModuleType) -> None:
    settings = PegLearning(alpha=0.2, planning_steps=3, planning_penalty=0.1, epsilon=0.3)
    agent = settings.agent(seed=5)
    for name in ("alpha", "planning_steps", "planning_penalty", "gamma", "epsilon"):
        assert getattr(agent, name) == getattr(settings, name), name
    assert (agent.step_size, agent.exploration, agent.seed) == ("visits", "least_tried", 5)
    assert settings.potential_shaping() == PotentialShaping(5.0)
    args = module.Args()
    for field in dataclasses.fields(PegLearning):
        assert getattr(args, field.name) == field.default, field.name


def test_grid_edges_from_the_command_line(module: ModuleType) -> None:
    args = module.Args(y_edges="-0.01, 0, 0.01,0.03", angle_edges="-0.1,0.1")
    config = module._config(args, noisy=False)
    assert config.y_edges == (-0.01, 0.0, 0.01, 0.03)
    assert config.angle_edges == (-0.1, 0.1)
    assert config.x_edges == module.PegInHoleConfig().x_edges  # empty: the default
    with pytest.raises(ValueError, match="y_edges must be comma-separated numbers"):
        module._config(module.Args(y_edges="0,a"), noisy=False)
    with pytest.raises(ValueError, match="x_edges"):
        module._config(module.Args(x_edges="0.02,0.01"), noisy=False)


@pytest.mark.bitwise("the same seed draws the same start by the same code")
def test_rounds_play_distinct_episodes() -> None:
    """Sub-environment i of a reset with seed s plays seed s + i: rounds seeded base + r would
    share all but one episode with the previous round; round_seed keeps every round's
    episodes distinct."""
    env = PegInHole2DVector(num_envs=4)
    starts = []
    for r in range(3):
        _, info = env.reset(seed=round_seed(7, r, num_envs=4))
        starts.append(info["peg_pose"])
    assert len(np.unique(np.concatenate(starts).round(12), axis=0)) == 12
    _, first = env.reset(seed=7)
    _, shifted = env.reset(seed=8)
    np.testing.assert_array_equal(first["peg_pose"][1:], shifted["peg_pose"][:-1])


def test_seed_table_aggregates_the_runs_metrics(module: ModuleType, tmp_path: Path) -> None:
    """The tables over training seeds: ``aggregate_seeds`` of each run's ``metrics.json``."""
    runs = [module.run(_tiny(module, tmp_path, seed=seed, rounds=1)) for seed in (0, 1)]
    metrics = [json.loads(Path(r["run_dir"], "metrics.json").read_text()) for r in runs]
    rows = aggregate_seeds({"sigma": metrics}, metrics=["execution/qmdp + physics/success"])
    (row,) = rows
    values = [r["evaluations"]["qmdp + physics"] for r in runs]
    assert row.statistics.n == 2
    assert row.statistics.mean == pytest.approx(sum(values) / 2, abs=1e-12)
    assert row.statistics.min == pytest.approx(min(values), abs=1e-12)
    assert "execution/qmdp + physics/success" in statistics_table(rows)
