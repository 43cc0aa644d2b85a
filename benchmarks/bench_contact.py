"""Contact solvers side by side: batched mode solve and PGS vs per-problem Lemke and QP loops.

Two-contact planar box problems (sliding, resting, tipping under a push), one thread. Lemke and
the QP fallback solve one problem at a time (what a user of an LCP or QP package would write);
their per-problem time is measured on a subset of the batch. Prints a markdown table and writes
``benchmarks/results/bench_contact.json``.

    python benchmarks/bench_contact.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

import torch
from _timing import best_time  # benchmarks/ is on sys.path when run as a script

from torchcontact.contact import ContactProblem, planar_box_problem, solve, solve_mode

RESULTS = Path(__file__).resolve().parent / "results" / "bench_contact.json"


def box_problems(count: int, seed: int = 0) -> ContactProblem:
    """``count`` distinct two-contact box problems: a third each sliding, resting, tipping."""
    gen = torch.Generator().manual_seed(seed)
    q = torch.zeros(count, 3, dtype=torch.float64)
    q[:, 1] = 0.25
    v = torch.zeros(count, 3, dtype=torch.float64)
    kind = torch.arange(count) % 3
    v[:, 0] = torch.where(
        kind == 0, 0.5 + torch.rand(count, generator=gen, dtype=torch.float64), 0.0
    )
    push = torch.zeros(count, 2, dtype=torch.float64)
    push[:, 0] = torch.where(
        kind == 2, 7.0 + torch.rand(count, generator=gen, dtype=torch.float64), 0.0
    )
    push[:, 0] += torch.where(kind == 1, torch.rand(count, generator=gen, dtype=torch.float64), 0.0)
    return planar_box_problem(q=q, v=v, force=push, force_point=(-0.5, 0.2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small sizes, for smoke tests")
    args = parser.parse_args()
    torch.set_num_threads(1)
    sizes = (1, 100) if args.quick else (1, 100, 10_000)
    unique = 30 if args.quick else 100
    templates = box_problems(unique)
    template_modes = solve(templates, "lemke").mode

    loop_lemke = best_time(lambda: solve(templates, "lemke"), 1 if args.quick else 3) / unique
    qp_subset = templates[: min(unique, 30)]
    loop_qp = best_time(lambda: solve(qp_subset, "qp"), 1) / qp_subset.batch_shape[0]

    rows = []
    for size in sizes:
        index = torch.arange(size) % unique
        problem = templates[index]
        modes = template_modes[index]
        repeats = 20 if size < 10_000 else 5
        mode_time = best_time(lambda p=problem, m=modes: solve_mode(p, m), repeats)
        pgs_time = best_time(lambda p=problem: solve(p, "pgs"), max(1, repeats // 4))
        for method, seconds in (
            ("solve_mode (batched)", mode_time),
            ("pgs (batched)", pgs_time),
            ("lemke (per-problem loop)", loop_lemke * size),
            ("qp / OSQP (per-problem loop)", loop_qp * size),
        ):
            per_problem = seconds / size
            rows.append(
                {
                    "B": size,
                    "method": method,
                    "total_ms": 1e3 * seconds,
                    "us_per_problem": 1e6 * per_problem,
                    "speedup_vs_qp_loop": loop_qp / per_problem,
                }
            )

    machine = platform.processor() or platform.machine()
    print(f"Contact solvers, one thread, {machine}, torch {torch.__version__}")
    print()
    print("| B | method | total (ms) | µs / problem | speed-up vs QP loop |")
    print("|---:|---|---:|---:|---:|")
    for row in rows:
        print(
            f"| {row['B']:,} | {row['method']} | {row['total_ms']:.2f} | "
            f"{row['us_per_problem']:.2f} | {row['speedup_vs_qp_loop']:.0f}× |"
        )
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "machine": platform.platform(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "rows": rows,
    }
    if not args.quick:
        RESULTS.write_text(json.dumps(payload, indent=2))
        print(f"\nwrote {RESULTS}")


if __name__ == "__main__":
    main()
