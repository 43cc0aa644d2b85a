"""Spatial simulator throughput: batched boxes on a plane vs MuJoCo, in one run, one thread.

Boxes (half extents 0.5 × 0.25 × 0.25 m, 2 kg, μ = 0.5, h = 0.01 s, eight friction
directions) on the ground: a third sliding at 1 m/s, a third tumbling (standing on an edge,
tilted 1.2 rad, falling over), a third resting, stepped ``T`` times at B = 1, 64, 1,024 and
4,096 scenes (``torch.no_grad()``). MuJoCo (the optional ``bench`` extra) steps the same box in
the same three states on one core, two ways: one ``mj_step`` loop per state (what a user
stepping one box writes), and ``mujoco.rollout`` with one model per scene and one ``MjData``
(one thread) over the same batch of B = 4,096 initial states. The faster of the two is the
per-core reference of the ratios. Every measurement runs once per round, in turn, for 3 rounds,
and keeps its best. Prints a markdown table and writes
``benchmarks/results/bench_sim3d.json``.

    python benchmarks/bench_sim3d.py [--quick] [--profile] [--device cuda] [--sizes 1,1024]
        [--steps 50] [--out results.json]

``--device cuda`` steps the batch on the GPU (B = 1, 1,024, 16,384 and 65,536 by default,
the clock read after ``torch.cuda.synchronize``); MuJoCo, a CPU reference, is left out there.

``--profile`` prints torch.profiler's top operators and cProfile's torchcontact functions for
one step at B = 4,096.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import importlib.util
import json
import platform
import time
from collections.abc import Callable
from pathlib import Path

import torch
from _timing import (  # benchmarks/ is on sys.path when run as a script
    device_name,
    parse_device,
    parse_sizes,
    pin_to_quietest_cpu,
    synchronize,
)

from torchcontact.geometry import Box, HalfSpace
from torchcontact.sim import SOLVED_BY_GUESS, Body, Scene, SceneState, Simulator

RESULTS = Path(__file__).resolve().parent / "results" / "bench_sim3d.json"
HALF_EXTENTS = (0.5, 0.25, 0.25)
MASS, FRICTION, H = 2.0, 0.5, 0.01
TILT = 1.2  # rad, the tumbling third's initial rotation about −y (standing on an edge)
MUJOCO_BOX = f"""
<mujoco>
  <option timestep="{H}"/>
  <worldbody>
    <geom type="plane" size="50 50 0.1" friction="{FRICTION}"/>
    <body pos="0 0 {HALF_EXTENTS[2]}">
      <freejoint/>
      <geom type="box" size="{" ".join(map(str, HALF_EXTENTS))}" mass="{MASS}"
            friction="{FRICTION}"/>
    </body>
  </worldbody>
</mujoco>
"""


def box_poses(count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(count, 7)`` poses and ``(count, 6)`` twists: sliding at 1 m/s along x, standing on an
    edge tilted by :data:`TILT` (tumbling), or resting, in turn."""
    kind = torch.arange(count) % 3
    theta = torch.where(kind == 1, TILT, 0.0).to(torch.float64)
    # A rotation by θ about −y maps the x–z plane like the planar rotation by θ maps x–y; the
    # edge through the corner (−a, ·, −c) is put on the ground at the origin.
    a, c = HALF_EXTENTS[0], HALF_EXTENTS[2]
    cos, sin = torch.cos(theta), torch.sin(theta)
    x = -(cos * -a - sin * -c)
    z = -(sin * -a + cos * -c)
    q = torch.zeros(count, 7, dtype=torch.float64)
    q[:, 0], q[:, 2] = x, z
    q[:, 3], q[:, 5] = torch.cos(theta / 2), -torch.sin(theta / 2)
    v = torch.zeros(count, 6, dtype=torch.float64)
    v[:, 0] = torch.where(kind == 0, 1.0, 0.0)
    return q, v


def box_states(sim: Simulator, count: int, device: torch.device) -> SceneState:
    q, v = box_poses(count)
    return sim.initial_state(q=q.unsqueeze(1).to(device), v=v.unsqueeze(1).to(device))


def torchcontact_timer(
    sim: Simulator, count: int, steps: int, device: torch.device
) -> Callable[[], float]:
    """A timer of ``steps`` steps of ``count`` scenes on ``device``: each call returns
    box-steps/s of one rollout (warmed up once here)."""
    state = box_states(sim, count, device)
    with torch.no_grad():
        sim.rollout(state, steps=2)

    def measure() -> float:
        with torch.no_grad():
            synchronize(device)
            start = time.perf_counter()
            sim.rollout(state, steps=steps)
            synchronize(device)
            return count * steps / (time.perf_counter() - start)

    return measure


def fast_path_share(sim: Simulator, count: int, steps: int, device: torch.device) -> float:
    """The share of box-steps solved without an exact solver."""
    with torch.no_grad():
        run = sim.rollout(box_states(sim, count, device), steps=steps)
    return float((run.solver == SOLVED_BY_GUESS).double().mean())


def mujoco_states(count: int) -> tuple[object, list[list[float]]]:
    """The MuJoCo model and its qpos + qvel for the :func:`box_poses` states (a free joint's
    qvel is the linear velocity in the world frame and the angular one in the body frame; the
    states start at rest or translating, so both agree)."""
    import mujoco  # an optional dependency (the bench extra)

    model = mujoco.MjModel.from_xml_string(MUJOCO_BOX)
    q, v = box_poses(count)
    return model, torch.cat([q, v], dim=-1).tolist()


def mujoco_loop_timer(steps: int) -> Callable[[], float]:
    """A timer of one ``mj_step`` loop per state (three states, ``steps`` steps each): each call
    returns steps/s."""
    import mujoco

    model, states = mujoco_states(3)
    data = mujoco.MjData(model)

    def measure() -> float:
        elapsed = 0.0
        for state in states:
            mujoco.mj_resetData(model, data)
            data.qpos[:], data.qvel[:] = state[:7], state[7:]
            mujoco.mj_forward(model, data)
            start = time.perf_counter()
            for _ in range(steps):
                mujoco.mj_step(model, data)
            elapsed += time.perf_counter() - start
        return 3 * steps / elapsed

    return measure


def mujoco_rollout_timer(count: int, steps: int) -> Callable[[], float]:
    """A timer of ``mujoco.rollout`` with ``count`` models and one ``MjData`` (so one thread),
    ``steps`` steps each: each call returns steps/s."""
    import mujoco
    import numpy as np
    from mujoco import rollout

    model, states = mujoco_states(count)
    data = mujoco.MjData(model)
    full = np.zeros((count, mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS)))
    for b, state in enumerate(states):
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:] = state[:7], state[7:]
        mujoco.mj_getState(model, data, full[b], mujoco.mjtState.mjSTATE_FULLPHYSICS)
    models = [model] * count
    rollout.rollout(models, data, full, nstep=2)  # warm-up

    def measure() -> float:
        start = time.perf_counter()
        rollout.rollout(models, data, full, nstep=steps)
        return count * steps / (time.perf_counter() - start)

    return measure


def profile_one_step(sim: Simulator, count: int, device: torch.device) -> None:
    """Print torch.profiler's top operators (self CPU time) and cProfile's torchcontact functions
    (cumulative time) for one step of ``count`` scenes, after three steps (as in a rollout,
    where the previous modes are known)."""
    import cProfile
    import pstats

    from torch.profiler import ProfilerActivity, profile

    state = box_states(sim, count, device)
    with torch.no_grad():
        for _ in range(3):  # warm-up: the first step starts from unknown modes
            state = sim.step(state).state
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            sim.step(state)
        profiler = cProfile.Profile()
        profiler.runcall(sim.step, state)
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
    pstats.Stats(profiler).sort_stats("cumulative").print_stats("torchcontact", 30)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small sizes, for smoke tests")
    parser.add_argument("--profile", action="store_true", help="profile one step at B = 4,096")
    parser.add_argument("--device", default="cpu", help="where the batch is stepped (cuda)")
    parser.add_argument("--sizes", help="comma-separated batch sizes B (overrides the default)")
    parser.add_argument("--steps", type=int, help="steps per rollout (overrides the default)")
    parser.add_argument("--out", type=Path, default=RESULTS, help="the JSON results file")
    args = parser.parse_args()
    device = parse_device(args.device)
    torch.set_num_threads(1)
    cpu = pin_to_quietest_cpu(probes=2 if args.quick else 5)
    scene = Scene(
        bodies=(
            Body("ground", HalfSpace.ground(), kind="static"),
            Body("box", Box(list(HALF_EXTENTS)), mass=MASS),
        ),
        gravity=(0.0, 0.0, -9.81),
        friction=FRICTION,
        h=H,
        friction_directions=8,
    )
    sim = Simulator(scene)
    if args.profile:
        profile_one_step(sim, 4096, device)
        return
    if device.type == "cuda":
        sizes = (1, 1024) if args.quick else (1, 1024, 16384, 65536)
        steps = 10 if args.quick else 50
    else:
        sizes = (1, 64) if args.quick else (1, 64, 1024, 4096)
        steps = 10 if args.quick else 100
    sizes = parse_sizes(args.sizes) if args.sizes else sizes
    steps = args.steps or steps
    repeats = 1 if args.quick else 3

    # Every timer runs once per round, in turn, and keeps its best: on a shared machine the
    # load changes during a run, and interleaving exposes every method to the same load.
    timers = {count: torchcontact_timer(sim, count, steps, device) for count in sizes}
    # MuJoCo is a CPU reference: on a GPU the rows are reported without it.
    have_mujoco = device.type == "cpu" and importlib.util.find_spec("mujoco") is not None
    if have_mujoco:
        timers["mujoco_loop"] = mujoco_loop_timer(20 * steps)
        timers["mujoco_rollout"] = mujoco_rollout_timer(max(sizes), steps)
    best = dict.fromkeys(timers, 0.0)
    for _ in range(repeats):
        for key, measure in timers.items():
            best[key] = max(best[key], measure())
    mujoco_loop = best.get("mujoco_loop")
    mujoco_rollout = best.get("mujoco_rollout")
    reference = max(mujoco_loop or 0.0, mujoco_rollout or 0.0) or None

    rows = []
    for count in sizes:
        rate = best[count]
        rows.append(
            {
                "B": count,
                "box_steps_per_s": rate,
                "ms_per_step": 1e3 * count / rate,
                "fast_path_share": fast_path_share(sim, count, steps, device),
                "ratio_to_mujoco_loop": None if mujoco_loop is None else rate / mujoco_loop,
                "ratio_to_mujoco_rollout": (
                    None if mujoco_rollout is None else rate / mujoco_rollout
                ),
            }
        )

    machine = device_name(device)
    print(f"Spatial box simulation, one thread, {device}: {machine}, torch {torch.__version__}")
    if reference is None:
        print("MuJoCo not installed (pip install -e '.[bench]'): no reference column.")
    else:
        print(f"MuJoCo mj_step loop, one box: {mujoco_loop:,.0f} steps/s on one core")
        print(f"MuJoCo rollout, {max(sizes):,} models, one thread: {mujoco_rollout:,.0f} steps/s")
    print()
    print("| B | ms / step | box-steps / s | fast path | vs MuJoCo loop | vs MuJoCo rollout |")
    print("|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        ratios = [
            "n/a" if row[key] is None else f"{row[key]:.3f}×"
            for key in ("ratio_to_mujoco_loop", "ratio_to_mujoco_rollout")
        ]
        print(
            f"| {row['B']:,} | {row['ms_per_step']:.2f} | {row['box_steps_per_s']:,.0f} "
            f"| {100 * row['fast_path_share']:.0f}% | {ratios[0]} | {ratios[1]} |"
        )
    if reference is not None:
        ratio = rows[-1]["box_steps_per_s"] / reference
        verdict = "met" if ratio >= 1.0 else "not met"
        print(
            f"\nTarget box-steps/s at B = {rows[-1]['B']:,} ≥ 1.0× MuJoCo per core: "
            f"{ratio:.3f}×, {verdict}"
        )
    if not args.quick or args.out != RESULTS:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "machine": platform.platform(),
            "device": str(device),
            "device_name": machine,
            "cpu": cpu,
            "torch": torch.__version__,
            "mujoco": None if not have_mujoco else importlib.metadata.version("mujoco"),
            "threads": torch.get_num_threads(),
            "steps": steps,
            "repeats": repeats,
            "mujoco_loop_steps_per_s": mujoco_loop,
            "mujoco_rollout_steps_per_s": mujoco_rollout,
            "mujoco_rollout_batch": max(sizes),
            "rows": rows,
        }
        args.out.write_text(json.dumps(payload, indent=2))
        print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
