"""The contact models' gate on modes: log-weights of modes that contradict themselves at the
linearization point (shared by :class:`~torchcontact.filters.PlanarContactModel` and
:class:`~torchcontact.filters.SpatialContactModel`)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcontact._checks import check_real


def check_gate(*, penalty: float, tolerance: float, gap: float) -> None:
    """Validate a contact model's gate settings.

    Args:
        penalty: ``inconsistency_penalty``, nats, ``>= 0`` or ``inf``.
        tolerance: ``consistency_tolerance``, in ``(0, 1)``.
        gap: ``consistency_gap``, metres, ``>= 0``.

    Raises:
        ValueError: naming the field at fault.
    """
    if penalty != math.inf:  # inf rules inconsistent modes out
        check_real("inconsistency_penalty", penalty, low=0.0)
    check_real("consistency_gap", gap, low=0.0)
    check_real("consistency_tolerance", tolerance, low=0.0, high=1.0, low_open=True, high_open=True)


def gate_log_weight(
    consistent: Tensor,
    *,
    penalty: float,
    dtype: torch.dtype,
    converged: Tensor | None = None,
    nearly: Tensor | None = None,
) -> Tensor:
    """Per-mode log-weights of a step: ``0`` for a consistent mode, ``-penalty`` for an
    inconsistent one, ``-inf`` for one whose equalities could not be solved.

    With ``penalty = inf`` a batch entry none of whose modes is consistent keeps the solved
    modes that pass a looser check (``nearly``; all solved ones if none does or if it is
    None) at ``0``, the measurements and the transition deciding among them, instead of
    ruling out every mode: the mean the modes are checked at is an estimate, and an entry
    with no mode left would have no step at all.

    Args:
        consistent: ``(*B, K)`` bool, the consistency check's verdict.
        penalty: ``inconsistency_penalty`` (nats; ``inf`` rules inconsistent modes out).
        dtype: the log-weights' dtype.
        converged: ``(*B, K)`` bool, the mode's equalities were solved, or None (all were).
        nearly: ``(*B, K)`` bool, the mode passes a looser consistency check, or None.

    Returns:
        ``(*B, K)`` log-weights (``ModeDynamics.mode_log_weight``).
    """
    weight = torch.full(consistent.shape, -penalty, dtype=dtype, device=consistent.device)
    weight = weight.masked_fill(consistent, 0.0)
    solved = torch.ones_like(consistent) if converged is None else converged
    if math.isinf(penalty):
        stranded = ~(consistent & solved).any(-1, keepdim=True)
        loose = solved if nearly is None else nearly & solved
        loose = torch.where(loose.any(-1, keepdim=True), loose, solved)
        weight = weight.masked_fill(stranded & loose, 0.0)
    return weight.masked_fill(~solved, -math.inf)
