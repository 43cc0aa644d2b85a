"""The RL tests use tiny tensors: run them on one intra-op thread (on a busy machine a
thread pool only adds contention) and restore the setting after each test."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch


@pytest.fixture(autouse=True)
def _one_thread() -> Iterator[None]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
