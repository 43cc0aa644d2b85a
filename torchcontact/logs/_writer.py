"""Writing a run log: a :class:`RunLog` to an MCAP file."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from torchcontact.logs._run_log import RunLog
from torchcontact.logs._schemas import (
    CAMERA_POSE,
    CHANNELS,
    MESSAGE_ENCODING,
    PARAMETERS,
    PRIOR,
    ROBOT_COMMAND,
    ROBOT_STATE,
    RUN_INFO,
    SCHEMA_ENCODING,
    TACTILE,
    TRUE_CONTACTS,
    TRUE_STATE,
    Channel,
)

#: The MCAP header's ``library`` field of the files this library writes.
LIBRARY = "torchcontact.logs"


def _messages(run: RunLog) -> list[tuple[int, Channel, dict[str, Any]]]:
    """``(instant, channel, message)`` of every message of ``run``, in writing order."""
    T = run.steps
    out: list[tuple[int, Channel, dict[str, Any]]] = [
        (
            0,
            RUN_INFO,
            {
                "name": run.name,
                "h": run.h,
                "body": run.body,
                "joints": list(run.joints),
                "bodies": list(run.bodies),
                "source": run.source,
            },
        )
    ]
    if run.prior_mean is not None and run.prior_covariance is not None:
        prior = {"mean": run.prior_mean.tolist(), "covariance": run.prior_covariance.tolist()}
        out.append((0, PRIOR, prior))
    if run.parameters:
        out.append((0, PARAMETERS, {"values": dict(run.parameters)}))
    seen = (~run.vision[:, 0].isnan()).tolist()
    contacts = run.truth_contacts
    for k in range(T + 1):
        out.append((k, ROBOT_STATE, {"position": run.robot_position[k].tolist()}))
        if k < T:
            out.append((k, ROBOT_COMMAND, {"velocity": run.robot_velocity[k].tolist()}))
        if seen[k]:
            out.append((k, CAMERA_POSE, {"frame_id": "world", "pose": run.vision[k].tolist()}))
        if k < T:
            out.append((k, TACTILE, {"triggered": run.tactile[k].tolist()}))
        if run.truth_pose is not None and run.truth_twist is not None:
            state = {"pose": run.truth_pose[k].tolist(), "twist": run.truth_twist[k].tolist()}
            out.append((k, TRUE_STATE, state))
        if contacts is not None and k < T:
            step = {
                "mode": contacts.mode[k].tolist(),
                "normal_impulse": contacts.normal_impulse[k].tolist(),
                "friction_impulse": contacts.friction_impulse[k].tolist(),
                "point": contacts.point[k].tolist(),
                "normal": contacts.normal[k].tolist(),
                "candidate": contacts.candidate[k].tolist(),
                "solver": int(contacts.solver[k]),
            }
            out.append((k, TRUE_CONTACTS, step))
    return out


def _encode(channel: Channel, message: dict[str, Any]) -> bytes:
    """The message as compact JSON; floats as Python's shortest round-trip ``repr``."""
    try:
        text = json.dumps(message, allow_nan=False, separators=(",", ":"), sort_keys=True)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{channel.topic}: the message is not JSON-able ({error})") from None
    return text.encode()


def write_run(path: str | os.PathLike[str], run: RunLog) -> Path:
    """Write ``run`` to an MCAP file at ``path`` (replaced whole: written to a temporary file
    in the same folder, then renamed).

    Every message is stamped (log and publish time) with its instant ``run.time_ns[k]``; the
    channels are those of :data:`CHANNELS` that the run has (the user guide's page on
    recorded logs lists them). Chunks are zstd-compressed; the summary section indexes the
    channels and schemas. Floats are written as the shortest decimal that reads back as the
    same float64 (Python's ``repr``), so :func:`read_run` returns them exactly.

    Args:
        path: the file to write, conventionally ``*.mcap``; its folder must exist.
        run: the run.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ValueError: ``run`` is not a :class:`RunLog`, its ``source`` is not JSON-able (or holds
            NaN or inf), or ``path`` cannot be written.
    """
    if not isinstance(run, RunLog):
        raise ValueError(f"run: expected a RunLog, got {type(run).__name__}")
    if not isinstance(path, str | os.PathLike):
        raise ValueError(f"path: expected a str or os.PathLike, got {type(path).__name__}")
    target = Path(path)
    encoded = [(k, channel, _encode(channel, message)) for k, channel, message in _messages(run)]
    temporary = target.with_name(f".{target.name}.tmp")
    try:
        with temporary.open("wb") as stream:
            writer = Writer(stream, compression=CompressionType.ZSTD)
            writer.start(profile="", library=LIBRARY)
            ids = {}
            used = {channel.topic for _, channel, _ in encoded}
            for channel in (c for c in CHANNELS if c.topic in used):
                schema = writer.register_schema(
                    channel.schema_name, SCHEMA_ENCODING, channel.schema_bytes()
                )
                ids[channel.topic] = writer.register_channel(
                    channel.topic, MESSAGE_ENCODING, schema
                )
            sequence = dict.fromkeys(ids, 0)
            for k, channel, data in encoded:
                time = int(run.time_ns[k])
                writer.add_message(
                    ids[channel.topic],
                    log_time=time,
                    data=data,
                    publish_time=time,
                    sequence=sequence[channel.topic],
                )
                sequence[channel.topic] += 1
            writer.finish()  # type: ignore[no-untyped-call]
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, target)
    except OSError as error:
        temporary.unlink(missing_ok=True)
        raise ValueError(f"path {str(target)!r} cannot be written ({error})") from None
    return target
