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
# # 04 · Tracking a grasped triangle: the contact RBPF against baselines
#
# A parallel-jaw gripper closes on a triangle lying on a table. While the fingers are close the
# camera cannot see the triangle, so for most of the grasp the only information is physics (the
# fingers push it, the table carries it) and a tactile array on its edges. This notebook walks
# through the experiment of `train/triangle_grasp.py` with the pipeline it runs,
# `torchcontact.experiments`:
#
# 1. the scene and one simulated grasp;
# 2. the measurements: an occluded camera and noisy tactile sensors;
# 3. the contact modes learned from training rollouts;
# 4. one grasp tracked by the RBPF over contact modes and by a particle filter through the
#    simulator, pictured;
# 5. the results table of a small run, with the plain particle filter given the RBPF's CPU
#    time.

# %%
import os
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import torch

from torchcontact.experiments import (
    TriangleGrasp,
    evaluate_tracking,
    grasp_contact_model,
    grasp_summary,
    grasp_trials,
    plot_grasp_snapshots,
    plot_mode_timeline,
    plot_tracking_errors,
    run_estimators,
    run_pf,
    run_rbpf,
    run_vision,
    timed,
    tracking_table,
)
from torchcontact.sim import draw_scene
from torchcontact.states import mode_label

FAST = os.environ.get("TORCHCONTACT_FAST") == "1"
# Figures and files go to the folder named by TORCHCONTACT_OUT, else to a new temporary one.
OUT = Path(os.environ.get("TORCHCONTACT_OUT") or tempfile.mkdtemp(prefix="torchcontact_"))
OUT.mkdir(parents=True, exist_ok=True)
print(f"outputs in {OUT}")
torch.manual_seed(0)
torch.set_num_threads(1)

# %% [markdown]
# ## 1. The scene
#
# A triangle (8 cm sides, 0.2 kg) starts slightly tilted and off-centre, falls flat onto the
# table, and two kinematic fingers (their twists are the control) close until they are 1.5 mm
# wider than the triangle, pushing it towards the middle; they hold, then open. Friction is
# drawn per trial between 0.4 and 0.6; the filters assume 0.5. `grasp_trials` makes the training
# rollouts (for the mode table), the evaluation trials and their measurements in one go.

# %%
settings = TriangleGrasp(
    trials=3 if FAST else 8,
    train_trials=16 if FAST else 64,
    steps=48 if FAST else 80,
    rbpf_particles=50 if FAST else 200,
)
trials = grasp_trials(settings)
truth = trials.truth
T, h = trials.steps, trials.scene.h
moments = [0, T // 8, int(0.35 * T), T // 2, int(0.8 * T)]
fig, axes = plt.subplots(1, len(moments), figsize=(3.0 * len(moments), 2.4))
for ax, t in zip(axes, moments, strict=True):
    draw_scene(ax, trials.scene, q=truth.q[t, 0], q_kinematic=truth.q_kinematic[t, 0])
    ax.set_xlim(-0.08, 0.08)
    ax.set_ylim(-0.005, 0.075)
    hidden = " (occluded)" if t > 0 and trials.occluded[t - 1] else ""
    ax.set_title(f"t = {h * t:.2f} s{hidden}", fontsize=9)
fig.tight_layout()
fig.savefig(OUT / "04_scene.png", dpi=80)

# %% [markdown]
# ## 2. Measurements
#
# The camera measures the pose `(x, y, θ)` with 4 mm and 0.03 rad noise, except during the
# occlusion (NaN). Nine tactile sensors, three per edge, report the contacts near them with a
# 5 % false-positive and 10 % false-negative rate. The finger poses are known exactly.

# %%
time_s = h * torch.arange(1, T + 1)
fig, axes = plt.subplots(2, 1, figsize=(8, 4.5), sharex=True)
axes[0].plot(time_s, 1e3 * trials.y[:, 0, 0], "x", color="0.5", ms=4, label="camera")
axes[0].plot(time_s, 1e3 * truth.q[1:, 0, 0, 0], "k", label="truth")
axes[0].set_ylabel("triangle x (mm)")
axes[0].legend(loc="upper right")
readings = trials.readings[:, 0].T.float()
axes[1].imshow(
    readings,
    aspect="auto",
    cmap="Greys",
    origin="lower",
    extent=(float(time_s[0]) - 0.005, float(time_s[-1]) + 0.005, -0.5, readings.shape[0] - 0.5),
)
axes[1].set_yticks(
    range(9), [f"edge {i // 3}, {('20', '50', '80')[i % 3]} %" for i in range(9)], fontsize=7
)
axes[1].set_xlabel("time (s)")
for ax in axes:
    occ = time_s[trials.occluded]
    ax.axvspan(float(occ[0]), float(occ[-1]), color="C1", alpha=0.1)
fig.tight_layout()
fig.savefig(OUT / "04_measurements.png", dpi=80)

# %% [markdown]
# The bottom edge (edge 0) reads the table at its two corners; edge 1 (right) lights up when
# the right finger pushes. The orange band is the occlusion.
#
# ## 3. Contact modes from training rollouts
#
# Every distinct per-slot mode vector the simulator produced in the training rollouts becomes a
# discrete filter mode; their empirical transition matrix is the RBPF's mode prior.
# `torchcontact.states.mode_label` names each one by the bodies touching the triangle and their
# state.

# %%
for k, row in enumerate(trials.table):
    print(f"mode {k:2d}: {mode_label(trials.scene, row, body='triangle')}")
K = trials.table.shape[0]
in_table = (trials.true_ids < K).double().mean()
print(f"true mode of the evaluation trials found in the table at {100 * in_table:.0f} % of steps")

# %% [markdown]
# ## 4. One grasp, tracked
#
# `run_rbpf` runs the RBPF over these modes (`PlanarContactModel`: each mode's contact step
# linearized at the belief's mean, one Kalman filter per particle, tactile log-likelihood per
# mode). After each step it projects every particle's Gaussian out of the bodies its mean
# penetrates (`torchcontact.filters.project_out_of_contact`): the shared linearization point
# can leave a particle inside a finger. `run_pf` runs
# `torchcontact.filters.SimulatorParticleFilter`, the bootstrap particle filter that steps every
# particle through the simulator. Both run on all trials as one batch; the pictures show
# trial 0.

# %%
model = grasp_contact_model(settings, trials)
outputs, timings = {}, {}
outputs["rbpf"], timings["rbpf"] = timed(
    lambda: run_rbpf(model, trials, settings, torch.Generator().manual_seed(2))
)
outputs["pf"], timings["pf"] = timed(
    lambda: run_pf(trials, settings, settings.rbpf_particles, torch.Generator().manual_seed(3))
)
outputs["vision"] = run_vision(trials)
for method in ("rbpf", "pf"):
    milliseconds = 1e3 * timings[method].wall / T
    print(f"{method}: {settings.rbpf_particles} particles, {milliseconds:.0f} ms per step")

# %%
fig = plot_grasp_snapshots(trials, outputs, [T // 5, int(0.45 * T), int(0.8 * T)])
fig.savefig(OUT / "04_snapshots.png", dpi=80)

# %% [markdown]
# Top: the truth, the fingers and the RBPF's particle means (red dots). Bottom: a 12 × 6 mm
# window centred on the true position: the particles (size ∝ weight) of both filters and the
# estimates. Before the occlusion both filters average the camera. While a finger pushes, the
# contact ties the triangle's x to the finger's and the RBPF's cloud collapses; it spreads
# again when the finger stops and the triangle slides on by a distance that depends on the
# true friction, which the filters only know to ±20 %.

# %%
metrics, errors = evaluate_tracking(trials, outputs)
fig = plot_tracking_errors(trials, errors)
fig.savefig(OUT / "04_errors.png", dpi=80)
fig = plot_mode_timeline(trials, outputs["rbpf"]["marginals"])
fig.savefig(OUT / "04_modes.png", dpi=80)
print(tracking_table(metrics))

# %% [markdown]
# The contact-state timeline shades the RBPF's mode marginals; red circles are the true modes,
# black dots the MAP. The held camera drifts once the fingers push the triangle it cannot see.
# (The particle filter's modes rarely match: its process noise keeps the table contacts of its
# particles sliding, so its MAP mode is mostly a sliding variant of the true one.)
#
# ## 5. The results table of a small run
#
# `run_estimators` runs every method on the trials and gives the plain particle filter **the
# RBPF's CPU time**: it times the PF with 8 and 64 particles on the same trials, fits
# `time = a + b·N` and runs it with the `N` that matches the RBPF's measured time (`pf`);
# `pf_same_n` is the PF with the RBPF's particle count (slower). `evaluate_tracking` scores them
# and `grasp_summary` holds the ratios the README reports. The numbers in the README come from
# `python train/triangle_grasp.py --trials 64`, which also writes TensorBoard logs,
# `results.md`, `metrics.json` and the plots to a new folder,
# `<out_dir>/<name>__<seed>__<unix time>`.

# %%
small = TriangleGrasp(
    trials=2 if FAST else 8,
    train_trials=8 if FAST else 64,
    steps=48 if FAST else 80,
    rbpf_particles=20 if FAST else 200,
    reference_pf=not FAST,
)
small_trials = grasp_trials(small)
runs = run_estimators(small, small_trials, grasp_contact_model(small, small_trials))
metrics, _ = evaluate_tracking(small_trials, runs.outputs)
for method, row in metrics.items():
    row["particles"] = float(runs.particles.get(method, 0))
    row["cpu_ms_per_step"] = 1e3 * runs.timings[method].cpu / small_trials.steps
print(tracking_table(metrics))
summary = grasp_summary(small_trials, metrics)
ratio = summary["ratio_pos_occ"]
print(f"RBPF over the best baseline, position RMSE during the occlusion: {ratio:.3f}")
