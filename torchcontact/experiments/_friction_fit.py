"""Fitting friction and camera noise to logs of boxes sliding to a stop, three ways.

A set of boxes slides across the ground at about 1 m/s until friction stops it; a camera sees
their poses with Gaussian noise. The contact RBPF's evidence ``log p(y | μ, σ)`` over the
logs is maximized by gradient (:func:`~torchcontact.filters.fit_parameters`), by a grid over
the box of plausible values and by CMA-ES (the ``cma`` package), on the same evidence.

Identifiability: with no applied force known, the box's mass scales gravity, friction and
inertia alike and is not identified; a box that slides flat does not rotate, so neither is its
inertia. The friction coefficient (from the deceleration ``μ g``) and the camera's noise (from
the scatter of the measurements about the motion) are.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

import torch
from torch import Tensor

from torchcontact.filters import RBPF, Gaussian, PlanarContactModel, fit_parameters
from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import Body, Scene, Simulator

#: The methods compared, in table order.
FIT_METHODS = ("gradient", "grid", "cma")


class FitSearch(Protocol):
    """The search box and budgets of the fitting methods (:class:`SlidingFit` and
    :class:`~torchcontact.experiments.GraspFit` have them)."""

    @property
    def seed(self) -> int:
        """Seed of CMA-ES (plus one)."""
        ...

    @property
    def mu_range(self) -> tuple[float, float]:
        """Search range of the friction coefficient."""
        ...

    @property
    def sigma_mm_range(self) -> tuple[float, float]:
        """Search range of the camera noise, mm."""
        ...

    @property
    def grid_points(self) -> int:
        """Grid points per parameter."""
        ...

    @property
    def cma_evaluations(self) -> int:
        """Evidence evaluations allowed to CMA-ES."""
        ...


@dataclass(frozen=True)
class SlidingFit:
    """Settings of the sliding-box fitting experiment.

    Attributes:
        seed: seed of the experiments' true parameters and logs.
        rounds: number of independent experiments, one per round (true parameters drawn per
            experiment; a run resumed with more rounds adds experiments).
        trials: boxes per experiment (the evidence sums over them).
        steps: time steps per log (10 ms).
        particles: RBPF particles (all-modes proposal).
        mu_range: range of the true friction coefficients and of the grid and CMA-ES search.
        sigma_mm_range: range of the true camera noise (position, mm; the angle's is 10 mrad
            per mm) and of the searches.
        grid_points: grid points per parameter.
        cma_evaluations: evidence evaluations allowed to CMA-ES.
    """

    seed: int = 0
    rounds: int = 4
    trials: int = 8
    steps: int = 40
    particles: int = 8
    mu_range: tuple[float, float] = (0.2, 0.8)
    sigma_mm_range: tuple[float, float] = (1.0, 4.0)
    grid_points: int = 13
    cma_evaluations: int = 120


@dataclass(frozen=True, eq=False)
class SlidingLogs:
    """One experiment's simulated logs.

    Attributes:
        mu: the true friction coefficient.
        sigma_mm: the true camera noise (position, mm).
        y: ``(T, B, 3)`` camera poses, float64.
        prior: the filter's prior over the boxes' first state.
        model: the contact model of the scene's two modes (sliding, sticking), with the
            nominal friction 0.5 and noise 2 mm (the fit replaces both).
    """

    mu: float
    sigma_mm: float
    y: Tensor
    prior: Gaussian
    model: PlanarContactModel


@dataclass(frozen=True)
class FitOutcome:
    """One method's fit of one experiment.

    Attributes:
        mu: estimated friction.
        sigma_mm: estimated camera noise, mm.
        log_evidence: evidence at the estimate.
        evaluations: evidence evaluations (with gradients, for ``gradient``).
        seconds: wall time.
        cpu_seconds: this process's CPU time (the steadier measure on a shared machine).
        mu_error: standard error of ``mu`` (``gradient`` only, else nan).
    """

    mu: float
    sigma_mm: float
    log_evidence: float
    evaluations: int
    seconds: float
    cpu_seconds: float
    mu_error: float = math.nan


def box_scene(mu: float | Tensor) -> Scene:
    """A 0.2 × 0.1 m, 1 kg box on the ground, friction ``mu``, 10 ms steps."""
    return Scene(
        bodies=(
            Body("ground", HalfPlane.ground(), kind="static"),
            Body("box", Polygon.box(0.2, 0.1), mass=1.0),
        ),
        friction=mu,
        h=0.01,
    )


def _camera_sigma(sigma_mm: Tensor) -> Tensor:
    """``(3,)`` camera standard deviations: position ``σ`` m, angle ``10 σ`` rad."""
    scale = torch.tensor([1.0, 1.0, 10.0], dtype=torch.float64)
    return 1e-3 * sigma_mm * scale


def sliding_logs(settings: SlidingFit, experiment: int) -> SlidingLogs:
    """Simulate one experiment: true ``μ`` and ``σ`` drawn uniformly in their ranges, boxes
    launched from a known pose at 0.9–1.1 m/s, noisy camera poses."""
    f64 = torch.float64
    generator = torch.Generator().manual_seed(1000 * settings.seed + experiment)
    draw = torch.rand(2, generator=generator, dtype=f64)
    mu = settings.mu_range[0] + float(draw[0]) * (settings.mu_range[1] - settings.mu_range[0])
    low, high = settings.sigma_mm_range
    sigma_mm = low + float(draw[1]) * (high - low)
    simulator = Simulator(box_scene(mu))
    B, T = settings.trials, settings.steps
    q = torch.zeros(B, 1, 3, dtype=f64)
    q[:, 0, 1] = 0.05
    v = torch.zeros(B, 1, 3, dtype=f64)
    v[:, 0, 0] = 0.9 + 0.2 * torch.rand(B, generator=generator, dtype=f64)
    rollout = simulator.rollout(simulator.initial_state(q=q, v=v), steps=T)
    sigma = _camera_sigma(torch.tensor(sigma_mm, dtype=f64))
    y = rollout.q[1:, :, 0] + sigma * torch.randn(T, B, 3, generator=generator, dtype=f64)
    nominal = box_scene(0.5)
    # The two modes of a flat sliding box (both bottom corners sliding, both sticking), from
    # a nominal rollout that slides and stops.
    nominal_simulator = Simulator(nominal)
    nominal_rollout = nominal_simulator.rollout(
        nominal_simulator.initial_state(q=q[:1], v=v[:1]), steps=T
    )
    model = PlanarContactModel.from_rollout(
        nominal,
        nominal_rollout,
        Q=torch.diag(torch.tensor([1e-8] * 3 + [1e-6] * 3, dtype=f64)),
        R=torch.diag(_camera_sigma(torch.tensor(2.0, dtype=f64)) ** 2),
    )
    # The boxes start at a known pose; their launch speed is 1 ± 0.1 m/s.
    launch = torch.tensor([1.0, 0.0, 0.0], dtype=f64).expand(B, 3)
    prior = Gaussian(
        torch.cat([rollout.q[0, :, 0], launch], -1),
        torch.diag(torch.tensor([1e-6, 1e-6, 1e-5, 1e-2, 1e-4, 1e-4], dtype=f64)).expand(B, 6, 6),
    )
    return SlidingLogs(mu=mu, sigma_mm=sigma_mm, y=y, prior=prior, model=model)


def sliding_evidence(logs: SlidingLogs, particles: int) -> Callable[[dict[str, Tensor]], Tensor]:
    """``{"mu", "sigma_mm"} ↦ log p(y | μ, σ)``, summed over the trials: the contact RBPF
    (all-modes proposal, a fixed generator) over the logs, differentiable in both."""

    def log_evidence(theta: dict[str, Tensor]) -> Tensor:
        R = torch.diag(_camera_sigma(theta["sigma_mm"]) ** 2)
        model = replace(logs.model, scene=box_scene(theta["mu"]), R=R)
        rbpf = RBPF(model, particles, proposal="all_modes")
        generator = torch.Generator().manual_seed(0)
        belief = rbpf.init(logs.prior)
        for t in range(len(logs.y)):
            belief = rbpf.step(belief, logs.y[t], generator=generator)
        return belief.log_evidence.sum()

    return log_evidence


def fit_by_gradient(
    evidence: Callable[[dict[str, Tensor]], Tensor], settings: FitSearch
) -> FitOutcome:
    """:func:`~torchcontact.filters.fit_parameters` from the middle of the search box."""
    start, cpu = time.perf_counter(), time.process_time()
    fit = fit_parameters(
        evidence,
        {"mu": sum(settings.mu_range) / 2, "sigma_mm": sum(settings.sigma_mm_range) / 2},
        lower={"mu": 0.0, "sigma_mm": 0.0},
    )
    return FitOutcome(
        mu=float(fit.values["mu"]),
        sigma_mm=float(fit.values["sigma_mm"]),
        log_evidence=float(fit.log_evidence),
        evaluations=fit.evaluations,
        seconds=time.perf_counter() - start,
        cpu_seconds=time.process_time() - cpu,
        mu_error=float(fit.standard_errors["mu"]),
    )


def fit_by_grid(evidence: Callable[[dict[str, Tensor]], Tensor], settings: FitSearch) -> FitOutcome:
    """The best point of a ``grid_points × grid_points`` grid over the search box."""
    start, cpu = time.perf_counter(), time.process_time()
    mus = torch.linspace(*settings.mu_range, settings.grid_points, dtype=torch.float64)
    sigmas = torch.linspace(*settings.sigma_mm_range, settings.grid_points, dtype=torch.float64)
    best = (-math.inf, 0.0, 0.0)
    with torch.no_grad():
        for mu in mus:
            for sigma in sigmas:
                value = float(evidence({"mu": mu, "sigma_mm": sigma}))
                best = max(best, (value, float(mu), float(sigma)))
    return FitOutcome(
        mu=best[1],
        sigma_mm=best[2],
        log_evidence=best[0],
        evaluations=settings.grid_points**2,
        seconds=time.perf_counter() - start,
        cpu_seconds=time.process_time() - cpu,
    )


def fit_by_cma(evidence: Callable[[dict[str, Tensor]], Tensor], settings: FitSearch) -> FitOutcome:
    """CMA-ES (``cma``, the reference implementation of N. Hansen) in the search box scaled to
    the unit square, from its centre with step 0.3, for ``cma_evaluations`` evaluations."""
    import cma  # the dev extra's; imported here so that the library does not need it

    (mu_low, mu_high), (s_low, s_high) = settings.mu_range, settings.sigma_mm_range
    start, cpu = time.perf_counter(), time.process_time()
    evaluations = 0

    def negative(point: list[float]) -> float:
        nonlocal evaluations
        evaluations += 1
        mu = mu_low + point[0] * (mu_high - mu_low)
        sigma = s_low + point[1] * (s_high - s_low)
        theta = {
            "mu": torch.tensor(mu, dtype=torch.float64),
            "sigma_mm": torch.tensor(sigma, dtype=torch.float64),
        }
        with torch.no_grad():
            return -float(evidence(theta))

    options = {
        "bounds": [[0.0, 0.0], [1.0, 1.0]],
        "maxfevals": settings.cma_evaluations,
        "seed": settings.seed + 1,
        "verbose": -9,
    }
    strategy = cma.CMAEvolutionStrategy([0.5, 0.5], 0.3, options)
    strategy.optimize(negative)
    point = strategy.result.xbest
    return FitOutcome(
        mu=mu_low + float(point[0]) * (mu_high - mu_low),
        sigma_mm=s_low + float(point[1]) * (s_high - s_low),
        log_evidence=-float(strategy.result.fbest),
        evaluations=evaluations,
        seconds=time.perf_counter() - start,
        cpu_seconds=time.process_time() - cpu,
    )


#: The fitting functions by method name.
FITTERS: dict[str, Callable[[Callable[[dict[str, Tensor]], Tensor], FitSearch], FitOutcome]] = {
    "gradient": fit_by_gradient,
    "grid": fit_by_grid,
    "cma": fit_by_cma,
}
