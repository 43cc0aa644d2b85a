"""solve_mode on batches of large systems with two threads: the batched LU must stay right.

torch 2.13 factors a CPU batch of matrices concurrently over the batch, and MKL's getrf, run
concurrently on matrices of about 150 rows or more, returns pivots outside ``[1, m]`` while
reporting success (or never returns). The failure shows on a process's first LAPACK calls, so
the solve runs in a fresh process with two threads. The reference is a sticking step built
backwards from chosen impulses (its end velocity in closed form, NumPy), solved by the batch at
once and problem by problem.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from torchcontact.contact import STICKING, ContactProblem, iterated_tikhonov, tikhonov_system
from torchcontact.contact._tikhonov import LU_SEQUENTIAL_MIN_ORDER

BATCH, DOFS, SLOTS, H = 4, 200, 90, 0.01  # 2 · 90 = 180 active rows per problem

# The child solves the batch at once and problem by problem, and saves both.
_CHILD = """
import sys
import torch
torch.set_num_threads(2)
from torchcontact.contact import ContactProblem, solve_mode
fields = torch.load(sys.argv[1])
mode = fields.pop("mode")
problem = ContactProblem(**fields, h=float(sys.argv[3]))
batched = solve_mode(problem, mode)
single = [solve_mode(problem[i : i + 1], mode[i : i + 1]) for i in range(mode.shape[0])]
torch.save(
    {
        "v_next": batched.v_next,
        "converged": batched.status.converged,
        "v_next_single": torch.cat([s.v_next for s in single]),
    },
    sys.argv[2],
)
"""


def _many_contact_problem() -> tuple[ContactProblem, torch.Tensor]:
    """``BATCH`` planar problems of ``SLOTS`` random sticking contacts on ``DOFS`` velocities,
    and ``(BATCH, DOFS)`` their end velocities.

    The step is built backwards from chosen impulses ``x = [pn; λ]`` (loads in ``[1, 2]``,
    friction in ``[−0.5, 0.5]``): with ``v⁺ = v + h M⁻¹ f + M⁻¹ Cᵀ x`` (NumPy), the known
    velocities ``bn = −Jn v⁺ − φ/h`` and ``bt = ∓Jt₀ v⁺`` make every sticking equality hold,
    and ``C M⁻¹ Cᵀ`` (``C = [Jn; Jt₀]``, full row rank) makes ``x`` and ``v⁺`` unique.
    """
    gen = torch.Generator().manual_seed(7)

    def uniform(low: float, high: float, *shape: int) -> torch.Tensor:
        return low + (high - low) * torch.rand(*shape, generator=gen, dtype=torch.float64)

    def randn(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=gen, dtype=torch.float64)

    X = randn(BATCH, DOFS, DOFS)
    M = X @ X.mT / DOFS + torch.eye(DOFS, dtype=torch.float64)
    v, f, Jn, Jt0 = (
        randn(BATCH, DOFS),
        randn(BATCH, DOFS),
        randn(BATCH, SLOTS, DOFS),
        randn(BATCH, SLOTS, DOFS),
    )
    phi = uniform(0.0, 0.01, BATCH, SLOTS)
    x = torch.cat([uniform(1.0, 2.0, BATCH, SLOTS), uniform(-0.5, 0.5, BATCH, SLOTS)], dim=-1)
    C = torch.cat([Jn, Jt0], dim=-2).numpy()
    v_next = torch.from_numpy(
        np.stack(
            [
                v[i].numpy()
                + np.linalg.solve(M[i].numpy(), H * f[i].numpy() + C[i].T @ x[i].numpy())
                for i in range(BATCH)
            ]
        )
    )
    bn = -(Jn @ v_next.unsqueeze(-1)).squeeze(-1) - phi / H
    bt0 = -(Jt0 @ v_next.unsqueeze(-1)).squeeze(-1)
    problem = ContactProblem(
        M=M,
        v=v,
        f=f,
        Jn=Jn,
        Jt=torch.stack([Jt0, -Jt0], dim=-2),
        phi=phi,
        mu=torch.ones(BATCH, SLOTS, dtype=torch.float64),
        h=H,
        bn=bn,
        bt=torch.stack([bt0, -bt0], dim=-1),
    )
    return problem, v_next


def test_two_thread_batched_solve_of_180_rows_matches_the_built_step(tmp_path: Path) -> None:
    problem, reference = _many_contact_problem()
    mode = torch.full((BATCH, SLOTS), STICKING)
    fields = ("M", "v", "f", "Jn", "Jt", "phi", "mu", "bn", "bt")
    torch.save(
        {name: getattr(problem, name) for name in fields} | {"mode": mode},
        tmp_path / "problem.pt",
    )
    root = Path(__file__).resolve().parents[2]
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "2",
        "PYTHONPATH": os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")])),
    }
    # A hang (MKL spinning on bad pivots) is a failure, not a stuck test run.
    child = subprocess.run(
        [
            sys.executable,
            "-c",
            _CHILD,
            str(tmp_path / "problem.pt"),
            str(tmp_path / "out.pt"),
            str(H),
        ],
        cwd=root,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert child.returncode == 0, child.stderr[-2000:]
    assert "oneMKL ERROR" not in child.stderr, child.stderr[-2000:]
    out = torch.load(tmp_path / "out.pt")
    assert bool(out["converged"].all())
    # cond(C M⁻¹ Cᵀ) is about 2·10³ here: 1e-9 relative leaves three digits of margin over
    # float64 rounding amplified by it.
    scale = reference.abs().amax()
    torch.testing.assert_close(out["v_next"], reference, rtol=0.0, atol=1e-9 * float(scale))
    torch.testing.assert_close(out["v_next_single"], reference, rtol=0.0, atol=1e-9 * float(scale))


def test_matrix_by_matrix_factorization_solves_and_differentiates_like_the_inverse() -> None:
    """At the order from which batches are factored one matrix at a time, on a ``(2, 2)``
    batch: the iterate and its gradients against ``x = A⁻¹ b``, ``∂L/∂b = A⁻ᵀ g`` and
    ``∂L/∂A = −A⁻ᵀ g xᵀ`` for ``L = Σ g·x`` (NumPy inverses, one matrix at a time)."""
    m = LU_SEQUENTIAL_MIN_ORDER
    gen = torch.Generator().manual_seed(3)
    A = (torch.randn(2, 2, m, m, generator=gen, dtype=torch.float64) / m**0.5).add(
        3.0 * torch.eye(m, dtype=torch.float64)
    )
    b = torch.randn(2, 2, m, 1, generator=gen, dtype=torch.float64)
    g = torch.randn(2, 2, m, 1, generator=gen, dtype=torch.float64)
    A.requires_grad_(True)
    b.requires_grad_(True)
    shift = torch.full((2, 2, m), 1e-8, dtype=torch.float64)
    x = iterated_tikhonov(tikhonov_system(A, shift), b, refinements=4)
    grad_A, grad_b = torch.autograd.grad((g * x).sum(), (A, b))

    inverse = torch.from_numpy(np.linalg.inv(A.detach().numpy()))  # stacked: one at a time
    x_ref = inverse @ b.detach()
    grad_b_ref = inverse.mT @ g
    # cond(A) is below 10 and the shift's error shrinks by 1e-8 an iteration: rounding only.
    torch.testing.assert_close(x, x_ref, rtol=0.0, atol=1e-12)
    torch.testing.assert_close(grad_b, grad_b_ref, rtol=0.0, atol=1e-12)
    torch.testing.assert_close(grad_A, -grad_b_ref @ x_ref.mT, rtol=0.0, atol=1e-12)
