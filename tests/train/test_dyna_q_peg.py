"""The Dyna-Q peg-in-hole script runs end to end on a tiny budget and resumes exactly."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import torch

from tests.train import load_script
from torchcontact.envs import PegInHole2DVector
from torchcontact.experiments import PegLearning, PotentialShaping, load_checkpoint, round_seed


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
    )
    return dataclasses.replace(args, **changes)


@pytest.fixture(scope="module")
def module() -> ModuleType:
    return load_script("dyna_q_peg")


def test_runs_and_writes_its_artefacts(module: ModuleType, tmp_path: Path) -> None:
    result = module.run(_tiny(module, tmp_path))
    run_dir = Path(result["run_dir"])
    artefacts = ("results.md", "q_table.pt", "graph.json", "graph.png", "learning.png")
    for name in (*artefacts, "checkpoint.pt"):
        assert (run_dir / name).is_file(), name
    assert set(result["evaluations"]) == {"oracle", "raw", "qmdp"}
    assert len(result["history"]) == 2
    assert "greedy_success" in result["history"][-1]
    assert list(run_dir.glob("events.out.tfevents.*"))
    text = (run_dir / "results.md").read_text()
    assert "| qmdp | 3 |" in text
    greedy = [f"{100 * h['greedy_success']:.1f} %" for h in result["history"]]
    assert "| greedy success (true state) | " + " | ".join(greedy) + " |" in text


def test_a_finished_run_is_evaluated_again_without_training(
    module: ModuleType, tmp_path: Path
) -> None:
    trained = module.run(_tiny(module, tmp_path, rounds=1, final_episodes=0))
    assert trained["evaluations"] == {}
    run_dir = Path(trained["run_dir"])
    assert "No final evaluation." in (run_dir / "results.md").read_text()
    q_table = torch.load(run_dir / "q_table.pt")
    again = module.run(
        _tiny(module, tmp_path, rounds=1, final_episodes=2, particles=30, vision_sigma=0.004)
    )
    assert set(again["evaluations"]) == {"oracle", "raw", "qmdp"}
    assert again["history"] == trained["history"]
    assert torch.equal(torch.load(run_dir / "q_table.pt"), q_table)
    with pytest.raises(ValueError, match="other arguments"):  # a training argument
        module.run(_tiny(module, tmp_path, rounds=1, final_episodes=0, epsilon=0.2))
    with pytest.raises(ValueError, match="free names fields"):
        load_checkpoint(run_dir / "checkpoint.pt", _tiny(module, tmp_path), free=("sigma",))


def test_resuming_from_a_checkpoint_reproduces_the_uninterrupted_run(
    module: ModuleType, tmp_path: Path
) -> None:
    straight = module.run(_tiny(module, tmp_path / "a"))
    module.run(_tiny(module, tmp_path / "b", rounds=1))
    resumed = module.run(_tiny(module, tmp_path / "b"))
    assert resumed["history"] == straight["history"]
    q_a = torch.load(Path(straight["run_dir"]) / "q_table.pt")
    q_b = torch.load(Path(resumed["run_dir"]) / "q_table.pt")
    assert torch.equal(q_a, q_b)
    with pytest.raises(ValueError, match="other arguments"):
        module.run(_tiny(module, tmp_path / "b", alpha=0.5))


def test_help_lists_the_arguments(module: ModuleType, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        module.main(["--help"])
    text = capsys.readouterr().out
    assert "--planning-steps" in text
    assert "--no-resume" in text


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


def test_bad_choices_name_the_argument(module: ModuleType, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="exploration must be 'uniform' or 'least_tried'"):
        module.run(_tiny(module, tmp_path, exploration="greedy"))
    with pytest.raises(ValueError, match="step_size must be 'constant' or 'visits'"):
        module.run(_tiny(module, tmp_path, step_size="decay"))


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
