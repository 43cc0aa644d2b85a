"""Planar shapes and contact slots against hand computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcontact.geometry import (
    HalfPlane,
    Polygon,
    planar_slot_table,
    planar_slots,
    transform_points,
)


def test_box_and_triangle_mass_properties_match_closed_form() -> None:
    box = Polygon.box(2.0, 1.0)
    assert box.area == pytest.approx(2.0)
    assert box.unit_inertia() == pytest.approx((2.0**2 + 1.0**2) / 12)
    triangle = Polygon.triangle(3.0, 2.0)
    assert triangle.area == pytest.approx(3.0)
    # Isosceles triangle about its centroid: (b² / 24 + h² / 18) per unit mass.
    assert triangle.unit_inertia() == pytest.approx(3.0**2 / 24 + 2.0**2 / 18)
    torch.testing.assert_close(triangle.vertices.mean(0), torch.zeros(2, dtype=torch.float64))


def test_regular_polygon_inertia_tends_to_disc() -> None:
    polygon = Polygon.regular(256, 0.5)
    assert polygon.unit_inertia() == pytest.approx(0.5**2 / 2, rel=1e-3)


@pytest.mark.parametrize(
    ("vertices", "message"),
    [
        ([[0.0, 0.0], [1.0, 0.0]], "at least 3"),
        ([[-1.0, -1.0], [-1.0, 1.0], [1.0, 1.0], [1.0, -1.0]], "counter-clockwise"),
        ([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]], "centroid"),
    ],
)
def test_bad_polygons_are_rejected(vertices, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Polygon(torch.tensor(vertices, dtype=torch.float64))


def _slots_by_loop(
    shapes: list[Polygon | HalfPlane],
    poses: list[tuple[float, float, float]],
    groups: list[tuple[int, int]],
    margin: float,
) -> list[tuple[tuple[float, float], tuple[float, float], float, bool]]:
    """The slots vertex by vertex, edge by edge, in Python floats: (point, normal, φ, active)."""

    def world(shape: Polygon, pose: tuple[float, float, float]) -> list[tuple[float, float]]:
        x, y, theta = pose
        c, s = math.cos(theta), math.sin(theta)
        return [(x + c * px - s * py, y + s * px + c * py) for px, py in shape.vertices.tolist()]

    slots = []
    for receiver, other in groups:
        shape = shapes[receiver]
        assert isinstance(shape, Polygon)
        target = shapes[other]
        for p in world(shape, poses[receiver]):
            if isinstance(target, HalfPlane):
                n = tuple(target.normal.tolist())
                p0 = target.point.tolist()
                phi = n[0] * (p[0] - p0[0]) + n[1] * (p[1] - p0[1])
                slots.append((p, n, phi, phi <= margin))
                continue
            corners = world(target, poses[other])
            centre = (
                sum(c[0] for c in corners) / len(corners),
                sum(c[1] for c in corners) / len(corners),
            )
            edges = []
            for e, a in enumerate(corners):
                b = corners[(e + 1) % len(corners)]
                length = math.hypot(b[0] - a[0], b[1] - a[1])
                d = ((b[0] - a[0]) / length, (b[1] - a[1]) / length)
                n = (d[1], -d[0])
                distance = n[0] * (p[0] - a[0]) + n[1] * (p[1] - a[1])
                along = d[0] * (p[0] - a[0]) + d[1] * (p[1] - a[1])
                facing = n[0] * (p[0] - centre[0]) + n[1] * (p[1] - centre[1])
                edges.append((distance, facing, n, along, length))
            phi = max(edge[0] for edge in edges)
            longest = max(edge[4] for edge in edges)
            tied = [edge for edge in edges if edge[0] >= phi - 1e-9 * longest]
            _, _, n, along, length = max(tied, key=lambda edge: edge[1])
            active = phi <= margin and -margin <= along <= length + margin
            slots.append((p, n, phi, active))
    return slots


#: Slot groups of :func:`_random_scene`: every pair, and the pentagon against the others only
#: (its five vertices, but at most four edges to test against).
GROUPS = {
    "all": [(0, 1), (1, 0), (0, 2), (2, 0), (1, 2), (2, 1), (0, 3), (1, 3), (2, 3)],
    "fewer edges": [(2, 0), (2, 1), (2, 3)],
}


def _random_scene(
    seed: int, groups: str = "all"
) -> tuple[list[Polygon | HalfPlane], torch.Tensor, list[tuple[int, int]]]:
    """A box, a triangle, a pentagon and a tilted ground, at random nearby poses."""
    shapes: list[Polygon | HalfPlane] = [
        Polygon.box(0.4, 0.2),
        Polygon.triangle(0.3, 0.25),
        Polygon.regular(5, 0.15),
        HalfPlane.ground(0.02, 0.1),
    ]
    gen = torch.Generator().manual_seed(seed)
    poses = torch.zeros(64, 4, 3, dtype=torch.float64)
    poses[:, :3, :2] = 0.3 * torch.rand(64, 3, 2, generator=gen, dtype=torch.float64)
    poses[:, :3, 2] = 2 * math.pi * torch.rand(64, 3, generator=gen, dtype=torch.float64)
    return shapes, poses, GROUPS[groups]


@pytest.mark.parametrize("groups", GROUPS)
def test_planar_slots_match_a_vertex_by_vertex_loop(groups: str) -> None:
    shapes, poses, pairs = _random_scene(0, groups)
    table = planar_slot_table(shapes, pairs, margin=0.05)
    slots = planar_slots(table, poses)
    assert slots.phi.shape == (64, table.num_slots)
    seen_active = 0
    for b in range(poses.shape[0]):
        expected = _slots_by_loop(shapes, [tuple(p) for p in poses[b].tolist()], pairs, 0.05)
        points, normals, phi, active = zip(*expected, strict=True)
        torch.testing.assert_close(slots.points[b], torch.tensor(points, dtype=torch.float64))
        torch.testing.assert_close(slots.normals[b], torch.tensor(normals, dtype=torch.float64))
        torch.testing.assert_close(slots.phi[b], torch.tensor(phi, dtype=torch.float64))
        # A candidate test within round-off of its bound may go either way.
        assert slots.active[b].tolist() == list(active)
        seen_active += sum(active)
    assert seen_active > 20


def test_planar_slots_in_float32_match_float64() -> None:
    shapes, poses, groups = _random_scene(1)
    table = planar_slot_table(shapes, groups, margin=0.05)
    wide = planar_slots(table, poses)
    narrow = planar_slots(table.to(dtype=torch.float32), poses.float())
    torch.testing.assert_close(narrow.phi.double(), wide.phi, atol=1e-6, rtol=0)
    torch.testing.assert_close(narrow.points.double(), wide.points, atol=1e-6, rtol=0)
    # Away from candidate boundaries and edge ties the discrete choices agree.
    assert float((narrow.active == wide.active).double().mean()) > 0.99


@pytest.mark.parametrize(
    "chosen",
    [[8, 6, 7], [0, 5, 1], [4], list(range(9))],
    ids=["half-planes", "polygons", "one", "all"],
)
def test_a_subtable_computes_its_groups_slots(chosen: list[int]) -> None:
    """The groups' slots of a subtable (its shapes' poses selected) against the full table's:
    the same rows, so the same numbers, with the padding cut (three half-plane groups need one
    edge, not five)."""
    shapes, poses, pairs = _random_scene(4)
    table = planar_slot_table(shapes, pairs, margin=0.05)
    sub, picked, slots = table.subtable(chosen)
    full = planar_slots(table, poses)
    part = planar_slots(sub, poses.index_select(-2, picked))
    starts = [0, *torch.tensor([len(shapes[r].vertices) for r, _ in pairs]).cumsum(0).tolist()]
    expected = [
        k for g in range(len(pairs)) if g in chosen for k in range(starts[g], starts[g + 1])
    ]
    assert slots.tolist() == expected
    assert picked.tolist() == sorted({i for g in chosen for i in pairs[g]})
    assert sub.num_slots == len(expected)
    if chosen == [8, 6, 7]:
        assert sub.facing_offset.shape[-1] == 1  # one edge: the half-plane's
    torch.testing.assert_close(part.points, full.points[:, slots], rtol=0, atol=1e-15)
    torch.testing.assert_close(part.normals, full.normals[:, slots], rtol=0, atol=1e-15)
    torch.testing.assert_close(part.phi, full.phi[:, slots], rtol=0, atol=1e-15)
    assert part.active.tolist() == full.active[:, slots].tolist()
    assert bool(part.active.any())


def test_bad_subtables_name_the_groups() -> None:
    shapes, _, pairs = _random_scene(4)
    table = planar_slot_table(shapes, pairs, margin=0.05)
    for groups in ([], [0, 0], [9], [-1]):
        with pytest.raises(ValueError, match=r"^groups must be distinct group indices"):
            table.subtable(groups)


@pytest.mark.parametrize("groups", GROUPS)
def test_planar_slot_tangents_match_automatic_differentiation(groups: str) -> None:
    """Derivatives along random pose directions against ``jacfwd``."""
    shapes, poses, pairs = _random_scene(2, groups)
    table = planar_slot_table(shapes, pairs, margin=0.05)
    gen = torch.Generator().manual_seed(3)
    directions = torch.randn(64, 2, 4, 3, generator=gen, dtype=torch.float64)
    directions[..., 3, :] = 0.0  # the ground stays
    stacked = planar_slots(table, poses, directions)
    plain = planar_slots(table, poses)
    torch.testing.assert_close(stacked.phi[:, 0], plain.phi, rtol=0, atol=1e-15)
    torch.testing.assert_close(stacked.normals[:, 0], plain.normals, rtol=0, atol=1e-15)

    def values(pose: torch.Tensor) -> torch.Tensor:
        slots = planar_slots(table, pose)
        return torch.cat([slots.points, slots.normals, slots.phi.unsqueeze(-1)], dim=-1)

    agree = 0
    for b in range(8):
        jac = torch.func.jacfwd(values)(poses[b])  # (S, 5, 4, 3)
        expected = torch.einsum("skij,tij->tsk", jac, directions[b])
        actual = torch.cat(
            [stacked.points[b, 1:], stacked.normals[b, 1:], stacked.phi[b, 1:, :, None]], -1
        )
        agree += int(((actual - expected).abs().amax(dim=(0, 2)) <= 1e-12).sum())
    assert agree == 8 * table.num_slots


def test_vertex_against_polygon_edge_distance_and_normal() -> None:
    """A small box's corners 0.1 right of a unit square, and 0.05 inside near its top edge."""
    square, box = Polygon.box(1.0, 1.0), Polygon.box(0.2, 0.2)
    table = planar_slot_table([box, square], [(0, 1)], margin=0.2)
    poses = torch.tensor([[[0.7, 0.0, 0.0], [0.0, 0.0, 0.0]]], dtype=torch.float64)
    slots = planar_slots(table, poses)
    # Corners (0.6, ±0.1) face the right edge at 0.1; (0.8, ±0.1) at 0.3, beyond the margin.
    torch.testing.assert_close(
        slots.phi[0], torch.tensor([0.1, 0.3, 0.3, 0.1], dtype=torch.float64)
    )
    torch.testing.assert_close(slots.normals[0], torch.tensor([[1.0, 0.0]] * 4).double())
    assert slots.active[0].tolist() == [True, False, False, True]
    # Its bottom corners (±0.1, 0.45) 0.05 inside, nearest the top edge.
    inside = planar_slots(table, torch.tensor([[[0.0, 0.55, 0.0], [0.0, 0.0, 0.0]]]).double())
    torch.testing.assert_close(inside.phi[0, :2], torch.tensor([-0.05, -0.05]).double())
    torch.testing.assert_close(inside.normals[0, :2], torch.tensor([[0.0, 1.0]] * 2).double())


def test_vertex_at_a_corner_takes_the_edge_facing_it() -> None:
    """Aligned boxes side by side: the touching vertices lie on two edges of the other box.

    Seen from the 1 × 0.5 box's centre its corner (−0.5, −0.25) lies more to the left than
    below, so the left edge (normal −x) is the contact feature, not the bottom edge.
    """
    box = Polygon.box(1.0, 0.5)
    table = planar_slot_table([box, box], [(0, 1)], margin=0.1)
    poses = torch.tensor([[[-1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]], dtype=torch.float64)
    slots = planar_slots(table, poses)
    # The receiver's right corners (1 and 2) touch the other box's left corners.
    torch.testing.assert_close(slots.normals[0, 1:3], torch.tensor([[-1.0, 0.0]] * 2).double())
    torch.testing.assert_close(slots.phi[0, 1:3], torch.zeros(2, dtype=torch.float64))


def test_halfplane_slots_of_a_tilted_box() -> None:
    box = Polygon.box(1.0, 0.5)
    pose = torch.tensor([0.0, 0.4, math.radians(30)], dtype=torch.float64)
    world = transform_points(pose, box.vertices)
    table = planar_slot_table([box, HalfPlane.ground()], [(0, 1)], margin=0.05)
    slots = planar_slots(table, torch.stack([pose, torch.zeros(3, dtype=torch.float64)]))
    torch.testing.assert_close(slots.phi, world[:, 1])
    lowest = int(world[:, 1].argmin())
    assert slots.active.tolist() == [i == lowest for i in range(4)]


def test_bad_slot_tables_name_the_argument() -> None:
    box = Polygon.box(1.0, 0.5)
    with pytest.raises(ValueError, match="shapes"):
        planar_slot_table([HalfPlane.ground()], [], margin=0.1)
    with pytest.raises(ValueError, match="groups"):
        planar_slot_table([box, HalfPlane.ground()], [(1, 0)], margin=0.1)
    with pytest.raises(ValueError, match="groups"):
        planar_slot_table([box], [(0, 2)], margin=0.1)
    with pytest.raises(ValueError, match="margin"):
        planar_slot_table([box, box], [(0, 1)], margin=-0.1)


@pytest.mark.bitwise("an angle in range is returned unchanged: θ − 2π·0")
def test_wrap_angle_matches_numpys_modulo_and_keeps_angles_in_range() -> None:
    from torchcontact.geometry import wrap_angle

    gen = torch.Generator().manual_seed(0)
    angle = 200.0 * torch.rand(1000, generator=gen, dtype=torch.float64) - 100.0
    wrapped = wrap_angle(angle)
    expected = np.mod(angle.numpy() + np.pi, 2 * np.pi) - np.pi
    np.testing.assert_allclose(wrapped.numpy(), expected, rtol=0, atol=1e-13)
    assert bool((wrapped >= -math.pi).all())
    assert bool((wrapped < math.pi).all())
    inside = torch.tensor([-math.pi, -1.0, 0.0, 3.0], dtype=torch.float64)
    assert torch.equal(wrap_angle(inside), inside)


def test_quaternion_rotation_matrices_match_scipy() -> None:
    from scipy.spatial.transform import Rotation

    from torchcontact.geometry import quat_to_matrix

    gen = torch.Generator().manual_seed(1)
    q = torch.randn(50, 4, generator=gen, dtype=torch.float64)  # normalized by the function
    expected = Rotation.from_quat(q[:, [1, 2, 3, 0]].numpy()).as_matrix()  # scalar last
    np.testing.assert_allclose(quat_to_matrix(q).numpy(), expected, rtol=0, atol=1e-14)
