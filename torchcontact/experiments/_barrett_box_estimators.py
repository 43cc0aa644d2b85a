"""Estimators of the BarrettHand box grasp: the simulator particle filter, an EKF without
contact, the last camera pose held (and the contact RBPF where its model is available).

Every estimator tracks all trials of :class:`~torchcontact.experiments.BoxTrials` in one
batch. The filters assume the nominal box (the middle of each drawn range: size, mass,
friction) and see the robot as kinematic: its measured joint angles (at the start of each
step) and velocities (over the step) are the known control.

1. ``pf`` / ``pf_same_n``: :class:`~torchcontact.filters.SimulatorParticleFilter` on the
   spatial scene, every particle stepped by the simulator, process noise in the tangent,
   weighted by the camera and the tactile pads (the pads' triggers of each particle's
   simulated contacts, :func:`~torchcontact.experiments.pad_triggers`);
2. ``ekf``: constant-velocity EKF on :data:`~torchcontact.filters.SE3` (no gravity, no
   contact), camera updates only;
3. ``camera``: the last camera pose, held while occluded.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact.filters import (
    SE3,
    Gaussian,
    SimulatorParticleFilter,
    ekf_predict,
    ekf_update,
)
from torchcontact.geometry import quat_exp, quat_mul
from torchcontact.robots import load
from torchcontact.sim import Scene, SceneState, StepResult
from torchcontact.states import TactileArray

from torchcontact.experiments._barrett_box import (
    F64,
    H,
    BarrettBoxGrasp,
    BoxTrials,
    barrett_member,
    box_scene,
    hand_pads,
    pad_triggers,
    pair_slots,
    pair_states,
)

#: Per-step process noise std of the particle filters: position (m), rotation (rad, body
#: frame), linear (m/s) and angular (rad/s) velocity.
PF_NOISE_STD = (5e-4, 5e-4, 5e-4, 5e-3, 5e-3, 5e-3, 0.01, 0.01, 0.01, 0.2, 0.2, 0.2)
#: The prior's std: position (m), rotation (rad), linear and angular velocity.
PRIOR_STD = (0.005, 0.005, 0.005, 0.035, 0.035, 0.035, 0.01, 0.01, 0.01, 0.1, 0.1, 0.1)


@dataclass(frozen=True, eq=False)
class JointMotion:
    """The robot's measured motion over one step (a
    :class:`~torchcontact.filters.RobotMotion`): joint angles ``q_robot`` ``(B, Nj)`` at the
    start, velocities ``v_robot`` ``(B, Nj)`` over the step; the base stays at the origin."""

    q_robot: Tensor
    v_robot: Tensor
    robot_base: Tensor | None = None
    base_twist: Tensor | None = None


def filter_scene(settings: BarrettBoxGrasp) -> Scene:
    """The filters' scene: the nominal box on the table and the kinematic robot."""
    return box_scene(
        settings.nominal_half_extents(),
        settings.nominal_mass(),
        settings.nominal_friction(),
        barrett_member(load("wam7_bhand"), mode="kinematic"),
    )


def joint_motion(trials: BoxTrials, t: int) -> JointMotion:
    """The measured robot motion of step ``t`` (angles at its start, velocities over it)."""
    assert trials.truth.q_robot is not None
    assert trials.truth.v_robot is not None
    return JointMotion(trials.truth.q_robot[t], trials.truth.v_robot[t + 1])


def box_prior(trials: BoxTrials, gen: torch.Generator) -> Gaussian:
    """The filters' initial belief: the true initial pose perturbed by :data:`PRIOR_STD`
    (as a first camera look would), at rest; tangent covariance ``diag(PRIOR_STD²)``."""
    std = torch.tensor(PRIOR_STD, dtype=F64)
    start = torch.cat([trials.truth.q[0, :, 0], torch.zeros(trials.batch, 6, dtype=F64)], -1)
    delta = std * torch.randn(trials.batch, 12, generator=gen, dtype=F64)
    delta[:, 6:] = 0.0
    mean = SE3.retract(start, delta)
    return Gaussian(mean, torch.diag(std.pow(2)).expand(trials.batch, 12, 12).contiguous())


def _tactile_term(
    scene: Scene, pads: dict[str, TactileArray], readings: Tensor
) -> Callable[[SceneState, StepResult], Tensor]:
    """The PF's ``extra_log_likelihood``: ``log p(readings)`` ``(B, N)`` of the ``(B, S)``
    pad readings given each particle's simulated contacts."""
    arrays = list(pads.values())

    def log_likelihood(state: SceneState, result: StepResult) -> Tensor:
        assert state.q_robot is not None
        assert state.robot_base is not None
        triggers = pad_triggers(
            scene,
            pads,
            q_robot=state.q_robot,
            robot_base=state.robot_base,
            points=result.geometry.points,
            normals=result.geometry.normals,
            pn=result.pn,
            mode=result.mode,
            active=result.geometry.active,
        )
        on = torch.cat(
            [pad.reading_probability(triggers[..., i : i + 1]) for i, pad in enumerate(arrays)],
            -1,
        )
        return torch.where(readings[:, None], torch.log(on), torch.log1p(-on)).sum(-1)

    return log_likelihood


def run_box_pf(
    trials: BoxTrials,
    settings: BarrettBoxGrasp,
    num_particles: int,
    gen: torch.Generator,
    *,
    prior: Gaussian,
    trial: int = 0,
) -> dict[str, Tensor]:
    """The simulator particle filter on every trial (batch ``B × N``).

    Returns:
        ``pose`` ``(T, B, 7)`` (the weighted mean, :meth:`SimulatorPFBelief.mean`),
        ``state_probs`` ``(T, B, P, 3)`` (the weighted histogram of each pair's contact
        state over the particles' simulated modes), ``cloud`` ``(T, N, 7)`` and
        ``cloud_weight`` ``(T, N)`` of trial ``trial``.
    """
    scene = filter_scene(settings)
    slots = pair_slots(scene)
    pads = hand_pads(settings, scene.robots[0].robot)
    pf = SimulatorParticleFilter(
        scene,
        num_particles,
        process_std=torch.tensor(PF_NOISE_STD, dtype=F64),
        measurement_std=settings.camera_std(),
    )
    belief = pf.init(prior, generator=gen)
    poses, probs, clouds, cloud_weights = [], [], [], []
    for t in range(trials.steps):
        belief = pf.step(
            belief,
            trials.y[t],
            control=joint_motion(trials, t),
            extra_log_likelihood=_tactile_term(scene, pads, trials.readings[t]),
            generator=gen,
        )
        weights = belief.weights()
        poses.append(belief.mean()[..., :7])
        states = pair_states(belief.modes, slots)  # (B, N, P)
        one_hot = torch.nn.functional.one_hot(states, 3).to(F64)
        probs.append((weights[..., None, None] * one_hot).sum(-3))
        clouds.append(belief.particles[trial, :, :7].clone())
        cloud_weights.append(weights[trial].clone())
    return {
        "pose": torch.stack(poses),
        "state_probs": torch.stack(probs),
        "cloud": torch.stack(clouds),
        "cloud_weight": torch.stack(cloud_weights),
    }


def run_box_ekf(trials: BoxTrials, settings: BarrettBoxGrasp, prior: Gaussian) -> dict[str, Tensor]:
    """Constant-velocity EKF on SE(3) without gravity or contact; camera updates only."""

    def f(x: Tensor) -> Tensor:
        turned = quat_mul(quat_exp(H * x[10:13]), x[3:7])
        return torch.cat([x[:3] + H * x[7:10], turned, x[7:]])

    def measure(x: Tensor) -> Tensor:
        return x[:7]

    std = torch.tensor(PF_NOISE_STD, dtype=F64)
    Q = torch.diag(std.pow(2))
    R = torch.diag(settings.camera_std().pow(2))
    g = prior
    poses = []
    for t in range(trials.steps):
        g = ekf_predict(g, f, Q=Q, manifold=SE3)
        g, _ = ekf_update(g, trials.y[t], measure, R=R, manifold=SE3, measurement_manifold=SE3)
        poses.append(g.mean[..., :7])
    return {"pose": torch.stack(poses)}


def run_box_camera(trials: BoxTrials, prior: Gaussian) -> dict[str, Tensor]:
    """The last camera pose (the prior mean before the first)."""
    last = prior.mean[..., :7]
    poses = []
    for t in range(trials.steps):
        seen = torch.isfinite(trials.y[t]).all(-1, keepdim=True)
        last = torch.where(seen, trials.y[t], last)
        poses.append(last)
    return {"pose": torch.stack(poses)}

