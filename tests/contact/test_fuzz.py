"""Property tests of the contact entry points: right answers at every scale, or a ValueError.

The LCP conditions are checked by :func:`check_lcp`, a slow NumPy checker written here that
shares no code with the library. Its tolerances are relative to the problem's own scales:
impulses to the largest of ``|M v|``, ``|h f|`` and the largest impulse, constraint velocities
to the largest free constraint velocity, penetration rate ``-φ/h`` or velocity change the
impulses cause. A solver that reports ``converged`` must pass it whatever the units.
"""

from __future__ import annotations

import math
from dataclasses import replace
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


# --- bad inputs: a ValueError naming the argument, never another exception ----------------

_FIELDS = ("M", "v", "f", "Jn", "Jt", "phi", "mu", "bn", "bt")


def _spoil(value: torch.Tensor, how: str) -> Any:
    """A damaged copy of a field: wrong dtype, NaN/inf, wrong shape, or not a tensor."""
    if how == "nan":
        return value.flatten().index_fill(0, torch.tensor([0]), math.nan).reshape(value.shape)
    if how == "inf":
        return value.flatten().index_fill(0, torch.tensor([0]), math.inf).reshape(value.shape)
    if how == "shape":
        return value[..., :-1] if value.shape[-1] > 1 else value.unsqueeze(-1).repeat(1, 2)
    if how == "list":
        return value.tolist()
    return value.to(
        {
            "int": torch.long,
            "half": torch.float16,
            "complex": torch.complex128,
            "f32": torch.float32,
        }[how]
    )


@FUZZ
@given(
    seed=st.integers(0, 2**32 - 1),
    field=st.sampled_from(_FIELDS),
    how=st.sampled_from(["nan", "inf", "shape", "list", "int", "half", "complex", "f32"]),
)
def test_contact_problem_names_a_bad_field(seed: int, field: str, how: str) -> None:
    data = _box_data(seed, log_h=-2.0, log_mass=0.0, log_speed=0.0, slots=2)
    fields = {k: torch.tensor(v, dtype=torch.float64) for k, v in data.items() if k in _FIELDS}
    if how == "shape" and fields[field].dim() == 1 and fields[field].shape[0] == 2:
        fields[field] = fields[field][:1]  # (K,) fields: a wrong K
    else:
        fields[field] = _spoil(fields[field], how)
    with pytest.raises(ValueError, match=rf"^{field}\b"):
        ContactProblem(h=data["h"], mask=torch.tensor(data["mask"]), **fields)


@FUZZ
@given(
    h=st.one_of(st.floats(max_value=0.0), st.sampled_from([math.nan, math.inf, True, "0.1"])),
    mass=st.floats(-1e6, 0.0),
    mu=st.floats(-1.0, -1e-12),
)
def test_negative_physical_parameters_are_named(h: Any, mass: float, mu: float) -> None:
    data = _box_data(0, log_h=-2.0, log_mass=0.0, log_speed=0.0, slots=2)
    with pytest.raises(ValueError, match=r"^h\b"):
        _problem(data | {"h": h})
    with pytest.raises(ValueError, match=r"^M\b"):  # not positive definite
        _problem(data | {"M": np.diag([mass, 1.0, 1.0])})
    with pytest.raises(ValueError, match=r"^mu\b"):
        _problem(data | {"mu": np.array([mu, 0.5])})
    with pytest.raises(ValueError, match=r"^M\b"):  # not symmetric
        _problem(data | {"M": np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])})


@FUZZ
@given(
    seed=st.integers(0, 2**32 - 1),
    bad=st.one_of(
        st.integers(-5, -1),
        st.integers(4, 9),
    ),
    shape=st.sampled_from(["ok", "short", "float", "bool"]),
)
def test_solve_mode_and_is_consistent_name_bad_modes(seed: int, bad: int, shape: str) -> None:
    problem = _problem(_box_data(seed, log_h=-2.0, log_mass=0.0, log_speed=0.0, slots=2))
    mode = torch.full((2,), bad)
    if shape == "short":
        mode = torch.zeros(3, dtype=torch.long)
    elif shape == "float":
        mode = mode.double()
    elif shape == "bool":
        mode = mode > 0
    with pytest.raises(ValueError, match=r"^mode"):
        solve_mode(problem, mode)
    good = solve(problem, "lemke")
    with pytest.raises(ValueError, match=r"^solution.mode"):
        is_consistent(problem, replace(good, mode=mode))
    with pytest.raises(ValueError, match=r"^solution.pn"):
        is_consistent(problem, replace(good, pn=good.pn.float()))
    with pytest.raises(ValueError, match=r"^solution\b"):
        is_consistent(problem, good.pn)  # type: ignore[arg-type]


@pytest.mark.parametrize("method", ["lemke", "pgs", "qp"])
@pytest.mark.parametrize("batch", [(0,), (3,), (2, 0)])
@pytest.mark.parametrize("slots", [0, 2])
def test_empty_batches_and_no_slots_give_free_motion(
    method: str, batch: tuple[int, ...], slots: int
) -> None:
    """K = 0 is free motion, v⁺ = v + h M⁻¹ f (closed form); empty batches, empty results."""
    rng = np.random.default_rng(0)
    A = rng.normal(size=(3, 3))
    M = A @ A.T + 3.0 * np.eye(3)
    v, f, h = rng.normal(size=3), rng.normal(size=3), 0.05

    def t(x: np.ndarray) -> torch.Tensor:
        return torch.tensor(x, dtype=torch.float64)

    K = 0 if slots == 0 else slots
    problem = ContactProblem(
        M=t(M).expand(*batch, 3, 3),
        v=t(v).expand(*batch, 3),
        f=t(f),
        Jn=torch.zeros(K, 3, dtype=torch.float64),
        Jt=torch.zeros(K, 2, 3, dtype=torch.float64),
        phi=torch.ones(K, dtype=torch.float64),
        mu=torch.zeros(K, dtype=torch.float64),
        h=h,
    )
    solution = solve(problem, method)  # type: ignore[arg-type]
    assert solution.v_next.shape == (*batch, 3)
    assert solution.pn.shape == (*batch, K)
    assert solution.pt.shape == (*batch, K, 2)
    assert solution.status.converged.shape == batch
    assert bool(solution.status.converged.all())
    expected = v + h * np.linalg.solve(M, f)
    np.testing.assert_allclose(
        solution.v_next.reshape(-1, 3).numpy(),
        np.broadcast_to(expected, (math.prod(batch), 3)),
        rtol=1e-12,
        atol=1e-12,
    )
    again = solve_mode(problem, torch.zeros(*batch, K, dtype=torch.long))
    assert again.v_next.shape == (*batch, 3)
    assert is_consistent(problem, solution).shape == batch


def test_planar_box_problem_batch_zero_and_bad_arguments() -> None:
    empty = torch.zeros(0, 3, dtype=torch.float64)
    assert planar_box_problem(q=empty, v=empty).batch_shape == (0,)
    q = torch.zeros(1, 3, dtype=torch.float64)
    for kwargs, name in (
        ({"q": q.half(), "v": q}, "q"),
        ({"q": q, "v": q.float()}, "v"),
        ({"q": q, "v": q, "mass": -1.0}, "mass"),
        ({"q": q, "v": q, "mu": -0.1}, "mu"),
        ({"q": q, "v": q, "h": 0.0}, "h"),
        ({"q": q, "v": q, "corners": (0, 7)}, r"corners\[1\]"),
    ):
        with pytest.raises(ValueError, match=rf"^{name}"):
            planar_box_problem(**kwargs)  # type: ignore[arg-type]


def test_solver_options_are_checked() -> None:
    problem = _problem(_box_data(0, log_h=-2.0, log_mass=0.0, log_speed=0.0, slots=2))
    for method, options, name in (
        ("lemke", {"max_pivots": 0}, "max_pivots"),
        ("pgs", {"max_sweeps": 0}, "max_sweeps"),
        ("pgs", {"tol": -1.0}, "tol"),
        ("qp", {"max_rounds": 1.5}, "max_rounds"),
        ("lemke", {"max_sweeps": 3}, "options"),
        ("newton", {}, "method"),
    ):
        with pytest.raises(ValueError, match=rf"^{name}"):
            solve(problem, method, **options)  # type: ignore[arg-type]
