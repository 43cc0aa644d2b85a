"""Linear Kalman filter: batched torch vs a per-filter NumPy reference, missing data, masks,
gradients, stability, and input validation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tests.filters import reference as ref
from torchcontact.filters import Gaussian, kf_predict, kf_update
from torchcontact.filters import _linalg as la

F64 = torch.float64


def _spd(*shape: int, scale: float = 1.0, gen: torch.Generator | None = None) -> torch.Tensor:
    n = shape[-1]
    A = torch.randn(*shape, dtype=F64, generator=gen)
    return scale * (A @ A.mT / n + 0.1 * torch.eye(n, dtype=F64))


def _system(B: int, n: int, m: int, seed: int = 0) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    return {
        "mean": torch.randn(B, n, dtype=F64, generator=gen),
        "cov": _spd(B, n, n, gen=gen),
        "F": torch.eye(n, dtype=F64) + 0.3 * torch.randn(B, n, n, dtype=F64, generator=gen),
        "c": torch.randn(B, n, dtype=F64, generator=gen),
        "Q": _spd(B, n, n, scale=0.1, gen=gen),
        "H": torch.randn(m, n, dtype=F64, generator=gen),  # shared: broadcast over the batch
        "d": torch.randn(m, dtype=F64, generator=gen),
        "R": _spd(B, m, m, scale=0.5, gen=gen),
        "ys": torch.randn(6, B, m, dtype=F64, generator=gen),
    }


def _run_torch(s: dict[str, torch.Tensor]) -> list[tuple[Gaussian, torch.Tensor]]:
    g = Gaussian(s["mean"], s["cov"])
    out = []
    for y in s["ys"]:
        g = kf_predict(g, F=s["F"], c=s["c"], Q=s["Q"])
        g, ll = kf_update(g, y, H=s["H"], d=s["d"], R=s["R"])
        out.append((g, ll))
    return out


def test_batched_kf_matches_numpy_per_filter() -> None:
    B, n, m = 7, 4, 3
    s = _system(B, n, m)
    out = _run_torch(s)
    np_s = {k: v.numpy() for k, v in s.items()}
    for b in range(B):
        mean, cov = np_s["mean"][b], np_s["cov"][b]
        for t in range(len(np_s["ys"])):
            mean, cov = ref.kf_predict(mean, cov, np_s["F"][b], np_s["c"][b], np_s["Q"][b])
            mean, cov, ll = ref.kf_update(
                mean, cov, np_s["ys"][t, b], np_s["H"], np_s["d"], np_s["R"][b]
            )
            g, log_lik = out[t]
            np.testing.assert_allclose(g.mean[b].numpy(), mean, rtol=0, atol=1e-10)
            np.testing.assert_allclose(g.cov[b].numpy(), cov, rtol=0, atol=1e-10)
            assert abs(log_lik[b].item() - ll) < 1e-10


def test_large_measurement_matches_numpy() -> None:
    """m > 8 exercises the LAPACK path of the innovation factorization."""
    B, n, m = 3, 5, 10
    s = _system(B, n, m, seed=1)
    g = Gaussian(s["mean"], s["cov"])
    post, ll = kf_update(g, s["ys"][0], H=s["H"], d=s["d"], R=s["R"])
    for b in range(B):
        mean, cov, ll_ref = ref.kf_update(
            s["mean"][b].numpy(),
            s["cov"][b].numpy(),
            s["ys"][0, b].numpy(),
            s["H"].numpy(),
            s["d"].numpy(),
            s["R"][b].numpy(),
        )
        np.testing.assert_allclose(post.mean[b].numpy(), mean, atol=1e-10)
        np.testing.assert_allclose(post.cov[b].numpy(), cov, atol=1e-10)
        assert abs(ll[b].item() - ll_ref) < 1e-10


def test_singular_prior_and_large_state_match_numpy() -> None:
    """n > 8 (column-oriented factorization) with a rank-deficient prior covariance."""
    B, n, m = 3, 10, 2
    s = _system(B, n, m, seed=11)
    cov = s["cov"].clone()
    cov[:, 0, :] = 0.0  # state 0 known exactly
    cov[:, :, 0] = 0.0
    R = s["R"].clone().requires_grad_()
    post, ll = kf_update(Gaussian(s["mean"], cov), s["ys"][0], H=s["H"], d=s["d"], R=R)
    for b in range(B):
        mean, P, ll_ref = ref.kf_update(
            s["mean"][b].numpy(),
            cov[b].numpy(),
            s["ys"][0, b].numpy(),
            s["H"].numpy(),
            s["d"].numpy(),
            s["R"][b].numpy(),
        )
        np.testing.assert_allclose(post.mean[b].detach().numpy(), mean, atol=1e-10)
        np.testing.assert_allclose(post.cov[b].detach().numpy(), P, atol=1e-10)
        assert abs(ll[b].item() - ll_ref) < 1e-10
    assert post.cov[:, 0].abs().max().item() < 1e-12
    (grad,) = torch.autograd.grad(ll.sum() + post.cov.sum(), R)
    assert torch.isfinite(grad).all()


def test_batched_equals_looped_and_permutation_equivariant() -> None:
    B, n, m = 6, 3, 2
    s = _system(B, n, m, seed=2)
    batched = _run_torch(s)
    for b in range(B):
        single = {
            "mean": s["mean"][b],
            "cov": s["cov"][b],
            "F": s["F"][b],
            "c": s["c"][b],
            "Q": s["Q"][b],
            "H": s["H"],
            "d": s["d"],
            "R": s["R"][b],
            "ys": s["ys"][:, b],
        }
        for (g_b, ll_b), (g_1, ll_1) in zip(batched, _run_torch(single), strict=True):
            torch.testing.assert_close(g_b.mean[b], g_1.mean, rtol=0, atol=1e-12)
            torch.testing.assert_close(g_b.cov[b], g_1.cov, rtol=0, atol=1e-12)
            torch.testing.assert_close(ll_b[b], ll_1, rtol=0, atol=1e-12)
    perm = torch.randperm(B)
    permuted = {
        k: (v if k in ("H", "d") else v[:, perm] if k == "ys" else v[perm]) for k, v in s.items()
    }
    for (g, ll), (g_p, ll_p) in zip(batched, _run_torch(permuted), strict=True):
        torch.testing.assert_close(g.mean[perm], g_p.mean, rtol=0, atol=1e-12)
        torch.testing.assert_close(g.cov[perm], g_p.cov, rtol=0, atol=1e-12)
        torch.testing.assert_close(ll[perm], ll_p, rtol=0, atol=1e-12)


@pytest.mark.bitwise("an entry without a measurement is passed through untouched")
def test_nan_measurement_leaves_entry_unchanged() -> None:
    B, n, m = 5, 3, 2
    s = _system(B, n, m, seed=3)
    g = Gaussian(s["mean"], s["cov"])
    y = s["ys"][0].clone()
    y[1] = math.nan
    y[3] = math.nan
    post, ll = kf_update(g, y, H=s["H"], d=s["d"], R=s["R"])
    for b in (1, 3):
        assert torch.equal(post.mean[b], g.mean[b])
        assert torch.equal(post.cov[b], g.cov[b])
        assert ll[b].item() == 0.0
    keep = torch.tensor([0, 2, 4])
    ref_post, ref_ll = kf_update(g[keep], y[keep], H=s["H"], d=s["d"], R=s["R"][keep])
    torch.testing.assert_close(post.mean[keep], ref_post.mean, rtol=0, atol=1e-14)
    torch.testing.assert_close(post.cov[keep], ref_post.cov, rtol=0, atol=1e-14)
    torch.testing.assert_close(ll[keep], ref_ll, rtol=0, atol=1e-14)


@pytest.mark.bitwise("an entry without a measurement is passed through untouched")
def test_mask_equals_row_deletion() -> None:
    B, n, m = 16, 4, 3
    s = _system(B, n, m, seed=4)
    g = Gaussian(s["mean"], s["cov"])
    gen = torch.Generator().manual_seed(5)
    mask = torch.rand(B, m, generator=gen) < 0.6
    mask[0] = False  # nothing observed
    mask[1] = True  # everything observed
    y = s["ys"][0].clone()
    y[~mask] = math.nan  # masked components may hold NaN
    post, ll = kf_update(g, y, H=s["H"], d=s["d"], R=s["R"], mask=mask)
    for b in range(B):
        rows = mask[b].nonzero().squeeze(-1).numpy()
        if rows.size == 0:
            assert torch.equal(post.mean[b], g.mean[b])
            assert torch.equal(post.cov[b], g.cov[b])
            assert ll[b].item() == 0.0
            continue
        mean, cov, ll_ref = ref.kf_update(
            s["mean"][b].numpy(),
            s["cov"][b].numpy(),
            y[b].numpy()[rows],
            s["H"].numpy()[rows],
            s["d"].numpy()[rows],
            s["R"][b].numpy()[np.ix_(rows, rows)],
        )
        np.testing.assert_allclose(post.mean[b].numpy(), mean, rtol=0, atol=1e-12)
        np.testing.assert_allclose(post.cov[b].numpy(), cov, rtol=0, atol=1e-12)
        assert abs(ll[b].item() - ll_ref) < 1e-12


@pytest.mark.bitwise("both functions run the same operations on the same tensors in one process")
def test_update_log_likelihood_is_update_cores_to_the_bit() -> None:
    """The likelihood alone equals update_core's: from the full covariance (any H, with and
    without a mask that leaves an entry unobserved) and, for an H that reads the leading
    components, from their mean and covariance block; at sizes on both sides of the
    products' switch between a broadcast reduction and accumulation."""
    from torchcontact.filters import _linalg as la
    from torchcontact.filters._kalman import update_core, update_log_likelihood

    gen = torch.Generator().manual_seed(7)
    n, k, r = 6, 3, 3
    select = torch.zeros(k, n, dtype=F64)
    select[:, :r] = torch.eye(r, dtype=F64)
    for B in (40, 700):
        mean = torch.randn(n, B, dtype=F64, generator=gen)
        cov = la.to_batch_last(_spd(B, n, n, gen=gen), 2, 1)
        R = la.to_batch_last(_spd(B, k, k, scale=0.5, gen=gen), 2, 1)
        y = torch.randn(k, B, dtype=F64, generator=gen)
        d = torch.randn(k, 1, dtype=F64, generator=gen)
        observed = torch.rand(k, B, generator=gen) > 0.3
        observed[:, 0] = False
        for H in (select, torch.randn(k, n, dtype=F64, generator=gen)):
            for obs in (None, observed):
                *_, expected = update_core(mean, cov, y, H[..., None], d, R, obs)
                got = update_log_likelihood(mean, cov, y, H[..., None], d, R, obs)
                assert torch.equal(got, expected)
        for obs in (None, observed):
            *_, expected = update_core(mean, cov, y, select[..., None], None, R, obs)
            got = update_log_likelihood(mean[:r], cov[:r, :r], y, select[..., None], None, R, obs)
            assert torch.equal(got, expected)


@pytest.mark.bitwise(
    "a factor's upper triangle is exact zeros; a refactored batch runs the same function"
)
def test_psd_cholesky_per_batch_and_entrywise() -> None:
    """Both modes factor PD and singular PSD matrices exactly (L Lᵀ = A, lower triangular,
    finite); on a batch of PD matrices the entrywise factor is the plain one to rounding, and
    NumPy's Cholesky is the reference; a batch with one singular matrix is refactored whole."""
    gen = torch.Generator().manual_seed(3)
    pd = _spd(5, 6, 6, gen=gen)
    v = torch.randn(6, 2, dtype=F64, generator=gen)
    singular = (v @ v.T).unsqueeze(0)  # rank 2
    mixed = torch.cat([pd, singular])
    for a in (pd, mixed):
        a_bl = la.to_batch_last(a, 2, 1).contiguous()  # (6, 6, B), the kernels' layout
        for entrywise in (False, True):
            low = la.to_batch_first(la.psd_cholesky(a_bl, entrywise=entrywise), 2)
            assert torch.isfinite(low).all()
            assert torch.equal(low, low.tril())
            torch.testing.assert_close(low @ low.mT, a, rtol=0, atol=1e-12)
    mixed_bl = la.to_batch_last(mixed, 2, 1).contiguous()
    assert torch.equal(la.psd_cholesky(mixed_bl), la.semidefinite_cholesky(mixed_bl))
    reference = torch.from_numpy(np.linalg.cholesky(pd.numpy()))
    for entrywise in (False, True):
        low = la.psd_cholesky(la.to_batch_last(pd, 2, 1).contiguous(), entrywise=entrywise)
        torch.testing.assert_close(la.to_batch_first(low, 2), reference, rtol=0, atol=1e-13)


def test_partial_nan_without_mask_raises() -> None:
    s = _system(2, 3, 2)
    y = s["ys"][0].clone()
    y[0, 1] = math.nan
    with pytest.raises(ValueError, match=r"^y:"):
        kf_update(Gaussian(s["mean"], s["cov"]), y, H=s["H"], R=s["R"])


def test_float32_agrees_with_float64() -> None:
    s = _system(4, 4, 2, seed=6)
    out64 = _run_torch(s)
    out32 = _run_torch({k: v.float() for k, v in s.items()})
    for (g64, ll64), (g32, ll32) in zip(out64, out32, strict=True):
        assert g32.mean.dtype == torch.float32
        assert ll32.dtype == torch.float32
        torch.testing.assert_close(g32.mean.double(), g64.mean, rtol=1e-4, atol=1e-4)
        torch.testing.assert_close(g32.cov.double(), g64.cov, rtol=1e-4, atol=1e-4)
        torch.testing.assert_close(ll32.double(), ll64, rtol=1e-4, atol=1e-4)


def test_log_likelihood_gradcheck_wrt_noise() -> None:
    s = _system(3, 3, 2, seed=7)
    q_root = torch.linalg.cholesky(s["Q"]).requires_grad_()
    r_root = torch.linalg.cholesky(s["R"]).requires_grad_()

    def total_log_lik(q_root: torch.Tensor, r_root: torch.Tensor) -> torch.Tensor:
        Q, R = q_root @ q_root.mT, r_root @ r_root.mT
        g = Gaussian(s["mean"], s["cov"])
        total = torch.zeros((), dtype=F64)
        for y in s["ys"][:3]:
            g = kf_predict(g, F=s["F"], c=s["c"], Q=Q)
            g, ll = kf_update(g, y, H=s["H"], d=s["d"], R=R)
            total = total + ll.sum()
        return total

    assert torch.autograd.gradcheck(total_log_lik, (q_root, r_root))


def test_log_likelihood_gradient_matches_numpy_finite_differences() -> None:
    """d log p(y) / d sigma_r for R = sigma_r² I against central differences of the NumPy KF."""
    s = _system(1, 3, 2, seed=8)
    sigma = torch.tensor(0.7, dtype=F64, requires_grad=True)
    g = Gaussian(s["mean"][0], s["cov"][0])
    total = torch.zeros((), dtype=F64)
    for y in s["ys"][:, 0]:
        g = kf_predict(g, F=s["F"][0], Q=s["Q"][0])
        g, ll = kf_update(g, y, H=s["H"], R=sigma**2 * torch.eye(2, dtype=F64))
        total = total + ll
    (grad,) = torch.autograd.grad(total, sigma)

    def np_log_lik(sig: float) -> float:
        m, P, out = s["mean"][0].numpy(), s["cov"][0].numpy(), 0.0
        for y in s["ys"][:, 0].numpy():
            m, P = ref.kf_predict(m, P, s["F"][0].numpy(), np.zeros(3), s["Q"][0].numpy())
            m, P, ll = ref.kf_update(m, P, y, s["H"].numpy(), np.zeros(2), sig**2 * np.eye(2))
            out += ll
        return out

    h = 1e-6
    fd = (np_log_lik(0.7 + h) - np_log_lik(0.7 - h)) / (2 * h)
    assert abs(grad.item() - fd) < 1e-6 * max(1.0, abs(fd))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.bitwise("(P + Pᵀ) / 2 is symmetric bit for bit: IEEE addition commutes")
def test_stability_tiny_R_huge_P0(dtype: torch.dtype) -> None:
    """1,000 steps of a constant-acceleration model observed in position only, for three
    (R, P0, Q) regimes side by side; R/P0 spans up to 20 orders of magnitude, far beyond
    float32's 7 digits, where products of covariances cancel catastrophically."""
    dt = 0.1
    F = torch.tensor([[1, dt, 0.5 * dt**2], [0, 1, dt], [0, 0, 1]], dtype=dtype)
    r_var = torch.tensor([1e-6, 1e-8, 1e-10], dtype=F64)
    p0_var = torch.tensor([1e6, 1e8, 1e10], dtype=dtype)
    q_var = torch.tensor([1e-4, 0.0, 1e-6], dtype=dtype)
    eye = torch.eye(3, dtype=dtype)
    Q = q_var[:, None, None] * eye
    H = torch.tensor([[1.0, 0.0, 0.0]], dtype=dtype)
    R = r_var.to(dtype)[:, None, None]
    g = Gaussian(torch.zeros(3, 3, dtype=dtype), p0_var[:, None, None] * eye)
    gen = torch.Generator().manual_seed(0)
    x = torch.tensor([0.0, 1.0, 0.1], dtype=F64)
    covs, log_liks = [], []
    for _ in range(1000):
        x = F.double() @ x
        noise = r_var.sqrt() * torch.randn(3, dtype=F64, generator=gen)
        y = (x[0] + noise).to(dtype)[:, None]
        g = kf_predict(g, F=F, Q=Q)
        covs.append(g.cov)
        g, ll = kf_update(g, y, H=H, R=R)
        covs.append(g.cov)
        log_liks.append(ll)
    cov = torch.stack(covs)
    assert torch.isfinite(cov).all()
    assert torch.isfinite(torch.stack(log_liks)).all()
    assert torch.isfinite(g.mean).all()
    assert torch.equal(cov, cov.mT)
    eig = torch.linalg.eigvalsh(cov.double())
    worst = (eig.min(-1).values / eig.abs().max(-1).values).min().item()
    assert worst >= -100 * torch.finfo(dtype).eps
    # the position is pinned to the measurement accuracy
    error = (g.mean[:, 0].double() - x[0]).abs()
    assert (error < 100 * r_var.sqrt() + 1e-3 * x[0].abs() * torch.finfo(dtype).eps ** 0.5).all()


@pytest.mark.bitwise("indexing copies the entries")
def test_gaussian_indexing_and_to() -> None:
    s = _system(6, 3, 2)
    g = Gaussian(s["mean"].reshape(2, 3, 3), s["cov"].reshape(2, 3, 3, 3))
    for index in (1, (slice(None), 2), (..., 0), torch.tensor([1, 0]), g.mean[..., 0] > 0):
        sub = g[index]
        batch_index = index if isinstance(index, tuple) else (index,)
        expected_mean = g.mean[(*batch_index, slice(None))]
        expected_cov = g.cov[(*batch_index, slice(None), slice(None))]
        torch.testing.assert_close(sub.mean, expected_mean, rtol=0, atol=0)
        torch.testing.assert_close(sub.cov, expected_cov, rtol=0, atol=0)
    assert g.batch_shape == (2, 3)
    assert g.dim == 3
    g32 = g.to(torch.float32)
    assert g32.dtype == torch.float32
    assert g32.mean.shape == g.mean.shape


def _good() -> dict[str, object]:
    s = _system(2, 3, 2)
    return {
        "g": Gaussian(s["mean"], s["cov"]),
        "F": s["F"],
        "Q": s["Q"],
        "H": s["H"],
        "R": s["R"],
        "y": s["ys"][0],
    }


@pytest.mark.parametrize(
    ("call", "argument"),
    [
        (lambda v: Gaussian([0.0], torch.eye(1)), "mean"),
        (lambda v: Gaussian(torch.zeros(3), torch.eye(2, 3)), "cov"),
        (lambda v: Gaussian(torch.zeros(2, 3), torch.eye(3).expand(3, 3, 3)), "cov"),
        (lambda v: Gaussian(torch.tensor([0.0, math.nan]), torch.eye(2)), "mean"),
        (lambda v: Gaussian(torch.zeros(2), torch.eye(2, dtype=F64)), "cov"),
        (lambda v: Gaussian(torch.zeros(2, dtype=torch.long), torch.eye(2)), "mean"),
        (lambda v: kf_predict("g", F=v["F"], Q=v["Q"]), "g"),
        (lambda v: kf_predict(v["g"], F=v["F"][..., :2], Q=v["Q"]), "F"),
        (lambda v: kf_predict(v["g"], F=v["F"], Q=v["Q"].float()), "Q"),
        (lambda v: kf_predict(v["g"], F=v["F"], Q=v["Q"] * math.inf), "Q"),
        (lambda v: kf_predict(v["g"], F=v["F"], c=torch.zeros(2, dtype=F64), Q=v["Q"]), "c"),
        (lambda v: kf_predict(v["g"], F=torch.eye(3, dtype=F64).expand(5, 3, 3), Q=v["Q"]), "F"),
        (lambda v: kf_update(v["g"], v["y"], H=v["H"][:, :2], R=v["R"]), "H"),
        (lambda v: kf_update(v["g"], v["y"], H=v["H"], R=v["R"][..., :1]), "R"),
        (lambda v: kf_update(v["g"], v["y"] * math.inf, H=v["H"], R=v["R"]), "y"),
        (lambda v: kf_update(v["g"], 1.0, H=v["H"], R=v["R"]), "y"),
        (lambda v: kf_update(v["g"], v["y"], H=v["H"], R=-v["R"]), "R"),
        (lambda v: kf_update(v["g"], v["y"], H=v["H"], R=v["R"], mask=torch.ones(2, 2)), "mask"),
        (
            lambda v: kf_update(
                v["g"], v["y"], H=v["H"], R=v["R"], mask=torch.ones(2, 3, dtype=torch.bool)
            ),
            "mask",
        ),
    ],
)
def test_bad_input_raises_value_error_naming_argument(call, argument: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError, match=f"^{argument}:"):
        call(_good())
