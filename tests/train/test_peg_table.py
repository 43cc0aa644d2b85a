"""The execution table's missing cells: the raw observation on the occluded variant (the last
camera pose carried with the gripper), belief features that mean the same under the physics
model, and the neural script's final comparison on either belief model."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import torch

from tests.train import load_script
from torchcontact.envs import (
    NUM_CONTACT_CLASSES,
    PegInHole2DVector,
    PegInHoleFilter,
    PegPhysicsModel,
)
from torchcontact.experiments import NUM_BELIEF_FEATURES, QLookup, belief_features, raw_poses
from torchcontact.rl import DynaQ


def _world(gripper: np.ndarray, grasp: np.ndarray) -> np.ndarray:
    """``g ⊕ x`` by complex numbers: position ``g + e^{iγ} (u + i w)``, angle ``γ + φ``."""
    z = (
        gripper[:, 0]
        + 1j * gripper[:, 1]
        + np.exp(1j * gripper[:, 2]) * (grasp[:, 0] + 1j * grasp[:, 1])
    )
    return np.stack([z.real, z.imag, gripper[:, 2] + grasp[:, 2]], -1)


def test_raw_poses_carry_the_last_seen_pose_with_the_gripper() -> None:
    """Seen rows are the camera's pose exactly; a blind row is the gripper composed with the
    grasp of the last seen pose (by complex numbers), or with the initial hold if never seen."""
    rng = np.random.default_rng(0)
    grasp = rng.normal(scale=[0.01, 0.05, 0.1], size=(3, 3))
    gripper0 = rng.normal(scale=[0.05, 0.1, 0.3], size=(3, 3))
    camera0 = _world(gripper0, grasp)
    camera0[2] = np.nan  # episode 2 is blind from the start
    hold = torch.tensor([0.0, -0.07, 0.0], dtype=torch.float64).expand(3, 3)
    pose, held = raw_poses({"peg_pose": camera0, "gripper_pose": gripper0}, held=hold)
    assert (pose[:2] == torch.as_tensor(camera0[:2])).all()  # passed through: exact
    torch.testing.assert_close(held[:2], torch.as_tensor(grasp[:2]), rtol=0, atol=1e-12)
    expected = _world(gripper0[2:], hold[2:].numpy())
    torch.testing.assert_close(pose[2:], torch.as_tensor(expected), rtol=0, atol=1e-12)
    # the gripper moves and turns; the camera sees only episode 1 now
    gripper1 = gripper0 + rng.normal(scale=[0.02, 0.02, 0.2], size=(3, 3))
    camera1 = np.full((3, 3), np.nan)
    camera1[1] = [0.01, 0.02, 0.03]
    pose, held = raw_poses({"peg_pose": camera1, "gripper_pose": gripper1}, held=held)
    assert (pose[1] == torch.as_tensor(camera1[1])).all()
    torch.testing.assert_close(
        pose[0], torch.as_tensor(_world(gripper1[:1], grasp[:1])[0]), rtol=0, atol=1e-12
    )
    torch.testing.assert_close(
        pose[2], torch.as_tensor(_world(gripper1[2:], hold[2:].numpy())[0]), rtol=0, atol=1e-12
    )
    with pytest.raises(ValueError, match="peg_pose must be finite or all NaN"):
        raw_poses({"peg_pose": [[0.0, np.nan, 0.0]], "gripper_pose": [[0.0] * 3]}, held=hold[:1])
    with pytest.raises(ValueError, match="gripper_pose must be finite"):
        raw_poses({"peg_pose": [[0.0] * 3], "gripper_pose": [[np.inf, 0, 0]]}, held=hold[:1])


def test_belief_features_have_the_class_marginals_under_the_physics_model(
    tabular_run: Path,
) -> None:
    """Under the physics model (33-odd modes) the features have the fitted model's size, and
    their class marginals are the particle weights summed by their modes' classes (a loop)."""
    physics: PegPhysicsModel = torch.load(tabular_run / "physics_model.pt", weights_only=False)
    assert physics.num_modes != NUM_CONTACT_CLASSES
    saved = torch.load(tabular_run / "checkpoint.pt", weights_only=False)
    lookup = QLookup(DynaQ.from_state_dict(saved["agent"]), physics.task.states)
    env = PegInHole2DVector(num_envs=2, config=physics.task.config, observation="noisy")
    observation, _ = env.reset(seed=3)
    filt = PegInHoleFilter(physics, num_particles=24)
    belief = filt.init(observation)
    generator = torch.Generator().manual_seed(0)
    for action in (3, 4, 4):  # +y, then down twice
        observation, *_ = env.step(np.full(2, action))
        belief = filt.step(belief, np.full(2, action), observation, generator=generator)
    features = belief_features(filt, belief, lookup, observation)
    M = lookup.table.shape[0]
    assert features.shape == (2, M + NUM_BELIEF_FEATURES)
    assert torch.isfinite(features).all()
    weights = belief.rbpf.log_weights.exp()
    expected = torch.zeros(2, NUM_CONTACT_CLASSES, dtype=torch.float64)
    for b in range(2):
        for i in range(filt.num_particles):
            expected[b, int(physics.mode_class[belief.rbpf.modes[b, i]])] += weights[b, i]
    marginal = features[:, M + 8 : M + 8 + NUM_CONTACT_CLASSES]
    torch.testing.assert_close(marginal, expected, rtol=0, atol=1e-12)
    entropy = -(expected * expected.clamp(min=1e-300).log()).sum(-1)
    torch.testing.assert_close(features[:, M + 6], entropy, rtol=0, atol=1e-12)


@pytest.fixture(scope="module")
def module() -> ModuleType:
    return load_script("neural_q_peg")


def _tiny(module: ModuleType, out: Path, tabular: Path, **changes: object) -> object:
    args = module.Args(
        out_dir=str(out),
        tabular_run=str(tabular),
        num_envs=2,
        rounds=1,
        particles=24,
        hidden=8,
        learning_starts=10_000,
        eval_episodes=2,
        final_episodes=3,
        mode_episodes=8,
    )
    return dataclasses.replace(args, **changes)


def test_the_final_comparison_runs_on_both_belief_models(
    module: ModuleType, tabular_run: Path, tmp_path: Path
) -> None:
    """``--belief both`` labels the qmdp and neural rows by model, ``--final-settings`` picks
    the rows (raw included on the occluded variant), a finished run resumed with other final
    arguments only evaluates again, and the gated network is QMDP on a camera that always
    sees, episode for episode, under either model."""
    first = module.run(_tiny(module, tmp_path, tabular_run, occlusion_radius=0.05))
    assert set(first["evaluations"]) == {"oracle", "qmdp", "probe", "shift", "neural"}
    changes = {"occlusion_radius": 0.05, "belief": "both", "resume": first["run_dir"]}
    again = module.run(
        _tiny(module, tmp_path, tabular_run, final_settings=("raw", "qmdp"), **changes)
    )
    assert again["run_dir"] == first["run_dir"]
    assert again["history"] == first["history"]
    assert set(again["evaluations"]) == {"raw", "qmdp + fitted", "qmdp + physics"}
    metrics = json.loads((Path(first["run_dir"]) / "metrics.json").read_text())
    assert {"execution/raw/success", "execution/qmdp + physics/ms_per_decision"} <= set(metrics)
    standard = module.run(
        _tiny(module, tmp_path, tabular_run, blind_only=True, belief="both", final_episodes=4)
    )
    assert set(standard["evaluations"]) == {
        "oracle",
        "raw",
        "qmdp + fitted",
        "qmdp + physics",
        "neural + fitted",
        "neural + physics",
    }
    run_dir = Path(standard["run_dir"])
    for model in ("fitted", "physics"):
        for kind in ("successes", "lengths"):
            qmdp = np.load(run_dir / f"{kind}_qmdp_{model}.npy")
            neural = np.load(run_dir / f"{kind}_neural_{model}.npy")
            assert (qmdp == neural).all(), (model, kind)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"belief": "exact"}, r"belief: expected one of \('fitted', 'physics', 'both'\)"),
        ({"final_settings": ("qmdp", "best")}, r"final_settings: expected one of \("),
        ({"mode_episodes": 0}, r"mode_episodes: expected an int >= 1"),
    ],
)
def test_bad_final_arguments_fail_before_any_work(
    module: ModuleType, tabular_run: Path, tmp_path: Path, change: dict[str, object], message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        module.run(_tiny(module, tmp_path / "runs", tabular_run, **change))
    assert not (tmp_path / "runs").exists()
