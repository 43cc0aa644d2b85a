"""The triangle-grasp trials as run logs (:mod:`torchcontact.logs`), and the estimators
replayed over logs.

:func:`grasp_run_logs` turns each simulated trial into a :class:`~torchcontact.logs.RunLog`
(the finger poses and twists as the robot's coordinates ``left.x, left.y, left.theta,
right.x, …``, vision, tactile readings, the filters' prior, and the simulator's ground truth
with the trial's friction; the experiment's settings in ``source``), and
:func:`write_grasp_logs` writes them. :func:`grasp_trials_from_logs` rebuilds the
:class:`GraspTrials` from logs (the mode table from the settings' training rollouts), and
:func:`replay` runs one estimator of :data:`GRASP_METHODS` over them as the experiment does:
same code, same seeds, same scores (:func:`evaluate_tracking`).
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchcontact._checks import check_choice, check_int
from torchcontact.experiments._triangle_grasp import (
    F64,
    FILTER_SEED_OFFSETS,
    GRASP_METHODS,
    GraspTrials,
    H,
    Timing,
    TriangleGrasp,
    evaluate_tracking,
    grasp_contact_model,
    grasp_mode_table,
    run_ekf,
    run_pf,
    run_rbpf,
    run_vision,
    timed,
    triangle_scene,
    triangle_tactile_array,
)
from torchcontact.filters import Gaussian
from torchcontact.logs import ContactTruth, RunLog, read_run, write_run
from torchcontact.sim import Rollout
from torchcontact.states import mode_ids

_EXPERIMENT = "triangle_grasp"  # the ``source["experiment"]`` of the grasp's logs
_BODY = "triangle"
#: The robot coordinates of the grasp's logs: the fingers' ``(x, y, θ)``.
FINGER_JOINTS = tuple(f"{finger}.{c}" for finger in ("left", "right") for c in ("x", "y", "theta"))


def _settings_dict(settings: TriangleGrasp) -> dict[str, Any]:
    return {f.name: getattr(settings, f.name) for f in dataclasses.fields(TriangleGrasp)}


def grasp_run_logs(settings: TriangleGrasp, trials: GraspTrials) -> list[RunLog]:
    """One run log per trial of :func:`grasp_trials`.

    The instants are ``k h`` (``h`` = 0.01 s, in integer nanoseconds); the vision
    measurement after step ``k`` (``trials.y[k]``) sits at instant ``k + 1``, none at instant
    0 nor while occluded; the tactile readings and the true contact slots of step ``k`` at
    instant ``k``. ``source`` holds ``{"experiment": "triangle_grasp", "trial": b,
    "settings": {…}}`` (the fields of :class:`TriangleGrasp`).

    Args:
        settings: the settings the trials were simulated with.
        trials: the trials.

    Returns:
        ``B`` logs named ``triangle_grasp__<seed>__trial<b>``.
    """
    T, B = trials.steps, trials.batch
    truth = trials.truth
    step_ns = round(H * 1e9)
    time_ns = step_ns * torch.arange(T + 1, dtype=torch.int64)
    friction = torch.as_tensor(trials.scene.friction, dtype=F64).expand(B)
    no_vision = torch.full((1, 3), math.nan, dtype=F64)
    settings_dict = _settings_dict(settings)
    logs = []
    for b in range(B):
        contacts = ContactTruth(
            mode=truth.mode[:, b].clone(),
            normal_impulse=truth.pn[:, b].clone(),
            friction_impulse=truth.pt[:, b].clone(),
            point=truth.points[:, b].clone(),
            normal=truth.normals[:, b].clone(),
            candidate=truth.active[:, b].clone(),
            solver=truth.solver[:, b].clone(),
        )
        logs.append(
            RunLog(
                name=f"{_EXPERIMENT}__{settings.seed}__trial{b:03d}",
                h=H,
                body=_BODY,
                joints=FINGER_JOINTS,
                time_ns=time_ns,
                robot_position=truth.q_kinematic[:, b].reshape(T + 1, -1).clone(),
                robot_velocity=trials.controls[:, b].reshape(T, -1).clone(),
                vision=torch.cat([no_vision, trials.y[:, b]]),
                tactile=trials.readings[:, b].clone(),
                source={"experiment": _EXPERIMENT, "trial": b, "settings": settings_dict},
                prior_mean=trials.prior.mean[b].clone(),
                prior_covariance=trials.prior.cov[b].clone(),
                bodies=(_BODY,),
                truth_pose=truth.q[:, b].clone(),
                truth_twist=truth.v[:, b].clone(),
                truth_contacts=contacts,
                parameters={"friction": float(friction[b])},
            )
        )
    return logs


def write_grasp_logs(
    folder: str | os.PathLike[str], settings: TriangleGrasp, trials: GraspTrials
) -> list[Path]:
    """Write :func:`grasp_run_logs` to ``folder/trial_<b>.mcap`` (``b`` zero-padded to 3
    digits; the folder is created).

    Returns:
        The paths, in trial order.
    """
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    return [
        write_run(out / f"trial_{b:03d}.mcap", log)
        for b, log in enumerate(grasp_run_logs(settings, trials))
    ]


def logged_settings(logs: Sequence[RunLog]) -> TriangleGrasp:
    """The :class:`TriangleGrasp` settings recorded in the logs' ``source``.

    Raises:
        ValueError: a log was not written by :func:`grasp_run_logs`, or the logs' settings
            differ.
    """
    found = []
    for i, log in enumerate(logs):
        source = log.source
        if source.get("experiment") != _EXPERIMENT or not isinstance(source.get("settings"), dict):
            raise ValueError(
                f"logs[{i}] ({log.name}): records no {_EXPERIMENT} settings in its source; "
                "give the settings"
            )
        found.append(source["settings"])
    if any(s != found[0] for s in found):
        raise ValueError("logs: the logs record different settings; give the settings")
    names = {f.name for f in dataclasses.fields(TriangleGrasp)}
    if set(found[0]) != names:
        raise ValueError(
            f"logs: the recorded settings have the fields {sorted(found[0])}, expected "
            f"{sorted(names)}"
        )
    settings = TriangleGrasp(**found[0])
    settings.check()
    return settings


def _require(i: int, log: RunLog, what: str, present: bool) -> None:
    if not present:
        raise ValueError(f"logs[{i}] ({log.name}): the triangle grasp's replay needs {what}")


def grasp_trials_from_logs(logs: Sequence[RunLog], settings: TriangleGrasp) -> GraspTrials:
    """The :class:`GraspTrials` of the logs (batch ``B = len(logs)``, in their order).

    The mode table and transition come from the settings' training rollouts
    (:func:`grasp_mode_table`), the tactile array from the settings
    (:func:`triangle_tactile_array`); the true scene has the logs' ``friction`` parameter.
    The rest comes from the logs: for logs of :func:`grasp_run_logs` the trials are those
    that were written, tensor for tensor.

    Raises:
        ValueError: no logs; a log is not of the triangle grasp (time step, robot
            coordinates, tracked body, tactile sensors), lacks the prior, the ground truth or
            the ``friction`` parameter; or the logs differ in steps or slots, or in the
            instants without vision (the evaluation scores one occlusion schedule).
    """
    if not logs:
        raise ValueError("logs: expected at least one run log, got none")
    settings.check()
    tactile = triangle_tactile_array(settings)
    S = tactile.positions.shape[0]
    T = logs[0].steps
    for i, log in enumerate(logs):
        if not isinstance(log, RunLog):
            raise ValueError(f"logs[{i}]: expected a RunLog, got {type(log).__name__}")
        _require(i, log, "the prior (/estimate/prior)", log.prior_mean is not None)
        _require(i, log, "the true states (/ground_truth/state)", log.truth_pose is not None)
        _require(
            i, log, "the true contacts (/ground_truth/contacts)", log.truth_contacts is not None
        )
        _require(
            i, log, "the true friction (/ground_truth/parameters)", "friction" in log.parameters
        )
        expected = (H, _BODY, FINGER_JOINTS, S, T, (_BODY,))
        got = (log.h, log.body, log.joints, log.tactile.shape[1], log.steps, log.bodies)
        if got != expected:
            raise ValueError(
                f"logs[{i}] ({log.name}): expected a triangle-grasp run (h, body, joints, "
                f"tactile sensors, steps, true bodies) = {expected}, got {got}"
            )
    contacts = [log.truth_contacts for log in logs if log.truth_contacts is not None]
    if len({c.mode.shape[1] for c in contacts}) != 1:
        raise ValueError("logs: the logs' true contacts have different numbers of slots")

    def stack(values: Sequence[Tensor | None]) -> Tensor:
        return torch.stack([v for v in values if v is not None], 1)

    y = stack([log.vision[1:] for log in logs])
    missing = torch.isnan(y[..., 0])
    if bool(torch.isnan(logs[0].vision[0]).logical_not().any()) or not bool(
        (missing == missing[:, :1]).all()
    ):
        raise ValueError(
            "logs: the triangle grasp's evaluation needs vision missing at instant 0 and at "
            "the same instants in every log"
        )
    truth = Rollout(
        q=stack([log.truth_pose for log in logs]),
        v=stack([log.truth_twist for log in logs]),
        q_kinematic=stack([log.robot_position.reshape(T + 1, 2, 3) for log in logs]),
        pn=stack([c.normal_impulse for c in contacts]),
        pt=stack([c.friction_impulse for c in contacts]),
        mode=stack([c.mode for c in contacts]),
        points=stack([c.point for c in contacts]),
        normals=stack([c.normal for c in contacts]),
        active=stack([c.candidate for c in contacts]),
        solver=stack([c.solver for c in contacts]),
    )
    table, transition = grasp_mode_table(settings)
    prior = Gaussian(
        torch.stack([log.prior_mean for log in logs if log.prior_mean is not None]),
        torch.stack([log.prior_covariance for log in logs if log.prior_covariance is not None]),
    )
    return GraspTrials(
        scene=triangle_scene(torch.tensor([log.parameters["friction"] for log in logs], dtype=F64)),
        truth=truth,
        controls=stack([log.robot_velocity.reshape(T, 2, 3) for log in logs]),
        y=y,
        readings=stack([log.tactile for log in logs]),
        tactile=tactile,
        prior=prior,
        occluded=missing[:, 0].clone(),
        table=table,
        transition=transition,
        true_ids=mode_ids(truth.mode, table),
    )


@dataclass(frozen=True, eq=False)
class Replay:
    """What :func:`replay` gives.

    Attributes:
        method: the estimator, one of :data:`GRASP_METHODS`.
        settings: the settings it ran with.
        trials: the trials rebuilt from the logs.
        output: the estimator's output (as in :attr:`EstimatorRuns.outputs`): ``pose (T, B,
            3)`` and, for the particle filters, ``marginals``, ``cloud`` and ``cloud_weight``.
        timing: the time it took.
        particles: its particle count (0 for ``ekf`` and ``vision``).
        metrics: ``{metric: value}``, its row of :func:`evaluate_tracking`.
        errors: ``(position error (T, B), angle error (T, B))`` of :func:`evaluate_tracking`.
    """

    method: str
    settings: TriangleGrasp
    trials: GraspTrials
    output: dict[str, Tensor]
    timing: Timing
    particles: int
    metrics: dict[str, float]
    errors: tuple[Tensor, Tensor]


def replay(
    logs: Sequence[RunLog | str | os.PathLike[str]],
    *,
    filter: str = "rbpf",
    settings: TriangleGrasp | None = None,
) -> Replay:
    """Run one estimator of the triangle-grasp experiment over run logs, as the experiment
    does (:func:`run_estimators`): the same functions, the same seeds
    (:data:`FILTER_SEED_OFFSETS`), the same scores.

    Over the logs that :func:`write_grasp_logs` wrote for a run of the experiment, in trial
    order and with the same settings, the estimates are those of the experiment (``pf`` with
    ``settings.pf_particles`` particles: give the count the experiment's calibration chose).

    Args:
        logs: run logs or paths of MCAP files, one per trial (batched in this order).
        filter: one of :data:`GRASP_METHODS`.
        settings: the settings (filters, sensors, training rollouts); ``None``: those
            recorded in the logs (:func:`logged_settings`).

    Returns:
        The estimates, their scores and timing.

    Raises:
        ValueError: ``filter`` is unknown; a path is not a readable log; the settings are
            missing or out of range (``rbpf_particles`` below the number of modes,
            ``pf_particles`` 0 for ``pf``); or the logs do not fit
            (:func:`grasp_trials_from_logs`).
    """
    method = check_choice("filter", filter, GRASP_METHODS)
    if isinstance(logs, str | os.PathLike) or not isinstance(logs, Sequence):
        raise ValueError(f"logs: expected a sequence of RunLog or paths, got {type(logs).__name__}")
    runs = [log if isinstance(log, RunLog) else read_run(log) for log in logs]
    if not runs:
        raise ValueError("logs: expected at least one run log, got none")
    if settings is None:
        settings = logged_settings(runs)
    elif not isinstance(settings, TriangleGrasp):
        raise ValueError(f"settings: expected a TriangleGrasp, got {type(settings).__name__}")
    if method == "pf":
        check_int("pf_particles", settings.pf_particles, low=1, why="the plain PF's count")
    trials = grasp_trials_from_logs(runs, settings)

    def generator() -> torch.Generator:
        return torch.Generator().manual_seed(settings.seed + FILTER_SEED_OFFSETS[method])

    particles = 0
    if method == "rbpf":
        model = grasp_contact_model(settings, trials)
        particles = check_int(
            "rbpf_particles", settings.rbpf_particles, low=model.num_modes, why="K modes"
        )
        output, timing = timed(lambda: run_rbpf(model, trials, settings, generator()))
    elif method in ("pf", "pf_same_n"):
        particles = settings.pf_particles if method == "pf" else settings.rbpf_particles
        output, timing = timed(lambda: run_pf(trials, settings, particles, generator()))
    elif method == "ekf":
        output, timing = timed(lambda: run_ekf(settings, trials))
    else:
        output, timing = timed(lambda: run_vision(trials))
    metrics, errors = evaluate_tracking(trials, {method: output})
    return Replay(
        method, settings, trials, output, timing, particles, metrics[method], errors[method]
    )
