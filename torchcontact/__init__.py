"""torchcontact: contact-aware estimation, learning and execution for robotic manipulation.

The subpackages load on first use (``torchcontact.filters``, ``import torchcontact.contact``):
importing the contact solvers does not import gymnasium or pytorch-kinematics.
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from torchcontact import (
        contact,
        envs,
        experiments,
        filters,
        geometry,
        logs,
        rl,
        robots,
        sim,
        states,
    )

__all__ = [
    "__version__",
    "contact",
    "envs",
    "experiments",
    "filters",
    "geometry",
    "logs",
    "rl",
    "robots",
    "sim",
    "states",
]

__version__ = "0.1.0"

_SUBPACKAGES = frozenset(__all__) - {"__version__"}


def __getattr__(name: str) -> ModuleType:
    if name in _SUBPACKAGES:
        module = importlib.import_module(f"torchcontact.{name}")
        globals()[name] = module
        return module
    raise AttributeError(f"module 'torchcontact' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
