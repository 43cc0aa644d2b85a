"""Dyna-Q on the peg-in-hole task: rounds of batched episodes, shaped rewards, recorded data."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

from torchcontact.envs import PegInHole2DVector, PegInHoleStates, PegTransitions
from torchcontact.experiments._q_lookup import QLookup
from torchcontact.rl import DynaQ, Exploration, StepSize, greedy_action
from torchcontact.states import ManipulationState


@dataclass(frozen=True)
class PotentialShaping:
    r"""Potential-based reward shaping for the peg-in-hole task (Ng, Harada and Russell 1999).

    A learner with discount factor :math:`γ` sees :math:`r' = r + γ Φ(s′) − Φ(s)`
    (:math:`Φ(s′) = 0` at termination) with
    :math:`Φ = −\mathrm{scale} \cdot (|b_x| + |b_y + d|)`, the distance (m, L1) from the peg's
    bottom centre :math:`b` to the goal at the insertion depth :math:`d` below the hole's
    mouth. With the learner's own :math:`γ` in the term, the shaped discounted return of every
    policy differs from the unshaped one by :math:`−Φ(s_0)` only, so the optimal policies are
    unchanged, while the learner is told, before it ever succeeds, which way the goal lies.
    (With :math:`Φ(s′) − Φ(s)` and :math:`γ < 1` the shaping would instead pay
    :math:`(1 − γ)|Φ|` per step for staying far away.) ``scale = 0`` switches shaping off.

    Attributes:
        scale: ``>= 0``, in reward per metre (a 2 mm move changes ``Φ`` by ``0.002 scale``).
    """

    scale: float

    def __post_init__(self) -> None:
        if not (isinstance(self.scale, (int, float)) and math.isfinite(self.scale)):
            raise ValueError(f"scale must be a finite number >= 0, got {self.scale!r}")
        if self.scale < 0:
            raise ValueError(f"scale must be >= 0, got {self.scale!r}")

    def potential(
        self, states: PegInHoleStates, peg_pose: NDArray[np.float64], depth: float
    ) -> NDArray[np.float64]:
        """``Φ`` of peg poses ``(B, 3)`` (world frame), ``(B,)``."""
        relative = states.relative_pose(torch.as_tensor(peg_pose)).numpy()
        distance = np.abs(relative[:, 0]) + np.abs(relative[:, 1] + depth)
        return np.asarray(-self.scale * distance, dtype=np.float64)

    def shaped(
        self,
        reward: NDArray[np.float64],
        *,
        potential: NDArray[np.float64],
        next_potential: NDArray[np.float64],
        terminated: NDArray[np.bool_],
        gamma: float,
    ) -> NDArray[np.float64]:
        """``r + γ Φ(s′) − Φ(s)`` per entry ``(B,)``, with ``Φ(s′) = 0`` where ``terminated``."""
        return np.asarray(reward + np.where(terminated, 0.0, gamma * next_potential) - potential)


@dataclass(frozen=True)
class PegLearning:
    """The Dyna-Q settings that learn the peg-in-hole task (the train script's defaults).

    Chosen on the task (README, "Learning and execution"): step sizes
    ``max(alpha, 1/N(s, a))``, pessimistic planning and sweeps (model rewards less
    ``planning_penalty / √N(s, a)``), count-directed ε exploration and potential-based
    shaping of ``shaping`` reward per metre.

    Attributes:
        alpha: Q-learning step size (the floor of the visit-count step size).
        step_size: ``"visits"`` or ``"constant"``.
        planning_steps: Dyna-Q planning updates per real step.
        planning_penalty: pessimism of planning and sweeps.
        gamma: discount factor.
        epsilon: exploration rate.
        exploration: ``"least_tried"`` or ``"uniform"``.
        shaping: scale of :class:`PotentialShaping`.
    """

    alpha: float = 0.1
    step_size: StepSize = "visits"
    planning_steps: int = 10
    planning_penalty: float = 0.05
    gamma: float = 0.99
    epsilon: float = 0.1
    exploration: Exploration = "least_tried"
    shaping: float = 5.0

    def agent(self, *, seed: int, num_actions: int = 7) -> DynaQ:
        """A fresh agent with these settings (arguments checked by :class:`DynaQ`)."""
        return DynaQ(
            num_actions,
            alpha=self.alpha,
            gamma=self.gamma,
            epsilon=self.epsilon,
            planning_steps=self.planning_steps,
            seed=seed,
            exploration=self.exploration,
            step_size=self.step_size,
            planning_penalty=self.planning_penalty,
        )

    def potential_shaping(self) -> PotentialShaping:
        """The reward shaping of the learning updates."""
        return PotentialShaping(self.shaping)


def round_seed(base: int, round_index: int, *, num_envs: int) -> int:
    """The seed of round ``round_index`` of a run whose rounds reset ``num_envs`` environments.

    A vector environment reset with seed ``s`` seeds sub-environment ``i`` with ``s + i``, so
    the seeds of consecutive rounds must lie ``num_envs`` apart for their episodes to differ
    (seeds ``base + r`` would share all but one episode with the previous round).

    Args:
        base: the run's seed base (e.g. ``seed * 1_000_003``, plus an offset per purpose).
        round_index: the round, ``>= 0``.
        num_envs: the episodes per round.
    """
    return base + round_index * num_envs


@dataclass(frozen=True)
class RoundResult:
    """One round of ``B`` episodes.

    Attributes:
        returns: ``(B,)`` undiscounted environment returns (no shaping).
        lengths: ``(B,)`` episode lengths (steps).
        successes: ``(B,)`` bool, the peg reached the insertion depth.
        td_error: mean absolute TD error of the learning updates (NaN if none).
        transitions: every step taken, for fitting the filter's model.
        slot_modes: ``(T, S)`` long per-slot contact modes of the scene at the last simulator
            step of each of those steps (the mode table of
            :class:`~torchcontact.envs.PegPhysicsModel`).
    """

    returns: NDArray[np.float64]
    lengths: NDArray[np.int64]
    successes: NDArray[np.bool_]
    td_error: float
    transitions: PegTransitions
    slot_modes: Tensor


def run_round(
    env: PegInHole2DVector,
    agent: DynaQ,
    *,
    seed: int,
    shaping: PotentialShaping,
    learn: bool = True,
) -> RoundResult:
    """Run one episode in each of the ``B`` sub-environments, all started with ``seed``.

    Every sub-environment plays exactly one episode (started by ``env.reset(seed=seed)``; a
    finished one idles until the last ends), so a round depends only on the agent and
    ``seed``: checkpoints between rounds resume exactly. The agent acts on the true
    manipulation state (``info["manipulation_state_id"]`` as a
    :class:`~torchcontact.states.ManipulationState` key): ε-greedy and learning (each
    sub-environment's transitions in index order, shaped by ``shaping`` with the agent's
    discount factor) when ``learn``,
    else greedy (:func:`~torchcontact.rl.greedy_action`: ties broken at random by a generator
    seeded with ``seed``) and no update, where states the agent never acted from borrow the
    nearest known state's values (:class:`QLookup`).

    Args:
        env: the vector environment (any observation mode; the true state comes from infos).
        agent: the Dyna-Q agent (``num_actions`` = the env's actions).
        seed: the round's seed.
        shaping: the reward shaping of the learning updates.
        learn: learn (ε-greedy) or only evaluate (greedy).
    """
    B = env.num_envs
    depth = env.config.insertion_depth
    key = env.states.key

    def keys(info: dict[str, Any]) -> list[ManipulationState]:
        """The agent's state keys (only learning needs them; greedy reads the lookup)."""
        return [key(int(i)) for i in info["manipulation_state_id"]] if learn else []

    _, info = env.reset(seed=seed)
    states = keys(info)
    potential = shaping.potential(env.states, info["peg_pose"], depth)
    live = np.ones(B, dtype=bool)
    first = np.ones(B, dtype=bool)
    returns = np.zeros(B)
    lengths = np.zeros(B, dtype=np.int64)
    successes = np.zeros(B, dtype=bool)
    td_errors: list[float] = []
    parts: list[PegTransitions] = []
    modes: list[Tensor] = []
    lookup = None if learn else QLookup(agent, env.states)
    generator = torch.Generator().manual_seed(seed)
    while live.any():
        if learn:
            actions = np.array(
                [agent.act(s) if on else 0 for s, on in zip(states, live, strict=True)]
            )
        else:
            assert lookup is not None
            values, _ = lookup.values(torch.as_tensor(info["manipulation_state_id"]))
            actions = greedy_action(values, generator=generator).numpy()
        _, reward, terminated, truncated, next_info = env.step(actions)
        next_states = keys(next_info)
        next_potential = shaping.potential(env.states, next_info["peg_pose"], depth)
        shaped = shaping.shaped(
            reward,
            potential=potential,
            next_potential=next_potential,
            terminated=terminated,
            gamma=agent.gamma,
        )
        parts.append(
            PegTransitions.from_infos(info, actions, next_info, valid=live, first=first & live)
        )
        modes.append(env.physics.mode[torch.from_numpy(live)])
        for b in np.flatnonzero(live):
            if learn:
                s, a, s2 = states[b], int(actions[b]), next_states[b]
                target = shaped[b] + (
                    0.0 if terminated[b] else agent.gamma * float(agent.q_values(s2).max())
                )
                td_errors.append(abs(target - float(agent.q_values(s)[a])))
                agent.observe(s, a, float(shaped[b]), s2, bool(terminated[b]))
            returns[b] += reward[b]
            lengths[b] += 1
            successes[b] |= bool(next_info["success"][b])
        live = live & ~(terminated | truncated)
        first[:] = False
        states, potential, info = next_states, next_potential, next_info
    return RoundResult(
        returns=returns,
        lengths=lengths,
        successes=successes,
        td_error=float(np.mean(td_errors)) if td_errors else math.nan,
        transitions=PegTransitions.concat(parts),
        slot_modes=torch.cat(modes),
    )
