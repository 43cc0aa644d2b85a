"""Small test worlds for the RL tests, each with an exact solution computed independently."""

from __future__ import annotations

from collections import deque

import numpy as np

from torchcontact.rl import DynaQ

Cell = tuple[int, int]

# Actions: up, down, left, right.
MOVES = ((-1, 0), (1, 0), (0, -1), (0, 1))

MAZE = (
    "S....",
    ".###.",
    "...#.",
    ".#...",
    ".#.#G",
)


class GridWorld:
    """A deterministic maze: ``#`` walls, start ``S``, goal ``G``, reward −1 per step.

    Moving into a wall or off the grid leaves the agent in place. Reaching the goal ends the
    episode. With ``slip > 0`` the move goes in a uniformly random direction with that
    probability (drawn from the generator passed to :meth:`step`).
    """

    def __init__(self, maze: tuple[str, ...] = MAZE, slip: float = 0.0) -> None:
        self.rows, self.cols = len(maze), len(maze[0])
        self.walls = {
            (r, c) for r in range(self.rows) for c in range(self.cols) if maze[r][c] == "#"
        }
        self.start = self._find(maze, "S")
        self.goal = self._find(maze, "G")
        self.slip = slip
        self.cells = [
            (r, c) for r in range(self.rows) for c in range(self.cols) if (r, c) not in self.walls
        ]

    @staticmethod
    def _find(maze: tuple[str, ...], mark: str) -> Cell:
        return next((r, c) for r, row in enumerate(maze) for c, x in enumerate(row) if x == mark)

    def move(self, cell: Cell, action: int) -> Cell:
        """The deterministic result of ``action`` in ``cell``."""
        r, c = cell[0] + MOVES[action][0], cell[1] + MOVES[action][1]
        if not (0 <= r < self.rows and 0 <= c < self.cols) or (r, c) in self.walls:
            return cell
        return (r, c)

    def step(
        self, cell: Cell, action: int, rng: np.random.Generator | None = None
    ) -> tuple[Cell, float, bool]:
        """``(next cell, reward, terminal)``."""
        if self.slip and rng is not None and rng.random() < self.slip:
            action = int(rng.integers(4))
        nxt = self.move(cell, action)
        return nxt, -1.0, nxt == self.goal

    def shortest_path(self) -> int:
        """Breadth-first search: the fewest moves from start to goal."""
        distance = {self.start: 0}
        queue = deque([self.start])
        while queue:
            cell = queue.popleft()
            for action in range(4):
                nxt = self.move(cell, action)
                if nxt not in distance:
                    distance[nxt] = distance[cell] + 1
                    queue.append(nxt)
        return distance[self.goal]

    def optimal_q(self, gamma: float, sweeps: int = 500) -> dict[Cell, np.ndarray]:
        """Exact value iteration on the deterministic maze: ``Q*(cell, ·)``."""
        value = dict.fromkeys(self.cells, 0.0)
        q: dict[Cell, np.ndarray] = {}
        for _ in range(sweeps):
            for cell in self.cells:
                if cell == self.goal:
                    q[cell] = np.zeros(4)
                    continue
                row = []
                for action in range(4):
                    nxt = self.move(cell, action)
                    row.append(-1.0 + (0.0 if nxt == self.goal else gamma * value[nxt]))
                q[cell] = np.array(row)
            value = {cell: float(q[cell].max()) for cell in self.cells}
        return q


def greedy_rollout(world: GridWorld, agent: DynaQ, cap: int = 50) -> list[Cell]:
    """Cells visited by the agent's greedy policy from the start, stopping at the goal or
    after ``cap`` moves."""
    cell, path = world.start, [world.start]
    for _ in range(cap):
        if cell == world.goal:
            break
        cell = world.move(cell, agent.greedy(cell))
        path.append(cell)
    return path


def run_episode(
    world: GridWorld, agent: DynaQ, rng: np.random.Generator | None = None, cap: int = 500
) -> int:
    """One ε-greedy training episode from the start; returns the number of steps."""
    cell = world.start
    for t in range(1, cap + 1):
        action = agent.act(cell)
        nxt, reward, terminal = world.step(cell, action, rng)
        agent.observe(cell, action, reward, nxt, terminal)
        cell = nxt
        if terminal:
            return t
    return cap
