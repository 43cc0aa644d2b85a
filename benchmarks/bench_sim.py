"""Simulator throughput: batched planar boxes vs MuJoCo stepping one box, in one run.

Boxes on the ground (four corner slots each), a third sliding, a third tipping over a corner,
a third resting, stepped ``T`` times at B = 1, 64 and 1,024 scenes, one thread, and the time of
the contact problem's assembly alone (:func:`~torchcontact.sim.contact_problem`, every slot,
best of several repetitions) at the same states. MuJoCo (the
optional ``bench`` extra) steps one free box on a plane for the same number of steps; its
steps per second on one core is the reference for the ratio. Prints a markdown table and writes
``benchmarks/results/bench_sim.json``.

    python benchmarks/bench_sim.py [--quick]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import platform
import time
from pathlib import Path

import torch

from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import (
    SOLVED_BY_GUESS,
    Body,
    Scene,
    SceneState,
    Simulator,
    contact_problem,
)

RESULTS = Path(__file__).resolve().parent / "results" / "bench_sim.json"
MUJOCO_BOX = """
<mujoco>
  <option timestep="0.01"/>
  <worldbody>
    <geom type="plane" size="50 50 0.1" friction="0.5"/>
    <body pos="0 0 0.25">
      <freejoint/>
      <geom type="box" size="0.5 0.25 0.25" mass="2" friction="0.5"/>
    </body>
  </worldbody>
</mujoco>
"""


def box_states(sim: Simulator, count: int) -> SceneState:
    """``count`` boxes: sliding at 1 m/s, balanced past a corner (tipping), or resting."""
    kind = torch.arange(count) % 3
    theta = torch.where(kind == 1, 1.2, 0.0).to(torch.float64)
    corner = torch.tensor([-0.5, -0.25], dtype=torch.float64)
    cos, sin = torch.cos(theta), torch.sin(theta)
    center = -torch.stack(
        [cos * corner[0] - sin * corner[1], sin * corner[0] + cos * corner[1]], -1
    )
    q = torch.stack([center[:, 0], center[:, 1], theta], dim=-1)
    v = torch.zeros(count, 3, dtype=torch.float64)
    v[:, 0] = torch.where(kind == 0, 1.0, 0.0)
    return sim.initial_state(q=q.unsqueeze(1), v=v.unsqueeze(1))


def time_torchcontact(sim: Simulator, count: int, steps: int) -> tuple[float, float]:
    """Seconds for ``steps`` steps of ``count`` scenes, and the fast-path share."""
    state = box_states(sim, count)
    sim.rollout(state, steps=2)  # warm-up
    start = time.perf_counter()
    with torch.no_grad():
        run = sim.rollout(state, steps=steps)
    seconds = time.perf_counter() - start
    return seconds, float((run.solver == SOLVED_BY_GUESS).double().mean())


def time_assembly(sim: Simulator, count: int, repeats: int) -> float:
    """Milliseconds for one :func:`contact_problem` of ``count`` scenes, best of 5 runs of
    ``repeats``."""
    state = box_states(sim, count)
    best = float("inf")
    with torch.no_grad():
        contact_problem(sim.scene, state)  # warm-up (builds the scene's tables)
        for _ in range(5):
            start = time.perf_counter()
            for _ in range(repeats):
                contact_problem(sim.scene, state)
            best = min(best, (time.perf_counter() - start) / repeats)
    return 1e3 * best


def time_mujoco(steps: int) -> float | None:
    """Seconds for MuJoCo to step one sliding box ``steps`` times; ``None`` if not installed."""
    if importlib.util.find_spec("mujoco") is None:
        return None
    import mujoco  # an optional dependency (the bench extra)

    model = mujoco.MjModel.from_xml_string(MUJOCO_BOX)
    data = mujoco.MjData(model)
    data.qvel[0] = 1.0
    mujoco.mj_step(model, data)
    start = time.perf_counter()
    for _ in range(steps):
        mujoco.mj_step(model, data)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small sizes, for smoke tests")
    args = parser.parse_args()
    torch.set_num_threads(1)
    scene = Scene(
        bodies=(
            Body("ground", HalfPlane.ground(), kind="static"),
            Body("box", Polygon.box(1.0, 0.5), mass=2.0),
        ),
        friction=0.5,
        h=0.01,
    )
    sim = Simulator(scene)
    sizes = (1, 64) if args.quick else (1, 64, 1024)
    steps = 20 if args.quick else 200
    mujoco_seconds = time_mujoco(20 * steps)
    mujoco_rate = None if mujoco_seconds is None else 20 * steps / mujoco_seconds

    rows = []
    for count in sizes:
        seconds, fast = time_torchcontact(sim, count, steps)
        assembly = time_assembly(sim, count, steps // 4)
        rate = count * steps / seconds
        rows.append(
            {
                "B": count,
                "box_steps_per_s": rate,
                "ms_per_step": 1e3 * seconds / steps,
                "assembly_ms": assembly,
                "fast_path_share": fast,
                "ratio_to_mujoco": None if mujoco_rate is None else rate / mujoco_rate,
            }
        )

    machine = platform.processor() or platform.machine()
    print(f"Planar box simulation, one thread, {machine}, torch {torch.__version__}")
    if mujoco_rate is None:
        print("MuJoCo not installed (pip install -e '.[bench]'): no reference column.")
    else:
        print(f"MuJoCo one box on a plane: {mujoco_rate:,.0f} steps/s on one core")
    print()
    print("| B | ms / step | assembly ms | box-steps / s | fast path | ratio to MuJoCo steps / s |")
    print("|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        ratio = "n/a" if row["ratio_to_mujoco"] is None else f"{row['ratio_to_mujoco']:.2f}×"
        print(
            f"| {row['B']:,} | {row['ms_per_step']:.2f} | {row['assembly_ms']:.2f} "
            f"| {row['box_steps_per_s']:,.0f} "
            f"| {100 * row['fast_path_share']:.0f}% | {ratio} |"
        )
    if not args.quick:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "machine": platform.platform(),
            "torch": torch.__version__,
            "threads": torch.get_num_threads(),
            "steps": steps,
            "mujoco_steps_per_s": mujoco_rate,
            "rows": rows,
        }
        RESULTS.write_text(json.dumps(payload, indent=2))
        print(f"\nwrote {RESULTS}")


if __name__ == "__main__":
    main()
