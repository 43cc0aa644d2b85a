"""The occluded peg-in-hole variant: the camera returns nothing (NaN) exactly inside the
occlusion zone, by hand-computed geometry, while the tactile readings still tell on which side
of the hole the peg came down; the filter takes the blind steps as no measurement."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch

from torchcontact.envs import (
    OCCLUDED_CONFIG,
    PEG_IN_HOLE_OCCLUDED_ID,
    PegInHole2D,
    PegInHole2DVector,
    PegInHoleBeliefModel,
    PegInHoleConfig,
    PegInHoleFilter,
    PegTransitions,
)
from torchcontact.experiments import PotentialShaping, run_round
from torchcontact.rl import DynaQ

#: Pressing straight down from 1 cm above the mouth, peg upright in the grasp.
_ABOVE = {"peg_height": 0.01, "gripper_angle": 0.0, "grasp_angle": 0.0, "grasp_offset": 0.04}
_DOWN = 4  # ACTION_NAMES.index("-y")


def _distance_to_mouth(config: PegInHoleConfig, peg_pose: np.ndarray) -> float:
    """Distance of the peg's bottom centre from the centre of the mouth, by hand."""
    x, y, theta = peg_pose
    half = config.peg_height / 2
    return math.hypot(x + half * math.sin(theta), y - half * math.cos(theta) - config.hole_depth)


def test_the_camera_returns_nothing_exactly_inside_the_zone() -> None:
    """Over a random-action episode from starts near and far, the camera's pose is all NaN
    when (and only when) the true peg's bottom lies within the radius; elsewhere it is the
    true pose plus noise of the camera's σ."""
    config = PegInHoleConfig(occlusion_radius=0.03)
    env = PegInHole2D(config=config, observation="noisy")
    rng = np.random.default_rng(0)
    inside = outside = 0
    for seed, x in enumerate((0.0, 0.06)):
        observation, info = env.reset(seed=seed, options={**_ABOVE, "gripper_x": x})
        for _ in range(40):
            distance = _distance_to_mouth(config, info["peg_pose"])
            pose = observation["peg_pose"]
            if distance < config.occlusion_radius - 1e-9:
                inside += 1
                assert np.isnan(pose).all()
            elif distance > config.occlusion_radius + 1e-9:
                outside += 1
                error = (pose - info["peg_pose"]) / np.asarray(config.pose_noise_std)
                assert np.isfinite(pose).all()
                assert np.abs(error).max() < 6.0  # 6σ
            action = _DOWN if rng.random() < 0.6 else int(rng.integers(7))
            observation, _, terminated, _, info = env.step(action)
            if terminated:
                break
    assert inside >= 5
    assert outside >= 5


def test_the_occlusion_changes_nothing_but_the_camera() -> None:
    """The same seeded episode with and without occlusion: equal physics, tactile readings
    and, where the peg is visible, camera poses (the noise is drawn either way)."""
    runs = []
    for radius in (0.0, 0.05):
        env = PegInHole2DVector(
            num_envs=3, config=PegInHoleConfig(occlusion_radius=radius), observation="noisy"
        )
        observation, info = env.reset(seed=7)
        steps = [(observation, info)]
        for _ in range(8):
            observation, _, _, _, info = env.step(np.full(3, _DOWN))
            steps.append((observation, info))
        runs.append(steps)
    hidden = 0
    for (open_obs, open_info), (blind_obs, blind_info) in zip(*runs, strict=True):
        np.testing.assert_allclose(blind_info["peg_pose"], open_info["peg_pose"], atol=1e-12)
        assert (blind_obs["tactile"] == open_obs["tactile"]).all()  # the same draws, 0/1
        seen = np.isfinite(blind_obs["peg_pose"]).all(-1)
        hidden += int((~seen).sum())
        np.testing.assert_allclose(blind_obs["peg_pose"][seen], open_obs["peg_pose"][seen])
        assert np.isfinite(open_obs["peg_pose"]).all()
    assert hidden > 0


@pytest.mark.parametrize("offset", [-0.015, 0.015])
def test_touch_tells_the_side_of_the_hole_while_the_camera_is_blind(offset: float) -> None:
    """Blind and pressed down 15 mm off the hole's centre, the peg's bottom corner on that
    side lands on the chamfer (the peg reaches 35 mm out, the hole 22 mm): the bottom sensor
    on that side of the peg (noise-free sensors) reads it; centred, the peg enters the hole
    and no bottom sensor fires. The readings inform the lateral offset."""
    config = PegInHoleConfig(
        occlusion_radius=0.05, tactile_false_positive=0.0, tactile_false_negative=0.0
    )
    env = PegInHole2D(config=config, observation="noisy")
    positions = env.task.sensors.positions.numpy()
    bottom = np.flatnonzero(np.isclose(positions[:, 1], -config.peg_height / 2))
    assert bottom.size == 2
    fired = {}
    for x in (offset, 0.0):
        observation, _ = env.reset(seed=0, options={**_ABOVE, "gripper_x": x})
        readings = np.zeros(positions.shape[0], dtype=bool)
        for _ in range(8):
            assert np.isnan(observation["peg_pose"]).all()  # blind all along
            observation, _, terminated, _, _ = env.step(_DOWN)
            readings |= observation["tactile"].astype(bool)
            if terminated:
                break
        fired[x] = bottom[readings[bottom]]
    assert fired[0.0].size == 0
    assert fired[offset].size == 1
    assert np.sign(positions[fired[offset][0], 0]) == np.sign(offset)


def test_the_variant_is_registered() -> None:
    env = gym.make(PEG_IN_HOLE_OCCLUDED_ID, observation="noisy")
    assert env.spec is not None
    assert env.spec.max_episode_steps == OCCLUDED_CONFIG.max_steps
    assert env.unwrapped.config.occlusion_radius == pytest.approx(0.05)
    observation, _ = env.reset(seed=0, options={**_ABOVE, "gripper_x": 0.0})
    assert np.isnan(observation["peg_pose"]).all()
    env.close()


@pytest.mark.parametrize("radius", [-0.01, math.nan, math.inf])
def test_a_bad_radius_is_named(radius: float) -> None:
    with pytest.raises(ValueError, match="occlusion_radius"):
        PegInHoleConfig(occlusion_radius=radius)


def test_the_filter_takes_blind_steps_as_no_measurement() -> None:
    """On the variant, a blind step is the Kalman prediction alone: every particle's grasp
    covariance is its ancestor's plus the process noise ``Q ⪰ floor``, so the smallest trace
    over the particles grows by at least the floor's trace (0.2 mm, 0.2 mm, 3 mrad)² per
    step; the seen entry's stays below. A partly NaN camera row is refused."""
    config = PegInHoleConfig(max_steps=25, occlusion_radius=0.05)
    env = PegInHole2DVector(num_envs=4, config=config)
    agent = DynaQ(7, epsilon=0.5, planning_steps=0, seed=1)
    rounds = [run_round(env, agent, seed=s, shaping=PotentialShaping(5.0)) for s in range(2)]
    data = PegTransitions.concat([r.transitions for r in rounds])
    model = PegInHoleBeliefModel.fit(data, agent.graph, task=env.task)
    filt = PegInHoleFilter(model, num_particles=32)
    noisy = PegInHole2DVector(num_envs=2, config=config, observation="noisy")
    # Entry 0 starts blind right above the hole; entry 1 far to the side, seen.
    observation, _ = noisy.reset(seed=3, options={**_ABOVE, "gripper_x": [0.0, 0.09]})
    assert np.isnan(observation["peg_pose"][0]).all()
    assert np.isfinite(observation["peg_pose"][1]).all()
    belief = filt.init(observation)
    generator = torch.Generator().manual_seed(0)
    floor = (2e-4) ** 2 * 2 + (3e-3) ** 2
    for _ in range(3):
        before = torch.diagonal(belief.rbpf.gaussians.cov, dim1=-2, dim2=-1).sum(-1)
        observation, *_ = noisy.step(np.array([0, 0]))  # stay
        belief = filt.step(belief, np.array([0, 0]), observation, generator=generator)
        after = torch.diagonal(belief.rbpf.gaussians.cov, dim1=-2, dim2=-1).sum(-1)
        assert float(after[0].min()) >= float(before[0].min()) + floor * (1 - 1e-9)
        assert float(after[1].max()) < float(after[0].min())  # the camera's update
    partial = dict(observation)
    partial["peg_pose"] = observation["peg_pose"].copy()
    partial["peg_pose"][1, 0] = np.nan
    with pytest.raises(ValueError, match="peg_pose finite or all-NaN"):
        filt.step(belief, np.array([0, 0]), partial)
