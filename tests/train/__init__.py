"""Tests of the experiment scripts in train/ (loaded from their files by :func:`load_script`)."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path
from types import ModuleType
from typing import Any

from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

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


def _as_written(value: Any) -> Any:
    """A value read back from JSON as ``dataclasses.asdict`` held it: lists were tuples."""
    if isinstance(value, list):
        return tuple(_as_written(item) for item in value)
    if isinstance(value, dict):
        return {key: _as_written(item) for key, item in value.items()}
    return value


def assert_logged(run_dir: Path, fields: Iterable[str], expected: Mapping[str, Any]) -> None:
    """The run folder logs its arguments and throughput (read back with TensorBoard's reader).

    ``args.json`` holds exactly ``fields`` with the ``expected`` values (JSON: tuples as
    lists); the TensorBoard text ``hyperparameters`` has a Markdown row per argument; and
    ``charts/SPS`` is logged, positive and finite.
    """
    saved = json.loads((run_dir / "args.json").read_text())
    assert list(saved) == list(fields)
    for name, value in expected.items():
        assert saved[name] == json.loads(json.dumps(value)), name
    events = EventAccumulator(str(run_dir))
    events.Reload()
    (text,) = events.Tensors("hyperparameters/text_summary")
    table = text.tensor_proto.string_val[0].decode()
    assert table.startswith("| argument | value |\n|---|---|\n")
    for name, value in saved.items():
        assert f"| {name} | {_as_written(value)} |" in table, name
    rates = [event.value for event in events.Scalars("charts/SPS")]
    assert rates
    assert all(0 < rate < math.inf for rate in rates)
