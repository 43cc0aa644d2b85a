"""Timing helper shared by the benchmark scripts."""

from __future__ import annotations

import os
import time
from collections.abc import Callable


def best_time(fn: Callable[[], object], repeats: int) -> float:
    """Best wall time of ``repeats`` calls, in seconds (after one warm-up call)."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def _probe(seconds: float = 0.02) -> float:
    """Seconds per iteration of a pure-Python loop: the speed of the CPU we run on."""
    count, start = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        for _ in range(1_000):
            count += 1
    return elapsed / count


def pin_to_quietest_cpu(*, probes: int = 5) -> dict[str, object]:
    """Pin this process to the CPU on which a pure-Python probe loop runs fastest.

    On a shared virtual machine one virtual CPU can be slower than another for a whole run
    (it shares a physical core with other load), by tens of percent. Timing every method on
    the quietest CPU compares them under the same conditions and makes runs comparable.
    Where affinity is not supported (macOS, Windows) nothing is pinned.

    Returns:
        ``{"pinned_cpu": int | None, "probe_ns": {cpu: best ns per iteration}}`` for the
        results' machine description.
    """
    if not hasattr(os, "sched_setaffinity"):
        return {"pinned_cpu": None, "probe_ns": {}}
    cpus = sorted(os.sched_getaffinity(0))
    speed = {}
    for cpu in cpus:
        os.sched_setaffinity(0, {cpu})
        speed[cpu] = 1e9 * min(_probe() for _ in range(probes))
    quietest = min(speed, key=speed.__getitem__)
    os.sched_setaffinity(0, {quietest})
    return {"pinned_cpu": quietest, "probe_ns": {cpu: round(ns, 2) for cpu, ns in speed.items()}}
