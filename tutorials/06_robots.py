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
# # 06 · Robots: the WAM, the BarrettHand, and contact Jacobians
#
# `torchcontact.robots` wraps [pytorch-kinematics](https://github.com/UM-ARM-Lab/pytorch_kinematics)
# around the robot descriptions that ship inside the package, in `torchcontact/models/` (written
# from Barrett's published DH tables and dimensions; the sources are in each URDF's header). A
# robot gives batched forward kinematics, geometric Jacobians of any point on any link, and
# **contact Jacobians**: the rows that turn joint velocities into a contact point's velocity along
# the contact normal and the friction directions, which is how a robot enters a contact problem.
#
# Here we load the 7-DOF WAM with a BarrettHand on its tool plate, draw it, and look at the contact
# Jacobian of a fingertip.

# %%
import os

import matplotlib.pyplot as plt
import torch

from torchcontact.robots import load

FAST = os.environ.get("TORCHCONTACT_FAST") == "1"
torch.set_default_dtype(torch.float64)

robot = load("wam7_bhand")
print(robot.dof, "actuated coordinates:", robot.joint_names)
print(len(robot.link_names), "links, e.g.", robot.link_names[:3], "...", robot.link_names[-3:])

# %% [markdown]
# The hand's 8 joints are driven by 4 motors: one spread motor turns fingers F1 and F2
# symmetrically, and each finger's motor drives its inner joint and, through Barrett's TorqueSwitch,
# its outer joint at one third of the inner angle. pytorch-kinematics ignores URDF `<mimic>` tags,
# so torchcontact keeps that coupling as a linear map `q_full = C q`; every Jacobian is returned in
# the actuated coordinates (`J_full @ C`). Load with `coupled=False` for all 15 joints.

# %%
print(robot.coupling.full_names[7:])
print(robot.coupling.matrix[7:, 7:])

# %% [markdown]
# ## Forward kinematics at a few configurations
#
# `forward_kinematics(q)` returns every link's pose `(*B, 4, 4)` in the base frame (where the WAM's
# first two axes meet), for a whole batch of configurations at once. We draw each link frame's
# origin joined to its parent's.

# %%
configurations = torch.tensor(
    [
        #  J1    J2    J3    J4    J5    J6    J7   spread F1    F2    F3
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [0.6, 0.8, 0.0, 1.6, 0.0, 0.7, 0.0, 0.0, 1.2, 1.2, 1.2],
        [-0.9, 1.1, 0.5, 1.2, -0.4, -0.3, 1.0, 1.05, 0.6, 0.6, 0.6],
    ]
)
if FAST:
    configurations = configurations[:2]
poses = robot.forward_kinematics(configurations)


def draw(ax, poses, b, color):
    for child, parent in robot.link_parents.items():
        a, c = poses[parent][b, :3, 3], poses[child][b, :3, 3]
        ax.plot([a[0], c[0]], [a[1], c[1]], [a[2], c[2]], color=color, lw=2)
    tips = torch.stack([poses[f"bhand_f{k}_tip"][b, :3, 3] for k in (1, 2, 3)])
    ax.scatter(tips[:, 0], tips[:, 1], tips[:, 2], color=color, s=12)


fig = plt.figure(figsize=(6, 6))
ax = fig.add_subplot(projection="3d")
for b, color in zip(
    range(len(configurations)), ["tab:gray", "tab:blue", "tab:orange"], strict=False
):
    draw(ax, poses, b, color)
ax.set(xlabel="x [m]", ylabel="y [m]", zlabel="z [m]", title="WAM + BarrettHand")
ax.set_box_aspect((1, 1, 1))
ax.set(xlim=(-0.6, 0.6), ylim=(-0.6, 0.6), zlim=(-0.2, 1.0))
plt.show()

print("tool position at q = 0:", poses["wam_tool"][0, :3, 3])

# %% [markdown]
# ## Contact Jacobian at a fingertip
#
# Suppose finger F3's tip touches an object at the tip frame's origin, and the object's surface
# normal there, pointing out of the object toward the finger, is `n`; `t` are the friction
# directions (here four, spaced around `n`). `contact_jacobian` gives
#
# * `Jn` `(dof,)` with `Jn @ qdot = n · v_p`, the rate at which the finger opens the gap, and
# * `Jt` `(D, dof)` with `Jt[d] @ qdot = t_d · v_p`, the sliding rate along each direction,
#
# where `v_p` is the velocity of the finger's material point at the contact. For a robot whose
# motion is the control (kinematically driven), these give the contact problem's known terms
# `bn = Jn q̇` and `bt = Jt q̇`; for a dynamic robot, `Jn`, `Jt` are its columns of the problem's
# `Jn`, `Jt`.

# %%
q = configurations[1]
tip = poses["bhand_f3_tip"][1]
pad_normal = tip[:3, 2]  # the tip frame's z axis: outward normal of the finger's grasping side
normal = -pad_normal  # the object's surface normal, out of the object toward the finger
t1 = tip[:3, 0]
t2 = torch.linalg.cross(normal, t1)
tangents = torch.stack([t1, t2, -t1, -t2])
Jn, Jt = robot.contact_jacobian(
    q, "bhand_f3_tip", point=torch.zeros(3), normal=normal, tangents=tangents
)
print("Jn =", Jn)
print("Jt =", Jt)

# %% [markdown]
# Of the hand's columns only F3's own motor is non-zero (F3 has no spread); the arm joints move the
# contact too (at this configuration J6 and J7 slide it without opening the gap). Check `bn` against
# a finite difference of the gap to the object's tangent plane at the contact:

# %%
qdot = torch.zeros(robot.dof)
qdot[[1, 3, 10]] = torch.tensor([0.2, -0.3, 0.5])  # shoulder pitch, elbow, F3
h = 1e-6
ahead = robot.forward_kinematics(q + h * qdot, "bhand_f3_tip")[:3, 3]
behind = robot.forward_kinematics(q - h * qdot, "bhand_f3_tip")[:3, 3]
velocity = (ahead - behind) / (2 * h)
print("bn = Jn · q̇              :", float(Jn @ qdot))
print("finite difference of n·x :", float(normal @ velocity))
print("bt = Jt · q̇              :", (Jt @ qdot).tolist())

# %% [markdown]
# The same call works on batches: one configuration with many contacts (points, normals and tangents
# with a leading `K` dimension), or many configurations at once, in float32 or float64.

# %%
batch = configurations[:1].expand(4096 if not FAST else 256, -1).float()
Jn_batch, Jt_batch = robot.contact_jacobian(
    batch,
    "bhand_f3_tip",
    point=torch.zeros(3, dtype=torch.float32),
    normal=normal.float(),
    tangents=tangents.float(),
)
print(Jn_batch.shape, Jt_batch.shape, Jn_batch.dtype)
