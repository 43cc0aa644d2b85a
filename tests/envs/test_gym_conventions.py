"""Gymnasium's conventions as a new user meets them: vectorizers, time limits, rendering.

``gymnasium.make_vec`` in the ``"sync"`` and ``"async"`` modes stacks the single
environments' infos (they must have fixed shapes); ``gymnasium.make(..., max_episode_steps=n)``
truncates at ``n`` through ``TimeLimit``; rendering writes nothing to the terminal.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import replace
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from torchcontact.envs import (
    PEG_IN_HOLE_ID,
    PegInHole2D,
    PegInHole2DVector,
    PegInHoleConfig,
    observation_bounds,
)
from torchcontact.sim import SceneState, Simulator, StepResult

STAY, RIGHT, LEFT, UP, DOWN, TURN_LEFT, TURN_RIGHT = range(7)
#: Actions of the vectorizer tests, one row per step (the peg stays in the grasp).
ACTIONS = np.array([[DOWN, UP, RIGHT, STAY], [DOWN, LEFT, TURN_LEFT, UP], [STAY, DOWN, DOWN, LEFT]])


def single_runs(num_envs: int, seed: int, steps: int) -> list[list[dict[str, Any]]]:
    """Each sub-environment alone: ``gym.make``, reset with ``seed + i``, the same actions."""
    runs = []
    for i in range(num_envs):
        env = gym.make(PEG_IN_HOLE_ID)
        infos = [env.reset(seed=seed + i)[1]]
        for t in range(steps):
            infos.append(env.step(int(ACTIONS[t, i]))[4])
        runs.append(infos)
    return runs


def assert_stacked(infos: dict[str, Any], singles: list[dict[str, Any]]) -> None:
    """``infos`` holds each single environment's info in its row, every ``_key`` mask set."""
    assert set(infos) == set(singles[0]) | {f"_{key}" for key in singles[0]}
    for key, first in singles[0].items():
        assert infos[f"_{key}"].all(), key
        for i, single in enumerate(singles):
            if isinstance(first, np.ndarray) and first.dtype.kind == "f":
                # Same code and inputs; the tolerance allows for another thread count in a
                # worker process.
                np.testing.assert_allclose(infos[key][i], single[key], rtol=0, atol=1e-9)
            elif isinstance(first, np.ndarray):  # bools, ints, body names: exact
                assert (infos[key][i] == single[key]).all(), key
            else:  # ints, bools, hashable manipulation and contact states
                assert infos[key][i] == single[key], key


def assert_pads_press_with_the_grip_force(infos: dict[str, Any], config: PegInHoleConfig) -> None:
    """Each finger at rest presses the peg with ``grip_force`` (its servo acts on the jaws' mean,
    so the grip alone pushes it onto the peg): ``|Σ pn n| / h ≈ grip_force`` over its slots.

    3 % tolerance: after ``settle_steps`` the servo transient has not quite died out.
    """
    for i in range(len(infos["contact_active"])):
        for finger in ("finger_left", "finger_right"):
            mask = infos["contact_active"][i] & (infos["contact_partners"][i] == finger)
            assert mask.any()
            impulse = infos["contact_impulses"][i][mask, None] * infos["contact_normals"][i][mask]
            force = float(np.linalg.norm(impulse.sum(0))) / config.h
            assert force == pytest.approx(config.grip_force, rel=0.03), (i, finger)


def test_sync_vectorization_stacks_the_infos() -> None:
    """The issue's crash: ``make_vec(..., "sync")`` broadcast contact arrays of different
    lengths into one array at ``reset``. Slots padded to the scene's count stack."""
    B, seed = 4, 0
    env = gym.make_vec(PEG_IN_HOLE_ID, num_envs=B, vectorization_mode="sync")
    singles = single_runs(B, seed, len(ACTIONS))
    observations, infos = env.reset(seed=seed)
    assert env.observation_space.contains(observations)
    K = singles[0][0]["contact_active"].shape[0]
    assert infos["contact_points"].shape == (B, K, 2)
    assert infos["contact_partners"].shape == (B, K)
    assert_stacked(infos, [run[0] for run in singles])
    assert_pads_press_with_the_grip_force(infos, PegInHoleConfig())
    for t, actions in enumerate(ACTIONS):
        observations, _, terminated, truncated, infos = env.step(actions)
        assert env.observation_space.contains(observations)
        assert not terminated.any()
        assert not truncated.any()
        assert_stacked(infos, [run[t + 1] for run in singles])
    env.close()


def test_async_vectorization_stacks_the_infos() -> None:
    """Worker processes send the infos through pipes (pickled) and the parent stacks them."""
    B, seed, steps = 2, 5, 2
    env = gym.make_vec(PEG_IN_HOLE_ID, num_envs=B, vectorization_mode="async")
    try:
        singles = single_runs(B, seed, steps)
        _, infos = env.reset(seed=seed)
        assert_stacked(infos, [run[0] for run in singles])
        for t in range(steps):
            observations, _, _, _, infos = env.step(ACTIONS[t, :B])
            assert env.observation_space.contains(observations)
            assert_stacked(infos, [run[t + 1] for run in singles])
    finally:
        env.close()


def test_the_spec_sets_the_time_limit_and_make_overrides_it() -> None:
    default = gym.make(PEG_IN_HOLE_ID)
    assert default.spec is not None
    assert default.spec.max_episode_steps == PegInHoleConfig().max_steps == 200
    longer = gym.make(PEG_IN_HOLE_ID, max_episode_steps=300)
    assert longer.spec is not None
    assert longer.spec.max_episode_steps == 300
    vector = gym.make_vec(PEG_IN_HOLE_ID, num_envs=2, vectorization_mode="vector_entry_point")
    assert isinstance(vector.unwrapped, PegInHole2DVector)
    assert vector.unwrapped.max_episode_steps == 200
    vector = gym.make_vec(PEG_IN_HOLE_ID, num_envs=2, max_episode_steps=300)
    assert isinstance(vector.unwrapped, PegInHole2DVector)
    assert vector.unwrapped.max_episode_steps == 300


def test_an_episode_truncates_at_the_requested_limit_not_the_configs() -> None:
    """``config.max_steps`` (5) no longer cuts an episode that ``make`` allows 9 steps."""
    config = PegInHoleConfig(max_steps=5)
    env = gym.make(PEG_IN_HOLE_ID, config=config, max_episode_steps=9)
    env.reset(seed=0)
    for step in range(1, 10):
        _, reward, terminated, truncated, _ = env.step(STAY)
        assert not terminated
        assert truncated == (step == 9)
        assert reward == pytest.approx(-config.step_cost)
    vector = gym.make_vec(PEG_IN_HOLE_ID, num_envs=2, config=config, max_episode_steps=7)
    vector.reset(seed=0)
    for step in range(1, 8):
        _, _, terminated, truncated, _ = vector.step(np.zeros(2, dtype=np.int64))
        assert not terminated.any()
        assert (truncated == (step == 7)).all()


def test_observation_bounds_follow_the_geometry() -> None:
    """Hand-computed from the default config: gripper hull, grasp reach r, step time τ."""
    bounds = observation_bounds(PegInHoleConfig())
    r = np.hypot(0.16 / 2, 0.04 / 2 + 0.02)  # half the peg's length; half its width + finger
    tau = 2 * 0.01
    # Workspace x ±0.2 (holds start_x), angle ±0.5 (holds start_angle); y: the workspace's
    # low 0.05 and the highest start, mouth 0.06 + height 0.05 + offset 0.05 + half peg 0.08.
    gripper = (np.array([-0.2, 0.05, -0.5]), np.array([0.2, 0.4, 0.5]))
    np.testing.assert_allclose(bounds["gripper_pose"][0], gripper[0], rtol=0, atol=1e-15)
    np.testing.assert_allclose(bounds["gripper_pose"][1], gripper[1], rtol=0, atol=1e-15)
    widen = np.array([2 * r, 2 * r, np.pi / 2])
    np.testing.assert_allclose(bounds["peg_pose"][0], gripper[0] - widen, rtol=1e-15)
    np.testing.assert_allclose(bounds["peg_pose"][1], gripper[1] + widen, rtol=1e-15)
    speed = 2 * r / tau + np.sqrt(2) * 0.002 / tau
    spin = np.pi / 2 / tau + 0.02 / tau
    np.testing.assert_allclose(bounds["peg_twist"][1], [speed, speed, spin], rtol=1e-15)
    np.testing.assert_allclose(bounds["peg_twist"][0], [-speed, -speed, -spin], rtol=1e-15)
    # Starts beyond the workspace widen the gripper's hull: the highest start has the upright
    # peg at its longest offset; the lowest one its shortest offset at the largest tilt.
    config = PegInHoleConfig(start_height=(0.001, 0.3), workspace_y=(0.2, 0.3))
    hull = observation_bounds(config)["gripper_pose"]
    assert hull[1][1] == pytest.approx(0.06 + 0.3 + 0.05 + 0.08, abs=1e-15)
    assert hull[0][1] == pytest.approx(0.06 + 0.001 + (0.03 + 0.08) * np.cos(0.15), abs=1e-15)


def test_observations_are_clipped_to_the_bounds_info_keeps_the_truth(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A peg flung 10 m away in the step that drops it: the observation sits on the bound."""
    env = PegInHole2D()
    env.reset(seed=0)
    low, high = observation_bounds(env.config)["peg_pose"]
    solve = Simulator.step

    def flinging(self: Simulator, state: SceneState, **kwargs: Any) -> StepResult:
        result = solve(self, state, **kwargs)
        q = result.state.q.clone()
        q[:, 0, 0] += 10.0  # the peg is dynamic body 0
        return replace(result, state=replace(result.state, q=q))

    monkeypatch.setattr(Simulator, "step", flinging)
    observation, _, terminated, _, info = env.step(STAY)
    assert info["dropped"]
    assert terminated
    assert info["peg_pose"][0] > 10.0
    assert observation[0] == pytest.approx(high[0], abs=1e-12)
    assert env.observation_space.contains(observation)
    assert low[0] < 0 < high[0] < 10.0


def test_rendering_prints_nothing_and_keeps_metres_square(
    capfd: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    """No matplotlib message (it used to log one per frame: both limits fixed with an equal
    aspect made by moving them); one metre spans as many pixels along x as along y."""
    env = gym.make(PEG_IN_HOLE_ID, render_mode="rgb_array")
    options = {"gripper_angle": 0.0, "grasp_angle": 0.0}
    env.reset(seed=2, options=options)
    capfd.readouterr()
    with caplog.at_level(logging.DEBUG, logger="matplotlib"), warnings.catch_warnings():
        warnings.simplefilter("error")
        frame = env.render()
    out, err = capfd.readouterr()
    assert (out, err) == ("", "")
    assert not [r for r in caplog.records if r.levelno >= logging.INFO]
    assert isinstance(frame, np.ndarray)
    assert frame.shape == (360, 480, 3)
    # The peg, upright: the runs of its blue (tab:blue) pixels, down and across through a
    # point inside it, span its length and its width.
    unwrapped = env.unwrapped
    assert isinstance(unwrapped, PegInHole2D)
    c = unwrapped.config
    x, y, _ = unwrapped.physics.state.q[0, 0].tolist()
    x += c.peg_width / 3  # off the axis, where the gripper's red cross lies
    top = max(c.workspace_y[1], float(unwrapped.physics.gripper[0, 1]) + c.finger_height)
    span_y = top + 0.02  # the view holds y from -0.02 to top; x is widened to 4:3
    scale = 360 / span_y  # pixels per metre
    x_min = -(480 / scale) / 2
    column, row = round((x - x_min) * scale), round((top - y) * scale)
    blue = np.abs(frame.astype(int) - [31, 119, 180]).sum(-1) <= 6
    assert blue[row, column]
    across = _run(blue[row], column)
    down = _run(blue[:, column], row)
    # Each run loses the same inner half of the outline and its antialiased pixels at both
    # ends (≈ 3 pixels), so their difference is the peg's length minus its width.
    assert c.peg_width * scale - 5 <= across <= c.peg_width * scale
    assert down - across == pytest.approx((c.peg_height - c.peg_width) * scale, abs=2)


def _run(line: np.ndarray, index: int) -> int:
    """Length of the run of ``True`` in ``line`` through ``index``."""
    left = index
    while left > 0 and line[left - 1]:
        left -= 1
    right = index
    while right + 1 < len(line) and line[right + 1]:
        right += 1
    return right - left + 1


def test_the_vector_environment_renders_one_frame_per_sub_environment() -> None:
    """``render_mode`` used to raise a TypeError in the vector environment."""
    vector = gym.make_vec(PEG_IN_HOLE_ID, num_envs=2, render_mode="rgb_array")
    assert isinstance(vector.unwrapped, PegInHole2DVector)
    assert vector.render_mode == "rgb_array"
    vector.reset(seed=3)
    frames = vector.render()
    assert frames is not None
    assert len(frames) == 2
    for i, frame in enumerate(frames):
        single = PegInHole2D(render_mode="rgb_array")
        single.reset(seed=3 + i)
        expected = single.render()
        assert expected is not None
        assert (frame == expected).all()  # uint8 pixels of the same drawing
    assert not (frames[0] == frames[1]).all()
    assert PegInHole2DVector(num_envs=2).render() is None
    with pytest.raises(ValueError, match="render_mode"):
        PegInHole2DVector(num_envs=2, render_mode="human")
    with pytest.raises(ValueError, match="max_episode_steps"):
        PegInHole2DVector(num_envs=2, max_episode_steps=0)
