"""Observations, rewards and info of the peg-in-hole task, batched over environments."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np
import torch
from gymnasium import spaces
from numpy.typing import NDArray

from torchcontact.envs._states import contact_classes
from torchcontact.envs._task import NUM_START_SAMPLES, PEG, PegInHoleTask, Physics
from torchcontact.states import ContactSet

ObservationMode = Literal["state", "noisy"]
OBSERVATION_MODES = ("state", "noisy")
#: Keys of ``options`` in ``reset`` that fix a start value, in the order of the samples.
START_KEYS = ("gripper_x", "peg_height", "gripper_angle", "grasp_offset", "grasp_angle")


def observation_space(task: PegInHoleTask, mode: ObservationMode) -> spaces.Space[Any]:
    """The observation space of one environment.

    ``"state"``: a ``(9,)`` float64 box, peg pose ``(x, y, θ)``, peg twist ``(vx, vy, ω)`` and
    gripper pose, world frame. ``"noisy"``: a dict of the peg pose seen by vision with Gaussian
    noise (``"peg_pose"``, ``(3,)``), the gripper pose (``"gripper_pose"``, exact:
    proprioception) and the tactile readings (``"tactile"``, ``(S,)`` int8 0/1).
    """
    if mode == "state":
        return spaces.Box(-np.inf, np.inf, shape=(9,), dtype=np.float64)
    pose = spaces.Box(-np.inf, np.inf, shape=(3,), dtype=np.float64)
    return spaces.Dict(
        {
            "peg_pose": pose,
            "gripper_pose": spaces.Box(-np.inf, np.inf, shape=(3,), dtype=np.float64),
            "tactile": spaces.MultiBinary(task.sensors.num_sensors),
        }
    )


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

    Each environment draws, in order, 3 normals (pose noise) and ``S`` uniforms (tactile
    noise) in ``"noisy"`` mode, nothing in ``"state"`` mode.

    Args:
        task: the task.
        physics: the batch, ``B`` entries.
        rngs: the ``B`` generators.
        mode: the observation mode.
        triggered: ``(B, S)`` noise-free tactile readings (``summaries(...)["tactile_triggered"]``).
    """
    if mode == "state":
        return task.state_vector(physics)
    c = task.config
    S = task.sensors.num_sensors
    normals = np.stack([rng.normal(size=3) for rng in rngs])
    uniforms = np.stack([rng.random(S) for rng in rngs])
    peg = physics.state.q[:, PEG].numpy()
    noisy = peg + normals * np.asarray(c.pose_noise_std)
    probability = task.sensors.reading_probability(torch.from_numpy(triggered)).numpy()
    readings = (uniforms < probability).astype(np.int8)
    return {
        "peg_pose": noisy.astype(np.float64),
        "gripper_pose": physics.gripper.numpy().astype(np.float64),
        "tactile": readings,
    }


def summaries(
    task: PegInHoleTask, physics: Physics, contacts: ContactSet
) -> dict[str, NDArray[Any]]:
    """Batched ground truth: poses, twist, contact class, manipulation state, flags.

    Args:
        task: the task.
        physics: the batch.
        contacts: ``task.peg_contacts(physics)``.
    """
    classes = contact_classes(contacts)
    peg = physics.state.q[:, PEG]
    ids = task.states.ids(peg, classes)
    success, dropped = task.outcome(physics)
    return {
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
