"""Bad input at the filters' entry points: each case raises ``ValueError`` naming the argument
at fault (never another exception, never a silent NaN/inf/non-PSD result), and a measurement
with an extra batch dim broadcasts like any other batch dim."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import pytest
import torch
from torch import Tensor

from torchcontact.filters import (
    RBPF,
    SE2,
    SE3,
    Gaussian,
    LinearSwitchingModel,
    PlanarContactModel,
    Proposal,
    ekf_predict,
    ekf_update,
    kf_predict,
    kf_update,
    quat_exp,
    quat_log,
    wrap_angle,
)


def _prior(dtype: torch.dtype = torch.float64, n: int = 2, scale: float = 1.0) -> Gaussian:
    return Gaussian(torch.zeros(n, dtype=dtype), scale * torch.eye(n, dtype=dtype))


def test_kf_update_refuses_non_symmetric_R() -> None:
    # Before: accepted, and the posterior covariance had a negative eigenvalue.
    R = torch.tensor([[1.0, 100.0], [0.0, 1.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^R: must be symmetric"):
        kf_update(_prior(), torch.zeros(2, dtype=torch.float64), H=torch.eye(2).double(), R=R)


def test_kf_update_refuses_negative_definite_R_even_with_positive_innovation() -> None:
    # H P Hᵀ + R = 9.5 I is positive definite, R = -0.5 I is not a covariance.
    R = -0.5 * torch.eye(2, dtype=torch.float64)
    g = _prior(scale=10.0)
    with pytest.raises(ValueError, match=r"^R: must be symmetric positive semi-definite"):
        kf_update(g, torch.zeros(2, dtype=torch.float64), H=torch.eye(2).double(), R=R)


def test_kf_predict_refuses_negative_Q() -> None:
    # Before: returned the "covariance" -9 I.
    Q = -10.0 * torch.eye(2, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^Q: must be symmetric positive semi-definite"):
        kf_predict(_prior(), F=torch.eye(2, dtype=torch.float64), Q=Q)


def test_kf_predict_overflow_names_F() -> None:
    # Before: returned inf (1e30² overflows float32).
    F = 1e30 * torch.eye(2)
    with pytest.raises(ValueError, match=r"^F: the prediction .* overflows torch.float32"):
        kf_predict(_prior(torch.float32), F=F, Q=torch.eye(2))


def test_kf_update_overflow_names_H_and_y() -> None:
    g = _prior(torch.float32)
    with pytest.raises(ValueError, match=r"^H: the innovation covariance .* overflows"):
        kf_update(g, torch.zeros(2), H=1e20 * torch.eye(2), R=torch.eye(2))
    with pytest.raises(ValueError, match=r"^y: the residual"):
        kf_update(g, torch.full((2,), 3e38), H=torch.eye(2), R=torch.eye(2) * 1e-30)


def _numpy_update(
    mean: np.ndarray, cov: np.ndarray, y: np.ndarray, H: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """The Kalman update written out in NumPy (the textbook equations)."""
    S = H @ cov @ H.T + R
    K = cov @ H.T @ np.linalg.inv(S)
    r = y - H @ mean
    A = np.eye(len(mean)) - K @ H
    log_lik = -0.5 * (r @ np.linalg.solve(S, r) + np.linalg.slogdet(S)[1])
    return mean + K @ r, A @ cov @ A.T + K @ R @ K.T, log_lik - 0.5 * len(y) * np.log(2 * np.pi)


def test_kf_update_broadcasts_a_measurement_with_an_extra_batch_dim() -> None:
    # The documented rule: y (*B', m) broadcasts against the batch of g. Before: failed in
    # torch.cat with a RuntimeError.
    rng = np.random.default_rng(0)
    A = rng.normal(size=(3, 3))
    cov = A @ A.T + np.eye(3)
    mean, H, R = rng.normal(size=3), rng.normal(size=(2, 3)), np.diag([0.5, 2.0])
    ys = rng.normal(size=(4, 2))
    g = Gaussian(torch.from_numpy(mean), torch.from_numpy(cov))
    post, log_lik = kf_update(g, torch.from_numpy(ys), H=torch.from_numpy(H), R=torch.from_numpy(R))
    assert post.mean.shape == (4, 3)
    assert post.cov.shape == (4, 3, 3)
    assert log_lik.shape == (4,)
    for i, y in enumerate(ys):
        m_ref, c_ref, l_ref = _numpy_update(mean, cov, y, H, R)
        np.testing.assert_allclose(post.mean[i].numpy(), m_ref, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(post.cov[i].numpy(), c_ref, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(float(log_lik[i]), l_ref, rtol=1e-10)


def test_ekf_update_refuses_a_nan_measurement_function() -> None:
    # Before: h(x) = NaN was taken for "no measurement" (prior returned, likelihood 1).
    def h(x: Tensor) -> Tensor:
        return x * torch.nan

    with pytest.raises(ValueError, match=r"^h: returned NaN or inf"):
        ekf_update(_prior(), torch.zeros(2, dtype=torch.float64), h, R=torch.eye(2).double())


def test_ekf_predict_refuses_nan_dynamics() -> None:
    # Before: returned a NaN mean.
    def f(x: Tensor) -> Tensor:
        return x + torch.nan

    with pytest.raises(ValueError, match=r"^f: returned NaN or inf"):
        ekf_predict(_prior(), f, Q=torch.eye(2, dtype=torch.float64))


def test_ekf_refuses_non_symmetric_noise() -> None:
    bad = torch.tensor([[1.0, 5.0], [0.0, 1.0]], dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^Q: must be symmetric"):
        ekf_predict(_prior(), lambda x: x, Q=bad)
    with pytest.raises(ValueError, match=r"^R: must be symmetric"):
        ekf_update(_prior(), torch.zeros(2, dtype=torch.float64), lambda x: x, R=bad)


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("mean", lambda: torch.zeros(2, dtype=torch.float16), r"^mean: expected float32"),
        ("cov", lambda: torch.tensor([[1.0, 3.0], [0.0, 1.0]]), r"^cov: must be symmetric"),
        ("cov", lambda: torch.tensor([[1.0, 2.0], [2.0, 1.0]]), r"^cov: must be symmetric pos"),
    ],
)
def test_gaussian_refuses_float16_and_non_psd(
    field: str, value: Callable[[], Tensor], match: str
) -> None:
    fields = {"mean": torch.zeros(2), "cov": torch.eye(2)}
    fields[field] = value()
    with pytest.raises(ValueError, match=match):
        Gaussian(**fields)


def _switching(dtype: torch.dtype = torch.float64) -> LinearSwitchingModel:
    K, n = 2, 2
    return LinearSwitchingModel(
        F=torch.eye(n, dtype=dtype).expand(K, n, n).clone(),
        c=torch.zeros(K, n, dtype=dtype),
        Q=0.1 * torch.eye(n, dtype=dtype).expand(K, n, n).clone(),
        H=torch.eye(n, dtype=dtype)[:1].expand(K, 1, n).clone(),
        d=torch.zeros(K, 1, dtype=dtype),
        R=torch.ones(K, 1, 1, dtype=dtype),
        transition=torch.tensor([[0.9, 0.1], [0.2, 0.8]], dtype=dtype),
        initial=torch.tensor([0.5, 0.5], dtype=dtype),
    )


def test_linear_switching_model_refuses_float16() -> None:
    model = _switching()
    fields = {f.name: getattr(model, f.name).half() for f in dataclasses.fields(model)}
    with pytest.raises(ValueError, match=r"^F: expected a float32 or float64"):
        LinearSwitchingModel(**fields)


@pytest.mark.parametrize("proposal", ["bootstrap", "all_modes"])
@pytest.mark.parametrize(
    ("change", "match"),
    [
        (lambda b: {"log_evidence": torch.full_like(b.log_evidence, torch.nan)}, "log_evidence"),
        (lambda b: {"log_weights": b.log_weights.clone().fill_(torch.nan)}, "log_weights"),
        (lambda b: {"modes": b.modes + 5}, r"modes must lie in \[0, K\)"),
        (lambda b: {"modes": b.modes - 1}, r"modes must lie in \[0, K\)"),
    ],
)
def test_rbpf_step_validates_the_belief(
    proposal: Proposal, change: Callable[..., dict[str, Tensor]], match: str
) -> None:
    # Before: NaN log_evidence carried on silently; out-of-range modes raised RuntimeError.
    rbpf = RBPF(_switching(), 4, proposal=proposal)
    belief = rbpf.init(_prior(), (3,))
    bad = dataclasses.replace(belief, **change(belief))
    with pytest.raises(ValueError, match=rf"^belief: .*{match}"):
        rbpf.step(bad, torch.zeros(1, dtype=torch.float64))
    assert torch.isfinite(rbpf.step(belief, torch.zeros(1, dtype=torch.float64)).log_evidence).all()


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("Q", lambda K: 1e-4 * torch.eye(6, dtype=torch.float16), r"^Q: expected float32"),
        ("inconsistency_penalty", lambda K: "5", r"^inconsistency_penalty\b"),
        ("inconsistency_penalty", lambda K: math.nan, r"^inconsistency_penalty\b"),
        ("consistency_gap", lambda K: None, r"^consistency_gap\b"),
        ("consistency_tolerance", lambda K: math.inf, r"^consistency_tolerance\b"),
        (
            "R",
            lambda K: torch.tensor([[1.0, 2, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64),
            r"^R:",
        ),
        ("transition", lambda K: torch.full((K, K), 1.0, dtype=torch.float64), r"^transition:"),
    ],
)
def test_planar_contact_model_refuses_bad_fields(
    field: str, value: Callable[[int], object], match: str
) -> None:
    # Before: a string penalty or gap raised TypeError, a float16 Q was blamed on "F".
    from tests.filters.test_contact_model import _noise, _scene

    scene = _scene()
    table = torch.zeros(2, scene.num_slots, dtype=torch.long)
    fields: dict[str, object] = {"scene": scene, "modes": table, **_noise(2)}
    fields[field] = value(2)
    with pytest.raises(ValueError, match=match):
        PlanarContactModel(**fields)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: quat_exp(torch.ones(2)), r"^v must have shape \(\*B, 3\)"),
        (lambda: quat_log(torch.ones(3)), r"^q must have shape \(\*B, 4\)"),
        (lambda: wrap_angle(torch.tensor([1, 2])), r"^angle: expected a float32 or float64"),
        (lambda: SE2.retract(torch.zeros(3), torch.zeros(2)), r"^delta must have shape"),
        (lambda: SE3.retract(torch.zeros(7), torch.zeros(7)), r"^delta must have shape"),
        (lambda: SE3.local(torch.zeros(6), torch.zeros(6)), r"^x: .*n >= 7"),
        (lambda: SE2.tangent_dim("3"), r"^dim\b"),  # type: ignore[arg-type]
    ],
)
def test_manifold_functions_refuse_wrong_shapes_and_dtypes(
    call: Callable[[], object], match: str
) -> None:
    # Before: garbage results, NaN, RuntimeError or TypeError.
    with pytest.raises(ValueError, match=match):
        call()
