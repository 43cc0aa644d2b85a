"""The BarrettHand box grasp: the metrics on hand-made inputs, the ground truth's physics, the
spatial simulator particle filter, and the script with a tiny budget."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
import torch

from tests.train import assert_logged, load_script
from torchcontact.experiments import (
    BOX_PAIRS,
    TIP_ANGLE,
    BarrettBoxGrasp,
    BoxTrials,
    approach_plan,
    barrett_box_scene,
    barrett_member,
    box_tracking_metrics,
    box_trials,
    pair_states,
)
from torchcontact.filters import (
    SE3,
    Gaussian,
    KinematicControl,
    RobotControl,
    SimulatorParticleFilter,
    SimulatorPFBelief,
)
from torchcontact.geometry import quat_to_matrix
from torchcontact.robots import load
from torchcontact.sim import Simulator

F64 = torch.float64
SIGNS = torch.tensor(
    [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=F64
)


def about_z(degrees: float) -> list[float]:
    half = math.radians(degrees) / 2
    return [math.cos(half), 0.0, 0.0, math.sin(half)]


def test_metrics_of_hand_made_estimates() -> None:
    """Known answers: a constant (3, 4, 0) mm offset is 5 mm RMSE; a 10° turn about z on the
    occluded steps only is 10° RMSE there and 10° √(occluded share) overall; state accuracy
    and log-probabilities counted by hand; tip detections 2 and 10 steps late."""
    T, B = 10, 4
    true_pose = torch.tensor([0.1, 0.2, 0.05, 1.0, 0.0, 0.0, 0.0], dtype=F64).expand(T, B, 7)
    pose = true_pose.clone()
    pose[..., :3] += torch.tensor([0.003, 0.004, 0.0], dtype=F64)
    occluded = torch.zeros(T, dtype=torch.bool)
    occluded[6:] = True  # 4 of 10 steps
    pose[6:, :, 3:] = torch.tensor(about_z(10.0), dtype=F64)
    # Two pairs; the filter puts 0.7 on the true state except at pair 1 of trial 0, where it
    # puts 0.2 on it (and 0.8 on another): 1 of 8 (trial, pair) cells wrong at every step.
    true_states = torch.zeros(T, B, 2, dtype=torch.long)
    true_states[:, :, 1] = 2
    probs = torch.zeros(T, B, 2, 3, dtype=F64)
    probs[..., 0, :] = torch.tensor([0.7, 0.2, 0.1], dtype=F64)
    probs[..., 1, :] = torch.tensor([0.1, 0.2, 0.7], dtype=F64)
    probs[:, 0, 1] = torch.tensor([0.0, 0.8, 0.2], dtype=F64)
    true_tip = torch.tensor([5, -1, 10, -1])
    tip = torch.tensor([7, 3, 20, -1])
    row = box_tracking_metrics(
        true_pose=true_pose,
        pose=pose,
        occluded=occluded,
        true_tip=true_tip,
        tip=tip,
        true_states=true_states,
        state_probs=probs,
        pair_names=("a", "b"),
        wall=2.0,
        cpu=1.5,
    )
    expected = {
        "pos_rmse_mm": 5.0,
        "pos_rmse_occ_mm": 5.0,
        "rot_rmse_deg": 10.0 * math.sqrt(0.4),
        "rot_rmse_occ_deg": 10.0,
        "state_accuracy": 7 / 8,
        "state_accuracy_a": 1.0,
        "state_accuracy_b": 3 / 4,  # wrong in trial 0 of 4
        # per (step, trial): trials 1..3 have 2 log 0.7, trial 0 has log 0.7 + log 0.2
        "state_logprob": (3 * 2 * math.log(0.7) + math.log(0.7) + math.log(0.2)) / 4,
        "tip_trials": 2.0,
        "tip_within": 0.5,  # 2 steps late is within 3, 10 steps late is not
        "tip_step_error": 6.0,  # (2 + 10) / 2
        "tip_false_alarms": 0.5,  # trial 1 detected at step 3, trial 3 not at all
        "ms_per_step": 200.0,
        "cpu_ms_per_step": 150.0,
    }
    assert row.keys() == expected.keys()
    for key, value in expected.items():
        assert row[key] == pytest.approx(value, rel=1e-12, abs=1e-12), key


def test_metrics_reject_bad_shapes() -> None:
    pose = torch.zeros(3, 2, 7, dtype=F64)
    pose[..., 3] = 1.0
    occluded = torch.tensor([False, True, True])
    tips = torch.tensor([-1, -1])
    with pytest.raises(ValueError, match=r"^pose"):
        box_tracking_metrics(
            true_pose=pose, pose=pose[:, :1], occluded=occluded, true_tip=tips, tip=tips
        )
    with pytest.raises(ValueError, match=r"^occluded"):
        box_tracking_metrics(
            true_pose=pose,
            pose=pose,
            occluded=torch.zeros(3, dtype=torch.bool),
            true_tip=tips,
            tip=tips,
        )


def test_pair_states_follow_the_contact_set_definitions() -> None:
    """Separated when no slot touches, sliding when any slides (mode >= 2), else sticking."""
    slots = {name: [i] for i, name in enumerate(BOX_PAIRS)}
    slots["table"] = [0, 5]
    mode = torch.tensor([[0, 1, 3, 0, 1, 0], [1, 0, 0, 0, 0, 2], [1, 0, 0, 0, 0, 1]])
    assert pair_states(mode, slots).tolist() == [
        [0, 1, 2, 0, 1],
        [2, 0, 0, 0, 0],
        [1, 0, 0, 0, 0],
    ]


def test_settings_name_the_bad_one() -> None:
    BarrettBoxGrasp().check()
    with pytest.raises(ValueError, match=r"^steps: expected an int >= 12"):
        BarrettBoxGrasp(steps=5).check()
    with pytest.raises(ValueError, match=r"^mass\[1\]"):
        BarrettBoxGrasp(mass=(0.3, 0.1)).check()


@pytest.fixture(scope="module")
def trials() -> BoxTrials:
    """Four trials of one box (seed 2: two of them tip over)."""
    return box_trials(BarrettBoxGrasp(trials=4, trials_per_box=4, seed=2))


def corners(trials: BoxTrials) -> torch.Tensor:
    """``(T + 1, B, 8, 3)`` world corners of the true boxes (independent of the slots)."""
    rotation = quat_to_matrix(trials.truth.q[:, :, 0, 3:])
    local = SIGNS * trials.half_extents[:, None, :]  # (B, 8, 3)
    return (rotation[:, :, None] @ local[None, ..., None]).squeeze(-1) + trials.truth.q[
        :, :, 0, None, :3
    ]


def test_the_box_rests_still_without_the_hand() -> None:
    """A box out of the hand's reach (behind the robot) stays at rest on the table to 1e-9:
    static equilibrium, the weight carried by the four bottom corners."""
    robot = load("wam7_bhand")
    scene = barrett_box_scene((0.03, 0.025, 0.05), 0.3, 0.5, barrett_member(robot))
    simulator = Simulator(scene)
    initial, commands = approach_plan(robot, 40)
    q = torch.tensor([[[-0.6, 0.1, 0.05, *about_z(20.0)]]], dtype=F64)
    state = simulator.initial_state(q=q, q_robot=initial[None].clone())
    run = simulator.rollout(state, steps=40, joint_commands=commands[:, None])
    torch.testing.assert_close(run.q[:, 0, 0], q[0, 0].expand(41, 7), rtol=0, atol=1e-9)
    assert float(run.v.abs().max()) < 1e-9
    # the weight m g, over one step's impulses of the 8 table slots
    assert float(run.pn[-1, 0, :8].sum()) == pytest.approx(0.3 * 9.81 * scene.h, rel=1e-6)


def test_nothing_sinks_and_only_tipping_boxes_leave_the_table(trials: BoxTrials) -> None:
    """No corner ever sinks below the table (1 μm); a box that does not tip keeps a corner
    within 2 mm of the table (the closing hand lifts nothing), a tipping one rises."""
    low = corners(trials)[..., 2].min(-1).values  # (T + 1, B)
    assert float(low.min()) > -1e-6
    tipped = trials.tip_step >= 0
    assert 0 < int(tipped.sum()) < trials.batch
    assert float(low[:, ~tipped].max()) < 2e-3


def test_tipping_is_a_rotation_about_a_bottom_edge(trials: BoxTrials) -> None:
    """At the tip-over step, two corners that share a bottom edge stay on the table and the
    other corners are raised; the box's tilting rotation (the horizontal part of its angular
    velocity) is about that edge."""
    world = corners(trials)
    for b in (trials.tip_step >= 0).nonzero().squeeze(-1).tolist():
        t = int(trials.tip_step[b]) + 1
        z = world[t, b, :, 2]
        low = z.argsort()[:2]
        assert float(z[low].max()) < 5e-4
        assert float(z.sort().values[2]) > 3e-3
        differ = (SIGNS[low[0]] != SIGNS[low[1]]).sum()
        assert int(differ) == 1  # the two corners share an edge
        edge = world[t, b, low[0]] - world[t, b, low[1]]
        omega = trials.truth.v[t, b, 0, 3:]
        horizontal = torch.cat([omega[:2], omega.new_zeros(1)])
        sine = torch.linalg.cross(horizontal, edge).norm() / (horizontal.norm() * edge.norm())
        assert float(sine) < 0.05
        assert float(horizontal.norm()) > 0.1  # it is turning
    assert pytest.approx(math.radians(5.0)) == TIP_ANGLE


def test_measurements_are_noisy_truth_hidden_while_occluded(trials: BoxTrials) -> None:
    seen = ~trials.occluded
    assert bool(torch.isnan(trials.y[trials.occluded]).all())
    error = (trials.y[seen, :, :3] - trials.pose[seen, :, :3]).reshape(-1)
    # 3 × 20 seen steps × 4 trials = 240 draws of N(0, 5 mm): the sample std within 20 %
    assert float(error.std()) == pytest.approx(0.005, rel=0.2)
    assert trials.readings.shape == trials.triggers.shape == (trials.steps, trials.batch, 7)
    assert bool(trials.triggers.any())  # the fingers touch


def test_spatial_particle_filter_without_contact_weights_by_the_camera() -> None:
    """A box high above the table and far from the robot falls freely; the PF's particles
    follow ballistic motion (semi-implicit Euler: v⁺ = v + g h, p⁺ = p + h v⁺; the particles
    start at rest up to 1e-8, so their orientation stays put to 1e-9) and their
    weights are the camera's Gaussian likelihood of each particle (compared with the density
    written out)."""
    robot = load("wam7_bhand")
    scene = barrett_box_scene(
        (0.03, 0.025, 0.05), 0.3, 0.5, barrett_member(robot, mode="kinematic")
    )
    std = torch.tensor([0.01] * 3 + [0.05] * 3, dtype=F64)
    pf = SimulatorParticleFilter(
        scene, 5, process_std=torch.zeros(12, dtype=F64), measurement_std=std
    )
    mean = torch.tensor([[-0.6, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, *[0.0] * 6]], dtype=F64)
    variance = torch.tensor([1e-4] * 6 + [1e-16] * 6, dtype=F64)
    prior = Gaussian(mean, torch.diag(variance)[None])
    gen = torch.Generator().manual_seed(0)
    belief = pf.init(prior, generator=gen)
    y = torch.tensor([[-0.6, 0.0, 0.999, 1.0, 0.0, 0.0, 0.0]], dtype=F64)
    initial, _ = approach_plan(robot, 20)
    control = RobotControl(q_robot=initial[None].clone(), v_robot=torch.zeros(1, 11, dtype=F64))
    after = pf.step(belief, y, control=control, generator=gen)
    h = scene.h
    expected = belief.particles.clone()
    expected[..., 9] -= 9.81 * h
    expected[..., :3] += h * expected[..., 7:10]
    torch.testing.assert_close(after.particles, expected, rtol=0, atol=1e-9)
    # log N(y; x, σ²) up to a constant: position and body-frame rotation-vector residuals
    residual = SE3.local(after.particles[0, :, :7], y.expand(5, 7))
    log_w = -0.5 * (residual / std).pow(2).sum(-1)
    torch.testing.assert_close(
        after.log_weights[0], torch.log_softmax(log_w, -1), rtol=0, atol=1e-12
    )


def test_the_script_runs_with_a_tiny_budget(tmp_path: Path) -> None:
    """``run(args)`` with the tiny budget writes the table, the records, the figures and the
    logs (arguments and throughput)."""
    script = load_script("barrett_box_grasp")
    args = script.Args(fast=True, out_dir=str(tmp_path), name="tiny")
    result = script.run(args)
    run_dir = Path(result["run_dir"])
    assert_logged(
        run_dir, [f.name for f in dataclasses.fields(args)], {"name": "tiny", "fast": True}
    )
    records = json.loads((run_dir / "results.json").read_text())["methods"]
    methods = ["rbpf", "rbpf_no_projection", "rbpf_servo", "pf", "pf_same_n", "ekf", "camera"]
    assert [r["method"] for r in records] == methods
    for name in ("results.md", "results.json", "errors.png", "snapshots.png", "states.png"):
        assert (run_dir / name).is_file(), name
    assert list(result["metrics"]) == methods
    for method in methods:  # a box at rest under a 5 mm camera, two steps of occlusion
        assert result["metrics"][method]["pos_rmse_mm"] < 50.0, method
    text = (run_dir / "results.md").read_text()
    assert "| rbpf | 1 |" in text  # one mode from the tiny training rollout: N = K = 1


def test_spatial_particle_mean_treats_q_and_minus_q_as_one_rotation() -> None:
    """Two particles holding the same rotation as q and −q, and a third turned 20° about z
    with half the weight of each: the mean rotation is the chordal mean, 4° about z here
    (weights 0.4, 0.4, 0.2 of the unit quaternions at 0° and 20°, normalized), not a
    cancelled sum."""
    q = torch.tensor(about_z(0.0), dtype=F64)
    turned = torch.tensor(about_z(20.0), dtype=F64)
    rows = [
        torch.cat([torch.zeros(3, dtype=F64), r, torch.zeros(6, dtype=F64)])
        for r in (q, -q, turned)
    ]
    weights = torch.tensor([0.4, 0.4, 0.2], dtype=F64)
    belief = SimulatorPFBelief(
        particles=torch.stack(rows)[None],
        modes=torch.zeros(1, 3, 4, dtype=torch.long),
        log_weights=weights.log()[None],
        log_evidence=torch.zeros(1, dtype=F64),
        stepped=True,
    )
    mean = belief.mean()[0, 3:7]
    chordal = 0.8 * q + 0.2 * turned
    expected = chordal / chordal.norm()
    torch.testing.assert_close(mean * torch.sign(mean[0]), expected, rtol=0, atol=1e-12)
    # the chordal mean's angle, from its half-angle components
    angle = 2 * math.degrees(math.atan2(float(expected[3]), float(expected[0])))
    assert angle == pytest.approx(
        2
        * math.degrees(
            math.atan2(0.2 * math.sin(math.radians(10)), 0.8 + 0.2 * math.cos(math.radians(10)))
        )
    )


def test_spatial_particle_filter_rejects_a_planar_control() -> None:
    robot = load("wam7_bhand")
    scene = barrett_box_scene(
        (0.03, 0.025, 0.05), 0.3, 0.5, barrett_member(robot, mode="kinematic")
    )
    with pytest.raises(ValueError, match=r"^process_std"):
        SimulatorParticleFilter(
            scene,
            2,
            process_std=torch.zeros(6, dtype=F64),
            measurement_std=torch.ones(6, dtype=F64),
        )
    pf = SimulatorParticleFilter(
        scene, 2, process_std=torch.zeros(12, dtype=F64), measurement_std=torch.ones(6, dtype=F64)
    )
    mean = torch.tensor([[-0.6, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0, *[0.0] * 6]], dtype=F64)
    belief = pf.init(Gaussian(mean, 1e-4 * torch.eye(12, dtype=F64)[None]))
    y = torch.full((1, 7), math.nan, dtype=F64)
    control = KinematicControl(q=torch.zeros(1, 0, 3, dtype=F64), v=torch.zeros(1, 0, 3, dtype=F64))
    with pytest.raises(ValueError, match=r"^control: expected a RobotControl"):
        pf.step(belief, y, control=control)
    with pytest.raises(ValueError, match=r"^y"):
        pf.step(belief, y[:, :3], control=control)
