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
# # 02 · Kalman filters and the Rao-Blackwellized particle filter
#
# Given the contact mode, the contact dynamics are linear (tutorial 01), so a Kalman filter
# tracks the object exactly. The mode is unknown, so the Rao-Blackwellized particle filter
# (RBPF) *samples* mode sequences and keeps one Kalman filter per particle. This notebook:
#
# 1. runs the batched Kalman filter on a linear system;
# 2. checks the RBPF against the exact posterior of a small switching system (every mode
#    sequence enumerated);
# 3. tracks a box pushed by a finger — switching between resting, pushed and coasting — with
#    the planar contact model, from a noisy camera.

# %%
import itertools
import os
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import torch

from torchcontact.filters import (
    RBPF,
    Gaussian,
    KinematicControl,
    LinearSwitchingModel,
    PlanarContactModel,
    collect_modes,
    empirical_transition,
    kf_predict,
    kf_update,
)
from torchcontact.sim import pushed_box_rollout, pushed_box_scene

FAST = os.environ.get("TORCHCONTACT_FAST") == "1"
# Figures and files go to the folder named by TORCHCONTACT_OUT, else to a new temporary one.
OUT = Path(os.environ.get("TORCHCONTACT_OUT") or tempfile.mkdtemp(prefix="torchcontact_"))
OUT.mkdir(parents=True, exist_ok=True)
print(f"outputs in {OUT}")
torch.manual_seed(0)
F64 = torch.float64

# %% [markdown]
# ## 1. A Kalman filter on a linear system
#
# A point moving at constant velocity in 1-D, state `(position, velocity)`, position measured
# with noise. `kf_predict` / `kf_update` are batched: here 500 independent filters (one per
# simulated trajectory) run as one tensor batch, and `kf_update` also returns the
# log-likelihood of each measurement.

# %%
h, steps, batch = 0.1, 50, 500
F = torch.tensor([[1.0, h], [0.0, 1.0]], dtype=F64)
Q = 1e-3 * torch.tensor([[h**3 / 3, h**2 / 2], [h**2 / 2, h]], dtype=F64)
H = torch.tensor([[1.0, 0.0]], dtype=F64)
R = torch.tensor([[0.25]], dtype=F64)
c, d = torch.zeros(2, dtype=F64), torch.zeros(1, dtype=F64)

x = torch.stack([torch.zeros(batch, dtype=F64), torch.ones(batch, dtype=F64)], -1)
belief = Gaussian(torch.zeros(batch, 2, dtype=F64), torch.eye(2, dtype=F64).expand(batch, 2, 2))
L_Q = torch.linalg.cholesky(Q)
truth, estimate, std, measured = [], [], [], []
for _ in range(steps):
    x = x @ F.T + torch.randn(batch, 2, dtype=F64) @ L_Q.T
    y = x[:, :1] + 0.5 * torch.randn(batch, 1, dtype=F64)
    belief = kf_predict(belief, F=F, c=c, Q=Q)
    belief, log_lik = kf_update(belief, y, H=H, d=d, R=R)
    truth.append(x[0, 0])
    measured.append(y[0, 0])
    estimate.append(belief.mean[0, 0])
    std.append(belief.cov[0, 0, 0].sqrt())
errors = torch.stack(truth) - torch.stack(estimate)
camera_errors = torch.stack(truth) - torch.stack(measured)
print(f"position RMSE over the first trajectory: filter {errors.pow(2).mean().sqrt():.3f}")
print(f"                                         camera {camera_errors.pow(2).mean().sqrt():.3f}")

# %%
t = torch.arange(steps) * h
est, sd = torch.stack(estimate), torch.stack(std)
fig, ax = plt.subplots(figsize=(7, 3))
ax.plot(t, torch.stack(measured), ".", color="0.6", label="measurement")
ax.plot(t, torch.stack(truth), "k", label="truth")
ax.plot(t, est, "C0", label="Kalman mean")
ax.fill_between(t, est - 2 * sd, est + 2 * sd, color="C0", alpha=0.2, label="±2σ")
ax.set_xlabel("time (s)")
ax.set_ylabel("position")
ax.legend(loc="upper left")
fig.tight_layout()
fig.savefig(OUT / "02_kalman.png", dpi=80)

# %% [markdown]
# ## 2. The RBPF against the exact posterior of a switching system
#
# A scalar random walk whose drift switches between `−1`, `0` and `+1` (K = 3 modes, a sticky
# Markov chain). With K modes and T steps there are `K^T` mode sequences; for T = 6 that is
# 729, few enough to run one Kalman filter per sequence and weight it by its evidence: the
# exact posterior `p(m_T | y_1:T)`. The RBPF approximates it with N particles.

# %%
K, T = 3, 6
model = LinearSwitchingModel(
    F=torch.ones(K, 1, 1, dtype=F64),
    c=torch.tensor([[-1.0], [0.0], [1.0]], dtype=F64),
    Q=torch.full((K, 1, 1), 0.1, dtype=F64),
    H=torch.ones(K, 1, 1, dtype=F64),
    d=torch.zeros(K, 1, dtype=F64),
    R=torch.full((K, 1, 1), 0.5, dtype=F64),
    transition=torch.tensor([[0.8, 0.15, 0.05], [0.1, 0.8, 0.1], [0.05, 0.15, 0.8]], dtype=F64),
    initial=torch.full((K,), 1.0 / K, dtype=F64),
)
prior = Gaussian(torch.zeros(1, dtype=F64), torch.eye(1, dtype=F64))
ys = torch.tensor([[0.9], [2.1], [2.8], [3.1], [2.2], [0.8]], dtype=F64)

# Exact: one Kalman filter per mode sequence, all sequences as one batch.
sequences = torch.tensor(list(itertools.product(range(K), repeat=T)))  # (K^T, T)
# m_0 ~ initial comes before the first step, so the first measured mode m_1 ~ initial · P.
log_p = torch.log(model.initial @ model.transition)[sequences[:, 0]]
log_p = log_p + torch.log(model.transition[sequences[:, :-1], sequences[:, 1:]]).sum(-1)
g = Gaussian(prior.mean.expand(len(sequences), 1), prior.cov.expand(len(sequences), 1, 1))
for step in range(T):
    m = sequences[:, step]
    g = kf_predict(g, F=model.F[m], c=model.c[m], Q=model.Q[m])
    g, ll = kf_update(g, ys[step], H=model.H[m], d=model.d[m], R=model.R[m])
    log_p = log_p + ll
exact = torch.zeros(K, dtype=F64).index_add_(0, sequences[:, -1], torch.softmax(log_p, 0))
print("exact p(m_T | y):", [round(v, 4) for v in exact.tolist()])

# %%
particle_counts = [10, 30, 100, 300] if FAST else [10, 30, 100, 300, 1000, 3000]
seeds = 20 if FAST else 100
error = {}
for N in particle_counts:
    rbpf = RBPF(model, N, proposal="bootstrap")
    belief = rbpf.init(prior, batch_shape=(seeds,))  # independent replicas as a batch
    gen = torch.Generator().manual_seed(N)
    for step in range(T):
        belief = rbpf.step(belief, ys[step], generator=gen)
    error[N] = (belief.mode_marginals() - exact).abs().sum(-1).mean().item()
    print(f"N = {N:5d}: mean L1 error of p(m_T | y) over {seeds} runs = {error[N]:.4f}")

# %%
fig, ax = plt.subplots(figsize=(5, 3))
ax.loglog(list(error), list(error.values()), "o-", label="bootstrap RBPF")
n = torch.tensor(particle_counts, dtype=F64)
ax.loglog(n, error[particle_counts[0]] * (n / n[0]) ** -0.5, "k--", label="∝ N^(-1/2)")
ax.set_xlabel("particles N")
ax.set_ylabel("L1 error of mode marginals")
ax.legend()
fig.tight_layout()
fig.savefig(OUT / "02_convergence.png", dpi=80)

# %% [markdown]
# With `proposal="all_modes"`, every particle expands into all K children, and while there
# are at most N children of positive weight nothing is sampled: the filter *is* the exact
# enumeration. (The paths start at `m_0`, so T steps make `K^(T+1)` of them.)

# %%
exhaustive = RBPF(model, K ** (T + 1), proposal="all_modes")
belief = exhaustive.init(prior)
for step in range(T):
    belief = exhaustive.step(belief, ys[step])
print("all_modes, N = K^(T+1):", [round(v, 4) for v in belief.mode_marginals().tolist()])
torch.testing.assert_close(belief.mode_marginals(), exact, atol=1e-10, rtol=0)

# %% [markdown]
# ## 3. Tracking a pushed box with the contact model
#
# A finger pushes a box along the ground, pauses, pushes again. The simulator's modes over
# 32 training rollouts give the mode table (each mode fixes all 12 contact slots) and an
# empirical transition matrix. `PlanarContactModel` turns the scene into a switching model:
# at every step it linearizes the mode-decoupled contact step (`solve_mode` + pose
# integration) at the belief's mean, once per mode, and penalizes modes whose step
# contradicts them (a stopped finger pulling the box). The camera sees the box pose with 5 mm
# and 0.02 rad noise; the finger's motion is known (it is the control).

# %%
scene = pushed_box_scene()
steps = 60
train, _ = pushed_box_rollout(scene, batch=32, steps=steps, seed=0)
table, ids, counts = collect_modes(train.mode)
K = len(table)
print(f"{K} modes seen in training; per-slot modes of the most frequent:")
print(table[:3])
sigma = torch.tensor([0.005, 0.005, 0.02], dtype=F64)
contact_model = PlanarContactModel(
    scene=scene,
    modes=table,
    Q=torch.diag(torch.tensor([1e-6] * 3 + [1e-4] * 3, dtype=F64)),
    R=torch.diag(sigma**2),
    transition=empirical_transition(ids, K, smoothing=0.1),
    initial=torch.full((K,), 1.0 / K, dtype=F64),
)
truth, controls = pushed_box_rollout(scene, batch=1, steps=steps, seed=1)
gen = torch.Generator().manual_seed(2)
y = truth.q[1:, 0, 0] + sigma * torch.randn(steps, 3, generator=gen, dtype=F64)

rbpf = RBPF(contact_model, 100 if FAST else 300, proposal="all_modes")
belief = rbpf.init(
    Gaussian(
        torch.tensor([0.01, 0.05, 0.0, 0.0, 0.0, 0.0], dtype=F64),
        torch.diag(torch.tensor([1e-4, 1e-6, 1e-4, 1e-2, 1e-2, 1e-2], dtype=F64)),
    )
)
means, stds, marginals, particles_x = [], [], [], []
for t in range(steps):
    control = KinematicControl(q=truth.q_kinematic[t, 0], v=controls[t, 0])
    belief = rbpf.step(belief, y[t], control=control, generator=gen)
    means.append(belief.mean())
    stds.append(belief.cov().diagonal().sqrt())
    marginals.append(belief.mode_marginals())
    particles_x.append(belief.gaussians.mean[:, 0])
means_t, stds_t, marg = torch.stack(means), torch.stack(stds), torch.stack(marginals)
true_x = truth.q[1:, 0, 0, 0]
true_id = torch.tensor([int((table == m).all(-1).nonzero()[0]) for m in truth.mode[:, 0]])
rmse_filter = (means_t[10:, 0] - true_x[10:]).pow(2).mean().sqrt()
rmse_camera = (y[10:, 0] - true_x[10:]).pow(2).mean().sqrt()
accuracy = (marg.argmax(-1) == true_id).double().mean()
print(f"x RMSE: RBPF {1e3 * rmse_filter:.2f} mm, camera {1e3 * rmse_camera:.2f} mm")
print(f"MAP mode = true mode in {100 * accuracy:.0f} % of the steps")

# %%
time = torch.arange(1, steps + 1) * scene.h
fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
ax = axes[0]
for t in range(steps):
    ax.plot(
        torch.full_like(particles_x[t], float(time[t])),
        1e3 * particles_x[t],
        ".",
        color="C0",
        alpha=0.05,
        ms=3,
    )
ax.plot(time, 1e3 * y[:, 0], "x", color="0.5", ms=4, label="camera")
ax.plot(time, 1e3 * true_x, "k", label="truth")
ax.plot(time, 1e3 * means_t[:, 0], "C1", label="RBPF mean (dots: particles)")
ax.set_ylabel("box x (mm)")
ax.legend(loc="upper left")
ax = axes[1]
ax.imshow(
    marg.T,
    aspect="auto",
    origin="lower",
    cmap="Blues",
    extent=(float(time[0]) - scene.h / 2, float(time[-1]) + scene.h / 2, -0.5, K - 0.5),
)
ax.plot(time, true_id, "r.", ms=4, label="true mode")
ax.set_ylabel("mode id")
ax.legend(loc="upper right")
ax = axes[2]
ax.plot(time, 1e3 * (y[:, 0] - true_x).abs(), color="0.5", label="|camera error|")
ax.plot(time, 1e3 * (means_t[:, 0] - true_x).abs(), "C1", label="|RBPF error|")
ax.plot(time, 2e3 * stds_t[:, 0], "C1--", label="RBPF 2σ")
ax.set_ylabel("x error (mm)")
ax.set_xlabel("time (s)")
ax.legend(loc="upper right")
fig.tight_layout()
fig.savefig(OUT / "02_pushed_box.png", dpi=80)
assert rmse_filter < rmse_camera

# %% [markdown]
# The ground fixes the box's height and angle exactly (the linearized contact constraint
# pins them), and while the finger pushes, the box moves with it. The filter is least sure
# right after the finger stops: whether the box coasts or stops with the finger only shows in
# the camera a few steps later. The `fixed_lag_marginals(lag)` of the belief answer that
# question in hindsight.
