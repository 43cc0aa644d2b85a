"""Figures of the triangle-grasp experiment: snapshots, error curves and the mode timeline.

matplotlib is imported when a figure is drawn.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from torchcontact.experiments._triangle_grasp import GraspTrials, H
from torchcontact.sim import draw_scene
from torchcontact.states import mode_label

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def _shade_occlusion(ax: Any, trials: GraspTrials, time_s: Tensor) -> None:
    occ = time_s[trials.occluded]
    ax.axvspan(float(occ[0]) - H / 2, float(occ[-1]) + H / 2, color="0.88", zorder=0)


def plot_grasp_snapshots(
    trials: GraspTrials, outputs: dict[str, dict[str, Tensor]], steps: list[int], trial: int = 0
) -> Figure:
    """Trial ``trial`` after the given steps: the scene (top) and the particles (bottom).

    Top: truth with the fingers and the RBPF's particle means. Bottom: a 12 mm window around
    the true position with the RBPF's and the PF's particles (size ∝ weight) and the estimates.
    """
    import matplotlib.pyplot as plt

    truth = trials.truth
    fig, axes = plt.subplots(2, len(steps), figsize=(3.6 * len(steps), 4.4), squeeze=False)
    for column, t in enumerate(steps):
        top, bottom = axes[0, column], axes[1, column]
        draw_scene(
            top, trials.scene, q=truth.q[t + 1, trial], q_kinematic=truth.q_kinematic[t + 1, trial]
        )
        top.set_xlim(-0.08, 0.08)
        top.set_ylim(-0.005, 0.075)
        top.set_xticks([-0.05, 0.0, 0.05])
        top.set_yticks([0.0, 0.05])
        occluded = " (occluded)" if trials.occluded[t] else ""
        top.set_title(f"t = {H * (t + 1):.2f} s{occluded}", fontsize=9)
        true_xy = 1e3 * truth.q[t + 1, trial, 0, :2]
        for method, color in (("pf", "C2"), ("rbpf", "C3")):
            if method not in outputs:
                continue
            cloud = outputs[method]["cloud"][t]
            weight = outputs[method]["cloud_weight"][t]
            size = 4 + 60 * weight / weight.max()
            xy = 1e3 * cloud[:, :2] - true_xy
            bottom.scatter(
                xy[:, 0],
                xy[:, 1],
                s=size,
                color=color,
                alpha=0.4,
                lw=0,
                label=f"{method} particles",
            )
            if method == "rbpf":
                top.plot(cloud[:, 0], cloud[:, 1], ".", color=color, ms=2)
        for method, marker in (("rbpf", "x"), ("pf", "+"), ("vision", "s")):
            if method in outputs:
                xy = 1e3 * outputs[method]["pose"][t, trial, :2] - true_xy
                bottom.plot(
                    xy[0], xy[1], marker, color="k", ms=7, mfc="none", label=f"{method} estimate"
                )
        bottom.plot(0, 0, "*", color="C0", ms=10, label="truth")
        bottom.set_xlim(-6, 6)
        bottom.set_ylim(-3, 3)
        bottom.set_aspect("equal")
        bottom.set_xlabel("x error (mm)")
    axes[1, 0].set_ylabel("y error (mm)")
    axes[1, 0].legend(fontsize=6, loc="lower left")
    fig.tight_layout()
    return fig


def plot_tracking_errors(
    trials: GraspTrials,
    errors: dict[str, tuple[Tensor, Tensor]],
    labels: dict[str, str] | None = None,
) -> Figure:
    """Position and angle RMSE over the trials against time, the occlusion shaded.

    Args:
        trials: the trials.
        errors: ``{method: (position error (T, B), angle error (T, B))}`` from
            :func:`evaluate_tracking`.
        labels: legend text per method (default: the method's name).
    """
    import matplotlib.pyplot as plt

    labels = labels or {}
    time_s = H * torch.arange(1, trials.steps + 1)
    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    for method, (pos, ang) in errors.items():
        label = labels.get(method, method)
        axes[0].plot(time_s, 1e3 * pos.pow(2).mean(-1).sqrt(), label=label)
        axes[1].plot(time_s, torch.rad2deg(ang.pow(2).mean(-1).sqrt()), label=label)
    for ax in axes:
        _shade_occlusion(ax, trials, time_s)
        ax.set_yscale("log")
    axes[0].set_ylabel("position RMSE (mm)")
    axes[1].set_ylabel("angle RMSE (deg)")
    axes[1].set_xlabel("time (s); shaded: camera occluded")
    axes[0].legend(fontsize=7, ncol=3, loc="lower center", bbox_to_anchor=(0.5, 1.0), frameon=False)
    fig.tight_layout()
    return fig


def plot_mode_timeline(trials: GraspTrials, marginals: Tensor, trial: int = 0) -> Figure:
    """Mode marginals of one trial over time (shade), the true mode and the MAP mode.

    Args:
        trials: the trials.
        marginals: ``(T, B, K)`` filtered mode marginals.
        trial: which trial.
    """
    import matplotlib.pyplot as plt

    K = trials.table.shape[0]
    time_s = H * torch.arange(1, trials.steps + 1)
    marg = marginals[:, trial]
    labels = [
        f"{k}: {mode_label(trials.scene, trials.table[k], body='triangle')}" for k in range(K)
    ]
    fig, ax = plt.subplots(figsize=(9, 0.28 * K + 1.6))
    ax.imshow(
        marg.T,
        aspect="auto",
        origin="lower",
        cmap="Blues",
        vmin=0.0,
        vmax=1.0,
        extent=(float(time_s[0]) - H / 2, float(time_s[-1]) + H / 2, -0.5, K - 0.5),
    )
    true_ids = trials.true_ids[:, trial]
    ax.plot(time_s, true_ids.clamp(max=K - 1), "o", mfc="none", color="C3", ms=6, label="true mode")
    ax.plot(time_s, marg.argmax(-1), "k.", ms=3, label="RBPF MAP mode")
    occ = time_s[trials.occluded]
    ax.axvspan(float(occ[0]) - H / 2, float(occ[-1]) + H / 2, color="0.5", alpha=0.12)
    ax.set_yticks(range(K), labels, fontsize=7)
    ax.set_xlabel("time (s); shaded: camera occluded")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    return fig
