"""The vectorized peg-in-hole environment: ``B`` environments stepped as one tensor batch."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from numpy.typing import NDArray
from torch import Tensor

from torchcontact._checks import check_int
from torchcontact.envs._config import PegInHoleConfig
from torchcontact.envs._observe import (
    OBSERVATION_MODES,
    ObservationMode,
    observation_space,
    observe,
    rewards,
    start_samples,
    summaries,
)
from torchcontact.envs._render import render_environment
from torchcontact.envs._states import PegInHoleStates
from torchcontact.envs._task import ACTION_NAMES, PegInHoleTask, Physics
from torchcontact.states import ContactSet

Observation = NDArray[np.float64] | dict[str, NDArray[Any]]


class PegInHole2DVector(VectorEnv[Observation, NDArray[np.int64], NDArray[Any]]):
    """``num_envs`` copies of :class:`~torchcontact.envs.PegInHole2D` simulated as one batch.

    Every simulator step of all environments is one batched contact solve. Sub-environment
    ``i`` owns its own random generator, seeded with ``seed + i`` by ``reset(seed=seed)`` (or
    with ``seed[i]`` for a list), and draws from it exactly what a single environment reset
    with that seed would draw, so the batch reproduces a loop over single environments.

    Auto-reset follows gymnasium's next-step convention
    (``metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP``): the step that ends an
    episode returns its last observation with ``terminated`` or ``truncated`` set; the next
    call to :meth:`step` ignores that sub-environment's action, resets it and returns its
    first observation with reward 0 and both flags ``False``.

    Episodes are truncated after ``max_episode_steps`` steps (``config.max_steps`` unless
    given; ``gymnasium.make_vec`` passes the spec's, which ``max_episode_steps=`` overrides).

    ``infos`` holds, as arrays with a leading ``num_envs`` axis (each with its ``_key`` mask):
    ``peg_pose``, ``peg_twist``, ``gripper_pose``, ``peg_in_gripper``, ``contact_class``,
    ``manipulation_state_id``, ``tactile_triggered``, the contacts in the peg's ``K`` slots
    (``contact_active``, ``contact_points``, ``contact_normals``, ``contact_impulses``,
    ``contact_partners``; see :class:`PegInHole2D`), ``success`` and ``dropped``.

    Args:
        num_envs: number of environments ``B >= 1``.
        config: the task configuration (default :class:`PegInHoleConfig()`).
        observation: ``"state"`` or ``"noisy"``.
        max_episode_steps: steps before truncation, an int ``>= 1``; ``None`` takes
            ``config.max_steps``.
        render_mode: ``None`` or ``"rgb_array"`` (:meth:`render` returns one frame per
            sub-environment).

    Raises:
        ValueError: an argument is invalid (the message names it).
    """

    # gymnasium declares ``metadata`` as a plain class attribute, not a ClassVar.
    metadata: dict[str, Any] = {  # noqa: RUF012
        "autoreset_mode": AutoresetMode.NEXT_STEP,
        "render_modes": ["rgb_array"],
        "render_fps": 50,
    }

    def __init__(
        self,
        *,
        num_envs: int,
        config: PegInHoleConfig | None = None,
        observation: ObservationMode = "state",
        max_episode_steps: int | None = None,
        render_mode: str | None = None,
    ) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be an int >= 1, got {num_envs!r}")
        config = PegInHoleConfig() if config is None else config
        if not isinstance(config, PegInHoleConfig):
            raise ValueError(f"config must be a PegInHoleConfig, got {type(config).__name__}")
        if observation not in OBSERVATION_MODES:
            raise ValueError(f"observation must be 'state' or 'noisy', got {observation!r}")
        if max_episode_steps is None:
            max_episode_steps = config.max_steps
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.num_envs = num_envs
        self.max_episode_steps = check_int("max_episode_steps", max_episode_steps, low=1)
        self.render_mode = render_mode
        self.config = config
        self.observation_mode: ObservationMode = observation
        self.task = PegInHoleTask(config)
        self.single_action_space = spaces.Discrete(len(ACTION_NAMES))
        self.action_space = spaces.MultiDiscrete(np.full(num_envs, len(ACTION_NAMES)))
        self.single_observation_space = observation_space(self.task, observation)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self._rngs: list[np.random.Generator] | None = None
        self._physics: Physics | None = None
        self._steps = np.zeros(num_envs, dtype=np.int64)
        self._autoreset = np.zeros(num_envs, dtype=bool)

    @property
    def states(self) -> PegInHoleStates:
        """The manipulation-state discretization."""
        return self.task.states

    @property
    def physics(self) -> Physics:
        """The current batched physical state.

        Raises:
            RuntimeError: before the first :meth:`reset`.
        """
        if self._physics is None:
            raise RuntimeError("call reset() before using the environment")
        return self._physics

    def reset(
        self,
        *,
        seed: int | Sequence[int | None] | None = None,
        options: dict[str, Any] | None = None,
    ) -> tuple[Observation, dict[str, Any]]:
        """Reset every sub-environment.

        Args:
            seed: ``None`` (keep the generators, or seed them from entropy the first time), an
                int (sub-environment ``i`` gets ``seed + i``) or one seed per sub-environment.
            options: start values fixed for every sub-environment (see :class:`PegInHole2D`).
        """
        B = self.num_envs
        if seed is None:
            seeds: list[int | None] | None = None if self._rngs is not None else [None] * B
        elif isinstance(seed, bool):
            raise ValueError(f"seed must be an int, a sequence of ints or None, got {seed!r}")
        elif isinstance(seed, int):
            seeds = [seed + i for i in range(B)]
        else:
            seeds = list(seed)
            if len(seeds) != B:
                raise ValueError(f"seed must hold {B} seeds (num_envs), got {len(seeds)}")
        if seeds is not None:
            self._rngs = [seeding.np_random(s)[0] for s in seeds]
        rngs = self._generators()
        self._physics = self.task.reset(start_samples(self.task, rngs, options))
        self._steps[:] = 0
        self._autoreset[:] = False
        return self._report(self._physics, rngs)

    def step(
        self, actions: NDArray[np.int64]
    ) -> tuple[Observation, NDArray[Any], NDArray[Any], NDArray[Any], dict[str, Any]]:
        """Step every sub-environment (auto-resetting those that ended on the last step).

        Args:
            actions: ``(num_envs,)`` integer array of actions in ``[0, 7)``.

        Raises:
            ValueError: ``actions`` is not an integer array of that shape and range (floats,
                bools and strings are refused, not cast).
            RuntimeError: :meth:`reset` was never called.
        """
        physics = self.physics
        rngs = self._generators()
        B = self.num_envs
        message = f"actions must be {B} ints in [0, {len(ACTION_NAMES)}), got {actions!r}"
        try:
            action = np.asarray(actions)
        except ValueError as error:  # a ragged sequence
            raise ValueError(message) from error
        # Integers only: a cast would truncate 2.5 to 2 and read "1" or True as actions.
        integral = np.issubdtype(action.dtype, np.integer)
        if action.shape != (B,) or not integral:
            raise ValueError(message)
        action = action.astype(np.int64)
        if not self.action_space.contains(action):
            raise ValueError(message)
        resetting = self._autoreset.copy()
        stepping = ~resetting
        moved = torch.from_numpy(np.flatnonzero(stepping))
        if resetting.any():
            if moved.numel():
                sub = self.task.step(physics.index(moved), torch.from_numpy(action[stepping]))
                physics = physics.put(moved, sub)
            restarted = np.flatnonzero(resetting)
            samples = start_samples(self.task, [rngs[i] for i in restarted], None)
            physics = physics.put(torch.from_numpy(restarted), self.task.reset(samples))
            self._steps[resetting] = 0
        else:
            physics = self.task.step(physics, torch.from_numpy(action.astype(np.int64)))
        self._physics = physics
        self._steps[stepping] += 1
        observation, infos = self._report(physics, rngs)
        success, dropped = infos["success"], infos["dropped"]
        reward = np.where(stepping, rewards(self.task, success, dropped), 0.0)
        terminated = stepping & (success | dropped)
        truncated = stepping & ~terminated & (self._steps >= self.max_episode_steps)
        self._autoreset = terminated | truncated
        return observation, reward, terminated, truncated, infos

    def render(self) -> tuple[NDArray[np.uint8], ...] | None:
        """One RGB image per sub-environment (``render_mode="rgb_array"``), else ``None``.

        Raises:
            RuntimeError: :meth:`reset` was never called.
        """
        if self.render_mode != "rgb_array":
            return None
        physics = self.physics
        return tuple(render_environment(self.task, physics, i) for i in range(self.num_envs))

    def peg_contacts(self) -> ContactSet:
        """The peg's contacts of the last simulator step, batch ``(num_envs,)``."""
        return self.task.peg_contacts(self.physics)

    def manipulation_state_of(
        self, peg_pose: Tensor, contacts: ContactSet | Tensor | int | None = None
    ) -> Tensor:
        """Manipulation-state ids of peg poses (see :meth:`PegInHole2D.manipulation_state_of`)."""
        return self.states.ids(peg_pose, contacts)

    def _generators(self) -> list[np.random.Generator]:
        if self._rngs is None:
            raise RuntimeError("call reset() before using the environment")
        return self._rngs

    def _report(
        self, physics: Physics, rngs: list[np.random.Generator]
    ) -> tuple[Observation, dict[str, Any]]:
        """Observations and infos of the batch (draws the observation noise)."""
        batch = summaries(self.task, physics, self.task.peg_contacts(physics))
        observation = observe(
            self.task, physics, rngs, self.observation_mode, triggered=batch["tactile_triggered"]
        )
        infos: dict[str, Any] = {}
        mask = np.ones(self.num_envs, dtype=bool)
        for key, value in batch.items():
            infos[key] = value
            infos[f"_{key}"] = mask.copy()
        return observation, infos
