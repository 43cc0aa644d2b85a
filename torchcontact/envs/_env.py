"""The single planar peg-in-hole environment."""

from __future__ import annotations

from typing import Any, SupportsFloat

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from numpy.typing import NDArray
from torch import Tensor

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
from torchcontact.states import ContactSet, ManipulationState, contact_states

Observation = NDArray[np.float64] | dict[str, NDArray[Any]]


class PegInHole2D(gym.Env[Observation, Any]):
    """Planar peg-in-hole with a friction grasp, on the LCP contact simulator.

    **Scene** (vertical plane, gravity ``−y``; :func:`~torchcontact.envs.build_scene`): a
    table, two static blocks whose facing sides form a hole of width ``peg_width +
    clearance`` centred on ``x = 0`` (its mouth at ``y = hole_depth``, optionally chamfered by
    cutting the blocks' mouth corners at 45°), a rectangular dynamic peg, and two *dynamic*
    fingers that taper to short flat pads.

    **Grasp.** Two velocity-driven (kinematic) fingers cannot squeeze anything in a rigid LCP:
    with no penetration the normal impulse between them and the peg is indeterminate, and two
    inward velocities make the problem infeasible. So the gripper is a virtual frame moved
    kinematically by the actions, and each finger is a dynamic body (``finger_mass``, with a
    rotational inertia ``finger_inertia`` standing for its mount) pushed by applied forces (the
    simulator's ``force`` input): an implicit PD servo toward the gripper frame (along the
    fingers, in angle, and for the jaws' centre along the closing axis), a constant grip force
    ``grip_force`` toward the other finger, and compensation of its own weight
    (:meth:`PegInHoleTask.servo_forces`). With the defaults the servo's static stiffness is
    ``m ω² / (1 + ω²h² + 2ζωh) ≈ 1800 N/m`` per finger. The peg is held only by friction at the
    pads, which touch its sides at their two corners: it slides along the pads when pushed
    along them harder than ``2 μ grip_force`` (4.8 N by default, minus its weight), and it
    turns in the grasp when a contact pushes it with more torque about the pads than their
    friction resists (of order ``μ grip_force peg_width``), e.g. a tilted peg pressed onto a
    surface or a peg pushed sideways against the hole's wall. Physics runs in float64 on the
    CPU.

    **Actions** (``Discrete(7)``, :data:`ACTION_NAMES`): stay, gripper ``±x``, ``±y``
    (``move_step``), ``±θ`` (``turn_step``); one environment step moves the gripper at
    constant twist over ``substeps`` simulator steps of length ``h`` (targets are clamped to
    the workspace).

    **Episode.** ``reset(seed=..., options=...)`` draws the gripper's start and the peg's
    offset and tilt in the grasp (``options`` may fix any of
    ``gripper_x, peg_height, gripper_angle, grasp_offset, grasp_angle``), then lets the grasp
    settle for ``settle_steps`` simulator steps. Each step costs ``step_cost``; reaching the
    insertion depth ends the episode (``terminated``) with ``success_reward``; losing the peg
    from the grasp ends it with ``−drop_penalty``. The time limit follows gymnasium's
    convention: the environment itself never truncates; ``gymnasium.make`` wraps it in
    ``TimeLimit`` with the spec's ``max_episode_steps`` (registered as
    ``PegInHoleConfig().max_steps``, 200; ``gymnasium.make(..., max_episode_steps=n)`` sets
    another), and a directly constructed environment needs
    ``gymnasium.wrappers.TimeLimit(env, n)`` for one.

    **Observations** (``observation=``): ``"state"`` is the true state (peg pose and twist,
    gripper pose, ``(9,)``) for oracle runs; ``"noisy"`` is a dict of the peg pose seen by
    vision with Gaussian noise (``pose_noise_std``), the gripper pose and binary tactile
    readings of sensors on the peg's sides with false-positive and false-negative rates.

    **Observation bounds** follow from the task's geometry (workspace, starts, the grasp's
    reach; :func:`~torchcontact.envs.observation_bounds`); observations are clipped to them,
    which only the last step of an episode that drops the peg can reach.

    **Info** (fixed shapes, so that gymnasium's sync and async vectorizers stack it):
    ``peg_pose``, ``peg_twist``, ``gripper_pose``, ``peg_in_gripper`` (the peg's pose in the
    gripper frame), ``contact_class`` and ``manipulation_state_id`` (ints),
    ``manipulation_state`` (a hashable :class:`~torchcontact.states.ManipulationState`),
    ``contact_state`` (the peg's full :class:`~torchcontact.states.ContactState` on a
    :class:`~torchcontact.states.FeatureGrid` of ``contact_radius``, ``contact_angle``), the
    contacts in the peg's ``K`` slots of the scene: ``contact_active`` ``(K,)`` (the slots
    that carry an impulse) and, zero (``""``) in the other slots, ``contact_points`` /
    ``contact_normals`` ``(K, 2)`` (world frame, normals into the peg) /
    ``contact_impulses`` ``(K,)`` / ``contact_partners`` ``(K,)`` (body names), the
    noise-free ``tactile_triggered``, and ``success`` / ``dropped``. :meth:`peg_contacts`
    returns the contacts as a :class:`~torchcontact.states.ContactSet`.

    **Manipulation states** (:attr:`states`): the peg's pose relative to the hole on a grid
    that is fine near the mouth and coarse far away, times a contact class of the peg with the
    fingers and with the hole; :meth:`manipulation_state_of` maps a batch of (estimated) poses
    to integer ids.

    Args:
        config: the task configuration (default :class:`PegInHoleConfig()`).
        observation: ``"state"`` or ``"noisy"``.
        render_mode: ``None`` or ``"rgb_array"``.

    Raises:
        ValueError: an argument is invalid (the message names it).
    """

    # gymnasium declares ``metadata`` as a plain class attribute, not a ClassVar.
    metadata: dict[str, Any] = {"render_modes": ["rgb_array"], "render_fps": 50}  # noqa: RUF012

    def __init__(
        self,
        *,
        config: PegInHoleConfig | None = None,
        observation: ObservationMode = "state",
        render_mode: str | None = None,
    ) -> None:
        config = PegInHoleConfig() if config is None else config
        if not isinstance(config, PegInHoleConfig):
            raise ValueError(f"config must be a PegInHoleConfig, got {type(config).__name__}")
        if observation not in OBSERVATION_MODES:
            raise ValueError(f"observation must be 'state' or 'noisy', got {observation!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.config = config
        self.observation_mode: ObservationMode = observation
        self.render_mode = render_mode
        self.task = PegInHoleTask(config)
        self.action_space = spaces.Discrete(len(ACTION_NAMES))
        self.observation_space = observation_space(self.task, observation)
        self._physics: Physics | None = None

    @property
    def states(self) -> PegInHoleStates:
        """The manipulation-state discretization."""
        return self.task.states

    @property
    def physics(self) -> Physics:
        """The current batched (``B = 1``) physical state.

        Raises:
            RuntimeError: before the first :meth:`reset`.
        """
        if self._physics is None:
            raise RuntimeError("call reset() before using the environment")
        return self._physics

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Observation, dict[str, Any]]:
        """Start an episode.

        Args:
            seed: seeds the environment's generator (start pose, grasp, observation noise).
            options: start values to fix instead of drawing them, any of ``START_KEYS``
                (``gripper_x`` and ``gripper_angle`` of the gripper, ``peg_height`` of the
                peg's bottom above the mouth, ``grasp_offset`` from the pads down to the peg's
                centre, ``grasp_angle`` of the peg relative to the fingers); the draws happen
                anyway, so the random stream does not depend on the options.

        Returns:
            The first observation and the info (see the class docstring).

        Raises:
            ValueError: ``options`` holds an unknown key or a non-finite value.
        """
        super().reset(seed=seed)
        samples = start_samples(self.task, [self.np_random], options)
        self._physics = self.task.reset(samples)
        return self._report()

    def step(self, action: Any) -> tuple[Observation, SupportsFloat, bool, bool, dict[str, Any]]:
        """Move the gripper by one action and simulate ``substeps`` simulator steps.

        Args:
            action: an int in ``[0, 7)`` (:data:`ACTION_NAMES`).

        Returns:
            ``(observation, reward, terminated, truncated, info)``; ``truncated`` is always
            ``False`` here: the time limit is gymnasium's ``TimeLimit`` wrapper's.

        Raises:
            ValueError: ``action`` is not a valid action.
            RuntimeError: :meth:`reset` was never called.
        """
        if isinstance(action, (bool, np.bool_)) or not self.action_space.contains(action):
            raise ValueError(f"action must be an int in [0, {len(ACTION_NAMES)}), got {action!r}")
        physics = self.physics
        actions = torch.tensor([int(action)], dtype=torch.long)
        self._physics = self.task.step(physics, actions)
        observation, info = self._report()
        success, dropped = bool(info["success"]), bool(info["dropped"])
        reward = float(rewards(self.task, np.array([success]), np.array([dropped]))[0])
        terminated = success or dropped
        return observation, reward, terminated, False, info

    def render(self) -> NDArray[np.uint8] | None:
        """An RGB image of the scene (``render_mode="rgb_array"``), else ``None``."""
        if self.render_mode != "rgb_array":
            return None
        return render_environment(self.task, self.physics, 0)

    def peg_contacts(self) -> ContactSet:
        """The peg's contacts of the last simulator step (batch shape ``()``, world frame)."""
        return self.task.peg_contacts(self.physics)[0]

    def manipulation_state_of(
        self, peg_pose: Tensor, contacts: ContactSet | Tensor | int | None = None
    ) -> Tensor:
        """Manipulation-state ids of peg poses, e.g. a filter's ``(N, 3)`` particles.

        Args:
            peg_pose: ``(*B, 3)`` peg poses, world frame.
            contacts: contact classes (a :class:`ContactSet` of batch ``*B``, class ids, or
                ``None`` for a firm grasp without other contact); see
                :meth:`PegInHoleStates.ids`.

        Returns:
            ``(*B,)`` long ids; :meth:`manipulation_state_key` maps them to hashable states.
        """
        return self.states.ids(peg_pose, contacts)

    def manipulation_state_key(self, state_id: int) -> ManipulationState:
        """The hashable manipulation state of an id (see :meth:`PegInHoleStates.key`)."""
        return self.states.key(state_id)

    def _report(self) -> tuple[Observation, dict[str, Any]]:
        """The observation and info of the current state (draws the observation noise)."""
        physics = self.physics
        contacts = self.task.peg_contacts(physics)
        batch = summaries(self.task, physics, contacts)
        observation = observe(
            self.task,
            physics,
            [self.np_random],
            self.observation_mode,
            triggered=batch["tactile_triggered"],
        )
        info: dict[str, Any] = {key: value[0].copy() for key, value in batch.items()}
        for key in ("contact_class", "manipulation_state_id"):
            info[key] = int(info[key])
        for key in ("success", "dropped"):
            info[key] = bool(info[key])
        info["manipulation_state"] = self.states.key(info["manipulation_state_id"])
        info["contact_state"] = contact_states(contacts, self.task.contact_grid)[0]
        return _first(observation), info


def _first(observation: Observation) -> Observation:
    if isinstance(observation, dict):
        return {key: value[0].copy() for key, value in observation.items()}
    first: NDArray[np.float64] = observation[0].copy()
    return first
