"""The manipulation graph: transition statistics between manipulation states under actions."""

from __future__ import annotations

import json
import math
import numbers
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchcontact._checks import (
    FLOAT_DTYPES,
    check_field,
    check_float,
    check_int,
    check_real,
    parse_json,
    read_text_file,
)
from torchcontact.states._manipulation_state import ManipulationState
from torchcontact.states._registry import StateTable

_FORMAT = "torchcontact.ManipulationGraph"


def _float_dtype(dtype: torch.dtype | None) -> torch.dtype:
    """``dtype`` (float32 or float64), or torch's default dtype for ``None``."""
    if dtype is None:
        return torch.get_default_dtype()
    if dtype not in FLOAT_DTYPES:
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    return dtype


def _is_real(value: object) -> bool:
    """Whether ``value`` is a real number (not a bool)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


class ManipulationGraph:
    r"""Manipulation states as nodes, observed transitions under actions as edges.

    The graph is built incrementally from tuples ``(m, a, m′, r)`` (:meth:`observe`) and keeps
    the counts ``N(m, a, m′)`` and reward sums. States get integer ids in first-seen order
    (as source or destination); ``K`` is the number of known states and actions are the
    integers ``0 … A − 1``. The transition model is the posterior mean under a symmetric
    Dirichlet prior of concentration ``α = smoothing`` over the known states:

    .. math::

        P(m' \mid m, a) = \frac{N(m, a, m') + α}{N(m, a) + α K},
        \qquad N(m, a) = \sum_{m'} N(m, a, m').

    **Unknown inputs, explicitly:**

    * an unvisited pair ``(m, a)`` (``N(m, a) = 0``) gets the prior: uniform over the ``K``
      known states if ``α > 0``, and a self-loop ``P(m | m, a) = 1`` if ``α = 0`` (nothing is
      known to happen, so the state persists); adding states changes ``K`` and so the
      smoothed probabilities of every pair;
    * a transition never observed has mean reward ``default_reward``;
    * a state that is not in the graph raises :class:`UnknownStateError`, a ``ValueError``
      and a ``KeyError`` (register it with :meth:`add_state` to get the prior above).

    The graph exports the filter's mode-transition model (:meth:`transition_tensor`,
    :meth:`transition_matrix`, with :attr:`states` as the id ↔ state table), the sampling model
    of Dyna-Q planning (:meth:`sample`, :meth:`sample_ids`), JSON (:meth:`to_json`, exact
    round trip), networkx (:meth:`to_networkx`) and a drawing (:meth:`draw`).

    Args:
        num_actions: number of actions ``A >= 1``.
        smoothing: Dirichlet concentration ``α >= 0``.
        default_reward: mean reward of transitions never observed.

    References:
        Seed paper, Section III (the manipulation graph, built by Dyna-Q and used as the
        filter's transition model). J. Xiao and X. Ji, "On automatic generation of high-level
        contact state space", IJRR 20(7), 2001 (contact-state graphs). R. S. Sutton, "Dyna, an
        integrated architecture for learning, planning, and reacting", SIGART Bull. 2(4), 1991.
    """

    def __init__(
        self, num_actions: int, *, smoothing: float = 0.0, default_reward: float = 0.0
    ) -> None:
        if (
            isinstance(num_actions, bool)
            or not isinstance(num_actions, int)
            or not 1 <= num_actions < 2**31
        ):
            raise ValueError(f"num_actions must be an int >= 1 and < 2**31, got {num_actions!r}")
        if not _is_real(smoothing) or not math.isfinite(smoothing) or smoothing < 0:
            raise ValueError(f"smoothing must be a finite number >= 0, got {smoothing!r}")
        if not _is_real(default_reward) or not math.isfinite(default_reward):
            raise ValueError(f"default_reward must be finite, got {default_reward!r}")
        self._num_actions = num_actions
        self._smoothing = float(smoothing)
        self._default_reward = float(default_reward)
        self._table: StateTable[ManipulationState] = StateTable()
        # (m, a) -> {m′: [count, reward sum]}, in first-observed order.
        self._edges: dict[tuple[int, int], dict[int, list[Any]]] = {}
        self._tensors: tuple[Tensor, Tensor] | None = None  # see _model

    @property
    def num_actions(self) -> int:
        """``A``, the number of actions."""
        return self._num_actions

    @property
    def smoothing(self) -> float:
        """The Dirichlet concentration ``α``."""
        return self._smoothing

    @property
    def default_reward(self) -> float:
        """Mean reward of transitions never observed."""
        return self._default_reward

    @property
    def num_states(self) -> int:
        """``K``, the number of known states."""
        return len(self._table)

    @property
    def states(self) -> tuple[ManipulationState, ...]:
        """The known states, indexed by id (the filter's mode table)."""
        return self._table.states

    def __contains__(self, state: object) -> bool:
        return state in self._table

    def index(self, state: ManipulationState) -> int:
        """The id of a known state (:class:`UnknownStateError` if unknown)."""
        return self._table.index(state)

    def add_state(self, state: ManipulationState) -> int:
        """Register ``state`` without a transition and return its id."""
        if not isinstance(state, ManipulationState):
            raise ValueError(f"state must be a ManipulationState, got {type(state).__name__}")
        known = len(self._table)
        index = self._table.add(state)
        if len(self._table) != known:
            self._tensors = None
        return index

    def observe(
        self,
        state: ManipulationState,
        action: int,
        next_state: ManipulationState,
        reward: float,
    ) -> None:
        """Record one transition ``(m, a, m′, r)``.

        Raises:
            ValueError: a state is not a :class:`ManipulationState`, the action is outside
                ``[0, A)``, or the reward is not finite.
        """
        self._check_action(action)
        if not _is_real(reward) or not math.isfinite(reward):
            raise ValueError(f"reward must be finite, got {reward!r}")
        for name, value in (("state", state), ("next_state", next_state)):
            if not isinstance(value, ManipulationState):
                raise ValueError(f"{name} must be a ManipulationState, got {type(value).__name__}")
        source = self.add_state(state)
        target = self.add_state(next_state)
        entry = self._edges.setdefault((source, action), {}).setdefault(target, [0, 0.0])
        entry[0] += 1
        entry[1] += float(reward)
        self._tensors = None

    def count(
        self,
        state: ManipulationState,
        action: int | None = None,
        next_state: ManipulationState | None = None,
    ) -> int:
        """Observed count ``N(m, a, m′)``, summed over ``a`` and/or ``m′`` where ``None``."""
        source = self.index(state)
        target = None if next_state is None else self.index(next_state)
        if action is not None:
            self._check_action(action)
        total = 0
        for (i, a), row in self._edges.items():
            if i == source and action in (None, a):
                total += sum(n for j, (n, _) in row.items() if target in (None, j))
        return total

    def visits(self, state: ManipulationState) -> int:
        """How often an action was taken in ``state``: ``Σ_a N(m, a)``."""
        return self.count(state)

    def mean_reward(
        self, state: ManipulationState, action: int, next_state: ManipulationState
    ) -> float:
        """Mean observed reward of ``(m, a, m′)``, ``default_reward`` if never observed."""
        self._check_action(action)
        row = self._edges.get((self.index(state), action), {})
        n, total = row.get(self.index(next_state), (0, 0.0))
        return total / n if n else self._default_reward

    def transition_probabilities(
        self, state: ManipulationState, action: int, *, dtype: torch.dtype | None = None
    ) -> Tensor:
        """``P(· | m, a)`` over the known states, in ``O(K)`` (no ``(A, K, K)`` tensor).

        Returns:
            ``(K,)`` probabilities indexed by state id (see the class docstring for unvisited
            pairs), equal to ``transition_tensor()[a, index(m)]``.
        """
        self._check_action(action)
        row = self._probability_row(self.index(state), action)
        return row.to(_float_dtype(dtype))

    def _probability_row(self, source: int, action: int) -> Tensor:
        """``(K,)`` float64 ``P(· | m_source, a)``, with the arithmetic of :meth:`_model`."""
        K, alpha = self.num_states, self._smoothing
        counts = torch.zeros(K, dtype=torch.float64)
        for j, (n, _) in self._edges.get((source, action), {}).items():
            counts[j] = n
        total = counts.sum() + alpha * K
        if total > 0:
            return (counts + alpha) / total
        return torch.eye(K, dtype=torch.float64)[source]

    def _model(self) -> tuple[Tensor, Tensor]:
        """``(A, K, K)`` float64 transition probabilities and mean rewards, cached until the
        graph changes."""
        if self._tensors is None:
            shape = (self._num_actions, self.num_states, self.num_states)
            counts = torch.zeros(shape, dtype=torch.float64)
            sums = torch.zeros(shape, dtype=torch.float64)
            for (i, a), row in self._edges.items():
                for j, (n, total) in row.items():
                    counts[a, i, j] = n
                    sums[a, i, j] = total
            K, alpha = self.num_states, self._smoothing
            totals = counts.sum(-1, keepdim=True) + alpha * K
            smoothed = (counts + alpha) / torch.where(totals > 0, totals, 1.0)
            self_loop = torch.eye(K, dtype=torch.float64).expand_as(counts)
            probabilities = torch.where(totals > 0, smoothed, self_loop)
            default = torch.full_like(sums, self._default_reward)
            rewards = torch.where(counts > 0, sums / counts.clamp(min=1.0), default)
            self._tensors = probabilities, rewards
        return self._tensors

    def count_entries(self) -> tuple[Tensor, Tensor]:
        """The observed counts as sparse entries, without building an ``(A, K, K)`` tensor.

        Returns:
            ``index (3, E)`` long rows ``(i, a, j)`` and ``counts (E,)`` long ``N(m_i, a, m_j)
            > 0``, one entry per observed triple, in first-observed order of ``(i, a)``.
        """
        rows = [(i, a, j, n) for (i, a), row in self._edges.items() for j, (n, _) in row.items()]
        table = torch.tensor(rows, dtype=torch.long).reshape(-1, 4)
        return table[:, :3].T.contiguous(), table[:, 3].contiguous()

    def transition_tensor(self, *, dtype: torch.dtype | None = None) -> Tensor:
        """Action-conditioned transition model ``T[a, i, j] = P(m_j | m_i, a)``.

        Returns:
            ``(A, K, K)`` row-stochastic tensor (a new tensor of the default dtype unless
            ``dtype`` is given), computed in float64.
        """
        probabilities, _ = self._model()
        return probabilities.to(_float_dtype(dtype), copy=True)

    def transition_matrix(
        self, action_probabilities: Tensor | None = None, *, dtype: torch.dtype | None = None
    ) -> Tensor:
        """Transition model marginalized over actions, for the filter's mode transitions.

        ``P(m_j | m_i) = Σ_a π(a | m_i) P(m_j | m_i, a)``.

        Args:
            action_probabilities: ``(A,)`` action distribution, or ``(K, A)`` one per state
                (a policy); ``None`` is uniform.
            dtype: floating dtype of the result (default: torch's default dtype).

        Returns:
            ``(K, K)`` row-stochastic matrix (row = from, column = to).

        Raises:
            ValueError: ``action_probabilities`` has the wrong shape, is negative, or its rows
                do not sum to 1 (within 1e-6).
        """
        A, K = self._num_actions, self.num_states
        if action_probabilities is None:
            policy = torch.full((K, A), 1.0 / A, dtype=torch.float64)
        else:
            check_float("action_probabilities", action_probabilities, trailing=(A,), what=f"({A},)")
            if action_probabilities.shape not in ((A,), (K, A)):
                raise ValueError(
                    f"action_probabilities must have shape ({A},) or ({K}, {A}), "
                    f"got {tuple(action_probabilities.shape)}"
                )
            policy = action_probabilities.to(torch.float64).expand(K, A)
            error = (policy.sum(-1) - 1).abs().max() if K else torch.zeros(())
            if bool((policy < 0).any()) or float(error) > 1e-6:
                raise ValueError("action_probabilities must be >= 0 with rows summing to 1")
        matrix = torch.einsum("ia,aij->ij", policy, self._model()[0])
        return matrix.to(_float_dtype(dtype))

    def reward_tensor(self, *, dtype: torch.dtype | None = None) -> Tensor:
        """Mean rewards ``R[a, i, j]`` of ``(m_i, a, m_j)``; ``default_reward`` where unseen.

        Returns:
            ``(A, K, K)`` tensor (a new tensor of the default dtype unless ``dtype`` is given).
        """
        _, rewards = self._model()
        return rewards.to(_float_dtype(dtype), copy=True)

    def sample(
        self,
        state: ManipulationState,
        action: int,
        *,
        generator: torch.Generator | None = None,
    ) -> tuple[ManipulationState, float]:
        """Draw ``m′ ~ P(· | m, a)`` and its mean reward ``R(m, a, m′)`` (Dyna-Q planning).

        Costs ``O(K)``; :meth:`sample_ids` draws many pairs at once from the cached
        ``(A, K, K)`` model.

        Raises:
            UnknownStateError: ``state`` is unknown (a ``ValueError`` and a ``KeyError``).
            ValueError: ``action`` is not in ``[0, A)``.
        """
        self._check_action(action)
        source = self.index(state)
        row = self._probability_row(source, action)
        target = int(torch.multinomial(row, 1, generator=generator))
        return self._table[target], self.mean_reward(state, action, self._table[target])

    def sample_ids(
        self,
        state_ids: Tensor,
        actions: Tensor,
        *,
        generator: torch.Generator | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Vectorized :meth:`sample` of many ``(m, a)`` pairs given by id.

        Args:
            state_ids: ``(N,)`` long state ids in ``[0, K)``.
            actions: ``(N,)`` long actions in ``[0, A)``.
            generator: CPU source of randomness; ``None`` uses torch's global generator.

        Returns:
            ``next_ids (N,)`` long and ``rewards (N,)`` float64 mean rewards.

        Raises:
            ValueError: wrong shapes, dtypes or out-of-range ids or actions.
        """
        K, A = self.num_states, self._num_actions
        for name, value, high in (("state_ids", state_ids, K), ("actions", actions, A)):
            if not isinstance(value, Tensor) or value.dtype != torch.long or value.ndim != 1:
                raise ValueError(f"{name} must be a (N,) long tensor")
            if value.numel() and (int(value.min()) < 0 or int(value.max()) >= high):
                raise ValueError(f"{name} must lie in [0, {high})")
        if state_ids.shape != actions.shape:
            raise ValueError(
                f"actions must have the shape of state_ids {tuple(state_ids.shape)}, "
                f"got {tuple(actions.shape)}"
            )
        if state_ids.numel() == 0:
            return state_ids.clone(), torch.zeros(0, dtype=torch.float64)
        probabilities, rewards = self._model()
        rows = probabilities[actions, state_ids]
        next_ids = torch.multinomial(rows, 1, generator=generator).squeeze(-1)
        return next_ids, rewards[actions, state_ids, next_ids]

    def _check_action(self, action: int) -> None:
        if isinstance(action, bool) or not isinstance(action, int):
            raise ValueError(f"action must be an int, got {action!r}")
        if not 0 <= action < self._num_actions:
            raise ValueError(f"action must lie in [0, {self._num_actions}), got {action}")

    def to_json(self) -> str:
        """The whole graph as a JSON string; :meth:`from_json` restores it exactly.

        Transitions are stored as ``[m, a, m′, count, reward_sum]`` rows; floats are written
        in their shortest round-trip form, so every count, sum and derived probability or mean
        reward is bit-identical after loading.
        """
        transitions = [
            [i, a, j, n, total]
            for (i, a), row in self._edges.items()
            for j, (n, total) in row.items()
        ]
        data = {
            "format": _FORMAT,
            "version": 1,
            "num_actions": self._num_actions,
            "smoothing": self._smoothing,
            "default_reward": self._default_reward,
            "states": [s.to_json() for s in self._table],
            "transitions": transitions,
        }
        return json.dumps(data)

    @classmethod
    def from_json(cls, text: str | bytes) -> ManipulationGraph:
        """Inverse of :meth:`to_json`.

        Every field is checked at load: ids in ``[0, K)``, actions in ``[0, A)``, counts
        ``>= 1``, finite reward sums, distinct states and transitions.

        Raises:
            ValueError: ``text`` is not JSON or not a saved manipulation graph; the message
                names the field (and the entry) at fault.
        """
        data: Any = parse_json("text", text)
        if not isinstance(data, dict) or data.get("format") != _FORMAT:
            raise ValueError(f"text is not a {_FORMAT} JSON document")

        def field(key: str) -> Any:
            return check_field("text", data, key)

        if data.get("version", 1) != 1 or isinstance(data.get("version"), bool):
            raise ValueError(f"text field 'version' must be 1, got {data.get('version')!r}")
        try:
            graph = cls(
                field("num_actions"),
                smoothing=field("smoothing"),
                default_reward=field("default_reward"),
            )
        except ValueError as error:
            raise ValueError(f"text field {error}") from None
        states = field("states")
        if not isinstance(states, list):
            raise ValueError(f"text field 'states' must be a list, got {type(states).__name__}")
        for k, entry in enumerate(states):
            try:
                state = ManipulationState.from_json(entry)
            except ValueError as error:
                raise ValueError(f"text field 'states'[{k}]: {error}") from None
            if graph.add_state(state) != k:
                raise ValueError(f"text field 'states'[{k}] repeats an earlier state")
        transitions = field("transitions")
        if not isinstance(transitions, list):
            raise ValueError(
                f"text field 'transitions' must be a list, got {type(transitions).__name__}"
            )
        K, A = graph.num_states, graph.num_actions
        for k, row in enumerate(transitions):
            where = f"text field 'transitions'[{k}]"
            if not isinstance(row, list) or len(row) != 5:
                raise ValueError(f"{where} must be [m, a, m', count, reward_sum], got {row!r}")
            i, a, j, n, total = row
            check_int(f"{where} m", i, low=0, high=K)
            check_int(f"{where} a", a, low=0, high=A)
            check_int(f"{where} m'", j, low=0, high=K)
            check_int(f"{where} count", n, low=1, high=2**53)
            total = check_real(f"{where} reward_sum", total)
            entry = graph._edges.setdefault((i, a), {})
            if j in entry:
                raise ValueError(f"{where} repeats the transition ({i}, {a}, {j})")
            entry[j] = [n, total]
        return graph

    def merged(self, key: Callable[[ManipulationState], ManipulationState]) -> ManipulationGraph:
        """A coarser graph in which the states with the same ``key(state)`` become one.

        Counts and reward sums add up: ``N′(M, a, M′) = Σ N(m, a, m′)`` over ``key(m) = M``,
        ``key(m′) = M′``, so the merged model is the empirical model of the same data under
        the coarser abstraction (for instance the contact state alone, to draw a graph of
        thousands of manipulation states). Settings are kept; states appear in the order
        their keys are first met.

        Args:
            key: maps each state to its merged state.

        Raises:
            ValueError: ``key`` returns something other than a :class:`ManipulationState`.
        """
        graph = ManipulationGraph(
            self._num_actions, smoothing=self._smoothing, default_reward=self._default_reward
        )
        ids = [graph.add_state(key(state)) for state in self._table]
        for (i, a), row in self._edges.items():
            merged = graph._edges.setdefault((ids[i], a), {})
            for j, (n, total) in row.items():
                entry = merged.setdefault(ids[j], [0, 0.0])
                entry[0] += n
                entry[1] += total
        return graph

    def save(self, path: str | Path) -> None:
        """Write :meth:`to_json` to ``path``."""
        Path(path).write_text(self.to_json())

    @classmethod
    def load(cls, path: str | Path) -> ManipulationGraph:
        """Read a graph written by :meth:`save`.

        Raises:
            ValueError: ``path`` cannot be read, or see :meth:`from_json`.
        """
        return cls.from_json(read_text_file("path", path))

    def to_networkx(self) -> Any:
        """The graph as a ``networkx.DiGraph`` over state ids.

        Nodes carry ``state``, ``label`` (``str(state)``) and ``visits``. There is one edge
        ``i → j`` per pair with an observed transition under any action, carrying ``count``
        (``Σ_a N(i, a, j)``), ``probability`` (``Σ_a N(i, a, j) / Σ_a N(i, a)``, the empirical
        frequency under the actions taken), ``mean_reward`` (over those transitions) and
        ``counts`` (``{a: N(i, a, j)}``).
        """
        import networkx as nx

        graph = nx.DiGraph()
        visits = dict.fromkeys(range(self.num_states), 0)
        edges: dict[tuple[int, int], dict[str, Any]] = {}
        for (i, a), row in self._edges.items():
            for j, (n, total) in row.items():
                visits[i] += n
                edge = edges.setdefault((i, j), {"count": 0, "reward_sum": 0.0, "counts": {}})
                edge["count"] += n
                edge["reward_sum"] += total
                edge["counts"][a] = n
        for i, state in enumerate(self._table):
            graph.add_node(i, state=state, label=str(state), visits=visits[i])
        for (i, j), edge in edges.items():
            graph.add_edge(
                i,
                j,
                count=edge["count"],
                probability=edge["count"] / visits[i],
                mean_reward=edge["reward_sum"] / edge["count"],
                counts=edge["counts"],
            )
        return graph

    def draw(
        self,
        ax: Any = None,
        *,
        labels: Mapping[int, str] | None = None,
        positions: Mapping[int, Iterable[float]] | None = None,
        seed: int = 0,
    ) -> Any:
        """Draw the graph: node area grows with visits, edge width with probability.

        Each node shows its id; a legend beside the graph maps the ids to the labels, one
        entry ``"id: label"`` per node (labels as long as a contact state's text would
        cover the graph if written on the nodes).

        Args:
            ax: matplotlib ``Axes`` to draw on; ``None`` makes a new figure.
            labels: node labels by id; default ``str(state)``.
            positions: node positions by id; default a spring layout seeded with ``seed``.
            seed: seed of the default layout.

        Returns:
            The ``Axes`` drawn on; ``ax.get_legend()`` is the legend of the node labels.
        """
        import matplotlib.pyplot as plt
        import networkx as nx
        from matplotlib.lines import Line2D

        graph = self.to_networkx()
        if ax is None:
            _, ax = plt.subplots(figsize=(10, 5))
        if positions is None:
            positions = nx.spring_layout(graph, seed=seed)
        if labels is None:
            labels = {i: data["label"] for i, data in graph.nodes(data=True)}
        color = "#9ecae1"
        most = max([v for _, v in graph.nodes(data="visits")] + [1])
        sizes = [300 + 1700 * v / most for _, v in graph.nodes(data="visits")]
        widths = [0.5 + 4.0 * p for _, _, p in graph.edges(data="probability")]
        nx.draw_networkx_nodes(graph, positions, ax=ax, node_size=sizes, node_color=color)
        nx.draw_networkx_edges(
            graph,
            positions,
            ax=ax,
            width=widths,
            node_size=sizes,
            arrowsize=14,
            connectionstyle="arc3,rad=0.12",
        )
        ids = {i: str(i) for i in graph.nodes}
        nx.draw_networkx_labels(graph, positions, labels=ids, ax=ax, font_size=8)
        node = Line2D([], [], ls="", marker="o", markersize=8, color=color)
        ax.legend(
            [node] * graph.number_of_nodes(),
            [f"{i}: {labels.get(i, '')}" for i in graph.nodes],
            title="node labels",
            loc="center left",
            bbox_to_anchor=(1.0, 0.5),
            fontsize=8,
            title_fontsize=9,
            frameon=False,
        )
        ax.margins(0.15)
        ax.set_axis_off()
        return ax
