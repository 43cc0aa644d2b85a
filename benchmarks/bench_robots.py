"""WAM kinematics side by side: batched torchcontact.robots vs a per-configuration NumPy DH loop.

Forward kinematics of the tool frame and the tool's geometric Jacobian for B random configurations,
float64, one thread. The alternative is what a user would write without a batched library: a Python
loop over configurations multiplying Barrett's seven DH matrices in NumPy (and Spong's Jacobian
columns from the same frames). Both are checked to agree before timing. Prints a markdown table and
writes ``benchmarks/results/bench_robots.json``.

    python benchmarks/bench_robots.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
from functools import partial
from pathlib import Path

import numpy as np
import torch
from _timing import best_time  # benchmarks/ is on sys.path when run as a script

from torchcontact.robots import load

RESULTS = Path(__file__).resolve().parent / "results" / "bench_robots.json"

# Barrett WAM Arm User's Manual, 7-DOF DH table (Spong: T_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)).
DH_A = (0.0, 0.0, 0.045, -0.045, 0.0, 0.0, 0.0)
DH_ALPHA = (-math.pi / 2, math.pi / 2, -math.pi / 2, math.pi / 2, -math.pi / 2, math.pi / 2, 0.0)
DH_D = (0.0, 0.0, 0.55, 0.0, 0.3, 0.0, 0.06)


def numpy_frames(q: np.ndarray) -> list[np.ndarray]:
    """DH frames 0..7 of one configuration ``q`` ``(7,)``."""
    frames = [np.eye(4)]
    for qi, a, alpha, d in zip(q, DH_A, DH_ALPHA, DH_D, strict=True):
        c, s = math.cos(qi), math.sin(qi)
        ca, sa = math.cos(alpha), math.sin(alpha)
        step = np.array(
            [
                [c, -s * ca, s * sa, a * c],
                [s, c * ca, -c * sa, a * s],
                [0, sa, ca, d],
                [0, 0, 0, 1.0],
            ]
        )
        frames.append(frames[-1] @ step)
    return frames


def numpy_fk(q: np.ndarray) -> np.ndarray:
    """Tool transforms ``(B, 4, 4)``, one configuration at a time."""
    return np.stack([numpy_frames(qb)[7] for qb in q])


def numpy_jacobian(q: np.ndarray) -> np.ndarray:
    """Tool Jacobians ``(B, 6, 7)``, one configuration at a time."""
    out = np.empty((q.shape[0], 6, 7))
    for b, qb in enumerate(q):
        frames = numpy_frames(qb)
        tip = frames[7][:3, 3]
        for i in range(7):
            z, o = frames[i][:3, 2], frames[i][:3, 3]
            out[b, :3, i] = np.cross(z, tip - o)
            out[b, 3:, i] = z
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small sizes, for smoke tests")
    args = parser.parse_args()
    torch.set_num_threads(1)
    sizes = (1, 100) if args.quick else (1, 100, 10_000)
    robot = load("wam7")
    rng = np.random.default_rng(0)
    rows = []
    for size in sizes:
        q_np = rng.uniform(robot.lower.numpy(), robot.upper.numpy(), size=(size, 7))
        q = torch.from_numpy(q_np)
        np.testing.assert_allclose(
            robot.forward_kinematics(q, "wam_tool").numpy(), numpy_fk(q_np), atol=1e-12
        )
        np.testing.assert_allclose(
            robot.jacobian(q, "wam_tool").numpy(), numpy_jacobian(q_np), atol=1e-12
        )
        repeats = 50 if size == 1 else (20 if size == 100 else 3)
        cases = (
            ("forward kinematics", partial(robot.forward_kinematics, q, "wam_tool"), numpy_fk),
            ("Jacobian", partial(robot.jacobian, q, "wam_tool"), numpy_jacobian),
        )
        for operation, ours, theirs in cases:
            t_ours = best_time(ours, repeats)
            t_numpy = best_time(partial(theirs, q_np), repeats)
            rows.append(
                {
                    "B": size,
                    "operation": operation,
                    "torchcontact_ms": 1e3 * t_ours,
                    "numpy_loop_ms": 1e3 * t_numpy,
                    "speedup": t_numpy / t_ours,
                }
            )

    print(
        f"WAM kinematics, float64, one thread, {platform.processor() or platform.machine()}, "
        f"torch {torch.__version__}\n"
    )
    print("| B | operation | torchcontact.robots (ms) | NumPy DH loop (ms) | speed-up |")
    print("|---:|---|---:|---:|---:|")
    for row in rows:
        print(
            f"| {row['B']:,} | {row['operation']} | {row['torchcontact_ms']:.3f} | "
            f"{row['numpy_loop_ms']:.3f} | {row['speedup']:.1f}x |"
        )
    payload = {
        "machine": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "threads": 1,
        "dtype": "float64",
        "rows": rows,
    }
    if not args.quick:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(json.dumps(payload, indent=2) + "\n")
        print(f"\nwrote {RESULTS}")


if __name__ == "__main__":
    main()
