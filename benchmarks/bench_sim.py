"""Simulator throughput: batched planar boxes vs MuJoCo stepping one box, in one run.

Boxes on the ground (four corner slots each), a third sliding, a third tipping over a corner,
a third resting, stepped ``T`` times at B = 1, 64 and 1,024 scenes, one thread pinned to the
quietest CPU (``_timing.pin_to_quietest_cpu``), eagerly and with ``Simulator(compiled=True)``
(its compilation in the warm-up, not timed; the two rollouts alternate, best of 3 each), and the
time of the contact problem's assembly alone (:func:`~torchcontact.sim.contact_problem`, every
slot, best of several repetitions) at the same states. MuJoCo (the
optional ``bench`` extra) steps one free box on a plane for 20 times the number of steps,
before the first size and after each (the best of these is the reference, so that it sees the
load the rows saw); its steps per second on one core is the reference for the ratio. Prints
a markdown table and writes ``benchmarks/results/bench_sim.json``.

    python benchmarks/bench_sim.py [--quick] [--device cuda] [--sizes 1,1024] [--steps 50]
        [--out results.json] [--eager]

``--device cuda`` steps the batch on the GPU (B = 1, 1,024, 16,384 and 65,536 by default,
the clock read after ``torch.cuda.synchronize``); MuJoCo, a CPU reference, is left out there.
``--eager`` leaves out the compiled simulator (its columns are NaN).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import platform
import time
from pathlib import Path

import torch
from _timing import (  # benchmarks/ is on sys.path when run as a script
    device_name,
    parse_device,
    parse_sizes,
    pin_to_quietest_cpu,
    synchronize,
)

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


def box_states(sim: Simulator, count: int, device: torch.device) -> SceneState:
    """``count`` boxes on ``device``: sliding at 1 m/s, balanced past a corner (tipping), or
    resting."""
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
    return sim.initial_state(q=q.unsqueeze(1).to(device), v=v.unsqueeze(1).to(device))


def time_torchcontact(
    sims: tuple[Simulator, ...], count: int, steps: int, device: torch.device
) -> tuple[list[float], float]:
    """Seconds for ``steps`` steps of ``count`` scenes with each simulator (best of 3, the
    simulators' rollouts alternating so that they share the machine's load), and the fast-path
    share of the first."""
    state = box_states(sims[0], count, device)
    seconds = [float("inf")] * len(sims)
    with torch.no_grad():
        for sim in sims:
            sim.rollout(state, steps=3)  # warm-up (a compiled step compiles at its second step)
        for _ in range(3):
            for i, sim in enumerate(sims):
                synchronize(device)
                start = time.perf_counter()
                run = sim.rollout(state, steps=steps)
                synchronize(device)
                seconds[i] = min(seconds[i], time.perf_counter() - start)
                if i == 0:
                    fast = float((run.solver == SOLVED_BY_GUESS).double().mean())
    return seconds, fast


def time_assembly(sim: Simulator, count: int, repeats: int, device: torch.device) -> float:
    """Milliseconds for one :func:`contact_problem` of ``count`` scenes, best of 5 runs of
    ``repeats``."""
    state = box_states(sim, count, device)
    best = float("inf")
    with torch.no_grad():
        contact_problem(sim.scene, state)  # warm-up (builds the scene's tables)
        for _ in range(5):
            synchronize(device)
            start = time.perf_counter()
            for _ in range(repeats):
                contact_problem(sim.scene, state)
            synchronize(device)
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
    parser.add_argument("--device", default="cpu", help="where the batch is stepped (cuda)")
    parser.add_argument("--sizes", help="comma-separated batch sizes B (overrides the default)")
    parser.add_argument("--steps", type=int, help="steps per rollout (overrides the default)")
    parser.add_argument("--out", type=Path, default=RESULTS, help="the JSON results file")
    parser.add_argument("--eager", action="store_true", help="no compiled simulator")
    args = parser.parse_args()
    device = parse_device(args.device)
    torch.set_num_threads(1)
    pinned = pin_to_quietest_cpu()
    scene = Scene(
        bodies=(
            Body("ground", HalfPlane.ground(), kind="static"),
            Body("box", Polygon.box(1.0, 0.5), mass=2.0),
        ),
        friction=0.5,
        h=0.01,
    )
    sim = Simulator(scene)
    sims = (sim,) if args.eager else (sim, Simulator(scene, compiled=True))
    if device.type == "cuda":
        sizes = (1, 1024) if args.quick else (1, 1024, 16384, 65536)
        steps = 20 if args.quick else 50
    else:
        sizes = (1, 64) if args.quick else (1, 64, 1024)
        steps = 20 if args.quick else 200
    sizes = parse_sizes(args.sizes) if args.sizes else sizes
    steps = args.steps or steps
    # MuJoCo is a CPU reference: on a GPU the rows are reported without it.
    timer = time_mujoco if device.type == "cpu" else lambda _steps: None
    # MuJoCo is timed before and after every size (best of them): on a shared machine the load
    # changes during a run, and the reference should see the same load as the rows.
    mujoco_seconds = [timer(20 * steps)]

    rows = []
    for count in sizes:
        timed, fast = time_torchcontact(sims, count, steps, device)
        seconds, compiled_seconds = (*timed, math.nan)[:2]
        assembly = time_assembly(sim, count, max(1, steps // 4), device)
        mujoco_seconds.append(timer(20 * steps))
        rate = count * steps / seconds
        compiled_rate = count * steps / compiled_seconds
        rows.append(
            {
                "B": count,
                "box_steps_per_s": rate,
                "ms_per_step": 1e3 * seconds / steps,
                "compiled_box_steps_per_s": compiled_rate,
                "compiled_ms_per_step": 1e3 * compiled_seconds / steps,
                "assembly_ms": assembly,
                "fast_path_share": fast,
            }
        )
    timed = [t for t in mujoco_seconds if t is not None]
    mujoco_rate = 20 * steps / min(timed) if timed else None
    for row in rows:
        row["ratio_to_mujoco"] = (
            None if mujoco_rate is None else row["box_steps_per_s"] / mujoco_rate
        )
        row["compiled_ratio_to_mujoco"] = (
            None if mujoco_rate is None else row["compiled_box_steps_per_s"] / mujoco_rate
        )

    machine = device_name(device)
    print(f"Planar box simulation, one thread, {device}: {machine}, torch {torch.__version__}")
    if mujoco_rate is None:
        print("MuJoCo not installed (pip install -e '.[bench]'): no reference column.")
    else:
        print(f"MuJoCo one box on a plane: {mujoco_rate:,.0f} steps/s on one core")
    print()
    print(
        "| B | ms / step | compiled ms / step | assembly ms | box-steps / s "
        "| compiled box-steps / s | fast path | ratio to MuJoCo steps / s (compiled) |"
    )
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        ratio = "n/a"
        if mujoco_rate is not None:
            ratio = f"{row['ratio_to_mujoco']:.2f}× ({row['compiled_ratio_to_mujoco']:.2f}×)"
        print(
            f"| {row['B']:,} | {row['ms_per_step']:.2f} | {row['compiled_ms_per_step']:.2f} "
            f"| {row['assembly_ms']:.2f} | {row['box_steps_per_s']:,.0f} "
            f"| {row['compiled_box_steps_per_s']:,.0f} "
            f"| {100 * row['fast_path_share']:.0f}% | {ratio} |"
        )
    if not args.quick or args.out != RESULTS:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "machine": platform.platform(),
            "device": str(device),
            "device_name": machine,
            "torch": torch.__version__,
            "threads": torch.get_num_threads(),
            "pinned_cpu": pinned["pinned_cpu"],
            "steps": steps,
            "mujoco_steps_per_s": mujoco_rate,
            "rows": rows,
        }
        args.out.write_text(json.dumps(payload, indent=2))
        print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
