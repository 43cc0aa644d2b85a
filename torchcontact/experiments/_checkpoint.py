"""Resuming an experiment script from the checkpoint in its run folder."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import torch


def load_checkpoint(path: Path, args: Any, *, free: tuple[str, ...] = ()) -> dict[str, Any] | None:
    """The checkpoint at ``path`` (``None`` if there is none), checked against ``args``.

    A run is extended by resuming with a larger ``rounds``; every other argument must equal
    the one the checkpoint was written with (its ``"args"`` entry, ``dataclasses.asdict``
    of the script's argument dataclass), except those named in ``free``: arguments that only
    act after training (a final evaluation's budget or noise level), so a finished run can be
    evaluated again without training again.

    Args:
        path: the checkpoint file (``torch.save`` of a dict with an ``"args"`` entry).
        args: the script's arguments, a dataclass instance with a ``rounds`` field.
        free: names of further fields that may differ from the checkpoint's.

    Raises:
        ValueError: the checkpoint was written with other arguments.
    """
    if not path.exists():
        return None
    saved: dict[str, Any] = torch.load(path, weights_only=False)
    current = dataclasses.asdict(args)
    unknown = set(free) - set(current)
    if unknown:
        raise ValueError(f"free names fields that args lacks: {sorted(unknown)}")
    kept = {name: saved["args"].get(name) for name in ("rounds", *free)}
    if saved["args"] != current | kept:
        raise ValueError(f"{path} was written with other arguments")
    return saved
