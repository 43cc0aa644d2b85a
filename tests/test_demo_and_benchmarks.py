"""The main job and the benchmarks run end to end (small sizes)."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from torchcontact.demo import DemoArgs, run

ROOT = Path(__file__).resolve().parents[1]


def test_demo_writes_plot_and_summary_with_closed_form_agreement(tmp_path: Path) -> None:
    summary = run(DemoArgs(out=tmp_path, problems=60, peg_rounds=1, peg_envs=2, peg_episodes=2))
    assert (tmp_path / "demo.png").stat().st_size > 10_000
    assert (tmp_path / "summary.md").read_text() == summary
    slide_error = float(re.search(r"max\(v₀ − μ g t, 0\)\| = ([0-9.e+-]+)", summary).group(1))
    assert slide_error < 1e-12
    assert "| lemke (loop) |" in summary
    assert "60/60" in summary
    assert "| qmdp | 2 |" in summary


def test_contact_benchmark_quick_mode_prints_its_table() -> None:
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_contact.py"), "--quick"],
        capture_output=True,
        text=True,
        check=True,
        cwd=ROOT,
    )
    rows = [line for line in result.stdout.splitlines() if line.startswith("| 100 |")]
    assert len(rows) == 4


def run_quick(script: str) -> str:
    """The stdout of ``benchmarks/<script> --quick``."""
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), "--quick"],
        capture_output=True,
        text=True,
        check=True,
        cwd=ROOT,
    )
    return result.stdout


@pytest.mark.slow  # compiles the simulator's step for two batch sizes: a minute on a CPU
def test_simulator_benchmark_quick_mode_prints_eager_and_compiled_times() -> None:
    stdout = run_quick("bench_sim.py")
    rows = [line.split("|") for line in stdout.splitlines() if line.startswith(("| 1 |", "| 64 |"))]
    assert len(rows) == 2
    assert all(float(row[2]) > 0 and float(row[3]) > 0 for row in rows)  # ms / step, both


def test_spatial_simulator_benchmark_quick_mode_prints_its_table() -> None:
    stdout = run_quick("bench_sim3d.py")
    rows = [line.split("|") for line in stdout.splitlines() if line.startswith(("| 1 |", "| 64 |"))]
    assert len(rows) == 2
    assert all(float(row[3].replace(",", "")) > 0 for row in rows)  # box-steps / s


def test_spatial_accuracy_benchmark_quick_mode_meets_the_closed_forms() -> None:
    """torchcontact's row against the closed forms: no creep on a 20° incline with μ = 0.5,
    a rolling sphere at (5/7) g sin 30°, and the tipping height w / (2 μ) within the quick
    bisection's resolution (the midpoint after 5 halvings of [0.6, 1.5] × the threshold is
    within 0.9 / 64 of it)."""
    stdout = run_quick("accuracy_sim3d.py")
    lines = [line.split("|") for line in stdout.splitlines() if line.startswith("| ")]
    rows = {line[1].strip(): line for line in lines}
    ours = rows["torchcontact"]
    assert abs(float(ours[2])) <= 1e-9  # creep, m/s
    assert abs(float(ours[3])) <= 1e-9  # steady creep, m/s
    assert abs(float(ours[5].rstrip("% "))) <= 100 * 0.9 / 64  # tipping error, percent
    assert abs(float(ours[7])) <= 1e-6  # rolling acceleration, relative error
    if importlib.util.find_spec("mujoco") is not None:
        assert {"MuJoCo, defaults", "MuJoCo, elliptic + noslip 10"} <= rows.keys()


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity here")
def test_benchmarks_pin_themselves_to_the_fastest_probed_cpu() -> None:
    # In a child process: pinning changes the affinity of the process that asks.
    code = (
        "import json, os, sys; sys.path.insert(0, 'benchmarks');"
        "from _timing import pin_to_quietest_cpu;"
        "before = sorted(os.sched_getaffinity(0)); pinned = pin_to_quietest_cpu(probes=2);"
        "print(json.dumps([before, sorted(os.sched_getaffinity(0)), pinned]))"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT
    )
    before, after, pinned = json.loads(result.stdout)
    probed = {int(cpu): ns for cpu, ns in pinned["probe_ns"].items()}
    assert sorted(probed) == before
    assert all(ns > 0 for ns in probed.values())
    assert after == [pinned["pinned_cpu"]] == [min(probed, key=probed.__getitem__)]


def test_interleaved_timing_runs_every_setting_in_turn(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    from bench_filters import interleaved_best_of

    calls: list[str] = []
    clock = iter(range(1_000))  # a fake wall clock: every reading advances it by one second
    monkeypatch.setattr("bench_filters.time.perf_counter", lambda: float(next(clock)))
    timings = interleaved_best_of(
        [(lambda: calls.append("a"), 2), (lambda: calls.append("b"), 1)], rounds=3
    )
    # Each round: one untimed call, then the timed ones, of every setting in turn.
    assert "".join(calls) == "aaabb" * 3
    # Each run reads the clock twice in a row: 1 s per run, over its number of calls.
    assert [t["best_s"] for t in timings] == [0.5, 1.0]
    assert [t["median_s"] for t in timings] == [0.5, 1.0]
