"""penetration(): the penetrating slots of contact_problem, to rounding, for less work."""

from __future__ import annotations

import math

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


def _grasp_scene() -> Scene:
    return Scene(
        bodies=(
            Body("table", HalfPlane.ground(), kind="static"),
            Body("triangle", Polygon.triangle(0.08, 0.0693), mass=0.2),
            Body("left", Polygon.box(0.01, 0.03), kind="kinematic"),
            Body("right", Polygon.box(0.01, 0.03), kind="kinematic"),
        ),
        friction=0.5,
    )


def _states_at_the_boxes(dtype: torch.dtype, count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Triangles whose right base vertex lies on the right finger's boundary, where the sign
    of its gap is rounding's: at a corner or on an edge of the finger, upright or turned by a
    multiple of 90° (its sides on its bounding box's) or at any angle, some moved by ``δ``
    across it (``|δ|`` from 1e-17 to 1e-6); the left finger is far."""
    gen = torch.Generator().manual_seed(6)
    finger = Polygon.box(0.01, 0.03).vertices
    angle = 2 * math.pi * torch.rand(count, generator=gen, dtype=F64)
    square = torch.rand(count, generator=gen) < 0.5
    angle[square] = math.pi / 2 * torch.randint(0, 4, (int(square.sum()),), generator=gen).to(F64)
    position = 2 * torch.rand(count, 2, generator=gen, dtype=F64) - 1
    cos, sin = angle.cos()[:, None], angle.sin()[:, None]
    world = (
        torch.stack(
            [finger[:, 0] * cos - finger[:, 1] * sin, finger[:, 0] * sin + finger[:, 1] * cos], -1
        )
        + position[:, None]
    )  # (count, 4, 2)
    edge = torch.randint(0, 4, (count,), generator=gen)
    along = torch.rand(count, 1, generator=gen, dtype=F64)
    along[torch.rand(count, generator=gen) < 0.5] = 0.0  # a corner
    rows = torch.arange(count)
    start, end = world[rows, edge], world[rows, (edge + 1) % 4]
    vertex = start + along * (end - start)
    delta = 10.0 ** -torch.randint(6, 18, (count, 2), generator=gen).to(F64)
    sign = torch.randint(-1, 2, (count, 2), generator=gen).to(F64)  # −1, 0 or 1
    vertex = vertex + sign * delta
    triangle = Polygon.triangle(0.08, 0.0693).vertices
    q = torch.cat([vertex - triangle[1], torch.zeros(count, 1, dtype=F64)], -1)[:, None]
    far = torch.tensor([-5.0, 0.04, 0.0], dtype=F64).expand(count, 3)
    q_kinematic = torch.stack([far, torch.cat([position, angle[:, None]], -1)], 1)
    return q.to(dtype), q_kinematic.to(dtype)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_cull_is_exact_at_the_fingers_boxes(dtype: torch.dtype) -> None:
    """Random states, most with the fingers far from the triangle (culled), some overlapping
    it, and states on the boundaries of a finger's bounding box: every state where
    contact_problem finds a penetrating triangle–finger slot passes the box test, so the
    culled query finds what computing every slot finds (without the boxes' widening, some
    boundary states penetrate by rounding from just outside the box and fail here)."""
    from torchcontact.sim._penetration import _culling, _near

    scene = _grasp_scene()
    gen = torch.Generator().manual_seed(5)
    P = 800
    rest = -float(Polygon.triangle(0.08, 0.0693).vertices[:, 1].min())
    noise = torch.rand(P, 3, generator=gen, dtype=F64) - 0.5
    q = torch.stack([0.02 * noise[:, 0], rest + 0.004 * noise[:, 1], 0.4 * noise[:, 2]], -1)
    close = torch.rand(P, generator=gen, dtype=F64) < 0.1
    gap = torch.where(close, 0.035 + 0.02 * noise[:, 0], 0.08 + 0.2 * noise[:, 1].abs())
    q_kinematic = torch.zeros(P, 2, 3, dtype=F64)
    q_kinematic[:, :, 0] = torch.stack([-gap, gap], -1)
    q_kinematic[:, :, 1] = 0.025
    q_kinematic[:, :, 2] = 0.3 * noise[:, None, 2]
    edge_q, edge_kinematic = _states_at_the_boxes(dtype, 20_000)
    q = torch.cat([q[:, None].to(dtype), edge_q])
    q_kinematic = torch.cat([q_kinematic.to(dtype), edge_kinematic])

    phi, Jn, penetrating = penetration(scene, q=q, q_kinematic=q_kinematic)
    phi_ref, Jn_ref, expected = _expected(scene, q, q_kinematic)
    fingers = torch.arange(scene.num_slots) >= 3  # every group but the triangle on the table
    near = _near(_culling(scene, dtype, q.device), torch.cat([q, q_kinematic], -2))
    culled = int((~near[:P]).sum())
    assert 0.8 * P < culled < P  # most random states skip the finger slots, not all
    assert not bool(expected[~near][:, fingers].any())  # the culled states did not penetrate
    edge = slice(P, None)
    assert bool(expected[edge, fingers].any())  # the boundary states do
    assert bool(expected[:P, fingers].any())
    # Where the gap's sign is not rounding's, the slots agree; where both penetrate, so do
    # their gaps and rows (the same functions on the same numbers).
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    clear = phi_ref.abs() > tol
    assert torch.equal(penetrating[clear], expected[clear])
    both = penetrating & expected
    atol = 1e-15 if dtype == torch.float64 else 1e-7
    torch.testing.assert_close(phi[both], phi_ref[both], rtol=tol, atol=atol)
    torch.testing.assert_close(Jn[both], Jn_ref[both], rtol=tol, atol=atol)
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
