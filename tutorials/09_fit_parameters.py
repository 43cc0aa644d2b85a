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
# # 09 · Fitting friction from the filter's evidence
#
# Once a filter tracks an object, the next question is: what are the physical parameters of
# the set-up? The contact RBPF's running evidence `log p(y | θ)` (the log-likelihood of all
# measurements given the parameters θ) is differentiable in the scene's friction and in the
# noise covariances, so θ can be fitted by maximizing it, with a standard error from its
# curvature. This notebook:
#
# 1. simulates boxes sliding to a stop under a noisy camera, with a friction coefficient
#    μ = 0.37 that the fit is not told;
# 2. writes the evidence as a function of μ (and of the camera noise σ) with the RBPF;
# 3. draws the evidence around the truth;
# 4. fits μ with `torchcontact.filters.fit_parameters`, with its standard error, and compares
#    it to the truth.
#
# `train/fit_params.py` runs this experiment over many drawn parameters and compares the
# gradient fit against a grid and CMA-ES ([results](../experiments/fitting.md)). In fast mode
# (`TORCHCONTACT_FAST=1`) the logs are short and few, so the numbers are illustrations.

# %%
import os
import tempfile
from dataclasses import replace
from pathlib import Path

import matplotlib.pyplot as plt
import torch

from torchcontact.experiments import box_scene
from torchcontact.filters import RBPF, Gaussian, PlanarContactModel, fit_parameters
from torchcontact.sim import Simulator

FAST = os.environ.get("TORCHCONTACT_FAST") == "1"
# Figures and files go to the folder named by TORCHCONTACT_OUT, else to a new temporary one.
OUT = Path(os.environ.get("TORCHCONTACT_OUT") or tempfile.mkdtemp(prefix="torchcontact_"))
OUT.mkdir(parents=True, exist_ok=True)
print(f"outputs in {OUT}")
# The filter works on small matrices, for which one thread is fastest (the fitting script too
# runs on one core).
torch.set_num_threads(1)
F64 = torch.float64

# %% [markdown]
# ## 1. Boxes sliding to a stop
#
# A 0.2 × 0.1 m, 1 kg box (`box_scene`) is launched along the ground at about 0.6 m/s;
# Coulomb friction decelerates it at μ g until it sticks, after about 0.17 s. A camera
# measures its planar pose `(x, y, angle)` every 10 ms with Gaussian noise: σ = 2 mm on the
# position, 20 mrad on the angle. Several boxes, launched at slightly different speeds, make
# one data set.

# %%
TRUE_MU, TRUE_SIGMA_MM = 0.37, 2.0
boxes, steps = (3, 20) if FAST else (8, 40)
generator = torch.Generator().manual_seed(0)

simulator = Simulator(box_scene(TRUE_MU))
q = torch.zeros(boxes, 1, 3, dtype=F64)  # (trial, body, (x, y, angle))
q[:, 0, 1] = 0.05  # resting on the ground: the box's centre is half its height up
v = torch.zeros(boxes, 1, 3, dtype=F64)
v[:, 0, 0] = 0.55 + 0.1 * torch.rand(boxes, generator=generator, dtype=F64)
rollout = simulator.rollout(simulator.initial_state(q=q, v=v), steps=steps)


def camera_sigma(sigma_mm: torch.Tensor | float) -> torch.Tensor:
    """(3,) camera standard deviations: σ mm on x and y, 10 σ mrad on the angle."""
    return 1e-3 * torch.as_tensor(sigma_mm, dtype=F64) * torch.tensor([1.0, 1.0, 10.0], dtype=F64)


y = rollout.q[1:, :, 0] + camera_sigma(TRUE_SIGMA_MM) * torch.randn(
    steps, boxes, 3, generator=generator, dtype=F64
)
time_s = 0.01 * torch.arange(1, steps + 1)
fig, ax = plt.subplots(figsize=(6, 3))
for b in range(boxes):
    ax.plot(time_s, 1e3 * rollout.v[1:, b, 0, 0], color=f"C{b}")
ax.set_xlabel("time (s)")
ax.set_ylabel("true speed (mm/s)")
ax.set_title(f"{boxes} boxes sliding to a stop, μ = {TRUE_MU}")
fig.tight_layout()
fig.savefig(OUT / "09_speeds.png", dpi=80)

# %% [markdown]
# ## 2. The evidence as a function of the parameters
#
# The filter is the RBPF over the contact modes a sliding box visits: both bottom corners
# sliding, then both sticking. `PlanarContactModel.from_rollout` collects them from a rollout
# of a *nominal* scene (μ = 0.5, a guess: only the list of modes is taken from it) and
# linearizes the contact dynamics of each mode exactly. Replacing the model's scene by one with
# friction μ, and its measurement covariance by one with noise σ, gives the filter of those
# parameters; its `log_evidence`, summed over the boxes, is `log p(y | μ, σ)`.
#
# With the all-modes proposal every particle expands into all modes at every step, and the
# children are cut back to the particle count by keeping every heavy child and sampling only
# among the light ones (Fearnhead–Clifford resampling), so the random numbers hardly matter:
# the evidence is the same to about a thousandth of a nat for any seed, and its gradient comes
# from autograd through the linearized dynamics and the Kalman updates.

# %%
nominal = box_scene(0.5)
nominal_simulator = Simulator(nominal)
nominal_rollout = nominal_simulator.rollout(
    nominal_simulator.initial_state(q=q[:1], v=v[:1]), steps=steps
)
model = PlanarContactModel.from_rollout(
    nominal,
    nominal_rollout,
    Q=torch.diag(torch.tensor([1e-8] * 3 + [1e-6] * 3, dtype=F64)),  # small process noise
    R=torch.diag(camera_sigma(TRUE_SIGMA_MM) ** 2),
)
print(f"{model.num_modes} contact modes")
# The boxes start at a known pose; their launch speed is known to about ±0.1 m/s.
prior = Gaussian(
    torch.cat([q[:, 0], torch.tensor([0.6, 0.0, 0.0], dtype=F64).expand(boxes, 3)], -1),
    torch.diag(torch.tensor([1e-6, 1e-6, 1e-5, 1e-2, 1e-4, 1e-4], dtype=F64)).expand(boxes, 6, 6),
)
particles = 4 if FAST else 8


def log_evidence(theta: dict[str, torch.Tensor], seed: int = 0) -> torch.Tensor:
    """log p(y | μ, σ) over all boxes; σ is the true one unless theta has "sigma_mm"."""
    sigma_mm = theta.get("sigma_mm", torch.tensor(TRUE_SIGMA_MM, dtype=F64))
    fitted = replace(model, scene=box_scene(theta["mu"]), R=torch.diag(camera_sigma(sigma_mm) ** 2))
    rbpf = RBPF(fitted, particles, proposal="all_modes")
    rng = torch.Generator().manual_seed(seed)
    belief = rbpf.init(prior)
    for t in range(steps):
        belief = rbpf.step(belief, y[t], generator=rng)
    return belief.log_evidence.sum()


at_truth = {"mu": torch.tensor(TRUE_MU, dtype=F64, requires_grad=True)}
value = log_evidence(at_truth)
(slope,) = torch.autograd.grad(value, [at_truth["mu"]])
print(f"log p(y | μ = {TRUE_MU}) = {value.item():.3f} nats, d/dμ = {slope.item():.1f} nats")
with torch.no_grad():
    for seed in (1, 2):
        change = log_evidence(at_truth, seed=seed) - value
        print(f"with random seed {seed}: {change.item():+.4f} nats")

# %% [markdown]
# ## 3. The evidence around the truth
#
# On a grid of μ around the truth (σ at its true value) the evidence peaks near the truth. How
# sharp the peak is says how well the data pin μ down: near its maximum `log p` is close to
# the parabola `log p(μ̂) − (μ − μ̂)² / (2 s²)`, where `s` is the standard error that the fit
# of the next section computes from the curvature.
#
# The curve is not perfectly smooth: where a small change of μ moves the step at which the
# filter's box comes to rest, the evidence steps by up to about a nat. Against a peak tens of
# nats deep (many boxes, long logs) that is a ripple; with the few short logs of fast mode it
# is not, and the fit may stop on a ripple a little off the grid's best point.

# %%
with torch.no_grad():
    grid = torch.linspace(TRUE_MU - 0.06, TRUE_MU + 0.06, 5 if FAST else 25, dtype=F64)
    curve = torch.stack([log_evidence({"mu": mu}) for mu in grid])
print(f"grid maximum at μ = {float(grid[curve.argmax()]):.3f}")

# %% [markdown]
# ## 4. Fitting μ, with a standard error
#
# `fit_parameters` maximizes the evidence with L-BFGS from a starting guess, keeping μ ≥ 0
# through the parametrization μ = exp(u), and returns the estimate with its standard error
# (the square root of the inverse curvature of `log p` at the estimate). The estimate should
# lie within about two standard errors of the truth: the plot shows the evidence, the parabola
# of the standard error, the truth and the estimate's ± 2 s.e. band.

# %%
fit = fit_parameters(log_evidence, {"mu": 0.5}, lower={"mu": 0.0})
mu_hat, mu_error = float(fit.values["mu"]), float(fit.standard_errors["mu"])
print(
    f"μ = {mu_hat:.4f} ± {mu_error:.4f} (truth {TRUE_MU}; "
    f"{(mu_hat - TRUE_MU) / mu_error:+.1f} standard errors off), "
    f"{fit.evaluations} evaluations, converged: {fit.converged}"
)

fine = torch.linspace(float(grid[0]), float(grid[-1]), 200, dtype=F64)
parabola = float(fit.log_evidence) - (fine - mu_hat) ** 2 / (2 * mu_error**2)
fig, ax = plt.subplots(figsize=(6, 3.5))
ax.plot(grid, curve - curve.max(), "o-", label="evidence (RBPF)")
ax.plot(fine, parabola - curve.max(), "--", label="parabola from the standard error")
ax.axvline(TRUE_MU, color="k", lw=1, label="true μ")
ax.axvspan(mu_hat - 2 * mu_error, mu_hat + 2 * mu_error, alpha=0.2, label="estimate ± 2 s.e.")
ax.set_ylim(float((curve - curve.max()).min()) - 1, 1)
ax.set_xlabel("friction coefficient μ")
ax.set_ylabel("log p(y | μ) − max (nats)")
ax.legend(fontsize=8)
fig.tight_layout()
fig.savefig(OUT / "09_evidence.png", dpi=80)

# %% [markdown]
# `fit_parameters` fits several parameters at once: `train/fit_params.py` fits the friction
# and the camera noise together, `{"mu": ..., "sigma_mm": ...}` with both bounded below by 0,
# and their standard errors then account for each other's uncertainty. What it cannot do is
# fit what the data do not determine: with no known applied force the box's mass scales
# gravity, friction and inertia alike, so its evidence is flat in the mass and its standard
# error would be `nan`.
