"""The constrained Kalman projection out of contact against a NumPy Kalman update and a closed
form."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcontact.filters import Gaussian, RBPFBelief, project_out_of_contact
from torchcontact.sim import Scene, penetration, pushed_box_scene

F64 = torch.float64
A, B = 0.1, 0.05  # the pushed box's half extents
FAR = torch.tensor([[-0.5, 0.03, 0.0]], dtype=F64)  # the finger, away from the box


def _belief(mean: torch.Tensor, cov: torch.Tensor) -> RBPFBelief:
    """An RBPF belief with the given ``(*B, N, 6)`` particle means and ``(*B, N, 6, 6)``
    covariances, one mode, uniform weights."""
    *batch, N, _ = mean.shape
    prior = Gaussian(mean[..., 0, :], cov[..., 0, :, :])
    return RBPFBelief(
        modes=torch.zeros(*batch, N, dtype=torch.long),
        log_weights=torch.full((*batch, N), -math.log(N), dtype=F64),
        gaussians=Gaussian(mean, cov),
        log_evidence=torch.zeros(batch, dtype=F64),
        history=torch.zeros(*batch, N, 1, dtype=torch.long),
        degenerate=torch.zeros(batch, dtype=torch.bool),
        prior=prior,
        num_modes=1,
    )


def _gaps(scene: Scene, pose: np.ndarray, q_kinematic: torch.Tensor) -> np.ndarray:
    phi, _, _ = penetration(
        scene, q=torch.tensor(pose, dtype=F64)[None], q_kinematic=q_kinematic.to(F64)
    )
    return phi.numpy()


def test_closed_form_box_two_millimetres_under_the_ground() -> None:
    """Flat box, mean 2 mm deep: its two bottom corners give the rows ``(0, 1, ∓a)`` with
    gap −2 mm; with a diagonal covariance the joint update has the closed form
    ``Δy = 2 δ p_y / (2 p_y + σ²)``, ``p_y⁺ = p_y σ² / (2 p_y + σ²)``,
    ``p_θ⁺ = p_θ σ² / (2 a² p_θ + σ²)``, the rest unchanged."""
    scene = pushed_box_scene()
    depth, sigma = 0.002, 1e-4
    variances = torch.tensor([25e-6, 16e-6, 1e-3, 1e-4, 1e-4, 1e-2], dtype=F64)
    mean = torch.tensor([[0.01, B - depth, 0.0, 0.1, 0.0, 0.0]], dtype=F64)
    belief = _belief(mean, variances.diag()[None])
    out = project_out_of_contact(belief, scene, FAR, gap_sigma=sigma).gaussians
    _, p_y, p_t = variances[:3].tolist()
    expected = mean.clone()
    expected[0, 1] += 2 * depth * p_y / (2 * p_y + sigma**2)
    torch.testing.assert_close(out.mean, expected, rtol=0, atol=1e-12)
    assert float(out.mean[0, 1]) == pytest.approx(B, abs=2 * depth * sigma**2 / (2 * p_y))
    expected_cov = variances.clone()
    expected_cov[1] = p_y * sigma**2 / (2 * p_y + sigma**2)
    expected_cov[2] = p_t * sigma**2 / (2 * A**2 * p_t + sigma**2)
    torch.testing.assert_close(out.cov[0], expected_cov.diag(), rtol=1e-9, atol=1e-18)
    assert float(out.cov[0, 1, 1]) < 1e-3 * p_y  # shrunk along the normal


def test_matches_a_numpy_kalman_update_with_finite_difference_gap_rows() -> None:
    """Random particles entering the ground and a finger: each one's posterior is the
    textbook Kalman update with ``0 = φ(μ) + J (x − μ) + e`` for its penetrating slots,
    ``J`` from central differences of the gaps."""
    scene = pushed_box_scene()
    generator = torch.Generator().manual_seed(3)
    N = 12
    finger = torch.tensor([[-A - 0.01 + 0.001, 0.03, 0.0]], dtype=F64)  # 1 mm into the box
    mean = torch.zeros(N, 6, dtype=F64)
    mean[:, 0] = 0.001 * torch.randn(N, generator=generator, dtype=F64)
    mean[:, 1] = B - 0.002 * torch.rand(N, generator=generator, dtype=F64) + 0.0005
    mean[:, 2] = 0.02 * torch.randn(N, generator=generator, dtype=F64)
    mean[:, 3:] = 0.1 * torch.randn(N, 3, generator=generator, dtype=F64)
    mean[:3, :2] += torch.tensor([0.005, 0.01], dtype=F64)  # clear of the ground and finger
    root = 0.003 * torch.randn(N, 6, 6, generator=generator, dtype=F64)
    cov = root @ root.mT + 1e-6 * torch.eye(6, dtype=F64)
    sigma = 1e-4
    out = project_out_of_contact(_belief(mean, cov), scene, finger, gap_sigma=sigma).gaussians
    penetrated = 0
    for i in range(N):
        mu, P = mean[i].numpy(), cov[i].numpy()
        phi = _gaps(scene, mu[:3], finger)
        _, _, inside = penetration(scene, q=mean[i, None, :3], q_kinematic=finger)
        slots = inside.nonzero().squeeze(-1).numpy()
        if slots.size == 0:
            torch.testing.assert_close(out.mean[i], mean[i], rtol=0, atol=1e-15)
            continue
        penetrated += 1
        J = np.zeros((slots.size, 6))
        step = 1e-7
        for k in range(3):
            dq = np.zeros(3)
            dq[k] = step
            up, down = _gaps(scene, mu[:3] + dq, finger), _gaps(scene, mu[:3] - dq, finger)
            J[:, k] = (up[slots] - down[slots]) / (2 * step)
        S = J @ P @ J.T + sigma**2 * np.eye(slots.size)
        K = P @ J.T @ np.linalg.inv(S)
        expected_mean = mu + K @ (0.0 - phi[slots])
        expected_cov = (np.eye(6) - K @ J) @ P
        torch.testing.assert_close(
            out.mean[i], torch.from_numpy(expected_mean), rtol=1e-6, atol=1e-9
        )
        torch.testing.assert_close(
            out.cov[i], torch.from_numpy(expected_cov), rtol=1e-5, atol=1e-12
        )
    assert 3 <= penetrated < N  # both branches were exercised


@pytest.mark.bitwise("particles that penetrate nothing are returned as they came (no arithmetic)")
def test_particles_that_penetrate_nothing_and_the_weights_are_untouched() -> None:
    scene = pushed_box_scene()
    mean = torch.tensor([[0.0, B - 0.002, 0.0, 0, 0, 0], [0.0, B + 0.001, 0.0, 0, 0, 0]], dtype=F64)
    cov = (1e-5 * torch.eye(6, dtype=F64)).expand(2, 6, 6)
    belief = _belief(mean, cov)
    projected = project_out_of_contact(belief, scene, FAR, gap_sigma=1e-4)
    after = projected.gaussians
    torch.testing.assert_close(after.mean[1], mean[1], rtol=0, atol=0)
    torch.testing.assert_close(after.cov[1], cov[1], rtol=0, atol=0)
    torch.testing.assert_close(projected.log_weights, belief.log_weights, rtol=0, atol=0)
    assert not torch.allclose(after.mean[0], mean[0])
    # Nothing penetrates: the same belief comes back.
    clear = _belief(mean[1:], cov[1:])
    assert project_out_of_contact(clear, scene, FAR, gap_sigma=1e-4) is clear


def test_bad_arguments_name_the_argument() -> None:
    scene = pushed_box_scene()
    belief = _belief(torch.zeros(1, 6, dtype=F64), torch.eye(6, dtype=F64)[None])
    with pytest.raises(ValueError, match=r"^gap_sigma: "):
        project_out_of_contact(belief, scene, FAR, gap_sigma=0.0)
    with pytest.raises(ValueError, match=r"^q_kinematic"):
        project_out_of_contact(belief, scene, FAR[None], gap_sigma=1e-4)
