"""Executing a learned peg-in-hole policy under uncertainty: oracle, raw, QMDP and neural Q."""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal, get_args

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

from torchcontact._checks import check_real
from torchcontact.envs import (
    NUM_CONTACT_CLASSES,
    PegBelief,
    PegInHole2DVector,
    PegInHoleBeliefModel,
    PegInHoleConfig,
    PegInHoleFilter,
    PegInHoleTask,
)
from torchcontact.experiments._peg_probing import (
    PRESS,
    PROBE_THRESHOLD,
    bottom_sides,
    bottom_touch,
    lateral_spread,
    probe_presses,
    shift_actions,
)
from torchcontact.experiments._q_lookup import QLookup
from torchcontact.geometry import rotation_matrix
from torchcontact.rl import QNetwork, greedy_action, qmdp_action

#: The execution settings compared by :func:`evaluate`.
Setting = Literal["oracle", "raw", "qmdp", "probe", "shift", "neural"]
SETTINGS: tuple[str, ...] = get_args(Setting)
#: Belief features after the state probabilities (see :func:`belief_features`).
NUM_BELIEF_FEATURES = 11 + NUM_CONTACT_CLASSES


def belief_features(
    filt: PegInHoleFilter, belief: PegBelief, lookup: QLookup, observation: Mapping[str, Any]
) -> Tensor:
    """The input of the neural Q function: ``(B, M + F)``, probabilities first.

    Features after the ``M`` state probabilities (:meth:`QLookup.probabilities`): the weighted
    mean of the peg's bottom centre relative to the hole and its angle (cm, cm, rad × 10),
    the log standard deviation of the pose (3), the entropy of the contact-class marginal,
    the effective sample size over ``N``, the ``K = 24`` contact-class marginals
    (:meth:`~torchcontact.envs.PegInHoleFilter.class_marginals`: the fitted model's modes,
    or the physics model's modes summed by class, so the features have the same meaning and
    size under either belief model), then the latest
    observation's touch (part of the observation history the belief conditions on, which the
    fitted belief model reads only as a contact class): whether the camera is blind (its pose
    all NaN) and whether the left and the right half of the peg's bottom touch
    (:func:`~torchcontact.experiments.bottom_sides`), each 0 or 1.

    Args:
        filt: the filter.
        belief: its belief, batch ``(B,)``.
        lookup: the tabular Q values' state map.
        observation: the latest noisy observation, ``"peg_pose" (B, 3)`` and ``"tactile"
            (B, S)``.
    """
    rbpf = belief.rbpf
    ids, weights = filt.particle_states(belief)
    probabilities = lookup.probabilities(ids, weights)
    relative = filt.model.task.states.relative_pose(filt.particle_poses(belief))  # (B, N, 3)
    mean = (weights.unsqueeze(-1) * relative).sum(1)
    spread = (weights.unsqueeze(-1) * (relative - mean.unsqueeze(1)) ** 2).sum(1)
    # each particle's own covariance, in its model's state frame (the fitted model's: the
    # gripper's; the physics model's: the world's; they differ by the gripper's small rotation)
    pose_variance = torch.diagonal(rbpf.gaussians.cov, dim1=-2, dim2=-1)[..., :3]
    variance = spread + (weights[..., None] * pose_variance).sum(1)
    marginal = filt.class_marginals(belief)
    entropy = -(marginal * torch.log(marginal.clamp(min=1e-300))).sum(-1, keepdim=True)
    ess = rbpf.ess().unsqueeze(-1) / filt.num_particles
    scale = torch.tensor([100.0, 100.0, 10.0], dtype=mean.dtype)
    return torch.cat(
        [
            probabilities,
            mean * scale,
            0.5 * torch.log(variance.clamp(min=1e-12)),
            entropy,
            ess,
            marginal,
            _touch_features(filt.model.task, observation).to(mean.dtype),
        ],
        dim=-1,
    )


def _touch_features(task: PegInHoleTask, observation: Mapping[str, Any]) -> Tensor:
    """``(B, 3)`` the touch part of :func:`belief_features`: blind camera, left and right half
    of the peg's bottom touching (float64, each 0 or 1).

    Args:
        task: the task (its sensors).
        observation: a noisy observation, ``"peg_pose" (B, 3)`` (NaN where the camera is blind)
            and ``"tactile" (B, S)``.
    """
    pose = torch.as_tensor(np.asarray(observation["peg_pose"]))
    blind = torch.isnan(pose).all(-1, keepdim=True)
    sides = bottom_sides(task, torch.as_tensor(np.asarray(observation["tactile"])).bool())
    return torch.cat([blind, sides], -1).to(torch.float64)


def qmdp_actions(
    lookup: QLookup, ids: Tensor, weights: Tensor, *, generator: torch.Generator | None = None
) -> Tensor:
    r"""The QMDP actions ``argmax_a Σ_i w_i Q(m_i, a)`` of particles in states ``m_i``.

    :func:`~torchcontact.rl.qmdp_action` of the agent's table under the belief
    :meth:`QLookup.probabilities` over its states, with its tie rule: the lowest action index,
    or with ``generator`` a uniformly random one of the tied actions
    (:func:`~torchcontact.rl.greedy_action`).

    Args:
        lookup: the tabular Q values; every state must have a row (:attr:`QLookup.complete`,
            e.g. ``nearest=True``), so that every belief has values.
        ids: ``(B, N)`` manipulation-state ids of the particles
            (:meth:`~torchcontact.envs.PegInHoleFilter.particle_states`).
        weights: ``(B, N)`` their normalized weights.
        generator: the random source of the tie-breaking keys; None for the lowest index.

    Returns:
        ``(B,)`` long actions.

    Raises:
        ValueError: ``lookup`` leaves a state without a row, or ``weights`` do not sum to 1.
    """
    if not lookup.complete:
        raise ValueError("lookup must give every state a row (QLookup(..., nearest=True)) for QMDP")
    return qmdp_action(lookup.table, lookup.probabilities(ids, weights), generator=generator)


@dataclass(frozen=True)
class Evaluation:
    """Outcome of :func:`evaluate` on ``E`` episodes.

    Attributes:
        setting: the execution setting's label (e.g. ``"qmdp + physics"``).
        successes: ``(E,)`` bool.
        lengths: ``(E,)`` steps per episode.
        seconds_per_decision: wall time of one batched decision over the ``E`` episodes,
            filter update included.
        true_class_log_prob: mean over every step of every episode of the log-probability
            that the filter's belief gives the true contact class after the step
            (:meth:`~torchcontact.envs.PegInHoleFilter.class_marginals`, floored at
            ``1e-12``); NaN for settings without a filter.
    """

    setting: str
    successes: NDArray[np.bool_]
    lengths: NDArray[np.int64]
    seconds_per_decision: float
    true_class_log_prob: float = math.nan

    @property
    def success_rate(self) -> float:
        """Fraction of successful episodes."""
        return float(self.successes.mean())

    @property
    def mean_steps(self) -> float:
        """Mean length of the successful episodes (NaN if none)."""
        return float(self.lengths[self.successes].mean()) if self.successes.any() else math.nan

    def metrics(self) -> dict[str, float]:
        """The table's numbers: ``success`` (fraction), ``steps`` (mean of the successful
        episodes), ``log_p_true_class`` and ``ms_per_decision``."""
        return {
            "success": self.success_rate,
            "steps": self.mean_steps,
            "log_p_true_class": self.true_class_log_prob,
            "ms_per_decision": 1e3 * self.seconds_per_decision,
        }


def evaluate(
    env: PegInHole2DVector,
    setting: Setting,
    *,
    lookup: QLookup,
    seed: int,
    filt: PegInHoleFilter | None = None,
    network: QNetwork | None = None,
    label: str | None = None,
    probe_threshold: float = PROBE_THRESHOLD,
) -> Evaluation:
    """Run one episode per sub-environment of ``env`` (noisy observations) under a setting.

    * ``"oracle"``: greedy on the true manipulation state;
    * ``"raw"``: greedy on the state of the raw observation: the camera's pose and the
      contact class that best explains the tactile readings
      (:meth:`~torchcontact.envs.PegInHoleBeliefModel.most_likely_classes` of ``filt``'s
      model, a fitted one); while the camera is blind, the pose it last saw carried with the
      gripper (:func:`raw_poses`; before it first sees the peg, the model's
      :attr:`~torchcontact.envs.PegInHoleBeliefModel.grasp_prior` mean);
    * ``"qmdp"``: QMDP over the particles of ``filt`` (:func:`qmdp_actions`);
    * ``"probe"``: probe, then insert: QMDP, except that while the camera is blind and the
      belief's lateral spread exceeds ``probe_threshold`` it presses the peg down until a
      bottom sensor fires (:func:`probe_presses`, once per episode), for the occluded variant;
    * ``"shift"``: touch-and-shift: QMDP, except that while the camera is blind it moves away
      from a bottom corner that touches alone, and presses while nothing touches and the
      spread exceeds ``probe_threshold`` (:func:`shift_actions`);
    * ``"neural"``: ``network`` on :func:`belief_features` of ``filt``'s belief.

    Every setting takes the action of highest value with one tie rule,
    :func:`~torchcontact.rl.greedy_action` with a generator seeded by ``seed``: exactly tied
    actions are chosen uniformly at random by keys drawn from that generator (one per action
    and episode at every decision, before the filter's step draws from it), nothing is added to
    the values. The particles' manipulation-state ids are computed once per step, by the filter
    (:attr:`~torchcontact.envs.PegBelief.state_ids`).

    Args:
        env: a vector environment with ``observation="noisy"``.
        setting: one of :data:`SETTINGS`.
        lookup: the tabular Q values.
        seed: seed of the episodes and of the generator of the filter and the tie-breaking.
        filt: the filter (``"qmdp"``, ``"neural"``; for ``"raw"`` one on a
            :class:`~torchcontact.envs.PegInHoleBeliefModel`, whose tactile model reads the
            sensors).
        network: the neural Q function (``"neural"``).
        label: the :attr:`Evaluation.setting` (default: ``setting``).
        probe_threshold: the lateral spread (m) above which ``"probe"`` and ``"shift"``
            press.

    Raises:
        ValueError: a missing or invalid argument.
    """
    check_real("probe_threshold", probe_threshold, low=0.0)
    if setting not in SETTINGS:
        raise ValueError(f"setting must be one of {SETTINGS}, got {setting!r}")
    if env.observation_mode != "noisy":
        raise ValueError("env must have observation='noisy'")
    if setting != "oracle" and filt is None:
        raise ValueError(f"filt is required for setting {setting!r} (its model reads the sensors)")
    if setting == "neural" and network is None:
        raise ValueError("network is required for setting 'neural'")
    fitted = isinstance(getattr(filt, "model", None), PegInHoleBeliefModel)
    if setting in ("raw", "probe", "shift") and not fitted:
        raise ValueError(f"filt must run on a PegInHoleBeliefModel for setting {setting!r}")
    E = env.num_envs
    states = env.states
    generator = torch.Generator().manual_seed(seed)
    first, info = env.reset(seed=seed)
    observation = _noisy(first)
    tracking = setting in ("qmdp", "probe", "shift", "neural")
    belief = filt.init(observation) if filt is not None and tracking else None
    live = np.ones(E, dtype=bool)
    successes = np.zeros(E, dtype=bool)
    lengths = np.zeros(E, dtype=np.int64)
    seconds, decisions = 0.0, 0
    log_prob, scored = 0.0, 0
    touched = torch.zeros(E, dtype=torch.bool)
    held = torch.zeros(E, 3, dtype=torch.float64)  # "raw": the grasp while the camera is blind
    if setting == "raw" and filt is not None and isinstance(filt.model, PegInHoleBeliefModel):
        held = filt.model.grasp_prior.mean.expand(E, 3)  # before the camera first sees the peg
    while live.any():
        start = time.perf_counter()
        if setting == "oracle":
            true_ids = torch.as_tensor(info["manipulation_state_id"])
            choice = greedy_action(lookup.values(true_ids)[0], generator=generator)
        elif setting == "raw":
            assert filt is not None
            readings = torch.as_tensor(observation["tactile"]).bool()
            assert isinstance(filt.model, PegInHoleBeliefModel)
            classes = filt.model.most_likely_classes(readings)
            raw_pose, held = raw_poses(observation, held=held)
            raw_ids = states.ids(raw_pose, classes)
            choice = greedy_action(lookup.values(raw_ids)[0], generator=generator)
        elif setting in ("qmdp", "probe", "shift"):
            assert belief is not None
            assert filt is not None
            choice = qmdp_actions(lookup, *filt.particle_states(belief), generator=generator)
            if setting == "probe":
                press = probe_presses(
                    blind=torch.as_tensor(np.isnan(observation["peg_pose"]).all(-1)),
                    spread=lateral_spread(filt, belief),
                    touched=touched,
                    threshold=probe_threshold,
                )
                choice = torch.where(press, PRESS, choice)
            elif setting == "shift":
                choice = shift_actions(
                    choice,
                    blind=torch.as_tensor(np.isnan(observation["peg_pose"]).all(-1)),
                    spread=lateral_spread(filt, belief),
                    sides=bottom_sides(
                        filt.model.task, torch.as_tensor(observation["tactile"]).bool()
                    ),
                    threshold=probe_threshold,
                )
        else:
            assert belief is not None
            assert filt is not None
            assert network is not None
            with torch.no_grad():
                features = belief_features(filt, belief, lookup, observation)
                choice = greedy_action(
                    network(features.to(network.table.dtype)), generator=generator
                )
        actions = choice.numpy()
        seconds += time.perf_counter() - start
        next_observation, _, terminated, truncated, info = env.step(actions)
        observation = _noisy(next_observation)
        if setting == "probe" and filt is not None:
            readings = torch.as_tensor(observation["tactile"]).bool()
            touched |= press & bottom_touch(filt.model.task, readings)
        if belief is not None and filt is not None:
            start = time.perf_counter()
            belief = filt.step(belief, actions, observation, generator=generator)
            seconds += time.perf_counter() - start
            true_class = torch.as_tensor(info["contact_class"])[torch.from_numpy(live)]
            marginal = filt.class_marginals(belief)[torch.from_numpy(live)]
            p_true = marginal.gather(1, true_class[:, None]).clamp(min=1e-12)
            log_prob += float(p_true.log().sum())
            scored += int(live.sum())
        decisions += 1
        lengths[live] += 1
        successes |= live & info["success"]
        live = live & ~(terminated | truncated)
    return Evaluation(
        setting if label is None else label,
        successes,
        lengths,
        seconds / max(decisions, 1),
        log_prob / scored if scored else math.nan,
    )


def raw_poses(observation: Mapping[str, Any], *, held: Tensor) -> tuple[Tensor, Tensor]:
    """The peg poses the raw observation gives, and the grasps to hold while the camera is blind.

    Where the camera sees the peg, its pose as measured; where it is blind (the row all NaN,
    :attr:`~torchcontact.envs.PegInHoleConfig.occlusion_radius`), the gripper's pose composed
    with the grasp ``held``: the peg's pose in the gripper frame when the camera last saw it,
    ``(u, w, φ) = (R(γ)ᵀ (p − g), θ − γ)`` for the camera's pose ``(p, θ)`` and the gripper's
    ``(g, γ)``, world pose ``(g + R(γ) (u, w), γ + φ)``.

    Args:
        observation: a noisy observation, ``"peg_pose" (B, 3)`` (world frame, all NaN where
            the camera is blind) and ``"gripper_pose" (B, 3)`` (world frame).
        held: ``(B, 3)`` the grasps held so far (gripper frame; at the start, e.g. a
            prior's mean).

    Returns:
        ``(B, 3)`` peg poses (world frame) and ``(B, 3)`` the grasps to hold from now on
        (updated where the camera sees).

    Raises:
        ValueError: a pose row is neither finite nor all NaN, or the gripper pose is not finite.
    """
    camera = torch.as_tensor(np.asarray(observation["peg_pose"]), dtype=torch.float64)
    gripper = torch.as_tensor(np.asarray(observation["gripper_pose"]), dtype=torch.float64)
    seen = torch.isfinite(camera).all(-1)
    if not bool((seen | torch.isnan(camera).all(-1)).all()):
        raise ValueError("observation: peg_pose must be finite or all NaN per row")
    if not bool(torch.isfinite(gripper).all()):
        raise ValueError("observation: gripper_pose must be finite")
    rotation = rotation_matrix(gripper[:, 2])  # (B, 2, 2), gripper to world
    offset = torch.where(seen[:, None], camera[:, :2] - gripper[:, :2], 0.0)
    grasp = torch.cat(
        [
            (rotation.transpose(-1, -2) @ offset.unsqueeze(-1)).squeeze(-1),
            (torch.where(seen, camera[:, 2], 0.0) - gripper[:, 2]).unsqueeze(-1),
        ],
        -1,
    )
    held = torch.where(seen[:, None], grasp, held.to(torch.float64))
    carried = torch.cat(
        [
            gripper[:, :2] + (rotation @ held[:, :2].unsqueeze(-1)).squeeze(-1),
            (gripper[:, 2] + held[:, 2]).unsqueeze(-1),
        ],
        -1,
    )
    return torch.where(seen[:, None], camera, carried), held


def _noisy(observation: object) -> Mapping[str, Any]:
    if not isinstance(observation, Mapping):
        raise ValueError("env must have observation='noisy' (a dict of arrays)")
    return observation


def evaluate_settings(
    settings: tuple[Setting, ...],
    *,
    num_episodes: int,
    config: PegInHoleConfig,
    lookup: QLookup,
    seed: int,
    filt: PegInHoleFilter | None = None,
    network: QNetwork | None = None,
    filters: Mapping[str, PegInHoleFilter] | None = None,
    probe_threshold: float = PROBE_THRESHOLD,
) -> list[Evaluation]:
    """:func:`evaluate` each setting on the same ``num_episodes`` seeded episodes.

    Args:
        settings: the settings, in table order.
        num_episodes: episodes per setting.
        config: the task configuration (its camera noise).
        lookup: the tabular Q values.
        seed: seed of the episodes (the same for every setting).
        filt: the filter of ``"raw"`` (its fitted tactile model), and of ``"qmdp"`` and
            ``"neural"`` unless ``filters`` is given.
        network: the neural Q function (``"neural"``).
        filters: belief filters by name: ``"qmdp"`` and ``"neural"`` run once with each,
            labelled ``"<setting> + <name>"`` (e.g. ``{"fitted": ..., "physics": ...}``).
        probe_threshold: the lateral spread (m) above which ``"probe"`` and ``"shift"``
            press.
    """
    env = PegInHole2DVector(num_envs=num_episodes, config=config, observation="noisy")
    evaluations = []
    for setting in settings:
        if setting in ("qmdp", "neural") and filters:
            for name, named in filters.items():
                evaluations.append(
                    evaluate(
                        env,
                        setting,
                        lookup=lookup,
                        seed=seed,
                        filt=named,
                        network=network,
                        label=f"{setting} + {name}",
                    )
                )
        else:
            evaluations.append(
                evaluate(
                    env,
                    setting,
                    lookup=lookup,
                    seed=seed,
                    filt=filt,
                    network=network,
                    probe_threshold=probe_threshold,
                )
            )
    return evaluations


def results_table(evaluations: list[Evaluation]) -> str:
    """A markdown table: success rate, mean steps of successes, the belief's mean
    log-probability of the true contact class per step, time per batched decision."""
    lines = [
        "| setting | episodes | success | mean steps (successes) | log p(true contact class) "
        "| ms per decision (batch) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for e in evaluations:
        log_p = "–" if math.isnan(e.true_class_log_prob) else f"{e.true_class_log_prob:.2f}"
        lines.append(
            f"| {e.setting} | {e.successes.size} | {100 * e.success_rate:.0f} % | "
            f"{e.mean_steps:.1f} | {log_p} | {1e3 * e.seconds_per_decision:.1f} |"
        )
    return "\n".join(lines)
