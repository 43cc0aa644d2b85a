"""The triangle-grasp fit: the launched slide against its closed form, the pair frictions of the
scene, and the evidence's gradient against finite differences under common random numbers."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from torchcontact.experiments import (
    GraspFit,
    grasp_fit_evidence,
    grasp_fit_logs,
    grasp_fit_scene,
    launched_grasps,
)
from torchcontact.sim import slot_friction

F64 = torch.float64
#: A small trial: two grasps of 24 steps, a filter of 16 particles over the modes of 4 grasps.
SMALL = GraspFit(grasps=2, steps=24, particles=16, train_trials=4)


def test_scene_gives_the_table_and_the_fingers_their_frictions() -> None:
    scene = grasp_fit_scene(0.3, 0.7)
    mu = slot_friction(scene, dtype=F64, device=torch.device("cpu"))
    names = [b.name for b in scene.bodies]
    for group in scene.slot_groups:
        pair = {names[group.receiver], names[group.other]}
        expected = 0.3 if pair == {"triangle", "table"} else 0.7
        assert "triangle" in pair
        # exact: the coefficients are copied, not computed
        assert (mu[group.start : group.start + group.count] == expected).all(), pair


def test_launched_triangle_stops_where_coulomb_friction_stops_it() -> None:
    """Before the fingers reach it the triangle slides flat on its base: the semi-implicit
    Euler step loses ``μ g h`` of speed per step, so it stops after
    ``h Σ_k max(v0 − k μ g h, 0)`` (closed form of the discrete motion)."""
    settings = GraspFit(steps=80, speed_range=(0.4, 0.5))
    mu = 0.45
    generator = torch.Generator().manual_seed(5)
    rollout, _, launch = launched_grasps(settings, grasp_fit_scene(mu, 0.5), 3, generator)
    h, g = 0.01, 9.81
    for b in range(3):
        v0 = float(launch[b, 0])
        speeds = [max(abs(v0) - k * mu * g * h, 0.0) for k in range(1, 30)]
        travel = h * sum(speeds) * (1.0 if v0 > 0 else -1.0)
        x = rollout.q[:, b, 0, 0]
        stop = len([s for s in speeds if s > 0]) + 1  # first step at rest
        # at rest before the closing fingers arrive (step 10 of 80 starts the closing)
        torch.testing.assert_close(
            x[stop], x[0] + travel, rtol=0, atol=1e-9, msg=f"trial {b}, v0 {v0}"
        )
        assert abs(float(rollout.q[stop, b, 0, 2])) < 1e-9  # flat: no rotation


@pytest.fixture(scope="module")
def small_logs() -> object:
    """Without the consistency gate: a step function of the friction by design (a mode is
    penalized once the friction it needs exceeds μ times its normal impulse), whose jumps
    central differences would straddle."""
    return grasp_fit_logs(dataclasses.replace(SMALL, inconsistency_penalty=0.0), 0)


def test_evidence_gradient_matches_finite_differences(small_logs: object) -> None:
    """Under common random numbers (the filter's fixed generator) the evidence is a smooth
    function of the parameters between the discrete events of resampling and of the
    consistency gate: autograd's gradient agrees with central differences to 1e-3 relative.
    Steps of 1e-5: the round-off of the evidence (~100 nats, ~1e-14 relative) gives the
    differences an error of ~1e-9, their truncation one of ~1e-10 × the third derivative."""
    evidence = grasp_fit_evidence(small_logs)  # type: ignore[arg-type]
    point = {"mu": 0.47, "sigma_mm": 2.2, "finger_mu": 0.55}
    leaves = {k: torch.tensor(v, dtype=F64, requires_grad=True) for k, v in point.items()}
    value = evidence(leaves)
    grads = torch.autograd.grad(value, list(leaves.values()))
    step = 1e-5
    for (name, x), grad in zip(point.items(), grads, strict=True):
        with torch.no_grad():
            up = evidence({**_tensors(point), name: torch.tensor(x + step, dtype=F64)})
            down = evidence({**_tensors(point), name: torch.tensor(x - step, dtype=F64)})
        fd = float(up - down) / (2 * step)
        assert abs(float(grad) - fd) <= 1e-3 * max(abs(fd), 1.0), (name, float(grad), fd)
    # the evidence depends on the ground friction and the noise
    assert abs(float(grads[0])) > 1.0
    assert abs(float(grads[1])) > 1.0


def test_trials_draw_their_parameters_in_the_ranges() -> None:
    settings = dataclasses.replace(SMALL, mu_range=(0.3, 0.31), sigma_mm_range=(2.0, 2.5))
    logs = grasp_fit_logs(settings, 3)
    assert 0.3 <= logs.mu <= 0.31
    assert 2.0 <= logs.sigma_mm <= 2.5
    assert SMALL.finger_mu_range[0] <= logs.finger_mu <= SMALL.finger_mu_range[1]
    # the camera's scatter about the truth is the drawn noise (visible steps only)
    seen = torch.isfinite(logs.trials.y[..., 0])
    residual = (logs.trials.y - logs.trials.truth.q[1:, :, 0])[seen][:, :2]
    assert residual.abs().max() < 5e-3 * logs.sigma_mm


def _tensors(point: dict[str, float]) -> dict[str, torch.Tensor]:
    return {k: torch.tensor(v, dtype=F64) for k, v in point.items()}
