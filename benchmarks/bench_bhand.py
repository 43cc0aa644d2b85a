"""BarrettHand grasp throughput: batched hands closing on a box vs MuJoCo, one run, one thread.

The scene of the BarrettHand grasp test (``tests/sim/test_robots_in_scene.py``): the hand
(``torchcontact/models/bhand.urdf``) palm down above a box (half extents 0.04 × 0.06 × 0.04 m,
0.2 kg, μ = 0.5, h = 0.01 s) resting on the ground, its three fingers (spread 0, finger 3
opposing fingers 1 and 2) servoed from 0.85 rad towards a target ramping closed at 1 rad/s to
1.3 rad, so that they reach the box's vertical faces and squeeze it at their torque limits
(0.2, 0.2, 0.4 N m, gravity compensated). Each of the ``B`` scenes starts with the box shifted
along x by a different amount in ±5 mm, so the batch does not repeat one problem. ``T`` steps
(``torch.no_grad()``), every one with the exact LCP behind it: the fast path's mode guess checked
for consistency, Lemke for the rest.

MuJoCo (the optional ``bench`` extra) steps the same hand, loaded from the same URDF (MuJoCo
turns its ``<mimic>`` tags into joint equalities; the cylinders become capsules, as torchcontact
reads them), with position actuators of the same gains and force limits on the spread and
inner joints, gravity compensation on the finger links, the same box, friction and time step,
from the same initial state and with the same targets: one ``mj_step`` loop on one core. Every
measurement runs once per round, in turn, for 3 rounds, and keeps its best. Prints a markdown
table and writes ``benchmarks/results/bench_bhand.json``.

    python benchmarks/bench_bhand.py [--quick]
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
from _timing import pin_to_quietest_cpu  # benchmarks/ is on sys.path when run as a script

from torchcontact.geometry import Box, HalfSpace
from torchcontact.robots import load
from torchcontact.sim import SOLVED_BY_GUESS, Body, RobotMember, Scene, SceneState, Simulator

RESULTS = Path(__file__).resolve().parent / "results" / "bench_bhand.json"
H, FRICTION = 0.01, 0.5
BOX_HALF_EXTENTS, BOX_MASS = (0.04, 0.06, 0.04), 0.2
#: Servo gains and torque limits of the actuated coordinates (spread, F1, F2, F3 inner).
STIFFNESS = (50.0, 5.0, 5.0, 10.0)
DAMPING = (1.0, 0.05, 0.05, 0.1)
TORQUE_LIMIT = (10.0, 0.2, 0.2, 0.4)
#: Palm down above the box: turned by π about x, palm surface 0.14 m above the ground.
BASE_POSE = (0.0, 0.0, 0.2264, 0.0, 1.0, 0.0, 0.0)
START, CLOSED, RATE = 0.85, 1.3, 1.0  # finger angles (rad) and closing rate (rad/s)
SHIFT = 0.005  # m, the largest shift of a scene's box along x


def simulator() -> Simulator:
    """The torchcontact scene: ground, box, and the servoed hand."""
    member = RobotMember(
        "hand",
        load("bhand"),
        stiffness=torch.tensor(STIFFNESS, dtype=torch.float64),
        damping=torch.tensor(DAMPING, dtype=torch.float64),
        torque_limit=torch.tensor(TORQUE_LIMIT, dtype=torch.float64),
        gravity_compensation=True,
        base_pose=torch.tensor(BASE_POSE, dtype=torch.float64),
    )
    box = Body("box", Box(BOX_HALF_EXTENTS), mass=BOX_MASS)
    ground = Body("ground", HalfSpace.ground(), kind="static")
    return Simulator(Scene(bodies=(ground, box), robots=(member,), friction=FRICTION, h=H))


def box_shifts(count: int) -> torch.Tensor:
    """``(count,)`` the boxes' x shifts, evenly spread over ``[−SHIFT, SHIFT]``."""
    if count == 1:
        return torch.zeros(1, dtype=torch.float64)
    return torch.linspace(-SHIFT, SHIFT, count, dtype=torch.float64)


def targets(steps: int) -> torch.Tensor:
    """``(steps, 4)`` joint targets: spread 0, fingers ramping from ``START`` to ``CLOSED``."""
    ramp = (START + RATE * H * torch.arange(1, steps + 1, dtype=torch.float64)).clamp(max=CLOSED)
    command = torch.zeros(steps, 4, dtype=torch.float64)
    command[:, 1:] = ramp[:, None]
    return command


def initial_state(sim: Simulator, count: int) -> SceneState:
    q = torch.zeros(count, 1, 7, dtype=torch.float64)
    q[:, 0, 0], q[:, 0, 2], q[:, 0, 3] = box_shifts(count), BOX_HALF_EXTENTS[2], 1.0
    q_robot = torch.tensor([0.0, START, START, START], dtype=torch.float64).expand(count, 4)
    return sim.initial_state(q=q, q_robot=q_robot)


def torchcontact_timer(sim: Simulator, count: int, steps: int) -> Callable[[], float]:
    """A timer of a ``steps``-step grasp of ``count`` scenes: each call returns steps/s (one
    step of one scene: the hand and the box)."""
    state = initial_state(sim, count)
    commands = targets(steps)[:, None, :].expand(steps, count, 4)
    with torch.no_grad():
        sim.rollout(state, steps=2, joint_commands=commands[:2])

    def measure() -> float:
        with torch.no_grad():
            start = time.perf_counter()
            sim.rollout(state, steps=steps, joint_commands=commands)
            return count * steps / (time.perf_counter() - start)

    return measure


def grasp_summary(sim: Simulator, count: int, steps: int) -> dict[str, float]:
    """The fast-path share, the grip (total normal force on the box from the fingers at the
    last step, N) and the box's largest drift from its start (m) of one rollout."""
    state = initial_state(sim, count)
    commands = targets(steps)[:, None, :].expand(steps, count, 4)
    with torch.no_grad():
        run = sim.rollout(state, steps=steps, joint_commands=commands)
    # The ground's slots come first (8 box corners), then the fingers' against the box.
    grip = run.pn[-1, :, 8:].sum(-1) / H
    drift = (run.q[:, :, 0, :3] - run.q[:1, :, 0, :3]).norm(dim=-1).amax()
    return {
        "fast_path_share": float((run.solver == SOLVED_BY_GUESS).double().mean()),
        "grip_N": float(grip.mean()),
        "box_drift_m": float(drift),
    }


def mujoco_model() -> object:
    """The MuJoCo model: the URDF hand (MuJoCo's importer) wrapped in a fixed body at
    :data:`BASE_POSE`, capsules for cylinders, position servos with the gains and limits of
    the torchcontact servo, gravity compensation, the box and the ground."""
    import mujoco

    spec = mujoco.MjSpec.from_file(load("bhand").source)
    spec.option.timestep = H
    # MuJoCo's URDF importer keeps cylinders; torchcontact reads them as capsules.
    for geom in spec.geoms:
        if geom.type == mujoco.mjtGeom.mjGEOM_CYLINDER:
            geom.type = mujoco.mjtGeom.mjGEOM_CAPSULE
    spec.compile()
    text = spec.to_xml()
    # The importer fuses the palm into the world body: its contents go into a fixed body at
    # the base pose. The hand's geoms touch the box only (as in torchcontact, no
    # self-contact), its links are gravity compensated.
    hand = text[text.index("<worldbody>") + len("<worldbody>") : text.index("</worldbody>")]
    hand = hand.replace("<body ", '<body gravcomp="1" ')
    hand = hand.replace("<geom ", '<geom contype="2" conaffinity="0" ')
    x, y, z, qw, qx, qy, qz = BASE_POSE
    half = " ".join(map(str, BOX_HALF_EXTENTS))
    world = f"""<default><geom friction="{FRICTION} 0.005 0.0001"/></default>
  <worldbody>
    <geom type="plane" size="5 5 0.1" contype="1" conaffinity="1"/>
    <body name="box" pos="0 0 {BOX_HALF_EXTENTS[2]}">
      <freejoint/>
      <geom type="box" size="{half}" mass="{BOX_MASS}" contype="1" conaffinity="3"/>
    </body>
    <body name="hand" pos="{x} {y} {z}" quat="{qw} {qx} {qy} {qz}">{hand}</body>
  </worldbody>
  <actuator>
"""
    joints = ("bhand_f1_spread", "bhand_f1_inner", "bhand_f2_inner", "bhand_f3_inner")
    for joint, kp, kd, limit in zip(joints, STIFFNESS, DAMPING, TORQUE_LIMIT, strict=True):
        world += (
            f'    <position joint="{joint}" kp="{kp}" kv="{kd}" forcelimited="true" '
            f'forcerange="{-limit} {limit}"/>\n'
        )
    world += "  </actuator>"
    end = text.index("</worldbody>") + len("</worldbody>")
    return mujoco.MjModel.from_xml_string(text[: text.index("<worldbody>")] + world + text[end:])


def mujoco_grasp(steps: int) -> tuple[Callable[[], None], Callable[[], float]]:
    """A ``reset`` of the MuJoCo grasp and a ``run`` of its ``steps`` steps (targets as in
    :func:`targets`) that returns the fingers' total normal force on the box at the end (N)."""
    import mujoco
    import numpy as np

    model = mujoco_model()
    data = mujoco.MjData(model)
    command = targets(steps).tolist()
    box_geom = model.body("box").geomadr[0]
    hand_start = {"bhand_f1_inner": START, "bhand_f2_inner": START, "bhand_f3_inner": START}
    hand_start |= {name.replace("inner", "outer"): START / 3 for name in list(hand_start)}

    def reset() -> None:
        mujoco.mj_resetData(model, data)
        for name, value in hand_start.items():
            data.joint(name).qpos[0] = value
        mujoco.mj_forward(model, data)

    def run() -> float:
        for row in command:
            data.ctrl[:] = row
            mujoco.mj_step(model, data)
        force, grip = np.zeros(6), 0.0
        for index in range(data.ncon):
            contact = data.contact[index]
            other = contact.geom1 if contact.geom2 == box_geom else contact.geom2
            if box_geom in (contact.geom1, contact.geom2) and model.geom_contype[other] == 2:
                mujoco.mj_contactForce(model, data, index, force)
                grip += float(force[0])
        return grip

    return reset, run


def mujoco_loop_timer(steps: int, episodes: int) -> Callable[[], float]:
    """A timer of ``episodes`` grasps of ``steps`` steps, one ``mj_step`` loop each: each call
    returns steps/s."""
    reset, run = mujoco_grasp(steps)

    def measure() -> float:
        elapsed = 0.0
        for _ in range(episodes):
            reset()
            start = time.perf_counter()
            run()
            elapsed += time.perf_counter() - start
        return episodes * steps / elapsed

    return measure


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small sizes, for smoke tests")
    args = parser.parse_args()
    torch.set_num_threads(1)
    cpu = pin_to_quietest_cpu(probes=2 if args.quick else 5)
    sim = simulator()
    sizes = (1, 64) if args.quick else (1, 64, 1024)
    steps = 15 if args.quick else 40  # the fingers reach the box at step 12
    repeats = 1 if args.quick else 3

    timers: dict[object, Callable[[], float]] = {
        count: torchcontact_timer(sim, count, steps) for count in sizes
    }
    have_mujoco = importlib.util.find_spec("mujoco") is not None
    if have_mujoco:
        timers["mujoco_loop"] = mujoco_loop_timer(steps, episodes=100)
    best = dict.fromkeys(timers, 0.0)
    for _ in range(repeats):
        for key, measure in timers.items():
            best[key] = max(best[key], measure())
    reference = best.get("mujoco_loop")

    rows = []
    for count in sizes:
        rate = best[count]
        rows.append(
            {
                "B": count,
                "steps_per_s": rate,
                "ms_per_step": 1e3 * count / rate,
                **grasp_summary(sim, count, steps),
                "ratio_to_mujoco": None if reference is None else rate / reference,
            }
        )

    machine = platform.processor() or platform.machine()
    print(f"BarrettHand grasp, one thread, {machine}, torch {torch.__version__}")
    if reference is None:
        print("MuJoCo not installed (pip install -e '.[bench]'): no reference column.")
    else:
        print(f"MuJoCo mj_step loop, one hand: {reference:,.0f} steps/s on one core")
    print()
    print("| B | ms / step | scene-steps / s | fast path | grip (N) | vs MuJoCo loop |")
    print("|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        ratio = "n/a" if row["ratio_to_mujoco"] is None else f"{row['ratio_to_mujoco']:.3f}×"
        print(
            f"| {row['B']:,} | {row['ms_per_step']:.2f} | {row['steps_per_s']:,.0f} "
            f"| {100 * row['fast_path_share']:.0f}% | {row['grip_N']:.3f} | {ratio} |"
        )
    if reference is not None:
        ratio = rows[-1]["steps_per_s"] / reference
        verdict = "met" if ratio >= 0.3 else "not met"
        print(
            f"\nTarget steps/s at B = {rows[-1]['B']:,} ≥ 0.3× MuJoCo per core: "
            f"{ratio:.3f}×, {verdict}"
        )
    if not args.quick:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "machine": platform.platform(),
            "cpu": cpu,
            "torch": torch.__version__,
            "mujoco": None if not have_mujoco else importlib.metadata.version("mujoco"),
            "threads": torch.get_num_threads(),
            "steps": steps,
            "repeats": repeats,
            "mujoco_loop_steps_per_s": reference,
            "rows": rows,
        }
        RESULTS.write_text(json.dumps(payload, indent=2))
        print(f"\nwrote {RESULTS}")


if __name__ == "__main__":
    main()
