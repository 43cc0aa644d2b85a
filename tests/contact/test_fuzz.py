"""Property tests of the contact entry points: right answers at every scale, or a ValueError.

The LCP conditions are checked by :func:`check_lcp`, a slow NumPy checker written here that
shares no code with the library. Its tolerances are relative to the problem's own scales:
impulses to the largest of ``|M v|``, ``|h f|`` and the largest impulse, constraint velocities
to the largest free constraint velocity, penetration rate ``-φ/h`` or velocity change the
impulses cause. A solver that reports ``converged`` must pass it whatever the units.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchcontact.contact import (
    ContactProblem,
    is_consistent,
    planar_box_problem,
    solve,
    solve_mode,
)

#: Relative tolerance of the checker: the solvers accept 1e-9 (float64), and the test
#: problems' Delassus matrices have condition numbers below 1e3 after scaling.
CHECK_TOL = 1e-6

FUZZ = settings(max_examples=60, deadline=None, derandomize=True)


def _numpy_fields(problem: dict[str, Any]) -> dict[str, np.ndarray]:
    return {k: np.asarray(v, dtype=np.float64) for k, v in problem.items()}


def check_lcp(
    data: dict[str, Any], v_next: np.ndarray, pn: np.ndarray, pt: np.ndarray, tol: float
) -> list[str]:
    """The Stewart–Trinkle conditions a solution violates (empty when it is a solution).

    ``data`` holds one problem (no batch) as NumPy arrays: ``M (n, n)``, ``v, f (n,)``,
    ``Jn (K, n)``, ``Jt (K, D, n)``, ``phi, mu, bn (K,)``, ``bt (K, D)``, ``mask (K,)``, ``h``.
    """
    M, v, f, h = data["M"], data["v"], data["f"], float(data["h"])
    Jn, Jt, phi, mu = data["Jn"], data["Jt"], data["phi"], data["mu"]
    bn, bt, mask = data["bn"], data["bt"], data["mask"].astype(bool)
    violations = []
    if not (np.isfinite(v_next).all() and np.isfinite(pn).all() and np.isfinite(pt).all()):
        return ["non-finite answer"]
    generalized = Jn.T @ pn + np.einsum("kdn,kd->n", Jt, pt)
    v_free = v + h * np.linalg.solve(M, f)
    momentum = max(np.abs(M @ v).max(), np.abs(h * f).max(), np.abs(generalized).max())
    impulse_scale = max(momentum, np.abs(pn).max(initial=0.0), np.abs(pt).max(initial=0.0))
    newton = M @ (v_next - v) - h * f - generalized
    if np.abs(newton).max() > tol * max(momentum, np.abs(M @ v_next).max()):
        violations.append(f"Newton-Euler residual {np.abs(newton).max():.3g}")
    if (np.abs(pn[~mask]).max(initial=0.0) > 0) or (np.abs(pt[~mask]).max(initial=0.0) > 0):
        violations.append("impulse on a padding slot")
    real = np.flatnonzero(mask)
    if real.size == 0:
        return violations
    gap = Jn @ v_next + bn + phi / h
    slip = np.einsum("kdn,n->kd", Jt, v_next) + bt
    free = np.concatenate([Jn @ v_free + bn, (np.einsum("kdn,n->kd", Jt, v_free) + bt).ravel()])
    change = np.concatenate(
        [Jn @ (v_next - v_free), np.einsum("kdn,n->kd", Jt, v_next - v_free).ravel()]
    )
    rows = np.concatenate(
        [real, len(mu) + (real[:, None] * Jt.shape[1] + np.arange(Jt.shape[1])).ravel()]
    )
    velocity_scale = max(
        np.abs(free[rows]).max(),
        np.abs(change[rows]).max(),
        np.abs(np.minimum(phi[real], 0.0) / h).max(),
    )
    P, V = max(impulse_scale, 1e-300), max(velocity_scale, 1e-300)
    for k in real:
        sigma = max(0.0, -slip[k].min())
        cone = mu[k] * pn[k] - pt[k].sum()
        checks = {
            "pn >= 0": pn[k] / P >= -tol,
            "gap rate >= 0": gap[k] / V >= -tol,
            "pn ⊥ gap rate": min(pn[k] / P, gap[k] / V) <= tol,
            "pt >= 0": (pt[k] / P >= -tol).all(),
            "pt ⊥ slip + σ": (np.minimum(pt[k] / P, (slip[k] + sigma) / V) <= tol).all(),
            "friction inside the cone": cone / P >= -tol,
            "σ ⊥ cone": min(sigma / V, cone / P) <= tol,
        }
        violations.extend(f"slot {k}: {name}" for name, ok in checks.items() if not ok)
    return violations


def _box_data(
    seed: int, *, log_h: float, log_mass: float, log_speed: float, slots: int
) -> dict[str, Any]:
    """One random planar box problem at the given scales (NumPy, independent of the library).

    The box (half extents ``a, b``) touches ground ``y = 0`` near ``slots`` of its corners,
    with gaps of either sign; ``h = 10^log_h``, mass ``10^log_mass``, speed ``10^log_speed``.
    """
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(0.1, 2.0, size=2)
    mass = 10.0**log_mass
    inertia = mass * (a * a + b * b) / 3.0
    theta = rng.uniform(-0.3, 0.3)
    corners = np.array([[-a, -b], [a, -b], [a, b], [-a, b]])[:slots]
    rotation = np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    r = corners @ rotation.T
    Jn = np.stack([np.zeros(slots), np.ones(slots), r[:, 0]], axis=-1)
    tangent = np.stack([np.ones(slots), np.zeros(slots), -r[:, 1]], axis=-1)
    speed = 10.0**log_speed
    direction = rng.normal(size=3)
    h = 10.0**log_h
    return {
        "M": np.diag([mass, mass, inertia]),
        "v": speed * direction / np.linalg.norm(direction),
        "f": np.array([0.0, -9.81 * mass, 0.0]) * rng.choice([0.0, 1.0]),
        "Jn": Jn,
        "Jt": np.stack([tangent, -tangent], axis=1),
        "phi": rng.choice([0.0, 1.0], size=slots) * rng.uniform(-1e-3, 1e-2, size=slots),
        "mu": rng.uniform(0.0, 1.0, size=slots),
        "bn": np.zeros(slots),
        "bt": np.zeros((slots, 2)),
        "mask": rng.random(slots) < 0.9,
        "h": h,
    }


def _problem(data: dict[str, Any], dtype: torch.dtype = torch.float64) -> ContactProblem:
    fields = {k: torch.tensor(v, dtype=dtype) for k, v in data.items() if k not in ("h", "mask")}
    return ContactProblem(h=data["h"], mask=torch.tensor(data["mask"]), **fields)


scales = {
    "seed": st.integers(0, 2**32 - 1),
    "log_h": st.floats(-12.0, 0.0),
    "log_mass": st.floats(-6.0, 6.0),
    "log_speed": st.floats(-6.0, 3.0),
    "slots": st.integers(1, 4),
}


@pytest.mark.parametrize("method", ["lemke", "pgs", "qp"])
@FUZZ
@given(**scales)
def test_converged_answers_solve_the_lcp_at_every_scale(
    method: str, seed: int, log_h: float, log_mass: float, log_speed: float, slots: int
) -> None:
    data = _box_data(seed, log_h=log_h, log_mass=log_mass, log_speed=log_speed, slots=slots)
    problem = _problem(data)
    solution = solve(problem, method)  # type: ignore[arg-type]
    if not bool(solution.status.converged):
        # Non-convergence is an honest answer for the iterative solvers; Lemke solves every
        # Stewart–Trinkle LCP with a positive definite M (its matrix is copositive-plus).
        assert method != "lemke", solution.status
        return
    violations = check_lcp(
        _numpy_fields(data) | {"mask": data["mask"]},
        solution.v_next.numpy(),
        solution.pn.numpy(),
        solution.pt.numpy(),
        CHECK_TOL,
    )
    assert not violations, violations
    # The exact solution agrees with its own modes at every scale, too.
    assert method != "lemke" or bool(is_consistent(problem, solution))
