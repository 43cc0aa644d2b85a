"""Long-run numerical stability in float32 (the figures of the README's Reliability section).

* Kalman: 100,000 steps of ``kf_predict`` + ``kf_update`` on a constant-velocity model with a
  position measurement, four filters at once (one per measurement noise, from 1 mm to 1 m):
  every covariance stays finite and symmetric PSD, and the predicted covariance converges to
  the discrete algebraic Riccati solution (``scipy.linalg.solve_discrete_are``, float64).
* RBPF: 20,000 steps of a two-mode linear switching model in float32: finite weights and
  evidence throughout, and the evidence close to a float64 run of the same seed.

Run with ``-s`` to print the measured figures.
"""

from __future__ import annotations

import math
import time

import numpy as np
import scipy.linalg
import torch

from torchcontact.filters import RBPF, Gaussian, LinearSwitchingModel, kf_predict, kf_update
from torchcontact.filters import _linalg as la
from torchcontact.filters._kalman import predict_core, update_core

DT, ACCEL_PSD = 0.01, 0.5  # 100 Hz, white-noise acceleration (m²/s³)
SIGMAS = (1e-3, 1e-2, 1e-1, 1.0)  # position measurement noise of the four filters (m)


def constant_velocity() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``F, Q, H, R (4, 1, 1)`` of the 1-D constant-velocity model, rounded to float32 (so
    the float64 reference solves the model the float32 filter runs)."""
    F = np.array([[1.0, DT], [0.0, 1.0]])
    Q = ACCEL_PSD * np.array([[DT**3 / 3, DT**2 / 2], [DT**2 / 2, DT]])
    H = np.array([[1.0, 0.0]])
    R = np.array(SIGMAS)[:, None, None] ** 2
    return tuple(a.astype(np.float32).astype(np.float64) for a in (F, Q, H, R))  # type: ignore[return-value]


def simulate(steps: int, seed: int = 0) -> np.ndarray:
    """``(steps, 4)`` position measurements of one trajectory, each filter's own noise."""
    rng = np.random.default_rng(seed)
    F, Q, _, _ = constant_velocity()
    root = np.linalg.cholesky(Q)
    x = np.zeros(2)
    ys = np.empty((steps, len(SIGMAS)))
    for t in range(steps):
        x = F @ x + root @ rng.normal(size=2)
        ys[t] = x[0] + np.array(SIGMAS) * rng.normal(size=len(SIGMAS))
    return ys


def test_kalman_100k_steps_float32_stays_psd_and_reaches_the_riccati_solution() -> None:
    steps, B = 100_000, len(SIGMAS)
    F64, Q64, H64, R64 = constant_velocity()
    ys = torch.from_numpy(simulate(steps)).float()
    F, Q, H = (torch.from_numpy(a).float() for a in (F64, Q64, H64))
    R = torch.from_numpy(R64).float()  # (4, 1, 1)
    prior = Gaussian(torch.zeros(B, 2), torch.eye(2).expand(B, 2, 2).contiguous())

    # The public functions on the first steps, and their kernels (predict_core, update_core,
    # which kf_predict and kf_update run between validation and layout views) for the rest:
    # the same operations on the same numbers (checked to float32 rounding: a layout view may
    # take another BLAS kernel).
    check = 200
    g = prior
    for t in range(check):
        g = kf_predict(g, F=F, Q=Q)
        g, _ = kf_update(g, ys[t, :, None], H=H, R=R)
    F_bl, Q_bl, H_bl = (la.to_batch_last(a, 2, 1) for a in (F, Q, H))
    R_bl = la.to_batch_last(R, 2, 1)
    mean, cov = la.to_batch_last(prior.mean, 1, 1), la.to_batch_last(prior.cov, 2, 1)
    y_bl = ys.T.contiguous()  # (1 → m, B) per step below: ys[t] as (1, B)
    posterior = torch.empty(steps, 2, 2, B)
    predicted_last = cov
    start = time.perf_counter()
    for t in range(steps):
        mean, cov = predict_core(mean, cov, F_bl, None, Q_bl)
        predicted_last = cov
        mean, cov, _ = update_core(mean, cov, y_bl[:, t].unsqueeze(0), H_bl, None, R_bl, None)
        posterior[t] = cov
        if t == check - 1:
            torch.testing.assert_close(la.to_batch_first(mean, 1), g.mean, rtol=1e-5, atol=1e-7)
            torch.testing.assert_close(la.to_batch_first(cov, 2), g.cov, rtol=1e-5, atol=1e-9)
    wall = time.perf_counter() - start
    assert bool(torch.isfinite(mean).all())
    assert bool(torch.isfinite(posterior).all())
    P = posterior.double()
    asymmetry = float((P - P.transpose(1, 2)).abs().max())
    a, b, d = P[:, 0, 0], P[:, 0, 1], P[:, 1, 1]
    # smallest eigenvalue of each 2 × 2 matrix, relative to its largest entry (float64)
    eig_min = (a + d) / 2 - torch.sqrt(((a - d) / 2) ** 2 + b**2)
    rel_eig_min = float((eig_min / P.abs().amax(dim=(1, 2))).min())
    # Riccati: the steady predicted covariance X = F X Fᵀ - F X Hᵀ (H X Hᵀ + R)⁻¹ H X Fᵀ + Q
    errors = []
    for i in range(B):
        X = scipy.linalg.solve_discrete_are(F64.T, H64.T, Q64, R64[i])
        Pi = predicted_last[..., i].double().numpy()
        errors.append(np.abs(Pi - X).max() / np.abs(X).max())
    print(
        f"\nKalman float32, {steps} steps x {B} filters: wall {wall:.1f} s, max |P - Pᵀ| "
        f"{asymmetry:.3g}, min eigenvalue / max|P| {rel_eig_min:.3g}, Riccati relative "
        f"error {', '.join(f'{e:.2g}' for e in errors)} (R = {SIGMAS} m²)"
    )
    assert asymmetry == 0.0  # symmetrized exactly at every step
    # PSD to the tolerance of check_symmetric_psd (8 n eps relative to the largest entry)
    assert rel_eig_min >= -8 * 2 * torch.finfo(torch.float32).eps
    # The Riccati recursion contracts towards X, slowly for the filter with R = 1 m² (a few
    # percent per step): each step's float32 rounding (a few eps ≈ 1e-7 relative, and the
    # input rounding of F, Q, H, R is in the reference) accumulates over the ~1 / (1 - ρ²)
    # steps it takes to forget it, to ~1e-5 (measured 5e-6). 1e-4 (≈ 800 eps) leaves that
    # margin; a drift would grow with the step count instead.
    assert max(errors) < 1e-4


def switching_model(dtype: torch.dtype) -> LinearSwitchingModel:
    """Two modes of a 2-D state (position, velocity): free motion and a sticking contact."""
    F = torch.tensor([[[1.0, 0.1], [0.0, 1.0]], [[1.0, 0.0], [0.0, 0.2]]], dtype=torch.float64)
    Q = torch.tensor([[1e-3, 0.0], [0.0, 1e-2]], dtype=torch.float64).expand(2, 2, 2)
    return LinearSwitchingModel(
        F=F,
        c=torch.tensor([[0.0, 0.0], [0.0, -0.05]], dtype=torch.float64),
        Q=Q.clone(),
        H=torch.tensor([[1.0, 0.0]], dtype=torch.float64).expand(2, 1, 2).clone(),
        d=torch.zeros(2, 1, dtype=torch.float64),
        R=torch.full((2, 1, 1), 0.01, dtype=torch.float64),
        transition=torch.tensor([[0.95, 0.05], [0.1, 0.9]], dtype=torch.float64),
        initial=torch.tensor([0.5, 0.5], dtype=torch.float64),
    ).to(dtype)


def simulate_switching(steps: int, seed: int = 1) -> torch.Tensor:
    """``(steps, 1)`` measurements drawn from the float64 model."""
    model = switching_model(torch.float64)
    rng = np.random.default_rng(seed)
    F, c, Q = model.F.numpy(), model.c.numpy(), model.Q.numpy()
    trans = model.transition.numpy()
    mode, x = 0, np.zeros(2)
    ys = np.empty((steps, 1))
    for t in range(steps):
        mode = int(rng.choice(2, p=trans[mode]))
        x = F[mode] @ x + c[mode] + np.linalg.cholesky(Q[mode]) @ rng.normal(size=2)
        x[0] = np.clip(x[0], -50.0, 50.0)  # keep the free motion bounded
        ys[t] = x[0] + 0.1 * rng.normal()
    return torch.from_numpy(ys)


def run_rbpf(dtype: torch.dtype, ys: torch.Tensor) -> tuple[torch.Tensor, bool, float]:
    """The final log-evidence, whether every step's weights and evidence were finite, and
    the wall time."""
    rbpf = RBPF(switching_model(dtype), 32)
    belief = rbpf.init(Gaussian(torch.zeros(2, dtype=dtype), torch.eye(2, dtype=dtype)))
    gen = torch.Generator().manual_seed(0)
    finite = torch.tensor(True)
    ys = ys.to(dtype)
    start = time.perf_counter()
    for y in ys:
        belief = rbpf.step(belief, y, generator=gen)
        # no host synchronization per step: one boolean accumulated on the tensors
        finite = finite & (belief.log_weights < math.inf).all() & belief.log_evidence.isfinite()
    return belief.log_evidence, bool(finite), time.perf_counter() - start


def test_rbpf_20k_steps_float32_keeps_finite_weights_and_evidence() -> None:
    steps = 20_000
    ys = simulate_switching(steps)
    ev32, finite32, wall32 = run_rbpf(torch.float32, ys)
    ev64, finite64, _ = run_rbpf(torch.float64, ys)
    per_step = abs(float(ev32) - float(ev64)) / steps
    print(
        f"\nRBPF float32, {steps} steps, N = 32: wall {wall32:.1f} s, log-evidence "
        f"{float(ev32):.6g} (float64 {float(ev64):.6g}; |difference| / steps {per_step:.2g})"
    )
    assert finite32
    assert finite64
    assert not bool(ev32.isnan())
    # The same draws (float64 uniforms in both runs) with weights rounded differently: the
    # runs agree until a resampling decision differs, then differ by Monte Carlo noise,
    # here far below the ~1e-3 nats per step of a mistaken mode path.
    assert per_step < 1e-3
