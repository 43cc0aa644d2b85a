"""Dyna-Q: tabular Q-learning that learns a manipulation graph and plans with it."""

from __future__ import annotations

import copy
import json
from collections.abc import Hashable, Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor

from torchcontact._checks import (
    FLOAT_DTYPES,
    all_finite,
    check_dtype,
    check_field,
    check_float,
    check_generator_state,
    check_int,
    check_real,
)
from torchcontact.states import ContactState, ManipulationGraph, ManipulationState, StateTable

_FORMAT = "torchcontact.DynaQ"

Sampler = Literal["index", "graph"]
Exploration = Literal["uniform", "least_tried"]
StepSize = Literal["constant", "visits"]


@dataclass(frozen=True)
class SweepResult:
    """Outcome of :meth:`DynaQ.sweep`.

    Attributes:
        sweeps: full sweeps done.
        residual: the largest change of a Q value in the last sweep.
        converged: ``residual <= tolerance``.
    """

    sweeps: int
    residual: float
    converged: bool


def _placeholder(index: int) -> ManipulationState:
    """The graph-side stand-in of the non-manipulation state with id ``index``."""
    return ManipulationState((index,), ContactState())


class DynaQ:
    r"""Tabular Dyna-Q over hashable states, with a :class:`ManipulationGraph` as its model.

    Every real transition ``(s, a, r, s′)`` passed to :meth:`observe` does three things:

    1. **direct RL**: the Q-learning update
       ``Q(s, a) ← Q(s, a) + α (r + γ max_b Q(s′, b) − Q(s, a))`` (no bootstrap when
       ``terminal``);
    2. **model learning**: the transition is recorded in :attr:`graph`, whose counts give the
       empirical model ``P(s′ | s, a) = N(s, a, s′) / N(s, a)`` and whose reward sums give the
       mean rewards ``R(s, a, s′)``;
    3. **planning**: ``planning_steps`` more Q-learning updates on simulated transitions: a
       previously observed pair ``(s, a)`` uniformly at random, ``s′ ~ P(· | s, a)`` and
       ``r = R(s, a, s′)`` from the model.

    All ``n`` planning samples of a step are drawn at once; the updates are then applied one
    after the other (each sees the previous ones, as in sequential Dyna-Q). A state that was
    once reached with ``terminal=True`` counts as terminal (value 0) in planning.

    **States and ids.** States get integer ids in first-seen order; :attr:`states` is the
    id → state table and row ``i`` of :meth:`q_table` belongs to ``states[i]``. The graph uses
    the same ids: a :class:`~torchcontact.states.ManipulationState` is stored in the graph as
    itself (so ``graph.states == agent.states`` and the graph is directly the filter's mode
    table), any other hashable state as the stand-in ``ManipulationState((id,), ContactState())``.
    Every Q value starts at ``initial_value`` (unknown states keep it): 0 by default, or an
    optimistic value (at least the best achievable return) so that a greedy agent still tries
    every action of a state before it settles (Sutton and Barto, Section 2.6).

    **Samplers.** ``sampler="index"`` (default) keeps an incremental sparse index of the
    graph's counts (``O(1)`` per observation, ``O(deg)`` per planning sample);
    ``sampler="graph"`` draws with :meth:`ManipulationGraph.sample_ids`, which rebuilds the
    dense ``(A, K, K)`` model after every observation (``O(A K²)`` per step). Both sample the
    same distribution but consume randomness differently.

    **Exploration.** With probability ε, :meth:`act` explores: ``"uniform"`` picks any action;
    ``"least_tried"`` picks uniformly among the actions tried least often in the state
    (``argmin_a N(s, a)``), so every action of a frequently visited state gets tried before any
    is tried twice by exploration — a directed, count-based exploration that leaves fewer
    untried actions (stuck at ``initial_value``) on the greedy policy's path.

    **Step sizes.** ``step_size="constant"`` updates every pair with ``α``;
    ``"visits"`` uses ``α(s, a) = max(α, 1 / N(s, a))`` with ``N(s, a)`` the real transitions
    observed from the pair so far (planning updates of the pair use the same value). The
    first updates of a pair then average its targets instead of shrinking the first one by
    ``α`` (a pair tried once has ``Q = target``, not ``α · target``), so rarely tried actions
    are not undervalued against often tried ones; after ``1/α`` visits it is constant-``α``
    Q-learning (Even-Dar and Mansour 2003 on polynomial step sizes).

    **Pessimistic planning.** With ``planning_penalty = β > 0`` every planning update and
    every sweep uses the reward ``R̂(s, a, s′) − β / √N(s, a)`` (real updates are unchanged):
    a lower confidence bound on the empirical model. Planning and sweeps take the maximum
    over actions of values estimated from the model, so pairs seen once or twice, whose one
    sampled outcome happened to be lucky, are overvalued and the bias compounds along
    chains of such pairs (the optimizer's curse). When the action gaps are small against
    that noise (long horizons, shaped rewards, an aliased state grid), an unpenalized model
    draws the greedy policy into barely explored regions; the penalty shrinks as the pair is
    visited (pessimism in the face of uncertainty, as in model-based offline RL: Yu et al.,
    "MOPO", NeurIPS 2020; the opposite sign of Dyna-Q+'s exploration bonus).

    **Sweeps.** :meth:`sweep` runs value iteration on the learned model (expected updates of
    every observed pair until the values stop changing, Sutton and Barto Section 8.5): the
    sample updates of planning then leave no inconsistency between neighbouring states'
    values for a greedy policy to exploit.

    **Randomness.** Exploration, tie-breaking and planning use the agent's own generators,
    seeded by ``seed``: two agents with the same seed and the same inputs behave identically,
    and :meth:`state_dict` / :meth:`load_state_dict` resume a run exactly.

    Args:
        num_actions: number of actions ``A >= 1``; actions are the ints ``0 … A − 1``.
        alpha: step size in ``(0, 1]``.
        gamma: discount factor in ``[0, 1]``.
        epsilon: exploration probability of :meth:`act` in ``[0, 1]``.
        planning_steps: planning updates per real transition, ``>= 0`` (0 is Q-learning).
        seed: seed of the agent's random generators, an int ``>= 0``.
        sampler: ``"index"`` or ``"graph"``, see above.
        initial_value: the Q value of every state-action pair before its first update.
        exploration: ``"uniform"`` or ``"least_tried"``, see above.
        step_size: ``"constant"`` or ``"visits"``, see above.
        planning_penalty: ``β >= 0``, see above (0: the plain empirical model).

    Raises:
        ValueError: an argument is out of range (the message names it).

    References:
        R. S. Sutton, "Dyna, an integrated architecture for learning, planning, and reacting",
        SIGART Bull. 2(4), 1991. R. S. Sutton and A. G. Barto, "Reinforcement Learning: An
        Introduction", 2nd ed., Section 8.2 (tabular Dyna-Q).
    """

    def __init__(
        self,
        num_actions: int,
        alpha: float = 0.1,
        gamma: float = 0.95,
        epsilon: float = 0.1,
        planning_steps: int = 10,
        seed: int = 0,
        *,
        sampler: Sampler = "index",
        initial_value: float = 0.0,
        exploration: Exploration = "uniform",
        step_size: StepSize = "constant",
        planning_penalty: float = 0.0,
    ) -> None:
        self._num_actions = check_int("num_actions", num_actions, low=1)
        self._initial_value = check_real("initial_value", initial_value)
        self.alpha = alpha
        self._gamma = check_real("gamma", gamma, low=0.0, high=1.0)
        self.epsilon = epsilon
        self.planning_steps = planning_steps
        self._seed = check_int("seed", seed, low=0)
        if sampler not in ("index", "graph"):
            raise ValueError(f"sampler must be 'index' or 'graph', got {sampler!r}")
        self._sampler: Sampler = sampler
        self._exploration = _check_exploration("exploration", exploration)
        self._step_size = _check_step_size("step_size", step_size)
        self._planning_penalty = check_real("planning_penalty", planning_penalty, low=0.0)
        self._rng = np.random.default_rng(self._seed)
        self._torch_rng = torch.Generator().manual_seed(self._seed)
        self._reset_tables()

    def _reset_tables(self) -> None:
        A = self._num_actions
        self._table: StateTable[Hashable] = StateTable()
        self._graph = ManipulationGraph(A)
        self._q = np.full((8, A), self._initial_value, dtype=np.float64)
        self._terminal = np.zeros(8, dtype=bool)
        # The sampling index mirrors the graph's counts: pair p = (s, a) in first-observed
        # order, its total count N(s, a) and its edges [s′, N(s, a, s′), reward sum].
        self._pair_ids: dict[tuple[int, int], int] = {}
        self._pairs = np.zeros((8, 2), dtype=np.int64)
        self._pair_totals = np.zeros(8, dtype=np.int64)
        self._edges: list[list[list[Any]]] = []
        self._steps = 0
        self._planning_updates = 0

    # ----------------------------------------------------------------------------- settings

    @property
    def num_actions(self) -> int:
        """``A``, the number of actions."""
        return self._num_actions

    @property
    def alpha(self) -> float:
        """Step size in ``(0, 1]`` (settable)."""
        return self._alpha

    @alpha.setter
    def alpha(self, value: float) -> None:
        self._alpha = check_real("alpha", value, low=0.0, high=1.0, low_open=True)

    @property
    def gamma(self) -> float:
        """Discount factor in ``[0, 1]``."""
        return self._gamma

    @property
    def epsilon(self) -> float:
        """Exploration probability of :meth:`act` in ``[0, 1]`` (settable, e.g. by a
        :class:`EpsilonSchedule`)."""
        return self._epsilon

    @epsilon.setter
    def epsilon(self, value: float) -> None:
        self._epsilon = check_real("epsilon", value, low=0.0, high=1.0)

    @property
    def planning_steps(self) -> int:
        """Planning updates per real transition (settable)."""
        return self._planning_steps

    @planning_steps.setter
    def planning_steps(self, value: int) -> None:
        self._planning_steps = check_int("planning_steps", value, low=0)

    @property
    def initial_value(self) -> float:
        """The Q value of every action of a state before any update."""
        return self._initial_value

    @property
    def sampler(self) -> Sampler:
        """How planning draws next states: ``"index"`` or ``"graph"``."""
        return self._sampler

    @property
    def exploration(self) -> Exploration:
        """How :meth:`act` explores: ``"uniform"`` or ``"least_tried"``."""
        return self._exploration

    @property
    def step_size(self) -> StepSize:
        """``"constant"`` or ``"visits"`` (see the class docstring)."""
        return self._step_size

    @property
    def planning_penalty(self) -> float:
        """``β``, the pessimism of planning and sweeps (see the class docstring)."""
        return self._planning_penalty

    @property
    def seed(self) -> int:
        """The seed the agent was created with."""
        return self._seed

    # ------------------------------------------------------------------------------ queries

    @property
    def graph(self) -> ManipulationGraph:
        """The learned model (the live object: read it, do not modify it)."""
        return self._graph

    @property
    def states(self) -> tuple[Hashable, ...]:
        """The known states, indexed by id."""
        return self._table.states

    @property
    def num_states(self) -> int:
        """``K``, the number of known states."""
        return len(self._table)

    @property
    def steps(self) -> int:
        """Number of real transitions observed."""
        return self._steps

    @property
    def planning_updates(self) -> int:
        """Number of planning updates made."""
        return self._planning_updates

    def __contains__(self, state: object) -> bool:
        return state in self._table

    def index(self, state: Hashable) -> int:
        """The id of a known state.

        Raises:
            UnknownStateError: ``state`` is unknown (a ``ValueError`` and a ``KeyError``).
        """
        return self._table.index(state)

    def q_values(self, state: Hashable, *, dtype: torch.dtype = torch.float64) -> Tensor:
        """``Q(state, ·)``, :attr:`initial_value` for an unknown state.

        Returns:
            ``(A,)`` new tensor of ``dtype``.

        Raises:
            ValueError: ``state`` is not hashable or ``dtype`` is not float32 or float64.
        """
        dtype = _check_float_dtype(dtype)
        return torch.from_numpy(self._row(state).copy()).to(dtype)

    def q_table(self, *, dtype: torch.dtype = torch.float64) -> Tensor:
        """The Q table in id order (rows follow :attr:`states` and ``graph.states``).

        Returns:
            ``(K, A)`` new tensor of ``dtype``; feed it to :func:`qmdp_action` with a belief
            over the graph's states.

        Raises:
            ValueError: ``dtype`` is not float32 or float64.
        """
        dtype = _check_float_dtype(dtype)
        return torch.from_numpy(self._q[: self.num_states].copy()).to(dtype)

    def is_terminal(self, state: Hashable) -> bool:
        """Whether ``state`` was reached with ``terminal=True``."""
        index = self._table.get(self._check_hashable("state", state))
        return index >= 0 and bool(self._terminal[index])

    # ------------------------------------------------------------------------------- acting

    def act(self, state: Hashable) -> int:
        """ε-greedy action: with probability ε an exploratory one (see :attr:`exploration`),
        else a maximizing action; ties broken uniformly at random (the agent's generator).
        """
        row = self._row(state)
        if self._rng.random() < self._epsilon:
            if self._exploration == "uniform":
                return int(self._rng.integers(self._num_actions))
            tried = self.action_counts(state)
            least = np.flatnonzero(tried == tried.min())
            return int(least[self._rng.integers(least.size)])
        best = np.flatnonzero(row == row.max())
        if best.size == 1:
            return int(best[0])
        return int(best[self._rng.integers(best.size)])

    def greedy(self, state: Hashable) -> int:
        """A maximizing action, the lowest one among ties (deterministic; no randomness used)."""
        return int(np.argmax(self._row(state)))

    def action_counts(self, state: Hashable) -> np.ndarray:
        """``(A,)`` int64 counts ``N(s, a)`` of the real transitions observed from ``state``."""
        index = self._table.get(self._check_hashable("state", state))
        counts = np.zeros(self._num_actions, dtype=np.int64)
        if index < 0:
            return counts
        for a in range(self._num_actions):
            pair = self._pair_ids.get((index, a))
            if pair is not None:
                counts[a] = self._pair_totals[pair]
        return counts

    def _row(self, state: Hashable) -> np.ndarray:
        index = self._table.get(self._check_hashable("state", state))
        if index < 0:
            return np.full(self._num_actions, self._initial_value, dtype=np.float64)
        row: np.ndarray = self._q[index]
        return row

    # ----------------------------------------------------------------------------- learning

    def observe(
        self,
        state: Hashable,
        action: int,
        reward: float,
        next_state: Hashable,
        terminal: bool,
    ) -> None:
        """Learn from one real transition: Q update, model update, then planning updates.

        Args:
            state: the state ``s`` the action was taken in.
            action: the action ``a`` in ``[0, A)``.
            reward: the reward ``r``, a finite number.
            next_state: the resulting state ``s′``.
            terminal: ``s′`` ends the episode (its value is 0); pass ``False`` when an episode
                is only cut by a time limit.

        Raises:
            ValueError: a state is not hashable, the action is out of range, the reward is
                not finite or ``terminal`` is not a bool.
        """
        a = check_int("action", action, low=0, high=self._num_actions)
        r = check_real("reward", reward)
        if not isinstance(terminal, (bool, np.bool_)):
            raise ValueError(f"terminal must be a bool, got {terminal!r}")
        # Check both states before registering either, so that a failure changes nothing.
        K = len(self._table)
        state_is_new = self._table.get(self._check_hashable("state", state)) < 0
        if state_is_new:
            self._check_stand_in("state", state, K)
        if self._table.get(self._check_hashable("next_state", next_state)) < 0 and not (
            state_is_new and next_state == state
        ):
            self._check_stand_in("next_state", next_state, K + state_is_new)
        s = self._register("state", state)
        s2 = self._register("next_state", next_state)
        self._graph.observe(self._graph_state(s), a, self._graph_state(s2), r)
        pair = self._record(s, a, s2, r)
        if terminal:
            self._terminal[s2] = True
        q = self._q
        target = r if terminal else r + self._gamma * float(q[s2].max())
        q[s, a] += float(self._step_sizes(self._pair_totals[pair])) * (target - q[s, a])
        self._steps += 1
        self._plan()

    def _step_sizes(self, totals: np.ndarray) -> np.ndarray:
        """Step sizes of pairs observed ``totals`` (``N(s, a) >= 1``) times, same shape."""
        if self._step_size == "constant":
            return np.full(np.shape(totals), self._alpha)
        return np.maximum(self._alpha, 1.0 / totals)

    def _check_hashable(self, name: str, state: object) -> Hashable:
        try:
            hash(state)
        except TypeError:
            raise ValueError(f"{name} must be hashable, got {type(state).__name__}") from None
        return state

    def _graph_state(self, index: int) -> ManipulationState:
        state = self._table[index]
        return state if isinstance(state, ManipulationState) else _placeholder(index)

    def _check_stand_in(self, name: str, state: object, index: int) -> ManipulationState:
        """The graph-side state of a new ``state`` that would get id ``index``.

        Raises:
            ValueError: it is already in the graph (as another state's stand-in, or a
                stand-in equal to a manipulation state).
        """
        graph_state = state if isinstance(state, ManipulationState) else _placeholder(index)
        if graph_state in self._graph:
            raise ValueError(
                f"{name} {state!r} collides in the graph with the stand-in of another state"
            )
        return graph_state

    def _register(self, name: str, state: object) -> int:
        """The id of ``state``, registering it (in the table, Q table and graph) if new."""
        known = self._table.get(self._check_hashable(name, state))
        if known >= 0:
            return known
        index = len(self._table)
        graph_state = self._check_stand_in(name, state, index)
        self._table.add(state)
        self._graph.add_state(graph_state)
        if index >= self._q.shape[0]:
            self._q = _grow(self._q, index + 1)
            self._terminal = _grow(self._terminal, index + 1)
        self._q[index] = self._initial_value
        return index

    def _record(self, s: int, a: int, s2: int, r: float) -> int:
        """Add ``(s, a, s′, r)`` to the sampling index (same arithmetic as the graph); return
        the pair's index."""
        pair = self._pair_ids.get((s, a))
        if pair is None:
            pair = self._pair_ids[(s, a)] = len(self._edges)
            if pair >= self._pairs.shape[0]:
                self._pairs = _grow(self._pairs, pair + 1)
                self._pair_totals = _grow(self._pair_totals, pair + 1)
            self._pairs[pair] = (s, a)
            self._edges.append([])
        self._pair_totals[pair] += 1
        for edge in self._edges[pair]:
            if edge[0] == s2:
                edge[1] += 1
                edge[2] += r
                return pair
        self._edges[pair].append([s2, 1, r])
        return pair

    def plan(self, num_updates: int | None = None) -> None:
        """Planning updates without a real transition (e.g. between episodes).

        Args:
            num_updates: how many, ``>= 0``; ``None`` is :attr:`planning_steps`. Nothing
                happens before the first :meth:`observe`.

        Raises:
            ValueError: ``num_updates`` is negative or not an int.
        """
        n = self._planning_steps if num_updates is None else num_updates
        self._plan(check_int("num_updates", n, low=0))

    def _plan(self, n: int | None = None) -> None:
        n = self._planning_steps if n is None else n
        num_pairs = len(self._edges)
        if n == 0 or num_pairs == 0:
            return
        picks = self._rng.integers(num_pairs, size=n)
        sources = self._pairs[picks, 0].tolist()
        actions = self._pairs[picks, 1].tolist()
        if self._sampler == "graph":
            next_ids, mean_rewards = self._graph.sample_ids(
                torch.as_tensor(self._pairs[picks, 0]),
                torch.as_tensor(self._pairs[picks, 1]),
                generator=self._torch_rng,
            )
            targets: list[int] = next_ids.tolist()
            rewards: list[float] = mean_rewards.tolist()
        else:
            tickets = self._rng.integers(self._pair_totals[picks]).tolist()
            targets, rewards = [], []
            for pair, ticket in zip(picks.tolist(), tickets, strict=True):
                edges, k = self._edges[pair], 0
                while ticket >= edges[k][1]:  # the edge holding ticket ∈ [0, N(s, a))
                    ticket -= edges[k][1]
                    k += 1
                s2, count, total = edges[k]
                targets.append(s2)
                rewards.append(total / count)
        if self._planning_penalty > 0:
            penalty = self._planning_penalty / np.sqrt(self._pair_totals[picks])
            rewards = (np.asarray(rewards) - penalty).tolist()
        alphas = self._step_sizes(self._pair_totals[picks]).tolist()
        q, terminal, gamma = self._q, self._terminal, self._gamma
        for s, a, s2, r, alpha in zip(sources, actions, targets, rewards, alphas, strict=True):
            target = r if terminal[s2] else r + gamma * float(q[s2].max())
            q[s, a] += alpha * (target - q[s, a])
        self._planning_updates += n

    def sweep(self, *, tolerance: float = 1e-8, max_sweeps: int = 10_000) -> SweepResult:
        """Value iteration on the learned model, in place.

        Every observed pair gets the expected update
        ``Q(s, a) ← Σ_s′ P(s′ | s, a) (R(s, a, s′) + γ max_b Q(s′, b)) − β / √N(s, a)`` (no
        bootstrap from terminal states; ``β`` = :attr:`planning_penalty`), all pairs at once
        per sweep, until no value changes by more than
        ``tolerance``. Pairs never observed keep their values. For ``γ < 1`` this converges
        to the optimal Q function of the empirical model (a γ-contraction).

        Args:
            tolerance: ``> 0``, the convergence threshold on the largest change.
            max_sweeps: ``>= 1``, the most sweeps.

        Returns:
            The number of sweeps, the last residual and whether it converged (with ``γ = 1``
            and a model with cycles it may not: check ``converged``).

        Raises:
            ValueError: an argument is out of range.
        """
        tolerance = check_real("tolerance", tolerance, low=0.0, low_open=True)
        max_sweeps = check_int("max_sweeps", max_sweeps, low=1)
        num_pairs = len(self._edges)
        if num_pairs == 0:
            return SweepResult(0, 0.0, True)
        rows = [
            (pair, s2, count, total)
            for pair, edges in enumerate(self._edges)
            for s2, count, total in edges
        ]
        pair, target, count, total = (np.array(column) for column in zip(*rows, strict=True))
        probability = count / self._pair_totals[pair]
        reward = probability * total / count  # P(s′|s,a) R(s,a,s′)
        source, action = self._pairs[:num_pairs, 0], self._pairs[:num_pairs, 1]
        q, live = self._q, ~self._terminal[target]
        penalty = self._planning_penalty / np.sqrt(self._pair_totals[:num_pairs])
        residual = float("inf")
        for done in range(1, max_sweeps + 1):
            backup = reward + probability * self._gamma * np.where(live, q[target].max(1), 0.0)
            values = np.bincount(pair, weights=backup, minlength=num_pairs) - penalty
            residual = float(np.abs(values - q[source, action]).max())
            q[source, action] = values
            if residual <= tolerance:
                return SweepResult(done, residual, True)
        return SweepResult(max_sweeps, residual, False)

    # -------------------------------------------------------------------------- checkpoints

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume exactly: settings, states, Q table, terminal flags,
        the graph, the sampling index, the generators' states and the counters.

        The result shares no memory with the agent. It holds the states themselves (any
        hashable objects), so save it with ``torch.save`` and read it back with
        ``torch.load(..., weights_only=False)`` (or pickle).
        """
        K, P = self.num_states, len(self._edges)
        edge_rows = [
            (pair, s2, count, total)
            for pair, edges in enumerate(self._edges)
            for s2, count, total in edges
        ]
        edge_pair, edge_next, edge_count, edge_sum = (
            [row[k] for row in edge_rows] for k in range(4)
        )
        return {
            "format": _FORMAT,
            "version": 1,
            "num_actions": self._num_actions,
            "alpha": self._alpha,
            "gamma": self._gamma,
            "epsilon": self._epsilon,
            "planning_steps": self._planning_steps,
            "seed": self._seed,
            "sampler": self._sampler,
            "initial_value": self._initial_value,
            "exploration": self._exploration,
            "step_size": self._step_size,
            "planning_penalty": self._planning_penalty,
            "states": list(self._table.states),
            "q_table": torch.from_numpy(self._q[:K].copy()),
            "terminal": torch.from_numpy(self._terminal[:K].copy()),
            "graph": self._graph.to_json(),
            "pairs": torch.from_numpy(self._pairs[:P].copy()),
            "edge_pair": torch.tensor(edge_pair, dtype=torch.long),
            "edge_next": torch.tensor(edge_next, dtype=torch.long),
            "edge_count": torch.tensor(edge_count, dtype=torch.long),
            "edge_reward_sum": torch.tensor(edge_sum, dtype=torch.float64),
            "numpy_rng": copy.deepcopy(self._rng.bit_generator.state),
            "torch_rng": self._torch_rng.get_state(),
            "steps": self._steps,
            "planning_updates": self._planning_updates,
        }

    def load_state_dict(self, state_dict: Mapping[str, Any]) -> None:
        """Restore a :meth:`state_dict` (settings included); the agent then continues exactly
        as the saved one would have.

        Raises:
            ValueError: ``state_dict`` is not a DynaQ state, was saved with another number of
                actions, misses an entry, has an entry of the wrong type, shape or range (a
                count below 1, an id or action out of range, NaN or inf, an RNG state that
                does not load), or its parts disagree with each other; the message names the
                entry and the agent is unchanged.
        """
        restored = DynaQ(self._num_actions)
        restored._restore(state_dict)
        self.__dict__.update(restored.__dict__)

    def _restore(self, state_dict: Mapping[str, Any]) -> None:
        """Load ``state_dict`` into this (fresh) agent; see :meth:`load_state_dict`.

        Every entry is checked (presence, type, shape, range) before use, and the parts are
        checked against each other, so that a corrupt state raises ``ValueError`` naming the
        entry instead of failing later (a zero count would make :meth:`sweep` divide by it).
        """
        if not isinstance(state_dict, Mapping) or state_dict.get("format") != _FORMAT:
            raise ValueError(f"state_dict is not a {_FORMAT} state")

        def field(key: str) -> Any:
            return check_field("state_dict", state_dict, key)

        version = state_dict.get("version", 1)
        if version != 1 or isinstance(version, bool):
            raise ValueError(f"state_dict version must be 1, got {version!r}")
        num_actions = check_int("state_dict num_actions", field("num_actions"), low=1)
        if num_actions != self._num_actions:
            raise ValueError(
                f"state_dict has num_actions = {num_actions}, this agent has {self._num_actions}"
            )
        states = field("states")
        if not isinstance(states, (list, tuple)):
            raise ValueError(f"state_dict states must be a list, got {type(states).__name__}")
        K, A = len(states), self._num_actions
        q_table = check_float("state_dict q_table", field("q_table"), what=f"({K}, {A})")
        terminal = check_dtype("state_dict terminal", field("terminal"), torch.bool, f"({K},)")
        if q_table.shape != (K, A) or terminal.shape != (K,):
            raise ValueError(
                f"state_dict q_table/terminal must have shapes ({K}, {A})/({K},), "
                f"got {tuple(q_table.shape)}/{tuple(terminal.shape)}"
            )
        alpha = check_real("state_dict alpha", field("alpha"), low=0.0, high=1.0, low_open=True)
        epsilon = check_real("state_dict epsilon", field("epsilon"), low=0.0, high=1.0)
        gamma = check_real("state_dict gamma", field("gamma"), low=0.0, high=1.0)
        planning_steps = check_int("state_dict planning_steps", field("planning_steps"), low=0)
        sampler = field("sampler")
        if sampler not in ("index", "graph"):
            raise ValueError(f"state_dict sampler must be 'index' or 'graph', got {sampler!r}")
        seed = check_int("state_dict seed", field("seed"), low=0)
        steps = check_int("state_dict steps", field("steps"), low=0)
        planning_updates = check_int(
            "state_dict planning_updates", field("planning_updates"), low=0
        )
        torch_rng = check_generator_state("state_dict torch_rng", field("torch_rng"))
        numpy_rng = np.random.default_rng()
        try:
            numpy_rng.bit_generator.state = copy.deepcopy(field("numpy_rng"))
        except (TypeError, ValueError, KeyError) as error:
            raise ValueError(
                f"state_dict numpy_rng is not a numpy bit-generator state ({error!r})"
            ) from None
        text = field("graph")
        if not isinstance(text, str):
            raise ValueError(f"state_dict graph must be a JSON str, got {type(text).__name__}")
        try:
            graph = ManipulationGraph.from_json(text)
        except ValueError as error:
            raise ValueError(f"state_dict graph: {error}") from None
        initial_value = state_dict.get("initial_value", 0.0)  # a state dict without it: 0
        self._initial_value = check_real("state_dict initial_value", initial_value)
        self._exploration = _check_exploration(
            "state_dict exploration", state_dict.get("exploration", "uniform")
        )
        self._step_size = _check_step_size(
            "state_dict step_size", state_dict.get("step_size", "constant")
        )
        self._planning_penalty = check_real(
            "state_dict planning_penalty", state_dict.get("planning_penalty", 0.0), low=0.0
        )
        self._reset_tables()
        for index, state in enumerate(states):
            if self._register("state_dict states", state) != index:
                raise ValueError("state_dict states must be distinct")
        if graph.states != self._graph.states or graph.num_actions != A:
            raise ValueError("state_dict graph does not match state_dict states")
        self._graph = graph
        self._q[:K] = q_table.to(torch.float64).numpy()
        self._terminal[:K] = terminal.numpy()
        self._load_index(state_dict, K)
        self._alpha, self._gamma, self._epsilon = alpha, gamma, epsilon
        self._planning_steps, self._sampler = planning_steps, sampler
        self._seed = seed
        self._rng = numpy_rng
        self._torch_rng.set_state(torch_rng)
        self._steps, self._planning_updates = steps, planning_updates

    def _load_index(self, state_dict: Mapping[str, Any], K: int) -> None:
        """Rebuild the sampling index and check it against the graph's counts.

        Raises:
            ValueError: an index entry has the wrong dtype or shape, an id, action or count
                is out of range (every count ``>= 1``, every pair with an edge), a reward sum
                is not finite, or the index disagrees with the graph.
        """
        A = self._num_actions
        pairs_value = check_dtype(
            "state_dict pairs", check_field("state_dict", state_dict, "pairs"), torch.long, "(P, 2)"
        )
        if pairs_value.ndim != 2 or pairs_value.shape[1] != 2:
            raise ValueError(
                f"state_dict pairs must have shape (P, 2), got {tuple(pairs_value.shape)}"
            )
        P = pairs_value.shape[0]
        for column, name, high in ((0, "state ids", K), (1, "actions", A)):
            values = pairs_value[:, column]
            if P and (int(values.min()) < 0 or int(values.max()) >= high):
                raise ValueError(f"state_dict pairs {name} must lie in [0, {high})")
        columns: list[Tensor] = []
        for key, dtype in (
            ("edge_pair", torch.long),
            ("edge_next", torch.long),
            ("edge_count", torch.long),
            ("edge_reward_sum", torch.float64),
        ):
            name = f"state_dict {key}"
            value = check_dtype(name, check_field("state_dict", state_dict, key), dtype, "(E,)")
            if value.ndim != 1 or (columns and value.shape != columns[0].shape):
                raise ValueError(
                    f"{name} must have shape (E,) like state_dict edge_pair, "
                    f"got {tuple(value.shape)}"
                )
            columns.append(value)
        edge_pair, edge_next, edge_count, edge_sum = columns
        if edge_pair.numel():
            ranges: list[tuple[str, Tensor, int, int | None]] = [
                ("edge_pair", edge_pair, 0, P),
                ("edge_next", edge_next, 0, K),
                ("edge_count", edge_count, 1, None),
            ]
            for key, values, low, upper in ranges:
                too_high = upper is not None and int(values.max()) >= upper
                if int(values.min()) < low or too_high:
                    bounds = f"[{low}, {upper})" if upper is not None else f">= {low}"
                    raise ValueError(f"state_dict {key} must lie in {bounds}")
            if not all_finite(edge_sum):
                raise ValueError("state_dict edge_reward_sum contains NaN or inf")
        pairs = pairs_value.tolist()
        self._pairs = _grow(self._pairs, P)
        self._pair_totals = _grow(self._pair_totals, P)
        for pair, (s, a) in enumerate(pairs):
            self._pair_ids[(s, a)] = pair
            self._pairs[pair] = (s, a)
            self._edges.append([])
        if len(self._pair_ids) != P:
            raise ValueError("state_dict pairs must be distinct")
        counts: dict[tuple[int, int, int], tuple[int, float]] = {}
        rows = zip(
            edge_pair.tolist(),
            edge_next.tolist(),
            edge_count.tolist(),
            edge_sum.tolist(),
            strict=True,
        )
        for pair, s2, count, total in rows:
            self._edges[pair].append([s2, count, total])
            self._pair_totals[pair] += count
            s, a = pairs[pair]
            counts[(s, a, s2)] = (count, total)
        if P and int(self._pair_totals[:P].min()) < 1:
            raise ValueError("state_dict pairs must each have an edge (a count N(s, a) >= 1)")
        graph_counts = {
            (i, a, j): (n, total)
            for i, a, j, n, total in json.loads(self._graph.to_json())["transitions"]
        }
        if counts != graph_counts or sum(map(len, self._edges)) != len(counts):
            raise ValueError("state_dict sampling index does not match its graph")

    @classmethod
    def from_state_dict(cls, state_dict: Mapping[str, Any]) -> DynaQ:
        """A new agent restored from :meth:`state_dict`.

        Raises:
            ValueError: see :meth:`load_state_dict`.
        """
        if not isinstance(state_dict, Mapping) or state_dict.get("format") != _FORMAT:
            raise ValueError(f"state_dict is not a {_FORMAT} state")
        num_actions = check_field("state_dict", state_dict, "num_actions")
        agent = cls(check_int("state_dict num_actions", num_actions, low=1))
        agent.load_state_dict(state_dict)
        return agent

    def __repr__(self) -> str:
        return (
            f"DynaQ(num_actions={self._num_actions}, alpha={self._alpha}, gamma={self._gamma}, "
            f"epsilon={self._epsilon}, planning_steps={self._planning_steps}, "
            f"seed={self._seed}, sampler={self._sampler!r}, "
            f"exploration={self._exploration!r}, step_size={self._step_size!r}, "
            f"planning_penalty={self._planning_penalty}, "
            f"states={self.num_states}, "
            f"steps={self._steps})"
        )


def _check_float_dtype(dtype: object) -> torch.dtype:
    if dtype not in FLOAT_DTYPES:
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    assert isinstance(dtype, torch.dtype)
    return dtype


def _check_exploration(name: str, value: object) -> Exploration:
    if value == "uniform":
        return "uniform"
    if value == "least_tried":
        return "least_tried"
    raise ValueError(f"{name} must be 'uniform' or 'least_tried', got {value!r}")


def _check_step_size(name: str, value: object) -> StepSize:
    if value == "constant":
        return "constant"
    if value == "visits":
        return "visits"
    raise ValueError(f"{name} must be 'constant' or 'visits', got {value!r}")


def _grow(array: np.ndarray, size: int) -> np.ndarray:
    """``array`` zero-padded along dim 0 to a capacity ``>= size`` (doubling)."""
    if array.shape[0] >= size:
        return array
    capacity = max(size, 2 * array.shape[0], 8)
    grown = np.zeros((capacity, *array.shape[1:]), dtype=array.dtype)
    grown[: array.shape[0]] = array
    return grown
