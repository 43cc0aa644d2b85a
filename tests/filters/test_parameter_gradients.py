"""Gradients of the planar contact model and of the RBPF's evidence with respect to the scene's
physical parameters (friction, mass, inertia), against Richardson-extrapolated differences."""

from __future__ import annotations

import math
from dataclasses import replace

import torch

from torchcontact.filters import RBPF, Gaussian, KinematicControl, PlanarContactModel
from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import Body, Rollout, Scene, pushed_box_rollout, pushed_box_scene

F64 = torch.float64
STEPS = 12


def _with_parameters(
    scene: Scene, *, mu: torch.Tensor, inertia: torch.Tensor | None = None
) -> Scene:
    """``scene`` with the friction of every pair ``mu`` and the box's moment of inertia."""
    bodies = tuple(
        replace(body, inertia=inertia) if body.kind == "dynamic" else body for body in scene.bodies
    )
    return replace(scene, bodies=bodies, friction=mu)


def _data() -> tuple[Scene, Rollout, torch.Tensor, PlanarContactModel]:
    scene = pushed_box_scene(friction=0.4, mass=1.0)
    rollout, controls = pushed_box_rollout(scene, batch=2, steps=STEPS, seed=5)
    model = PlanarContactModel.from_rollout(
        scene,
        rollout,
        Q=torch.diag(torch.tensor([1e-7] * 3 + [1e-4] * 3, dtype=F64)),
        R=torch.diag(torch.tensor([2e-3, 2e-3, 1e-2], dtype=F64) ** 2),
    )
    return scene, rollout, controls, model


def _richardson(fn, value: float, step: float) -> torch.Tensor:  # type: ignore[no-untyped-def]
    """``d fn / d value`` by central differences at ``step`` and ``step / 2``, extrapolated."""
    wide = (fn(value + step) - fn(value - step)) / (2 * step)
    narrow = (fn(value + step / 2) - fn(value - step / 2)) / step
    return (4 * narrow - wide) / 3


def test_linearization_gradient_matches_differences_in_friction_and_inertia() -> None:
    """∂F/∂μ, ∂c/∂μ, ∂F/∂I and ∂c/∂I by autograd through the exact linearization equal
    extrapolated differences of the linearization, on every mode, at a box tipping on its
    lower-left corner (so that its rotation, and with it the inertia, is free): the corner
    sticks, slides either way, or leaves the ground. (The mass alone is not identifiable
    here: gravity and friction scale with it.)"""
    half_width, half_height, theta = 0.1, 0.05, 0.3
    scene = Scene(
        bodies=(
            Body("ground", HalfPlane.ground(), kind="static"),
            Body("box", Polygon.box(2 * half_width, 2 * half_height), mass=1.0),
        ),
        friction=0.4,
        h=0.01,
    )
    corner = torch.tensor([-half_width, -half_height], dtype=F64)
    rotation = torch.tensor(
        [[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]], dtype=F64
    )
    centre = -(rotation @ corner)  # the corner at the origin
    x = torch.tensor([[*centre.tolist(), theta, 0.3, -0.1, 0.5]], dtype=F64)
    modes = torch.tensor([[1, 0, 0, 0], [2, 0, 0, 0], [3, 0, 0, 0], [0, 0, 0, 0]])
    model = PlanarContactModel(
        scene=scene,
        modes=modes,
        Q=torch.eye(6, dtype=F64) * 1e-6,
        R=torch.eye(3, dtype=F64) * 1e-4,
        transition=torch.full((4, 4), 0.25, dtype=F64),
        initial=torch.full((4,), 0.25, dtype=F64),
    )
    inertia0 = 1.0 * (0.2**2 + 0.1**2) / 12

    def linearized(mu: float | torch.Tensor, inertia: float | torch.Tensor) -> torch.Tensor:
        moved = _with_parameters(
            scene, mu=torch.as_tensor(mu, dtype=F64), inertia=torch.as_tensor(inertia, dtype=F64)
        )
        F, c = replace(model, scene=moved).linearize(x)
        return torch.cat([F.flatten(-2), c], -1)

    mu = torch.tensor(0.4, dtype=F64, requires_grad=True)
    inertia = torch.tensor(inertia0, dtype=F64, requires_grad=True)
    value = linearized(mu, inertia)
    weights = torch.randn(value.shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    grad_mu, grad_inertia = torch.autograd.grad((weights * value).sum(), (mu, inertia))
    with torch.no_grad():
        fd_mu = _richardson(lambda m: (weights * linearized(m, inertia0)).sum(), 0.4, 1e-4)
        fd_inertia = _richardson(
            lambda i: (weights * linearized(0.4, i)).sum(), inertia0, 1e-3 * inertia0
        )
    assert abs(float(fd_mu)) > 1e-2  # both matter here
    assert abs(float(fd_inertia)) > 1.0
    torch.testing.assert_close(grad_mu, fd_mu, rtol=1e-7, atol=0.0)
    torch.testing.assert_close(grad_inertia, fd_inertia, rtol=1e-7, atol=0.0)


def test_evidence_gradient_matches_differences_in_friction() -> None:
    """d log p(y_1:T) / dμ of a bootstrap RBPF without resampling (fixed random numbers, so
    the evidence is a smooth function of μ between switches of the consistency gate) equals
    extrapolated differences of the evidence."""
    scene, rollout, controls, model = _data()
    prior = Gaussian(
        torch.cat([rollout.q[0, :, 0], rollout.v[0, :, 0]], -1),
        torch.diag(torch.tensor([1e-6, 1e-6, 1e-5, 1e-4, 1e-4, 1e-4], dtype=F64)).expand(2, 6, 6),
    )
    noise = torch.randn(STEPS, 2, 3, generator=torch.Generator().manual_seed(1), dtype=F64)
    y = rollout.q[1:, :, 0] + noise * torch.tensor([2e-3, 2e-3, 1e-2], dtype=F64)

    def evidence(mu: float | torch.Tensor) -> torch.Tensor:
        moved = replace(model, scene=_with_parameters(scene, mu=torch.as_tensor(mu, dtype=F64)))
        rbpf = RBPF(moved, 16, ess_threshold=0.0)
        generator = torch.Generator().manual_seed(2)
        belief = rbpf.init(prior)
        for t in range(STEPS):
            control = KinematicControl(q=rollout.q_kinematic[t], v=controls[t])
            belief = rbpf.step(belief, y[t], control=control, generator=generator)
        return belief.log_evidence.sum()

    mu = torch.tensor(0.4, dtype=F64, requires_grad=True)
    (gradient,) = torch.autograd.grad(evidence(mu), mu)
    with torch.no_grad():
        reference = _richardson(evidence, 0.4, 1e-5)
    assert abs(float(reference)) > 1.0  # the data speak about friction
    torch.testing.assert_close(gradient, reference, rtol=1e-5, atol=1e-6)
