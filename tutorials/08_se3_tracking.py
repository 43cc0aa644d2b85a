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
# # 08 · Tracking a box in SE(3) while a BarrettHand grasps it
#
# The WAM carries the BarrettHand palm down to a box lying on a table and the hand closes. As
# soon as the fingers start closing they hide the box from the camera, so for the rest of the
# grasp the filter knows only physics (the fingers push the box, the table carries it), the
# hand's joint angles and its tactile pads. This notebook runs the experiment of
# `train/barrett_box_grasp.py` in small, with the pipeline it uses from
# `torchcontact.experiments`:
#
# 1. the simulated trials: box size, mass, friction and pose drawn per trial, the truth's
#    contact states and the measurements (a Kinect-like camera, tactile pads);
# 2. the contact RBPF's switching model on SE(3), `filters.SpatialContactModel`, with its modes
#    from training rollouts;
# 3. every estimator on the same trials, the table and the pictures.

# %%
import os
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import torch

from torchcontact.experiments import (
    BOX_PAIRS,
    BarrettBoxGrasp,
    box_contact_model,
    box_tracking_table,
    box_trials,
    plot_box_errors,
    plot_box_snapshots,
    plot_box_states,
    run_box_estimators,
    score_box_estimators,
)

FAST = os.environ.get("TORCHCONTACT_FAST") == "1"
# Figures and files go to the folder named by TORCHCONTACT_OUT, else to a new temporary one.
OUT = Path(os.environ.get("TORCHCONTACT_OUT") or tempfile.mkdtemp(prefix="torchcontact_"))
OUT.mkdir(parents=True, exist_ok=True)
print(f"outputs in {OUT}")
torch.set_num_threads(1)

# %% [markdown]
# ## 1. The trials
#
# `BarrettBoxGrasp` holds the settings: the ranges of the box's half extents, mass and friction
# (uniform draws, one box per group of `trials_per_box` trials, simulated in one batch), the
# box's offset from where the hand aims, the camera's noise (5 mm and 2° per axis) and the
# pads' false-positive and false-negative rates. The camera sees the box until the fingers
# start closing (occluded by phase, from a quarter of the steps on).

# %%
settings = BarrettBoxGrasp(
    seed=0, trials=2 if FAST else 8, trials_per_box=2, steps=40 if FAST else 80
)
trials = box_trials(settings)
print(f"{trials.batch} trials of {trials.steps} steps (h = 10 ms)")
print(f"occluded from step {int(trials.occluded.nonzero()[0])} on")
print(f"tip-over step per trial (-1: the box does not tip): {trials.tip_step.tolist()}")
print(f"friction per trial: {[round(mu, 2) for mu in trials.friction.tolist()]}")

# %% [markdown]
# `trials.states` is the true contact state of the box against each of `BOX_PAIRS` during
# each step: separated (0), sticking (1) or sliding (2), from the simulator's per-slot modes
# (a pair slides when any of its contacts slides). Here is the first trial's:

# %%
print(" " * 8 + "".join(f"{t:>3d}" for t in range(0, trials.steps, 4)))
for p, pair in enumerate(BOX_PAIRS):
    row = trials.states[::4, 0, p].tolist()
    print(f"{pair:>8s}" + "".join(f"{'.|>'[s]:>3s}" for s in row))

# %% [markdown]
# ## 2. The contact model
#
# `filters.SpatialContactModel` makes the scene a switching model for the RBPF: the state is
# the box's pose (position and unit quaternion) and twist, with its covariance in the 12-dim
# tangent space (error-state form on SE(3)); a mode fixes the contact mode of every slot (box
# against table, palm and finger links), and given the mode the simulator's step is smooth, so
# each mode's Kalman predict uses its exact Jacobian at the belief's mean. The robot is known
# control: its measured joint angles and velocities. `box_contact_model` collects the modes
# and their transition from the rollouts of training trials (other seeds, other boxes), and
# rules out the modes that the physics contradicts at the mean (a finger that would have to
# pull the box, friction that would reverse a slip).

# %%
train = box_trials(
    BarrettBoxGrasp(seed=1, trials=2 if FAST else 8, trials_per_box=2, steps=settings.steps),
    seed=10_000,
)
model = box_contact_model(settings, train)
print(f"K = {model.num_modes} modes over {model.modes.shape[-1]} slots")

# %% [markdown]
# ## 3. Every estimator on the same trials
#
# `run_box_estimators` runs, batched over the trials: the contact RBPF (all-modes proposal,
# every particle's Gaussian projected out of the bodies it penetrates after each step), the
# same without the projection, the simulator particle filter with as many particles as fit in
# the RBPF's CPU time per step (`pf`) and with the RBPF's particle count (`pf_same_n`), an EKF
# on SE(3) that ignores contact, and the last camera pose held.

# %%
runs = run_box_estimators(
    settings, trials, rbpf_particles=0, pf_particles=4 if FAST else 0, model=model
)
metrics = score_box_estimators(trials, runs)
print(box_tracking_table(metrics))

# %% [markdown]
# How to read it: "occl." is the part of the grasp during which the hand hides the box. A box
# that the hand grasps cleanly barely moves while hidden, so holding the last estimate (the
# EKF without contact, the held camera pose) is hard to beat on those trials; the physics pays
# where a finger pushes the box across the table or tips it over. The contact-state columns
# exist only for the filters with contact (the EKF and the camera have none). The position
# error against time, with the occlusion shaded:

# %%
fig = plot_box_errors(trials, runs.outputs, {m: m for m in runs.outputs})
fig.savefig(OUT / "08_errors.png", dpi=80)
plt.show()

# %% [markdown]
# Truth, the camera's last pose and the estimates at three moments of the first trial:

# %%
moments = [trials.steps // 5, trials.steps // 2, trials.steps - 1]
fig = plot_box_snapshots(trials, runs.outputs, moments)
fig.savefig(OUT / "08_snapshots.png", dpi=80)
plt.show()

# %% [markdown]
# And the RBPF's contact-state probabilities against the truth: the marginal of its modes
# summed over the modes in which each pair is separated, sticking or sliding.

# %%
fig = plot_box_states(trials, runs.outputs["rbpf"]["state_probs"], trial=0)
fig.savefig(OUT / "08_states.png", dpi=80)
plt.show()

# %% [markdown]
# `train/barrett_box_grasp.py --trials 32` runs the experiment at full size and writes the
# same table, the figures and TensorBoard scalars to `runs/`; the results are in the
# documentation's BarrettHand box-grasp page.
