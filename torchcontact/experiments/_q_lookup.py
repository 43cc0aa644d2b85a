"""Q rows by manipulation-state id, with a nearest-known-state fallback."""

from __future__ import annotations

import torch
from torch import Tensor

from torchcontact.envs import NUM_CONTACT_CLASSES, PegInHoleStates
from torchcontact.rl import DynaQ


class QLookup:
    """The Q values of a :class:`DynaQ` agent indexed by manipulation-state id.

    It maps state ids (true, observed, or a belief's particles) to rows of the agent's Q table;
    the policies act on what it returns (greedy on :meth:`values`, QMDP on
    :meth:`probabilities` with :func:`~torchcontact.rl.qmdp_action`).

    A state the agent never acted from (never visited, or only ever reached) has no Q values
    of its own. With ``nearest`` it borrows the row of the nearest *known* state (acted from,
    or terminal): the smallest L1 distance between pose-cell indices ``(i_x, i_y, i_θ)``
    among the states of the same contact class, or among all known states if the class was
    never acted from; ties go to the lowest agent row. Greedy execution then moves on from
    start poses and contacts that training missed instead of idling on an all-zero row.
    Without ``nearest`` unknown states read as zero.

    Args:
        agent: an agent whose states are keys of ``states`` (``ManipulationState``).
        states: the task's state discretization.
        nearest: let unknown states borrow the nearest known state's row.
    """

    def __init__(self, agent: DynaQ, states: PegInHoleStates, *, nearest: bool = True) -> None:
        self.table = agent.q_table()  # (M, A) float64
        self.row = torch.full((states.num_states,), -1, dtype=torch.long)
        known = [
            i
            for i, s in enumerate(agent.states)
            if agent.is_terminal(s) or agent.action_counts(s).any()
        ]
        ids = torch.tensor([states.index(agent.states[i]) for i in known], dtype=torch.long)  # type: ignore[arg-type]
        self.row[ids] = torch.tensor(known, dtype=torch.long)
        #: ``(num_states,)`` bool: the state has Q values of its own.
        self.known = self.row >= 0
        if nearest and known:
            self._borrow_nearest(states, ids)
        #: Every state has a row (its own or borrowed): every belief has QMDP values.
        self.complete = bool((self.row >= 0).all())

    def _borrow_nearest(self, states: PegInHoleStates, known_ids: Tensor) -> None:
        cells = torch.arange(states.num_cells) * NUM_CONTACT_CLASSES
        cell_index, _ = states.unravel(cells)  # (C, 3)
        known_index, known_contact = states.unravel(known_ids)

        def nearest_of(pool: Tensor) -> Tensor:
            """Per cell, the nearest known id among ``pool``; the first minimum is the lowest
            row."""
            distance = (cell_index.unsqueeze(1) - known_index[pool]).abs().sum(-1)  # (C, K_c)
            return known_ids[pool][distance.argmin(1)]

        any_class: Tensor | None = None  # for classes never acted from
        for contact in range(NUM_CONTACT_CLASSES):
            pool = known_contact == contact
            if bool(pool.any()):
                nearest = nearest_of(pool)
            else:
                if any_class is None:
                    any_class = nearest_of(torch.ones_like(pool))
                nearest = any_class
            ids = cells + contact
            self.row[ids] = torch.where(self.known[ids], self.row[ids], self.row[nearest])

    @property
    def num_rows(self) -> int:
        """``M``, the states the agent knows."""
        return int(self.table.shape[0])

    def values(self, ids: Tensor) -> tuple[Tensor, Tensor]:
        """Q values ``(*B, A)`` of state ids ``(*B,)`` (zero where neither known nor borrowed)
        and the mask ``(*B,)`` of states known in their own right."""
        row = self.row[ids]
        values = torch.where((row >= 0).unsqueeze(-1), self.table[row.clamp(min=0)], 0.0)
        return values, self.known[ids]

    def probabilities(self, ids: Tensor, weights: Tensor) -> Tensor:
        """``(B, M)`` belief over the agent's states from particles ``ids, weights (B, N)``;
        particles in states with no row (unknown, nothing borrowed) are dropped and the rest
        renormalized (all zero if none has a row)."""
        row = self.row[ids]
        w = torch.where(row >= 0, weights, 0.0)
        total = w.sum(-1, keepdim=True)
        w = torch.where(total > 0, w / total.clamp(min=1e-300), 0.0)
        out = torch.zeros(ids.shape[0], self.num_rows, dtype=weights.dtype)
        return out.scatter_add_(1, row.clamp(min=0), w)
