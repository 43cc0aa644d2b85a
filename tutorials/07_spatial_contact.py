# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 07 · Spatial contact: boxes and spheres in 3D, against closed forms
#
# The planar scenes of tutorial 01 carry over to three dimensions in the same engine: a scene is
# spatial when its shapes are (`Box`, `Sphere`, `Capsule`, `HalfSpace`). A body's pose is its
# position and a unit quaternion `(x, y, z, qw, qx, qy, qz)`, its twist `(v, ω)` in the world
# frame; `q` has shape `(*B, Nd, 7)` and `v` `(*B, Nd, 6)`. Friction is a polyhedral cone of `D`
# directions per contact (`friction_directions`, 8 by default), and every step is still the
# exact Stewart–Trinkle LCP.
#
# We check the simulator against rigid-body mechanics where the answer is known in closed form:
#
# * a sphere on an incline rolls at `a = (5/7) g sin θ` when friction allows, and slides at
#   `a = g (sin θ − μ cos θ)` when `μ < (2/7) tan θ`;
# * a box on an incline flatter than `arctan μ` stays put (no creep), and slides on a steeper one;
# * a box pushed at height `H` by a frictionless finger tips iff `H > w / (2 μ)`;
#
# then picture a box tumbling onto the ground, and put robots inside the physics: the WAM
# carries the BarrettHand to a box and the hand closes on it.
#
# The inclines tilt gravity instead of the ground: the ground stays `z = 0`, and gravity
# `g (sin θ, 0, −cos θ)` pulls down a slope along `+x`.

# %%
import math
import os
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import torch
from mpl_toolkits.mplot3d.art3d import Poly3DCollection

from torchcontact.geometry import Box, HalfSpace, Sphere, quat_to_matrix
from torchcontact.sim import Body, Scene, Simulator

FAST = os.environ.get("TORCHCONTACT_FAST") == "1"
# Figures and files go to the folder named by TORCHCONTACT_OUT, else to a new temporary one.
OUT = Path(os.environ.get("TORCHCONTACT_OUT") or tempfile.mkdtemp(prefix="torchcontact_"))
OUT.mkdir(parents=True, exist_ok=True)
print(f"outputs in {OUT}")

torch.set_default_dtype(torch.float64)
G, H = 9.81, 0.01
IDENTITY = (1.0, 0.0, 0.0, 0.0)
ground = Body("ground", HalfSpace.ground(), kind="static")


def on_incline(theta, mu, body):
    """A simulator of ``body`` on an incline of ``theta`` radians (gravity tilted)."""
    gravity = (G * math.sin(theta), 0.0, -G * math.cos(theta))
    return Simulator(Scene(bodies=(ground, body), gravity=gravity, friction=mu, h=H))


def at(x, z, batch=1):
    """``(batch, 1, 7)`` unrotated poses at ``(x, 0, z)``."""
    return torch.tensor([[[x, 0.0, z, *IDENTITY]]]).expand(batch, 1, 7)


# %% [markdown]
# ## A sphere rolling or sliding down a 30° incline
#
# A solid sphere (`I = (2/5) m r²`) released on an incline rolls without slipping as long as the
# friction it needs, `(2/7) m g sin θ`, is within `μ m g cos θ`, i.e. `μ ≥ (2/7) tan θ ≈ 0.165`
# at 30°. Then `a = (5/7) g sin θ` and the contact point is at rest: `v = ω r`. Below that it
# slides at `a = g (sin θ − μ cos θ)` and spins up at `ω̇ = (5/2) μ g cos θ / r`.

# %%
theta, radius = math.radians(30.0), 0.1
steps = 30 if FAST else 100
t = H * torch.arange(steps + 1)
fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
for mu, color in ((0.5, "tab:blue"), (0.1, "tab:red")):
    simulator = on_incline(theta, mu, Body("ball", Sphere(radius), mass=1.0))
    run = simulator.rollout(simulator.initial_state(q=at(0.0, radius)), steps=steps)
    v, spin = run.v[:, 0, 0, 0], run.v[:, 0, 0, 4] * radius
    rolls = mu >= 2.0 / 7.0 * math.tan(theta)
    a = 5.0 / 7.0 * G * math.sin(theta) if rolls else G * (math.sin(theta) - mu * math.cos(theta))
    label = "rolls" if rolls else "slides"
    axes[0].plot(t, v, color=color, lw=3, alpha=0.5, label=f"μ = {mu} ({label}): simulated")
    axes[0].plot(t, a * t, "k--", lw=1)
    axes[1].plot(t, v - spin, color=color, label=f"μ = {mu}")
    error = float(((v[1:] - v[:-1]) / H / a - 1.0).abs().max())
    print(f"μ = {mu}: {label}, a = {a:.4f} m/s², largest relative error per step {error:.1e}")
axes[0].plot([], [], "k--", lw=1, label="closed form")
axes[0].set(xlabel="t (s)", ylabel="speed down the slope (m/s)", title="sphere on a 30° incline")
axes[0].legend()
axes[1].set(xlabel="t (s)", ylabel="v − ω r (m/s)", title="slip at the contact point")
axes[1].legend()
fig.tight_layout()
fig.savefig(OUT / "07_sphere.png", dpi=80)

# %% [markdown]
# ## A box on an incline: no creep
#
# A box stays put on an incline as long as `tan θ < μ`. Its four bottom corners are four
# redundant sticking contacts; the exact LCP holds it with zero velocity, where soft-contact
# simulators let it creep downhill (MuJoCo 4.0 with default settings at about 3 mm/s in this
# scene: see the *Benchmarks* page). On a slope steeper than `arctan μ` it slides at
# `a = g (sin θ − μ cos θ)`.

# %%
mu, half = 0.5, [0.1, 0.1, 0.05]
steps = 50 if FAST else 200
t = H * torch.arange(steps + 1)
fig, ax = plt.subplots(figsize=(6, 3.6))
for degrees, color in ((20.0, "tab:blue"), (30.0, "tab:red")):
    angle = math.radians(degrees)
    simulator = on_incline(angle, mu, Body("box", Box(half), mass=1.0))
    run = simulator.rollout(simulator.initial_state(q=at(0.0, half[2])), steps=steps)
    travel = run.q[:, 0, 0, 0]
    a = max(G * (math.sin(angle) - mu * math.cos(angle)), 0.0)
    # the box starts at rest and reaches speed a h after the first step: x_k = a h² k (k + 1) / 2
    k = torch.arange(steps + 1)
    expected = 0.5 * a * H**2 * k * (k + 1)
    print(
        f"{degrees:.0f}°: travelled {float(travel[-1]):.6e} m in {steps * H:g} s "
        f"(closed form {float(expected[-1]):.6e} m), largest speed "
        f"{float(run.v.abs().max()):.1e} m/s"
    )
    ax.plot(t, travel, color=color, lw=3, alpha=0.5, label=f"{degrees:.0f}°, simulated")
    ax.plot(t, expected, "k--", lw=1)
ax.plot([], [], "k--", lw=1, label="closed form (the scheme's x_k)")
ax.set(xlabel="t (s)", ylabel="travel down the slope (m)", title=f"box on an incline, μ = {mu}")
ax.legend()
fig.tight_layout()
fig.savefig(OUT / "07_incline.png", dpi=80)

# %% [markdown]
# The dashed line for the sliding box is the time-stepping scheme's own closed form: an implicit
# Euler step updates the velocity first (`v_k = a h k`) and then the position with the new
# velocity, so `x_k = a h² k (k + 1) / 2`, which tends to `a t² / 2` as `h → 0`.
#
# ## Tipping or sliding: a box pushed at height H
#
# A frictionless sphere, a **kinematic** body moving at 5 cm/s, pushes a 0.2 m cube (μ = 0.8)
# at height `H`. The push `F` makes the cube slide once `F = μ m g` and tip over its front edge
# once `F H = m g w / 2`; whichever comes first wins, so it tips iff `H > w / (2 μ) = 0.125 m`.
# The heights are a batch: the kinematic poses `q_kinematic` differ per scene, and one rollout
# sweeps them all. The box's tilt after 60 steps (3 cm of push) shows the threshold. The box
# starts sliding at the pusher's speed: from rest, the first step would add the impulse `m v`
# to the push, a kick that tips the box from slightly lower heights.

# %%
w, mu_tip, pusher_radius = 0.2, 0.8, 0.02
threshold = w / (2 * mu_tip)
scene = Scene(
    bodies=(
        ground,
        Body("box", Box([w / 2] * 3), mass=1.0),
        Body("pusher", Sphere(pusher_radius), kind="kinematic"),
    ),
    friction=mu_tip,
    pair_friction={("box", "pusher"): 0.0},
    h=H,
)
simulator = Simulator(scene)
ratios = torch.linspace(0.8, 1.2, 6 if FAST else 40)
count, steps = len(ratios), 60
pusher = at(-w / 2 - pusher_radius, 0.0, count).clone()
pusher[:, 0, 2] = ratios * threshold
v = torch.zeros(count, 1, 6)
v[..., 0] = 0.05
state = simulator.initial_state(q=at(0.0, w / 2, count), v=v, q_kinematic=pusher)
controls = torch.zeros(steps, count, 1, 6)
controls[..., 0] = 0.05
run = simulator.rollout(state, steps=steps, controls=controls)
quaternion = run.q[-1, :, 0, 3:]
tilt = 2.0 * torch.atan2(quaternion[:, 1:].norm(dim=-1), quaternion[:, 0].abs())
travel = run.q[-1, :, 0, 0]

fig, ax = plt.subplots(figsize=(6, 3.6))
ax.plot(ratios, tilt, "o-", color="tab:blue", label="tilt after 0.6 s (rad)")
ax.plot(ratios, travel / (0.05 * steps * H), "s--", color="tab:red", label="travel / push")
ax.axvline(1.0, color="k", lw=1)
ax.set(xlabel="H / (w / 2μ)", title="pushed box: slides below the threshold, tips above")
ax.legend()
fig.tight_layout()
fig.savefig(OUT / "07_tipping.png", dpi=80)
below, above = tilt[ratios < 1.0], tilt[ratios > 1.0]
print(f"below the threshold: largest tilt {float(below.max()):.1e} rad")
print(f"above the threshold: smallest tilt {float(above.min()):.3f} rad")

# %% [markdown]
# Below the threshold the box slides with the pusher (travel / push = 1) without tilting; above it
# the box pivots on its far bottom edge, which stays put (its centre still moves forward as it
# rotates).
#
# ## A box tumbling onto the ground, in 3D
#
# A box dropped with a random orientation and spin bounces off a corner, rolls over an edge and
# comes to rest on a face. We draw it with matplotlib's `mplot3d`: it is already a dependency of
# the tutorials, renders without a display (the `Agg` backend of the docs build and the tests),
# and a handful of translucent boxes is all this picture needs; an interactive viewer (pyvista,
# meshcat) would add a dependency and an OpenGL or browser context for no gain here.

# %%
half = torch.tensor([0.15, 0.1, 0.05])
simulator = Simulator(
    Scene(bodies=(ground, Body("box", Box(half.tolist()), mass=1.0)), friction=0.6, h=H)
)
generator = torch.Generator().manual_seed(3)
orientation = torch.randn(4, generator=generator)
q0 = torch.cat([torch.tensor([0.0, 0.0, 0.35]), orientation / orientation.norm()])
v0 = torch.tensor([0.6, 0.2, 0.0, 4.0, -6.0, 3.0])
steps = 60 if FAST else 150
run = simulator.rollout(simulator.initial_state(q=q0[None, None], v=v0[None, None]), steps=steps)
poses = run.q[:, 0, 0]

signs = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
faces = [[0, 1, 3, 2], [4, 5, 7, 6], [0, 1, 5, 4], [2, 3, 7, 6], [0, 2, 6, 4], [1, 3, 7, 5]]


def box_faces(pose):
    corners = (quat_to_matrix(pose[3:]) @ (signs * half).T).T + pose[:3]
    return [corners[face].tolist() for face in faces]


fig = plt.figure(figsize=(7, 5))
ax = fig.add_subplot(projection="3d")
frames = list(range(0, steps + 1, 10))
colors = plt.cm.viridis(torch.linspace(0.0, 1.0, len(frames)).numpy())
for frame, color in zip(frames, colors, strict=True):
    ax.add_collection3d(
        Poly3DCollection(box_faces(poses[frame]), facecolor=color, edgecolor="k", alpha=0.35)
    )
ax.plot(*poses[:, :3].T.numpy(), color="k", lw=1)
extent = float(poses[:, :2].abs().max()) + 0.25
ax.set(xlim=(-extent, extent), ylim=(-extent, extent), zlim=(0.0, 0.5))
ax.set(xlabel="x (m)", ylabel="y (m)", zlabel="z (m)", title="a box tumbling onto the ground")
ax.set_box_aspect((1.0, 1.0, 0.5 / (2 * extent)))
fig.tight_layout()
fig.savefig(OUT / "07_tumbling.png", dpi=80)
lowest = (quat_to_matrix(poses[:, 3:]) @ (signs * half).T)[:, 2].min(dim=-1).values + poses[:, 2]
print(f"final height {float(poses[-1, 2]):.4f} m; deepest corner {float(lowest.min()):.1e} m")

# %% [markdown]
# ## The WAM carries the BarrettHand to a box, and the hand closes
#
# Robots are members of a spatial scene (`sim.RobotMember`): their links' collision capsules
# touch the dynamic bodies, and their joints are degrees of freedom of the same contact problem.
# Here the WAM's seven joints follow a planned approach (kinematic: the arm does not yield) and
# the BarrettHand's finger joints are servoed, a torque-limited PD law integrated implicitly,
# so the fingers stop where the box stops them. `torchcontact.experiments` holds this set-up,
# shared with the tracking experiment of tutorial 08: `barrett_member` (the servo gains and
# torque limits), `approach_plan` (inverse kinematics of the palm straight down above the box,
# then the fingers' closing ramp) and `barrett_box_scene` (table, box, robot).
#
# Two boxes side by side in one batch: one under the palm's centre, one 3 cm to the side, where
# two fingers reach it before the third and push it across the table until the third closes.

# %%
from torchcontact.experiments import (
    BOX_PAIRS,
    approach_plan,
    barrett_box_scene,
    barrett_member,
    box_tilt,
    pair_slots,
    pair_states,
)
from torchcontact.robots import load

wam = load("wam7_bhand")
steps = 80
q_robot0, commands = approach_plan(wam, steps)  # (11,) joints; (T, 11) WAM velocities, hand targets
half_extents = (0.03, 0.025, 0.05)
hand_scene = barrett_box_scene(half_extents, 0.2, 0.6, barrett_member(wam))
offsets = torch.tensor([0.0, 0.03])
box_q = torch.tensor([0.6, 0.0, half_extents[2], *IDENTITY]).repeat(2, 1, 1)  # (2, 1, 7)
box_q[:, 0, 1] += offsets
hand_sim = Simulator(hand_scene)
grasp = hand_sim.rollout(
    hand_sim.initial_state(q=box_q, q_robot=q_robot0.expand(2, -1).clone()),
    steps=steps,
    joint_commands=commands[:, None].expand(steps, 2, -1).contiguous(),
)
states = pair_states(grasp.mode, pair_slots(hand_scene))  # (T, 2, pairs): 0 off, 1 stick, 2 slide
box_path = grasp.q[:, :, 0]  # (T + 1, 2, 7)
for b, offset in enumerate(offsets.tolist()):
    moved = 1e3 * float((box_path[-1, b, :2] - box_path[0, b, :2]).norm())
    print(
        f"box {1e2 * offset:.0f} cm off-centre: slid {moved:.1f} mm, "
        f"lifted {1e3 * float(box_path[-1, b, 2] - half_extents[2]):.1f} mm, "
        f"tilt {math.degrees(float(box_tilt(box_path[-1, b]))):.1f}°"
    )

fig, axes = plt.subplots(1, 2, figsize=(9, 2.6), sharey=True)
cmap = plt.matplotlib.colors.ListedColormap(["white", "tab:green", "tab:orange"])
for ax, b in zip(axes, range(2), strict=True):
    ax.imshow(states[:, b].T, aspect="auto", cmap=cmap, vmin=0, vmax=2, interpolation="nearest")
    ax.set(title=f"box {1e2 * float(offsets[b]):.0f} cm off-centre", xlabel="step (10 ms)")
    ax.set_yticks(range(len(BOX_PAIRS)), BOX_PAIRS)
fig.suptitle("contact state of the box: white separated, green sticking, orange sliding")
fig.tight_layout(rect=(0, 0, 1, 0.95))
fig.savefig(OUT / "07_barrett_states.png", dpi=80)

# %% [markdown]
# The three fingers reach the centred box at the same step; it hops for a step or two as the
# grip settles (the table contact opens and slides) and then stands, held, on the table. The
# off-centre box is reached by two fingers 20 steps earlier than by the third: it slides on
# the table (orange) in front of them until the third finger closes, and the unbalanced grip
# then lifts it off the table by a few millimetres, tilted. Tutorial 08 tracks such grasps
# with the contact RBPF while the hand hides the box from the camera; tutorial 06 shows the
# robots' kinematics and contact Jacobians.
