"""Gymnasium environments on the planar contact simulator.

:class:`PegInHole2D` is a planar peg-in-hole task: a gripper holds a rectangular peg by
friction between two servoed fingers, so the peg can slip and turn in the grasp when the hole
pushes on it. :class:`PegInHole2DVector` steps a batch of them as one tensor batch. Their
manipulation states (:class:`PegInHoleStates`) are integer ids computed in one vectorized pass
from poses (true or estimated) and contact classes. :class:`PegInHoleFilter` tracks the peg in
the grasp with the RBPF over contact classes (init, step and restart on the environment's noisy
observations), on a :class:`PegInHoleBeliefModel` (the switching model fitted from recorded
steps, :class:`PegTransitions`, and the manipulation graph) or a :class:`PegPhysicsModel` (the
peg's mode-decoupled contact dynamics between the fingers and against the hole, and the graph).

Importing this package registers ``"torchcontact/PegInHole2D-v0"`` with gymnasium, its spec's
``max_episode_steps`` being ``PegInHoleConfig().max_steps`` (``gymnasium.make`` wraps the
environment in ``TimeLimit``; ``max_episode_steps=`` sets another limit), for
``gymnasium.make_vec`` in the ``"sync"``, ``"async"`` and ``"vector_entry_point"`` modes
(the last one steps :class:`PegInHole2DVector`). :func:`observation_bounds` gives the
observation spaces' bounds. ``"torchcontact/PegInHole2DOccluded-v0"`` is the same task with
:data:`OCCLUDED_CONFIG`: the camera loses the peg near the hole (``occlusion_radius``), so
only touch tells where the peg is there.
"""

from __future__ import annotations

import gymnasium

from torchcontact.envs._belief_filter import PegBelief, PegBeliefModel, PegInHoleFilter
from torchcontact.envs._belief_model import GraphClassTransition, PegControl, PegInHoleBeliefModel
from torchcontact.envs._config import PegInHoleConfig
from torchcontact.envs._env import PegInHole2D
from torchcontact.envs._observe import START_KEYS, observation_bounds, occluded
from torchcontact.envs._physics_model import PegPhysicsModel, filter_scene, slot_map
from torchcontact.envs._states import (
    CONTACT_TABLE,
    ENV_BELOW,
    ENV_LEFT,
    ENV_RIGHT,
    GRASP_NONE,
    GRASP_SLIDE,
    GRASP_STICK,
    HELD_FREE,
    NUM_CONTACT_CLASSES,
    PegInHoleStates,
    contact_classes,
    manipulation_state,
)
from torchcontact.envs._task import (
    ACTION_NAMES,
    BODY_NAMES,
    PegInHoleTask,
    Physics,
    build_scene,
)
from torchcontact.envs._transitions import PegTransitions
from torchcontact.envs._vector import PegInHole2DVector

#: Gymnasium id of :class:`PegInHole2D`.
PEG_IN_HOLE_ID = "torchcontact/PegInHole2D-v0"
#: Gymnasium id of the occluded variant (:data:`OCCLUDED_CONFIG`).
PEG_IN_HOLE_OCCLUDED_ID = "torchcontact/PegInHole2DOccluded-v0"
#: The occluded variant: the default task, its camera blind within 5 cm of the hole's mouth.
OCCLUDED_CONFIG = PegInHoleConfig(occlusion_radius=0.05)

if PEG_IN_HOLE_ID not in gymnasium.registry:
    gymnasium.register(
        id=PEG_IN_HOLE_ID,
        entry_point="torchcontact.envs:PegInHole2D",
        vector_entry_point="torchcontact.envs:PegInHole2DVector",
        max_episode_steps=PegInHoleConfig().max_steps,
    )
if PEG_IN_HOLE_OCCLUDED_ID not in gymnasium.registry:
    gymnasium.register(
        id=PEG_IN_HOLE_OCCLUDED_ID,
        entry_point="torchcontact.envs:PegInHole2D",
        vector_entry_point="torchcontact.envs:PegInHole2DVector",
        max_episode_steps=OCCLUDED_CONFIG.max_steps,
        kwargs={"config": OCCLUDED_CONFIG},
        # A blind camera's NaN pose lies outside every Box: the passive checker would warn.
        disable_env_checker=True,
    )

__all__ = [
    "ACTION_NAMES",
    "BODY_NAMES",
    "CONTACT_TABLE",
    "ENV_BELOW",
    "ENV_LEFT",
    "ENV_RIGHT",
    "GRASP_NONE",
    "GRASP_SLIDE",
    "GRASP_STICK",
    "HELD_FREE",
    "NUM_CONTACT_CLASSES",
    "OCCLUDED_CONFIG",
    "PEG_IN_HOLE_ID",
    "PEG_IN_HOLE_OCCLUDED_ID",
    "START_KEYS",
    "GraphClassTransition",
    "PegBelief",
    "PegBeliefModel",
    "PegControl",
    "PegInHole2D",
    "PegInHole2DVector",
    "PegInHoleBeliefModel",
    "PegInHoleConfig",
    "PegInHoleFilter",
    "PegInHoleStates",
    "PegInHoleTask",
    "PegPhysicsModel",
    "PegTransitions",
    "Physics",
    "build_scene",
    "contact_classes",
    "filter_scene",
    "manipulation_state",
    "observation_bounds",
    "occluded",
    "slot_map",
]
