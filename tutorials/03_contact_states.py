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
# # 03 · Contact states, tactile sensors and the manipulation graph
#
# Once the contact state of an object is known — where it touches, and whether each contact
# sticks or slides — its dynamics are linear (tutorial 01). Section III of the seed paper
# therefore discretizes a manipulation task by contact states:
#
# * a **contact state** groups contacts whose locations lie within `δ_r` and whose normals
#   agree within `δ_θ` into *features*, each sticking or sliding, kept apart for contacts with
#   the robot and with the environment (`torchcontact.states.ContactState`);
# * a **manipulation state** adds the robot's pose relative to the object, which is all that
#   tells states apart while the robot does not touch it (`ManipulationState`);
# * the **manipulation graph** counts transitions between manipulation states under actions
#   (`ManipulationGraph`); it is the mode-transition model of the particle filter and the
#   model that Dyna-Q plans with;
# * **tactile sensors** (`TactileArray`) observe contact states through noisy binary readings.
#
# > **Synthetic contacts.** The contact tensors below are written out by hand with
# > `planar_box_contacts` (which corners touch, which slide, where the finger pushes). The
# > simulator-driven version of this notebook, with contacts from `torchcontact.sim`, comes
# > with the simulator.

# %%
import math
import os
import tempfile
from dataclasses import replace
from pathlib import Path

import matplotlib.pyplot as plt
import torch

from torchcontact.states import (
    ContactSet,
    ContactStateRegistry,
    FeatureGrid,
    ManipulationGraph,
    PoseGrid,
    contact_states,
    manipulation_states,
    planar_box_contacts,
    rectangle_sensors,
)

FAST = os.environ.get("TORCHCONTACT_FAST") == "1"
# Figures and files go to the folder named by TORCHCONTACT_OUT, else to a new temporary one.
OUT = Path(os.environ.get("TORCHCONTACT_OUT") or tempfile.mkdtemp(prefix="torchcontact_"))
OUT.mkdir(parents=True, exist_ok=True)
print(f"outputs in {OUT}")
torch.set_default_dtype(torch.float64)
A, B = 0.5, 0.25  # box half extents (m)
STICK, SLIDE_BACK = 1, 3  # modes: sticking; sliding with friction along −x (moving +x)

# %% [markdown]
# ## A box pushed, then tipped
#
# One slot per box corner (environment) and one for a finger (robot). The finger first waits
# beside the box, then pushes low on its left face (both bottom corners slide), then pushes
# high: the box tips about its bottom-right corner, which sticks. Finally it falls back.


# %%
def box_pose(x: float, tip: float) -> list[float]:
    """Box pose; with ``tip > 0`` tipped clockwise about its bottom-right corner at ``x``."""
    if tip == 0:
        return [x, B, 0.0]
    c, s = math.cos(-tip), math.sin(-tip)
    return [x - A * c - B * s, -A * s + B * c, -tip]


# phase: (corner modes, finger point in the box frame or None, tip angle in degrees)
PHASES = {
    "rest": ((STICK, STICK, 0, 0), None, 0.0),
    "slide": ((SLIDE_BACK, SLIDE_BACK, 0, 0), (-A, 0.0), 0.0),
    "tip": ((0, STICK, 0, 0), (-A, 0.15), 6.0),
    "tip more": ((0, STICK, 0, 0), (-A, 0.15), 20.0),
}


def scene(phases: list[str], xs: list[float]) -> tuple[ContactSet, torch.Tensor]:
    """Contacts of the box in each (phase, x) and the finger's world pose, batch ``(T,)``."""
    corner_modes, fingers, touching, poses = [], [], [], []
    for phase, x in zip(phases, xs, strict=True):
        modes, finger, tip = PHASES[phase]
        corner_modes.append(modes)
        fingers.append(finger or (-A - 0.1, 0.0))
        touching.append(finger is not None)
        poses.append(box_pose(x, math.radians(tip)))
    pose, finger = torch.tensor(poses), torch.tensor(fingers)
    contacts = planar_box_contacts(
        pose=pose,
        corner_modes=torch.tensor(corner_modes),
        finger=finger,
        finger_normal=torch.tensor([1.0, 0.0]).expand(len(phases), 2),
        finger_mode=torch.tensor(touching).long(),
    )
    c, s = pose[:, 2].cos(), pose[:, 2].sin()
    world = pose[:, :2] + torch.stack(
        [c * finger[:, 0] - s * finger[:, 1], s * finger[:, 0] + c * finger[:, 1]], -1
    )
    return contacts, torch.cat([world, pose[:, 2:]], -1)


episode = ["rest", "rest", "slide", "slide", "slide", "tip", "tip more", "tip more", "rest"]
xs = [0.0, 0.0, 0.05, 0.1, 0.15, 0.65, 0.65, 0.65, 0.2]
contacts, finger_pose = scene(episode, xs)

# %% [markdown]
# ## Contact states and their ids
#
# `FeatureGrid(radius=δ_r, angle=δ_θ)` quantizes each contact in the **object frame**: its
# location to a cell whose points all lie within `δ_r` of the cell centre, its normal to a
# direction bin whose normals all lie within `δ_θ` of the bin's direction. Contacts with the
# same partner kind, cell and bin form one feature; the feature slides if any of its contacts
# slides. A `ContactStateRegistry` gives each new state the next integer id.

# %%
grid = FeatureGrid(dim=2, radius=0.05, angle=math.radians(15))
registry = ContactStateRegistry(grid)
ids = registry.ids(contacts)
for t, (phase, i) in enumerate(zip(episode, ids.tolist(), strict=True)):
    print(f"t={t}  {phase:9s} → contact state {i}: {registry[i]}")
assert ids.tolist() == [0, 0, 1, 1, 1, 2, 3, 3, 0]

# %% [markdown]
# Tipping by 6° keeps the ground normal (seen from the box) inside its direction bin; at 20°
# it has turned past `δ_θ`, and the box is in a new contact state. Moving the whole scene —
# box, contacts and finger — leaves every state unchanged, because states live in the object
# frame; permuting the slots does too.

# %%
angle, shift = 0.7, torch.tensor([3.0, -1.0])
c, s = math.cos(angle), math.sin(angle)
R = torch.tensor([[c, -s], [s, c]])
assert contacts.pose is not None
moved = replace(
    contacts,
    points=contacts.points @ R.T + shift,
    normals=contacts.normals @ R.T,
    pose=torch.cat([contacts.pose[:, :2] @ R.T + shift, contacts.pose[:, 2:] + angle], -1),
)
order = torch.tensor([4, 2, 0, 3, 1])
shuffled = replace(
    contacts,
    points=contacts.points[:, order],
    normals=contacts.normals[:, order],
    pn=contacts.pn[:, order],
    mode=contacts.mode[:, order],
    mask=None,
    partner=contacts.partner[order],
)
print("same states after a rigid motion:", torch.equal(registry.ids(moved, add=False), ids))
print("same states after permuting slots:", torch.equal(registry.ids(shuffled, add=False), ids))

# %%
COLORS = {"stick": "tab:blue", "slide": "tab:orange", "robot": "tab:red"}


def draw_box(ax: plt.Axes, frame: ContactSet, title: str) -> None:
    """The box outline, the ground, and the active contacts of one frame (batch shape ())."""
    assert frame.pose is not None
    x, y, theta = frame.pose.tolist()
    c, s = math.cos(theta), math.sin(theta)
    corners = torch.tensor([[-A, -B], [A, -B], [A, B], [-A, B], [-A, -B]])
    outline = corners @ torch.tensor([[c, s], [-s, c]]) + torch.tensor([x, y])
    ax.plot(outline[:, 0], outline[:, 1], "k-", lw=1.2)
    ax.axhline(0.0, color="0.5", lw=2)
    for k in range(frame.num_slots):
        if int(frame.mode[k]) == 0:
            continue
        kind = "robot" if k == 4 else ("slide" if int(frame.mode[k]) >= 2 else "stick")
        px, py = frame.points[k].tolist()
        nx, ny = frame.normals[k].tolist()
        ax.plot(px, py, "o", color=COLORS[kind], ms=7)
        ax.arrow(
            px - 0.2 * nx, py - 0.2 * ny, 0.15 * nx, 0.15 * ny, width=0.008, color=COLORS[kind]
        )
    ax.set(title=title, xlim=(-0.9, 1.4), ylim=(-0.3, 0.9), aspect="equal")
    ax.set_axis_off()


for i in (2, 3):
    print(f"state {i}: ground feature direction key {registry[i].environment[0].direction}")

shown = [0, 2, 5, 6, 8]
fig, axes = plt.subplots(1, len(shown), figsize=(3.2 * len(shown), 2.6))
for ax, t in zip(axes, shown, strict=True):
    draw_box(ax, contacts[t], f"t={t}: state {int(ids[t])}\n{registry[int(ids[t])]}")
fig.tight_layout()
fig.savefig(OUT / "03_contact_states.png", dpi=80)
plt.show()

# %% [markdown]
# Blue: sticking ground contacts; orange: sliding; red: the finger. Arrows are contact normals,
# pointing from the partner into the box. Labels count features per kind: `E2st` is two
# sticking environment features, `R1st` one sticking robot feature. States 2 and 3 have the
# same counts but not the same features: seen from the box, the ground normal has moved to
# another direction bin (keys: face, bin).
#
# ## Tactile sensors (Fig. 2 of the seed paper)
#
# A rectangle carries sensors on its sides. Each triggers when a contact lies within its radius
# and the contact normal lies inside its cone of directions (the triangles); readings are
# flipped by false negatives and false positives. In contact state `c1` the three bottom
# (green) sensors trigger; in `c2`, two contacts on the right side trigger the two red ones.

# %%
FALSE_POSITIVE, FALSE_NEGATIVE = 0.05, 0.1
sensors = rectangle_sensors(
    half_extents=(A, B),
    counts=(3, 2, 3, 2),
    radius=0.08,
    half_angle=math.radians(30),
    false_positive=FALSE_POSITIVE,
    false_negative=FALSE_NEGATIVE,
)


def touching(points: list[list[float]], normals: list[list[float]], kind: str) -> ContactSet:
    """Sticking contacts with one partner, in the object frame."""
    K = len(points)
    return ContactSet(
        points=torch.tensor(points),
        normals=torch.tensor(normals),
        pn=torch.ones(K),
        mode=torch.ones(K, dtype=torch.long),
        partner=torch.zeros(K, dtype=torch.long),
        partner_kind=(kind,),
    )


c1_contacts = touching([[-1 / 3, -B], [0.0, -B], [1 / 3, -B]], [[0.0, 1.0]] * 3, "environment")
c2_contacts = touching([[A, -0.125], [A, 0.125]], [[-1.0, 0.0]] * 2, "robot")
c1, c2 = contact_states(c1_contacts, grid)[0], contact_states(c2_contacts, grid)[0]
table = sensors.trigger_table([c1, c2], grid)
print("expected triggers, c1:", table[0].long().tolist())
print("expected triggers, c2:", table[1].long().tolist())

fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
for ax, (name, readings, color) in zip(
    axes,
    [("c1", table[0].bool(), "tab:green"), ("c2", table[1].bool(), "tab:red")],
    strict=True,
):
    ax.add_patch(plt.Rectangle((-A, -B), 2 * A, 2 * B, fill=False, lw=1.5))
    sensors.draw(ax, readings, color=color)
    ax.set(title=f"contact state {name}", xlim=(-0.8, 0.8), ylim=(-0.5, 0.5))
    ax.set_axis_off()
fig.tight_layout()
fig.savefig(OUT / "03_tactile.png", dpi=80)
plt.show()

# %% [markdown]
# `log_likelihood(readings, table)` scores readings under every state of a table at once; it
# is the particle filter's tactile measurement model. Noisy readings drawn from `c1` are far
# more likely under `c1`.

# %%
gen = torch.Generator().manual_seed(0)
noisy = sensors.sample(table[0].bool().expand(5, -1), generator=gen)
log_likelihood = sensors.log_likelihood(noisy, table)
posterior = torch.softmax(log_likelihood, dim=-1)
for r, p in zip(noisy.long().tolist(), posterior.tolist(), strict=True):
    print(f"readings {r}  P(c1) = {p[0]:.4f}  P(c2) = {p[1]:.4f}")
assert bool((posterior[:, 0] > 0.5).all())

# %% [markdown]
# ## Manipulation states and the manipulation graph
#
# A toy pusher with three actions — 0 wait, 1 push low, 2 push high — moves the box between
# the phases above at random (the box is written out, not simulated). Each step's manipulation
# state (relative finger pose on a 5 cm / 22.5° grid, plus the contact state) is computed from
# the contact tensors, and the graph counts the transitions. The reward is 1 for reaching the
# far-tipped phase, the goal of this toy task.

# %%
NEXT = {  # phase, action → (next phases, probabilities)
    ("rest", 0): (["rest"], [1.0]),
    ("rest", 1): (["slide", "rest"], [0.9, 0.1]),
    ("rest", 2): (["tip", "slide"], [0.6, 0.4]),
    ("slide", 0): (["rest"], [1.0]),
    ("slide", 1): (["slide"], [1.0]),
    ("slide", 2): (["tip", "slide"], [0.7, 0.3]),
    ("tip", 0): (["rest"], [1.0]),
    ("tip", 1): (["tip", "rest"], [0.5, 0.5]),
    ("tip", 2): (["tip more", "tip"], [0.8, 0.2]),
    ("tip more", 0): (["rest", "tip more"], [0.5, 0.5]),
    ("tip more", 1): (["tip more"], [1.0]),
    ("tip more", 2): (["tip more"], [1.0]),
}
episodes, steps = (20, 8) if FAST else (200, 12)
phases, actions, xs = [], [], []
for _ in range(episodes):
    phase, x = "rest", float(torch.rand((), generator=gen))
    for _ in range(steps):
        action = int(torch.randint(0, 3, (), generator=gen))
        phases.append(phase)
        actions.append(action)
        xs.append(x)
        options, weights = NEXT[(phase, action)]
        phase = options[int(torch.multinomial(torch.tensor(weights), 1, generator=gen))]
        x += 0.05 if phase == "slide" else 0.0
    phases.append(phase)
    actions.append(-1)  # the episode ends here
    xs.append(x)

contacts, finger_pose = scene(phases, xs)
pose_grid = PoseGrid(dim=2, position_step=0.05, angle_step=math.pi / 8)
states = manipulation_states(
    contacts, robot_pose=finger_pose, contact_grid=grid, pose_grid=pose_grid
)
graph = ManipulationGraph(num_actions=3, smoothing=0.0)
for t, action in enumerate(actions):
    if action >= 0:
        reward = 1.0 if phases[t + 1] == "tip more" else 0.0
        graph.observe(states[t], action, states[t + 1], reward)
print(f"{graph.num_states} manipulation states from {len(states)} frames:")
for i, state in enumerate(graph.states):
    print(f"  {i}: {state}  (visits {graph.visits(state)})")

# %%
fig, ax = plt.subplots(figsize=(11, 5))
graph.draw(ax, labels={i: str(m.contact) for i, m in enumerate(graph.states)}, seed=1)
ax.set_title("manipulation graph: node area ~ visits, edge width ~ P(m′ | m)")
fig.tight_layout()
fig.savefig(OUT / "03_graph.png", dpi=80)
plt.show()

# %% [markdown]
# ## The graph as a model
#
# The particle filter needs a row-stochastic mode-transition matrix over state ids (here
# marginalized over a uniform action distribution); Dyna-Q needs to sample `(m′, r)` for
# remembered `(m, a)` pairs — many at once with `sample_ids`. The graph saves to JSON and loads
# back exactly.

# %%
transition = graph.transition_matrix()
print("transition matrix (row = from):")
print(transition.numpy().round(2))
assert torch.allclose(transition.sum(-1), torch.ones(graph.num_states))

sliding = states[phases.index("slide")]
next_ids, rewards = graph.sample_ids(
    torch.full((1000,), graph.index(sliding)), torch.full((1000,), 2), generator=gen
)
frequency = torch.bincount(next_ids, minlength=graph.num_states) / 1000
print("P(· | slide, push high):", graph.transition_probabilities(sliding, 2).numpy().round(3))
print("sampled frequencies:    ", frequency.numpy().round(3))

graph.save(OUT / "03_graph.json")
loaded = ManipulationGraph.load(OUT / "03_graph.json")
print("JSON round trip exact:", torch.equal(loaded.transition_tensor(), graph.transition_tensor()))

# %% [markdown]
# ## From the simulator
#
# The same states come out of simulated contacts. A finger pushes a tall box (0.4 × 1 m,
# μ = 0.6) low or high: sliding needs the force μ m g, and that force tips the box once the
# push is higher than a / μ = 0.33 m. `object_contacts` turns the simulator's slots into the
# box's contact set (normals flipped where the finger's vertex touches the box).

# %%
from itertools import groupby

from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import Body, Scene, Simulator, draw_scene
from torchcontact.states import object_contacts

pushed_scene = Scene(
    bodies=(
        Body("ground", HalfPlane.ground(), kind="static"),
        Body("box", Polygon.box(0.4, 1.0), mass=2.0),
        Body("finger", Polygon.box(0.1, 0.1), kind="kinematic"),
    ),
    friction=0.6,
    h=0.01,
)
simulator = Simulator(pushed_scene)
steps = 60
start = simulator.initial_state(
    q=torch.tensor([[[0.0, 0.5, 0.0]], [[0.0, 0.5, 0.0]]], dtype=torch.float64),
    q_kinematic=torch.tensor([[[-0.3, 0.1, 0.0]], [[-0.3, 0.9, 0.0]]], dtype=torch.float64),
)
push = torch.tensor([0.3, 0.0, 0.0], dtype=torch.float64).expand(steps, 2, 1, 3)
run = simulator.rollout(start, steps=steps, controls=push)
labels = [[], []]
for t in range(steps):
    box_contacts = object_contacts(
        pushed_scene,
        body="box",
        q=run.q[t],
        points=run.points[t],
        normals=run.normals[t],
        pn=run.pn[t],
        mode=run.mode[t],
        active=run.active[t],
    )
    for row, state in zip(labels, contact_states(box_contacts, grid), strict=True):
        row.append(str(state))
for name, row in zip(("low push", "high push"), labels, strict=True):
    print(f"{name}: " + " → ".join(f"{label} ×{len(list(g))}" for label, g in groupby(row)))

fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
for column, title in enumerate(("low push: slides", "high push: tips")):
    for k in range(0, steps + 1, 15):
        draw_scene(
            axes[column],
            pushed_scene,
            q=run.q[k, column],
            q_kinematic=run.q_kinematic[k, column],
            alpha=0.2 + 0.8 * k / steps,
            extent=1.2,
        )
    axes[column].set(xlim=(-0.5, 0.8), ylim=(-0.1, 1.2), title=title)
fig.tight_layout()
plt.show()
