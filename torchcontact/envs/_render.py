"""Rendering the peg-in-hole scene to an RGB array with matplotlib (no pyplot state)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from numpy.typing import NDArray
from torch import Tensor

from torchcontact.sim import Scene, draw_scene


def render_frame(
    scene: Scene,
    *,
    q: Tensor,
    gripper: Tensor,
    extent: tuple[float, float, float, float],
    size: tuple[int, int] = (480, 360),
) -> NDArray[np.uint8]:
    """Draw one configuration with :func:`~torchcontact.sim.draw_scene` and return its pixels.

    Args:
        scene: the scene.
        q: ``(Nd, 3)`` dynamic-body poses.
        gripper: ``(3,)`` gripper pose, drawn as a cross with its ``y`` axis.
        extent: ``(x_min, x_max, y_min, y_max)`` of the view, metres.
        size: ``(width, height)`` of the image in pixels.

    Returns:
        ``(height, width, 3)`` uint8 RGB image.
    """
    width, height = size
    figure = Figure(figsize=(width / 100, height / 100), dpi=100)
    canvas: Any = FigureCanvasAgg(figure)
    ax = figure.add_axes((0.0, 0.0, 1.0, 1.0))
    draw_scene(ax, scene, q=q, extent=extent[1] - extent[0])
    pose = gripper.detach().to("cpu", torch.float64).tolist()
    x, y, angle = pose
    length = 0.02
    ax.plot([x], [y], marker="+", color="tab:red", markersize=10)
    direction = np.array([-np.sin(angle), np.cos(angle)]) * length
    ax.plot([x, x + direction[0]], [y, y + direction[1]], color="tab:red", lw=1.5)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_axis_off()
    canvas.draw()
    pixels = np.asarray(canvas.buffer_rgba())[..., :3]
    return np.ascontiguousarray(pixels, dtype=np.uint8)
