"""The main job: a planar contact scene, solved and checked, with a plot and a summary.

    python -m torchcontact.demo --out runs/demo

Steps a box that slides to a stop and a tall box pushed over its front corner with the exact
LCP solver, replays every step with the mode-decoupled solve, and compares the solvers on a
batch of random problems. Writes ``demo.png`` and ``summary.md`` to ``--out``.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import torch

from torchcontact.contact import (
    BoxRollout,
    planar_box_problem,
    rollout_planar_box,
    solve,
    solve_mode,
)

GRAVITY = 9.81
MU = 0.4
STEP = 0.01


@dataclass(frozen=True)
class DemoArgs:
    """Arguments of the demo.

    Attributes:
        out: folder for ``demo.png`` and ``summary.md``.
        problems: random problems in the solver comparison.
        seed: random seed.
    """

    out: Path = Path("runs/demo")
    problems: int = 2000
    seed: int = 0


def run(args: DemoArgs) -> str:
    """Run the demo and return the markdown summary it wrote."""
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)  # small batched solves: one thread is fastest and steadiest
    args.out.mkdir(parents=True, exist_ok=True)
    dtype = torch.float64
    box: dict[str, Any] = {"mu": MU, "h": STEP, "corners": (0, 1, 2, 3)}

    slide = rollout_planar_box(
        q=torch.tensor([0.0, 0.25, 0.0], dtype=dtype),
        v=torch.tensor([1.0, 0.0, 0.0], dtype=dtype),
        steps=40,
        **box,
    )
    time_axis = STEP * torch.arange(slide.v.shape[0], dtype=dtype)
    slide_error = (slide.v[:, 0] - (1.0 - MU * GRAVITY * time_axis).clamp(min=0.0)).abs().max()

    force = 0.9 * MU * 2.0 * GRAVITY
    height = 1.1 * 2.0 * GRAVITY * 0.25 / force
    tip = rollout_planar_box(
        q=torch.tensor([0.0, 0.5, 0.0], dtype=dtype),
        v=torch.zeros(3, dtype=dtype),
        steps=60,
        half_extents=(0.25, 0.5),
        force=torch.tensor([force, 0.0], dtype=dtype),
        force_point=(-0.25, height - 0.5),
        **box,
    )

    generator = torch.Generator().manual_seed(args.seed)
    count = args.problems
    theta = 0.3 * (torch.rand(count, generator=generator, dtype=dtype) - 0.5)
    height_cm = 0.25 * torch.cos(theta) + 0.5 * torch.sin(theta).abs()
    q = torch.stack([torch.zeros_like(theta), height_cm, theta], dim=-1)
    v = torch.randn(count, 3, generator=generator, dtype=dtype)
    push = 5.0 * torch.randn(count, 2, generator=generator, dtype=dtype)
    problem = planar_box_problem(q=q, v=v, force=push, **box)
    timings = {}
    start = time.perf_counter()
    exact = solve(problem, "lemke")
    timings["lemke"] = time.perf_counter() - start
    start = time.perf_counter()
    decoupled = solve_mode(problem, exact.mode)
    timings["solve_mode"] = time.perf_counter() - start
    start = time.perf_counter()
    pgs = solve(problem, "pgs")
    timings["pgs"] = time.perf_counter() - start
    mode_error = (decoupled.v_next - exact.v_next).abs().max()
    pgs_error = (pgs.v_next - exact.v_next).abs().max()

    _plot(slide, tip, args.out / "demo.png")
    lines = [
        "# torchcontact demo",
        "",
        f"Box sliding at 1 m/s, μ = {MU}: max |v − max(v₀ − μ g t, 0)| = {slide_error:.1e} m/s.",
        f"Tall box pushed at 1.1× the tipping height: angle after 0.6 s = "
        f"{math.degrees(tip.q[-1, 2].item()):+.2f}°, first-step modes {tip.mode[0].tolist()}.",
        "",
        f"{count} random box problems (modes seen: {sorted(set(exact.mode.flatten().tolist()))}):",
        "",
        "| solver | time (ms) | µs / problem | max error of v⁺ vs Lemke | converged |",
        "|---|---:|---:|---:|---:|",
        f"| lemke (loop) | {1e3 * timings['lemke']:.1f} | {1e6 * timings['lemke'] / count:.1f} "
        f"| 0 | {int(exact.status.converged.sum())}/{count} |",
        f"| solve_mode (batched) | {1e3 * timings['solve_mode']:.1f} "
        f"| {1e6 * timings['solve_mode'] / count:.2f} | {mode_error:.1e} "
        f"| {int(decoupled.status.converged.sum())}/{count} |",
        f"| pgs (batched) | {1e3 * timings['pgs']:.1f} | {1e6 * timings['pgs'] / count:.2f} "
        f"| {pgs_error:.1e} | {int(pgs.status.converged.sum())}/{count} |",
        "",
        "Plot: demo.png",
    ]
    summary = "\n".join(lines) + "\n"
    (args.out / "summary.md").write_text(summary)
    return summary


def _plot(slide: BoxRollout, tip: BoxRollout, path: Path) -> None:
    """Velocity of the sliding box and angle and corner forces of the tipping box."""
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.5))
    t_slide = STEP * torch.arange(slide.v.shape[0])
    axes[0].plot(t_slide, slide.v[:, 0], "o", ms=3, label="Lemke")
    axes[0].plot(t_slide, (1.0 - MU * GRAVITY * t_slide).clamp(min=0.0), label="closed form")
    axes[0].set(xlabel="time (s)", ylabel="vx (m/s)", title="sliding to a stop")
    axes[0].legend()
    t_tip = STEP * torch.arange(tip.q.shape[0])
    axes[1].plot(t_tip, torch.rad2deg(tip.q[:, 2]))
    axes[1].set(xlabel="time (s)", ylabel="angle (deg)", title="pushed over its front corner")
    for slot, name in ((0, "back-bottom"), (1, "front-bottom")):
        axes[2].plot(t_tip[1:], tip.pn[:, slot] / STEP, label=name)
    axes[2].set(xlabel="time (s)", ylabel="normal force (N)", title="corner forces while tipping")
    axes[2].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> None:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawTextHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=DemoArgs.out, help="output folder")
    parser.add_argument("--problems", type=int, default=DemoArgs.problems, help="random problems")
    parser.add_argument("--seed", type=int, default=DemoArgs.seed, help="random seed")
    namespace = parser.parse_args()
    print(run(DemoArgs(out=namespace.out, problems=namespace.problems, seed=namespace.seed)))


if __name__ == "__main__":
    main()
