"""The time-stepped contact problem: one batched Stewart–Trinkle step."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar, cast

import torch
from torch import Tensor

from torchcontact._checks import (
    FLOAT_DTYPES,
    all_finite,
    broadcast_batch,
    check_positive,
    describe,
)
from torchcontact.contact._tikhonov import ELIMINATION_MAX_ORDER, solve_by_elimination

_T = TypeVar("_T")

_TENSOR_FIELDS = ("M", "v", "f", "Jn", "Jt", "phi", "mu", "mask", "bn", "bt")
#: Number of trailing (non-batch) dimensions of each tensor field.
_TRAILING_DIMS = {
    "M": 2, "v": 1, "f": 1, "Jn": 2, "Jt": 3, "phi": 1, "mu": 1, "mask": 1, "bn": 1, "bt": 2,
}  # fmt: skip


@dataclass(frozen=True, eq=False)
class ContactProblem:
    r"""One time step of rigid-body contact dynamics, batched over leading dimensions ``*B``.

    The step is the velocity-level time-stepping scheme of Stewart and Trinkle (1996) with a
    polyhedral friction cone of ``D`` directions and the Anitescu–Potra gap stabilisation:

    .. math::

        M (v^+ - v) &= h f + J_n^\top p_n + J_t^\top p_t \\
        0 \le p_n &\perp J_n v^+ + b_n + \phi / h \ge 0 \\
        0 \le p_t &\perp J_t v^+ + b_t + E \sigma \ge 0 \\
        0 \le \sigma &\perp \mu p_n - E^\top p_t \ge 0

    where :math:`p_n, p_t` are impulses over the step, :math:`\sigma` is the sliding speed of
    each contact and :math:`E` repeats a per-contact scalar over its ``D`` directions.

    Friction directions follow one convention so that planar and spatial scenes share every
    solver: ``D`` is even, direction ``d + D/2`` is the opposite of direction ``d`` (rows of
    ``Jt`` and entries of ``bt``), and the directions are ordered by angle around the normal.
    ``D == 2`` is the planar case (``+t``, ``-t``); ``D >= 4`` is spatial, with the tangent
    plane spanned by directions 0 and 1.

    Fields (``n`` generalized velocities, ``K`` contact slots, ``D`` friction directions):

    Attributes:
        M: ``(*B, n, n)`` mass matrix, symmetric positive definite.
        v: ``(*B, n)`` generalized velocity at the start of the step.
        f: ``(*B, n)`` non-contact generalized force (gravity, applied forces).
        Jn: ``(*B, K, n)`` normal rows: the gap rate of slot ``k`` is ``Jn[k] @ v + bn[k]``.
        Jt: ``(*B, K, D, n)`` friction-direction rows (relative tangential velocity).
        phi: ``(*B, K)`` signed gap at the start of the step, ``>= 0`` when separated.
        mu: ``(*B, K)`` Coulomb friction coefficient, ``>= 0``.
        mask: ``(*B, K)`` bool, ``True`` where the slot is a real contact candidate.
        h: time step in seconds, ``> 0``.
        bn: ``(*B, K)`` known normal velocity of kinematically driven bodies (zero if none).
        bt: ``(*B, K, D)`` known tangential velocity of kinematically driven bodies.

    Fields are broadcast to a common batch shape at construction. Construction validates
    every field and raises ``ValueError`` naming the field at fault.

    References:
        D. E. Stewart and J. C. Trinkle, "An implicit time-stepping scheme for rigid body
        dynamics with inelastic collisions and Coulomb friction", IJNME 39(15), 1996.
        M. Anitescu and F. A. Potra, "Formulating dynamic multi-rigid-body contact problems
        with friction as solvable linear complementarity problems", Nonlinear Dyn. 14, 1997.
    """

    M: Tensor
    v: Tensor
    f: Tensor
    Jn: Tensor
    Jt: Tensor
    phi: Tensor
    mu: Tensor
    h: float
    mask: Tensor | None = None
    bn: Tensor | None = None
    bt: Tensor | None = None

    def __post_init__(self) -> None:
        _validate_and_broadcast(self)

    # The optional fields are always tensors after construction; these accessors say so.
    @property
    def slot_mask(self) -> Tensor:
        """``(*B, K)`` bool mask of real contact slots."""
        assert self.mask is not None
        return self.mask

    @property
    def b_normal(self) -> Tensor:
        """``(*B, K)`` known normal velocity term ``bn``."""
        assert self.bn is not None
        return self.bn

    @property
    def b_tangent(self) -> Tensor:
        """``(*B, K, D)`` known tangential velocity term ``bt``."""
        assert self.bt is not None
        return self.bt

    @property
    def batch_shape(self) -> torch.Size:
        """The leading batch shape ``*B``."""
        return self.M.shape[:-2]

    @property
    def num_dofs(self) -> int:
        """``n``, the number of generalized velocities."""
        return self.M.shape[-1]

    @property
    def num_slots(self) -> int:
        """``K``, the number of contact slots."""
        return self.Jn.shape[-2]

    @property
    def num_directions(self) -> int:
        """``D``, the number of friction directions per contact."""
        return self.Jt.shape[-2]

    @property
    def num_tangents(self) -> int:
        """Dimension of the tangent space: 1 for planar (``D == 2``), 2 for spatial."""
        return 1 if self.num_directions == 2 else 2

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype shared by all fields."""
        return self.M.dtype

    @property
    def device(self) -> torch.device:
        """Device shared by all fields."""
        return self.M.device

    def v_free(self) -> Tensor:
        """``(*B, n)`` contact-free velocity ``v + h M⁻¹ f`` (Cholesky solve; computed once
        per problem where no field requires grad)."""
        return self.cached(
            "v_free", lambda: self.v + self.h * self.mass_solve(self.f.unsqueeze(-1)).squeeze(-1)
        )

    def cached(self, name: str, compute: Callable[[], _T]) -> _T:
        """``compute()``, kept on the problem under ``name`` and returned again on later calls.

        For derived quantities that several steps of a solve need (the Cholesky factor of
        ``M``, ``v_free``, the constraint velocities at ``v_free``). A problem is immutable, so
        they stay valid; they are kept only where no field requires grad (a graph kept on
        the problem would be freed by the first backward pass through it) and outside
        :func:`torch.compile`'s tracing.

        Args:
            name: the quantity's key, one per ``compute``.
            compute: computes it from the problem's fields.
        """
        if torch.compiler.is_compiling() or any(
            getattr(self, field).requires_grad for field in _TENSOR_FIELDS
        ):
            return compute()
        cache = self.__dict__.get("_cache")
        if cache is None:
            cache = {}
            object.__setattr__(self, "_cache", cache)
        if name not in cache:
            cache[name] = compute()
        return cast(_T, cache[name])

    def cached_at(self, name: str, inputs: tuple[Tensor, ...], compute: Callable[[], _T]) -> _T:
        """``compute()`` of a candidate solution's ``inputs``, kept while the same are passed.

        For quantities at one solution that several checks read (the constraint velocities at
        ``v⁺``, the problem's scales at ``(v⁺, pn, pt)``): one entry per ``name``, replaced
        when other inputs come. Inputs are the same when they are views of the same memory
        with the same layout and version (a detached or reshaped solution is the same); the
        entry keeps them referenced, so their memory cannot be reused meanwhile. Nothing is
        kept where :meth:`cached` keeps nothing (inside :func:`torch.compile`'s tracing, the
        memory of a traced tensor is not known), an input requires grad, or an input has no
        memory or version of its own (an inference tensor, a tensor inside a
        :mod:`torch.func` transform).

        Args:
            name: the quantity's key, one per ``compute``.
            inputs: the tensors ``compute`` reads besides the problem's fields.
            compute: computes it.
        """
        if (
            torch.compiler.is_compiling()
            or any(t.is_inference() for t in inputs)
            or (torch.is_grad_enabled() and any(t.requires_grad for t in inputs))
        ):
            return compute()
        try:
            key: tuple[object, ...] = tuple(
                (t.untyped_storage().data_ptr(), t.storage_offset(), t.stride(), t._version)
                for t in inputs
            )
            key += tuple((t.shape, t.dtype) for t in inputs)
        except NotImplementedError:  # torch.func's wrapped tensors have no storage
            return compute()
        entry: dict[str, Any] = self.cached(f"{name} at", dict)
        if entry.get("key") != key:
            entry.update(key=key, inputs=inputs, value=compute())
        return cast(_T, entry["value"])

    def mass_solve(self, rhs: Tensor) -> Tensor:
        """``M⁻¹ rhs`` by Cholesky factorization, differentiable (traced by
        :func:`torch.compile` without gradients, up to ``n = 16``: by Gaussian elimination
        written out).

        A mass matrix shared by the whole batch (a field broadcast from ``(n, n)``, as
        assemblers build it) is factored once and solved with every right-hand side of the
        batch as one block of columns, instead of once per batch entry. Where the problem
        keeps ``M⁻¹`` (:meth:`cached` under ``"mass_inverse"``: an assembler that has it in
        closed form, as the simulator for rigid bodies, ``diag(1/m, R I⁻¹ Rᵀ)``), it is one
        product instead.

        Args:
            rhs: ``(*B, n, k)`` right-hand sides (``*B`` broadcasts to the problem's).

        Returns:
            ``(*B, n, k)``.
        """
        inverse = self.__dict__.get("_cache", {}).get("mass_inverse")
        if inverse is not None:
            return cast(Tensor, inverse @ rhs)
        M, batch = self.M, self.batch_shape
        shared = bool(batch) and 0 not in batch and all(s == 0 for s in M.stride()[: len(batch)])
        # Under torch.compile without gradients a small system is solved by elimination
        # written out, which fuses into the compiled loops (the Cholesky factorization and
        # solve are library calls; with gradients they keep their one-formula backward).
        written_out = (
            torch.compiler.is_compiling()
            and not torch.is_grad_enabled()
            and M.shape[-1] <= ELIMINATION_MAX_ORDER
        )
        if not shared:
            if written_out:
                return solve_by_elimination(M, rhs)
            return torch.cholesky_solve(
                rhs, self.cached("mass_factor", lambda: torch.linalg.cholesky(M))
            )
        rhs = rhs.expand(*batch, *rhs.shape[-2:])
        n, k = rhs.shape[-2:]
        columns = rhs.movedim(-2, 0).reshape(n, -1)
        if written_out:
            solved = solve_by_elimination(M[(0,) * len(batch)], columns)
        else:
            L = self.cached("mass_factor", lambda: torch.linalg.cholesky(M[(0,) * len(batch)]))
            solved = torch.cholesky_solve(columns, L)
        return solved.reshape(n, *batch, k).movedim(0, -2)

    @classmethod
    def unchecked(
        cls,
        *,
        M: Tensor,
        v: Tensor,
        f: Tensor,
        Jn: Tensor,
        Jt: Tensor,
        phi: Tensor,
        mu: Tensor,
        h: float,
        mask: Tensor,
        bn: Tensor,
        bt: Tensor,
    ) -> ContactProblem:
        """A problem from fields that are valid by construction, without validating them.

        For assemblers whose inputs were validated already (a simulator builds its problem
        from a checked state): the fields are only broadcast to their common batch shape.
        Passing anything that the constructor would reject is undefined behaviour.

        Args:
            M, v, f, Jn, Jt, phi, mu, mask, bn, bt: as the attributes, every one given.
            h: time step in seconds, ``> 0``.
        """
        values = {
            "M": M, "v": v, "f": f, "Jn": Jn, "Jt": Jt, "phi": phi,
            "mu": mu, "mask": mask, "bn": bn, "bt": bt,
        }  # fmt: skip
        shapes = {
            name: value.shape[: value.dim() - _TRAILING_DIMS[name]]
            for name, value in values.items()
        }
        # The longest batch shape is usually every field's (or theirs broadcast from nothing):
        # the general broadcast, a Python function, only where it is not.
        batch = torch.Size()
        for shape in shapes.values():  # the first longest (a loop: torch.compile traces it)
            if len(shape) > len(batch):
                batch = shape
        if any(shape and shape != batch for shape in shapes.values()):
            batch = torch.broadcast_shapes(*shapes.values())
        problem = object.__new__(cls)
        for name, value in values.items():
            if shapes[name] != batch:
                tail = value.shape[value.dim() - _TRAILING_DIMS[name] :]
                value = value.expand(*batch, *tail)
            object.__setattr__(problem, name, value)
        object.__setattr__(problem, "h", float(h))
        return problem

    def map_tensors(self, fn: Any) -> ContactProblem:
        """Apply ``fn`` to every tensor field (e.g. indexing, reshaping, casting).

        ``fn`` must preserve validity (batch indexing, reshaping the batch, casting): the
        result is not validated again, which keeps batch bookkeeping off the hot path.
        """
        mapped = object.__new__(ContactProblem)
        for name in _TENSOR_FIELDS:
            object.__setattr__(mapped, name, fn(getattr(self, name)))
        object.__setattr__(mapped, "h", self.h)
        return mapped

    def reshape(self, *batch_shape: int) -> ContactProblem:
        """Return the problem with its batch dimensions reshaped to ``batch_shape`` (itself
        when they have that shape already)."""
        if batch_shape == tuple(self.batch_shape):
            return self
        old = len(self.batch_shape)
        return self.map_tensors(lambda t: t.reshape(*batch_shape, *t.shape[old:]))

    def flatten(self) -> ContactProblem:
        """Return the problem with a single batch dimension ``(prod(*B),)`` (itself when it
        has one: the quantities it keeps, :meth:`cached`, stay with it)."""
        if len(self.batch_shape) == 1:
            return self
        return self.reshape(math.prod(self.batch_shape))

    def __getitem__(self, index: Any) -> ContactProblem:
        """Index the batch dimensions (trailing field dimensions are kept)."""
        return self.map_tensors(lambda t: t[index])

    def to(self, *args: Any, **kwargs: Any) -> ContactProblem:
        """``Tensor.to`` on every field (the bool mask keeps its dtype)."""

        def convert(t: Tensor) -> Tensor:
            if t.dtype == torch.bool:
                return t.to(device=kwargs.get("device", t.device))
            return t.to(*args, **kwargs)

        return self.map_tensors(convert)


def _validate_and_broadcast(problem: ContactProblem) -> None:
    """Check every field of ``problem`` and broadcast them to one batch shape (in place).

    Empty batches and ``K = 0`` slots are legal: every check holds vacuously.
    """
    for name in ("M", "v", "f", "Jn", "Jt", "phi", "mu"):
        value = getattr(problem, name)
        if not isinstance(value, Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
        if value.dtype not in FLOAT_DTYPES:
            raise ValueError(f"{name} must be float32 or float64, got dtype {value.dtype}")
    M = problem.M
    if M.dim() < 2 or M.shape[-1] != M.shape[-2] or M.shape[-1] == 0:
        raise ValueError(f"M must have shape (*B, n, n) with n > 0, got {tuple(M.shape)}")
    n = M.shape[-1]
    if problem.Jn.dim() < 2 or problem.Jn.shape[-1] != n:
        raise ValueError(f"Jn must have shape (*B, K, {n}), got {tuple(problem.Jn.shape)}")
    K = problem.Jn.shape[-2]
    Jt = problem.Jt
    if Jt.dim() < 3 or Jt.shape[-3] != K or Jt.shape[-1] != n:
        raise ValueError(f"Jt must have shape (*B, {K}, D, {n}), got {tuple(Jt.shape)}")
    D = Jt.shape[-2]
    if D < 2 or D % 2:
        raise ValueError(f"Jt must have an even number D >= 2 of friction directions, got {D}")
    h = check_positive("h", problem.h)

    dtype, device = M.dtype, M.device
    mask = problem.mask
    if mask is None:
        mask = torch.ones(problem.phi.shape, dtype=torch.bool, device=device)
    elif not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        raise ValueError(f"mask must be a bool tensor of shape (*B, K), got {describe(mask)}")
    bn = problem.bn if problem.bn is not None else torch.zeros((K,), dtype=dtype, device=device)
    bt = problem.bt if problem.bt is not None else torch.zeros((K, D), dtype=dtype, device=device)

    trailing = {
        "M": (n, n),
        "v": (n,),
        "f": (n,),
        "Jn": (K, n),
        "Jt": (K, D, n),
        "phi": (K,),
        "mu": (K,),
        "mask": (K,),
        "bn": (K,),
        "bt": (K, D),
    }
    values: dict[str, Tensor] = {
        "M": M,
        "v": problem.v,
        "f": problem.f,
        "Jn": problem.Jn,
        "Jt": Jt,
        "phi": problem.phi,
        "mu": problem.mu,
        "mask": mask,
        "bn": bn,
        "bt": bt,
    }
    batch_shapes = []
    for name, value in values.items():
        if not isinstance(value, Tensor):
            raise ValueError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
        tail = trailing[name]
        if value.dim() < len(tail) or tuple(value.shape[value.dim() - len(tail) :]) != tail:
            shape = ", ".join(["*B", *map(str, tail)])
            raise ValueError(f"{name} must have shape ({shape}), got {tuple(value.shape)}")
        if name != "mask":
            if value.dtype != dtype:
                raise ValueError(f"{name} has dtype {value.dtype}, but M has dtype {dtype}")
            if value.numel() and not all_finite(value):
                raise ValueError(f"{name} contains NaN or inf")
        if value.device != device:
            raise ValueError(f"{name} is on {value.device}, but M is on {device}")
        batch_shapes.append((name, value.shape[: value.dim() - len(tail)]))
    batch = broadcast_batch(batch_shapes)

    mu = values["mu"]
    if mu.numel() and bool((mu < 0).any()):
        raise ValueError(f"mu must be >= 0 everywhere, got minimum {float(mu.min())}")
    if M.numel():
        M_sym_error = (M - M.transpose(-1, -2)).abs().amax(dim=(-1, -2))
        M_scale = M.abs().amax(dim=(-1, -2))
        if bool((M_sym_error > 1e-8 * M_scale + torch.finfo(dtype).tiny).any()):
            raise ValueError("M must be symmetric")
        _, info = torch.linalg.cholesky_ex(M)
        if bool((info != 0).any()):
            raise ValueError("M must be positive definite (Cholesky factorization failed)")
    half = D // 2
    for name, value, axis in (("Jt", Jt, -2), ("bt", bt, -1)):
        if value.numel() == 0:
            continue
        first, second = value.split(half, dim=axis)
        scale = 1.0 + value.abs().amax()
        if bool(((first + second).abs() > 1e-6 * scale).any()):
            raise ValueError(
                f"{name}: friction direction d + D/2 must be the opposite of direction d "
                "(rows come in opposite pairs)"
            )

    for name, value in values.items():
        tail = trailing[name]
        object.__setattr__(problem, name, value.expand(*batch, *tail))
    object.__setattr__(problem, "h", h)
