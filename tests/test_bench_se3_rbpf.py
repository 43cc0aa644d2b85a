"""The SE(3) contact RBPF benchmark runs end to end (its quick, eager-only mode)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_se3_rbpf_benchmark_quick_mode_prints_its_table() -> None:
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_se3_rbpf.py"), "--quick"],
        capture_output=True,
        text=True,
        check=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},  # this checkout's torchcontact
    )
    rows = [line.split("|") for line in result.stdout.splitlines() if line.startswith("| 2 |")]
    assert len(rows) == 1
    assert rows[0][3].strip() == "eager"
    assert float(rows[0][4]) > 0  # ms per step
    assert float(rows[0][5]) > 0  # ms per linearization
