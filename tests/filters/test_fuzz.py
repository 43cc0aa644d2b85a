"""Property (fuzz) tests of the filters' entry points against bad input.

Every call either returns a correct answer (finite; covariances symmetric PSD to a tolerance;
where cheap, equal to a NumPy reference of the Kalman equations) or raises ``ValueError``
whose message starts with the name of an argument of the call. Any other exception, or a
NaN/inf/non-PSD result, fails. Inputs are built from a drawn "kind" (valid, NaN, inf,
asymmetric, indefinite, huge, wrong shape, wrong dtype, ...) and a drawn seed; an input of an
invalid kind must raise. Examples are derandomized, so failures reproduce.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import Tensor

from torchcontact.filters import (
    RBPF,
    Gaussian,
    LinearSwitchingModel,
    effective_sample_size,
    ekf_predict,
    ekf_update,
    kf_predict,
    kf_update,
    optimal_resample,
    resample,
    rts_smooth,
)

FUZZ = settings(max_examples=300, deadline=None, derandomize=True, database=None)

FLOATS = (torch.float32, torch.float64)
BAD_DTYPES = (torch.float16, torch.int64, torch.complex64)
#: Matrix kinds that are valid covariances, and kinds that must be refused.
VALID_COV = ("psd", "zero", "singular", "tiny", "large")
INVALID_COV = ("nan", "inf", "asym", "indefinite", "negative", "shape", "dtype", "mixed")
#: Kinds of a general (non-covariance) matrix or vector.
VALID_ANY = ("normal", "zero", "large")
INVALID_ANY = ("nan", "inf", "shape", "dtype", "mixed")
BATCHES: tuple[tuple[int, ...], ...] = ((), (0,), (3,), (2, 1))


def expect(call: Callable[[], Any], names: Sequence[str], *, must_raise: bool | None) -> Any | None:
    """Run ``call``: return its result, or None after a ``ValueError`` naming one of
    ``names`` first; fail on any other exception, or on no exception where one is due
    (``must_raise=None``: either outcome)."""
    try:
        result = call()
    except ValueError as err:
        pattern = rf"^({'|'.join(re.escape(n) for n in names)})(\[\d+\])?[: ]"
        if not re.match(pattern, str(err)):
            pytest.fail(f"message does not name {names}: {err}")
        return None
    assert must_raise is not True, "invalid input accepted"
    return result


def assert_finite(*values: Tensor) -> None:
    for value in values:
        assert bool(torch.isfinite(value).all()), "non-finite output"


def assert_covariance(cov: Tensor, slack: float = 64.0) -> None:
    """Finite, symmetric and PSD to ``slack · n · eps · max|P|`` (NumPy, float64)."""
    assert_finite(cov)
    if cov.numel() == 0:
        return
    a = cov.detach().double().numpy()
    n = a.shape[-1]
    tol = slack * n * torch.finfo(cov.dtype).eps * np.abs(a).max(axis=(-2, -1))
    np.testing.assert_array_less(
        np.abs(a - np.swapaxes(a, -1, -2)).max(axis=(-2, -1)), tol + 1e-300
    )
    sym = 0.5 * (a + np.swapaxes(a, -1, -2))
    assert (np.linalg.eigvalsh(sym).min(-1) >= -tol).all(), "covariance not PSD"


def matrix(
    kind: str, seed: int, shape: tuple[int, ...], dtype: torch.dtype, *, covariance: bool
) -> Tensor:
    """A ``(*B, r, c)`` matrix of a kind (a covariance ``A Aᵀ / c + 0.1 I`` if ``covariance``,
    ``r == c``; else standard normal entries); callers take ``[..., 0]`` for a vector."""
    rng = np.random.default_rng(seed)
    *batch, r, c = shape
    a = rng.normal(size=(*batch, r, c))
    if covariance:
        a = a @ np.swapaxes(a, -1, -2) / c + 0.1 * np.eye(r)
        if kind == "singular":
            v = rng.normal(size=(*batch, r, 1))
            a = v @ np.swapaxes(v, -1, -2)
        elif kind == "asym":
            a = a + np.triu(np.full((r, r), 3.0), 1)
        elif kind == "indefinite":
            a = a.copy()
            a[..., 0, 0] = -1.0 - np.abs(a).max(initial=0.0)
        elif kind == "negative":
            a = -a
    if kind == "zero":
        a = np.zeros_like(a)
    elif kind == "tiny":
        a = a * 1e-30
    elif kind == "large":
        a = a * 1e18
    out = torch.from_numpy(a).to(dtype)
    if kind in ("nan", "inf") and out.numel():
        out.view(-1)[int(rng.integers(out.numel()))] = torch.nan if kind == "nan" else torch.inf
    if kind == "shape":
        out = torch.zeros(*batch, r + 1, c + 1, dtype=dtype)
    elif kind == "dtype":
        out = out.to(BAD_DTYPES[seed % len(BAD_DTYPES)])
    elif kind == "mixed":
        out = out.to(torch.float64 if dtype == torch.float32 else torch.float32)
    return out


def is_invalid(kind: str, *, covariance: bool, numel: int = 1, n: int = 2) -> bool:
    """Whether a kind must be refused: a wrong shape or dtype always; a wrong value only in a
    non-empty tensor (``numel`` entries), asymmetry only for ``n > 1``."""
    if kind in ("shape", "dtype", "mixed"):
        return True
    if numel == 0 or (kind == "asym" and n == 1):
        return False
    return kind in (INVALID_COV if covariance else INVALID_ANY)


def prior(seed: int, n: int, batch: tuple[int, ...], dtype: torch.dtype) -> Gaussian:
    mean = matrix("normal", seed, (*batch, n, 1), dtype, covariance=False)[..., 0]
    return Gaussian(mean, matrix("psd", seed + 1, (*batch, n, n), dtype, covariance=True))


cov_kinds = st.sampled_from(VALID_COV * 2 + INVALID_COV)
any_kinds = st.sampled_from(VALID_ANY * 3 + INVALID_ANY)
seeds = st.integers(0, 2**16)
dims = st.integers(1, 3)
batches = st.sampled_from(BATCHES)
floats = st.sampled_from(FLOATS)


# ---------------------------------------------------------------------------------------------
# Gaussian


@FUZZ
@given(mean_kind=any_kinds, cov_kind=cov_kinds, seed=seeds, n=dims, batch=batches, dtype=floats)
def test_gaussian(
    mean_kind: str, cov_kind: str, seed: int, n: int, batch: tuple[int, ...], dtype: torch.dtype
) -> None:
    mean = matrix(mean_kind, seed, (*batch, n, 1), dtype, covariance=False)[..., 0]
    cov = matrix(cov_kind, seed + 1, (*batch, n, n), dtype, covariance=True)
    numel = int(np.prod(batch)) if batch else 1
    # a longer mean than cov is a manifold state (d <= n): the "shape" kind stays valid
    mean_bad = mean_kind != "shape" and is_invalid(mean_kind, covariance=False, numel=numel)
    cov_bad = is_invalid(cov_kind, covariance=True, numel=numel, n=n)
    if cov_kind == mean_kind and cov_kind in ("shape", "mixed"):
        mean_bad = cov_bad = False  # both one larger, or both the other dtype: consistent
    bad = mean_bad or cov_bad
    g = expect(lambda: Gaussian(mean, cov), ["mean", "cov"], must_raise=bad)
    if g is not None:
        assert g.batch_shape == batch
        assert_finite(g.mean)
        assert_covariance(g.cov)


# ---------------------------------------------------------------------------------------------
# Kalman predict / update, against NumPy


def numpy_predict(g: Gaussian, F: Tensor, c: Tensor | None, Q: Tensor) -> tuple[Any, Any]:
    m, P, F64, Q64 = (t.double().numpy() for t in (g.mean, g.cov, F, Q))
    mean = np.einsum("...ij,...j->...i", F64, m) + (0.0 if c is None else c.double().numpy())
    return mean, F64 @ P @ np.swapaxes(F64, -1, -2) + Q64


def close(actual: Tensor, expected: Any) -> None:
    a = actual.detach().double().numpy()
    scale = max(float(np.abs(expected).max(initial=0.0)), 1e-300)
    rtol = 1e-3 if actual.dtype == torch.float32 else 1e-9
    np.testing.assert_allclose(a, np.broadcast_to(expected, a.shape), atol=rtol * scale, rtol=0)


@FUZZ
@given(
    F_kind=any_kinds,
    c_kind=st.sampled_from(("none", *VALID_ANY, *INVALID_ANY)),
    Q_kind=cov_kinds,
    seed=seeds,
    n=dims,
    batch=batches,
    model_batch=st.sampled_from(((), (1,), (3,), (4,))),
    dtype=floats,
)
def test_kf_predict(
    F_kind: str,
    c_kind: str,
    Q_kind: str,
    seed: int,
    n: int,
    batch: tuple[int, ...],
    model_batch: tuple[int, ...],
    dtype: torch.dtype,
) -> None:
    g = prior(seed, n, batch, dtype)
    F = matrix(F_kind, seed + 2, (*model_batch, n, n), dtype, covariance=False)
    Q = matrix(Q_kind, seed + 3, (*model_batch, n, n), dtype, covariance=True)
    c = None if c_kind == "none" else matrix(c_kind, seed + 4, (n, 1), dtype, covariance=False)
    c = None if c is None else c[..., 0]
    size = n * int(np.prod(model_batch))
    try:
        torch.broadcast_shapes(batch, model_batch)
        broadcasts = True
    except RuntimeError:
        broadcasts = False
    bad = (
        not broadcasts
        or is_invalid(F_kind, covariance=False, numel=size)
        or is_invalid(Q_kind, covariance=True, numel=size, n=n)
        or (c_kind != "none" and is_invalid(c_kind, covariance=False))
    )
    out = expect(lambda: kf_predict(g, F=F, c=c, Q=Q), ["g", "F", "c", "Q"], must_raise=bad)
    if out is None:
        return
    assert out.batch_shape == torch.broadcast_shapes(batch, model_batch)
    assert_finite(out.mean)
    assert_covariance(out.cov)
    mean_ref, cov_ref = numpy_predict(g, F, c, Q)
    close(out.mean, mean_ref)
    close(out.cov, cov_ref)


def numpy_update(g: Gaussian, y: Tensor, H: Tensor, R: Tensor) -> tuple[Any, Any, Any]:
    """The textbook Kalman update in float64 (inverse of S; Joseph form)."""
    m, P, y64, H64, R64 = (t.double().numpy() for t in (g.mean, g.cov, y, H, R))
    Ht = np.swapaxes(H64, -1, -2)
    S = H64 @ P @ Ht + R64
    K = P @ Ht @ np.linalg.inv(S)
    r = y64 - np.einsum("...ij,...j->...i", H64, m)
    A = np.eye(m.shape[-1]) - K @ H64
    cov = A @ P @ np.swapaxes(A, -1, -2) + K @ R64 @ np.swapaxes(K, -1, -2)
    quad = np.einsum("...i,...i->...", r, np.linalg.solve(S, r[..., None])[..., 0])
    log_lik = -0.5 * (quad + np.linalg.slogdet(S)[1] + r.shape[-1] * np.log(2 * np.pi))
    return m + np.einsum("...ij,...j->...i", K, r), cov, log_lik


@FUZZ
@given(
    y_kind=st.sampled_from(("normal", "normal", "missing", "partial_nan", *INVALID_ANY)),
    H_kind=any_kinds,
    R_kind=cov_kinds,
    seed=seeds,
    n=dims,
    k=st.integers(1, 2),
    batch=batches,
    y_batch=st.sampled_from(((), (3,), (2, 3), (4,))),
    dtype=floats,
)
def test_kf_update(
    y_kind: str,
    H_kind: str,
    R_kind: str,
    seed: int,
    n: int,
    k: int,
    batch: tuple[int, ...],
    y_batch: tuple[int, ...],
    dtype: torch.dtype,
) -> None:
    g = prior(seed, n, batch, dtype)
    base = "normal" if y_kind in ("missing", "partial_nan") else y_kind
    y = matrix(base, seed + 5, (*y_batch, k, 1), dtype, covariance=False)[..., 0]
    if y_kind == "missing":
        y = torch.full_like(y, torch.nan)
    elif y_kind == "partial_nan" and k > 1 and y.numel():
        y[..., 0] = torch.nan
    H = matrix(H_kind, seed + 6, (k, n), dtype, covariance=False)
    R = matrix(R_kind, seed + 7, (k, k), dtype, covariance=True)
    try:
        out_batch = torch.broadcast_shapes(batch, y_batch)
    except RuntimeError:
        out_batch = None
    y_bad = y_kind in ("partial_nan",) and k > 1 and y.numel() > 0
    bad = (
        out_batch is None
        or y_bad
        or (y_kind != "nan" and is_invalid(y_kind, covariance=False, numel=y.numel()))
        or (y_kind == "nan" and y.numel() > 0 and k > 1)  # one NaN component: partial
        or is_invalid(H_kind, covariance=False)
        or is_invalid(R_kind, covariance=True, n=k)
    )
    out = expect(lambda: kf_update(g, y, H=H, R=R), ["g", "y", "H", "R"], must_raise=bad)
    if out is None:
        return
    post, log_lik = out
    assert post.batch_shape == out_batch
    assert log_lik.shape == out_batch
    assert_finite(post.mean, log_lik)
    assert_covariance(post.cov)
    if y_kind == "missing":
        close(post.mean, np.broadcast_to(g.mean.double().numpy(), (*out_batch, n)))
        assert bool((log_lik == 0).all())
        return
    if (
        y_kind == "normal"
        and R_kind in ("psd", "large")
        and H_kind == "normal"
        and dtype == torch.float64
    ):
        mean_ref, cov_ref, ll_ref = numpy_update(g, y, H, R)
        close(post.mean, mean_ref)
        close(post.cov, cov_ref)
        close(log_lik, ll_ref)


# ---------------------------------------------------------------------------------------------
# EKF


def _dynamics(kind: str) -> Callable[[Tensor], Tensor]:
    if kind == "nan":
        return lambda x: x * torch.nan
    if kind == "inf":
        return lambda x: x + torch.inf
    if kind == "shape":
        return lambda x: torch.cat([x, x])
    if kind == "overflow":
        return lambda x: 1e30 * x  # Jacobian 1e30: F P Fᵀ overflows float32
    return lambda x: torch.sin(x) + 0.5 * x


@FUZZ
@given(
    f_kind=st.sampled_from(("smooth", "smooth", "smooth", "nan", "inf", "shape", "overflow")),
    Q_kind=cov_kinds,
    seed=seeds,
    n=dims,
    batch=batches,
    dtype=floats,
)
def test_ekf_predict(
    f_kind: str, Q_kind: str, seed: int, n: int, batch: tuple[int, ...], dtype: torch.dtype
) -> None:
    g = prior(seed, n, batch, dtype)
    Q = matrix(Q_kind, seed + 3, (n, n), dtype, covariance=True)
    nonempty = int(np.prod(batch)) > 0 if batch else True
    bad = (
        is_invalid(Q_kind, covariance=True, n=n)
        or f_kind == "shape"
        or (f_kind in ("nan", "inf") and nonempty)
        or (f_kind == "overflow" and dtype == torch.float32 and nonempty)
    )
    f = _dynamics(f_kind)
    out = expect(lambda: ekf_predict(g, f, Q=Q), ["f", "g", "Q"], must_raise=bad)
    if out is not None:
        assert_finite(out.mean)
        assert_covariance(out.cov)


@FUZZ
@given(
    h_kind=st.sampled_from(("smooth", "smooth", "smooth", "nan", "inf", "shape")),
    y_kind=st.sampled_from(("normal", "normal", "missing", *INVALID_ANY)),
    R_kind=cov_kinds,
    seed=seeds,
    n=dims,
    batch=batches,
    dtype=floats,
)
def test_ekf_update(
    h_kind: str,
    y_kind: str,
    R_kind: str,
    seed: int,
    n: int,
    batch: tuple[int, ...],
    dtype: torch.dtype,
) -> None:
    g = prior(seed, n, batch, dtype)
    base = "normal" if y_kind == "missing" else y_kind
    y = matrix(base, seed + 5, (n, 1), dtype, covariance=False)[..., 0]
    if y_kind == "missing":
        y = torch.full_like(y, torch.nan)
    R = matrix(R_kind, seed + 7, (n, n), dtype, covariance=True)
    nonempty = int(np.prod(batch)) > 0 if batch else True
    bad: bool | None = (
        is_invalid(R_kind, covariance=True, n=n)
        or (y_kind == "nan" and n > 1 and nonempty)
        or (y_kind not in ("nan", "missing") and is_invalid(y_kind, covariance=False))
        or h_kind == "shape"
        or (h_kind in ("nan", "inf") and nonempty)
    )
    if not bad and y_kind == "nan" and n > 1:
        bad = None  # a partial NaN in a y broadcast to an empty batch: either outcome
    h = _dynamics(h_kind)
    out = expect(lambda: ekf_update(g, y, h, R=R), ["h", "g", "y", "R"], must_raise=bad)
    if out is not None:
        post, log_lik = out
        assert_finite(post.mean, log_lik)
        assert_covariance(post.cov)


# ---------------------------------------------------------------------------------------------
# Switching model and RBPF


def switching_fields(seed: int, dtype: torch.dtype, K: int = 2, n: int = 2) -> dict[str, Tensor]:
    rng = np.random.default_rng(seed)
    trans = rng.random((K, K)) + 0.1
    return {
        "F": torch.from_numpy(0.9 * np.eye(n) + 0.05 * rng.normal(size=(K, n, n))).to(dtype),
        "c": torch.from_numpy(0.1 * rng.normal(size=(K, n))).to(dtype),
        "Q": matrix("psd", seed, (K, n, n), dtype, covariance=True),
        "H": torch.from_numpy(rng.normal(size=(K, 1, n))).to(dtype),
        "d": torch.zeros(K, 1, dtype=dtype),
        "R": matrix("psd", seed + 1, (K, 1, 1), dtype, covariance=True),
        "transition": torch.from_numpy(trans / trans.sum(-1, keepdims=True)).to(dtype),
        "initial": torch.full((K,), 1.0 / K, dtype=dtype),
    }


@FUZZ
@given(
    field=st.sampled_from(("F", "c", "Q", "H", "d", "R", "transition", "initial")),
    kind=st.sampled_from(
        (
            *("valid", "valid", "nan", "inf", "shape", "dtype", "mixed", "asym"),
            *("indefinite", "not_stochastic", "negative_prob"),
        )
    ),
    seed=seeds,
    dtype=floats,
)
def test_linear_switching_model(field: str, kind: str, seed: int, dtype: torch.dtype) -> None:
    fields = switching_fields(seed, dtype)
    value = fields[field]
    probs = field in ("transition", "initial")
    if kind in ("nan", "inf"):
        value = value.clone()
        value.view(-1)[seed % value.numel()] = torch.nan if kind == "nan" else torch.inf
    elif kind == "shape":
        value = torch.cat([value, value], dim=-1)
    elif kind == "dtype":
        value = value.to(BAD_DTYPES[seed % len(BAD_DTYPES)])
    elif kind == "mixed":
        value = value.to(torch.float64 if dtype == torch.float32 else torch.float32)
    elif kind == "asym" and value.ndim > 1 and value.shape[-1] > 1:
        value = value + torch.triu(torch.ones_like(value), 1)
    elif kind == "indefinite":
        value = -value - 0.5 * torch.ones_like(value)
    elif kind == "not_stochastic":
        value = value * 1.5 + 0.01
    elif kind == "negative_prob":
        value = value.clone()
        value.view(-1)[0] = -0.2
    fields[field] = value
    changes_check = {
        "valid": False,
        "nan": True,
        "inf": True,
        "shape": True,
        "dtype": True,
        "mixed": True,
        # a general matrix may be asymmetric or negative; a covariance/probabilities not
        "asym": field in ("Q",) or (probs and value.shape[-1] > 1),
        "indefinite": field in ("Q", "R") or probs,
        "not_stochastic": probs,
        "negative_prob": probs,
    }
    if kind == "asym" and field == "transition":
        changes_check["asym"] = True  # the rows no longer sum to 1
    if kind == "asym" and field in ("R", "initial"):
        changes_check["asym"] = False  # (K, 1, 1) R and (K,) initial: triu adds nothing
    bad = changes_check[kind]
    # F sets the dtype the other fields must share: a mixed F is blamed on the next field
    names = list(fields) if kind == "mixed" and field == "F" else [field]
    expect(lambda: LinearSwitchingModel(**fields), names, must_raise=bad)


@FUZZ
@given(
    corruption=st.sampled_from(
        (
            *("none", "none", "nan_evidence", "inf_evidence", "nan_weights", "modes_high"),
            *("modes_low", "modes_float", "y_inf", "y_partial", "y_missing", "y_dtype"),
            "y_shape",
        )
    ),
    proposal=st.sampled_from(("bootstrap", "all_modes")),
    seed=seeds,
    batch=st.sampled_from(((), (0,), (2,))),
    dtype=floats,
)
def test_rbpf(
    corruption: str, proposal: Any, seed: int, batch: tuple[int, ...], dtype: torch.dtype
) -> None:
    model = LinearSwitchingModel(**switching_fields(seed, dtype))
    rbpf = RBPF(model, 4, proposal=proposal)
    g = prior(seed, 2, (), dtype)
    belief = rbpf.init(g, batch)
    y = torch.zeros(1, dtype=dtype)
    changes: dict[str, Tensor] = {}
    nonempty = int(np.prod(batch)) > 0 if batch else True
    if corruption == "nan_evidence":
        changes["log_evidence"] = torch.full_like(belief.log_evidence, torch.nan)
    elif corruption == "inf_evidence":
        changes["log_evidence"] = torch.full_like(belief.log_evidence, torch.inf)
    elif corruption == "nan_weights":
        changes["log_weights"] = torch.full_like(belief.log_weights, torch.nan)
    elif corruption == "modes_high":
        changes["modes"] = belief.modes + model.num_modes
    elif corruption == "modes_low":
        changes["modes"] = belief.modes - 3
    elif corruption == "modes_float":
        changes["modes"] = belief.modes.to(dtype)
    elif corruption == "y_inf":
        y = torch.full((1,), torch.inf, dtype=dtype)
    elif corruption in ("y_partial", "y_missing"):
        y = torch.full((1,), torch.nan, dtype=dtype)  # one component: a missing measurement
    elif corruption == "y_dtype":
        y = y.to(BAD_DTYPES[seed % len(BAD_DTYPES)])
    elif corruption == "y_shape":
        y = torch.zeros(2, dtype=dtype)
    bad_belief = dataclasses.replace(belief, **changes)
    bad = corruption in ("modes_float", "y_inf", "y_dtype", "y_shape") or (
        nonempty and corruption not in ("none", "y_partial", "y_missing")
    )
    out = expect(lambda: rbpf.step(bad_belief, y), ["belief", "y"], must_raise=bad)
    if out is None:
        return
    assert out.batch_shape == batch
    assert_finite(out.log_weights.exp(), out.log_evidence, out.gaussians.mean)
    assert_covariance(out.gaussians.cov.reshape(-1, 2, 2))
    total = torch.logsumexp(out.log_weights, -1)
    assert bool((total.abs() <= 1e3 * torch.finfo(dtype).eps).all()), "weights not normalized"


# ---------------------------------------------------------------------------------------------
# Smoother and resampling


@FUZZ
@given(
    F_kind=st.sampled_from(("normal", "normal", "mismatch", *VALID_ANY, *INVALID_ANY)),
    seed=seeds,
    n=dims,
    batch=batches,
    dtype=floats,
    T=st.integers(1, 4),
)
def test_rts_smooth(
    F_kind: str, seed: int, n: int, batch: tuple[int, ...], dtype: torch.dtype, T: int
) -> None:
    F_good = matrix("normal", seed + 2, (n, n), dtype, covariance=False) * 0.5
    Q = matrix("psd", seed + 3, (n, n), dtype, covariance=True)
    filtered = [prior(seed + 10 * t, n, batch, dtype) for t in range(T)]
    predicted = [kf_predict(g, F=F_good, Q=Q) for g in filtered[:-1]]
    if F_kind == "normal":
        F = F_good  # the dynamics of the predictions
    elif F_kind == "mismatch":
        F = 3.0 * F_good + torch.eye(n, dtype=dtype)  # not: the smoothed P may be indefinite
    else:
        F = matrix(F_kind, seed + 2, (n, n), dtype, covariance=False)
    bad: bool | None = T > 1 and is_invalid(F_kind, covariance=False)
    if not bad and F_kind != "normal":
        bad = None  # inconsistent with the predictions: an error or a PSD answer
    out = expect(lambda: rts_smooth(filtered, predicted, F=F), ["F", "predicted"], must_raise=bad)
    if out is not None:
        assert len(out) == T
        for g in out:
            assert g.batch_shape == batch
            assert_finite(g.mean)
            assert_covariance(g.cov, slack=1e4)


@FUZZ
@given(
    kind=st.sampled_from(("normal", "normal", "neginf_some", "dead_row", *INVALID_ANY)),
    method=st.sampled_from(("multinomial", "systematic", "stratified", "residual")),
    seed=seeds,
    batch=batches,
    N=st.integers(1, 6),
    dtype=floats,
)
def test_resampling(
    kind: str, method: Any, seed: int, batch: tuple[int, ...], N: int, dtype: torch.dtype
) -> None:
    base = kind if kind in INVALID_ANY else "normal"
    lw = matrix(base, seed, (*batch, N, 1), dtype, covariance=False)[..., 0]
    N = lw.shape[-1]  # the "shape" kind adds a particle
    if kind == "neginf_some" and N > 1:
        lw = lw.clone()
        lw[..., 0] = -torch.inf
    elif kind == "dead_row" and lw.numel():
        lw = lw.clone()
        lw[(0,) * len(batch)] = -torch.inf
    numel = lw.numel()
    # any (*B, N) shape is valid, and one tensor cannot mix dtypes
    value_bad = kind == "dtype" or (kind in ("nan", "inf") and numel > 0)
    bad = value_bad or (kind == "dead_row" and numel > 0)
    gen = torch.Generator().manual_seed(seed)
    idx = expect(
        lambda: resample(lw, method=method, generator=gen), ["log_weights"], must_raise=bad
    )
    if idx is not None:
        assert idx.shape == (*batch, N)
        assert idx.dtype == torch.long
        assert bool(((idx >= 0) & (idx < N)).all())
        if kind == "neginf_some" and N > 1:
            assert not bool((idx == 0).any()), "a zero-weight particle was drawn"
    opt = expect(
        lambda: optimal_resample(lw, max(N - 1, 1), generator=gen), ["log_weights"], must_raise=bad
    )
    if opt is not None:
        index, new_lw = opt
        assert bool(((index >= 0) & (index < N)).all())
        assert not bool(torch.isnan(new_lw).any() | torch.isposinf(new_lw).any())
    ess = expect(lambda: effective_sample_size(lw), ["log_weights"], must_raise=value_bad)
    if ess is not None:
        assert_finite(ess)
        assert bool(((ess >= 0) & (ess <= N * (1 + 1e-4))).all())


@pytest.mark.parametrize("dtype", FLOATS)
def test_empty_batch_kalman_returns_empty(dtype: torch.dtype) -> None:
    g = prior(0, 2, (0,), dtype)
    eye = torch.eye(2, dtype=dtype)
    p = kf_predict(g, F=eye, Q=eye)
    post, ll = kf_update(p, torch.zeros(0, 2, dtype=dtype), H=eye, R=eye)
    assert p.mean.shape == (0, 2)
    assert post.cov.shape == (0, 2, 2)
    assert ll.shape == (0,)
