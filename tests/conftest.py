"""Shared pytest configuration: every test starts from the same seeds."""

from __future__ import annotations

import random
from collections.abc import Iterator

import numpy as np
import pytest
import torch


@pytest.fixture(autouse=True)
def _seed_everything() -> Iterator[None]:
    """Seed Python, NumPy and torch before every test, and restore torch's defaults after."""
    random.seed(0)
    np.random.seed(0)  # noqa: NPY002 -- seeds the legacy global generator that libraries use
    torch.manual_seed(0)
    dtype = torch.get_default_dtype()
    yield
    torch.set_default_dtype(dtype)
