"""The DQN temporal-difference loss and target-network updates."""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional

from torchcontact._checks import FLOAT_DTYPES, all_finite, check_instance, check_real
from torchcontact.rl._replay import Transitions


def dqn_loss(
    online: nn.Module,
    target: nn.Module,
    batch: Transitions,
    gamma: float,
    *,
    double: bool = False,
    huber_delta: float = 1.0,
) -> Tensor:
    r"""Huber loss between ``Q(s, a)`` and the bootstrapped target of a target network.

    With ``N`` transitions ``(s, a, r, s′, done)``:

    .. math::

        y = r + γ (1 − \mathrm{done})\, Q_{\bar θ}(s′, a′), \qquad
        a′ = \begin{cases} \arg\max_b Q_{\bar θ}(s′, b) & \text{DQN} \\
                          \arg\max_b Q_θ(s′, b) & \text{double DQN} \end{cases}

    and the loss is the mean Huber loss ``H_δ(Q_θ(s, a) − y)``; ``y`` carries no gradient.

    Args:
        online: the trained network ``Q_θ``, mapping ``(N, *S)`` to ``(N, A)``.
        target: the target network ``Q_θ̄``, same signature (often a lagged copy).
        batch: the transitions (e.g. :meth:`ReplayBuffer.sample`).
        gamma: discount factor in ``[0, 1]``.
        double: pick ``a′`` with the online network (double DQN).
        huber_delta: ``δ > 0``, where the loss turns from quadratic to linear.

    Returns:
        ``()`` loss, differentiable with respect to ``online``'s parameters (0 for an empty
        batch).

    Raises:
        ValueError: a setting is out of range or of the wrong type, a network is not an
            ``nn.Module``, or the batch's fields or the networks' outputs
            have inconsistent shapes or dtypes, or an action is out of range.

    References:
        V. Mnih et al., "Human-level control through deep reinforcement learning", Nature 518,
        2015. H. van Hasselt, A. Guez and D. Silver, "Deep reinforcement learning with double
        Q-learning", AAAI 2016.
    """
    gamma = check_real("gamma", gamma, low=0.0, high=1.0)
    delta = check_real("huber_delta", huber_delta, low=0.0, low_open=True)
    if not isinstance(batch, Transitions):
        raise ValueError(f"batch must be a Transitions, got {type(batch).__name__}")
    if not isinstance(double, bool):
        raise ValueError(f"double must be a bool, got {double!r}")
    for name, module in (("online", online), ("target", target)):
        check_instance(name, module, nn.Module)
    for name, value in zip(Transitions._fields, batch, strict=True):
        if not isinstance(value, Tensor):
            raise ValueError(f"batch.{name} must be a tensor, got {type(value).__name__}")
    observations, actions, rewards, next_observations, terminals = batch
    N = observations.shape[0] if observations.ndim else -1
    if next_observations.shape != observations.shape:
        raise ValueError(
            f"batch.next_observations must have the shape of batch.observations "
            f"{tuple(observations.shape)}, got {tuple(next_observations.shape)}"
        )
    for name, value, dtype_ok in (
        ("actions", actions, actions.dtype == torch.long),
        ("rewards", rewards, rewards.dtype in FLOAT_DTYPES),
        ("terminals", terminals, terminals.dtype == torch.bool),
    ):
        if value.shape != (N,) or not dtype_ok:
            raise ValueError(
                f"batch.{name} must be a ({N},) tensor of the right dtype (long actions, "
                f"float32/float64 rewards, bool terminals), got {tuple(value.shape)} {value.dtype}"
            )
    if not all_finite(rewards):
        raise ValueError("batch.rewards contains NaN or inf")
    q = online(observations)
    if q.ndim != 2 or q.shape[0] != N:
        raise ValueError(f"online must return (N, A) = ({N}, A) values, got {tuple(q.shape)}")
    A = q.shape[1]
    if N and (int(actions.min()) < 0 or int(actions.max()) >= A):
        raise ValueError(f"batch.actions must lie in [0, {A})")
    taken = q.gather(-1, actions.unsqueeze(-1)).squeeze(-1)
    with torch.no_grad():
        next_q = target(next_observations)
        if next_q.shape != q.shape:
            raise ValueError(
                f"target must return values of shape {tuple(q.shape)}, got {tuple(next_q.shape)}"
            )
        if double:
            choice = online(next_observations).argmax(dim=-1, keepdim=True)
            next_value = next_q.gather(-1, choice).squeeze(-1)
        else:
            next_value = next_q.max(dim=-1).values
        next_value = torch.where(terminals, torch.zeros_like(next_value), next_value)
        targets = rewards.to(q.dtype) + gamma * next_value
    if N == 0:  # the mean over no transitions: 0, still differentiable in online's parameters
        zero: Tensor = taken.sum()
        return zero
    return functional.huber_loss(taken, targets, delta=delta)


def update_target(*, target: nn.Module, online: nn.Module, tau: float = 1.0) -> None:
    """Move the target network towards the online one: ``θ̄ ← (1 − τ) θ̄ + τ θ``.

    ``tau = 1`` is the hard update (a copy); ``0 < tau < 1`` the soft (Polyak) update.
    Buffers (e.g. batch-norm statistics) are always copied.

    Args:
        target: the network updated in place.
        online: the network followed; same parameter and buffer shapes as ``target``.
        tau: step in ``(0, 1]``.

    Raises:
        ValueError: ``tau`` is out of range, a network is not an ``nn.Module``, ``target`` is
            ``online``, or their parameters or buffers differ in number or shape.
    """
    tau = check_real("tau", tau, low=0.0, high=1.0, low_open=True)
    check_instance("target", target, nn.Module)
    check_instance("online", online, nn.Module)
    if target is online:
        raise ValueError("target must be a different module from online")
    pairs = []
    for kind, mine, theirs in (
        ("parameters", list(target.parameters()), list(online.parameters())),
        ("buffers", list(target.buffers()), list(online.buffers())),
    ):
        shapes = [t.shape for t in mine], [o.shape for o in theirs]
        if shapes[0] != shapes[1]:
            raise ValueError(f"target and online must have the same {kind} shapes")
        pairs.append(zip(mine, theirs, strict=True))
    with torch.no_grad():
        for t, o in pairs[0]:
            if tau == 1.0:
                t.copy_(o)
            else:
                t.lerp_(o.to(t.dtype), tau)
        for t, o in pairs[1]:
            t.copy_(o)
