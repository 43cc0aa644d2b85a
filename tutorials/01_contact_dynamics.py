# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 01 · Contact dynamics: scenes, the simulator and its solvers
#
# A rigid body touching the ground obeys the Stewart–Trinkle time-stepping scheme: over a step
# of length `h` the contact impulses `pn`, `pt` and the end velocity `v⁺` satisfy Newton–Euler
# together with complementarity conditions (no impulse unless touching, friction inside the
# Coulomb cone, sliding only at the cone's edge). `torchcontact` solves that problem
#
# * exactly, by Lemke's pivoting method (`solve(problem, "lemke")`, the reference);
# * by alternating two convex QPs in OSQP (`"qp"`, staggered projections);
# * by batched projected Gauss–Seidel (`"pgs"`);
# * and, once the **contact mode** (separated / sticking / sliding per contact) is known, by
#   one differentiable linear solve per problem (`solve_mode`), the building block of the filters.
#
# The simulator (`torchcontact.sim`) builds the problem from a scene of polygons, guesses each
# step's modes from the previous step, and calls an exact solver only where the guess fails.

# %%
import math
import os
import tempfile
import time
from pathlib import Path

import matplotlib.pyplot as plt
import torch

from torchcontact.contact import is_consistent, solve, solve_mode
from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import Body, Scene, Simulator, contact_problem, draw_scene

FAST = os.environ.get("TORCHCONTACT_FAST") == "1"
# Figures and files go to the folder named by TORCHCONTACT_OUT, else to a new temporary one.
OUT = Path(os.environ.get("TORCHCONTACT_OUT") or tempfile.mkdtemp(prefix="torchcontact_"))
OUT.mkdir(parents=True, exist_ok=True)
print(f"outputs in {OUT}")
G, H, MU = 9.81, 0.01, 0.4


def box_scene(*, angle=0.0, size=(1.0, 0.5), extra=()):
    """A 2 kg box on (possibly tilted) ground, plus any extra bodies."""
    bodies = (
        Body("ground", HalfPlane.ground(angle=angle), kind="static"),
        Body("box", Polygon.box(*size), mass=2.0),
        *extra,
    )
    return Simulator(Scene(bodies=bodies, friction=MU, h=H))


def pose(*values):
    return torch.tensor(values, dtype=torch.float64).reshape(1, 3)


# %% [markdown]
# ## A box sliding to a stop
#
# Launched at 1 m/s, the box loses `μ g h` of speed every step and stops at `t = v₀ / (μ g)`.
# Friction at the bottom corners also shifts the box's weight forward: the leading corner
# carries more, `a (pn_front − pn_back) = b μ (pn_front + pn_back)`.

# %%
sim = box_scene()
run = sim.rollout(sim.initial_state(q=pose(0, 0.25, 0), v=pose(1.0, 0, 0)), steps=40)
t = H * torch.arange(41, dtype=torch.float64)
closed_form = (1.0 - MU * G * t).clamp(min=0.0)
print(
    "largest error against max(v0 − μ g t, 0):", (run.v[:, 0, 0] - closed_form).abs().max().item()
)
print("steps solved by the previous step's modes:", int((run.solver == 0).sum()), "of 40")

fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
axes[0].plot(t, run.v[:, 0, 0], "o", ms=3, label="simulator")
axes[0].plot(t, closed_form, "-", label="closed form")
axes[0].set(xlabel="time (s)", ylabel="vx (m/s)", title="sliding to a stop")
axes[0].legend()
axes[1].plot(t[1:], run.pn[:, 0] / H, label="back corner")
axes[1].plot(t[1:], run.pn[:, 1] / H, label="front corner")
axes[1].axhline(2.0 * G / 2, color="gray", ls=":", label="m g / 2")
axes[1].set(xlabel="time (s)", ylabel="normal force (N)", title="corner forces")
axes[1].legend()
fig.tight_layout()
fig.savefig(OUT / "01_sliding.png", dpi=80)
plt.show()

# %% [markdown]
# ## Stick or slip on an incline
#
# On an incline of angle θ a block sticks iff `tan θ < μ`; otherwise it accelerates at
# `g (sin θ − μ cos θ)`. One step from rest shows the threshold at `θ* = atan μ ≈ 21.8°`.

# %%
angles = torch.linspace(0.0, 40.0, 9 if FAST else 41)
accelerations = []
for degrees in angles.tolist():
    theta = math.radians(degrees)
    sim = box_scene(angle=theta, size=(1.0, 0.2))
    center = (-0.1 * math.sin(theta), 0.1 * math.cos(theta))
    result = sim.step(sim.initial_state(q=pose(*center, theta)))
    accelerations.append(result.state.v[0, :2].norm().item() / H)
expected = [
    max(G * (math.sin(math.radians(d)) - MU * math.cos(math.radians(d))), 0.0)
    for d in angles.tolist()
]
fig, ax = plt.subplots(figsize=(5, 3.5))
ax.plot(angles, accelerations, "o", label="simulator")
ax.plot(angles, expected, "-", label="g (sin θ − μ cos θ)⁺")
ax.axvline(math.degrees(math.atan(MU)), color="gray", ls=":", label="atan μ")
ax.set(xlabel="incline (deg)", ylabel="acceleration (m/s²)", title="stick–slip threshold")
ax.legend()
fig.savefig(OUT / "01_incline.png", dpi=80)
plt.show()

# %% [markdown]
# ## Tipping
#
# A tall box (0.5 × 1 m) pushed on its left face at height `y` with a force below `μ m g`
# tips about its front corner iff `F y > m g a`. Below the threshold it stays put; above, the
# back corner lifts (mode 0) while the front one sticks (mode 1). A box released past its
# balance angle on a corner falls onto its side.

# %%
sim = box_scene(size=(0.5, 1.0))
force = 0.9 * MU * 2.0 * G
threshold = 2.0 * G * 0.25 / force
steps = 15 if FAST else 30
for ratio in (0.9, 1.1):
    height = ratio * threshold
    push = torch.tensor([force, 0.0, -(height - 0.5) * force], dtype=torch.float64)
    run = sim.rollout(
        sim.initial_state(q=pose(0, 0.5, 0)), steps=steps, forces=push.expand(steps, 1, 3)
    )
    angle = math.degrees(run.q[-1, 0, 2].item())
    print(
        f"push at {ratio:.1f}× the tipping height: angle {angle:+.2f}°, "
        f"first modes of the bottom corners {run.mode[0, :2].tolist()}"
    )

theta = 1.3  # the balance angle on a corner is atan(1.0 / 0.5) ≈ 1.107 rad for the wide box
sim = box_scene()
corner = torch.tensor([-0.5, -0.25], dtype=torch.float64)
rotation = torch.tensor(
    [[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]], dtype=torch.float64
)
center = -(rotation @ corner)
run = sim.rollout(sim.initial_state(q=pose(center[0].item(), center[1].item(), theta)), steps=150)
fig, ax = plt.subplots(figsize=(6, 3))
for k in range(0, 151, 15):
    draw_scene(ax, sim.scene, q=run.q[k], alpha=0.15 + 0.85 * k / 150, extent=1.5)
ax.set(xlim=(-1.0, 1.5), ylim=(-0.2, 1.2), title="a box falling onto its side")
fig.savefig(OUT / "01_tipping.png", dpi=80)
plt.show()
print(f"final angle {run.q[-1, 0, 2].item():.4f} rad (π/2 = {math.pi / 2:.4f})")

# %% [markdown]
# ## Pushing with a robot finger
#
# A kinematically driven finger (its velocity is the control) pushes the box; once in contact
# the box moves with it, against ground friction.

# %%
finger = Body("finger", Polygon.box(0.1, 0.3), kind="kinematic")
sim = box_scene(extra=(finger,))
controls = torch.tensor([0.3, 0.0, 0.0], dtype=torch.float64).expand(60, 1, 3)
state = sim.initial_state(q=pose(0, 0.25, 0), q_kinematic=pose(-0.7, 0.2, 0))
run = sim.rollout(state, steps=60, controls=controls)
fig, axes = plt.subplots(1, 2, figsize=(11, 3))
for k in range(0, 61, 10):
    draw_scene(
        axes[0],
        sim.scene,
        q=run.q[k],
        q_kinematic=run.q_kinematic[k],
        alpha=0.2 + 0.8 * k / 60,
        extent=1.5,
    )
axes[0].set(xlim=(-1.0, 1.2), ylim=(-0.2, 0.7), title="finger pushing a box")
axes[1].plot(H * torch.arange(61), run.v[:, 0, 0], label="box vx")
axes[1].axhline(0.3, color="gray", ls=":", label="finger speed")
axes[1].set(xlabel="time (s)", ylabel="m/s")
axes[1].legend()
fig.tight_layout()
fig.savefig(OUT / "01_finger.png", dpi=80)
plt.show()

# %% [markdown]
# ## The mode-decoupled solve reproduces Lemke
#
# Given the mode Lemke found, `solve_mode` is a single batched linear solve, exact to round-off
# and differentiable. Here: random box states (tilted, spinning, near the ground).

# %%
count = 200 if FAST else 2000
sim = box_scene()
gen = torch.Generator().manual_seed(0)
theta = 0.3 * (torch.rand(count, generator=gen, dtype=torch.float64) - 0.5)
height = 0.25 * torch.cos(theta) + 0.5 * torch.sin(theta).abs()
q = torch.stack([torch.zeros(count, dtype=torch.float64), height, theta], -1).unsqueeze(1)
v = (
    torch.randn(count, 3, generator=gen, dtype=torch.float64) * torch.tensor([1.0, 0.3, 1.0])
).unsqueeze(1)
problem, _ = contact_problem(sim.scene, sim.initial_state(q=q, v=v))

start = time.perf_counter()
exact = solve(problem, "lemke")
lemke_seconds = time.perf_counter() - start
start = time.perf_counter()
decoupled = solve_mode(problem, exact.mode)
mode_seconds = time.perf_counter() - start
print("modes seen:", sorted(set(exact.mode.flatten().tolist())))
print("max |v⁺(solve_mode) − v⁺(Lemke)|:", (decoupled.v_next - exact.v_next).abs().max().item())
print("all consistent:", bool(is_consistent(problem, decoupled).all()))
print(f"Lemke loop: {1e6 * lemke_seconds / count:.0f} µs/problem")
print(f"solve_mode: {1e6 * mode_seconds / count:.2f} µs/problem")

# %% [markdown]
# A wrong mode is not hidden: the linear system is still solved, but `status.residual` (the
# LCP's complementarity residual) and `is_consistent` report the violation.

# %%
stuck = solve_mode(problem, torch.where(problem.slot_mask, 1, 0))
print("residual with the right modes:", exact.status.residual.max().item())
print("residual with every touching corner forced to stick:", stuck.status.residual.max().item())
print(
    "consistent with forced sticking:",
    f"{is_consistent(problem, stuck).double().mean().item():.0%}",
)
