"""Contact states, tactile sensors, manipulation states and the manipulation graph.

A task is discretized by the object's contacts (Section III of the seed paper): a
:class:`ContactState` groups the object's contacts into features — contacts whose locations
lie within ``δ_r`` and whose normals agree within ``δ_θ`` (:class:`FeatureGrid`), with their
sticking/sliding status — separately for the robot and the environment. A
:class:`ManipulationState` adds the robot's discretized pose relative to the object
(:class:`PoseGrid`). The :class:`ManipulationGraph` holds transition statistics between
manipulation states under actions and exports the filter's mode-transition model and the
sampling model of Dyna-Q. A :class:`TactileArray` simulates binary contact sensors and gives
the likelihood of their readings under each contact state. :func:`mode_label`,
:func:`touch_codes` and :func:`mode_ids` read the simulator's per-slot mode vectors.

Everything starts from a :class:`ContactSet`: batched contact tensors of one time step.
"""

from torchcontact.states._contact_set import PARTNER_KINDS, ContactSet, PartnerKind
from torchcontact.states._contact_state import ContactFeature, ContactState, contact_states
from torchcontact.states._examples import planar_box_contacts
from torchcontact.states._frames import relative_pose
from torchcontact.states._from_sim import object_contacts
from torchcontact.states._graph import ManipulationGraph
from torchcontact.states._grid import FeatureGrid
from torchcontact.states._manipulation_state import (
    ManipulationState,
    PoseGrid,
    manipulation_states,
)
from torchcontact.states._registry import ContactStateRegistry, StateTable, UnknownStateError
from torchcontact.states._slot_modes import mode_ids, mode_label, touch_codes
from torchcontact.states._tactile import TactileArray, rectangle_sensors

__all__ = [
    "PARTNER_KINDS",
    "ContactFeature",
    "ContactSet",
    "ContactState",
    "ContactStateRegistry",
    "FeatureGrid",
    "ManipulationGraph",
    "ManipulationState",
    "PartnerKind",
    "PoseGrid",
    "StateTable",
    "TactileArray",
    "UnknownStateError",
    "contact_states",
    "manipulation_states",
    "mode_ids",
    "mode_label",
    "object_contacts",
    "planar_box_contacts",
    "rectangle_sensors",
    "relative_pose",
    "touch_codes",
]
