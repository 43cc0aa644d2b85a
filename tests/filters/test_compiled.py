"""``compiled=True``: the filters' kernels through ``torch.compile`` against the eager kernels
they compile (the same functions), and the linearization's compile-friendly variant (fixed
system sizes) against the reference derivative of the step."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from tests.filters.test_contact_model import (
    HEIGHT,
    _linearization_cases,
    _noise,
    _pushed_box,
    _reference_linearization,
)
from tests.filters.test_rbpf import _problem, _run
from torchcontact._compiled import kernel
from torchcontact.filters import (
    RBPF,
    Gaussian,
    KinematicControl,
    LinearSwitchingModel,
    PlanarContactModel,
    RBPFBelief,
    collect_modes,
    empirical_transition,
)
from torchcontact.filters import _contact_model as contact_model_module
from torchcontact.filters._planar_linearization import linearize_modes

F64 = torch.float64


def _linearize(
    model: PlanarContactModel, x: torch.Tensor, control: KinematicControl, *, for_compile: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    q_kin, v_kin = model._control(control, x.shape[:-1], F64)
    mu, inverse_mass = model._physics()
    return linearize_modes(
        model._layout,
        model._mode_table,
        x,
        q_kin,
        v_kin,
        mu=mu,
        inverse_mass=inverse_mass,
        consistency_gap=model.consistency_gap,
        consistency_tolerance=model.consistency_tolerance,
        for_compile=for_compile,
    )


def _assert_beliefs_close(a: RBPFBelief, b: RBPFBelief, *, rtol: float, atol: float) -> None:
    assert torch.equal(a.modes, b.modes)
    for x, y in (
        (a.log_weights, b.log_weights),
        (a.gaussians.mean, b.gaussians.mean),
        (a.gaussians.cov, b.gaussians.cov),
        (a.log_evidence, b.log_evidence),
    ):
        torch.testing.assert_close(x, y, rtol=rtol, atol=atol)


def test_fixed_shapes_match_the_reference_linearization() -> None:
    for model, x, control in _linearization_cases():
        dynamic = _linearize(model, x, control, for_compile=False)
        fixed = _linearize(model, x, control, for_compile=True)
        assert torch.equal(fixed[2], dynamic[2])  # the consistency verdicts
        for b in range(len(x)):
            u = KinematicControl(q=control.q[b], v=control.v[b])
            ref = _reference_linearization(model, x[b], u)
            # The tolerances of the eager linearization's test where the mode's system is
            # solvable (and smooth at the point); elsewhere solve_mode's regularised answer
            # amplifies round-off: only finite.
            scale = ref.jacobian.abs().amax(dim=(-2, -1), keepdim=True).clamp_min(1.0)
            smooth = (ref.solvable & ~ref.kink)[:, None, None]
            error = (fixed[0][b] - ref.jacobian).abs() / scale
            assert bool((error <= 1e-10).where(smooth, True).all())
            error = (fixed[0][b] - dynamic[0][b]).abs() / scale
            assert bool((error[ref.solvable] <= 1e-10).all())
            assert bool(torch.isfinite(fixed[0][b]).all())
            # c makes the linearization exact at the point, as the eager one.
            torch.testing.assert_close(
                (fixed[0][b] @ x[b, :, None]).squeeze(-1) + fixed[1][b],
                (dynamic[0][b] @ x[b, :, None]).squeeze(-1) + dynamic[1][b],
                atol=1e-5 * float(scale.max()),
                rtol=0,
            )


@pytest.mark.parametrize("proposal", ["bootstrap", "all_modes"])
def test_compiled_rbpf_equals_eager(proposal: str) -> None:
    # Extra evidence ruling a mode out and a missed measurement: every branch of the step.
    problem = _problem(extra=True)
    eager = _run(RBPF(problem.model(), 24, proposal=proposal), problem, seed=3)
    compiled = _run(RBPF(problem.model(), 24, proposal=proposal, compiled=True), problem, seed=3)
    _assert_beliefs_close(eager, compiled, rtol=1e-10, atol=1e-12)


def test_compiled_rbpf_refactors_semidefinite_covariances() -> None:
    # A state component without noise and a prior that knows the state exactly: predicted
    # covariances are singular, the plain factor fails and the semi-definite one takes over.
    model = _problem().model()
    Q = model.Q.clone()
    Q[:, 1, 1] = 0.0
    model = LinearSwitchingModel(**{**model.__dict__, "Q": Q})
    prior = Gaussian(torch.zeros(2, dtype=F64), torch.zeros(2, 2, dtype=F64))
    ys = torch.tensor([[0.3], [0.1], [-0.2]], dtype=F64)
    beliefs = []
    for compiled in (False, True):
        rbpf = RBPF(model, 12, compiled=compiled)
        gen = torch.Generator().manual_seed(0)
        belief = rbpf.init(prior)
        for y in ys:
            belief = rbpf.step(belief, y, generator=gen)
        beliefs.append(belief)
    assert bool(torch.isfinite(beliefs[1].gaussians.cov).all())
    _assert_beliefs_close(*beliefs, rtol=1e-10, atol=1e-12)


@pytest.mark.slow  # compiles the linearization and the RBPF's kernels: minutes on a CPU
def test_compiled_contact_model_equals_eager(monkeypatch: pytest.MonkeyPatch) -> None:
    model, x, control = _linearization_cases()[0]
    compiled = replace(model, compiled=True)
    # The same operations as the eager compile-friendly variant, fused: equal to rounding.
    F, c, consistent = _linearize(model, x, control, for_compile=True)
    F_c, c_c, consistent_c = compiled._linearize(x, control, F64)
    assert torch.equal(consistent_c, consistent)
    scale = F.abs().amax(dim=(-2, -1), keepdim=True).clamp_min(1.0)
    # Relative to each mode's largest entry: 1e-12 where the mode's equalities are met
    # (measured: 1e-18); elsewhere the derivative of solve_mode's regularised answer amplifies
    # the rounding (measured: 5e-7).
    solvable = torch.stack(
        [
            _reference_linearization(
                model, x[b], KinematicControl(q=control.q[b], v=control.v[b])
            ).solvable
            for b in range(len(x))
        ]
    )
    tolerance = torch.where(solvable, 1e-12, 1e-5)[..., None, None] * scale
    assert bool(((F_c - F).abs() <= tolerance).all())
    torch.testing.assert_close(c_c, c, rtol=0, atol=1e-5 * float(scale.max()))

    # A few filter steps on a pushed box, both kernels compiled, against the same kernels run
    # eagerly (the model's compile-friendly linearization included: the eager model's own,
    # sized by the data, differs by more than rounding where a mode's system is regularised;
    # the first test of the linearization bounds that difference).
    steps = 6
    scene, train, _ = _pushed_box(8, 30, seed=0)
    table, ids, _ = collect_modes(train.mode)
    K = len(table)
    fields = {**_noise(K), "transition": empirical_transition(ids, K, smoothing=0.1)}
    eager_model = PlanarContactModel(scene=scene, modes=table, **fields)
    _, truth, controls = _pushed_box(1, steps, seed=1)
    prior = Gaussian(
        torch.tensor([[0.01, HEIGHT / 2, 0.0, 0.0, 0.0, 0.0]], dtype=F64),
        torch.diag(torch.tensor([1e-4, 1e-6, 1e-4, 1e-2, 1e-2, 1e-2], dtype=F64))[None],
    )
    runs = []
    for compiled_run in (False, True):
        with monkeypatch.context() as patch:
            if not compiled_run:
                patch.setattr(contact_model_module, "kernel", lambda fn, compiled: fn)
            rbpf = RBPF(replace(eager_model, compiled=True), 32, compiled=compiled_run)
            gen = torch.Generator().manual_seed(5)
            belief, beliefs = rbpf.init(prior), []
            for t in range(steps):
                u = KinematicControl(q=truth.q_kinematic[t], v=controls[t])
                belief = rbpf.step(belief, truth.q[t + 1, :, 0], control=u, generator=gen)
                beliefs.append(belief)
        runs.append(beliefs)
    # Every step: the same modes, and what the filter reports equal to rounding. (Particles of
    # negligible weight in a regularised mode amplify the rounding: their means differ by up
    # to 2e-3 at step 4, and their log-weights by 2e-4, weighing less than 1e-12.)
    for eager_belief, compiled_belief in zip(*runs, strict=True):
        assert torch.equal(eager_belief.modes, compiled_belief.modes)
        for x, y in (
            (eager_belief.log_weights.exp(), compiled_belief.log_weights.exp()),
            (eager_belief.mean(), compiled_belief.mean()),
            (eager_belief.cov(), compiled_belief.cov()),
            (eager_belief.log_evidence, compiled_belief.log_evidence),
        ):
            torch.testing.assert_close(x, y, rtol=1e-8, atol=1e-9)


def test_compiled_must_be_a_bool() -> None:
    model = _problem().model()
    with pytest.raises(ValueError, match="compiled"):
        RBPF(model, 8, compiled=1)  # type: ignore[arg-type]
    box, _, _ = _linearization_cases()[0]
    with pytest.raises(ValueError, match="compiled"):
        replace(box, compiled="yes")


def _scaled_sum(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (2.0 * a + b).sum(0)


def test_views_of_different_bases_reuse_one_compiled_kernel() -> None:
    from torch._dynamo.utils import counters

    compiled = kernel(_scaled_sum, compiled=True)
    assert kernel(_scaled_sum, compiled=True) is compiled  # one per process
    assert kernel(_scaled_sum, compiled=False) is _scaled_sum
    base = torch.arange(24.0).reshape(4, 6)
    other = torch.arange(48.0).reshape(8, 6)
    inputs = [
        (base[:2], base[2:]),  # slices of one tensor
        (other[1:3], other[5:7]),  # of a larger one
        (base[:2].clone(), other[:2].clone()),  # no views
        (torch.arange(12.0).reshape(2, 6), other.T.contiguous().T[:2]),
    ]
    compiled(*inputs[0])
    before = counters["frames"]["ok"]
    for a, b in inputs:
        torch.testing.assert_close(compiled(a, b), _scaled_sum(a, b))
    assert counters["frames"]["ok"] == before  # compiled once, before the loop


def _doubled(a: torch.Tensor) -> torch.Tensor:
    return 2.0 * a


def test_more_variants_than_dynamo_default_limit_all_compile() -> None:
    """Twelve variants of one kernel (each rank a graph of its own) all compile: dynamo's
    default limit (8) would run the last four eagerly."""
    from torch._dynamo.utils import counters

    compiled = kernel(_doubled, compiled=True)
    before = counters["stats"]["unique_graphs"]
    for rank in range(1, 13):
        a = torch.ones((1,) * rank)
        torch.testing.assert_close(compiled(a), 2.0 * a)
    assert counters["stats"]["unique_graphs"] == before + 12
