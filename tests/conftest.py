"""Shared pytest configuration: every test starts from the same seeds, and floating-point
results are compared with tolerances unless the test says why its digits are exact.

The suite must pass on any x86-64 CPU (AVX2 or AVX-512, Intel or AMD) with 1 or 2 threads,
whose BLAS and vectorized kernels round differently. ``torch.equal`` on floating-point
tensors, and ``assert_close`` / ``np.testing`` comparisons with zero tolerance, judge those
digits; they fail a test here unless it carries ``@pytest.mark.bitwise(reason)``, where the
reason says why the digits cannot depend on the CPU (a value passed through untouched, exact
arithmetic on small integers, or the same code on the same inputs in the same process).
"""

from __future__ import annotations

import random
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
import torch

_RULE = (
    "compares floating-point results bit for bit: their digits depend on the CPU's kernels. "
    "Compare with a tolerance justified by the problem's conditioning, or mark the test "
    "@pytest.mark.bitwise(reason) saying why the digits are exact on every CPU"
)


def _inexact(*values: object) -> bool:
    for value in values:
        if isinstance(value, torch.Tensor) and (value.is_floating_point() or value.is_complex()):
            return True
        if isinstance(value, np.ndarray | np.floating | float) and np.issubdtype(
            np.asarray(value).dtype, np.inexact
        ):
            return True
    return False


def _guard_equal(equal: Callable[..., bool]) -> Callable[..., bool]:
    def guarded(a: Any, b: Any) -> bool:
        if _inexact(a, b):
            raise AssertionError(f"torch.equal {_RULE}")
        return equal(a, b)

    return guarded


def _guard_close(close: Callable[..., None]) -> Callable[..., None]:
    def guarded(actual: Any, expected: Any, *args: Any, **kwargs: Any) -> None:
        zero = kwargs.get("rtol") == 0 and kwargs.get("atol") == 0
        if zero and _inexact(actual, expected):
            raise AssertionError(f"a zero-tolerance comparison {_RULE}")
        close(actual, expected, *args, **kwargs)

    return guarded


def _guard_array_equal(array_equal: Callable[..., None]) -> Callable[..., None]:
    def guarded(actual: Any, expected: Any, *args: Any, **kwargs: Any) -> None:
        if _inexact(np.asarray(actual), np.asarray(expected)):
            raise AssertionError(f"np.testing.assert_array_equal {_RULE}")
        array_equal(actual, expected, *args, **kwargs)

    return guarded


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Put the files holding a test marked ``slow`` first, each file's tests in their order.

    ``make pytest`` hands each pytest-xdist worker whole files (``--dist loadfile``) in this
    order (``--no-loadscope-reorder``). A slow test compiles a model for minutes; a file of
    them started near the end would leave the other workers idle until it finishes.
    """
    slow = {item.path for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: item.path not in slow)  # stable: the rest keep their order


@pytest.fixture(autouse=True)
def _floating_point_rules(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """Reject digit-exact comparisons of floating-point results in unmarked tests."""
    marker = request.node.get_closest_marker("bitwise")
    if marker is not None:
        if not (marker.args and isinstance(marker.args[0], str) and marker.args[0].strip()):
            raise AssertionError("@pytest.mark.bitwise needs a reason")
        return
    monkeypatch.setattr(torch, "equal", _guard_equal(torch.equal))
    monkeypatch.setattr(torch.testing, "assert_close", _guard_close(torch.testing.assert_close))
    monkeypatch.setattr(
        np.testing, "assert_array_equal", _guard_array_equal(np.testing.assert_array_equal)
    )


@pytest.fixture(autouse=True)
def _seed_everything() -> Iterator[None]:
    """Seed Python, NumPy and torch before every test, and restore torch's defaults after."""
    random.seed(0)
    np.random.seed(0)  # noqa: NPY002 -- seeds the legacy global generator that libraries use
    torch.manual_seed(0)
    dtype = torch.get_default_dtype()
    yield
    torch.set_default_dtype(dtype)
