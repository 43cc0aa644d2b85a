"""The per-step kernels of the :class:`~torchcontact.filters.RBPF`: Kalman predict/update of
the particles under their modes' dynamics, reweighting and normalization, and the step's flags
(bad input, dead entries, resampling), all without host synchronization until
:func:`read_flags`. ``_compiled.kernel`` compiles :func:`predict_update`,
:func:`bootstrap_core` and :func:`predicted_log_likelihood`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcontact.filters import _linalg as la
from torchcontact.filters._kalman import predict_core, update_core, update_log_likelihood

_INVALID_WEIGHTS = "belief: a Kalman update produced NaN (a particle covariance is not PSD)"


def unpack_dynamics(params: Tensor, shared: dict[str, Tensor], n: int, m: int) -> list[Tensor]:
    """Batch-last ``F, c, Q, H, d, R`` views: the packed ones split from ``(D, *P)`` params,
    the shared ones with ``len(P)`` batch dims of size 1."""
    batch = params.shape[1:]
    shapes = {"F": (n, n), "c": (n,), "Q": (n, n), "H": (m, n), "d": (m,), "R": (m, m)}
    names = [name for name in shapes if name not in shared]
    parts = torch.split(params, [math.prod(shapes[name]) for name in names])
    fields = {
        name: part.reshape(*shapes[name], *batch) for name, part in zip(names, parts, strict=True)
    }
    ones = (1,) * len(batch)
    fields.update({name: value.reshape(*value.shape, *ones) for name, value in shared.items()})
    return [fields[name] for name in shapes]


def predict_update(
    mean: Tensor,
    cov: Tensor,
    params: Tensor,
    shared: dict[str, Tensor],
    y: Tensor,
    observed: Tensor | None,
    *,
    n: int,
    m: int,
    measured: bool = True,
    entrywise: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """Kalman predict + update of batch-last particles under per-particle model parameters.

    Args:
        mean: ``(n, *P)``; cov: ``(n, n, *P)`` (``*P`` = the particle batch dims).
        params: ``(D, *P')`` packed per-mode fields (see :meth:`RBPF._packed_dynamics`).
        shared: the fields every mode shares, without batch dims.
        y, observed: the measurement and its used components, batch-last
            (:func:`batch_last_measurement`).
        n, m: state and measurement sizes.
        measured: ``False`` predicts only (likelihood 1: nothing was measured).
        entrywise: factor the predicted covariances per particle: no host synchronization,
            so the compiled form is one kernel (see :func:`update_core`).

    Returns:
        ``(mean⁺ (n, *P), cov⁺ (n, n, *P), log_likelihood (*P))``.
    """
    F, c, Q, H, d, R = unpack_dynamics(params, shared, n, m)
    if not measured:
        mean, cov = predict_core(mean, cov, F, c, Q)
        return mean, cov, mean.new_zeros(mean.shape[1:])
    # update_core reads the lower triangle only, except that entries without a measurement
    # keep the predicted covariance as it is: symmetrize only then.
    mean, cov = predict_core(mean, cov, F, c, Q, symmetric=observed is not None)
    return update_core(mean, cov, y, H, d, R, observed, entrywise=entrywise)


def bootstrap_core(
    modes: Tensor,
    packed: Tensor,
    params: Tensor,
    shared: dict[str, Tensor],
    mode_log_weight: Tensor | None,
    mean: Tensor,
    cov: Tensor,
    y: Tensor,
    observed: Tensor | None,
    extra: Tensor | None,
    log_weights: Tensor,
    log_evidence: Tensor,
    history: Tensor,
    previous_modes: Tensor,
    *,
    n: int,
    m: int,
    measured: bool,
    entrywise: bool,
    log_ess_bound: float,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """A bootstrap step from the sampled modes up to resampling, without host
    synchronization (compiled: one kernel).

    Args:
        modes: ``(*B, N)`` the particles' new modes; packed: ``(*B', K, D)`` every mode's
            packed dynamics (tested for finite values only); params: ``(D, *B, N)`` the
            particles' (:func:`particle_params`, given rather than gathered here: the compiled loops
            vectorize over contiguous parameters, not over indirect loads); shared: the
            fields every mode shares; mode_log_weight: ``(*B', N or 1, K)`` or None, the
            model's log-weights of every particle's modes.
        mean: ``(n, *B, N)``; cov: ``(n, n, *B, N)``: the particles, batch-last.
        y, observed: batch-last (:func:`batch_last_measurement`); extra: ``(*B', K)`` or None.
        log_weights: ``(*B, N)``; log_evidence: ``(*B,)``; history: ``(*B, N, L + 1)``;
            previous_modes: ``(*B, N)``: the given belief's (tested by :func:`belief_flags`).
        n, m, measured, entrywise: as in :func:`predict_update`.
        log_ess_bound: resample where ``log Σ w² >`` this (``-log(threshold · N)``).

    Returns:
        The normalized log-weights, batch-last mean and covariance, evidence and history,
        ``dead (*B)`` (every weight zero: placeholders, see :func:`normalize_log_weights`),
        ``resample (*B)`` (ESS below the threshold, not dead) and the :func:`step_flags`.
    """
    mean, cov, log_lik = predict_update(
        mean,
        cov,
        params,
        shared,
        y,
        observed,
        n=n,
        m=m,
        measured=measured,
        entrywise=entrywise,
    )
    given_flags = belief_flags(previous_modes, log_weights, log_evidence, packed.shape[-2])
    log_w = log_weights + log_lik
    for weight in (None if extra is None else extra.unsqueeze(-2), mode_log_weight):
        if weight is not None:  # (*B', N or 1, K)
            log_w = log_w + weight.expand(*log_w.shape, weight.shape[-1]).gather(
                -1, modes.unsqueeze(-1)
            ).squeeze(-1)
    log_w, log_evidence, dead, invalid = normalize_log_weights(log_w, log_evidence)
    history = torch.cat([modes.unsqueeze(-1), history[..., :-1]], -1)
    # ESS = 1 / Σ w² < threshold · N, in log space
    resample = (torch.logsumexp(2.0 * log_w, -1) > log_ess_bound) & ~dead
    flags = step_flags(
        invalid,
        dead,
        *dynamics_flags(packed, shared, mode_log_weight),
        given_flags,
        resample,
    )
    return log_w, mean, cov, log_evidence, history, dead, resample, flags


def particle_params(packed: Tensor, modes: Tensor) -> Tensor:
    """Batch-last ``(D, *B, N)`` packed dynamics of the particles' ``modes (*B, N)``, from
    ``packed (K, D)`` (one set for the whole batch: one index_select) or ``(*B', K, D)``."""
    batch, N = modes.shape[:-1], modes.shape[-1]
    if packed.ndim == 2:
        return packed.T.index_select(1, modes.reshape(-1)).reshape(packed.shape[-1], *batch, N)
    params = packed.expand(*batch, *packed.shape[-2:]).gather(
        -2, modes.unsqueeze(-1).expand(*batch, N, packed.shape[-1])
    )
    return params.movedim(-1, 0)


def predicted_log_likelihood(
    predicted: Tensor,
    F: Tensor,
    cov: Tensor,
    Q: Tensor,
    y: Tensor,
    H: Tensor,
    d: Tensor | None,
    R: Tensor,
    observed: Tensor | None,
    *,
    size: int,
    entrywise: bool,
) -> Tensor:
    """The children's predictive log-likelihoods from the leading ``(r, r)`` block of
    :func:`~torchcontact.filters._kalman.predict_core`'s ``F P Fᵀ + Q``, computed by the same
    operations (products sized as the full step's, ``size``).

    Args:
        predicted: ``(r, *B)`` the leading components of the predicted means.
        F: ``(r, n, *B)`` the leading rows of the children's ``F``; cov: ``(n, n, *B)``;
            Q: ``(r, r, *B)``.
        y, H, d, R, observed: batch-last, as in :func:`update_log_likelihood`.
        entrywise: see :func:`update_core`.

    Returns:
        ``(*B)`` log-likelihoods.
    """
    block = la.add_(la.mm_t(la.mm(F, cov, size=size), F, size=size), Q)
    if observed is not None:  # as predict_update symmetrizes
        block = la.symmetrize(block)
    return update_log_likelihood(predicted, block, y, H, d, R, observed, entrywise=entrywise)


def batch_last_measurement(
    y: Tensor, observed: Tensor | None, batch_ndim: int
) -> tuple[Tensor, Tensor | None]:
    """``y (*B', m)`` and ``observed`` batch-last with ``batch_ndim`` batch dims: the particle
    dims that they lack are added as 1s on the right."""
    m = y.shape[-1]
    extra_dims = batch_ndim - (y.ndim - 1)  # particle dims that y does not have
    y_bl = la.to_batch_last(y.reshape(*y.shape[:-1], *(1,) * extra_dims, m), 1, batch_ndim)
    if observed is None:
        return y_bl, None
    observed = observed.reshape(*observed.shape[:-1], *(1,) * extra_dims, m)
    return y_bl, la.to_batch_last(observed, 1, batch_ndim)


def normalize_log_weights(
    log_w: Tensor, log_evidence: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Normalize incremental log-weights ``(*B, M)`` and accumulate the evidence ``(*B,)``,
    without host synchronization.

    Returns ``(log_w, log_evidence, dead, invalid)``: where every weight is zero (``dead``),
    the log-weights are a uniform placeholder (the caller resets the entry) and the evidence
    is ``-inf``, gradients staying finite everywhere; ``invalid`` flags a NaN or ``+inf`` sum
    (the caller raises).
    """
    increment = torch.logsumexp(log_w, -1)
    dead = torch.isneginf(increment)
    invalid = torch.isnan(increment) | torch.isposinf(increment)
    # Summed again without the dead entries' -inf (the same numbers elsewhere), so that the
    # gradient of the logsumexp is finite.
    log_w = torch.where(dead.unsqueeze(-1), 0.0, log_w)
    increment = torch.logsumexp(log_w, -1)
    log_evidence = torch.where(dead, -math.inf, log_evidence + increment)
    return log_w - increment.unsqueeze(-1), log_evidence, dead, invalid


# Entries of a step's flags (:func:`step_flags`).
INVALID, DEAD, BAD_DYNAMICS, BAD_MODE_WEIGHT, BAD_WEIGHTS, BAD_MODES, RESAMPLE = range(7)


def belief_flags(modes: Tensor, log_weights: Tensor, log_evidence: Tensor, K: int) -> Tensor:
    """Whether the belief given to a step holds NaN or ``+inf`` log-weights or evidence, and
    whether its modes leave ``[0, K)``: ``(2,)`` bool, no synchronization (the step reads it
    with its other flags).

    Args:
        modes: ``(*B, N)`` long; log_weights: ``(*B, N)``; log_evidence: ``(*B,)``.
        K: the number of modes.
    """
    # x < inf is False exactly for NaN and +inf
    bad_weights = ~((log_weights < math.inf).all() & (log_evidence < math.inf).all())
    return torch.stack([bad_weights, ((modes < 0) | (modes >= K)).any()])


def dynamics_flags(
    packed: Tensor, shared: dict[str, Tensor], mode_log_weight: Tensor | None
) -> tuple[Tensor, Tensor]:
    """Whether the model's dynamics of a step hold NaN or inf, and whether its
    ``mode_log_weight`` holds NaN or ``+inf``: two ``()`` bool tensors, no synchronization."""
    finite = torch.isfinite(packed).all()
    for value in shared.values():
        finite = finite & torch.isfinite(value).all()
    if mode_log_weight is None:
        return ~finite, torch.zeros_like(finite)
    return ~finite, (torch.isnan(mode_log_weight) | torch.isposinf(mode_log_weight)).any()


def step_flags(
    invalid: Tensor,
    dead: Tensor,
    bad_dynamics: Tensor,
    bad_mode_weight: Tensor,
    given_flags: Tensor,
    resample: Tensor | None = None,
) -> Tensor:
    """A step's ``(7,)`` bool flags (indexed by ``INVALID`` …): any NaN/+inf weight
    increment, any dead entry, the model's dynamics and mode log-weights bad, the given
    belief's :func:`belief_flags` (``given_flags``), any entry to resample (False if
    ``resample`` is None)."""
    wanted = resample.any() if resample is not None else torch.zeros_like(bad_dynamics)
    head = torch.stack([invalid.any(), dead.any(), bad_dynamics, bad_mode_weight])
    return torch.cat([head, given_flags, wanted.unsqueeze(0)])


def read_flags(flags: Tensor) -> list[bool]:
    """A step's :func:`step_flags` read (one host synchronization), raising the error they call
    for."""
    read: list[bool] = flags.tolist()
    # The given belief's and the model's faults come first: they make the weights NaN too.
    if read[BAD_WEIGHTS]:
        raise ValueError("belief: log_weights and log_evidence must not hold NaN or +inf")
    if read[BAD_MODES]:
        raise ValueError("belief: modes must lie in [0, K), the model's modes")
    if read[BAD_MODE_WEIGHT]:
        raise ValueError("model: mode_dynamics().mode_log_weight: contains NaN or +inf")
    if read[BAD_DYNAMICS]:
        raise ValueError("model: mode_dynamics() returned NaN or inf")
    if read[INVALID]:
        raise ValueError(_INVALID_WEIGHTS)
    return read


def gather_states(index: Tensor, mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
    """Select particles along the last dim of batch-last states: ``index (*B, N)``."""
    mean = mean.gather(-1, index.expand(mean.shape[0], *index.shape))
    cov = cov.gather(-1, index.expand(cov.shape[0], cov.shape[1], *index.shape))
    return mean, cov


def gather_particles(
    index: Tensor, modes: Tensor, history: Tensor, mean: Tensor, cov: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Resample modes ``(*B, N)``, history ``(*B, N, L+1)`` and batch-last states by ``index``."""
    modes = modes.gather(-1, index)
    history = history.gather(-2, index.unsqueeze(-1).expand(*history.shape))
    mean, cov = gather_states(index, mean, cov)
    return modes, history, mean, cov
