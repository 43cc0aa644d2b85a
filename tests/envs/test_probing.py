"""The probe-then-insert policy of the occluded variant: the belief's lateral spread against a
Monte Carlo draw of the particle mixture, the bottom sensors by their positions, and the
policy pressing exactly while blind, uncertain and untouched."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import torch

from torchcontact.envs import (
    ACTION_NAMES,
    PegBelief,
    PegInHole2DVector,
    PegInHoleBeliefModel,
    PegInHoleConfig,
    PegInHoleFilter,
    PegTransitions,
)
from torchcontact.experiments import (
    NUM_BELIEF_FEATURES,
    PotentialShaping,
    QLookup,
    belief_features,
    bottom_sides,
    bottom_touch,
    evaluate,
    lateral_spread,
    run_round,
    shift_actions,
)
from torchcontact.filters import Gaussian
from torchcontact.rl import DynaQ

#: Blind from the start: the peg 1 cm above the hole's centre, the camera out within 5 cm;
#: noise-free touch so that every reading is a contact.
BLIND = PegInHoleConfig(
    max_steps=30,
    occlusion_radius=0.05,
    start_x=(-0.01, 0.01),
    start_height=(0.01, 0.02),
    tactile_false_positive=0.0,
    tactile_false_negative=0.0,
)


@pytest.fixture(scope="module")
def fitted() -> tuple[PegInHoleBeliefModel, DynaQ]:
    env = PegInHole2DVector(num_envs=4, config=BLIND)
    agent = DynaQ(7, epsilon=0.5, planning_steps=0, seed=1)
    rounds = [run_round(env, agent, seed=s, shaping=PotentialShaping(5.0)) for s in range(2)]
    data = PegTransitions.concat([r.transitions for r in rounds])
    return PegInHoleBeliefModel.fit(data, agent.graph, task=env.task), agent


def test_lateral_spread_is_the_std_of_the_bottom_x_of_the_particle_mixture(
    fitted: tuple[PegInHoleBeliefModel, DynaQ],
) -> None:
    """Particles with random weights, grasp means and small covariances held by tilted
    grippers: the spread equals the standard deviation of ``b_x = g_x + cos g_θ u − sin g_θ w
    + h/2 sin(g_θ + φ)`` over 400,000 draws of the mixture (choose a particle by weight,
    draw its Gaussian). Monte Carlo's relative error of a std is ``1/√(2n)`` ≈ 0.1 %; the
    linearization's, with angle std ≤ 0.02 rad, is below 0.1 % too: 1.5 % tolerance."""
    model, _ = fitted
    filt = PegInHoleFilter(model, num_particles=24)
    generator = torch.Generator().manual_seed(0)
    B, N = 3, 24
    gripper = torch.tensor([[0.01, 0.2, 0.0], [-0.03, 0.18, 0.3], [0.02, 0.19, -0.4]])
    gripper = gripper.double()
    observation = {"peg_pose": gripper, "gripper_pose": gripper, "tactile": np.zeros((B, 14))}
    belief = filt.init(observation)
    mean = torch.randn(B, N, 3, generator=generator, dtype=torch.float64) * torch.tensor(
        [0.003, 0.01, 0.02], dtype=torch.float64
    )
    mean[..., 1] -= 0.04
    root = torch.randn(B, N, 3, 3, generator=generator, dtype=torch.float64)
    scale = torch.tensor([0.002, 0.004, 0.02], dtype=torch.float64)
    cov = scale[:, None] * (root @ root.transpose(-1, -2) / 3) * scale + 1e-10 * torch.eye(3)
    logits = torch.randn(B, N, generator=generator, dtype=torch.float64)
    rbpf = dataclasses.replace(
        belief.rbpf, gaussians=Gaussian(mean, cov), log_weights=torch.log_softmax(logits, -1)
    )
    belief = PegBelief(rbpf, gripper, belief.state_ids)
    spread = lateral_spread(filt, belief)

    draws = 400_000
    half = BLIND.peg_height / 2
    for b in range(B):
        pick = torch.multinomial(
            logits[b].softmax(-1), draws, replacement=True, generator=generator
        )
        noise = torch.randn(draws, 3, generator=generator, dtype=torch.float64)
        grasp = mean[b, pick] + torch.einsum(
            "nij,nj->ni", torch.linalg.cholesky(cov[b])[pick], noise
        )
        u, w, phi = grasp.unbind(-1)
        gx, _, angle = gripper[b].tolist()
        bottom_x = gx + np.cos(angle) * u - np.sin(angle) * w + half * torch.sin(angle + phi)
        assert float(spread[b]) == pytest.approx(float(bottom_x.std()), rel=0.015)


def test_bottom_touch_reads_only_the_sensors_on_the_bottom_side(
    fitted: tuple[PegInHoleBeliefModel, DynaQ],
) -> None:
    """By the sensors' positions (peg frame): the bottom side is ``y = −h/2``."""
    model, _ = fitted
    positions = model.task.sensors.positions
    bottom = torch.isclose(positions[:, 1], torch.tensor(-BLIND.peg_height / 2).double())
    S = positions.shape[0]
    readings = torch.eye(S, dtype=torch.bool)  # one sensor at a time
    assert (bottom_touch(model.task, readings) == bottom).all()  # bools: exact
    assert not bool(bottom_touch(model.task, torch.zeros(1, S, dtype=torch.bool)))


def test_the_probe_presses_while_blind_and_uncertain_until_the_bottom_touches(
    fitted: tuple[PegInHoleBeliefModel, DynaQ], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Blind from the start, a threshold of 0 (always uncertain): every episode presses
    ("-y") at each step until the first observation in which a bottom sensor fires, then
    leaves the choice to QMDP; with a threshold of 1 m it never probes and acts as QMDP,
    step for step."""
    model, agent = fitted
    lookup = QLookup(agent, model.task.states)
    env = PegInHole2DVector(num_envs=4, config=BLIND, observation="noisy")
    filt = PegInHoleFilter(model, num_particles=24)
    positions = model.task.sensors.positions.numpy()
    bottom = np.isclose(positions[:, 1], -BLIND.peg_height / 2)
    press = ACTION_NAMES.index("-y")
    step = env.step

    def run(setting: Any, threshold: float) -> list[tuple[np.ndarray, dict[str, Any]]]:
        steps: list[tuple[np.ndarray, dict[str, Any]]] = []

        def recorded(actions: np.ndarray) -> Any:
            result = step(actions)
            steps.append((np.array(actions), result[0]))
            return result

        monkeypatch.setattr(env, "step", recorded)
        evaluate(env, setting, lookup=lookup, seed=5, filt=filt, probe_threshold=threshold)
        return steps

    probed = run("probe", 0.0)
    first_observation, _ = env.reset(seed=5)
    assert np.isnan(first_observation["peg_pose"]).all()  # blind from the start
    touched = np.zeros(env.num_envs, dtype=bool)
    blind = np.ones(env.num_envs, dtype=bool)
    pressed = 0
    for actions, observation in probed:
        probing = blind & ~touched
        assert (actions[probing] == press).all()  # ints: exact
        pressed += int(probing.sum())
        touched |= probing & observation["tactile"][:, bottom].astype(bool).any(-1)
        blind = np.isnan(observation["peg_pose"]).all(-1)
    assert pressed >= env.num_envs
    assert touched.any()
    plain = run("qmdp", 0.0)
    never = run("probe", 1.0)  # 1 m: never uncertain enough
    assert len(plain) == len(never)
    for (a, _), (b, _) in zip(plain, never, strict=True):
        assert (a == b).all()  # ints: exact


def test_bad_probe_arguments_are_named(fitted: tuple[PegInHoleBeliefModel, DynaQ]) -> None:
    """A negative or NaN threshold, and a filter whose model is not the fitted one (whose
    state is the grasp), are refused before any episode runs."""
    model, agent = fitted
    lookup = QLookup(agent, model.task.states)
    env = PegInHole2DVector(num_envs=1, config=BLIND, observation="noisy")
    filt = PegInHoleFilter(model, num_particles=24)
    for threshold in (-0.001, float("nan")):
        with pytest.raises(ValueError, match="probe_threshold"):
            evaluate(env, "probe", lookup=lookup, seed=0, filt=filt, probe_threshold=threshold)
    other = SimpleNamespace(model=None)
    with pytest.raises(ValueError, match="PegInHoleBeliefModel for setting 'probe'"):
        evaluate(env, "probe", lookup=lookup, seed=0, filt=other)  # type: ignore[arg-type]


def test_bottom_sides_split_the_bottom_sensors_by_their_x(
    fitted: tuple[PegInHoleBeliefModel, DynaQ],
) -> None:
    """By the sensors' positions (peg frame): the bottom side is ``y = −h/2``, its left half
    ``x < 0``; no other sensor counts."""
    model, _ = fitted
    positions = model.task.sensors.positions
    bottom = torch.isclose(positions[:, 1], torch.tensor(-BLIND.peg_height / 2).double())
    readings = torch.eye(positions.shape[0], dtype=torch.bool)
    sides = bottom_sides(model.task, readings)
    assert (sides[:, 0] == (bottom & (positions[:, 0] < 0))).all()  # bools: exact
    assert (sides[:, 1] == (bottom & (positions[:, 0] > 0))).all()


def test_shift_actions_follow_the_rule_case_by_case() -> None:
    """Every combination of camera, touch and spread against the rule written out per case:
    blind and one corner touching: away from it; blind, nothing touching and uncertain:
    press; anything else: QMDP's action."""
    cases = []
    for blind in (False, True):
        for left in (False, True):
            for right in (False, True):
                for spread in (0.001, 0.003):
                    cases.append((blind, left, right, spread))
    qmdp = torch.full((len(cases),), ACTION_NAMES.index("+theta"))
    actions = shift_actions(
        qmdp,
        blind=torch.tensor([c[0] for c in cases]),
        spread=torch.tensor([c[3] for c in cases]),
        sides=torch.tensor([[c[1], c[2]] for c in cases]),
        threshold=0.002,
    )
    for (blind, left, right, spread), action in zip(cases, actions.tolist(), strict=True):
        if blind and right and not left:
            expected = "-x"
        elif blind and left and not right:
            expected = "+x"
        elif blind and not (left or right) and spread > 0.002:
            expected = "-y"
        else:
            expected = "+theta"
        assert ACTION_NAMES[action] == expected, (blind, left, right, spread)


def test_the_shift_probe_moves_away_from_the_corner_that_lands(
    fitted: tuple[PegInHoleBeliefModel, DynaQ], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Blind, the peg 15 mm right of the hole's centre (its right corner reaches past the
    chamfer, `tests/envs/test_occlusion.py`), threshold 0: the policy presses until the right
    bottom corner touches, then moves left ("-x") while it touches alone."""
    model, agent = fitted
    config = dataclasses.replace(
        BLIND, start_x=(0.015, 0.015), start_angle=(0.0, 0.0), grasp_angle=(0.0, 0.0)
    )
    lookup = QLookup(agent, model.task.states)
    env = PegInHole2DVector(num_envs=1, config=config, observation="noisy")
    filt = PegInHoleFilter(model, num_particles=24)
    positions = model.task.sensors.positions.numpy()
    bottom = np.isclose(positions[:, 1], -config.peg_height / 2)
    right = bottom & (positions[:, 0] > 0)
    steps: list[tuple[int, np.ndarray]] = []
    step = env.step

    def recorded(actions: np.ndarray) -> Any:
        result = step(actions)
        steps.append((int(actions[0]), result[0]["tactile"][0].astype(bool)))
        return result

    monkeypatch.setattr(env, "step", recorded)
    evaluate(env, "shift", lookup=lookup, seed=1, filt=filt, probe_threshold=0.0)
    names = [ACTION_NAMES[a] for a, _ in steps]
    touch = next(i for i, (_, reading) in enumerate(steps) if reading[bottom].any())
    assert set(names[: touch + 1]) == {"-y"}  # pressed until the first touch
    assert steps[touch][1][right].any()
    assert not steps[touch][1][bottom & ~right].any()
    assert names[touch + 1] == "-x"  # away from the right corner


def test_belief_features_end_with_the_latest_touch(
    fitted: tuple[PegInHoleBeliefModel, DynaQ],
) -> None:
    """The last three features: the camera blind (its pose all NaN), the left and the right
    half of the bottom touching, read off the sensors' positions (``y = −h/2``, sign of
    ``x``) for a reading that fires one sensor at a time."""
    model, agent = fitted
    positions = model.task.sensors.positions
    S = positions.shape[0]
    env = PegInHole2DVector(num_envs=S, config=BLIND, observation="noisy")
    observation, _ = env.reset(seed=3)
    filt = PegInHoleFilter(model, num_particles=24)
    belief = filt.init(observation)
    pose = np.array(observation["peg_pose"], dtype=np.float64)
    pose[::2] = np.nan  # every other row blind (BLIND starts blind: the others see a pose)
    pose[1::2] = 0.0
    touch = {"peg_pose": pose, "tactile": np.eye(S, dtype=np.float32)}
    lookup = QLookup(agent, model.task.states)
    features = belief_features(filt, belief, lookup, touch)
    assert features.shape == (S, lookup.table.shape[0] + NUM_BELIEF_FEATURES)
    bottom = torch.isclose(positions[:, 1], torch.tensor(-BLIND.peg_height / 2).double())
    expected = torch.stack(
        [
            torch.arange(S) % 2 == 0,
            bottom & (positions[:, 0] < 0),
            bottom & (positions[:, 0] > 0),
        ],
        -1,
    )
    assert bottom.any()
    assert ((features[:, -3:] == 1) == expected).all()  # 0 or 1 exactly
    assert ((features[:, -3:] == 0) == ~expected).all()
