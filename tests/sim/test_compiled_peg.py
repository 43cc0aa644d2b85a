"""``Simulator(compiled=True)`` on the peg-in-hole grasp (90 slots), in the conditions that broke
its first version.

The first version solved the mode-decoupled system on all ``K`` slots of the scene (the peg
scene: 180 × 180 systems, 170 of whose rows are the identity rows of separated slots). With two
threads, torch 2.13's batched CPU ``linalg.lu_factor`` calls LAPACK's ``getrf`` on several batch
entries at once whenever the matrices are larger than 14 × 14; MKL's ``getrf`` is not safe for
that at such sizes: it returned pivots outside ``[1, n]`` with ``info == 0`` (MKL: "Parameter 6
was incorrect on entry to DLASWP"), or spun, depending on what the process had run before (a
filter's compiled kernels). The compiled step now solves on the slots its modes activate (plus
one separated slot), the systems the eager step factors.

Tolerances: velocities and poses agree with the eager step's to 1e-9 m/s: the grasp's Delassus
matrices have condition numbers up to ~1e4 (rounding ~1e-12); impulses, whose split on the
redundant pad contacts is set by the Tikhonov regularisation, to 1e-7 of the largest normal
impulse (as on boxes, ``test_compiled.py``).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest
import torch

from tests.filters.test_rbpf import _problem, _run
from tests.sim.test_compiled import _assert_impulses, _assert_same, _count_eager_steps
from torchcontact.envs import PegInHoleConfig, PegInHoleTask
from torchcontact.filters import RBPF
from torchcontact.sim import _simulator as simulator_module

#: The task's action that moves the gripper by ``move_step`` along ``−x`` (0 holds it still).
MOVE_LEFT = 2


def _starts(task: PegInHoleTask, count: int) -> torch.Tensor:
    """``(count, ·)`` seeded start samples of the task."""
    rng = np.random.default_rng(0)
    return torch.from_numpy(np.stack([task.sample_start(rng) for _ in range(count)]))


@pytest.mark.slow  # compiles a filter's kernels, then the peg scene's step: minutes on a CPU
def test_compiled_peg_after_a_compiled_filter_equals_eager(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The reverted version's failure: a filter's kernels compiled first, two threads, then
    the peg scene stepped compiled. Two scenes (a batch, as the batched ``getrf`` that failed
    needs), their grasps settled eagerly, then moved by one action each (one moving the
    gripper, one holding it: two simulator steps), eagerly and compiled. The settled modes
    hold through the action, so the compiled step runs as one graph (a graph of the 90-slot
    scene compiles for about a minute on a CPU; each other number of active slots or batch
    size would compile one more) and takes no eager step."""
    calls = _count_eager_steps(monkeypatch)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        problem = _problem(extra=True)
        _run(RBPF(problem.model(), 24, compiled=True), problem, seed=3)
        task = PegInHoleTask(PegInHoleConfig())
        settled = task.reset(_starts(task, 2))
        actions = torch.tensor([MOVE_LEFT, 0])
        physics, eager_steps = [], []
        for compiled in (False, True):
            task.simulator = replace(task.simulator, compiled=compiled)
            before = len(calls)
            physics.append(task.step(settled, actions))
            eager_steps.append(calls[before:])
    finally:
        torch.set_num_threads(threads)
    (expected, actual), (eager_calls, compiled_calls) = physics, eager_steps
    assert eager_calls == [2] * task.config.substeps
    assert compiled_calls == []
    # The grasps hold: every pad presses the peg.
    assert bool((expected.mode.count_nonzero(dim=-1) >= 2).all())
    _assert_same(actual.state, expected.state, atol=1e-9)
    _assert_impulses(actual.pn, expected.pn, expected.pn)


def test_compiled_step_factors_the_systems_of_the_eager_step(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The kernel run eagerly on the peg scene: the largest matrix it LU-factors is no larger
    than the eager step's (rows of the slots its modes activate, not of all 90 slots)."""
    sizes: list[int] = []
    factor = torch.linalg.lu_factor

    def recorded(A: torch.Tensor, **kwargs: Any) -> Any:
        sizes.append(A.shape[-1])
        return factor(A, **kwargs)

    monkeypatch.setattr(torch.linalg, "lu_factor", recorded)
    monkeypatch.setattr(simulator_module, "kernel", lambda fn, **options: fn)
    task = PegInHoleTask(PegInHoleConfig())
    samples = _starts(task, 4)
    largest = []
    for compiled in (False, True):
        task.simulator = replace(task.simulator, compiled=compiled)
        sizes.clear()
        task.reset(samples)
        largest.append(max(sizes))
    assert largest[1] <= largest[0] < 2 * task.simulator.scene.num_slots
