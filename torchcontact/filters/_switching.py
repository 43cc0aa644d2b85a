"""Linear-Gaussian switching (jump Markov linear) models."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import torch
from torch import Tensor

from torchcontact._checks import FLOAT_DTYPES, check_symmetric_psd, describe


@dataclass(frozen=True, eq=False, kw_only=True)
class LinearSwitchingModel:
    r"""A jump Markov linear system with ``K`` discrete modes (e.g. contact states).

    With the mode :math:`m_t \in \{0, \dots, K-1\}` a Markov chain and the continuous state
    :math:`x_t \in \mathbb R^n` linear-Gaussian given the mode:

    .. math::

        m_0 &\sim \mathrm{initial}, \qquad
        P(m_t = j \mid m_{t-1} = i, u_t = a) = \mathrm{transition}[a, i, j] \\
        x_t &= F_{m_t} x_{t-1} + c_{m_t} + w_t, \quad w_t \sim N(0, Q_{m_t}) \\
        y_t &= H_{m_t} x_t + d_{m_t} + v_t, \quad v_t \sim N(0, R_{m_t})

    (``x_0`` is the filter's prior, independent of ``m_0``). Fields are keyword-only.

    Attributes:
        F: ``(K, n, n)`` per-mode state transition matrix.
        c: ``(K, n)`` per-mode known offset (e.g. gravity / control term of the step).
        Q: ``(K, n, n)`` per-mode process noise covariance, symmetric PSD.
        H: ``(K, m, n)`` per-mode measurement matrix.
        d: ``(K, m)`` per-mode measurement offset.
        R: ``(K, m, m)`` per-mode measurement noise covariance, symmetric positive definite.
        transition: ``(K, K)`` row-stochastic mode transition matrix (row = from, column =
            to), or ``(A, K, K)``: one matrix per action, selected by the filter's ``u``.
        initial: ``(K,)`` distribution of the mode ``m_0`` before the first step.

    All fields share one floating dtype and device and are validated at construction
    (shapes, finiteness, symmetry, semi-definiteness, stochasticity); failures raise
    ``ValueError`` naming the field. Gradients flow to every field through the filters.
    """

    F: Tensor
    c: Tensor
    Q: Tensor
    H: Tensor
    d: Tensor
    R: Tensor
    transition: Tensor
    initial: Tensor

    def __post_init__(self) -> None:
        F = self.F
        if not isinstance(F, Tensor) or F.dtype not in FLOAT_DTYPES or F.ndim != 3:
            raise ValueError(
                f"F: expected a float32 or float64 (K, n, n) tensor, got {describe(F)}"
            )
        K, n = int(F.shape[0]), int(F.shape[1])
        if K < 1 or n < 1 or F.shape[2] != n:
            raise ValueError(f"F: expected shape (K, n, n) with K, n >= 1, got {tuple(F.shape)}")
        H = self.H
        if not isinstance(H, Tensor) or H.ndim != 3:
            raise ValueError(f"H: expected a (K, m, n) tensor, got {describe(H)}")
        m = int(H.shape[1])
        shapes: dict[str, tuple[tuple[int, ...], ...]] = {
            "c": ((K, n),),
            "Q": ((K, n, n),),
            "H": ((K, m, n),),
            "d": ((K, m),),
            "R": ((K, m, m),),
            "transition": ((K, K), (-1, K, K)),
            "initial": ((K,),),
        }
        for name, allowed in shapes.items():
            value = getattr(self, name)
            if not isinstance(value, Tensor):
                raise ValueError(f"{name}: expected a torch.Tensor, got {describe(value)}")
            if value.dtype != F.dtype or value.device != F.device:
                raise ValueError(
                    f"{name}: expected dtype {F.dtype} on {F.device} (as F), got "
                    f"{value.dtype} on {value.device}"
                )
            if not any(_shape_matches(value.shape, shape) for shape in allowed):
                expected = " or ".join(str(s).replace("-1", "A") for s in allowed)
                raise ValueError(f"{name}: expected shape {expected}, got {tuple(value.shape)}")
        if m < 1:
            raise ValueError(f"H: expected m >= 1 measurement rows, got {tuple(H.shape)}")
        for f in fields(self):
            if not bool(torch.isfinite(getattr(self, f.name)).all()):
                raise ValueError(f"{f.name}: contains NaN or inf")
        check_symmetric_psd("Q", self.Q)
        check_symmetric_psd("R", self.R, definite=True)
        tol = max(1e-6, 8 * K * torch.finfo(F.dtype).eps)
        for name, probs in (("transition", self.transition.detach()), ("initial", self.initial)):
            probs = probs.detach()
            if bool((probs < 0).any()):
                raise ValueError(f"{name}: probabilities must be >= 0")
            err = float((probs.sum(-1) - 1).abs().max())
            if err > tol:
                raise ValueError(f"{name}: rows must sum to 1 (largest error {err:.3g})")

    @property
    def num_modes(self) -> int:
        """Number of discrete modes ``K``."""
        return int(self.F.shape[0])

    @property
    def state_dim(self) -> int:
        """State size ``n``."""
        return int(self.F.shape[1])

    @property
    def obs_dim(self) -> int:
        """Measurement size ``m``."""
        return int(self.H.shape[1])

    @property
    def num_actions(self) -> int | None:
        """Number of actions ``A`` of an action-dependent transition, else None."""
        return int(self.transition.shape[0]) if self.transition.ndim == 3 else None

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of every field."""
        return self.F.dtype

    @property
    def device(self) -> torch.device:
        """Device of every field."""
        return self.F.device

    def mode_dynamics(self, belief: object, control: object = None) -> ModeDynamics:
        """The per-mode dynamics and measurement of a step: the model's own (constant) fields.

        Args:
            belief: the belief being propagated (unused: the model is linear).
            control: must be None (the model has no control input besides the action that
                selects the transition).

        Returns:
            A :class:`ModeDynamics` without batch dims.
        """
        del belief
        if control is not None:
            raise ValueError("control: a LinearSwitchingModel takes no control input; pass None")
        return ModeDynamics(F=self.F, c=self.c, Q=self.Q, H=self.H, d=self.d, R=self.R)

    def to(self, *args: Any, **kwargs: Any) -> LinearSwitchingModel:
        """``Tensor.to`` applied to every field."""
        return LinearSwitchingModel(
            **{f.name: getattr(self, f.name).to(*args, **kwargs) for f in fields(self)}
        )


@dataclass(frozen=True, eq=False, kw_only=True)
class ModeDynamics:
    r"""Per-mode linear-Gaussian dynamics and measurement of one filter step.

    For mode :math:`k`: :math:`x_t = F_k x_{t-1} + c_k + w`, :math:`w \sim N(0, Q_k)`, and
    :math:`y_t = H_k x_t + d_k + v`, :math:`v \sim N(0, R_k)`. A
    :class:`LinearSwitchingModel` has constant dynamics; a nonlinear model (e.g.
    :class:`~torchcontact.filters.PlanarContactModel`) linearizes its dynamics at every step,
    with leading batch dims ``*B'`` (broadcastable to the belief's batch) where the
    linearization differs between batch entries. Fields are not validated here: the RBPF
    checks their shapes and finiteness when it uses them.

    Attributes:
        F: ``(*B', K, n, n)``.
        c: ``(*B', K, n)``.
        Q: ``(*B', K, n, n)`` symmetric PSD.
        H: ``(*B', K, m, n)``.
        d: ``(*B', K, m)``.
        R: ``(*B', K, m, m)`` symmetric positive definite.
        mode_log_weight: optional ``(*B', K)`` log-weight added to every particle that takes
            mode ``k`` in this step, like the step's ``extra_log_likelihood`` (e.g. the
            contact model's penalty on modes that are physically inconsistent at the
            linearization point); ``-inf`` rules a mode out.
        particle_log_weight: optional ``(*B', N, K)`` log-weight added to particle ``i``
            when it takes mode ``k`` in this step, on top of ``mode_log_weight`` (e.g. the
            spatial contact model's penalty on a mode whose contacts a particle's own state
            contradicts); ``-inf`` rules the mode out for that particle. Unlike
            ``transition_rows`` it is not normalized: a particle every mode of which is
            penalized loses weight against the others.
        transition_rows: optional ``(*B', N, K)`` per-particle mode transition of this step,
            ``p(m_t = k | particle i)``, each row non-negative and summing to 1. It replaces the
            row of the model's transition matrix that particle ``i``'s mode would select: for
            a model whose mode transition depends on each particle's continuous state (e.g. a
            manipulation graph over pose cells × contact states).
        origin: ``(*B', n)`` for a model on a manifold (its ``manifold`` attribute, e.g.
            :data:`~torchcontact.filters.SE3`): the point in whose tangent the dynamics read
            the particles' states, :math:`\delta_i = \mathrm{local}(\mathrm{origin}, \mu_i)`
            (their covariances are taken as they are, first order). ``F, c, Q`` then act on
            ``d``-dim tangent vectors, and the predicted mean is
            :math:`\mathrm{retract}(\mathrm{chart}, F_k \delta_i + c_k)`.
        chart: ``(*B', n)``: the point in whose tangent the dynamics predict and the
            measurement reads the state (required with ``origin``).
        measurement_chart: ``(*B', m)`` for a model whose measurement lies on a manifold (its
            ``measurement_manifold`` attribute): the measurement enters the update as
            :math:`\mathrm{local}(\mathrm{measurement\_chart}, y)`, a vector of the
            measurement's tangent dimension that ``H, d, R`` describe.
    """

    F: Tensor
    c: Tensor
    Q: Tensor
    H: Tensor
    d: Tensor
    R: Tensor
    mode_log_weight: Tensor | None = None
    particle_log_weight: Tensor | None = None
    transition_rows: Tensor | None = None
    origin: Tensor | None = None
    chart: Tensor | None = None
    measurement_chart: Tensor | None = None


def _shape_matches(shape: torch.Size, expected: tuple[int, ...]) -> bool:
    return len(shape) == len(expected) and all(
        e == -1 or s == e for s, e in zip(shape, expected, strict=True)
    )
