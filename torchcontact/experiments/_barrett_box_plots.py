"""Figures of the BarrettHand box grasp: error curves, 3D snapshots, contact-state timelines.

matplotlib is imported when a figure is drawn.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch
from torch import Tensor

from torchcontact.experiments._barrett_box import BOX_PAIRS, BoxTrials, H
from torchcontact.experiments._barrett_box_metrics import geodesic_angle
from torchcontact.geometry import quat_to_matrix

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: Faces of a box by corner index (corner ``i`` has signs of bits 2, 1, 0 along x, y, z).
_FACES = ((0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5))
_STATE_NAMES = ("separated", "sticking", "sliding")


def _shade_occlusion(ax: Any, occluded: Tensor, time_s: Tensor) -> None:
    occ = time_s[occluded]
    ax.axvspan(float(occ[0]) - H / 2, float(occ[-1]) + H / 2, color="0.88", zorder=0)


def _box_faces(pose: Tensor, half: Tensor) -> list[list[list[float]]]:
    """The six faces of a box of half extents ``half`` ``(3,)`` at ``pose`` ``(7,)``."""
    signs = torch.tensor(
        [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=pose.dtype
    )
    corners = (quat_to_matrix(pose[3:7]) @ (signs * half).T).T + pose[:3]
    return [corners[list(face)].tolist() for face in _FACES]


def plot_box_errors(
    trials: BoxTrials, outputs: dict[str, dict[str, Tensor]], labels: dict[str, str] | None = None
) -> Figure:
    """Position and orientation RMSE over the trials against time, the occlusion shaded."""
    import matplotlib.pyplot as plt

    labels = labels or {}
    time_s = H * torch.arange(1, trials.steps + 1)
    truth = trials.pose
    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    for method, out in outputs.items():
        pose = out["pose"]
        position = (pose[..., :3] - truth[..., :3]).pow(2).sum(-1).mean(-1).sqrt()
        angle = geodesic_angle(truth[..., 3:], pose[..., 3:]).pow(2).mean(-1).sqrt()
        label = labels.get(method, method)
        axes[0].plot(time_s.numpy(), (1e3 * position).numpy(), label=label)
        axes[1].plot(time_s.numpy(), torch.rad2deg(angle).numpy(), label=label)
    for ax in axes:
        _shade_occlusion(ax, trials.occluded, time_s)
        ax.set_yscale("log")
    axes[0].set_ylabel("position RMSE (mm)")
    axes[1].set_ylabel("orientation RMSE (deg)")
    axes[1].set_xlabel("time (s); shaded: camera occluded")
    axes[0].legend(fontsize=7, ncol=3, loc="lower center", bbox_to_anchor=(0.5, 1.0), frameon=False)
    fig.tight_layout()
    return fig


def plot_box_snapshots(
    trials: BoxTrials,
    outputs: dict[str, dict[str, Tensor]],
    steps: list[int],
    *,
    trial: int = 0,
    methods: tuple[str, ...] = ("rbpf", "pf", "ekf"),
) -> Figure:
    """Trial ``trial`` after the given steps in 3D: the true box (grey), the last camera
    pose (blue wireframe) and the estimates of ``methods`` (coloured wireframes, the
    particle filters' particle positions as dots)."""
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # type: ignore[import-untyped]

    half = trials.half_extents[trial]
    fig = plt.figure(figsize=(4.2 * len(steps), 4.2))
    centre = trials.pose[0, trial, :3]
    reach = float(half.max()) * 2.5
    for column, t in enumerate(steps):
        ax = fig.add_subplot(1, len(steps), column + 1, projection="3d")
        ax.add_collection3d(
            Poly3DCollection(
                _box_faces(trials.pose[t, trial], half), facecolor="0.6", edgecolor="k", alpha=0.3
            )
        )
        if "camera" in outputs:
            faces = _box_faces(outputs["camera"]["pose"][t, trial], half)
            ax.add_collection3d(
                Poly3DCollection(faces, facecolor="none", edgecolor="C0", linewidths=0.8)
            )
        for index, method in enumerate(m for m in methods if m in outputs):
            color = f"C{index + 1}"
            faces = _box_faces(outputs[method]["pose"][t, trial], half)
            ax.add_collection3d(
                Poly3DCollection(faces, facecolor="none", edgecolor=color, linewidths=0.8)
            )
            if "cloud" in outputs[method] and trial == 0:
                cloud = outputs[method]["cloud"][t]
                ax.scatter(*cloud[:, :3].T.tolist(), s=2, color=color, label=method)
            else:
                ax.plot([], [], color=color, label=method)
        ax.set(
            xlim=(float(centre[0]) - reach, float(centre[0]) + reach),
            ylim=(float(centre[1]) - reach, float(centre[1]) + reach),
            zlim=(0.0, 2 * reach),
        )
        occluded = " (occluded)" if bool(trials.occluded[t]) else ""
        ax.set_title(f"t = {H * (t + 1):.2f} s{occluded}", fontsize=9)
        ax.tick_params(labelsize=6)
    fig.axes[0].plot([], [], color="C0", label="camera (last seen)")
    fig.axes[0].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    return fig


def plot_box_states(trials: BoxTrials, state_probs: Tensor, *, trial: int = 0) -> Figure:
    """Contact-state timelines of one trial: per pair of :data:`BOX_PAIRS`, the filter's
    probability of each state (shade), the true state (circles) and the most probable one
    (dots).

    Args:
        trials: the trials.
        state_probs: ``(T, B, P, 3)`` a filter's contact-state probabilities.
        trial: which trial.
    """
    import matplotlib.pyplot as plt

    time_s = H * torch.arange(1, trials.steps + 1)
    fig, axes = plt.subplots(len(BOX_PAIRS), 1, figsize=(9, 1.1 * len(BOX_PAIRS) + 1), sharex=True)
    extent = (float(time_s[0]) - H / 2, float(time_s[-1]) + H / 2, -0.5, 2.5)
    for p, (ax, name) in enumerate(zip(axes, BOX_PAIRS, strict=True)):
        probs = state_probs[:, trial, p]
        ax.imshow(
            probs.T.numpy(),
            aspect="auto",
            origin="lower",
            cmap="Blues",
            vmin=0,
            vmax=1,
            extent=extent,
        )
        times = time_s.numpy()
        truth = trials.states[:, trial, p].numpy()
        ax.plot(times, truth, "o", mfc="none", color="C3", ms=5, label="truth")
        ax.plot(times, probs.argmax(-1).numpy(), "k.", ms=3, label="most probable")
        if int(trials.tip_step[trial]) >= 0:
            ax.axvline(H * (int(trials.tip_step[trial]) + 1), color="C1", lw=1)
        ax.set_yticks(range(3), _STATE_NAMES, fontsize=6)
        ax.set_ylabel(name, fontsize=8)
    axes[0].legend(fontsize=7, loc="upper left", ncol=2)
    axes[-1].set_xlabel("time (s); orange line: true tip-over")
    fig.tight_layout()
    return fig
