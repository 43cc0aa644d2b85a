"""The contact-state tests run in float64 (the root conftest restores the default after)."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(autouse=True)
def _float64() -> None:
    torch.set_default_dtype(torch.float64)
