"""Reading a run log: an MCAP file back to a :class:`RunLog`, with the format's checks."""

from __future__ import annotations

import json
import math
import os
import struct
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from mcap.exceptions import McapError
from mcap.reader import make_reader
from torch import Tensor
from zstandard import ZstdError

from torchcontact.logs._run_log import ContactTruth, RunLog
from torchcontact.logs._schemas import (
    CAMERA_POSE,
    CHANNELS,
    FORMAT_VERSION,
    MESSAGE_ENCODING,
    PARAMETERS,
    PRIOR,
    ROBOT_COMMAND,
    ROBOT_STATE,
    RUN_INFO,
    SCHEMA_ENCODING,
    SCHEMA_NAME,
    TACTILE,
    TRUE_CONTACTS,
    TRUE_STATE,
    Channel,
)

_KNOWN = {channel.topic: channel for channel in CHANNELS}
_KINDS: dict[str, tuple[tuple[type, ...], torch.dtype]] = {
    "number": ((int, float), torch.float64),
    "integer": ((int,), torch.int64),
    "boolean": ((bool,), torch.bool),
}


def _records(path: Path) -> dict[str, list[tuple[int, bytes]]]:
    """``{topic: [(log_time, data), ...]}`` of the known topics, in log-time order, after
    checking each channel's schema and encodings."""
    found: dict[str, list[tuple[int, bytes]]] = {}
    try:
        with path.open("rb") as stream:
            reader = make_reader(stream, validate_crcs=True)
            for schema, channel, message in reader.iter_messages(log_time_order=True):
                known = _KNOWN.get(channel.topic)
                if known is None:
                    continue  # channels of other tools ride along
                if channel.topic not in found:
                    _check_channel(path, known, schema, channel.message_encoding)
                    found[channel.topic] = []
                found[channel.topic].append((message.log_time, message.data))
    except (McapError, OSError, EOFError, struct.error) as error:
        raise ValueError(f"path {str(path)!r} is not a readable MCAP file ({error})") from None
    except (KeyError, IndexError, UnicodeDecodeError, RuntimeError, ZstdError) as error:
        # what the mcap reader raises on a corrupt record (an unknown id, a truncated or
        # undecodable chunk: zstd's error; lz4's is a RuntimeError)
        raise ValueError(f"path {str(path)!r} is a corrupt MCAP file ({error!r})") from None
    return found


def _check_channel(path: Path, channel: Channel, schema: Any, message_encoding: str) -> None:
    where = f"{path}: channel {channel.topic!r}"
    if schema is None:
        raise ValueError(f"{where} has no schema; expected {channel.schema_name!r}")
    match = SCHEMA_NAME.fullmatch(schema.name)
    if match is None:
        raise ValueError(f"{where} has schema {schema.name!r}; expected {channel.schema_name!r}")
    version = int(match.group(1))
    if version != FORMAT_VERSION:
        raise ValueError(
            f"{where} has schema {schema.name!r} of format version {version}; this reader "
            f"knows version {FORMAT_VERSION}"
        )
    if match.group(2) != channel.message:
        raise ValueError(f"{where} has schema {schema.name!r}; expected {channel.schema_name!r}")
    if schema.encoding != SCHEMA_ENCODING or message_encoding != MESSAGE_ENCODING:
        raise ValueError(
            f"{where} has schema encoding {schema.encoding!r} and message encoding "
            f"{message_encoding!r}; expected {SCHEMA_ENCODING!r} and {MESSAGE_ENCODING!r}"
        )


def _decode(where: str, data: bytes, channel: Channel) -> dict[str, Any]:
    try:
        message = json.loads(data)
    except ValueError as error:  # JSONDecodeError and UnicodeDecodeError
        raise ValueError(f"{where}: the message is not JSON ({error})") from None
    if not isinstance(message, dict):
        raise ValueError(f"{where}: expected a JSON object, got {type(message).__name__}")
    missing = sorted(set(channel.schema["required"]) - set(message))
    if missing:
        raise ValueError(f"{where}: the message lacks the fields {missing}")
    return message


def _flatten(where: str, value: object, shape: Sequence[int | None], kind: str) -> list[Any]:
    """The items of the nested JSON array ``value`` of ``shape`` (``None``: any length)."""
    if not shape:
        types = _KINDS[kind][0]
        if isinstance(value, bool) != (kind == "boolean") or not isinstance(value, types):
            raise ValueError(f"{where}: expected a {kind}, got {value!r}")
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{where}: expected a finite number, got {value!r}")
        return [value]
    if not isinstance(value, list) or shape[0] not in (None, len(value)):
        size = "a list" if shape[0] is None else f"a list of {shape[0]}"
        raise ValueError(f"{where}: expected {size}, got {value!r}")
    return [item for entry in value for item in _flatten(where, entry, shape[1:], kind)]


def _array(
    where: str, message: dict[str, Any], key: str, shape: tuple[int, ...], kind: str
) -> Tensor:
    """Field ``key`` as a tensor of ``shape`` (a leading ``-1``: any length)."""
    value = message[key]
    items = _flatten(f"{where}: field {key!r}", value, [None if s < 0 else s for s in shape], kind)
    out = torch.tensor(items, dtype=_KINDS[kind][1])
    if shape and shape[0] < 0:
        return out.reshape(len(value), *shape[1:])
    return out.reshape(shape)


def _stacked(
    path: Path,
    records: list[tuple[int, bytes]],
    channel: Channel,
    index: dict[int, int],
    instants: range,
    fields: dict[str, tuple[tuple[int, ...], str]],
) -> tuple[list[int], dict[str, Tensor]]:
    """The listed fields of the channel's messages stacked over their instants.

    Each message must sit on an instant of ``instants`` and no two on the same one.

    Returns:
        The instants, and ``{field: (n, *shape)}``.
    """
    at: list[int] = []
    values: dict[str, list[Tensor]] = {key: [] for key in fields}
    for time, data in records:
        where = f"{path}: {channel.topic} at {time} ns"
        k = index.get(time)
        if k is None or k not in instants:
            raise ValueError(
                f"{where}: not at an instant of /robot/state (instants {instants.start} to "
                f"{instants.stop - 1})"
            )
        if at and at[-1] == k:
            raise ValueError(f"{where}: a second message at this instant")
        at.append(k)
        message = _decode(where, data, channel)
        for key, (shape, kind) in fields.items():
            values[key].append(_array(where, message, key, shape, kind))
    stacked = {}
    for key in fields:
        try:
            stacked[key] = torch.stack(values[key])
        except RuntimeError:
            raise ValueError(f"{path}: {channel.topic}: field {key!r} changes size") from None
    return at, stacked


def _every_step(path: Path, channel: Channel, at: list[int], count: int) -> None:
    if at != list(range(count)):
        raise ValueError(
            f"{path}: {channel.topic}: expected one message at each of the first {count} "
            f"instants, got {len(at)}"
        )


def _single(
    path: Path, found: dict[str, list[tuple[int, bytes]]], channel: Channel, start: int
) -> dict[str, Any]:
    records = found[channel.topic]
    if len(records) != 1 or records[0][0] != start:
        raise ValueError(f"{path}: {channel.topic}: expected one message at the first instant")
    return _decode(f"{path}: {channel.topic}", records[0][1], channel)


def _names(where: str, value: object) -> tuple[str, ...]:
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise ValueError(f"{where}: expected a list of str, got {value!r}")
    return tuple(value)


def read_run(path: str | os.PathLike[str]) -> RunLog:
    """Read a run log written by :func:`write_run` (or by any tool that follows the format).

    Channels of other topics are ignored; every channel this format knows must carry its
    schema (``torchcontact.logs.v1.<Message>``, ``jsonschema``) with ``json`` messages.

    Args:
        path: the MCAP file.

    Returns:
        The run; ``vision`` is NaN at the instants without a ``/camera/pose`` message, the
        optional parts are ``None`` (or empty) where their channels are absent.

    Raises:
        ValueError: ``path`` is not a readable MCAP file (missing, corrupt, truncated), a
            channel's schema is of another format version or name or encoding, a required
            channel is missing, or a message does not fit the format (a field missing, of
            the wrong size or type, a non-finite number, off the time grid).
    """
    if not isinstance(path, str | os.PathLike):
        raise ValueError(f"path: expected a str or os.PathLike, got {type(path).__name__}")
    file = Path(path)
    found = _records(file)
    missing = [c.topic for c in CHANNELS if c.required and c.topic not in found]
    if missing:
        raise ValueError(f"{file}: the log lacks the required channels {missing}")
    states = found[ROBOT_STATE.topic]
    times = [time for time, _ in states]
    if len(states) < 2 or len(set(times)) != len(times) or times[-1] >= 2**63:
        raise ValueError(
            f"{file}: {ROBOT_STATE.topic}: expected >= 2 messages at distinct instants below "
            f"2**63 ns, got {len(states)}"
        )
    T = len(states) - 1
    index = {time: k for k, time in enumerate(times)}
    info = _single(file, found, RUN_INFO, times[0])
    where = f"{file}: {RUN_INFO.topic}"
    joints = _names(f"{where}: joints", info["joints"])
    bodies = _names(f"{where}: bodies", info["bodies"])
    J, Nd = len(joints), len(bodies)
    every = range(T + 1)
    steps = range(T)
    _, robot = _stacked(file, states, ROBOT_STATE, index, every, {"position": ((J,), "number")})
    at, command = _stacked(
        file,
        found[ROBOT_COMMAND.topic],
        ROBOT_COMMAND,
        index,
        steps,
        {"velocity": ((J,), "number")},
    )
    _every_step(file, ROBOT_COMMAND, at, T)
    at, tactile = _stacked(
        file, found[TACTILE.topic], TACTILE, index, steps, {"triggered": ((-1,), "boolean")}
    )
    _every_step(file, TACTILE, at, T)
    at, camera = _stacked(
        file, found[CAMERA_POSE.topic], CAMERA_POSE, index, every, {"pose": ((3,), "number")}
    )
    vision = torch.full((T + 1, 3), math.nan, dtype=torch.float64)
    vision[at] = camera["pose"]
    prior_mean = prior_covariance = None
    if PRIOR.topic in found:
        prior = _single(file, found, PRIOR, times[0])
        prior_mean = _array(f"{file}: {PRIOR.topic}", prior, "mean", (6,), "number")
        prior_covariance = _array(f"{file}: {PRIOR.topic}", prior, "covariance", (6, 6), "number")
    truth_pose = truth_twist = None
    if TRUE_STATE.topic in found:
        shape = ((Nd, 3), "number")
        at, state = _stacked(
            file, found[TRUE_STATE.topic], TRUE_STATE, index, every, {"pose": shape, "twist": shape}
        )
        _every_step(file, TRUE_STATE, at, T + 1)
        truth_pose, truth_twist = state["pose"], state["twist"]
    contacts = None
    if TRUE_CONTACTS.topic in found:
        fields = {
            "mode": ((-1,), "integer"),
            "normal_impulse": ((-1,), "number"),
            "friction_impulse": ((-1, 2), "number"),
            "point": ((-1, 2), "number"),
            "normal": ((-1, 2), "number"),
            "candidate": ((-1,), "boolean"),
            "solver": ((), "integer"),
        }
        at, truth = _stacked(file, found[TRUE_CONTACTS.topic], TRUE_CONTACTS, index, steps, fields)
        _every_step(file, TRUE_CONTACTS, at, T)
        try:
            contacts = ContactTruth(
                mode=truth["mode"],
                normal_impulse=truth["normal_impulse"],
                friction_impulse=truth["friction_impulse"],
                point=truth["point"],
                normal=truth["normal"],
                candidate=truth["candidate"],
                solver=truth["solver"],
            )
        except ValueError as error:
            raise ValueError(f"{file}: {TRUE_CONTACTS.topic}: {error}") from None
    parameters: dict[str, float] = {}
    if PARAMETERS.topic in found:
        values = _single(file, found, PARAMETERS, times[0])["values"]
        if not isinstance(values, dict):
            raise ValueError(f"{file}: {PARAMETERS.topic}: values: expected an object")
        for key, value in values.items():
            parameters[key] = float(
                _flatten(f"{file}: {PARAMETERS.topic}: {key}", value, [], "number")[0]
            )
    h, source = info["h"], info["source"]
    try:
        return RunLog(
            name=info["name"],
            h=float(h) if isinstance(h, int) and not isinstance(h, bool) else h,
            body=info["body"],
            joints=joints,
            time_ns=torch.tensor(times, dtype=torch.int64),
            robot_position=robot["position"],
            robot_velocity=command["velocity"],
            vision=vision,
            tactile=tactile["triggered"],
            source=source,
            prior_mean=prior_mean,
            prior_covariance=prior_covariance,
            bodies=bodies,
            truth_pose=truth_pose,
            truth_twist=truth_twist,
            truth_contacts=contacts,
            parameters=parameters,
        )
    except ValueError as error:
        raise ValueError(f"{file}: the log does not fit the format: {error}") from None
