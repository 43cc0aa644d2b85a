"""Filters tests run single-threaded: their tensors are small, and on a busy 2-core machine
torch's intra-op thread pool (e.g. inside batched LAPACK calls) can stall for milliseconds per
call while waiting for a descheduled worker."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch


@pytest.fixture(autouse=True)
def _single_thread() -> Iterator[None]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
