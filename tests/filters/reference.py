"""Straightforward NumPy references for the filter tests (one filter, one sequence at a time
or plain enumeration; no code shared with torchcontact.filters)."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def kf_predict(m: Array, P: Array, F: Array, c: Array, Q: Array) -> tuple[Array, Array]:
    """Textbook Kalman prediction of one filter."""
    return F @ m + c, F @ P @ F.T + Q


def kf_update(
    m: Array, P: Array, y: Array, H: Array, d: Array, R: Array
) -> tuple[Array, Array, float]:
    """Textbook Kalman update (Joseph form) of one filter, with log N(y; H m + d, S)."""
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    r = y - H @ m - d
    A = np.eye(len(m)) - K @ H
    P_new = A @ P @ A.T + K @ R @ K.T
    log_lik = -0.5 * (
        r @ np.linalg.solve(S, r) + np.linalg.slogdet(S)[1] + len(y) * math.log(2 * math.pi)
    )
    return m + K @ r, P_new, float(log_lik)


def rts(
    means: list[Array], covs: list[Array], F: Array, Q: Array
) -> tuple[list[Array], list[Array]]:
    """RTS smoother of one filter from its filtered moments (time-invariant F, Q, no offset)."""
    ms, Ps = [means[-1]], [covs[-1]]
    for t in reversed(range(len(means) - 1)):
        m_pred = F @ means[t]
        P_pred = F @ covs[t] @ F.T + Q
        G = covs[t] @ F.T @ np.linalg.inv(P_pred)
        ms.insert(0, means[t] + G @ (ms[0] - m_pred))
        Ps.insert(0, covs[t] + G @ (Ps[0] - P_pred) @ G.T)
    return ms, Ps


@dataclass
class Posterior:
    """Exact posterior of a switching model by enumeration of every mode path m_0..m_T."""

    log_evidence: float
    mode_marginals: Array  # (K,) p(m_T | y_1:T)
    lag_marginals: Array  # (T + 1, K): row l is p(m_{T-l} | y_1:T)
    mean: Array  # (n,) E[x_T | y_1:T]
    cov: Array  # (n, n) Cov[x_T | y_1:T]


def enumerate_switching(
    F: Array,
    c: Array,
    Q: Array,
    H: Array,
    d: Array,
    R: Array,
    transitions: Array,
    initial: Array,
    m0: Array,
    P0: Array,
    ys: Array,
    extra: Array | None = None,
) -> Posterior:
    """Exact inference for a small jump Markov linear system by enumerating every mode path.

    The K**T paths m_1..m_T each run their own Kalman filter (vectorized over paths with
    NumPy); m_0 is summed out exactly. Model arrays are per mode ``(K, ...)``.

    Args:
        F, c, Q, H, d, R: per-mode model arrays.
        transitions: ``(T, K, K)``: the transition matrix used at each step (row = from).
        initial: ``(K,)`` distribution of m_0; m0, P0: prior of x_0.
        ys: ``(T, m)`` measurements (a NaN row = no measurement).
        extra: ``(T, K)`` per-mode log-likelihood terms, or None.
    """
    K, n = F.shape[0], F.shape[1]
    T = ys.shape[0]
    paths = np.array(list(itertools.product(range(K), repeat=T)))  # (S, T): m_1..m_T
    S = len(paths)
    m = np.tile(m0, (S, 1))
    P = np.tile(P0, (S, 1, 1))
    log_p = np.zeros(S)
    with np.errstate(divide="ignore"):
        log_trans = np.log(transitions)
        log_initial = np.log(initial)
    for t in range(T):
        k = paths[:, t]
        if t > 0:
            log_p += log_trans[t, paths[:, t - 1], k]
        m = np.einsum("sij,sj->si", F[k], m) + c[k]
        P = F[k] @ P @ F[k].transpose(0, 2, 1) + Q[k]
        if not np.isnan(ys[t]).all():
            Hk = H[k]
            Sk = Hk @ P @ Hk.transpose(0, 2, 1) + R[k]
            gain = np.linalg.solve(Sk, Hk @ P).transpose(0, 2, 1)
            r = ys[t] - np.einsum("sij,sj->si", Hk, m) - d[k]
            A = np.eye(n) - gain @ Hk
            P = A @ P @ A.transpose(0, 2, 1) + gain @ R[k] @ gain.transpose(0, 2, 1)
            m = m + np.einsum("sij,sj->si", gain, r)
            quad = np.einsum("si,si->s", r, np.linalg.solve(Sk, r[..., None])[..., 0])
            log_p += -0.5 * (quad + np.linalg.slogdet(Sk)[1] + len(r[0]) * math.log(2 * math.pi))
        if extra is not None:
            log_p += extra[t, k]
    # joint with m_0: (S, K)
    log_joint = log_p[:, None] + log_initial[None, :] + log_trans[0][:, paths[:, 0]].T
    log_z = float(np.logaddexp.reduce(log_joint.ravel()))
    w_joint = np.exp(log_joint - log_z)
    w = w_joint.sum(1)
    lag = np.zeros((T + 1, K))
    for lag_index in range(T):
        np.add.at(lag[lag_index], paths[:, T - 1 - lag_index], w)
    lag[T] = w_joint.sum(0)
    mean = (w[:, None] * m).sum(0)
    dev = m - mean
    cov = (w[:, None, None] * (P + dev[:, :, None] * dev[:, None, :])).sum(0)
    return Posterior(log_z, lag[0], lag, mean, cov)
