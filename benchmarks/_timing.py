"""Timing helper shared by the benchmark scripts."""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable

import torch


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


def synchronize(device: torch.device) -> None:
    """Wait for the work queued on ``device`` (a CUDA stream runs asynchronously: the clock may
    be read only once its kernels are done); nothing to wait for on the CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def device_name(device: torch.device) -> str:
    """The device in words for the results: the GPU's name, or the CPU's model."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    cpuinfo = "/proc/cpuinfo"
    if os.path.exists(cpuinfo):
        with open(cpuinfo) as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def parse_device(value: str) -> torch.device:
    """The ``--device`` argument as a device; CUDA must be available when asked for."""
    device = torch.device(value)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit(f"--device {value}: CUDA is not available")
    return device


def parse_sizes(value: str) -> tuple[int, ...]:
    """A comma-separated list of positive integers (``--sizes 1,64,1024``)."""
    sizes = tuple(int(part) for part in value.split(","))
    if not sizes or min(sizes) < 1:
        raise SystemExit(f"sizes must be positive integers, got {value!r}")
    return sizes
