"""The penetrating contact slots of many states, without assembling the rest of the problem."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torchcontact._checks import check_batched, check_float
from torchcontact.geometry import planar_slots
from torchcontact.sim._assemble import dynamic_rows, scene_layout, shape_poses
from torchcontact.sim._scene import Scene


def penetration(scene: Scene, *, q: Tensor, q_kinematic: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Which contact slots of a batch of states penetrate, with their gaps and normal rows.

    A slot penetrates when it is a candidate (:class:`~torchcontact.geometry.SlotGeometry`'s
    ``active``) with a negative gap. Where it does, its gap and its row of ``Jn`` are those of
    :func:`~torchcontact.sim.contact_problem` at the state (the same functions on the same
    numbers), less everything the problem also holds (velocities, tangents, known terms,
    friction): the cheap query of a filter that projects many particles out of the bodies.

    Args:
        scene: the scene.
        q: ``(*B, Nd, 3)`` poses of the dynamic bodies (world frame).
        q_kinematic: ``(*B, Nk, 3)`` poses of the kinematic bodies (world frame).

    Returns:
        ``phi (*B, K)`` gaps, ``Jn (*B, K, 3 Nd)`` normal rows and the bool ``(*B, K)``
        penetrating slots; ``phi`` and ``Jn`` are zero at the slots that do not penetrate.

    Raises:
        ValueError: ``q`` or ``q_kinematic`` is not a finite float32/float64 tensor of the
            documented shape, or their dtypes differ.
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a Scene, got {type(scene).__name__}")
    num_dynamic, num_kinematic = len(scene.dynamic), len(scene.kinematic)
    q = check_float("q", q, trailing=(num_dynamic, 3), min_ndim=2, what=f"(*B, {num_dynamic}, 3)")
    batch = q.shape[:-2]
    check_batched(
        "q_kinematic", q_kinematic, shape=(*batch, num_kinematic, 3), like=q, like_name="q"
    )
    P, K = math.prod(batch), scene.num_slots
    layout = scene_layout(scene, q.dtype, q.device)
    poses = shape_poses(
        layout, q.reshape(P, num_dynamic, 3), q_kinematic.reshape(P, num_kinematic, 3)
    )
    geometry = planar_slots(layout.slots, poses)
    keep = torch.arange(K, device=q.device).expand(P, K)
    Jn = dynamic_rows(layout, poses, geometry.points, geometry.normals.unsqueeze(-2), keep)
    penetrating = geometry.active & (geometry.phi < 0)
    return (
        geometry.phi.where(penetrating, 0.0).reshape(*batch, K),
        (Jn[..., 0, :] * penetrating[..., None]).reshape(*batch, K, 3 * num_dynamic),
        penetrating.reshape(*batch, K),
    )
