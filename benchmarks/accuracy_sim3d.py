"""Accuracy beside speed: torchcontact's spatial simulator vs MuJoCo, on closed-form scenes.

Three scenes with a closed-form answer, each built twice with the same sizes, masses, friction
and time step (h = 0.01 s): as a torchcontact :class:`~torchcontact.sim.Scene` and as an MJCF
string. MuJoCo runs with its default settings (pyramidal cone, soft contacts) and with
``cone="elliptic"`` and ``noslip_iterations="10"`` (its recommended remedy for creep). The
inclines tilt gravity, not the ground (as ``tests/sim/test_spatial.py`` does).

- **creep**: a box (0.2 × 0.2 × 0.1 m, 1 kg) on a 20° incline with μ = 0.5 > tan 20°: it must not
  move. Its mean speed down the slope over 2 s (distance travelled along the slope / 2 s), and
  over the second half alone (the steady creep, after any settling into soft contact).
- **tipping threshold**: a 0.2 m cube (1 kg, μ = 0.8) pushed at 5 cm/s by a frictionless sphere
  (radius 2 cm) whose centre is at height H tips iff H > w / (2 μ) = 0.125 m. The cube starts
  sliding at the pusher's speed, so that the push is the friction force from the first step (a
  cube at rest would get an impulsive kick, m v / h on top of μ m g, in the first step, which
  tips it from a lower H). The threshold H is found by bisection (tipped: tilted more than
  0.02 rad at some step of 150, 7.5 cm of push; just above the threshold the tilt grows slowly);
  its relative error to w / (2 μ). MuJoCo's pusher is a mocap body moved every step, touching
  only the box, through one explicit frictionless contact pair (condim 1).
- **rolling**: a sphere (radius 0.1 m, 1 kg, μ = 0.5) on a 30° incline rolls at
  a = (5/7) g sin θ; the relative error of its acceleration between t = 0.1 s and 0.5 s.

The speed column is box-steps per second on one core, on the creep scene: torchcontact stepping a
batch of 1,024 scenes, MuJoCo an ``mj_step`` loop on one box. Prints a markdown table and writes
``benchmarks/results/accuracy_sim3d.json``.

    python benchmarks/accuracy_sim3d.py [--quick]
"""

from __future__ import annotations

import argparse
import importlib.metadata
import importlib.util
import json
import math
import platform
import time
from collections.abc import Callable
from pathlib import Path

import torch
from _timing import pin_to_quietest_cpu  # benchmarks/ is on sys.path when run as a script

from torchcontact.geometry import Box, HalfSpace, Sphere
from torchcontact.sim import Body, Scene, Simulator

RESULTS = Path(__file__).resolve().parent / "results" / "accuracy_sim3d.json"
G, H = 9.81, 0.01
IDENTITY = (1.0, 0.0, 0.0, 0.0)
CREEP_THETA, CREEP_MU, CREEP_HALF = math.radians(20.0), 0.5, (0.1, 0.1, 0.05)
TIP_MU, TIP_HALF, TIP_RADIUS, TIP_SPEED, TIP_STEPS = 0.8, 0.1, 0.02, 0.05, 150
TIP_THRESHOLD = 2 * TIP_HALF / (2 * TIP_MU)  # w / (2 μ)
TIPPED = 0.02  # rad, the largest tilt over the push that counts as tipping
BRACKET = (0.6, 1.5)  # the bisection's start, in units of w / (2 μ)
ROLL_THETA, ROLL_MU, ROLL_RADIUS = math.radians(30.0), 0.5, 0.1
CREEP_KEYS = ("creep_m_per_s", "steady_creep_m_per_s")
MUJOCO_SETTINGS = {
    "MuJoCo, defaults": "",
    "MuJoCo, elliptic + noslip 10": 'cone="elliptic" noslip_iterations="10"',
}


def tilted(theta: float) -> tuple[float, float, float]:
    """Gravity of an incline of angle ``theta`` whose slope runs down along ``+x``."""
    return (G * math.sin(theta), 0.0, -G * math.cos(theta))


def pose(x: float, z: float, batch: int = 1) -> torch.Tensor:
    """``(batch, 1, 7)`` poses at ``(x, 0, z)``, unrotated."""
    return torch.tensor([[[x, 0.0, z, *IDENTITY]]], dtype=torch.float64).expand(batch, 1, 7)


def tilt_of(quaternion: list[float]) -> float:
    """Rotation angle (rad) of a unit quaternion ``(w, x, y, z)``."""
    return 2.0 * math.atan2(math.hypot(*quaternion[1:]), abs(quaternion[0]))


def bisect_threshold(tips: Callable[[float], bool], iterations: int) -> float:
    """The height H at which ``tips(H)`` turns true, by bisection on [0.6, 1.5] × w / (2 μ)
    (asymmetric, so that no midpoint falls on the threshold itself)."""
    low, high = BRACKET[0] * TIP_THRESHOLD, BRACKET[1] * TIP_THRESHOLD
    if tips(low) or not tips(high):
        raise RuntimeError(f"the tipping threshold is not bracketed by {BRACKET} × w / (2 μ)")
    for _ in range(iterations):
        middle = 0.5 * (low + high)
        low, high = (low, middle) if tips(middle) else (middle, high)
    return 0.5 * (low + high)


# ----------------------------------------------------------------------------- torchcontact


def creep_speeds(x: list[float]) -> tuple[float, float]:
    """Mean speeds down the slope over the whole run and over its second half, from the
    positions ``x`` along the slope at every step (``steps + 1`` of them)."""
    steps = len(x) - 1
    half = steps // 2
    return (x[-1] - x[0]) / (steps * H), (x[-1] - x[half]) / ((steps - half) * H)


def torchcontact_creep(steps: int) -> tuple[float, float]:
    box = Body("box", Box(list(CREEP_HALF)), mass=1.0)
    simulator = Simulator(
        Scene(
            bodies=(Body("ground", HalfSpace.ground(), kind="static"), box),
            gravity=tilted(CREEP_THETA),
            friction=CREEP_MU,
            h=H,
        )
    )
    with torch.no_grad():
        run = simulator.rollout(simulator.initial_state(q=pose(0.0, CREEP_HALF[2])), steps=steps)
    return creep_speeds(run.q[:, 0, 0, 0].tolist())


def torchcontact_tips(height: float) -> bool:
    scene = Scene(
        bodies=(
            Body("ground", HalfSpace.ground(), kind="static"),
            Body("box", Box([TIP_HALF] * 3), mass=1.0),
            Body("pusher", Sphere(TIP_RADIUS), kind="kinematic"),
        ),
        friction=TIP_MU,
        pair_friction={("box", "pusher"): 0.0},
        h=H,
    )
    simulator = Simulator(scene)
    v = torch.zeros(1, 1, 6, dtype=torch.float64)
    v[..., 0] = TIP_SPEED
    state = simulator.initial_state(
        q=pose(0.0, TIP_HALF), v=v, q_kinematic=pose(-TIP_HALF - TIP_RADIUS, height)
    )
    controls = torch.zeros(TIP_STEPS, 1, 1, 6, dtype=torch.float64)
    controls[..., 0] = TIP_SPEED
    with torch.no_grad():
        run = simulator.rollout(state, steps=TIP_STEPS, controls=controls)
    return max(tilt_of(quaternion) for quaternion in run.q[:, 0, 0, 3:].tolist()) > TIPPED


def torchcontact_rolling() -> float:
    ball = Body("ball", Sphere(ROLL_RADIUS), mass=1.0)
    simulator = Simulator(
        Scene(
            bodies=(Body("ground", HalfSpace.ground(), kind="static"), ball),
            gravity=tilted(ROLL_THETA),
            friction=ROLL_MU,
            h=H,
        )
    )
    with torch.no_grad():
        run = simulator.rollout(simulator.initial_state(q=pose(0.0, ROLL_RADIUS)), steps=50)
    return float(run.v[50, 0, 0, 0] - run.v[10, 0, 0, 0]) / (40 * H)


def torchcontact_speed(count: int, steps: int) -> float:
    """Box-steps/s of the creep scene, ``count`` scenes at once, best of 3."""
    simulator = Simulator(
        Scene(
            bodies=(
                Body("ground", HalfSpace.ground(), kind="static"),
                Body("box", Box(list(CREEP_HALF)), mass=1.0),
            ),
            gravity=tilted(CREEP_THETA),
            friction=CREEP_MU,
            h=H,
        )
    )
    state = simulator.initial_state(q=pose(0.0, CREEP_HALF[2], count))
    best = float("inf")
    with torch.no_grad():
        simulator.rollout(state, steps=2)
        for _ in range(3):
            start = time.perf_counter()
            simulator.rollout(state, steps=steps)
            best = min(best, time.perf_counter() - start)
    return count * steps / best


# ----------------------------------------------------------------------------- MuJoCo


def mjcf(
    option: str, gravity: tuple[float, float, float], mu: float, body: str, extra: str = ""
) -> str:
    """A plane of friction ``mu`` and one free body (MJCF ``body`` text) under ``gravity``,
    h = 0.01 s, with the ``<option>`` attributes ``option``."""
    return f"""
<mujoco>
  <option timestep="{H}" gravity="{" ".join(map(str, gravity))}" {option}/>
  <worldbody>
    <geom name="ground" type="plane" size="10 10 0.1" friction="{mu}"/>
    {body}
  </worldbody>
  {extra}
</mujoco>
"""


def mujoco_creep_model(option: str) -> str:
    size = " ".join(map(str, CREEP_HALF))
    body = (
        f'<body pos="0 0 {CREEP_HALF[2]}"><freejoint/>'
        f'<geom type="box" size="{size}" mass="1" friction="{CREEP_MU}"/></body>'
    )
    return mjcf(option, tilted(CREEP_THETA), CREEP_MU, body)


def mujoco_creep(option: str, steps: int) -> tuple[float, float]:
    import mujoco  # an optional dependency (the bench extra)

    model = mujoco.MjModel.from_xml_string(mujoco_creep_model(option))
    data = mujoco.MjData(model)
    x = [float(data.qpos[0])]
    for _ in range(steps):
        mujoco.mj_step(model, data)
        x.append(float(data.qpos[0]))
    return creep_speeds(x)


def mujoco_tips(option: str, height: float) -> bool:
    import mujoco

    body = (
        f'<body pos="0 0 {TIP_HALF}"><freejoint/>'
        f'<geom name="box" type="box" size="{TIP_HALF} {TIP_HALF} {TIP_HALF}" mass="1" '
        f'friction="{TIP_MU}"/></body>'
        f'<body name="pusher" mocap="true" pos="{-TIP_HALF - TIP_RADIUS} 0 {height}">'
        f'<geom name="pusher" type="sphere" size="{TIP_RADIUS}" contype="0" conaffinity="0"/>'
        "</body>"
    )
    # The pusher touches nothing by contype/conaffinity, only the box through this pair.
    pair = '<contact><pair geom1="box" geom2="pusher" condim="1"/></contact>'
    text = mjcf(option, (0.0, 0.0, -G), TIP_MU, body, pair)
    model = mujoco.MjModel.from_xml_string(text)
    data = mujoco.MjData(model)
    data.qvel[0] = TIP_SPEED
    start, largest = -TIP_HALF - TIP_RADIUS, 0.0
    for k in range(TIP_STEPS):
        data.mocap_pos[0] = (start + TIP_SPEED * (k + 1) * H, 0.0, height)
        mujoco.mj_step(model, data)
        largest = max(largest, tilt_of(list(data.qpos[3:7])))
    return largest > TIPPED


def mujoco_rolling(option: str) -> float:
    import mujoco

    body = (
        f'<body pos="0 0 {ROLL_RADIUS}"><freejoint/>'
        f'<geom type="sphere" size="{ROLL_RADIUS}" mass="1" friction="{ROLL_MU}"/></body>'
    )
    text = mjcf(option, tilted(ROLL_THETA), ROLL_MU, body)
    model = mujoco.MjModel.from_xml_string(text)
    data = mujoco.MjData(model)
    velocity = []
    for _ in range(51):
        velocity.append(float(data.qvel[0]))
        mujoco.mj_step(model, data)
    return (velocity[50] - velocity[10]) / (40 * H)


def mujoco_speed(option: str, steps: int) -> float:
    """Steps/s of one box on the creep scene, an ``mj_step`` loop, best of 3."""
    import mujoco

    model = mujoco.MjModel.from_xml_string(mujoco_creep_model(option))
    data = mujoco.MjData(model)
    best = float("inf")
    for _ in range(3):
        mujoco.mj_resetData(model, data)
        start = time.perf_counter()
        for _ in range(steps):
            mujoco.mj_step(model, data)
        best = min(best, time.perf_counter() - start)
    return steps / best


# ----------------------------------------------------------------------------- report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small sizes, for smoke tests")
    args = parser.parse_args()
    torch.set_num_threads(1)
    cpu = pin_to_quietest_cpu(probes=2 if args.quick else 5)
    creep_steps = 20 if args.quick else 200
    iterations = 5 if args.quick else 14
    speed_batch, speed_steps = (64, 10) if args.quick else (1024, 100)
    rolling_expected = 5.0 / 7.0 * G * math.sin(ROLL_THETA)

    rows = [
        {
            "simulator": "torchcontact",
            **dict(zip(CREEP_KEYS, torchcontact_creep(creep_steps), strict=True)),
            "tipping_threshold_m": bisect_threshold(torchcontact_tips, iterations),
            "rolling_acceleration": torchcontact_rolling(),
            "box_steps_per_s": torchcontact_speed(speed_batch, speed_steps),
            "speed_batch": speed_batch,
        }
    ]
    have_mujoco = importlib.util.find_spec("mujoco") is not None
    if have_mujoco:
        for name, option in MUJOCO_SETTINGS.items():
            rows.append(
                {
                    "simulator": name,
                    **dict(zip(CREEP_KEYS, mujoco_creep(option, creep_steps), strict=True)),
                    "tipping_threshold_m": bisect_threshold(
                        lambda height, o=option: mujoco_tips(o, height), iterations
                    ),
                    "rolling_acceleration": mujoco_rolling(option),
                    "box_steps_per_s": mujoco_speed(option, 20 * speed_steps),
                    "speed_batch": 1,
                }
            )
    for row in rows:
        row["tipping_relative_error"] = row["tipping_threshold_m"] / TIP_THRESHOLD - 1.0
        row["rolling_relative_error"] = row["rolling_acceleration"] / rolling_expected - 1.0

    print(f"Accuracy beside speed, spatial scenes, h = {H} s, one thread")
    if not have_mujoco:
        print("MuJoCo not installed (pip install -e '.[bench]'): torchcontact alone.")
    print(
        f"creep over {creep_steps * H:g} s; tipping threshold w/(2μ) = {TIP_THRESHOLD:.4f} m; "
        f"rolling a = (5/7) g sin 30° = {rolling_expected:.4f} m/s²\n"
    )
    print(
        "| simulator | creep (m/s) | steady creep (m/s) | tipping H (m) | tipping error "
        "| rolling a (m/s²) | rolling error | box-steps / s |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for row in rows:
        print(
            f"| {row['simulator']} | {row['creep_m_per_s']:.2e} "
            f"| {row['steady_creep_m_per_s']:.2e} "
            f"| {row['tipping_threshold_m']:.5f} | {100 * row['tipping_relative_error']:+.3f}% "
            f"| {row['rolling_acceleration']:.5f} | {row['rolling_relative_error']:+.1e} "
            f"| {row['box_steps_per_s']:,.0f} |"
        )
    if not args.quick:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "machine": platform.platform(),
            "cpu": cpu,
            "torch": torch.__version__,
            "mujoco": importlib.metadata.version("mujoco") if have_mujoco else None,
            "threads": torch.get_num_threads(),
            "h": H,
            "creep_seconds": creep_steps * H,
            "tipping_threshold_exact_m": TIP_THRESHOLD,
            "bisection_iterations": iterations,
            "rolling_acceleration_exact": rolling_expected,
            "rows": rows,
        }
        RESULTS.write_text(json.dumps(payload, indent=2))
        print(f"\nwrote {RESULTS}")


if __name__ == "__main__":
    main()
