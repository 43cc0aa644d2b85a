"""Drawing planar scenes with matplotlib."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from torchcontact.geometry import HalfPlane, Polygon, perpendicular, transform_points
from torchcontact.sim._scene import Scene

_COLORS = {"dynamic": "tab:blue", "kinematic": "tab:orange", "static": "0.6"}


def draw_scene(
    ax: Any,
    scene: Scene,
    *,
    q: Tensor,
    q_kinematic: Tensor | None = None,
    alpha: float = 1.0,
    extent: float = 3.0,
) -> None:
    """Draw one configuration of a scene on matplotlib axes.

    Args:
        ax: matplotlib ``Axes``.
        scene: the scene.
        q: ``(Nd, 3)`` dynamic-body poses (world frame).
        q_kinematic: ``(Nk, 3)`` kinematic-body poses.
        alpha: opacity of the bodies (lower it to overlay a trajectory).
        extent: half-length in metres of the drawn part of each half-plane.
    """
    from matplotlib.patches import Polygon as PolygonPatch  # drawing loads matplotlib

    q = q.detach().to("cpu", torch.float64)
    for i, body in enumerate(scene.bodies):
        color = _COLORS[body.kind]
        if isinstance(body.shape, HalfPlane):
            normal = body.shape.normal.to(torch.float64)
            along = perpendicular(normal)
            point = body.shape.point.to(torch.float64)
            corners = torch.stack(
                [
                    point - extent * along,
                    point + extent * along,
                    point + extent * along - 0.1 * extent * normal,
                    point - extent * along - 0.1 * extent * normal,
                ]
            )
            ax.add_patch(PolygonPatch(corners.numpy(), closed=True, color=color, alpha=0.5))
            continue
        assert isinstance(body.shape, Polygon)
        if body.kind == "dynamic":
            pose = q[scene.dynamic.index(i)]
        elif body.kind == "kinematic":
            if q_kinematic is None:
                continue
            pose = q_kinematic.detach().to("cpu", torch.float64)[scene.kinematic.index(i)]
        else:
            assert body.pose is not None
            pose = body.pose.to(torch.float64)
        corners = transform_points(pose, body.shape.vertices.to(torch.float64))
        patch = PolygonPatch(
            corners.numpy(), closed=True, facecolor=color, edgecolor="k", alpha=alpha
        )
        ax.add_patch(patch)
    ax.set_aspect("equal")
    ax.autoscale_view()
