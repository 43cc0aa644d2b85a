"""Planar shapes and contact slots against hand computations."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchcontact.geometry import (
    HalfPlane,
    Polygon,
    halfplane_slots,
    polygon_slots,
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


def test_halfplane_slots_of_a_tilted_box() -> None:
    box = Polygon.box(1.0, 0.5)
    pose = torch.tensor([0.0, 0.4, math.radians(30)], dtype=torch.float64)
    world = transform_points(pose, box.vertices)
    slots = halfplane_slots(world, HalfPlane.ground(), margin=0.05)
    torch.testing.assert_close(slots.phi, world[:, 1])
    lowest = int(world[:, 1].argmin())
    assert slots.active.tolist() == [i == lowest for i in range(4)]


def test_vertex_against_polygon_edge_distance_and_normal() -> None:
    square = Polygon.box(1.0, 1.0).vertices
    # A point 0.1 to the right of the right edge, and one 0.05 inside near the top edge.
    points = torch.tensor([[[0.6, 0.2], [0.1, 0.45], [0.9, 0.9]]], dtype=torch.float64)
    slots = polygon_slots(points, square.unsqueeze(0), margin=0.2)
    torch.testing.assert_close(slots.phi[0, :2], torch.tensor([0.1, -0.05], dtype=torch.float64))
    torch.testing.assert_close(slots.normals[0, 0], torch.tensor([1.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(slots.normals[0, 1], torch.tensor([0.0, 1.0], dtype=torch.float64))
    # The far corner point is outside both edges' slabs by more than the margin.
    assert slots.active[0].tolist() == [True, True, False]


def test_vertex_at_a_corner_takes_the_edge_facing_it() -> None:
    """Aligned boxes side by side: the touching vertex lies on two edges of the other box.

    Seen from the 1 × 0.5 box's centre the corner (−0.5, −0.25) lies more to the left than
    below, so the left edge (normal −x) is the contact feature, not the bottom edge.
    """
    box = Polygon.box(1.0, 0.5).vertices.unsqueeze(0)
    corner = torch.tensor([[[-0.5, -0.25], [-0.5, 0.25]]], dtype=torch.float64)
    slots = polygon_slots(corner, box, margin=0.1)
    expected = torch.tensor([[-1.0, 0.0], [-1.0, 0.0]], dtype=torch.float64)
    torch.testing.assert_close(slots.normals[0], expected)
    torch.testing.assert_close(slots.phi[0], torch.zeros(2, dtype=torch.float64))


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
