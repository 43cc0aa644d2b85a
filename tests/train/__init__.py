"""Tests of the experiment scripts in train/ (loaded from their files by :func:`load_script`)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

TRAIN = Path(__file__).resolve().parents[2] / "train"


def load_script(name: str) -> ModuleType:
    """Import ``train/<name>.py`` as the module ``name`` (train/ is not a package)."""
    spec = importlib.util.spec_from_file_location(name, TRAIN / f"{name}.py")
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
