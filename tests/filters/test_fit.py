"""fit_parameters against closed-form maximum likelihood, and on a box sliding to a stop."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from torchcontact.experiments import box_scene
from torchcontact.filters import RBPF, Gaussian, PlanarContactModel, fit_parameters
from torchcontact.sim import Simulator

F64 = torch.float64


def test_gaussian_mean_and_scale_match_the_closed_form() -> None:
    """For ``y_i ~ N(m, s²)`` the estimates are the sample mean and the (biased) sample
    standard deviation, with standard errors ``s/√n`` and ``s/√(2n)``."""
    y = 3.0 + 0.5 * torch.randn(400, generator=torch.Generator().manual_seed(0), dtype=F64)
    n = len(y)

    def log_likelihood(theta: dict[str, torch.Tensor]) -> torch.Tensor:
        m, s = theta["m"], theta["s"]
        return (-0.5 * ((y - m) / s) ** 2 - torch.log(s) - 0.5 * math.log(2 * math.pi)).sum()

    fit = fit_parameters(log_likelihood, {"m": 0.0, "s": 2.0}, lower={"s": 0.0})
    mean = y.mean()
    scale = (y - mean).pow(2).mean().sqrt()
    assert fit.converged
    # A smooth maximum is located to about √(eps |log p| / curvature) ≈ 1e-8 relative here.
    torch.testing.assert_close(fit.values["m"], mean, rtol=1e-7, atol=0)
    torch.testing.assert_close(fit.values["s"], scale, rtol=1e-7, atol=0)
    # The curvature by differences of the exact gradient: 1e-6 relative.
    torch.testing.assert_close(fit.standard_errors["m"], scale / math.sqrt(n), rtol=1e-6, atol=0)
    torch.testing.assert_close(
        fit.standard_errors["s"], scale / math.sqrt(2 * n), rtol=1e-6, atol=0
    )
    torch.testing.assert_close(fit.log_evidence, log_likelihood(fit.values), rtol=1e-12, atol=0)


def test_a_flat_direction_has_no_standard_error() -> None:
    """Only ``a + b`` is identified: the curvature is singular and the errors are nan."""

    def log_likelihood(theta: dict[str, torch.Tensor]) -> torch.Tensor:
        return -((theta["a"] + theta["b"] - 1.0) ** 2)

    fit = fit_parameters(log_likelihood, {"a": 0.2, "b": 0.1})
    torch.testing.assert_close(fit.values["a"] + fit.values["b"], torch.tensor(1.0, dtype=F64))
    assert math.isnan(float(fit.standard_errors["a"]))


def test_friction_of_a_box_sliding_to_a_stop() -> None:
    """Eight boxes slide at about 1 m/s to a stop (μ = 0.37) under a 2 mm camera; the RBPF's
    evidence over its two modes (sliding, sticking) recovers μ within three standard errors,
    and the standard error is a few thousandths."""
    true = box_scene(0.37)
    simulator = Simulator(true)
    generator = torch.Generator().manual_seed(0)
    B, T = 8, 40
    q = torch.zeros(B, 1, 3, dtype=F64)
    q[:, 0, 1] = 0.05
    v = torch.zeros(B, 1, 3, dtype=F64)
    v[:, 0, 0] = 0.9 + 0.2 * torch.rand(B, generator=generator, dtype=F64)
    rollout = simulator.rollout(simulator.initial_state(q=q, v=v), steps=T)
    sigma = torch.tensor([2e-3, 2e-3, 2e-2], dtype=F64)
    y = rollout.q[1:, :, 0] + sigma * torch.randn(T, B, 3, generator=generator, dtype=F64)
    model = PlanarContactModel.from_rollout(
        true,
        rollout,
        Q=torch.diag(torch.tensor([1e-8] * 3 + [1e-6] * 3, dtype=F64)),
        R=torch.diag(sigma**2),
    )
    assert model.num_modes == 2
    prior = Gaussian(
        torch.cat([rollout.q[0, :, 0], rollout.v[0, :, 0]], -1),
        torch.diag(torch.tensor([1e-6, 1e-6, 1e-5, 1e-2, 1e-4, 1e-4], dtype=F64)).expand(B, 6, 6),
    )

    def log_evidence(theta: dict[str, torch.Tensor]) -> torch.Tensor:
        rbpf = RBPF(replace(model, scene=box_scene(theta["mu"])), 8, proposal="all_modes")
        rng = torch.Generator().manual_seed(1)
        belief = rbpf.init(prior)
        for t in range(T):
            belief = rbpf.step(belief, y[t], generator=rng)
        return belief.log_evidence.sum()

    fit = fit_parameters(log_evidence, {"mu": 0.3}, lower={"mu": 0.0})
    mu, error = float(fit.values["mu"]), float(fit.standard_errors["mu"])
    assert fit.converged
    assert 1e-3 < error < 1e-2
    assert abs(mu - 0.37) < 3 * error, (mu, error)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"initial": {}}, "initial"),
        ({"initial": {"a": math.nan}}, "initial"),
        ({"initial": {"a": -1.0}, "lower": {"a": 0.0}}, "initial"),
        ({"initial": {"a": 1.0}, "lower": {"b": 0.0}}, "lower"),
        ({"initial": {"a": 1.0}, "max_iterations": 0}, "max_iterations"),
        ({"initial": {"a": 1.0}, "tolerance": 0.0}, "tolerance"),
    ],
)
def test_bad_arguments_are_named(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        fit_parameters(lambda theta: -(theta["a"] ** 2), **kwargs)
