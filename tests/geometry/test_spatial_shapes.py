"""Spatial shapes: mass properties against published formulas and independent quadratures,
and validation of bad shapes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import integrate

from torchcontact.geometry import Box, Capsule, HalfSpace, Sphere


def _gauss_box_inertia(half: tuple[float, float, float]) -> tuple[float, np.ndarray]:
    """Volume and inertia per unit mass of a box by tensor-product Gauss-Legendre quadrature
    (3 points per axis: exact for the quadratic integrands)."""
    nodes, weights = np.polynomial.legendre.leggauss(3)
    axes = [h * nodes for h in half]
    axis_weights = [h * weights for h in half]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    w = np.einsum("i,j,k->ijk", *axis_weights)
    p = np.stack([x, y, z], -1)
    volume = w.sum()
    # I = ∫ (|p|² 1 − p pᵀ) dV / V
    second = np.einsum("ijk,ijka,ijkb->ab", w, p, p)
    inertia = (np.trace(second) * np.eye(3) - second) / volume
    return float(volume), inertia


def _revolved_inertia(profile, z_low: float, z_high: float, kinks: list[float]):
    """Volume and (transverse, axial) inertia per unit mass of a solid of revolution about z
    with radius ``profile(z)``: disc slices, ``dI_zz = π a⁴/2 dz``,
    ``dI_xx = π (a⁴/4 + a² z²) dz``, integrated by adaptive quadrature."""

    def quad(f):
        return integrate.quad(f, z_low, z_high, points=kinks, epsabs=0, epsrel=1e-13)[0]

    volume = quad(lambda z: math.pi * profile(z) ** 2)
    axial = quad(lambda z: math.pi * profile(z) ** 4 / 2) / volume
    transverse = quad(lambda z: math.pi * (profile(z) ** 4 / 4 + profile(z) ** 2 * z * z)) / volume
    return volume, transverse, axial


def test_box_mass_properties_match_published_formula_and_quadrature() -> None:
    half = (0.3, 0.2, 0.05)
    box = Box(half)
    width, depth, height = (2 * h for h in half)
    assert box.volume == pytest.approx(width * depth * height, rel=1e-14)
    # A solid cuboid of sides w, d, h: I_xx = m (d² + h²) / 12, ...
    published = np.diag([depth**2 + height**2, width**2 + height**2, width**2 + depth**2]) / 12
    np.testing.assert_allclose(box.unit_inertia().numpy(), published, rtol=1e-14, atol=1e-16)
    volume, quadrature = _gauss_box_inertia(half)
    assert box.volume == pytest.approx(volume, rel=1e-12)
    np.testing.assert_allclose(box.unit_inertia().numpy(), quadrature, rtol=1e-12, atol=1e-15)


def test_sphere_mass_properties_match_quadrature() -> None:
    sphere = Sphere(0.25)
    volume, transverse, axial = _revolved_inertia(
        lambda z: math.sqrt(max(0.25**2 - z * z, 0.0)), -0.25, 0.25, []
    )
    assert sphere.volume == pytest.approx(volume, rel=1e-10)
    expected = np.diag([transverse, transverse, axial])
    np.testing.assert_allclose(sphere.unit_inertia().numpy(), expected, rtol=1e-10, atol=1e-15)


@pytest.mark.parametrize(("radius", "half_length"), [(0.05, 0.2), (0.3, 0.1), (0.1, 0.0)])
def test_capsule_mass_properties_match_quadrature(radius: float, half_length: float) -> None:
    capsule = Capsule(radius, half_length)

    def profile(z: float) -> float:
        beyond = abs(z) - half_length
        return radius if beyond <= 0 else math.sqrt(max(radius**2 - beyond**2, 0.0))

    top = half_length + radius
    kinks = [-half_length, half_length] if half_length > 0 else [0.0]
    volume, transverse, axial = _revolved_inertia(profile, -top, top, kinks)
    assert capsule.volume == pytest.approx(volume, rel=1e-10)
    expected = np.diag([transverse, transverse, axial])
    np.testing.assert_allclose(capsule.unit_inertia().numpy(), expected, rtol=1e-9, atol=1e-15)


def test_capsule_of_zero_length_is_a_sphere() -> None:
    np.testing.assert_allclose(
        Capsule(0.2, 0.0).unit_inertia().numpy(), Sphere(0.2).unit_inertia().numpy(), rtol=1e-14
    )


@pytest.mark.parametrize("shape", [Box((0.1, 0.2, 0.3)), Sphere(0.1), Capsule(0.1, 0.2)])
def test_mass_properties_from_density_or_mass(shape: Box | Sphere | Capsule) -> None:
    mass, inertia = shape.mass_properties(density=1000.0)
    assert mass == pytest.approx(1000.0 * shape.volume, rel=1e-14)
    np.testing.assert_allclose(inertia.numpy(), mass * shape.unit_inertia().numpy(), rtol=1e-14)
    mass, inertia = shape.mass_properties(mass=2.5)
    assert mass == pytest.approx(2.5)
    np.testing.assert_allclose(inertia.numpy(), 2.5 * shape.unit_inertia().numpy(), rtol=1e-14)
    with pytest.raises(ValueError, match="exactly one"):
        shape.mass_properties()
    with pytest.raises(ValueError, match="exactly one"):
        shape.mass_properties(density=1.0, mass=1.0)
    with pytest.raises(ValueError, match="density"):
        shape.mass_properties(density=-1.0)
    with pytest.raises(ValueError, match="mass"):
        shape.mass_properties(mass=math.nan)


def test_box_accepts_a_tensor_and_lists_its_corners() -> None:
    box = Box(torch.tensor([0.1, 0.2, 0.3], dtype=torch.float32))
    assert box.half_extents.dtype == torch.float64
    corners = box.corners()
    assert corners.shape == (8, 3)
    np.testing.assert_allclose(corners.abs().numpy(), np.tile([0.1, 0.2, 0.3], (8, 1)), rtol=1e-7)
    assert len({tuple(np.sign(c)) for c in corners.numpy()}) == 8


def test_ground_is_z_up() -> None:
    ground = HalfSpace.ground(0.5)
    np.testing.assert_allclose(ground.point.numpy(), [0.0, 0.0, 0.5])
    np.testing.assert_allclose(ground.normal.numpy(), [0.0, 0.0, 1.0])


def test_tilted_ground_descends_along_x() -> None:
    # A 30-degree incline: a point 1 m along +x on the surface lies tan(30°) lower.
    incline = HalfSpace.ground(0.2, math.radians(30.0))
    normal, point = incline.normal.numpy(), incline.point.numpy()
    assert np.linalg.norm(normal) == pytest.approx(1.0, abs=1e-15)
    on_surface = np.array([1.0, 0.0, 0.2 - math.tan(math.radians(30.0))])
    assert normal @ (on_surface - point) == pytest.approx(0.0, abs=1e-15)
    assert normal[2] == pytest.approx(math.cos(math.radians(30.0)), abs=1e-15)


@pytest.mark.parametrize(
    ("build", "name"),
    [
        (lambda: Box((0.1, 0.0, 0.1)), "half_extents"),
        (lambda: Box((0.1, -0.2, 0.1)), "half_extents"),
        (lambda: Box((0.1, math.nan, 0.1)), "half_extents"),
        (lambda: Box((0.1, 0.2)), "half_extents"),
        (lambda: Box("abc"), "half_extents"),
        (lambda: Sphere(-0.1), "radius"),
        (lambda: Sphere(0.0), "radius"),
        (lambda: Sphere(math.inf), "radius"),
        (lambda: Capsule(-0.1, 0.2), "radius"),
        (lambda: Capsule(0.1, -0.2), "half_length"),
        (lambda: Capsule(0.1, math.nan), "half_length"),
        (lambda: HalfSpace((0.0, 0.0, 0.0), (0.0, 0.0, 2.0)), "normal"),
        (lambda: HalfSpace((0.0, math.inf, 0.0), (0.0, 0.0, 1.0)), "point"),
        (lambda: HalfSpace((0.0, 0.0, 0.0), (0.0, 1.0)), "normal"),
        (lambda: HalfSpace.ground(math.nan), "height"),
        (lambda: HalfSpace.ground(0.0, math.inf), "angle"),
    ],
)
def test_bad_shapes_raise_value_error_naming_the_argument(build, name: str) -> None:
    with pytest.raises(ValueError, match=name):
        build()


@pytest.mark.parametrize(
    ("shape", "profile", "top"),
    [
        (Box((0.3, 0.2, 0.05)), None, 0.05),
        (Sphere(0.25), lambda z: math.sqrt(max(0.25**2 - z * z, 0.0)), 0.25),
        (
            Capsule(0.05, 0.2),
            lambda z: 0.05 if abs(z) <= 0.2 else math.sqrt(max(0.05**2 - (abs(z) - 0.2) ** 2, 0)),
            0.25,
        ),
    ],
)
def test_bounding_radius_is_the_farthest_surface_point(
    shape: Box | Sphere | Capsule, profile: object, top: float
) -> None:
    """The largest distance from the centroid over a grid of surface points (the box's face
    grids hold its corners; a solid of revolution's meridian holds its tips)."""
    if isinstance(shape, Box):
        a, b, c = shape.half_extents.tolist()
        grid = np.stack(
            np.meshgrid(*(np.linspace(-h, h, 21) for h in (a, b, c)), indexing="ij"), -1
        ).reshape(-1, 3)
        on_surface = (np.abs(grid) >= np.array([a, b, c]) - 1e-15).any(-1)
        farthest = np.linalg.norm(grid[on_surface], axis=-1).max()
    else:
        z = np.linspace(-top, top, 4001)
        radial = np.array([profile(v) for v in z])  # type: ignore[operator]
        farthest = np.sqrt(z * z + radial * radial).max()
    assert shape.bounding_radius == pytest.approx(farthest, rel=1e-12)
