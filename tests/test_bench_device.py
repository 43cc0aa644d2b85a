"""The benchmarks' device plumbing (``--device``, ``--sizes``, ``--steps``, ``--out``) on the CPU:
what benchmarks/gpu_rows.sh passes them on a GPU."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def test_spatial_benchmark_writes_the_requested_rows_and_names_the_device(tmp_path: Path) -> None:
    out = tmp_path / "rows" / "bench_sim3d.json"
    subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "bench_sim3d.py"),
            "--quick",
            "--device=cpu",
            "--sizes=1,2",
            "--steps=2",
            f"--out={out}",
        ],
        capture_output=True,
        text=True,
        check=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},  # this checkout's torchcontact
    )
    record = json.loads(out.read_text())
    assert record["device"] == "cpu"
    assert record["device_name"]
    assert record["steps"] == 2
    assert [row["B"] for row in record["rows"]] == [1, 2]
    assert all(row["box_steps_per_s"] > 0 for row in record["rows"])


def test_benchmarks_refuse_cuda_where_there_is_none() -> None:
    code = "import sys; sys.path.insert(0, 'benchmarks'); from _timing import parse_device;"
    code += "print(parse_device('cuda'))"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    if torch.cuda.is_available():
        assert result.returncode == 0
        assert result.stdout.strip() == "cuda"
    else:  # a clear exit naming the argument, not a traceback from deep inside torch
        assert result.returncode != 0
        assert "--device cuda: CUDA is not available" in result.stderr
