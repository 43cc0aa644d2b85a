"""Rao-Blackwellized particle filter against exact references: a Kalman filter (one mode, or
identical modes) and the exact posterior of a small switching system by enumeration."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.filters import reference as ref
from torchcontact.filters import (
    RBPF,
    Gaussian,
    LinearSwitchingModel,
    ModeDynamics,
    RBPFBelief,
    kf_predict,
    kf_update,
)

F64 = torch.float64
K, N_STATE, T = 3, 2, 8


@dataclass
class Problem:
    arrays: dict[str, np.ndarray]  # F, c, Q, H, d, R: (K, ...); transition (A, K, K); initial
    ys: np.ndarray  # (T, m)
    actions: np.ndarray  # (T,) action per step (all 0 for a single transition matrix)
    extra: np.ndarray | None  # (T, K)

    def model(self, dtype: torch.dtype = F64, **override: torch.Tensor) -> LinearSwitchingModel:
        fields = {k: torch.tensor(v, dtype=dtype) for k, v in self.arrays.items()}
        if fields["transition"].shape[0] == 1:
            fields["transition"] = fields["transition"][0]
        fields.update(override)
        return LinearSwitchingModel(**fields)

    def exact(self) -> ref.Posterior:
        a = self.arrays
        return ref.enumerate_switching(
            a["F"],
            a["c"],
            a["Q"],
            a["H"],
            a["d"],
            a["R"],
            a["transition"][self.actions],
            a["initial"],
            np.zeros(N_STATE),
            np.eye(N_STATE),
            self.ys,
            self.extra,
        )


def _problem(*, actions: bool = False, extra: bool = False, seed: int = 0) -> Problem:
    arrays = {
        "F": np.array([[[1, 0.1], [0, 1]], [[1, 0.1], [0, 0.5]], [[0.9, 0], [0.2, 0.8]]]),
        "c": np.array([[0, 0.0], [0, 0.3], [0.1, -0.2]]),
        "Q": np.array([np.diag([0.01, 0.05]), np.diag([0.02, 0.01]), np.diag([0.05, 0.05])]),
        "H": np.array([[[1.0, 0.0]], [[1.0, 0.3]], [[0.8, -0.2]]]),
        "d": np.array([[0.0], [0.1], [-0.1]]),
        "R": np.array([[[0.1]], [[0.05]], [[0.2]]]),
        "transition": np.array([[[0.8, 0.15, 0.05], [0.1, 0.8, 0.1], [0.05, 0.15, 0.8]]]),
        "initial": np.array([0.6, 0.3, 0.1]),
    }
    rng = np.random.default_rng(seed)
    if actions:
        other = np.array([[0.2, 0.7, 0.1], [0.3, 0.3, 0.4], [0.0, 0.5, 0.5]])  # a zero entry
        arrays["transition"] = np.stack([arrays["transition"][0], other])
    # simulate the model
    a = arrays
    act = rng.integers(0, a["transition"].shape[0], size=T)
    mode = rng.choice(K, p=a["initial"])
    x = rng.multivariate_normal(np.zeros(N_STATE), np.eye(N_STATE))
    ys = []
    for t in range(T):
        mode = rng.choice(K, p=a["transition"][act[t], mode])
        x = a["F"][mode] @ x + a["c"][mode] + rng.multivariate_normal(np.zeros(2), a["Q"][mode])
        ys.append(a["H"][mode] @ x + a["d"][mode] + rng.normal(0, math.sqrt(a["R"][mode, 0, 0]), 1))
    ys_arr = np.array(ys)
    extra_arr = None
    if extra:
        extra_arr = rng.normal(size=(T, K))
        extra_arr[2, 1] = -math.inf  # tactile evidence rules mode 1 out at step 2
        ys_arr[4] = math.nan  # and the camera misses step 4
    return Problem(arrays, ys_arr, act, extra_arr)


def _prior(dtype: torch.dtype = F64) -> Gaussian:
    return Gaussian(torch.zeros(N_STATE, dtype=dtype), torch.eye(N_STATE, dtype=dtype))


def _run(
    rbpf: RBPF,
    problem: Problem,
    *,
    batch: tuple[int, ...] = (),
    seed: int = 0,
    dtype: torch.dtype = F64,
) -> RBPFBelief:
    gen = torch.Generator().manual_seed(seed)
    belief = rbpf.init(_prior(dtype), batch_shape=batch)
    actionful = problem.arrays["transition"].shape[0] > 1
    for t in range(T):
        extra = None if problem.extra is None else torch.tensor(problem.extra[t], dtype=dtype)
        belief = rbpf.step(
            belief,
            torch.tensor(problem.ys[t], dtype=dtype),
            action=int(problem.actions[t]) if actionful else None,
            extra_log_likelihood=extra,
            generator=gen,
        )
    return belief


# --------------------------------------------------------------------------------------------
# Kalman-filter limits


def _kf_reference(problem: Problem, mode: int) -> tuple[float, torch.Tensor, torch.Tensor]:
    a = {k: torch.tensor(v, dtype=F64) for k, v in problem.arrays.items()}
    g, total = _prior(), 0.0
    for t in range(T):
        g = kf_predict(g, F=a["F"][mode], c=a["c"][mode], Q=a["Q"][mode])
        g, ll = kf_update(
            g, torch.tensor(problem.ys[t]), H=a["H"][mode], d=a["d"][mode], R=a["R"][mode]
        )
        total += ll.item()
    return total, g.mean, g.cov


@pytest.mark.parametrize("proposal", ["bootstrap", "all_modes"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_single_mode_reproduces_the_kalman_filter(proposal: str, seed: int) -> None:
    problem = _problem(seed=seed)
    arrays = {k: v[:1] for k, v in problem.arrays.items() if k not in ("transition", "initial")}
    model = LinearSwitchingModel(
        **{k: torch.tensor(v) for k, v in arrays.items()},
        transition=torch.ones(1, 1, dtype=F64),
        initial=torch.ones(1, dtype=F64),
    )
    belief = _run(RBPF(model, 5, proposal=proposal), problem, seed=seed)  # type: ignore[arg-type]
    log_z, mean, cov = _kf_reference(problem, 0)
    assert abs(belief.log_evidence.item() - log_z) < 1e-10
    torch.testing.assert_close(belief.mean(), mean, rtol=0, atol=1e-10)
    torch.testing.assert_close(belief.cov(), cov, rtol=0, atol=1e-10)


@pytest.mark.parametrize(
    ("proposal", "resampling"),
    [("bootstrap", m) for m in ("systematic", "stratified", "multinomial", "residual")]
    + [("all_modes", "systematic")],
)
@pytest.mark.parametrize("seed", [0, 7])
def test_identical_modes_reproduce_the_kalman_filter(
    proposal: str, resampling: str, seed: int
) -> None:
    problem = _problem(seed=seed)
    shared = {
        k: np.repeat(problem.arrays[k][1:2], K, axis=0) for k in ("F", "c", "Q", "H", "d", "R")
    }
    problem.arrays.update(shared)
    rbpf = RBPF(problem.model(), 12, proposal=proposal, resampling=resampling, ess_threshold=0.9)  # type: ignore[arg-type]
    belief = _run(rbpf, problem, batch=(2,), seed=seed)
    log_z, mean, cov = _kf_reference(problem, 1)
    torch.testing.assert_close(
        belief.log_evidence, torch.full((2,), log_z, dtype=F64), rtol=0, atol=1e-10
    )
    torch.testing.assert_close(belief.mean(), mean.expand(2, -1), rtol=0, atol=1e-10)
    torch.testing.assert_close(belief.cov(), cov.expand(2, -1, -1), rtol=0, atol=1e-10)


@settings(max_examples=12, deadline=None, database=None)
@given(seed=st.integers(0, 2**31 - 1), all_modes=st.booleans())
def test_identical_modes_reproduce_the_kalman_filter_for_any_seed(
    seed: int, all_modes: bool
) -> None:
    problem = _problem(seed=1)
    shared = {
        k: np.repeat(problem.arrays[k][2:3], K, axis=0) for k in ("F", "c", "Q", "H", "d", "R")
    }
    problem.arrays.update(shared)
    rbpf = RBPF(problem.model(), 7, proposal="all_modes" if all_modes else "bootstrap")
    belief = _run(rbpf, problem, seed=seed)
    log_z, mean, _ = _kf_reference(problem, 2)
    assert abs(belief.log_evidence.item() - log_z) < 1e-10
    torch.testing.assert_close(belief.mean(), mean, rtol=0, atol=1e-10)


# --------------------------------------------------------------------------------------------
# Exact enumeration


def test_all_modes_without_reduction_equals_enumeration() -> None:
    """With N >= K^(T+1) every mode path keeps its own particle: the filter is exact. The
    problem uses action-dependent transitions (with a zero entry), a per-mode extra
    log-likelihood that rules a mode out, and a missing measurement."""
    problem = _problem(actions=True, extra=True, seed=3)
    exact = problem.exact()
    rbpf = RBPF(problem.model(), K ** (T + 1), proposal="all_modes", max_lag=T)
    belief = _run(rbpf, problem, seed=0)
    assert abs(belief.log_evidence.item() - exact.log_evidence) < 1e-10
    for lag in range(T + 1):
        np.testing.assert_allclose(
            belief.fixed_lag_marginals(lag).numpy(), exact.lag_marginals[lag], rtol=0, atol=1e-10
        )
    np.testing.assert_allclose(belief.mode_marginals().numpy(), exact.mode_marginals, atol=1e-10)
    np.testing.assert_allclose(belief.mean().numpy(), exact.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(belief.cov().numpy(), exact.cov, rtol=0, atol=1e-10)
    assert not belief.degenerate.any()


def test_all_modes_with_a_shared_partial_measurement_equals_enumeration() -> None:
    """A measurement that every mode shares and that reads the first state component only:
    the children's likelihoods come from the leading block of their prediction, and the
    survivors' Kalman updates from their parents; the filter stays exact."""
    problem = _problem(extra=True, seed=5)
    H = np.array([[1.0, 0.0]])
    problem.arrays["H"] = np.broadcast_to(H, (K, 1, N_STATE)).copy()
    exact = problem.exact()
    model = problem.model(H=torch.tensor(H, dtype=F64).expand(K, 1, N_STATE))
    rbpf = RBPF(model, K ** (T + 1), proposal="all_modes", max_lag=T)
    belief = _run(rbpf, problem, seed=0)
    assert abs(belief.log_evidence.item() - exact.log_evidence) < 1e-10
    np.testing.assert_allclose(belief.mode_marginals().numpy(), exact.mode_marginals, atol=1e-10)
    np.testing.assert_allclose(belief.mean().numpy(), exact.mean, rtol=0, atol=1e-10)
    np.testing.assert_allclose(belief.cov().numpy(), exact.cov, rtol=0, atol=1e-10)


@pytest.mark.parametrize("proposal", ["bootstrap", "all_modes"])
def test_estimates_converge_to_enumeration_as_particles_grow(proposal: str) -> None:
    problem = _problem(seed=4)
    exact = problem.exact()
    replicas, lag = 40, 2
    errors = []
    for n in (12, 192):
        rbpf = RBPF(problem.model(), n, proposal=proposal, max_lag=lag)  # type: ignore[arg-type]
        belief = _run(rbpf, problem, batch=(replicas,), seed=n)
        marg = (belief.mode_marginals().numpy() - exact.mode_marginals).__abs__().sum(-1).mean()
        lagged = belief.fixed_lag_marginals(lag).numpy() - exact.lag_marginals[lag]
        mean = np.linalg.norm(belief.mean().numpy() - exact.mean, axis=-1).mean()
        errors.append((marg, np.abs(lagged).sum(-1).mean(), mean))
    small, big = errors
    for e_small, e_big in zip(small, big, strict=True):
        assert e_big < 0.5 * e_small  # 16x the particles: ~4x smaller Monte Carlo error
        assert e_big < 0.15


@pytest.mark.parametrize(
    ("proposal", "resampling", "particles"),
    [("bootstrap", m, 16) for m in ("systematic", "stratified", "multinomial", "residual")]
    + [("all_modes", "systematic", 5)],
)
def test_evidence_estimate_is_unbiased(proposal: str, resampling: str, particles: int) -> None:
    """E[p̂(y_1:T)] = p(y_1:T): the mean of exp(log Ẑ - log Z) over replicas is 1 within
    its standard error (N = 5 < K² forces random reductions in all_modes)."""
    problem = _problem(seed=5)
    exact = problem.exact()
    replicas = 3000
    rbpf = RBPF(problem.model(), particles, proposal=proposal, resampling=resampling)  # type: ignore[arg-type]
    belief = _run(rbpf, problem, batch=(replicas,), seed=11)
    ratio = torch.exp(belief.log_evidence - exact.log_evidence)
    se = ratio.std() / math.sqrt(replicas)
    assert abs(ratio.mean().item() - 1.0) < 4 * se.item()
    assert 1e-4 < se.item() < 0.2  # the estimator is random (not exact) but not wild


def test_all_modes_reduction_does_not_collapse_onto_one_mode() -> None:
    """Equal children weights, laid out particle-major (i, k): a systematic pass over that
    layout would pick the same k for every survivor; the reduction must spread the modes."""
    problem = _problem(seed=12)
    same = {k: np.repeat(problem.arrays[k][:1], K, axis=0) for k in ("F", "c", "Q", "H", "d", "R")}
    problem.arrays.update(same)
    uniform = torch.full((K, K), 1.0 / K, dtype=F64)
    rbpf = RBPF(problem.model(transition=uniform), 30, proposal="all_modes")
    belief = rbpf.init(_prior(), batch_shape=(200,))
    gen = torch.Generator().manual_seed(0)
    for y in (0.3, 0.1, -0.2, 0.4):  # 9, 27, 81 (> 30: reduced), 90 (reduced) children
        belief = rbpf.step(belief, torch.tensor([y], dtype=F64), generator=gen)
    assert torch.isfinite(belief.log_weights).all()  # every slot holds a live particle
    counts = torch.nn.functional.one_hot(belief.modes, K).sum(-2).double()  # (200, K)
    assert counts.max().item() < 20  # never (nearly) a single mode
    torch.testing.assert_close(counts.mean(0), torch.full((K,), 10.0, dtype=F64), atol=0.6, rtol=0)
    marginals = belief.mode_marginals()
    torch.testing.assert_close(
        marginals.mean(0), torch.full((K,), 1 / K, dtype=F64), atol=0.02, rtol=0
    )


def test_ess_threshold_controls_bootstrap_resampling() -> None:
    problem = _problem(seed=13)
    never = _run(RBPF(problem.model(), 20, ess_threshold=0.0), problem, seed=1)
    always = _run(RBPF(problem.model(), 20, ess_threshold=1.0), problem, seed=1)
    torch.testing.assert_close(always.log_weights, torch.full((20,), -math.log(20), dtype=F64))
    assert never.log_weights.std().item() > 0.1
    # without resampling every particle keeps its own lineage: the start of each path is
    # still the deterministic initial allocation i mod K
    lineage = RBPF(problem.model(), 20, ess_threshold=0.0, max_lag=T)
    assert torch.equal(_run(lineage, problem, seed=1).history[:, T], torch.arange(20) % K)


# --------------------------------------------------------------------------------------------
# Degeneracy, gradients, reproducibility, dtypes


@pytest.mark.parametrize("proposal", ["bootstrap", "all_modes"])
def test_all_weights_zero_resets_to_the_prior(proposal: str) -> None:
    problem = _problem(seed=6)
    model = problem.model(R=torch.tensor(problem.arrays["R"]).requires_grad_())
    rbpf = RBPF(model, 9, proposal=proposal)  # type: ignore[arg-type]
    gen = torch.Generator().manual_seed(0)
    belief = rbpf.init(_prior(), batch_shape=(3,))
    belief = rbpf.step(belief, torch.tensor([0.1], dtype=F64), generator=gen)
    extra = torch.zeros(3, K, dtype=F64)
    extra[1] = -math.inf  # every mode ruled out for entry 1
    after = rbpf.step(
        belief, torch.tensor([0.2], dtype=F64), extra_log_likelihood=extra, generator=gen
    )
    assert after.degenerate.tolist() == [False, True, False]
    assert after.log_evidence[1].item() == -math.inf
    assert torch.isfinite(after.log_evidence[[0, 2]]).all()
    fresh = rbpf.init(_prior())
    assert torch.equal(after.modes[1], fresh.modes)
    torch.testing.assert_close(after.log_weights[1], fresh.log_weights)
    torch.testing.assert_close(after.gaussians.mean[1], fresh.gaussians.mean)
    torch.testing.assert_close(after.gaussians.cov[1], fresh.gaussians.cov)
    assert (after.history[1, :, 1:] == -1).all()
    for tensor in (after.log_weights, after.gaussians.mean, after.gaussians.cov, after.mean()):
        assert not torch.isnan(tensor).any()
    (grad,) = torch.autograd.grad(after.log_evidence[[0, 2]].sum(), model.R)
    assert torch.isfinite(grad).all()
    # the filter keeps going from the reset
    again = rbpf.step(after, torch.tensor([0.2], dtype=F64), generator=gen)
    assert not again.degenerate.any()
    assert torch.isfinite(again.mean()).all()


@pytest.mark.parametrize("proposal", ["bootstrap", "all_modes"])
def test_log_evidence_gradient_matches_finite_differences(proposal: str) -> None:
    """Stop-gradient resampling: for a fixed random stream the estimate is a smooth function
    of the noise parameters, and autograd gives its exact derivative."""
    problem = _problem(seed=7)
    base = {k: torch.tensor(v) for k, v in problem.arrays.items()}

    def log_evidence(
        r_scale: torch.Tensor, q_scale: torch.Tensor, stay: torch.Tensor
    ) -> torch.Tensor:
        move = (1 - stay) / 2
        transition = torch.stack(
            [torch.stack([stay if i == j else move for j in range(K)]) for i in range(K)]
        )
        model = problem.model(R=base["R"] * r_scale, Q=base["Q"] * q_scale, transition=transition)
        rbpf = RBPF(model, 6, proposal=proposal, ess_threshold=0.7)  # type: ignore[arg-type]
        return _run(rbpf, problem, batch=(4,), seed=3).log_evidence.sum()

    params = [torch.tensor(v, dtype=F64, requires_grad=True) for v in (1.3, 0.8, 0.85)]
    grads = torch.autograd.grad(log_evidence(*params), params, allow_unused=True)
    if proposal == "bootstrap":  # the bootstrap samples from the transition: no gradient
        assert grads[2] is None
        grads = grads[:2]
    h = 1e-6
    for i, grad in enumerate(grads):
        with torch.no_grad():
            up = [p + h if j == i else p for j, p in enumerate(params)]
            down = [p - h if j == i else p for j, p in enumerate(params)]
            fd = (log_evidence(*up) - log_evidence(*down)).item() / (2 * h)
        assert grad is not None
        assert abs(grad.item() - fd) < 1e-5 * max(1.0, abs(fd)), (i, grad.item(), fd)


@pytest.mark.parametrize("proposal", ["bootstrap", "all_modes"])
def test_noise_and_measurement_shared_by_every_mode_give_the_same_step(proposal: str) -> None:
    # Q, H, d, R given as views of one matrix are used without a copy per particle; the
    # numbers must be those of the same matrices stored once per mode.
    problem = _problem(extra=True)
    shared = {
        name: torch.tensor(problem.arrays[name][0], dtype=F64).expand(
            K, *problem.arrays[name][0].shape
        )
        for name in ("Q", "H", "d", "R")
    }
    views = RBPF(problem.model(**shared), 32, proposal=proposal)
    copies = RBPF(problem.model(**{k: v.clone() for k, v in shared.items()}), 32, proposal=proposal)
    a, b = _run(views, problem, seed=3), _run(copies, problem, seed=3)
    assert torch.equal(a.modes, b.modes)
    # The same numbers up to the rounding of kernels that may differ with the memory layout.
    for x, y in zip(
        (a.log_weights, a.log_evidence, a.gaussians.mean, a.gaussians.cov),
        (b.log_weights, b.log_evidence, b.gaussians.mean, b.gaussians.cov),
        strict=True,
    ):
        torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-12)


def test_steps_without_gradients_return_ordinary_tensors() -> None:
    # Without a gradient to carry, the step runs without autograd; what it returns must be
    # ordinary tensors, not inference ones (in-place updates and autograd work on them, and the
    # next compiled step sees the same kind of input), laid out as before.
    problem = _problem()
    belief = _run(RBPF(problem.model(), 16), problem)
    g = belief.gaussians
    tensors = (belief.modes, belief.log_weights, belief.log_evidence, g.mean, g.cov)
    assert not any(t.is_inference() for t in (*tensors, belief.history, belief.degenerate))
    assert g.cov.movedim(0, -1).is_contiguous()  # batch-last storage, as before
    g.mean.add_(0.0)
    scale = torch.ones((), dtype=F64, requires_grad=True)
    (g.cov * scale).sum().backward()  # saves the covariance for the backward pass
    assert scale.grad is not None


@pytest.mark.bitwise("the same code on the same inputs in the same process")
def test_generator_makes_runs_reproducible() -> None:
    problem = _problem(seed=8)
    rbpf = RBPF(problem.model(), 20)
    a, b = _run(rbpf, problem, batch=(2,), seed=5), _run(rbpf, problem, batch=(2,), seed=5)
    c = _run(rbpf, problem, batch=(2,), seed=6)
    assert torch.equal(a.modes, b.modes)
    assert torch.equal(a.log_evidence, b.log_evidence)
    assert not torch.equal(a.log_evidence, c.log_evidence)


def test_float32_exact_mode_matches_enumeration() -> None:
    problem = _problem(actions=True, extra=True, seed=9)
    exact = problem.exact()
    rbpf = RBPF(problem.model(torch.float32), K ** (T + 1), proposal="all_modes")
    belief = _run(rbpf, problem, dtype=torch.float32)
    assert belief.log_evidence.dtype == torch.float32
    assert belief.gaussians.cov.dtype == torch.float32
    assert abs(belief.log_evidence.item() - exact.log_evidence) < 1e-4 * abs(exact.log_evidence)
    np.testing.assert_allclose(belief.mode_marginals().numpy(), exact.mode_marginals, atol=1e-5)
    np.testing.assert_allclose(belief.mean().numpy(), exact.mean, atol=1e-5)


def test_float32_bootstrap_is_close_to_enumeration() -> None:
    problem = _problem(seed=9)
    exact = problem.exact()
    rbpf = RBPF(problem.model(torch.float32), 4000)
    belief = _run(rbpf, problem, dtype=torch.float32)
    assert abs(belief.log_evidence.item() - exact.log_evidence) < 0.2
    np.testing.assert_allclose(belief.mode_marginals().numpy(), exact.mode_marginals, atol=0.1)


def test_action_dependent_transition_requires_valid_actions() -> None:
    problem = _problem(actions=True)
    rbpf = RBPF(problem.model(), 6)
    belief = rbpf.init(_prior(), batch_shape=(2,))
    y = torch.zeros(1, dtype=F64)
    with pytest.raises(ValueError, match=r"^action:"):
        rbpf.step(belief, y)
    with pytest.raises(ValueError, match=r"^action:"):
        rbpf.step(belief, y, action=2)
    with pytest.raises(ValueError, match=r"^action:"):
        rbpf.step(belief, y, action=torch.tensor([0.0, 1.0]))
    out = rbpf.step(belief, y, action=torch.tensor([0, 1]))
    assert out.batch_shape == (2,)


def test_belief_accessors() -> None:
    problem = _problem(seed=10)
    belief = _run(RBPF(problem.model(), 50, max_lag=3), problem, batch=(2, 3))
    assert belief.modes.shape == (2, 3, 50)
    assert belief.modes.dtype == torch.long
    assert belief.gaussians.batch_shape == (2, 3, 50)
    torch.testing.assert_close(
        torch.logsumexp(belief.log_weights, -1), torch.zeros(2, 3, dtype=F64)
    )
    torch.testing.assert_close(belief.mode_marginals().sum(-1), torch.ones(2, 3, dtype=F64))
    assert torch.equal(belief.history[..., 0], belief.modes)
    assert ((belief.ess() > 0) & (belief.ess() <= 50 + 1e-9)).all()
    assert belief.cov().shape == (2, 3, 2, 2)
    with pytest.raises(ValueError, match=r"^lag:"):
        belief.fixed_lag_marginals(4)


# --------------------------------------------------------------------------------------------
# Validation


def _model_fields() -> dict[str, torch.Tensor]:
    return {k: torch.tensor(v) for k, v in _problem().arrays.items() if k != "transition"} | {
        "transition": torch.tensor(_problem().arrays["transition"][0])
    }


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("F", torch.zeros(3, 2)),
        ("c", torch.zeros(3, 3, dtype=F64)),
        ("Q", -torch.eye(2, dtype=F64).expand(3, 2, 2)),
        ("Q", torch.tensor([[0.0, 1.0], [0.0, 0.0]], dtype=F64).expand(3, 2, 2)),
        ("R", torch.zeros(3, 1, 1, dtype=F64)),
        ("H", torch.zeros(3, 1, 2)),
        ("d", torch.full((3, 1), math.nan, dtype=F64)),
        ("transition", torch.full((3, 3), 0.5, dtype=F64)),
        ("transition", torch.tensor([[1.5, -0.5, 0.0]] * 3, dtype=F64)),
        ("transition", torch.eye(4, dtype=F64)),
        ("initial", torch.tensor([0.5, 0.5, 0.5], dtype=F64)),
    ],
)
def test_model_validation_names_the_field(field: str, value: torch.Tensor) -> None:
    fields = _model_fields()
    fields[field] = value
    with pytest.raises(ValueError, match=f"^{field}:"):
        LinearSwitchingModel(**fields)


def test_rbpf_validation_names_the_argument() -> None:
    model = LinearSwitchingModel(**_model_fields())
    for kwargs, argument in (
        ({"num_particles": 2}, "num_particles"),
        ({"num_particles": 10, "proposal": "bogus"}, "proposal"),
        ({"num_particles": 10, "resampling": "bogus"}, "resampling"),
        ({"num_particles": 10, "ess_threshold": 2.0}, "ess_threshold"),
        ({"num_particles": 10, "max_lag": -1}, "max_lag"),
    ):
        with pytest.raises(ValueError, match=f"^{argument}:"):
            RBPF(model, **kwargs)  # type: ignore[arg-type]
    rbpf = RBPF(model, 10)
    belief = rbpf.init(_prior(), batch_shape=(2,))
    for call, argument in (
        (lambda: rbpf.init(_prior(torch.float32)), "prior"),
        (lambda: rbpf.init(_prior(), batch_shape=(3, 4, 5, 0.5)), "batch_shape"),
        (lambda: rbpf.step(belief, torch.zeros(2, dtype=F64)), "y"),
        (lambda: rbpf.step(belief, torch.zeros(3, 1, dtype=F64)), "y"),
        (lambda: rbpf.step(belief, torch.zeros(1, dtype=F64), action=1), "action"),
        (
            lambda: rbpf.step(
                belief,
                torch.zeros(1, dtype=F64),
                extra_log_likelihood=torch.full((3,), math.nan, dtype=F64),
            ),
            "extra_log_likelihood",
        ),
        (
            lambda: rbpf.step(
                belief,
                torch.zeros(1, dtype=F64),
                extra_log_likelihood=torch.full((3,), math.inf, dtype=F64),
            ),
            "extra_log_likelihood",
        ),
        (lambda: RBPF(model, 11).step(belief, torch.zeros(1, dtype=F64)), "belief"),
    ):
        with pytest.raises(ValueError, match=f"^{argument}:"):
            call()


# --------------------------------------------------------------------------------------------
# Per-particle transition rows (a mode transition that depends on the continuous state)


@dataclass(frozen=True, eq=False, kw_only=True)
class _StateDependentModel(LinearSwitchingModel):
    """p(m_t | m_{t-1}, x̂_{t-1}) ∝ transition[m_{t-1}] · exp(slope[m_{t-1}] · x̂_{t-1}), x̂
    the particle's filtered mean: the rows differ between particles of the same mode."""

    slope: torch.Tensor  # (K, K, n)

    def mode_dynamics(self, belief: RBPFBelief, control: object) -> ModeDynamics:
        logits = torch.log(self.transition)[belief.modes] + torch.einsum(
            "...kn,...n->...k", self.slope[belief.modes], belief.gaussians.mean
        )
        rows = torch.softmax(logits, dim=-1)
        return replace(super().mode_dynamics(belief, control), transition_rows=rows)


def _state_dependent_slope() -> np.ndarray:
    return np.random.default_rng(21).normal(scale=0.8, size=(K, K, N_STATE))


def _enumerate(
    problem: Problem, steps: int, log_children: Callable[[int, np.ndarray], np.ndarray]
) -> float:
    """log Σ over every mode path of its weight and p(y_1:steps | path), each path with its
    own Kalman filter: a step from mode ``m`` with filtered mean ``x̂`` to mode ``k`` weighs
    ``exp(log_children(m, x̂)[k])``."""
    a = problem.arrays

    def visit(t: int, mode: int, m: np.ndarray, P: np.ndarray, log_p: float) -> list[float]:
        if t == steps:
            return [log_p]
        log_w = log_children(mode, m)
        out = []
        for k in range(K):
            m_k, P_k = ref.kf_predict(m, P, a["F"][k], a["c"][k], a["Q"][k])
            m_k, P_k, ll = ref.kf_update(m_k, P_k, problem.ys[t], a["H"][k], a["d"][k], a["R"][k])
            out += visit(t + 1, k, m_k, P_k, log_p + log_w[k] + ll)
        return out

    leaves = []
    for k0 in range(K):
        leaves += visit(0, k0, np.zeros(N_STATE), np.eye(N_STATE), math.log(a["initial"][k0]))
    return float(np.logaddexp.reduce(np.array(leaves)))


def _enumerate_state_dependent(problem: Problem, slope: np.ndarray, steps: int) -> float:
    """log p(y_1:steps) of the transition ∝ transition[m] · exp(slope[m] · x̂)."""
    log_t = np.log(problem.arrays["transition"][0])

    def log_rows(mode: int, m: np.ndarray) -> np.ndarray:
        logits = log_t[mode] + slope[mode] @ m
        return logits - np.logaddexp.reduce(logits)

    return _enumerate(problem, steps, log_rows)


def test_transition_rows_equal_enumeration_of_a_state_dependent_transition() -> None:
    problem = _problem(seed=6)
    slope = _state_dependent_slope()
    steps = 4
    fields = {k: torch.tensor(v, dtype=F64) for k, v in problem.arrays.items()}
    fields["transition"] = fields["transition"][0]
    model = _StateDependentModel(**fields, slope=torch.tensor(slope))
    rbpf = RBPF(model, K ** (steps + 1), proposal="all_modes")
    belief = rbpf.init(_prior())
    for t in range(steps):
        belief = rbpf.step(belief, torch.tensor(problem.ys[t]))
    exact = _enumerate_state_dependent(problem, slope, steps)
    assert abs(belief.log_evidence.item() - exact) < 1e-10
    # the constant-transition filter gives a different answer: the rows mattered
    plain = RBPF(problem.model(), K ** (steps + 1), proposal="all_modes")
    other = plain.init(_prior())
    for t in range(steps):
        other = plain.step(other, torch.tensor(problem.ys[t]))
    assert abs(other.log_evidence.item() - exact) > 1e-3


def _seeded_run(model: LinearSwitchingModel, problem: Problem, proposal: str) -> RBPFBelief:
    """32 particles, batch 4, over the problem's T steps with fixed seeds."""
    rbpf = RBPF(model, 32, proposal=proposal)  # type: ignore[arg-type]
    gen = torch.Generator().manual_seed(3)
    torch.manual_seed(5)  # init draws from torch's default generator
    belief = rbpf.init(_prior(), batch_shape=(4,))
    for t in range(T):
        belief = rbpf.step(belief, torch.tensor(problem.ys[t]), generator=gen)
    return belief


@pytest.mark.parametrize("proposal", ["bootstrap", "all_modes"])
def test_transition_rows_from_the_matrix_reproduce_the_plain_filter(proposal: str) -> None:
    problem = _problem(seed=7)
    fields = {k: torch.tensor(v, dtype=F64) for k, v in problem.arrays.items()}
    fields["transition"] = fields["transition"][0]
    zero = torch.zeros(K, K, N_STATE, dtype=F64)
    rows_model = _StateDependentModel(**fields, slope=zero)
    plain, rows = (_seeded_run(model, problem, proposal) for model in (problem.model(), rows_model))
    torch.testing.assert_close(rows.log_evidence, plain.log_evidence, rtol=1e-12, atol=1e-12)
    assert torch.equal(rows.modes, plain.modes)


# --------------------------------------------------------------------------------------------
# Per-particle log-weights of the children (a model that judges each particle's modes)


@dataclass(frozen=True, eq=False, kw_only=True)
class _ParticleWeightModel(LinearSwitchingModel):
    """Child (i, k) weighted by exp(slope[k] · x̂_i), x̂_i particle i's filtered mean: not
    normalized over k, so a particle's total weight changes with its state."""

    slope: torch.Tensor  # (K, n)
    mode_weight: torch.Tensor  # (K,) the same for every particle

    def mode_dynamics(self, belief: RBPFBelief, control: object) -> ModeDynamics:
        weight = torch.einsum("kn,...n->...k", self.slope, belief.gaussians.mean)
        return replace(
            super().mode_dynamics(belief, control),
            particle_log_weight=weight,
            mode_log_weight=self.mode_weight,
        )


def _enumerate_weighted(problem: Problem, slope: np.ndarray, steps: int) -> float:
    """log Σ over every mode path of p(path, y_1:steps) Π_t exp(slope[k_t] · x̂_{t-1}), x̂ the
    path's filtered mean before step t: what the all-modes RBPF with one particle per path
    reports as its log-evidence."""
    log_t = np.log(problem.arrays["transition"][0])
    return _enumerate(problem, steps, lambda mode, m: log_t[mode] + slope @ m)


def test_particle_log_weight_equals_enumeration() -> None:
    problem = _problem(seed=8)
    slope = np.random.default_rng(22).normal(scale=0.8, size=(K, N_STATE))
    steps = 4
    fields = {k: torch.tensor(v, dtype=F64) for k, v in problem.arrays.items()}
    fields["transition"] = fields["transition"][0]
    zero = torch.zeros(K, dtype=F64)
    model = _ParticleWeightModel(**fields, slope=torch.tensor(slope), mode_weight=zero)
    rbpf = RBPF(model, K ** (steps + 1), proposal="all_modes")
    belief = rbpf.init(_prior())
    for t in range(steps):
        belief = rbpf.step(belief, torch.tensor(problem.ys[t]))
    exact = _enumerate_weighted(problem, slope, steps)
    assert abs(belief.log_evidence.item() - exact) < 1e-10
    # without the weights the evidence differs: they mattered
    assert abs(_enumerate_weighted(problem, 0 * slope, steps) - exact) > 1e-2


@pytest.mark.parametrize("proposal", ["bootstrap", "all_modes"])
def test_particle_log_weight_shared_by_the_particles_is_the_mode_log_weight(proposal: str) -> None:
    problem = _problem(seed=9)
    fields = {k: torch.tensor(v, dtype=F64) for k, v in problem.arrays.items()}
    fields["transition"] = fields["transition"][0]
    weight = torch.tensor([0.0, -1.5, -math.inf], dtype=F64)  # mode 2 ruled out

    @dataclass(frozen=True, eq=False, kw_only=True)
    class Shared(LinearSwitchingModel):
        def mode_dynamics(self, belief: RBPFBelief, control: object) -> ModeDynamics:
            return replace(super().mode_dynamics(belief, control), mode_log_weight=weight)

    @dataclass(frozen=True, eq=False, kw_only=True)
    class PerParticle(LinearSwitchingModel):
        def mode_dynamics(self, belief: RBPFBelief, control: object) -> ModeDynamics:
            rows = weight.expand(*belief.modes.shape, K)  # (*B, N, K)
            return replace(super().mode_dynamics(belief, control), particle_log_weight=rows)

    shared, per_particle = (
        _seeded_run(model, problem, proposal) for model in (Shared(**fields), PerParticle(**fields))
    )
    torch.testing.assert_close(
        per_particle.log_evidence, shared.log_evidence, rtol=1e-12, atol=1e-12
    )
    assert (per_particle.modes == shared.modes).all()  # integers
    assert torch.isneginf(shared.log_weights[shared.modes == 2]).all()  # ruled out


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("transition_rows", torch.full((5, K), 0.5, dtype=F64), "summing to 1"),
        (
            "transition_rows",
            torch.tensor([[1.5, -0.5, 0.0]], dtype=F64).expand(5, K),
            "non-negative",
        ),
        ("transition_rows", torch.full((4, K), 1.0 / K, dtype=F64), "transition_rows"),
        ("transition_rows", torch.full((2, 5, K), 1.0 / K, dtype=F64), "broadcast"),
        ("particle_log_weight", torch.full((5, K), math.nan, dtype=F64), "particle_log_weight"),
        ("particle_log_weight", torch.full((5, K), math.inf, dtype=F64), "particle_log_weight"),
        ("particle_log_weight", torch.zeros(4, K, dtype=F64), "particle_log_weight"),
        ("particle_log_weight", torch.zeros(2, 5, K, dtype=F64), "broadcast"),
    ],
)
def test_per_particle_dynamics_are_validated(field: str, value: torch.Tensor, match: str) -> None:
    problem = _problem(seed=7)

    @dataclass(frozen=True, eq=False, kw_only=True)
    class Fixed(LinearSwitchingModel):
        def mode_dynamics(self, belief: RBPFBelief, control: object) -> ModeDynamics:
            return replace(super().mode_dynamics(belief, control), **{field: value})

    fields = {k: torch.tensor(v, dtype=F64) for k, v in problem.arrays.items()}
    fields["transition"] = fields["transition"][0]
    rbpf = RBPF(Fixed(**fields), 5)
    belief = rbpf.init(_prior())
    with pytest.raises(ValueError, match=match):
        rbpf.step(belief, torch.tensor(problem.ys[0]))
