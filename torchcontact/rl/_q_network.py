"""A Q-network on belief features: a QMDP head plus a learned residual."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from torchcontact._checks import FLOAT_DTYPES, all_finite, check_float, check_int


class QNetwork(nn.Module):
    r"""Action values from a belief feature vector, ``Q(x, ·) = p @ T + g(x)``.

    The input ``x = (p, z)`` starts with a probability vector ``p`` over ``K`` discrete
    (manipulation) states, followed by ``F`` other features ``z`` (pose mean, covariance
    entries, entropy, effective sample size …). The output is the sum of

    * a linear **QMDP head** ``p @ T`` with a ``(K, A)`` parameter table ``T``
      (:attr:`table`): with ``T`` a tabular Q function this is exactly
      :func:`qmdp_values`;
    * an **MLP residual** ``g`` (:attr:`residual`) on all ``K + F`` features, or on the ``F``
      other features alone (``residual_on_probabilities=False``: with many states, the
      compact summary of the belief generalizes from fewer samples), whose last layer starts
      at zero, so a fresh network equals its QMDP head and learning only adds what the
      belief's other features explain. :meth:`residual_values` returns ``g(x)`` alone, e.g.
      for a trust-region penalty that keeps the network near QMDP. With ``gate`` the
      residual is multiplied by one of the other features, ``g(x) = z_gate · MLP(x)``: a 0/1
      feature (e.g. a blind camera) confines the learned correction to where it is 1.

    Args:
        num_states: ``K >= 1``, the length of the probability part of the input.
        num_features: ``F >= 0``, the number of other features.
        num_actions: ``A >= 1``.
        hidden: widths of the residual's hidden layers (``()`` makes it linear).
        activation: factory of the hidden activation module.
        residual_on_probabilities: whether the residual reads the probabilities too (else
            only the ``F >= 1`` other features).
        gate: index in ``[0, F)`` of the other feature that multiplies the residual; None
            for none.
        dtype: parameter dtype (default: torch's default dtype).
        device: parameter device.

    Raises:
        ValueError: a size is out of range or ``dtype`` is not float32 or float64.
    """

    def __init__(
        self,
        num_states: int,
        num_features: int,
        num_actions: int,
        hidden: Sequence[int] = (64, 64),
        *,
        activation: Callable[[], nn.Module] = nn.ReLU,
        residual_on_probabilities: bool = True,
        gate: int | None = None,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        self.num_states = check_int("num_states", num_states, low=1)
        self.num_features = check_int("num_features", num_features, low=0)
        self.num_actions = check_int("num_actions", num_actions, low=1)
        if not isinstance(residual_on_probabilities, bool):
            raise ValueError(
                f"residual_on_probabilities must be a bool, got {residual_on_probabilities!r}"
            )
        if not residual_on_probabilities and self.num_features == 0:
            raise ValueError("num_features must be >= 1 when the residual skips the probabilities")
        self.residual_on_probabilities = residual_on_probabilities
        if gate is not None:
            check_int("gate", gate, low=0, high=self.num_features)
        self.gate = gate
        if isinstance(hidden, (str, bytes)) or not isinstance(hidden, Sequence):
            raise ValueError(f"hidden must be a sequence of ints, got {hidden!r}")
        widths = [check_int("hidden", width, low=1) for width in hidden]
        if dtype is not None and dtype not in FLOAT_DTYPES:
            raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
        factory: dict[str, Any] = {"dtype": dtype, "device": device}
        self.table = nn.Parameter(torch.zeros(self.num_states, self.num_actions, **factory))
        layers: list[nn.Module] = []
        size = self.num_features + (self.num_states if residual_on_probabilities else 0)
        for width in widths:
            layers += [nn.Linear(size, width, **factory), activation()]
            size = width
        last = nn.Linear(size, self.num_actions, **factory)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.residual = nn.Sequential(*layers, last)

    @classmethod
    def from_table(
        cls,
        q_table: Tensor,
        num_features: int,
        hidden: Sequence[int] = (64, 64),
        *,
        activation: Callable[[], nn.Module] = nn.ReLU,
        residual_on_probabilities: bool = True,
        gate: int | None = None,
    ) -> QNetwork:
        """A network whose QMDP head is ``q_table``: at creation it returns exactly
        :func:`qmdp_values` ``(q_table, p)``.

        Args:
            q_table: ``(K, A)`` Q values of the discrete states (e.g.
                :meth:`DynaQ.q_table`); gives the network's dtype and device.
            num_features: ``F >= 0``, the number of features after the probabilities.
            hidden: widths of the residual's hidden layers.
            activation: factory of the hidden activation module.
            residual_on_probabilities: whether the residual reads the probabilities too.
            gate: index of the other feature that multiplies the residual; None for none.

        Raises:
            ValueError: ``q_table`` is not a finite ``(K, A)`` floating tensor.
        """
        q_table = check_float("q_table", q_table, min_ndim=2, what="(K, A)")
        if q_table.ndim != 2 or q_table.dtype not in (torch.float32, torch.float64):
            raise ValueError(
                f"q_table must be a (K, A) float32/float64 tensor, got {tuple(q_table.shape)} "
                f"{q_table.dtype}"
            )
        K, A = q_table.shape
        network = cls(
            K,
            num_features,
            A,
            hidden,
            activation=activation,
            residual_on_probabilities=residual_on_probabilities,
            gate=gate,
            dtype=q_table.dtype,
            device=q_table.device,
        )
        with torch.no_grad():
            network.table.copy_(q_table)
        return network

    @property
    def input_size(self) -> int:
        """``K + F``, the length of the feature vector."""
        return self.num_states + self.num_features

    def forward(self, features: Tensor) -> Tensor:
        """Action values.

        Args:
            features: ``(*B, K + F)`` belief features, probabilities first; the network's
                dtype and device.

        Returns:
            ``(*B, A)`` action values.

        Raises:
            ValueError: ``features`` has the wrong size, dtype or device, or holds NaN or inf.
        """
        features = self._check("features", features, self.input_size)
        residual = self.residual_values(features, check=False)
        return self.qmdp(features[..., : self.num_states], check=False) + residual

    def residual_values(self, features: Tensor, *, check: bool = True) -> Tensor:
        """The residual ``g(x)`` alone (the network's values less its QMDP head).

        Args:
            features: ``(*B, K + F)`` belief features, probabilities first.
            check: validate the input (shape, dtype, device, finiteness).

        Returns:
            ``(*B, A)`` values.
        """
        if check:
            features = self._check("features", features, self.input_size)
        inputs = features if self.residual_on_probabilities else features[..., self.num_states :]
        values: Tensor = self.residual(inputs)
        if self.gate is not None:
            values = features[..., self.num_states + self.gate, None] * values
        return values

    def qmdp(self, probabilities: Tensor, *, check: bool = True) -> Tensor:
        """The QMDP head alone, ``p @ T``.

        Args:
            probabilities: ``(*B, K)`` belief over the discrete states.
            check: validate the input (shape, dtype, device, finiteness).

        Returns:
            ``(*B, A)`` values.
        """
        if check:
            probabilities = self._check("probabilities", probabilities, self.num_states)
        values: Tensor = torch.matmul(probabilities.unsqueeze(-2), self.table).squeeze(-2)
        return values

    def _check(self, name: str, value: Tensor, size: int) -> Tensor:
        if not isinstance(value, Tensor) or value.dtype not in FLOAT_DTYPES:
            got = value.dtype if isinstance(value, Tensor) else type(value).__name__
            raise ValueError(f"{name} must be a floating tensor, got {got}")
        if value.ndim < 1 or value.shape[-1] != size:
            raise ValueError(f"{name} must have shape (*B, {size}), got {tuple(value.shape)}")
        if value.dtype != self.table.dtype or value.device != self.table.device:
            raise ValueError(
                f"{name} must have dtype {self.table.dtype} on {self.table.device}, "
                f"got {value.dtype} on {value.device}"
            )
        if not all_finite(value):
            raise ValueError(f"{name} contains NaN or inf")
        return value

    def extra_repr(self) -> str:
        return (
            f"num_states={self.num_states}, num_features={self.num_features}, "
            f"num_actions={self.num_actions}, "
            f"residual_on_probabilities={self.residual_on_probabilities}"
        )
