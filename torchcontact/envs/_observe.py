"""Observations, rewards and info of the peg-in-hole task, batched over environments."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
import torch
from gymnasium import spaces
from numpy.typing import NDArray

from torchcontact.envs._config import PegInHoleConfig
from torchcontact.envs._states import contact_classes
from torchcontact.envs._task import NUM_START_SAMPLES, PEG, PegInHoleTask, Physics
from torchcontact.states import ContactSet

ObservationMode = Literal["state", "noisy"]
OBSERVATION_MODES = ("state", "noisy")
#: Keys of ``options`` in ``reset`` that fix a start value, in the order of the samples.
START_KEYS = ("gripper_x", "peg_height", "gripper_angle", "grasp_offset", "grasp_angle")


def observation_space(task: PegInHoleTask, mode: ObservationMode) -> spaces.Space[Any]:
    """The observation space of one environment, bounded by :func:`observation_bounds`.

    ``"state"``: a ``(9,)`` float64 box, peg pose ``(x, y, θ)``, peg twist ``(vx, vy, ω)`` and
    gripper pose, world frame. ``"noisy"``: a dict of the peg pose seen by vision with Gaussian
    noise (``"peg_pose"``, ``(3,)``), the gripper pose (``"gripper_pose"``, exact:
    proprioception) and the tactile readings (``"tactile"``, ``(S,)`` int8 0/1).
    """
    bounds = observation_bounds(task.config)
    if mode == "state":
        low, high = (np.concatenate([b[i] for b in bounds.values()]) for i in (0, 1))
        return spaces.Box(low, high, dtype=np.float64)
    return spaces.Dict(
        {
            "peg_pose": spaces.Box(*bounds["peg_pose"], dtype=np.float64),
            "gripper_pose": spaces.Box(*bounds["gripper_pose"], dtype=np.float64),
            "tactile": spaces.MultiBinary(task.sensors.num_sensors),
        }
    )


def observation_bounds(
    config: PegInHoleConfig,
) -> dict[str, tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """``(low, high)`` bounds, ``(3,)`` each, of the observed peg pose, peg twist and gripper pose.

    They follow from the task's geometry (world frame, SI units):

    * gripper ``G``: the hull of the workspace and of the starts. Reset places the gripper at
      ``x ∈ start_x``, angle ``∈ start_angle`` and
      ``y = hole_depth + height + (offset + peg_height/2) cos(peg angle)``
      (:meth:`PegInHoleTask.initial_state`; ``height ∈ start_height``,
      ``offset ∈ grasp_offset``, peg angle ``∈ start_angle + grasp_angle``); every step
      clamps its target into the workspace.
    * peg position: ``G`` widened by twice the reach ``r = hypot(peg_height/2, peg_width/2 +
      finger_width)`` of the grasp. A held peg's centre lies within ``r`` of the gripper
      (:meth:`PegInHoleTask.outcome` calls it dropped beyond), and the step that drops it
      ends the episode; the second ``r`` is that step's travel.
    * peg angle: ``G``'s angles widened by ``π/2``: the peg turns at most ``π/4`` in a grasp
      that holds it, plus the step that drops it.
    * peg twist: ``±(2 r / τ + v_G)`` linear and ``±(π/2 / τ + ω_G)`` angular, with
      ``τ = substeps · h`` the step's duration and ``v_G = √2 move_step / τ``,
      ``ω_G = turn_step / τ`` the gripper's speeds: a peg moving faster relative to the
      gripper would cross the whole grasp within one step.

    Observations are clipped to these bounds (:func:`observe`), which a peg in the grasp stays
    well inside (e.g. ``|v| ≈ 0.15 m/s``, ``|ω| ≈ 1.8 rad/s`` over random-action episodes with
    the default config, against bounds of 9.1 m/s and 80 rad/s); only the last step of an
    episode that drops the peg can reach them. Non-finite values (a failed simulator step,
    which also ends the episode) are left as they are.

    Args:
        config: the task configuration.

    Returns:
        ``{"peg_pose": ..., "peg_twist": ..., "gripper_pose": ...}``, in the order of the
        ``"state"`` observation.
    """
    c = config
    half_h = c.peg_height / 2
    # The start's peg angle lies in start_angle + grasp_angle; its cosine is least at the end
    # farthest from 0 (or -1 past π).
    farthest = max(abs(a + b) for a, b in zip(c.start_angle, c.grasp_angle, strict=True))
    least_cos = math.cos(min(farthest, math.pi))
    lowest_start = (
        c.hole_depth
        + c.start_height[0]
        + least_cos * (c.grasp_offset[0 if least_cos >= 0 else 1] + half_h)
    )
    highest_start = c.hole_depth + c.start_height[1] + c.grasp_offset[1] + half_h
    gripper_low = np.array(
        [
            min(c.workspace_x[0], c.start_x[0]),
            min(c.workspace_y[0], lowest_start),
            min(c.workspace_angle[0], c.start_angle[0]),
        ]
    )
    gripper_high = np.array(
        [
            max(c.workspace_x[1], c.start_x[1]),
            max(c.workspace_y[1], highest_start),
            max(c.workspace_angle[1], c.start_angle[1]),
        ]
    )
    reach = math.hypot(half_h, c.peg_width / 2 + c.finger_width)
    widen = np.array([2 * reach, 2 * reach, math.pi / 2])
    tau = c.substeps * c.h
    speed = 2 * reach / tau + math.sqrt(2) * c.move_step / tau
    spin = (math.pi / 2) / tau + c.turn_step / tau
    twist = np.array([speed, speed, spin])
    return {
        "peg_pose": (gripper_low - widen, gripper_high + widen),
        "peg_twist": (-twist, twist),
        "gripper_pose": (gripper_low, gripper_high),
    }


def start_samples(
    task: PegInHoleTask,
    rngs: Sequence[np.random.Generator],
    options: Mapping[str, Any] | None,
) -> torch.Tensor:
    """Draw the starts of environments from their generators, then apply ``options``.

    Every start draws the same numbers whatever the options, so fixing one value leaves the
    random streams unchanged.

    Raises:
        ValueError: ``options`` holds an unknown key or a non-finite value.
    """
    rows = np.stack([task.sample_start(rng) for rng in rngs])
    if options:
        unknown = set(options) - set(START_KEYS)
        if unknown:
            raise ValueError(
                f"options holds unknown keys {sorted(unknown)}; known: {list(START_KEYS)}"
            )
        for column, key in enumerate(START_KEYS):
            if key in options:
                value = np.broadcast_to(np.asarray(options[key], dtype=np.float64), len(rngs))
                if not np.isfinite(value).all():
                    raise ValueError(f"options[{key!r}] must be finite, got {options[key]!r}")
                rows[:, column] = value
    assert rows.shape[1] == NUM_START_SAMPLES
    return torch.from_numpy(rows)


def observe(
    task: PegInHoleTask,
    physics: Physics,
    rngs: Sequence[np.random.Generator],
    mode: ObservationMode,
    *,
    triggered: NDArray[np.bool_],
) -> NDArray[np.float64] | dict[str, NDArray[Any]]:
    """Batched observations of ``B`` environments (noise drawn from each one's generator).

    Poses and twists are clipped to :func:`observation_bounds`. Each environment draws, in
    order, 3 normals (pose noise) and ``S`` uniforms (tactile noise) in ``"noisy"`` mode,
    nothing in ``"state"`` mode. In ``"noisy"`` mode the camera's ``peg_pose`` is NaN (all
    three components) where the peg is :func:`occluded` (the noise is drawn anyway, so the
    random streams do not depend on the occlusion).

    Args:
        task: the task.
        physics: the batch, ``B`` entries.
        rngs: the ``B`` generators.
        mode: the observation mode.
        triggered: ``(B, S)`` noise-free tactile readings (``summaries(...)["tactile_triggered"]``).
    """
    c = task.config
    bounds = observation_bounds(c)
    if mode == "state":
        low, high = (np.concatenate([b[i] for b in bounds.values()]) for i in (0, 1))
        return np.clip(task.state_vector(physics), low, high)
    S = task.sensors.num_sensors
    normals = np.stack([rng.normal(size=3) for rng in rngs])
    uniforms = np.stack([rng.random(S) for rng in rngs])
    peg = physics.state.q[:, PEG].numpy()
    noisy = peg + normals * np.asarray(c.pose_noise_std)
    noisy[occluded(task, physics)] = np.nan
    probability = task.sensors.reading_probability(torch.from_numpy(triggered)).numpy()
    readings = (uniforms < probability).astype(np.int8)
    return {
        "peg_pose": np.clip(noisy.astype(np.float64), *bounds["peg_pose"]),
        "gripper_pose": np.clip(physics.gripper.numpy(), *bounds["gripper_pose"]),
        "tactile": readings,
    }


def occluded(task: PegInHoleTask, physics: Physics) -> NDArray[np.bool_]:
    """``(B,)`` whether the camera loses the peg: its bottom centre lies within
    ``occlusion_radius`` of the centre of the hole's mouth (never when the radius is 0)."""
    peg = physics.state.q[:, PEG]
    finite = torch.isfinite(peg).all(-1)  # a failed step's pose: left to the camera as it is
    relative = task.states.relative_pose(torch.where(finite[:, None], peg, 0.0))
    distance = torch.hypot(relative[:, 0], relative[:, 1])
    hidden: NDArray[np.bool_] = (finite & (distance < task.config.occlusion_radius)).numpy()
    return hidden


def summaries(
    task: PegInHoleTask, physics: Physics, contacts: ContactSet
) -> dict[str, NDArray[Any]]:
    """Batched ground truth: poses, twist, contact class, manipulation state, contacts, flags.

    Every entry has a fixed shape ``(B, ...)``, so single environments' infos stack (gymnasium's
    vectorizers). The peg's contacts fill its ``K`` slots of the scene
    (``contacts.points.shape[-2]``): ``contact_active`` ``(B, K)`` marks the slots that carry
    an impulse, and ``contact_points`` ``(B, K, 2)``, ``contact_normals`` ``(B, K, 2)`` (world
    frame, into the peg), ``contact_impulses`` ``(B, K)`` and ``contact_partners`` ``(B, K)``
    (body names) are zero (``""``) in the other slots.

    Args:
        task: the task.
        physics: the batch.
        contacts: ``task.peg_contacts(physics)``.
    """
    classes = contact_classes(contacts)
    peg = physics.state.q[:, PEG]
    ids = task.states.ids(peg, classes)
    success, dropped = task.outcome(physics)
    active = contacts.active
    # Body names as Python strings in an object array: gymnasium compares a numpy str array
    # as numbers (``np.allclose``) in its checker.
    names = np.array([task.scene.bodies[i].name for i in contacts.partner.tolist()], dtype=object)
    return {
        "contact_active": active.numpy().copy(),
        "contact_points": torch.where(active[..., None], contacts.points, 0.0).numpy(),
        "contact_normals": torch.where(active[..., None], contacts.normals, 0.0).numpy(),
        "contact_impulses": torch.where(active, contacts.pn, 0.0).numpy(),
        "contact_partners": np.where(active.numpy(), names, "").astype(object),
        "peg_pose": peg.numpy().copy(),
        "peg_twist": physics.state.v[:, PEG].numpy().copy(),
        "gripper_pose": physics.gripper.numpy().copy(),
        "peg_in_gripper": task.peg_in_gripper(physics).numpy().copy(),
        "contact_class": classes.numpy().copy(),
        "manipulation_state_id": ids.numpy().copy(),
        "tactile_triggered": task.sensors.triggered(contacts).numpy().copy(),
        "success": success.numpy().copy(),
        "dropped": dropped.numpy().copy(),
    }


def rewards(task: PegInHoleTask, success: NDArray[Any], dropped: NDArray[Any]) -> NDArray[Any]:
    """``−step_cost + success_reward · success − drop_penalty · dropped``, ``(B,)`` float64."""
    c = task.config
    value = -c.step_cost + c.success_reward * success - c.drop_penalty * dropped
    return np.asarray(value, dtype=np.float64)
