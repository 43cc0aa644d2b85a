"""Rendering the peg-in-hole scene to an RGB array with matplotlib (no pyplot state)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from numpy.typing import NDArray
from torch import Tensor

from torchcontact.envs._task import PegInHoleTask, Physics
from torchcontact.sim import Scene, draw_scene

#: ``(width, height)`` of the environments' frames in pixels.
FRAME_SIZE = (480, 360)


def render_frame(
    scene: Scene,
    *,
    q: Tensor,
    gripper: Tensor,
    extent: tuple[float, float, float, float],
    size: tuple[int, int] = FRAME_SIZE,
) -> NDArray[np.uint8]:
    """Draw one configuration with :func:`~torchcontact.sim.draw_scene` and return its pixels.

    The view is ``extent`` widened about its centre along one axis to the image's aspect
    ratio, so that one metre spans as many pixels along ``x`` as along ``y`` and the axes fill
    the image: the limits and the equal aspect then agree, and matplotlib has nothing to
    adjust (it warns when both limits are fixed and the aspect must be made by moving them).

    Args:
        scene: the scene.
        q: ``(Nd, 3)`` dynamic-body poses.
        gripper: ``(3,)`` gripper pose, drawn as a cross with its ``y`` axis.
        extent: ``(x_min, x_max, y_min, y_max)`` the view must hold, metres.
        size: ``(width, height)`` of the image in pixels.

    Returns:
        ``(height, width, 3)`` uint8 RGB image.
    """
    width, height = size
    x_min, x_max, y_min, y_max = view_extent(extent, size)
    figure = Figure(figsize=(width / 100, height / 100), dpi=100)
    canvas: Any = FigureCanvasAgg(figure)
    ax = figure.add_axes((0.0, 0.0, 1.0, 1.0))
    draw_scene(ax, scene, q=q, extent=x_max - x_min)
    pose = gripper.detach().to("cpu", torch.float64).tolist()
    x, y, angle = pose
    length = 0.02
    ax.plot([x], [y], marker="+", color="tab:red", markersize=10)
    direction = np.array([-np.sin(angle), np.cos(angle)]) * length
    ax.plot([x, x + direction[0]], [y, y + direction[1]], color="tab:red", lw=1.5)
    ax.set_xlim(x_min, x_max)
    ax.set_ylim(y_min, y_max)
    ax.set_aspect("equal", adjustable="box")
    ax.set_axis_off()
    canvas.draw()
    pixels = np.asarray(canvas.buffer_rgba())[..., :3]
    return np.ascontiguousarray(pixels, dtype=np.uint8)


def view_extent(
    extent: tuple[float, float, float, float], size: tuple[int, int]
) -> tuple[float, float, float, float]:
    """``extent`` widened about its centre along ``x`` or ``y`` to the aspect of ``size``.

    Args:
        extent: ``(x_min, x_max, y_min, y_max)``, metres.
        size: ``(width, height)`` in pixels.

    Returns:
        ``(x_min, x_max, y_min, y_max)`` holding ``extent``, with
        ``(x_max − x_min) / (y_max − y_min) = width / height``.
    """
    x_min, x_max, y_min, y_max = extent
    ratio = size[0] / size[1]
    span_x, span_y = x_max - x_min, y_max - y_min
    if span_x < ratio * span_y:
        grow = (ratio * span_y - span_x) / 2
        x_min, x_max = x_min - grow, x_max + grow
    else:
        grow = (span_x / ratio - span_y) / 2
        y_min, y_max = y_min - grow, y_max + grow
    return x_min, x_max, y_min, y_max


def render_environment(task: PegInHoleTask, physics: Physics, index: int) -> NDArray[np.uint8]:
    """The frame of environment ``index`` of a batch: the blocks' width, table to gripper.

    Args:
        task: the task.
        physics: the batch.
        index: the environment to draw.

    Returns:
        ``(360, 480, 3)`` uint8 RGB image (:data:`FRAME_SIZE`).
    """
    c = task.config
    span = c.hole_width / 2 + c.block_width
    top = max(c.workspace_y[1], float(physics.gripper[index, 1]) + c.finger_height)
    return render_frame(
        task.scene,
        q=physics.state.q[index],
        gripper=physics.gripper[index],
        extent=(-span, span, -0.02, top),
    )
