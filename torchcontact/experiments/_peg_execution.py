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

from torchcontact.envs import (
    NUM_CONTACT_CLASSES,
    PegBelief,
    PegInHole2DVector,
    PegInHoleConfig,
    PegInHoleFilter,
)
from torchcontact.experiments._q_lookup import QLookup
from torchcontact.rl import QNetwork

#: The execution settings compared by :func:`evaluate`.
Setting = Literal["oracle", "raw", "qmdp", "neural"]
SETTINGS: tuple[str, ...] = get_args(Setting)
#: Belief features after the state probabilities (see :func:`belief_features`).
NUM_BELIEF_FEATURES = 8 + NUM_CONTACT_CLASSES


def belief_features(filt: PegInHoleFilter, belief: PegBelief, lookup: QLookup) -> Tensor:
    """The input of the neural Q function: ``(B, M + F)``, probabilities first.

    Features after the ``M`` state probabilities (:meth:`QLookup.probabilities`): the weighted
    mean of the peg's bottom centre relative to the hole and its angle (cm, cm, rad × 10),
    the log standard deviation of the pose (3), the entropy of the contact-class marginal,
    the effective sample size over ``N``, and the ``K = 24`` class marginals.
    """
    rbpf = belief.rbpf
    ids, weights = filt.particle_states(belief)
    probabilities = lookup.probabilities(ids, weights)
    relative = filt.model.task.states.relative_pose(filt.particle_poses(belief))  # (B, N, 3)
    mean = (weights.unsqueeze(-1) * relative).sum(1)
    spread = (weights.unsqueeze(-1) * (relative - mean.unsqueeze(1)) ** 2).sum(1)
    variance = spread + (
        weights[..., None] * torch.diagonal(rbpf.gaussians.cov, dim1=-2, dim2=-1)
    ).sum(1)
    marginal = rbpf.mode_marginals()
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
        ],
        dim=-1,
    )


@dataclass(frozen=True)
class Evaluation:
    """Outcome of :func:`evaluate` on ``E`` episodes.

    Attributes:
        setting: the execution setting.
        successes: ``(E,)`` bool.
        lengths: ``(E,)`` steps per episode.
        seconds_per_decision: wall time of one batched decision over the ``E`` episodes,
            filter update included.
    """

    setting: str
    successes: NDArray[np.bool_]
    lengths: NDArray[np.int64]
    seconds_per_decision: float

    @property
    def success_rate(self) -> float:
        """Fraction of successful episodes."""
        return float(self.successes.mean())

    @property
    def mean_steps(self) -> float:
        """Mean length of the successful episodes (NaN if none)."""
        return float(self.lengths[self.successes].mean()) if self.successes.any() else math.nan


def evaluate(
    env: PegInHole2DVector,
    setting: Setting,
    *,
    lookup: QLookup,
    seed: int,
    filt: PegInHoleFilter | None = None,
    network: QNetwork | None = None,
) -> Evaluation:
    """Run one episode per sub-environment of ``env`` (noisy observations) under a setting.

    * ``"oracle"``: greedy on the true manipulation state;
    * ``"raw"``: greedy on the state of the raw observation: the camera's pose and the
      contact class that best explains the tactile readings
      (:meth:`~torchcontact.envs.PegInHoleBeliefModel.most_likely_classes` of ``filt``'s model);
    * ``"qmdp"``: QMDP over the particles of ``filt`` (:meth:`QLookup.qmdp`);
    * ``"neural"``: ``network`` on :func:`belief_features` of ``filt``'s belief.

    Ties are broken at random (seeded by ``seed``).

    Args:
        env: a vector environment with ``observation="noisy"``.
        setting: one of :data:`SETTINGS`.
        lookup: the tabular Q values.
        seed: seed of the episodes and of the filter.
        filt: the filter (``"qmdp"``, ``"neural"``).
        network: the neural Q function (``"neural"``).

    Raises:
        ValueError: a missing or invalid argument.
    """
    if setting not in SETTINGS:
        raise ValueError(f"setting must be one of {SETTINGS}, got {setting!r}")
    if env.observation_mode != "noisy":
        raise ValueError("env must have observation='noisy'")
    if setting != "oracle" and filt is None:
        raise ValueError(f"filt is required for setting {setting!r} (its model reads the sensors)")
    if setting == "neural" and network is None:
        raise ValueError("network is required for setting 'neural'")
    E = env.num_envs
    states = env.states
    generator = torch.Generator().manual_seed(seed)
    first, info = env.reset(seed=seed)
    observation = _noisy(first)
    tracking = setting in ("qmdp", "neural")
    belief = filt.init(observation) if filt is not None and tracking else None
    live = np.ones(E, dtype=bool)
    successes = np.zeros(E, dtype=bool)
    lengths = np.zeros(E, dtype=np.int64)
    seconds, decisions = 0.0, 0
    while live.any():
        start = time.perf_counter()
        if setting == "oracle":
            values, _ = lookup.values(torch.as_tensor(info["manipulation_state_id"]))
        elif setting == "raw":
            assert filt is not None
            readings = torch.as_tensor(observation["tactile"]).bool()
            classes = filt.model.most_likely_classes(readings)
            values, _ = lookup.values(states.ids(torch.as_tensor(observation["peg_pose"]), classes))
        else:
            assert belief is not None
            assert filt is not None
            if setting == "qmdp":
                values = lookup.qmdp(*filt.particle_states(belief))
            else:
                assert network is not None
                with torch.no_grad():
                    values = network(belief_features(filt, belief, lookup).to(network.table.dtype))
        noise = 1e-9 * torch.rand(values.shape, generator=generator, dtype=torch.float64)
        actions = (values.to(torch.float64) + noise).argmax(-1).numpy()
        seconds += time.perf_counter() - start
        next_observation, _, terminated, truncated, info = env.step(actions)
        observation = _noisy(next_observation)
        if belief is not None and filt is not None:
            start = time.perf_counter()
            belief = filt.step(belief, actions, observation, generator=generator)
            seconds += time.perf_counter() - start
        decisions += 1
        lengths[live] += 1
        successes |= live & info["success"]
        live = live & ~(terminated | truncated)
    return Evaluation(setting, successes, lengths, seconds / max(decisions, 1))


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
) -> list[Evaluation]:
    """:func:`evaluate` each setting on the same ``num_episodes`` seeded episodes."""
    env = PegInHole2DVector(num_envs=num_episodes, config=config, observation="noisy")
    return [
        evaluate(env, setting, lookup=lookup, seed=seed, filt=filt, network=network)
        for setting in settings
    ]


def results_table(evaluations: list[Evaluation]) -> str:
    """A markdown table: success rate, mean steps of successes, time per batched decision."""
    lines = [
        "| setting | episodes | success | mean steps (successes) | ms per decision (batch) |",
        "|---|---:|---:|---:|---:|",
    ]
    for e in evaluations:
        lines.append(
            f"| {e.setting} | {e.successes.size} | {100 * e.success_rate:.0f} % | "
            f"{e.mean_steps:.1f} | {1e3 * e.seconds_per_decision:.1f} |"
        )
    return "\n".join(lines)
