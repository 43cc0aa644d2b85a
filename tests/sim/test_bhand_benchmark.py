"""The BarrettHand benchmark's quick mode: its table, its fast path and its grip.

The grip of the benchmark's grasp (finger torque limits τ, τ, 2τ with τ = 0.2 N m, the pad
points on the faces of a box of half width 0.06 m) is the closed form of the servo statics,
F_n = 4 τ / λ, with λ the lever ∂p_y/∂θ of the outer capsule's pad point along the coupled
finger coordinate (inner θ, outer θ/3), here by central differences of forward kinematics.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchcontact.robots import load

ROOT = Path(__file__).resolve().parents[2]
TAU = 0.2  # N m, the torque limit of fingers 1 and 2 in the benchmark (finger 3: 2 τ)
THETA = 0.9536  # rad, where the pad point's |y| is the box's half width 0.06 m


def pad_y(theta: float) -> float:
    """Hand-frame y of finger 1's pad point: the outer capsule's end-cap centre, offset by its
    radius (9.5 mm) towards the hand's centre."""
    hand = load("bhand")
    q = torch.tensor([0.0, theta, theta, theta], dtype=torch.float64)
    transform = hand.forward_kinematics(q, "bhand_f1_outer")
    centre = transform[:3, :3] @ torch.tensor([0.05, 0.0, 0.0], dtype=torch.float64)
    return float(centre[1] + transform[1, 3]) + 0.0095


def test_quick_mode_closes_on_the_fast_path_with_the_closed_form_grip() -> None:
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_bhand.py"), "--quick"],
        capture_output=True,
        text=True,
        check=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    rows = [
        [cell.strip() for cell in line.split("|")[1:-1]]
        for line in result.stdout.splitlines()
        if line.startswith(("| 1 |", "| 64 |"))
    ]
    assert len(rows) == 2
    eps = 1e-6
    lever = (pad_y(THETA + eps) - pad_y(THETA - eps)) / (2 * eps)
    assert pad_y(THETA) == pytest.approx(-0.06, abs=1e-4)
    grip = 4 * TAU / abs(lever)
    for _, _, rate, fast_path, measured, _ in rows:
        assert float(rate.replace(",", "")) > 0
        # Every step solved by the active set (none by the per-problem Lemke fallback).
        assert fast_path == "100%"
        # The table prints the grip to 1 mN; the statics hold to 1e-3 (as in the grasp test).
        assert float(measured) == pytest.approx(grip, rel=2e-3)
