"""penetration(): the penetrating slots of contact_problem, to rounding, for less work."""

from __future__ import annotations

import pytest
import torch

from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import Body, Scene, SceneState, contact_problem, penetration

F64 = torch.float64


def _expected(scene: Scene, q: torch.Tensor, q_kinematic: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """contact_problem's gaps, normal rows and penetrating slots (the slow reference)."""
    batch = q.shape[:-2]
    state = SceneState(
        q=q,
        v=torch.zeros_like(q),
        q_kinematic=q_kinematic,
        mode=torch.zeros(*batch, scene.num_slots, dtype=torch.long),
    )
    problem, geometry = contact_problem(scene, state)
    return geometry.phi, problem.Jn, geometry.active & (geometry.phi < 0)


def test_a_grasped_triangle_equals_contact_problem_where_fingers_are_culled() -> None:
    """Kinematic fingers near and far from a triangle on a table: most states skip the
    finger slots (no vertex in the other's bounding box)."""
    scene = Scene(
        bodies=(
            Body("table", HalfPlane.ground(), kind="static"),
            Body("triangle", Polygon.triangle(0.08, 0.0693), mass=0.2),
            Body("left", Polygon.box(0.01, 0.04), kind="kinematic"),
            Body("right", Polygon.box(0.01, 0.04), kind="kinematic"),
        ),
        friction=0.5,
    )
    gen = torch.Generator().manual_seed(0)
    P = 600
    rest = -float(Polygon.triangle(0.08, 0.0693).vertices[:, 1].min())
    noise = torch.rand(P, 3, generator=gen, dtype=F64) - 0.5
    q = torch.stack([0.03 * noise[:, 0], rest + 0.004 * noise[:, 1], 0.2 * noise[:, 2]], -1)
    gap = 0.02 + 0.05 * torch.rand(P, generator=gen, dtype=F64)  # the fingers' |x|
    q_kinematic = torch.zeros(P, 2, 3, dtype=F64)
    q_kinematic[:, :, 0] = torch.stack([-gap, gap], -1)
    q_kinematic[:, :, 1] = 0.02
    phi, Jn, penetrating = penetration(
        scene, q=q.view(20, 30, 1, 3), q_kinematic=q_kinematic.view(20, 30, 2, 3)
    )
    assert phi.shape == penetrating.shape == (20, 30, scene.num_slots)
    assert Jn.shape == (20, 30, scene.num_slots, 3)
    phi, Jn, penetrating = phi.view(P, -1), Jn.view(P, -1, 3), penetrating.view(P, -1)
    phi_ref, Jn_ref, expected = _expected(scene, q[:, None], q_kinematic)
    assert torch.equal(penetrating, expected)
    table = torch.arange(scene.num_slots) < 3  # the triangle's vertices against the table
    assert bool(penetrating[:, table].any())
    assert bool(penetrating[:, ~table].any())
    assert not bool(penetrating[:, ~table].any(-1).all())  # some states cull the fingers
    torch.testing.assert_close(phi[penetrating], phi_ref[penetrating], rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(Jn[penetrating], Jn_ref[penetrating], rtol=1e-12, atol=1e-15)
    assert not bool(phi[~penetrating].any())
    assert not bool(Jn[~penetrating].any())


def test_two_dynamic_bodies_get_both_blocks_of_their_rows() -> None:
    """Two overlapping boxes on the ground: a slot between them carries +row for the
    receiver and −row for the other, in each body's three columns."""
    scene = Scene(
        bodies=(
            Body("ground", HalfPlane.ground(), kind="static"),
            Body("low", Polygon.box(0.2, 0.1), mass=1.0),
            Body("high", Polygon.box(0.1, 0.1), mass=0.5),
        ),
        friction=0.4,
    )
    gen = torch.Generator().manual_seed(1)
    P = 64
    noise = torch.rand(P, 2, 3, generator=gen, dtype=F64) - 0.5
    q = torch.tensor([[0.0, 0.05, 0.0], [0.0, 0.145, 0.0]], dtype=F64) + noise * torch.tensor(
        [0.05, 0.02, 0.1], dtype=F64
    )
    q_kinematic = torch.zeros(P, 0, 3, dtype=F64)
    phi, Jn, penetrating = penetration(scene, q=q, q_kinematic=q_kinematic)
    phi_ref, Jn_ref, expected = _expected(scene, q, q_kinematic)
    assert Jn.shape == (P, scene.num_slots, 6)
    assert torch.equal(penetrating, expected)
    between = [g for g in scene.slot_groups if {g.receiver, g.other} == {1, 2}]
    columns = torch.cat([torch.arange(g.start, g.start + g.count) for g in between])
    assert bool(penetrating[:, columns].any())
    rows = Jn[:, columns][penetrating[:, columns]]  # (R, 6): both bodies' blocks filled
    assert bool((rows[:, :3] != 0).any(-1).all())
    assert bool((rows[:, 3:] != 0).any(-1).all())
    torch.testing.assert_close(phi[penetrating], phi_ref[penetrating], rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(Jn[penetrating], Jn_ref[penetrating], rtol=1e-12, atol=1e-15)


def test_bad_shapes_name_the_argument() -> None:
    scene = Scene(
        bodies=(
            Body("ground", HalfPlane.ground(), kind="static"),
            Body("box", Polygon.box(0.2, 0.1), mass=1.0),
        ),
        friction=0.4,
    )
    q = torch.zeros(4, 1, 3, dtype=F64)
    with pytest.raises(ValueError, match=r"^q must have shape"):
        penetration(scene, q=torch.zeros(4, 3, dtype=F64), q_kinematic=torch.zeros(4, 0, 3))
    with pytest.raises(ValueError, match=r"^q_kinematic must have shape"):
        penetration(scene, q=q, q_kinematic=torch.zeros(4, 1, 3, dtype=F64))
