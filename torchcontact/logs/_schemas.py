"""The channels of a run log and the JSON Schema of each channel's messages (format version 1).

Every channel has one schema, named ``torchcontact.logs.v<version>.<Message>``, with schema
encoding ``jsonschema`` and message encoding ``json`` (the MCAP registry's well-known
encodings: any MCAP tool shows the messages without generated code). The version in the name
is the format's: a reader refuses a schema of a version it does not know.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from typing import Any

#: The version of the log format this library writes and reads.
FORMAT_VERSION = 1
#: MCAP schema encoding of every channel's schema.
SCHEMA_ENCODING = "jsonschema"
#: MCAP message encoding of every channel.
MESSAGE_ENCODING = "json"
SCHEMA_PREFIX = "torchcontact.logs.v"
SCHEMA_NAME = re.compile(r"torchcontact\.logs\.v(\d+)\.(\w+)")


def _number() -> dict[str, Any]:
    return {"type": "number"}


def _vector(size: int | None, item: dict[str, Any], what: str) -> dict[str, Any]:
    schema: dict[str, Any] = {"type": "array", "items": item, "description": what}
    if size is not None:
        schema["minItems"] = schema["maxItems"] = size
    return schema


def _rows(width: int, what: str) -> dict[str, Any]:
    return _vector(None, _vector(width, _number(), "one row"), what)


def _message(title: str, description: str, properties: dict[str, Any]) -> dict[str, Any]:
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "description": description,
        "type": "object",
        "properties": properties,
        "required": sorted(properties),
    }


@dataclass(frozen=True)
class Channel:
    """One channel of a run log.

    Attributes:
        topic: the MCAP topic.
        message: the schema's message name (the schema is ``torchcontact.logs.v1.<message>``).
        schema: the JSON Schema (draft 2020-12) of its messages.
        required: whether every log has it.
    """

    topic: str
    message: str
    schema: dict[str, Any]
    required: bool

    @property
    def schema_name(self) -> str:
        """``torchcontact.logs.v<FORMAT_VERSION>.<message>``."""
        return f"{SCHEMA_PREFIX}{FORMAT_VERSION}.{self.message}"

    def schema_bytes(self) -> bytes:
        """The schema as the UTF-8 JSON text stored in the MCAP schema record."""
        return json.dumps(self.schema, sort_keys=True).encode()


RUN_INFO = Channel(
    "/run/info",
    "RunInfo",
    _message(
        "RunInfo",
        "What the run is; one message at the first instant.",
        {
            "name": {"type": "string", "description": "the run's name"},
            "h": {"type": "number", "exclusiveMinimum": 0, "description": "time step, s"},
            "body": {"type": "string", "description": "the tracked body the camera measures"},
            "joints": _vector(None, {"type": "string"}, "names of the robot's coordinates"),
            "bodies": _vector(None, {"type": "string"}, "bodies of /ground_truth/state"),
            "source": {"type": "object", "description": "free-form: what produced the run"},
        },
    ),
    required=True,
)
ROBOT_STATE = Channel(
    "/robot/state",
    "RobotState",
    _message(
        "RobotState",
        "Robot coordinates at an instant; one message per instant: these define the time grid.",
        {"position": _vector(None, _number(), "joint angles (rad) or body poses (m, rad)")},
    ),
    required=True,
)
ROBOT_COMMAND = Channel(
    "/robot/command",
    "RobotCommand",
    _message(
        "RobotCommand",
        "Velocity of the robot's coordinates held over the step that starts at this instant.",
        {"velocity": _vector(None, _number(), "rad/s or (m/s, rad/s), per coordinate")},
    ),
    required=True,
)
CAMERA_POSE = Channel(
    "/camera/pose",
    "CameraPose",
    _message(
        "CameraPose",
        "Vision measurement of the tracked body's planar pose; absent while it is not seen.",
        {
            "frame_id": {"const": "world", "description": "the frame of the pose"},
            "pose": _vector(3, _number(), "(x m, y m, θ rad)"),
        },
    ),
    required=True,
)
TACTILE = Channel(
    "/tactile/readings",
    "TactileReadings",
    _message(
        "TactileReadings",
        "Binary tactile readings of the contacts during the step that starts at this instant.",
        {"triggered": _vector(None, {"type": "boolean"}, "one per sensor")},
    ),
    required=True,
)
PRIOR = Channel(
    "/estimate/prior",
    "Prior",
    _message(
        "Prior",
        "The filters' initial Gaussian belief over the tracked body's state; first instant.",
        {
            "mean": _vector(6, _number(), "(x, y, θ, vx, vy, ω): m, rad, m/s, rad/s"),
            "covariance": _rows(6, "6 rows of 6, the units' products"),
        },
    ),
    required=False,
)
TRUE_STATE = Channel(
    "/ground_truth/state",
    "BodyStates",
    _message(
        "BodyStates",
        "True poses and twists of RunInfo.bodies at an instant; one message per instant.",
        {
            "pose": _rows(3, "(x m, y m, θ rad) per body, world frame"),
            "twist": _rows(3, "(vx m/s, vy m/s, ω rad/s) per body, world frame"),
        },
    ),
    required=False,
)
TRUE_CONTACTS = Channel(
    "/ground_truth/contacts",
    "Contacts",
    _message(
        "Contacts",
        "The simulator's contact slots over the step that starts at this instant.",
        {
            "mode": _vector(None, {"type": "integer"}, "per slot: 0 separated, 1 stick, 2+d slide"),
            "normal_impulse": _vector(None, _number(), "per slot, N s"),
            "friction_impulse": _rows(2, "per slot, along +t and -t, N s"),
            "point": _rows(2, "per slot, contact point at the step's start, world frame, m"),
            "normal": _rows(2, "per slot, unit normal, world frame"),
            "candidate": _vector(None, {"type": "boolean"}, "per slot: a real candidate"),
            "solver": {"type": "integer", "description": "the simulator's solver code"},
        },
    ),
    required=False,
)
PARAMETERS = Channel(
    "/ground_truth/parameters",
    "Parameters",
    _message(
        "Parameters",
        "True physical parameters of the run (e.g. friction); one message, first instant.",
        {"values": {"type": "object", "additionalProperties": _number()}},
    ),
    required=False,
)

#: Every channel of format version 1, in the order a log writes them at one instant.
CHANNELS = (
    RUN_INFO,
    ROBOT_STATE,
    ROBOT_COMMAND,
    CAMERA_POSE,
    TACTILE,
    PRIOR,
    TRUE_STATE,
    TRUE_CONTACTS,
    PARAMETERS,
)
