"""The peg-in-hole environments: gymnasium API, physics checks, seeding, vectorization."""

from __future__ import annotations

import bisect
import math
import warnings
from dataclasses import replace
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from gymnasium.wrappers import TimeLimit

from torchcontact.envs import (
    ENV_BELOW,
    GRASP_NONE,
    GRASP_SLIDE,
    HELD_FREE,
    NUM_CONTACT_CLASSES,
    PEG_IN_HOLE_ID,
    PegInHole2D,
    PegInHole2DVector,
    PegInHoleConfig,
    observation_bounds,
)
from torchcontact.sim import UNSOLVED, Simulator, StepResult
from torchcontact.states import ManipulationState

STAY, RIGHT, LEFT, UP, DOWN, TURN_LEFT, TURN_RIGHT = range(7)


def scripted_action(env: PegInHole2D, observation: np.ndarray) -> int:
    """Align the peg's angle, then its bottom over the hole, then descend."""
    bottom_x, bottom_y, angle = env.states.relative_pose(torch.as_tensor(observation[:3])).tolist()
    c = env.config
    if bottom_y > 0.003 and abs(angle) > 0.6 * c.turn_step:
        return TURN_RIGHT if angle > 0 else TURN_LEFT
    if bottom_y > 0.003 and abs(bottom_x) > 0.6 * c.move_step:
        return LEFT if bottom_x > 0 else RIGHT
    return DOWN


def flatten(observation: Any) -> np.ndarray:
    if isinstance(observation, dict):
        return np.concatenate(
            [np.asarray(observation[k], dtype=np.float64).ravel() for k in sorted(observation)]
        )
    return np.asarray(observation, dtype=np.float64).ravel()


@pytest.mark.parametrize("observation", ["state", "noisy"])
@pytest.mark.parametrize("render_mode", [None, "rgb_array"])
def test_passes_gymnasiums_env_checker_without_warnings(
    observation: str, render_mode: str | None
) -> None:
    """Every warning is an error: finite Box bounds, stackable info, a spec (from ``make``)."""
    env = gym.make(PEG_IN_HOLE_ID, observation=observation, render_mode=render_mode)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env.unwrapped)


def test_registered_with_gymnasium() -> None:
    env = gym.make(PEG_IN_HOLE_ID, observation="noisy")
    observation, _ = env.reset(seed=0)
    assert env.observation_space.contains(observation)
    assert isinstance(env.unwrapped, PegInHole2D)
    vector = gym.make_vec(PEG_IN_HOLE_ID, num_envs=2, vectorization_mode="vector_entry_point")
    assert isinstance(vector.unwrapped, PegInHole2DVector)


@pytest.mark.bitwise("the same code on the same inputs in the same process")
def test_same_seed_same_trajectory_different_seed_different() -> None:
    actions = np.random.default_rng(0).integers(0, 7, size=15)

    def run(seed: int) -> list[np.ndarray]:
        env = PegInHole2D(observation="noisy")
        observation, info = env.reset(seed=seed)
        rows = [np.concatenate([flatten(observation), info["peg_pose"]])]
        for action in actions:
            observation, reward, _, _, info = env.step(int(action))
            rows.append(np.concatenate([flatten(observation), info["peg_pose"], [reward]]))
        return rows

    first, again, other = run(7), run(7), run(8)
    for a, b in zip(first, again, strict=True):
        np.testing.assert_array_equal(a, b)
    assert not np.allclose(first[0], other[0])


def test_scripted_policy_inserts_the_peg_for_most_seeds() -> None:
    env = PegInHole2D()
    successes = 0
    for seed in range(8):
        observation, info = env.reset(seed=seed)
        assert info["contact_class"] == HELD_FREE
        for _ in range(env.config.max_steps):
            observation, reward, terminated, truncated, info = env.step(
                scripted_action(env, observation)
            )
            if terminated or truncated:
                break
        if info["success"]:
            successes += 1
            assert terminated
            assert not truncated
            assert reward == pytest.approx(env.config.success_reward - env.config.step_cost)
            bottom = env.states.relative_pose(torch.as_tensor(info["peg_pose"]))
            assert float(bottom[1]) <= -env.config.insertion_depth
            assert abs(float(bottom[0])) < env.config.hole_width / 2
    assert successes >= 7


def test_a_policy_on_manipulation_states_alone_inserts_the_peg() -> None:
    """The discrete state suffices: the cell says where the peg is even without contact."""
    env = PegInHole2D()
    c = env.config
    centre_x = bisect.bisect_right(c.x_edges, 0.0)
    centre_angle = bisect.bisect_right(c.angle_edges, 0.0)
    clear = bisect.bisect_right(c.y_edges, 0.004)  # bottom at least this far above the mouth

    def act(state: ManipulationState) -> int:
        i_x, i_y, i_angle = state.pose
        if i_y >= clear and i_angle != centre_angle:
            return TURN_RIGHT if i_angle > centre_angle else TURN_LEFT
        if i_y >= clear and i_x != centre_x:
            return LEFT if i_x > centre_x else RIGHT
        return DOWN

    for seed in range(4):
        _, info = env.reset(seed=100 + seed)
        for _ in range(c.max_steps):
            _, _, terminated, truncated, info = env.step(act(info["manipulation_state"]))
            if terminated or truncated:
                break
        assert info["success"], seed


@pytest.mark.bitwise("the noiseless channels copy the true values; tactile cells are 0 or 1")
def test_noisy_observations_follow_the_noise_model() -> None:
    """Pose noise is the generator's normals times the std; tactile flips at the given rates."""
    std = (0.003, 0.001, 0.05)
    env = PegInHole2D(config=PegInHoleConfig(pose_noise_std=std), observation="noisy")
    observation, info = env.reset(seed=11)
    generator = np.random.default_rng(11)  # what gymnasium seeds the environment with
    generator.uniform(size=5)  # the start's draws come first
    expected = info["peg_pose"] + np.asarray(std) * generator.normal(size=3)
    np.testing.assert_allclose(observation["peg_pose"], expected, atol=1e-15)
    np.testing.assert_array_equal(observation["gripper_pose"], info["gripper_pose"])
    for rates, reading in [((0.0, 0.0), None), ((1.0, 0.0), 1), ((0.0, 1.0), 0)]:
        config = PegInHoleConfig(tactile_false_positive=rates[0], tactile_false_negative=rates[1])
        env = PegInHole2D(config=config, observation="noisy")
        observation, info = env.reset(seed=1)
        triggered = info["tactile_triggered"].astype(np.int8)
        assert triggered.sum() >= 2  # the pads touch the peg's side sensors
        target = triggered if reading is None else np.full_like(triggered, reading)
        np.testing.assert_array_equal(observation["tactile"], target)


def test_peg_slips_and_turns_in_the_grasp_when_pressed_on_the_block() -> None:
    """A tilted peg pressed onto the flat block top slides up the pads and turns in them."""
    env = PegInHole2D()
    start = {"gripper_x": 0.1, "peg_height": 0.004, "gripper_angle": 0.2, "grasp_angle": 0.0}
    _, info = env.reset(seed=0, options={**start, "grasp_offset": 0.04})
    before = info["peg_in_gripper"].copy()
    held = env.reset(seed=0, options={**start, "grasp_offset": 0.04})[1]["peg_in_gripper"]
    for _ in range(10):  # holding still: the grasp is firm
        info = env.step(STAY)[4]
    np.testing.assert_allclose(info["peg_in_gripper"], held, atol=1e-3)
    env.reset(seed=0, options={**start, "grasp_offset": 0.04})
    classes = []
    for _ in range(10):  # pressing down on the block top
        info = env.step(DOWN)[4]
        classes.append(info["contact_class"])
    after = info["peg_in_gripper"]
    assert after[1] - before[1] > 0.01  # slid up along the pads
    assert abs(after[2] - before[2]) > 0.02  # turned relative to the fingers (rad)
    assert GRASP_SLIDE * 8 + ENV_BELOW in classes  # slipping grasp, resting on the block
    assert not info["dropped"]


def test_without_grip_force_the_peg_falls_freely() -> None:
    """Nothing squeezes the peg: it falls as semi-implicit Euler predicts, ≈ g t² / 2."""
    config = PegInHoleConfig(grip_force=0.0)
    g, h = config.gravity, config.h
    env = PegInHole2D(config=config)
    options = {"gripper_angle": 0.0, "grasp_angle": 0.0, "peg_height": 0.05, "grasp_offset": 0.0}
    _, info = env.reset(seed=3, options=options)
    start, settle = info["peg_pose"].copy(), config.settle_steps
    # The peg started at rest, touching the pads, ``settle`` steps before the reset returned.
    y_initial = start[1] + g * h**2 * settle * (settle + 1) / 2
    assert info["peg_twist"][1] == pytest.approx(-g * h * settle, abs=1e-12)
    for k in range(1, 3):
        info = env.step(STAY)[4]
        n = settle + k * config.substeps
        drop = y_initial - info["peg_pose"][1]
        assert drop == pytest.approx(g * h**2 * n * (n + 1) / 2, abs=1e-12)
        continuous = g * (n * h) ** 2 / 2  # the time-continuous fall, to O(h)
        assert abs(drop - continuous) <= g * h * (n * h) / 2 + 1e-12
        assert info["peg_pose"][0] == pytest.approx(start[0], abs=1e-12)
        assert info["peg_pose"][2] == pytest.approx(start[2], abs=1e-12)
        assert info["contact_class"] == GRASP_NONE * 8  # nothing touches the peg
    assert drop > 0.02


def test_vector_env_equals_a_loop_of_single_envs() -> None:
    """Same seeds and actions: the batch reproduces single environments, auto-resets included.

    Sub-environment 0 starts just above the hole and only descends, so it succeeds and
    auto-resets while the others are still stepping; all of them hit the time limit later.
    """
    config = PegInHoleConfig(max_steps=8, insertion_depth=0.004)
    B, T, seed = 3, 18, 10
    actions = np.random.default_rng(1).integers(0, 7, size=(T, B))
    actions[:, 0] = DOWN
    starts = {
        "gripper_x": np.array([0.0, 0.05, -0.05]),
        "peg_height": np.array([0.002, 0.02, 0.03]),
        "gripper_angle": 0.0,
        "grasp_angle": 0.0,
    }
    vector = PegInHole2DVector(num_envs=B, config=config, observation="noisy")
    assert vector.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    observation, infos = vector.reset(seed=seed, options=starts)
    batch = [(observation, infos["peg_pose"], None, None, None)]
    for t in range(T):
        observation, reward, terminated, truncated, infos = vector.step(actions[t])
        assert vector.observation_space.contains(observation)
        batch.append((observation, infos["peg_pose"], reward, terminated, truncated))
    ends: dict[str, list[int]] = {"terminated": [], "truncated": []}
    for i in range(B):
        env = TimeLimit(PegInHole2D(config=config, observation="noisy"), config.max_steps)
        options = {key: float(np.broadcast_to(value, B)[i]) for key, value in starts.items()}
        observation, info = env.reset(seed=seed + i, options=options)
        done = False
        for t in range(T + 1):
            if t > 0:
                if done:
                    observation, info = env.reset()
                    reward, terminated, truncated = 0.0, False, False
                else:
                    action = int(actions[t - 1, i])
                    observation, reward, terminated, truncated, info = env.step(action)
                done = terminated or truncated
                ends["terminated"] += [t] * terminated
                ends["truncated"] += [t] * truncated
                assert batch[t][2][i] == pytest.approx(reward, abs=1e-12)
                assert (batch[t][3][i], batch[t][4][i]) == (terminated, truncated)
            expected = {key: value[i] for key, value in batch[t][0].items()}
            np.testing.assert_allclose(flatten(expected), flatten(observation), atol=1e-9)
            np.testing.assert_allclose(batch[t][1][i], info["peg_pose"], atol=1e-9)
    assert ends["terminated"]  # a success ended an episode early...
    assert min(ends["terminated"]) < config.max_steps  # ...while the others kept stepping
    assert len(ends["truncated"]) >= B - 1


def test_random_actions_stay_finite_and_inside_the_observation_bounds() -> None:
    """The true poses and twists of held pegs (info, not clipped) lie inside the bounds."""
    vector = PegInHole2DVector(num_envs=12, observation="noisy")
    bounds = observation_bounds(vector.config)
    vector.reset(seed=0)
    rng = np.random.default_rng(2)
    for _ in range(40):
        observation, reward, _, _, infos = vector.step(rng.integers(0, 7, size=12))
        assert vector.observation_space.contains(observation)
        held = ~infos["dropped"]
        for key, (low, high) in bounds.items():
            assert ((infos[key][held] > low) & (infos[key][held] < high)).all(), key
        assert np.isfinite(observation["peg_pose"]).all()
        assert np.isfinite(reward).all()
        assert np.isfinite(infos["peg_twist"]).all()
        assert not bool(vector.physics.unsolved.any())
        assert (
            (infos["contact_class"] >= 0) & (infos["contact_class"] < NUM_CONTACT_CLASSES)
        ).all()


def test_info_reports_the_true_contacts_and_manipulation_state() -> None:
    env = PegInHole2D(render_mode="rgb_array")
    _, info = env.reset(seed=4)
    active = info["contact_active"]
    K = env.peg_contacts().points.shape[-2]  # the peg's slots in the scene
    assert active.shape == info["contact_impulses"].shape == info["contact_partners"].shape == (K,)
    assert info["contact_points"].shape == info["contact_normals"].shape == (K, 2)
    assert set(info["contact_partners"][active]) == {"finger_left", "finger_right"}
    assert set(info["contact_partners"][~active]) == {""}
    assert (info["contact_impulses"][active] > 0).all()
    inactive = np.concatenate(
        [info[key][~active].ravel() for key in ("contact_points", "contact_normals")]
        + [info["contact_impulses"][~active]]
    )
    assert (inactive == 0.0).all()  # exact: padding is written as zeros
    normals_x = info["contact_normals"][active, 0]  # the pads push the peg from both sides
    assert (normals_x > 0.9).any()
    assert (normals_x < -0.9).any()
    assert info["contact_state"].robot
    assert not info["contact_state"].environment
    peg = torch.as_tensor(info["peg_pose"]).unsqueeze(0)
    state_id = int(env.manipulation_state_of(peg, torch.tensor([info["contact_class"]]))[0])
    assert state_id == info["manipulation_state_id"]
    assert info["manipulation_state"] == env.manipulation_state_key(state_id)
    assert env.peg_contacts().batch_shape == ()
    image = env.render()
    assert image is not None
    assert image.shape == (360, 480, 3)
    assert image.dtype == np.uint8
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 3


def test_bad_arguments_raise_value_errors_naming_them() -> None:
    for field, value in [
        ("clearance", -0.001),
        ("substeps", 0),
        ("peg_mass", math.nan),
        ("x_edges", (0.1, 0.0)),
        ("workspace_x", (0.2, -0.2)),
        ("insertion_depth", 1.0),
        ("tactile_false_positive", 1.5),
        ("pose_noise_std", (0.1, 0.1)),
    ]:
        with pytest.raises(ValueError, match=field):
            PegInHoleConfig(**{field: value})
    with pytest.raises(ValueError, match="observation"):
        PegInHole2D(observation="pixels")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="render_mode"):
        PegInHole2D(render_mode="human")
    with pytest.raises(ValueError, match="config"):
        PegInHole2D(config={"clearance": 0.01})  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="num_envs"):
        PegInHole2DVector(num_envs=0)
    env = PegInHole2D()
    with pytest.raises(ValueError, match="options"):
        env.reset(seed=0, options={"peg_x": 0.0})
    with pytest.raises(ValueError, match="action"):
        env.step(7)
    vector = PegInHole2DVector(num_envs=3)
    with pytest.raises(ValueError, match="seed"):
        vector.reset(seed=[1, 2])
    vector.reset(seed=0)
    with pytest.raises(ValueError, match="actions"):
        vector.step(np.zeros(2, dtype=np.int64))


def test_a_failed_solve_ends_the_episode_as_dropped_with_clean_contacts(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A step whose solver fails (garbage impulses, some negative) ends the episode; it must not
    crash the contact report."""
    env = PegInHole2D()
    env.reset(seed=3)
    solve = Simulator.step

    def failing(self: Simulator, *args: Any, **kwargs: Any) -> StepResult:
        result = solve(self, *args, **kwargs)
        return replace(
            result,
            pn=result.pn - 0.05,
            solver=torch.full_like(result.solver, UNSOLVED),
            residual=torch.full_like(result.residual, 1.0),
        )

    monkeypatch.setattr(Simulator, "step", failing)
    _, reward, terminated, truncated, info = env.step(0)
    assert terminated
    assert not truncated
    assert info["dropped"]
    assert not info["success"]
    assert reward == pytest.approx(-env.config.step_cost - env.config.drop_penalty)
    assert (info["contact_impulses"] >= 0).all()
    assert (info["contact_impulses"][~info["contact_active"]] == 0.0).all()  # exact padding
