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

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact.contact import Method
from torchcontact.experiments._barrett_box import (
    BOX_PAIRS,
    F64,
    BarrettBoxGrasp,
    BoxTrials,
    H,
    barrett_box_scene,
    barrett_member,
    first_tip_step,
    hand_pads,
    pad_triggers,
    pair_slots,
    pair_states,
)
from torchcontact.experiments._barrett_box_metrics import box_tracking_metrics
from torchcontact.experiments._triangle_grasp import Timing, timed
from torchcontact.filters import (
    RBPF,
    SE3,
    Gaussian,
    Proposal,
    RobotControl,
    SimulatorParticleFilter,
    SpatialContactModel,
    ekf_predict,
    ekf_update,
    project_out_of_contact,
)
from torchcontact.geometry import quat_exp, quat_mul
from torchcontact.robots import load
from torchcontact.sim import Scene, SceneState, StepResult
from torchcontact.states import TactileArray

#: Per-step process noise std of the particle filters: position (m), rotation (rad, body
#: frame), linear (m/s) and angular (rad/s) velocity.
PF_NOISE_STD = (5e-4, 5e-4, 5e-4, 5e-3, 5e-3, 5e-3, 0.01, 0.01, 0.01, 0.2, 0.2, 0.2)
#: Per-step process noise std of the RBPF's modes, in the same tangent.
RBPF_NOISE_STD = (2e-4, 2e-4, 2e-4, 2e-3, 2e-3, 2e-3, 5e-3, 5e-3, 5e-3, 0.05, 0.05, 0.05)
#: Every method of :func:`run_box_estimators`, in table order.
BOX_METHODS = ("rbpf", "rbpf_no_projection", "rbpf_servo", "pf", "pf_same_n", "ekf", "camera")
#: The RBPF methods: with the projection out of contact, without (the ablation), and with
#: the hand's fingers servoed in the filter's model (see :func:`box_filter_scene`).
RBPF_METHODS = ("rbpf", "rbpf_no_projection", "rbpf_servo")
#: Each RBPF method's offset of the filters' seed (the PFs take 4 and 5).
RBPF_SEED_OFFSET = {"rbpf": 2, "rbpf_no_projection": 3, "rbpf_servo": 6}
#: Std (rad/s) of the hand's measured joint velocities at the end of a step about a mode's
#: servoed step at the mixture mean (``rbpf_servo``): the fingers close at up to 1.5 rad/s.
JOINT_VELOCITY_SIGMA = 0.1
#: The simulator PF's exact solvers: Lemke only. On the grasp's redundant rows the QP fallback
#: took 2.7 CPU s per problem (99 % of a 2-particle run); the particles Lemke leaves
#: unsolved get weight zero.
PF_FALLBACK: tuple[Method, ...] = ("lemke",)
#: Gaps (m) of a mode's contacts that the RBPF's model takes as closed at the linearization
#: point: two camera stds, the mixture mean's typical error along a contact normal.
CONSISTENCY_GAP = 0.01
#: Log-weight penalty (nats) of a particle's child under a mode whose contacts the
#: particle's own gaps contradict: the particles spread around the mean while the hand closes,
#: and a mode resolved at the mean would carry the far ones along its contacts' lever arms.
PARTICLE_PENALTY = 5.0
#: The largest velocity change (m/s) of a point of the box that a mode's step may make: the
#: training trials' true steps change it by at most 0.22 m/s (the fingers' speeds and g h).
MAX_SPEED_CHANGE = 1.0
#: The prior's std: position (m), rotation (rad), linear and angular velocity.
PRIOR_STD = (0.005, 0.005, 0.005, 0.035, 0.035, 0.035, 0.01, 0.01, 0.01, 0.1, 0.1, 0.1)


def box_filter_scene(
    settings: BarrettBoxGrasp,
    half_extents: tuple[float, float, float] | None = None,
    *,
    servo_hand: bool = False,
) -> Scene:
    """The filters' scene: the box (nominal mass and friction; the given size, else the
    nominal one) on the table and the robot, kinematic (its measured joint motion imposed on
    the box at every contact), or with ``servo_hand`` as the ground truth's (the WAM's
    joints kinematic, the hand's servoed with the robot's own gains, limits and commands, so
    that the fingers yield to the box wherever the filter places it)."""
    return barrett_box_scene(
        settings.nominal_half_extents() if half_extents is None else half_extents,
        settings.nominal_mass(),
        settings.nominal_friction(),
        barrett_member(load("wam7_bhand"), mode="servo" if servo_hand else "kinematic"),
    )


def joint_motion(trials: BoxTrials, t: int, *, servo_hand: bool = False) -> RobotControl:
    """The robot's measured motion over step ``t``: its joint angles at the start and
    velocities over the step; with ``servo_hand`` (:func:`box_filter_scene`), the velocities
    at the start, the commands over the step and the measured velocities at its end."""
    assert trials.truth.q_robot is not None
    assert trials.truth.v_robot is not None
    if not servo_hand:
        return RobotControl(q_robot=trials.truth.q_robot[t], v_robot=trials.truth.v_robot[t + 1])
    return RobotControl(
        q_robot=trials.truth.q_robot[t],
        v_robot=trials.truth.v_robot[t],
        joint_command=trials.commands[t].expand(trials.batch, -1),
        v_robot_next=trials.truth.v_robot[t + 1],
    )


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
        read = readings[:, None]
        terms = [
            pad.reading_log_likelihood(read[..., i : i + 1], triggers[..., i : i + 1])
            for i, pad in enumerate(arrays)
        ]
        return torch.stack(terms).sum(0)

    return log_likelihood


def run_box_pf(
    trials: BoxTrials,
    settings: BarrettBoxGrasp,
    num_particles: int,
    gen: torch.Generator,
    *,
    prior: Gaussian,
    half_extents: tuple[float, float, float] | None = None,
    trial: int = 0,
) -> dict[str, Tensor]:
    """The simulator particle filter on every trial (batch ``B × N``), on
    :func:`box_filter_scene` with ``half_extents``.

    Returns:
        ``pose`` ``(T, B, 7)`` (the weighted mean, :meth:`SimulatorPFBelief.mean`),
        ``state_probs`` ``(T, B, P, 3)`` (the weighted histogram of each pair's contact
        state over the particles' simulated modes), ``cloud`` ``(T, N, 7)`` and
        ``cloud_weight`` ``(T, N)`` of trial ``trial``.
    """
    scene = box_filter_scene(settings, half_extents)
    slots = pair_slots(scene)
    pads = hand_pads(settings, scene.robots[0].robot)
    pf = SimulatorParticleFilter(
        scene,
        num_particles,
        process_std=torch.tensor(PF_NOISE_STD, dtype=F64),
        measurement_std=settings.camera_std(),
        fallback=PF_FALLBACK,
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


def box_contact_model(settings: BarrettBoxGrasp, train: BoxTrials) -> SpatialContactModel:
    """The RBPF's switching model on :func:`box_filter_scene`: the modes and transition of the
    training trials' rollouts, process noise :data:`RBPF_NOISE_STD`, the camera's noise and
    the hand's pads. Modes inconsistent at the linearization point are ruled out
    (``inconsistency_penalty=inf``): with a finite penalty, modes whose fingers drag the box
    from a distance keep enough weight to carry it away while the camera is occluded. So are
    steps faster than :data:`MAX_SPEED_CHANGE`, and each particle's modes are checked
    against its own gaps (:data:`PARTICLE_PENALTY`)."""
    scene = box_filter_scene(settings)
    return SpatialContactModel.from_rollout(
        scene,
        train.truth,
        Q=torch.diag(torch.tensor(RBPF_NOISE_STD, dtype=F64).pow(2)),
        R=torch.diag(settings.camera_std().pow(2)),
        tactile=hand_pads(settings, scene.robots[0].robot),
        inconsistency_penalty=math.inf,
        consistency_gap=CONSISTENCY_GAP,
        resolve_slots=True,
        particle_penalty=PARTICLE_PENALTY,
        max_speed_change=MAX_SPEED_CHANGE,
    )


def run_box_rbpf(
    model: SpatialContactModel,
    trials: BoxTrials,
    num_particles: int,
    gen: torch.Generator,
    *,
    prior: Gaussian,
    projection: bool,
    proposal: Proposal = "all_modes",
    gap_sigma: float = 1e-4,
    trial: int = 0,
) -> dict[str, Tensor]:
    """The contact RBPF (``proposal``: every mode of every particle, or modes drawn from the
    transition) with the pads' per-mode evidence and, with
    ``projection``, every particle's Gaussian projected out of the bodies it penetrates
    after each step (:func:`~torchcontact.filters.project_out_of_contact`).

    Returns:
        ``pose`` ``(T, B, 7)`` the mixture mean, ``state_probs`` ``(T, B, P, 3)`` each pair's
        contact-state probabilities (the mode marginals summed over the modes in each
        state), ``cloud`` ``(T, N, 7)`` and ``cloud_weight`` ``(T, N)`` of trial ``trial``.
    """
    rbpf = RBPF(model, num_particles, proposal=proposal)  # type: ignore[arg-type]
    belief = rbpf.init(prior)
    assert trials.truth.q_robot is not None
    assert trials.truth.v_robot is not None
    q_robot = trials.truth.q_robot
    mode_states = pair_states(model.modes, pair_slots(model.scene))  # (K, P)
    one_hot = torch.nn.functional.one_hot(mode_states, 3).to(F64)  # (K, P, 3)
    poses, probs, clouds, cloud_weights = [], [], [], []
    servo_hand = model.scene.num_servo_joints > 0
    for t in range(trials.steps):
        control = joint_motion(trials, t, servo_hand=servo_hand)
        extra = model.tactile_log_likelihood(
            trials.readings[t], pose=belief.mean()[..., :7], control=control
        )
        belief = rbpf.step(
            belief, trials.y[t], extra_log_likelihood=extra, control=control, generator=gen
        )
        if projection:
            # the robot where and as the step leaves it: the belief's time
            after = dataclasses.replace(
                control, q_robot=q_robot[t + 1], v_robot=trials.truth.v_robot[t + 1]
            )
            # each mode's contacts where the belief now is (its group states resolved)
            table = model.slot_modes(belief.mean(), control=after)
            belief = project_out_of_contact(
                belief, model.scene, gap_sigma=gap_sigma, control=after, mode_table=table
            )
        poses.append(belief.mean()[..., :7])
        probs.append(torch.einsum("bk,kpc->bpc", belief.mode_marginals().to(F64), one_hot))
        clouds.append(belief.gaussians.mean[trial, :, :7].clone())
        cloud_weights.append(belief.log_weights[trial].exp())
    return {
        "pose": torch.stack(poses),
        "state_probs": torch.stack(probs),
        "cloud": torch.stack(clouds),
        "cloud_weight": torch.stack(cloud_weights),
    }


@dataclass(frozen=True, eq=False)
class BoxEstimatorRuns:
    """What :func:`run_box_estimators` gives.

    Attributes:
        outputs: ``{method: output}`` (``pose`` ``(T, B, 7)``; the filters with contact
            states also ``state_probs`` ``(T, B, P, 3)``, ``cloud`` and ``cloud_weight``).
        timings: ``{method: Timing}``.
        particles: ``{method: particle count}`` of the particle filters.
        calibration: ``{particles: CPU seconds}`` of the plain PF's calibration runs (empty
            without the RBPF or with a given ``pf_particles``).
    """

    outputs: dict[str, dict[str, Tensor]]
    timings: dict[str, Timing]
    particles: dict[str, int]
    calibration: dict[int, float]


#: An estimator's run on a group of trials: ``(trials, prior, box half extents or None)``.
GroupRun = Callable[[BoxTrials, Gaussian, tuple[float, float, float] | None], dict[str, Tensor]]


def _by_group(
    trials: BoxTrials, prior: Gaussian, known_size: bool, run: GroupRun
) -> dict[str, Tensor]:
    """``run(trials, prior, half_extents)`` on each group of trials with the group's box size
    (``known_size``) or once on all of them with the nominal size (``None``); per-trial
    outputs (``pose``, ``state_probs``) concatenated in trial order, the rest (the particle
    cloud of the first trial) from the first group."""
    if not known_size:
        return run(trials, prior, None)
    parts, order = [], []
    for group in torch.unique(trials.group).tolist():
        index = (trials.group == group).nonzero().squeeze(-1)
        half = trials.half_extents[index[0]].tolist()
        parts.append(run(trials.subset(index), prior[index], (half[0], half[1], half[2])))
        order.append(index)
    inverse = torch.argsort(torch.cat(order))
    joined = {}
    for key, value in parts[0].items():
        if key in ("pose", "state_probs"):
            joined[key] = torch.cat([part[key] for part in parts], 1)[:, inverse]
        else:
            joined[key] = value
    return joined


def run_box_estimators(
    settings: BarrettBoxGrasp,
    trials: BoxTrials,
    *,
    rbpf_particles: int,
    pf_particles: int,
    model: SpatialContactModel | None = None,
    rbpf_methods: tuple[str, ...] = RBPF_METHODS,
    proposal: Proposal = "all_modes",
    known_size: bool = True,
    seed: int = 0,
    done: Callable[[str], None] | None = None,
) -> BoxEstimatorRuns:
    """Run every estimator on the trials, timed (this process's CPU time and wall clock).

    The filters assume the nominal mass and friction; with ``known_size`` they know each
    box's size (as a camera measures it before the grasp: each group of trials of one box
    runs with its scene), else they assume the nominal size too. With ``model``, the RBPF
    methods of ``rbpf_methods`` (of :data:`RBPF_METHODS`: ``rbpf`` with the projection out of
    contact, ``rbpf_no_projection`` without, ``rbpf_servo`` with the projection, the hand
    servoed in its model and the hand's measured joint velocities as evidence for the modes,
    :data:`JOINT_VELOCITY_SIGMA`) run with ``rbpf_particles`` particles (0: the
    model's number of modes ``K``), and ``pf_same_n`` with as many. ``pf`` has
    ``pf_particles`` if it is positive, else as many as fit in the first RBPF method's CPU
    time per step (a line through timed runs with 2 and 8 particles, then a run at its
    solution); without the RBPF, ``rbpf_particles``. Every filter starts from the same prior
    (:func:`box_prior`) and draws from its own generator (``seed`` plus an offset).

    Args:
        settings: the settings.
        trials: the trials.
        rbpf_particles: the RBPF's particle count (and ``pf_same_n``'s), or 0.
        pf_particles: the plain PF's, or 0 (see above).
        model: the RBPF's model (:func:`box_contact_model`), or None.
        rbpf_methods: which RBPF methods to run.
        proposal: the RBPF's proposal.
        known_size: the filters know each box's size.
        seed: the seed of the filters' draws.
        done: called with each method's name as it finishes (e.g. a progress bar).

    Raises:
        ValueError: ``rbpf_methods`` names an unknown method.
    """
    unknown = [m for m in rbpf_methods if m not in RBPF_METHODS]
    if unknown:
        raise ValueError(f"rbpf_methods: expected names among {RBPF_METHODS}, got {unknown}")

    def generator(offset: int) -> torch.Generator:
        return torch.Generator().manual_seed(seed + offset)

    def report(method: str) -> None:
        if done is not None:
            done(method)

    prior = box_prior(trials, generator(1))
    outputs: dict[str, dict[str, Tensor]] = {}
    timings: dict[str, Timing] = {}
    particles: dict[str, int] = {}
    if model is not None and rbpf_particles == 0:
        rbpf_particles = model.num_modes
    for method in rbpf_methods if model is not None else ():
        gen = generator(RBPF_SEED_OFFSET[method])

        def rbpf_group(
            part: BoxTrials,
            part_prior: Gaussian,
            half: tuple[float, float, float] | None,
            projection: bool = method != "rbpf_no_projection",
            servo_hand: bool = method == "rbpf_servo",
            gen: torch.Generator = gen,
        ) -> dict[str, Tensor]:
            assert model is not None
            scene = box_filter_scene(settings, half, servo_hand=servo_hand)
            sigma = JOINT_VELOCITY_SIGMA if servo_hand else math.inf
            return run_box_rbpf(
                dataclasses.replace(model, scene=scene, joint_velocity_sigma=sigma),
                part,
                rbpf_particles,
                gen,
                prior=part_prior,
                projection=projection,
                proposal=proposal,
            )

        def rbpf_all(run: GroupRun = rbpf_group) -> dict[str, Tensor]:
            return _by_group(trials, prior, known_size, run)

        outputs[method], timings[method] = timed(rbpf_all)
        particles[method] = rbpf_particles
        report(method)
    calibration: dict[int, float] = {}

    def pf_run(n: int, offset: int = 4) -> tuple[dict[str, Tensor], Timing]:
        gen = generator(offset)

        def pf_group(
            part: BoxTrials, part_prior: Gaussian, half: tuple[float, float, float] | None
        ) -> dict[str, Tensor]:
            return run_box_pf(part, settings, n, gen, prior=part_prior, half_extents=half)

        return timed(lambda: _by_group(trials, prior, known_size, pf_group))

    if pf_particles > 0 or not timings:
        n = pf_particles if pf_particles > 0 else rbpf_particles
        outputs["pf"], timings["pf"] = pf_run(n)
    else:
        target = next(iter(timings.values())).cpu
        runs = {n: pf_run(n) for n in (2, 8)}
        calibration = {n: run[1].cpu for n, run in runs.items()}
        slope = max((calibration[8] - calibration[2]) / 6, 1e-9)
        n = max(2, round(2 + (target - calibration[2]) / slope))
        if n not in runs:
            runs[n] = pf_run(n)
            calibration[n] = runs[n][1].cpu
        outputs["pf"], timings["pf"] = runs[n]
    particles["pf"] = n
    report("pf")
    if timings.keys() - {"pf"}:
        outputs["pf_same_n"], timings["pf_same_n"] = pf_run(rbpf_particles, offset=5)
        particles["pf_same_n"] = rbpf_particles
        report("pf_same_n")
    outputs["ekf"], timings["ekf"] = timed(lambda: run_box_ekf(trials, settings, prior))
    report("ekf")
    outputs["camera"], timings["camera"] = timed(lambda: run_box_camera(trials, prior))
    report("camera")
    return BoxEstimatorRuns(outputs, timings, particles, calibration)


def score_box_estimators(trials: BoxTrials, runs: BoxEstimatorRuns) -> dict[str, dict[str, float]]:
    """:func:`~torchcontact.experiments.box_tracking_metrics` of every method that ran, in
    :data:`BOX_METHODS` order, with its particle count (``particles``) where it has one.

    Args:
        trials: the trials the methods tracked.
        runs: what :func:`run_box_estimators` gave on them.

    Returns:
        ``{method: {metric: value}}``.
    """
    metrics = {}
    for method in (m for m in BOX_METHODS if m in runs.outputs):
        out, timing = runs.outputs[method], runs.timings[method]
        has_states = "state_probs" in out
        row = box_tracking_metrics(
            true_pose=trials.pose,
            pose=out["pose"],
            occluded=trials.occluded,
            true_tip=trials.tip_step,
            tip=first_tip_step(out["pose"]),
            true_states=trials.states if has_states else None,
            state_probs=out["state_probs"] if has_states else None,
            pair_names=BOX_PAIRS if has_states else None,
            wall=timing.wall,
            cpu=timing.cpu,
        )
        if method in runs.particles:
            row["particles"] = float(runs.particles[method])
        metrics[method] = row
    return metrics
