"""Probing before inserting: a scripted belief policy for the occluded peg-in-hole variant."""

from __future__ import annotations

import torch
from torch import Tensor

from torchcontact.envs import (
    ACTION_NAMES,
    PegBelief,
    PegInHoleBeliefModel,
    PegInHoleFilter,
    PegInHoleTask,
)

#: The probing action: press the peg straight down (``"-y"``).
PRESS = ACTION_NAMES.index("-y")
# The shifts of shift_actions: "+x" and "-x".
_RIGHT, _LEFT = ACTION_NAMES.index("+x"), ACTION_NAMES.index("-x")
#: Default lateral standard deviation of the peg's bottom centre above which the probing
#: policy presses (m).
PROBE_THRESHOLD = 0.002


def lateral_spread(filt: PegInHoleFilter, belief: PegBelief) -> Tensor:
    r"""``(B,)`` standard deviation of the peg's bottom-centre ``x`` (world frame, m) under a
    belief of the fitted model (:class:`~torchcontact.envs.PegInHoleBeliefModel`).

    The bottom centre of a peg held with grasp ``(u, w, φ)`` by a gripper at ``(g_x, g_y,
    g_θ)`` lies at :math:`b_x = g_x + \cos g_θ\, u - \sin g_θ\, w + \tfrac{h}{2} \sin(g_θ +
    φ)` (``h`` the peg's length). The variance is that of the particle mixture: the weighted
    spread of the particles' :math:`b_x` at their means, plus the weighted mean of each
    particle's Gaussian pushed through the linearization :math:`J = (\cos g_θ, -\sin g_θ,
    \tfrac{h}{2} \cos(g_θ + φ))`.

    Args:
        filt: the filter (its model's state is the grasp in the gripper frame).
        belief: the belief, batch ``(B,)``.

    Raises:
        ValueError: ``filt`` does not run on a :class:`~torchcontact.envs.PegInHoleBeliefModel`
            (the physics model's state is the peg's world pose and twist).
    """
    if not isinstance(filt.model, PegInHoleBeliefModel):
        raise ValueError(
            f"filt must run on a PegInHoleBeliefModel, got {type(filt.model).__name__}"
        )
    rbpf = belief.rbpf
    weights = rbpf.log_weights.exp()  # (B, N)
    half = filt.model.task.config.peg_height / 2
    bottom_x = filt.model.task.states.relative_pose(filt.particle_poses(belief))[..., 0]
    mean = (weights * bottom_x).sum(-1, keepdim=True)
    spread = (weights * (bottom_x - mean) ** 2).sum(-1)
    angle = belief.gripper[:, 2:3]  # (B, 1)
    phi = rbpf.gaussians.mean[..., 2]  # (B, N)
    J = torch.stack(
        [
            torch.cos(angle).expand_as(phi),
            -torch.sin(angle).expand_as(phi),
            half * torch.cos(angle + phi),
        ],
        -1,
    )  # (B, N, 3)
    own = torch.einsum("bni,bnij,bnj->bn", J, rbpf.gaussians.cov[..., :3, :3], J)
    return (spread + (weights * own).sum(-1)).clamp(min=0.0).sqrt()


def bottom_touch(task: PegInHoleTask, readings: Tensor) -> Tensor:
    """``(B,)`` whether any sensor on the peg's bottom side reads a touch in ``readings
    (B, S)`` (bool; the sensors of ``task.sensors``, bottom first)."""
    bottom = task.config.tactile_counts[0]
    return readings[:, :bottom].any(-1)


def probe_presses(
    *, blind: Tensor, spread: Tensor, touched: Tensor, threshold: float = PROBE_THRESHOLD
) -> Tensor:
    """``(B,)`` where the probe-then-insert policy presses down instead of following QMDP.

    It presses while the camera is blind, the belief's lateral spread exceeds ``threshold``
    and the peg's bottom has not yet touched anything during the probe: pressed onto the
    chamfer or the surface beside the hole, a bottom sensor fires on the side of the offset;
    centred, the peg enters the hole. Afterwards QMDP acts on the belief that the touch
    updated (through the contact-class evidence and the graph's transition rows).

    Args:
        blind: ``(B,)`` bool, the camera returned no pose (all NaN).
        spread: ``(B,)`` :func:`lateral_spread` of the belief, m.
        touched: ``(B,)`` bool, a bottom sensor fired during an earlier press of the episode
            (:func:`bottom_touch`).
        threshold: lateral spread above which to press, m.
    """
    return blind & (spread > threshold) & ~touched


def bottom_sides(task: PegInHoleTask, readings: Tensor) -> Tensor:
    """``(B, 2)`` whether a sensor on the left (``x < 0`` in the peg's frame) and on the right
    half of the peg's bottom side reads a touch in ``readings (B, S)`` (bool)."""
    bottom = task.config.tactile_counts[0]
    x = task.sensors.positions[:bottom, 0]
    hits = readings[:, :bottom]
    return torch.stack([(hits & (x < 0)).any(-1), (hits & (x > 0)).any(-1)], -1)


def shift_actions(
    qmdp: Tensor,
    *,
    blind: Tensor,
    spread: Tensor,
    sides: Tensor,
    threshold: float = PROBE_THRESHOLD,
) -> Tensor:
    """``(B,)`` actions of the touch-and-shift probe: read the touch as a lateral position.

    While the camera is blind: if the bottom touches on one side only (that corner is on the
    chamfer or the surface beside the hole, so the peg lies off the hole towards that side),
    move the gripper away from it (``"-x"`` for the right corner, ``"+x"`` for the left); if
    nothing touches and the belief's lateral spread exceeds ``threshold``, press down;
    otherwise (seen, both corners on a surface, or a confident belief) take QMDP's action.
    The policy bypasses the belief for the lateral correction: it tests whether touch carries
    the information QMDP lacks.

    Args:
        qmdp: ``(B,)`` long QMDP actions.
        blind: ``(B,)`` bool, the camera returned no pose.
        spread: ``(B,)`` :func:`lateral_spread` of the belief, m.
        sides: ``(B, 2)`` :func:`bottom_sides` of the latest readings.
        threshold: lateral spread above which to press, m.
    """
    left, right = sides.unbind(-1)
    press = blind & (spread > threshold) & ~(left | right)
    out = torch.where(press, PRESS, qmdp)
    out = torch.where(blind & right & ~left, _LEFT, out)
    return torch.where(blind & left & ~right, _RIGHT, out)


__all__ = [
    "PRESS",
    "PROBE_THRESHOLD",
    "bottom_sides",
    "bottom_touch",
    "lateral_spread",
    "probe_presses",
    "shift_actions",
]
