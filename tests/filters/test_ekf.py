"""Extended Kalman filter and state manifolds: linear EKF = KF, Jacobians vs finite
differences, SE(2)/SE(3) retract/local round trips, quaternion maps vs SciPy."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from torchcontact.filters import (
    SE2,
    SE3,
    Gaussian,
    ekf_predict,
    ekf_update,
    kf_predict,
    kf_update,
    quat_exp,
    quat_log,
)
from torchcontact.geometry import quat_mul

F64 = torch.float64


def _spd(n: int, gen: torch.Generator, batch: tuple[int, ...] = ()) -> torch.Tensor:
    A = torch.randn(*batch, n, n, dtype=F64, generator=gen)
    return A @ A.mT / n + 0.1 * torch.eye(n, dtype=F64)


def _random_pose(gen: torch.Generator, batch: int, extra: int = 0) -> torch.Tensor:
    q = torch.randn(batch, 4, dtype=F64, generator=gen)
    q = q / q.norm(dim=-1, keepdim=True)
    p = torch.randn(batch, 3, dtype=F64, generator=gen)
    v = torch.randn(batch, extra, dtype=F64, generator=gen)
    return torch.cat([p, q, v], -1)


def test_ekf_on_linear_model_equals_kf() -> None:
    gen = torch.Generator().manual_seed(0)
    B, n, m, p = 5, 4, 2, 3
    F = torch.randn(n, n, dtype=F64, generator=gen)
    G = torch.randn(n, p, dtype=F64, generator=gen)
    H = torch.randn(m, n, dtype=F64, generator=gen)
    d = torch.randn(m, dtype=F64, generator=gen)
    u = torch.randn(B, p, dtype=F64, generator=gen)
    g = Gaussian(torch.randn(B, n, dtype=F64, generator=gen), _spd(n, gen, (B,)))
    Q, R = _spd(n, gen) * 0.1, _spd(m, gen)
    y = torch.randn(B, m, dtype=F64, generator=gen)

    g_ekf = ekf_predict(g, lambda x, u: F @ x + G @ u, u=u, Q=Q)
    g_kf = kf_predict(g, F=F, c=u @ G.T, Q=Q)
    torch.testing.assert_close(g_ekf.mean, g_kf.mean, rtol=0, atol=1e-12)
    torch.testing.assert_close(g_ekf.cov, g_kf.cov, rtol=0, atol=1e-12)
    post_ekf, ll_ekf = ekf_update(g_kf, y, lambda x: H @ x + d, R=R)
    post_kf, ll_kf = kf_update(g_kf, y, H=H, d=d, R=R)
    torch.testing.assert_close(post_ekf.mean, post_kf.mean, rtol=0, atol=1e-12)
    torch.testing.assert_close(post_ekf.cov, post_kf.cov, rtol=0, atol=1e-12)
    torch.testing.assert_close(ll_ekf, ll_kf, rtol=0, atol=1e-12)


def _central_jacobian(fun, x: np.ndarray, h: float = 1e-6) -> np.ndarray:  # type: ignore[no-untyped-def]
    cols = []
    for i in range(len(x)):
        e = np.zeros_like(x)
        e[i] = h
        cols.append((fun(x + e) - fun(x - e)) / (2 * h))
    return np.stack(cols, axis=-1)


def test_ekf_jacobians_match_finite_differences() -> None:
    gen = torch.Generator().manual_seed(1)
    dt = 0.1

    def f(x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:  # damped pendulum + cart
        return torch.stack(
            [
                x[0] + dt * x[1],
                x[1] - dt * (9.81 * torch.sin(x[0]) + 0.3 * x[1] - u[0]),
                x[2] * x[0],
            ]
        )

    def h(x: torch.Tensor) -> torch.Tensor:  # range and bearing of (x0, x2)
        return torch.stack([torch.sqrt(x[0] ** 2 + x[2] ** 2), torch.atan2(x[2], x[0])])

    B = 4
    g = Gaussian(torch.randn(B, 3, dtype=F64, generator=gen) + 2.0, _spd(3, gen, (B,)))
    u = torch.randn(B, 1, dtype=F64, generator=gen)
    Q, R = 0.01 * _spd(3, gen), 0.1 * _spd(2, gen)
    y = torch.randn(B, 2, dtype=F64, generator=gen)
    pred = ekf_predict(g, f, u=u, Q=Q)
    post, ll = ekf_update(pred, y, h, R=R)
    for b in range(B):
        x, P = g.mean[b].numpy(), g.cov[b].numpy()
        J = _central_jacobian(lambda z, b=b: f(torch.from_numpy(z), u[b]).numpy(), x)
        np.testing.assert_allclose(pred.mean[b].numpy(), f(g.mean[b], u[b]).numpy(), atol=1e-14)
        np.testing.assert_allclose(pred.cov[b].numpy(), J @ P @ J.T + Q.numpy(), atol=1e-8)
        xp = pred.mean[b].numpy()
        Hj = _central_jacobian(lambda z: h(torch.from_numpy(z)).numpy(), xp)
        lin = Gaussian(pred.mean[b], pred.cov[b])
        d = h(pred.mean[b]) - torch.from_numpy(Hj) @ pred.mean[b]
        ref_post, ref_ll = kf_update(lin, y[b], H=torch.from_numpy(Hj), d=d, R=R)
        torch.testing.assert_close(post.mean[b], ref_post.mean, rtol=0, atol=1e-8)
        torch.testing.assert_close(post.cov[b], ref_post.cov, rtol=0, atol=1e-8)
        torch.testing.assert_close(ll[b], ref_ll, rtol=0, atol=1e-8)


def test_ekf_gradient_flows_to_model_parameters() -> None:
    """d log p(y) / d dt through jacfwd + vmap, against central differences."""
    gen = torch.Generator().manual_seed(2)
    g = Gaussian(torch.tensor([0.3, -0.2], dtype=F64), _spd(2, gen))
    y = torch.tensor([[0.35], [0.2], [0.1]], dtype=F64)
    Q, R = 0.01 * torch.eye(2, dtype=F64), torch.tensor([[0.05]], dtype=F64)

    def log_evidence(dt: torch.Tensor) -> torch.Tensor:
        def f(x: torch.Tensor) -> torch.Tensor:
            return torch.stack([x[0] + dt * x[1], x[1] - dt * torch.sin(x[0])])

        belief, total = g, torch.zeros((), dtype=F64)
        for yt in y:
            belief = ekf_predict(belief, f, Q=Q)
            belief, ll = ekf_update(belief, yt, lambda x: x[:1] ** 3 + x[:1], R=R)
            total = total + ll
        return total

    dt = torch.tensor(0.2, dtype=F64, requires_grad=True)
    (grad,) = torch.autograd.grad(log_evidence(dt), dt)
    h = 1e-6
    with torch.no_grad():
        fd = (log_evidence(dt + h) - log_evidence(dt - h)) / (2 * h)
    assert abs(grad.item() - fd.item()) < 1e-6 * max(1.0, abs(fd.item()))


def test_quaternion_maps_match_scipy() -> None:
    gen = torch.Generator().manual_seed(3)
    v = torch.randn(64, 3, dtype=F64, generator=gen)
    v = v / v.norm(dim=-1, keepdim=True) * torch.rand(64, 1, dtype=F64, generator=gen) * 3.0
    v[:4] *= 1e-9  # Taylor branches
    q = quat_exp(v)
    ref = Rotation.from_rotvec(v.numpy()).as_quat()  # (x, y, z, w)
    ref_wxyz = np.concatenate([ref[:, 3:], ref[:, :3]], axis=1)
    sign = np.sign((ref_wxyz * q.numpy()).sum(-1, keepdims=True))
    np.testing.assert_allclose(q.numpy(), sign * ref_wxyz, atol=1e-14)
    np.testing.assert_allclose(quat_log(q).numpy(), v.numpy(), atol=1e-12)
    a, b = Rotation.random(8, random_state=0), Rotation.random(8, random_state=1)
    qa = torch.from_numpy(np.roll(a.as_quat(), 1, axis=1))
    qb = torch.from_numpy(np.roll(b.as_quat(), 1, axis=1))
    ab = np.roll((a * b).as_quat(), 1, axis=1)
    prod = quat_mul(qa, qb).numpy()
    np.testing.assert_allclose(prod * np.sign((prod * ab).sum(-1, keepdims=True)), ab, atol=1e-14)


@pytest.mark.parametrize("scale", [1e-9, 1e-3, 1.0, 3.0])
def test_se3_retract_local_round_trip(scale: float) -> None:
    gen = torch.Generator().manual_seed(4)
    x = _random_pose(gen, 32, extra=2)
    delta = torch.randn(32, 8, dtype=F64, generator=gen)
    rot = delta[:, 3:6]
    delta[:, 3:6] = rot / rot.norm(dim=-1, keepdim=True) * scale * torch.rand(32, 1, dtype=F64)
    delta[:, :3] *= scale
    y = SE3.retract(x, delta)
    assert torch.allclose(y[:, 3:7].norm(dim=-1), torch.ones(32, dtype=F64), atol=1e-15)
    torch.testing.assert_close(SE3.local(x, y), delta, rtol=0, atol=1e-11)
    # and the other way round, on arbitrary pose pairs (q and -q are the same orientation)
    z = _random_pose(gen, 32, extra=2)
    z[:16, 3:7] *= -1
    back = SE3.retract(x, SE3.local(x, z))
    same = torch.where((back[:, 3:7] * z[:, 3:7]).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    torch.testing.assert_close(back[:, 3:7] * same, z[:, 3:7], rtol=0, atol=1e-11)
    torch.testing.assert_close(back[:, :3], z[:, :3], rtol=0, atol=1e-12)
    torch.testing.assert_close(back[:, 7:], z[:, 7:], rtol=0, atol=1e-12)
    assert SE3.tangent_dim(9) == 8


def test_se2_wraps_heading() -> None:
    x = torch.tensor([[0.0, 0.0, 3.0, 1.0]], dtype=F64)
    y = SE2.retract(x, torch.tensor([[1.0, 2.0, 0.5, -1.0]], dtype=F64))
    torch.testing.assert_close(y, torch.tensor([[1.0, 2.0, 3.5 - 2 * math.pi, 0.0]], dtype=F64))
    torch.testing.assert_close(SE2.local(x, y), torch.tensor([[1.0, 2.0, 0.5, -1.0]], dtype=F64))


def _compose(x: torch.Tensor, twist: torch.Tensor, dt: float) -> torch.Tensor:
    """Constant body-frame twist over dt: p ← p + R(q) v dt, q ← q ⊗ Exp(ω dt)."""
    q = x[3:7]
    v = torch.cat([torch.zeros(1, dtype=x.dtype), twist[:3] * dt])
    moved = quat_mul(quat_mul(q, v), torch.cat([q[:1], -q[1:]]))[1:]
    return torch.cat([x[:3] + moved, quat_mul(q, quat_exp(twist[3:] * dt))])


def test_se3_ekf_tangent_jacobian_matches_finite_differences() -> None:
    gen = torch.Generator().manual_seed(5)
    x = _random_pose(gen, 3)
    twist = torch.randn(3, 6, dtype=F64, generator=gen)
    P = _spd(6, gen, (3,)) * 0.01
    Q = 1e-4 * torch.eye(6, dtype=F64)
    pred = ekf_predict(Gaussian(x, P), lambda x, u: _compose(x, u, 0.1), u=twist, Q=Q, manifold=SE3)
    for b in range(3):

        def moved(delta: np.ndarray, b: int = b) -> np.ndarray:
            xb = SE3.retract(x[b], torch.from_numpy(delta))
            base = _compose(x[b], twist[b], 0.1)
            return SE3.local(base, _compose(xb, twist[b], 0.1)).numpy()

        J = _central_jacobian(moved, np.zeros(6))
        expected = J @ P[b].numpy() @ J.T + Q.numpy()
        np.testing.assert_allclose(pred.cov[b].numpy(), expected, atol=1e-9)
        torch.testing.assert_close(pred.mean[b], _compose(x[b], twist[b], 0.1))


def test_se3_ekf_pose_measurement_pulls_to_the_measurement() -> None:
    gen = torch.Generator().manual_seed(6)
    x = _random_pose(gen, 4)
    truth = SE3.retract(x, 0.3 * torch.randn(4, 6, dtype=F64, generator=gen))
    prior = Gaussian(x, 0.09 * torch.eye(6, dtype=F64).expand(4, 6, 6))
    R = 1e-8 * torch.eye(6, dtype=F64)
    y = truth.clone()
    y[:2, 3:7] *= -1  # the same orientation, the other sign
    post, ll = ekf_update(prior, y, lambda x: x, R=R, manifold=SE3, measurement_manifold=SE3)
    # one (linearized) update with a near-exact measurement lands near it; a second is exact
    post, _ = ekf_update(post, y, lambda x: x, R=R, manifold=SE3, measurement_manifold=SE3)
    assert SE3.local(post.mean, truth).abs().max().item() < 1e-6
    assert post.cov.diagonal(dim1=-2, dim2=-1).max().item() < 2e-8
    assert torch.isfinite(ll).all()


@pytest.mark.bitwise("an entry without a measurement is passed through untouched")
def test_ekf_missing_measurement_leaves_pose_unchanged() -> None:
    gen = torch.Generator().manual_seed(7)
    x = _random_pose(gen, 2)
    prior = Gaussian(x, 0.01 * torch.eye(6, dtype=F64).expand(2, 6, 6))
    y = x.clone()
    y[0] = math.nan
    post, ll = ekf_update(
        prior,
        y,
        lambda x: x,
        R=1e-4 * torch.eye(6, dtype=F64),
        manifold=SE3,
        measurement_manifold=SE3,
    )
    assert torch.equal(post.mean[0], x[0])
    assert torch.equal(post.cov[0], prior.cov[0])
    assert ll[0].item() == 0.0
    assert ll[1].item() != 0.0


@pytest.mark.parametrize(
    ("call", "argument"),
    [
        (lambda g: ekf_predict(g, lambda x: x, Q=torch.eye(3, dtype=F64)), "Q"),
        (lambda g: ekf_predict(g, lambda x: x[:1], Q=torch.eye(2, dtype=F64)), "f"),
        (
            lambda g: ekf_predict(g, lambda x: x, Q=torch.eye(2, dtype=F64), manifold="SE3"),
            "manifold",
        ),
        (lambda g: ekf_predict(g, lambda x: x, Q=torch.eye(6, dtype=F64), manifold=SE3), "dim"),
        (
            lambda g: ekf_update(
                g, torch.zeros(2, dtype=F64), lambda x: x[:1], R=torch.eye(2, dtype=F64)
            ),
            "y",
        ),
        (
            lambda g: ekf_update(
                g, torch.zeros(1, dtype=F64), lambda x: x[:1], R=torch.eye(2, dtype=F64)
            ),
            "R",
        ),
        (
            lambda g: ekf_update(
                Gaussian(torch.zeros(7, dtype=F64), torch.eye(7, dtype=F64)),
                torch.zeros(1, dtype=F64),
                lambda x: x[:1],
                R=torch.eye(1, dtype=F64),
                manifold=SE3,
            ),
            "g",
        ),
    ],
)
def test_bad_input_raises_value_error_naming_argument(call, argument: str) -> None:  # type: ignore[no-untyped-def]
    g = Gaussian(torch.zeros(2, dtype=F64), torch.eye(2, dtype=F64))
    with pytest.raises(ValueError, match=f"^{argument}:"):
        call(g)
