"""Command lines generated from the argument dataclasses of the experiment scripts."""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any, TypeVar

T = TypeVar("T")


def parse_dataclass(cls: type[T], argv: list[str] | None, description: str) -> T:
    """Parse ``argv`` into an instance of the dataclass ``cls``.

    Every field becomes ``--field-name`` with its default and its ``metadata["help"]``;
    booleans get ``--flag`` / ``--no-flag``.

    Args:
        cls: a dataclass whose fields have defaults of type bool, int, float or str.
        argv: the arguments (``None``: ``sys.argv[1:]``).
        description: the ``--help`` description.
    """
    if not dataclasses.is_dataclass(cls):
        raise ValueError(f"cls must be a dataclass, got {cls!r}")
    parser = argparse.ArgumentParser(description=description)
    for field in dataclasses.fields(cls):
        default: Any = field.default
        flag = f"--{field.name.replace('_', '-')}"
        text = field.metadata.get("help", "")
        if isinstance(default, bool):
            parser.add_argument(
                flag, action=argparse.BooleanOptionalAction, default=default, help=text
            )
        else:
            parser.add_argument(
                flag, type=type(default), default=default, help=f"{text} (default: {default})"
            )
    return cls(**vars(parser.parse_args(argv)))
