"""The simulator particle filter against the simulator's rollout and a hand-computed
likelihood."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from torchcontact.filters import (
    Gaussian,
    KinematicControl,
    SimulatorParticleFilter,
    resample,
)
from torchcontact.sim import UNSOLVED, SceneState, Simulator, StepResult, pushed_box_scene

F64 = torch.float64
STEPS = 12


def _pushes(batch: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The pushed box at rest, its finger 5 mm left of it pushing at 0.3 m/s: ``(B, 6)`` box
    states, ``(STEPS + 1, B, 1, 3)`` finger poses and ``(STEPS, B, 1, 3)`` finger twists."""
    box = torch.tensor([0.0, 0.05, 0.0, 0.0, 0.0, 0.0], dtype=F64).expand(batch, 6)
    v = torch.zeros(STEPS, batch, 1, 3, dtype=F64)
    v[..., 0] = 0.3
    q0 = torch.tensor([[-0.115, 0.03, 0.0]], dtype=F64).expand(batch, 1, 3)
    q = torch.cat([q0[None], q0 + 0.01 * v.cumsum(0)])
    return box.clone(), q, v


def _filter(num_particles: int, process: float = 0.0) -> SimulatorParticleFilter:
    return SimulatorParticleFilter(
        pushed_box_scene(),
        num_particles,
        process_std=torch.full((6,), process, dtype=F64),
        measurement_std=torch.tensor([0.004, 0.004, 0.03], dtype=F64),
    )


def test_one_particle_without_process_noise_follows_the_simulator_rollout() -> None:
    pf = _filter(1)
    box, q_kin, v_kin = _pushes(2)
    prior = Gaussian(box, (1e-8 * torch.eye(6, dtype=F64)).expand(2, 6, 6))
    belief = pf.init(prior, generator=torch.Generator().manual_seed(0))
    start = belief.particles[:, 0]
    simulator = Simulator(pf.scene)
    state = simulator.initial_state(
        q=start[:, None, :3], v=start[:, None, 3:], q_kinematic=q_kin[0]
    )
    rollout = simulator.rollout(state, steps=STEPS, controls=v_kin)
    y = torch.full((2, 3), math.nan, dtype=F64)
    for t in range(STEPS):
        belief = pf.step(belief, y, control=KinematicControl(q=q_kin[t], v=v_kin[t]))
        x = belief.particles[:, 0]
        torch.testing.assert_close(x[:, :3], rollout.q[t + 1, :, 0], rtol=0, atol=1e-12)
        torch.testing.assert_close(x[:, 3:], rollout.v[t + 1, :, 0], rtol=0, atol=1e-12)
        assert belief.modes[:, 0].tolist() == rollout.mode[t].tolist()
    assert float(rollout.q[-1, 0, 0, 0]) > 0.01  # the finger pushed the box
    torch.testing.assert_close(belief.log_evidence, torch.zeros(2, dtype=F64), rtol=0, atol=1e-15)


def test_weights_and_evidence_follow_the_gaussian_measurement_likelihood() -> None:
    """Without process noise the particles are deterministic given the prior draws, so each
    weight is the hand-computed ``log N(y; x, diag(σ²))`` plus the extra term, normalized; the
    evidence is the log of the average likelihood."""
    pf = _filter(16)
    box, q_kin, v_kin = _pushes(3)
    cov = torch.diag(torch.tensor([1e-6, 1e-8, 1e-4, 1e-4, 1e-8, 1e-4], dtype=F64))
    belief = pf.init(Gaussian(box, cov.expand(3, 6, 6)), generator=torch.Generator().manual_seed(1))
    sigma = pf.measurement_std.numpy()
    y = torch.tensor([[0.002, 0.05, 0.01], [math.nan] * 3, [0.0, 0.049, 6.27]], dtype=F64)
    bonus = torch.linspace(-1.0, 0.0, 16, dtype=F64)

    def extra(state: SceneState, result: StepResult) -> torch.Tensor:
        assert state.q.shape == (3, 16, 1, 3)
        assert result.pn.shape[:2] == (3, 16)
        return bonus.expand(3, 16)

    control = KinematicControl(q=q_kin[0], v=v_kin[0])
    after = pf.step(belief, y, control=control, extra_log_likelihood=extra)
    x = after.particles.numpy()
    for b in range(3):
        if b == 1:  # not measured: only the extra term
            log_lik = bonus.numpy().copy()
        else:
            r = x[b, :, :3] - y[b].numpy()
            r[:, 2] = (r[:, 2] + np.pi) % (2 * np.pi) - np.pi
            log_lik = -0.5 * ((r / sigma) ** 2).sum(-1) - np.log(2 * np.pi * sigma**2).sum() / 2
            log_lik += bonus.numpy()
        expected_weights = log_lik - np.logaddexp.reduce(log_lik)
        expected_evidence = np.logaddexp.reduce(log_lik) - np.log(16)
        torch.testing.assert_close(after.log_weights[b], torch.from_numpy(expected_weights))
        torch.testing.assert_close(
            after.log_evidence[b], torch.tensor(expected_evidence, dtype=F64)
        )
    assert bool(torch.isfinite(after.log_evidence).all())
    torch.testing.assert_close(after.mean(), (after.weights()[..., None] * after.particles).sum(1))


def test_resampling_draws_the_library_scheme_and_the_evidence_stays_finite() -> None:
    """After a measured step the next one starts with :func:`resample` (the same draw from
    the same generator state), then steps the chosen particles through the simulator."""
    pf = _filter(8)
    box, q_kin, v_kin = _pushes(2)
    cov = torch.diag(torch.tensor([4e-6, 1e-14, 1e-14, 1e-4, 1e-14, 1e-14], dtype=F64))
    generator = torch.Generator().manual_seed(2)
    belief = pf.init(Gaussian(box, cov.expand(2, 6, 6)), generator=generator)
    y = torch.tensor([0.004, 0.05, 0.0], dtype=F64).expand(2, 3)
    belief = pf.step(belief, y, control=KinematicControl(q=q_kin[0], v=v_kin[0]))
    clone = torch.Generator().set_state(generator.get_state())
    index = resample(belief.log_weights, method="systematic", generator=clone)
    after = pf.step(
        belief, y, control=KinematicControl(q=q_kin[1], v=v_kin[1]), generator=generator
    )
    chosen = torch.gather(belief.particles, 1, index[..., None].expand(2, 8, 6))
    simulator = Simulator(pf.scene)
    state = simulator.initial_state(
        q=chosen[..., None, :3],
        v=chosen[..., None, 3:],
        q_kinematic=q_kin[1, :, None].expand(2, 8, 1, 3).contiguous(),
    )
    modes = torch.gather(belief.modes, 1, index[..., None].expand_as(belief.modes))
    step = simulator.step(
        dataclasses.replace(state, mode=modes), v_kin[1, :, None].expand(2, 8, 1, 3).contiguous()
    )
    assert bool((step.solver != UNSOLVED).all())
    torch.testing.assert_close(
        after.particles[..., :3], step.state.q[..., 0, :], rtol=0, atol=1e-12
    )
    assert len(set(index[0].tolist())) < 8  # the draw duplicated some particles
    assert bool(torch.isfinite(after.log_evidence).all())
    assert bool((after.log_evidence < belief.log_evidence + 20).all())


def test_bad_arguments_name_the_argument() -> None:
    with pytest.raises(ValueError, match=r"^num_particles: "):
        _filter(0)
    with pytest.raises(ValueError, match=r"^measurement_std: "):
        SimulatorParticleFilter(
            pushed_box_scene(),
            2,
            process_std=torch.zeros(6, dtype=F64),
            measurement_std=torch.zeros(3, dtype=F64),
        )
    with pytest.raises(ValueError, match=r"^fallback"):
        dataclasses.replace(_filter(2), fallback=("simplex",))
    pf = _filter(2)
    box, q_kin, v_kin = _pushes(1)
    belief = pf.init(Gaussian(box, torch.eye(6, dtype=F64)[None]))
    with pytest.raises(ValueError, match=r"^y: "):
        pf.step(
            belief, torch.zeros(2, 3, dtype=F64), control=KinematicControl(q=q_kin[0], v=v_kin[0])
        )
    with pytest.raises(ValueError, match=r"^control.q"):
        pf.step(
            belief,
            torch.zeros(1, 3, dtype=F64),
            control=KinematicControl(q=q_kin[0, 0], v=v_kin[0]),
        )
