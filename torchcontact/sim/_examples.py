"""A ready-made scene for filters, tutorials and benchmarks: a finger pushing a box."""

from __future__ import annotations

import torch
from torch import Tensor

from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim._scene import Body, Scene
from torchcontact.sim._simulator import Rollout, Simulator

BOX_SIZE = (0.2, 0.1)  # width, height (metres)
FINGER_SIZE = (0.02, 0.06)
FINGER_HEIGHT = 0.035  # finger centre above the ground (below the box's top)


def pushed_box_scene(*, friction: float = 0.4, h: float = 0.01, mass: float = 1.0) -> Scene:
    """A box (0.2 × 0.1 m) resting on the ground and a kinematic finger (0.02 × 0.06 m) that can
    push its left face: 12 contact slots (box corners against the ground and the finger, the
    finger's corners against the box)."""
    return Scene(
        bodies=(
            Body("ground", HalfPlane.ground(), kind="static"),
            Body("box", Polygon.box(*BOX_SIZE), mass=mass),
            Body("finger", Polygon.box(*FINGER_SIZE), kind="kinematic"),
        ),
        friction=friction,
        h=h,
    )


def pushed_box_rollout(
    scene: Scene, *, batch: int, steps: int, seed: int
) -> tuple[Rollout, Tensor]:
    """The finger pushes the resting box at a random speed (0.2–0.6 m/s) for the first third of
    the steps, pauses, pushes again from half to five sixths, then stops; it starts 15–45 mm
    from the box. Contact modes switch between resting, pushed (sliding on the ground with the
    finger sticking), coasting to a stop, and rocking on a corner at push onsets.

    Args:
        scene: :func:`pushed_box_scene` (or one with the same bodies).
        batch: number of independent rollouts ``B``.
        steps: ``T``.
        seed: seed of the random speeds and start gaps.

    Returns:
        The float64 :class:`Rollout` (batch ``B``) and the finger twists ``(T, B, 1, 3)``.
    """
    dtype = torch.float64
    gen = torch.Generator().manual_seed(seed)
    speed = 0.2 + 0.4 * torch.rand(batch, generator=gen, dtype=dtype)
    controls = torch.zeros(steps, batch, 1, 3, dtype=dtype)
    pushing = torch.zeros(steps, dtype=torch.bool)
    pushing[: steps // 3] = True
    pushing[steps // 2 : 5 * steps // 6] = True
    controls[pushing, :, 0, 0] = speed
    box_x = torch.zeros(batch, dtype=dtype)
    q_box = torch.stack([box_x, box_x + BOX_SIZE[1] / 2, box_x], -1)[:, None]
    gap = 0.015 + 0.03 * torch.rand(batch, generator=gen, dtype=dtype)
    finger_x = -(BOX_SIZE[0] + FINGER_SIZE[0]) / 2 - gap
    q_finger = torch.stack([finger_x, torch.full_like(finger_x, FINGER_HEIGHT), 0 * gap], -1)
    simulator = Simulator(scene)
    state = simulator.initial_state(q=q_box, q_kinematic=q_finger[:, None])
    return simulator.rollout(state, steps=steps, controls=controls), controls
