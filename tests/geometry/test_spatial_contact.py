"""Spatial contact slots against coal (an independent collision library: signed distances,
normals and witness points from GJK/EPA) at random poses, box-box contact manifolds against a
slow polygon clipping written here and against hand-computed cases, gradients against finite
differences, and input validation.

coal runs GJK and EPA to a tolerance of 1e-12 here; it agrees with the closed forms to about
1e-10 (the distances' and points' largest difference over these samples), so values are
compared to 1e-8 (metres, on shapes of size 0.1-1 m) and unit normals to 1e-6.
"""

from __future__ import annotations

import math

import coal
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from torchcontact.geometry import (
    FACE_PREFERENCE,
    SPATIAL_SLOT_COUNTS,
    Box,
    Capsule,
    HalfSpace,
    Sphere,
    quat_exp,
    slot_witness_points,
    spatial_slot_table,
    spatial_slots,
)

Shape = Box | Sphere | Capsule | HalfSpace
LENGTH_TOL = 1e-8
NORMAL_TOL = 1e-6


def _coal_shape(shape: Shape) -> coal.ShapeBase:
    if isinstance(shape, Box):
        return coal.Box(*(2 * shape.half_extents.numpy()))
    if isinstance(shape, Sphere):
        return coal.Sphere(shape.radius)
    if isinstance(shape, Capsule):
        return coal.Capsule(shape.radius, 2 * shape.half_length)
    normal = shape.normal.numpy()
    return coal.Halfspace(normal, float(normal @ shape.point.numpy()))


def _transform(pose: np.ndarray) -> coal.Transform3s:
    rotation = Rotation.from_quat(pose[3:], scalar_first=True).as_matrix()
    return coal.Transform3s(rotation, pose[:3].copy())


def _oracle(
    receiver: Shape, receiver_pose: np.ndarray, other: Shape, other_pose: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """coal's signed distance, normal (from the other shape into the receiver) and witness
    points on the receiver and on the other shape."""
    request = coal.DistanceRequest()
    request.gjk_tolerance = 1e-12
    request.epa_tolerance = 1e-12
    result = coal.DistanceResult()
    first, second = _coal_shape(other), _coal_shape(receiver)
    distance = coal.distance(
        first, _transform(other_pose), second, _transform(receiver_pose), request, result
    )
    # coal's normal points from its first object (the other shape) to its second (the receiver).
    return distance, result.normal.copy(), result.getNearestPoint2(), result.getNearestPoint1()


def _random_poses(rng: np.random.Generator, count: int, spread: float) -> np.ndarray:
    quaternions = rng.normal(size=(count, 4))
    quaternions /= np.linalg.norm(quaternions, axis=-1, keepdims=True)
    return np.concatenate([rng.uniform(-spread, spread, (count, 3)), quaternions], -1)


def _identity(count: int) -> np.ndarray:
    poses = np.zeros((count, 7))
    poses[:, 3] = 1.0
    return poses


def _box_sdf(point: np.ndarray, half: np.ndarray, pose: np.ndarray) -> float:
    """Signed distance of a world point to a posed box, in numpy."""
    rotation = Rotation.from_quat(pose[3:], scalar_first=True).as_matrix()
    local = rotation.T @ (point - pose[:3])
    excess = np.abs(local) - half
    return float(np.linalg.norm(np.maximum(excess, 0.0)) + min(excess.max(), 0.0))


def _box_overlap(a: Box, pose_a: np.ndarray, b: Box, pose_b: np.ndarray, axis: np.ndarray):
    """The overlap of two posed boxes' projections on a unit axis."""
    reach = 0.0
    for box, pose in ((a, pose_a), (b, pose_b)):
        rotation = Rotation.from_quat(pose[3:], scalar_first=True).as_matrix()
        reach += np.abs(rotation.T @ axis) @ box.half_extents.numpy()
    return reach - abs(axis @ (pose_a[:3] - pose_b[:3]))


BOX = Box((0.5, 0.4, 0.3))
PAIRS = {
    "sphere-box": (Sphere(0.3), BOX, 1.0, None),
    "box-ground": (Box((0.5, 0.4, 0.3)), HalfSpace.ground(0.1), 0.6, None),
    "sphere-tilted-plane": (
        Sphere(0.3),
        HalfSpace((0.1, 0.2, 0.0), (0.0, 0.6, 0.8)),
        0.6,
        None,
    ),
    "capsule-ground": (Capsule(0.1, 0.3), HalfSpace.ground(), 0.6, None),
    # Exact while the axis stays outside the box (penetration below the radius).
    "capsule-box": (Capsule(0.1, 0.3), BOX, 1.0, lambda d: d > -0.1),
    "sphere-sphere": (Sphere(0.3), Sphere(0.2), 0.6, None),
    "sphere-capsule": (Sphere(0.2), Capsule(0.1, 0.3), 0.6, None),
    # Exact while the axes do not cross.
    "capsule-capsule": (Capsule(0.1, 0.3), Capsule(0.15, 0.2), 0.6, lambda d: d > -0.25),
    "box-box": (Box((0.2, 0.3, 0.1)), BOX, 0.8, None),
    "cube-cube": (Box((0.2, 0.2, 0.2)), Box((0.2, 0.2, 0.2)), 0.5, None),
}


def _compare_with_coal(
    receiver: Shape,
    other: Shape,
    spread: float,
    keep,
    dtype: torch.dtype,
    count: int,
    length_tol: float,
    normal_tol: float,
    margin: float = 100.0,
) -> int:
    rng = np.random.default_rng(7)
    poses = np.stack([_random_poses(rng, count, spread), _identity(count)], 1)
    # The other shape turned about the origin (a half-space: its point and normal).
    poses[:, 1] = _random_poses(rng, count, 0.0)
    table = spatial_slot_table([receiver, other], [(0, 1)], margin=margin)
    slots = spatial_slots(table, torch.tensor(poses, dtype=dtype))
    on_receiver, on_other = (p.double().numpy() for p in slot_witness_points(slots))
    phi = slots.phi.double().numpy()
    normals = slots.normals.double().numpy()
    active = slots.active.numpy()
    assert slots.points.dtype == dtype
    compared = exact = 0
    for i in range(count):
        distance, normal, witness_receiver, witness_other = _oracle(
            receiver, poses[i, 0], other, poses[i, 1]
        )
        if keep is not None and not keep(distance):
            continue
        compared += 1
        gaps = np.where(active[i], phi[i], np.inf)
        k = int(gaps.argmin())
        if isinstance(receiver, Box) and isinstance(other, Box) and distance < 0:
            # A face normal within FACE_PREFERENCE of the least penetration is preferred:
            # the reported depth lies between coal's and (1 + FACE_PREFERENCE) times it.
            slack = FACE_PREFERENCE * abs(distance)
            assert distance - slack - length_tol <= gaps[k] <= distance + length_tol
            assert (phi[i][active[i]] >= distance - slack - length_tol).all()
            # Normals and witnesses are compared where the chosen normal is coal's: the
            # boxes' overlap along it (projected extents, in numpy) is the penetration.
            along = _box_overlap(receiver, poses[i, 0], other, poses[i, 1], normals[i, k])
            if abs(gaps[k] - distance) > length_tol or abs(along + distance) > length_tol:
                continue
        # No slot is deeper than the shapes' penetration.
        assert (phi[i][active[i]] >= distance - length_tol).all()
        exact += 1
        assert gaps[k] == pytest.approx(distance, abs=length_tol)
        np.testing.assert_allclose(normals[i, k], normal, atol=normal_tol)
        np.testing.assert_allclose(on_receiver[i, k], witness_receiver, atol=length_tol)
        np.testing.assert_allclose(on_other[i, k], witness_other, atol=length_tol)
    assert exact >= 0.7 * compared  # box-box: the rest are within FACE_PREFERENCE
    return compared


@pytest.mark.parametrize("pair", list(PAIRS))
def test_deepest_slot_matches_coal_at_random_poses(pair: str) -> None:
    receiver, other, spread, keep = PAIRS[pair]
    compared = _compare_with_coal(
        receiver, other, spread, keep, torch.float64, 300, LENGTH_TOL, NORMAL_TOL
    )
    assert compared >= 40


@pytest.mark.parametrize("pair", ["box-box", "cube-cube"])
def test_boxes_within_the_margin_match_coal(pair: str) -> None:
    # Only the pairs separated by at most the margin get the exact closest points: the batch
    # mixes them with penetrating and distant ones.
    receiver, other, spread, _ = PAIRS[pair]
    compared = _compare_with_coal(
        receiver, other, spread, lambda d: d <= 0.05, torch.float64, 300, LENGTH_TOL, NORMAL_TOL,
        margin=0.05,
    )  # fmt: skip
    assert compared >= 40


@pytest.mark.parametrize("pair", ["sphere-box", "capsule-box", "box-box", "box-ground"])
def test_float32_matches_coal(pair: str) -> None:
    # float32 rounding (eps 1.2e-7) over a few dozen operations on coordinates of size 1.
    receiver, other, spread, keep = PAIRS[pair]
    compared = _compare_with_coal(receiver, other, spread, keep, torch.float32, 100, 2e-5, 2e-4)
    assert compared >= 10


# Not box-box: there B's faces are preferred to A's (FACE_PREFERENCE), so the order can choose.
@pytest.mark.parametrize("pair", ["sphere-box", "capsule-box", "box-ground", "sphere-capsule"])
def test_either_order_gives_the_same_contacts_seen_from_the_other_side(pair: str) -> None:
    receiver, other, spread, _ = PAIRS[pair]
    rng = np.random.default_rng(3)
    poses = torch.tensor(np.stack([_random_poses(rng, 50, spread), _identity(50)], 1))
    forward = spatial_slots(spatial_slot_table([receiver, other], [(0, 1)], margin=1.0), poses)
    backward = spatial_slots(spatial_slot_table([receiver, other], [(1, 0)], margin=1.0), poses)
    torch.testing.assert_close(backward.phi, forward.phi)
    torch.testing.assert_close(backward.normals, -forward.normals)
    torch.testing.assert_close(backward.points, slot_witness_points(forward)[1])
    assert (backward.active == forward.active).all()


def test_capsule_deep_in_a_box_reports_at_most_its_penetration() -> None:
    # With the axis inside the box, a slot's depth is its axis point's: never deeper than
    # coal's penetration depth (minimum translation), and within it once the axis is outside.
    receiver, other = Capsule(0.1, 0.3), BOX
    rng = np.random.default_rng(11)
    poses = np.stack([_random_poses(rng, 200, 0.6), _random_poses(rng, 200, 0.0)], 1)
    slots = spatial_slots(
        spatial_slot_table([receiver, other], [(0, 1)], margin=100.0), torch.tensor(poses)
    )
    deep = 0
    for i in range(200):
        distance = _oracle(receiver, poses[i, 0], other, poses[i, 1])[0]
        deepest = float(slots.phi[i][slots.active[i]].min())
        assert deepest >= distance - LENGTH_TOL
        deep += distance < -0.1
    assert deep >= 20


def test_box_box_witness_points_lie_on_both_boxes() -> None:
    rng = np.random.default_rng(5)
    half_a, half_b = np.array([0.2, 0.3, 0.1]), np.array([0.5, 0.4, 0.3])
    poses = np.stack([_random_poses(rng, 300, 0.8), _random_poses(rng, 300, 0.0)], 1)
    table = spatial_slot_table([Box(half_a), Box(half_b)], [(0, 1)], margin=0.05)
    slots = spatial_slots(table, torch.tensor(poses))
    on_a, on_b = (p.numpy() for p in slot_witness_points(slots))
    checked = 0
    for i, k in zip(*np.nonzero(slots.active.numpy()), strict=True):
        assert abs(_box_sdf(on_a[i, k], half_a, poses[i, 0])) < 1e-9
        assert abs(_box_sdf(on_b[i, k], half_b, poses[i, 1])) < 1e-9
        checked += 1
    assert checked >= 100


# --- box-box contact manifolds ---------------------------------------------------------------


def _clip(polygon: list[np.ndarray], normal: np.ndarray, offset: float) -> list[np.ndarray]:
    """Sutherland-Hodgman: the part of a polygon with ``normal · p <= offset``."""
    result = []
    for a, b in zip(polygon, polygon[1:] + polygon[:1], strict=True):
        da, db = normal @ a - offset, normal @ b - offset
        if da <= 0:
            result.append(a)
        if da * db < 0:
            result.append(a + da / (da - db) * (b - a))
    return result


def _face_polygon(half: np.ndarray, pose: np.ndarray, direction: np.ndarray) -> list[np.ndarray]:
    """The world corners, in a cycle, of the face of a posed box whose outward normal is most
    along ``direction``."""
    rotation = Rotation.from_quat(pose[3:], scalar_first=True).as_matrix()
    local = rotation.T @ direction
    axis = int(np.abs(local).argmax())
    sign = np.sign(local[axis])
    u, v = (axis + 1) % 3, (axis + 2) % 3
    corners = []
    for su, sv in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        p = np.zeros(3)
        p[axis], p[u], p[v] = sign * half[axis], su * half[u], sv * half[v]
        corners.append(rotation @ p + pose[:3])
    return corners


def _reference_manifold(
    half_ref: np.ndarray, pose_ref: np.ndarray, half_inc: np.ndarray, pose_inc: np.ndarray,
    up: np.ndarray, margin: float,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The incident face (of the box ``inc``, facing ``-up``) clipped to the reference face
    (of ``ref``, facing ``up``) by its four side planes, one vertex at a time: the points on
    the incident face and their depths along ``up`` (kept when ``<= margin``)."""
    rotation = Rotation.from_quat(pose_ref[3:], scalar_first=True).as_matrix()
    axis = int(np.abs(rotation.T @ up).argmax())
    polygon = _face_polygon(half_inc, pose_inc, -up)
    for side in range(3):
        if side == axis:
            continue
        for sign in (1.0, -1.0):
            normal = sign * rotation[:, side]
            polygon = _clip(polygon, normal, normal @ pose_ref[:3] + half_ref[side])
    top = up @ pose_ref[:3] + half_ref[axis]
    points = np.array([p for p in polygon if up @ p - top <= margin]).reshape(-1, 3)
    return points, points @ up - top


def _assert_same_points(actual: np.ndarray, expected: np.ndarray, tol: float) -> None:
    assert len(actual) == len(expected), (actual, expected)
    for point in expected:
        assert np.linalg.norm(actual - point, axis=-1).min() < tol, (point, actual)


def _tilted_poses(rng: np.random.Generator, count: int) -> np.ndarray:
    """Quaternions of a random yaw followed by a tilt of 2-8 degrees about a random
    horizontal axis."""
    yaw = Rotation.from_rotvec(np.outer(rng.uniform(-np.pi, np.pi, count), [0.0, 0.0, 1.0]))
    tilt_axis = rng.uniform(-np.pi, np.pi, count)
    angle = np.radians(rng.uniform(2.0, 8.0, count))
    horizontal = np.stack([np.cos(tilt_axis), np.sin(tilt_axis), np.zeros(count)], -1)
    rotation = Rotation.from_rotvec(horizontal * angle[:, None]) * yaw
    return rotation.as_quat(scalar_first=True)


@pytest.mark.parametrize("reference_on_receiver", [False, True])
def test_box_box_manifold_matches_polygon_clipping(reference_on_receiver: bool) -> None:
    # A large flat box and a small tilted one pressed into it, the small one's deepest corner
    # over the large one's face (so that this face's normal is the least penetration): the
    # reference face is the large box's, the incident face the small box's, partly
    # overhanging or not.
    rng = np.random.default_rng(13)
    count, margin = 200, 0.004
    large, small = np.array([1.0, 0.8, 0.1]), np.array([0.2, 0.3, 0.1])
    quaternions = _tilted_poses(rng, count)
    up = np.array([0.0, 0.0, -1.0 if reference_on_receiver else 1.0])
    poses = np.zeros((count, 2, 7))
    poses[:, 0, 3] = 1.0
    poses[:, 1, 3:] = quaternions
    over_face = np.zeros(count, dtype=bool)
    for i in range(count):
        # The small box's corner farthest along -up goes 0-20 mm into the large box's face.
        rotation = Rotation.from_quat(quaternions[i], scalar_first=True).as_matrix()
        reach = np.abs(rotation.T @ up) @ small
        poses[i, 1, :2] = rng.uniform(-1.1, 1.1, 2)
        poses[i, 1, 2] = (0.1 + reach - rng.uniform(0.0, 0.02)) * up[2]
        corners = _face_polygon(small, poses[i, 1], -up)
        deepest = min(corners, key=lambda p: up @ p)
        over_face[i] = abs(deepest[0]) < large[0] and abs(deepest[1]) < large[1]
    # The small box receives (the planar convention: its corners are the slots, on the
    # reference face of the other box); with reference_on_receiver the large box receives.
    shapes = [Box(large), Box(small)]
    groups = [(0, 1)] if reference_on_receiver else [(1, 0)]
    slots = spatial_slots(spatial_slot_table(shapes, groups, margin=margin), torch.tensor(poses))
    on_receiver, on_other = (p.numpy() for p in slot_witness_points(slots))
    sizes, clipped = set(), 0
    for i in np.nonzero(over_face)[0]:
        points, depths = _reference_manifold(large, poses[i, 0], small, poses[i, 1], up, margin)
        active = slots.active[i].numpy()
        incident = on_other[i, active] if reference_on_receiver else on_receiver[i, active]
        _assert_same_points(incident, points, 1e-9)
        order = [int(np.linalg.norm(incident - p, axis=-1).argmin()) for p in points]
        np.testing.assert_allclose(slots.phi[i, active].numpy()[order], depths, atol=1e-12)
        normal = -up if reference_on_receiver else up
        normals = slots.normals[i, active].numpy()
        np.testing.assert_allclose(normals, np.broadcast_to(normal, normals.shape), atol=1e-12)
        sizes.add(len(points))
        on_boundary = np.isclose(np.abs(points[:, :2]), large[:2], rtol=0, atol=1e-12)
        clipped += bool(on_boundary.any())
    assert over_face.sum() >= 100
    assert {1, 2, 3, 4} <= sizes  # corners, edges and faces
    assert clipped >= 10  # faces cut by the reference face's sides


def _stacked(upper: Box, lower: Box, upper_pose: list[float], margin: float = 0.0):
    poses = torch.tensor([upper_pose, [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    table = spatial_slot_table([upper, lower], [(0, 1)], margin=margin)
    slots = spatial_slots(table, poses)
    return slots.points[slots.active].numpy(), slots.phi[slots.active].numpy(), slots


def test_equal_aligned_cubes_touch_at_four_corners() -> None:
    cube = Box((0.2, 0.2, 0.2))
    points, phi, slots = _stacked(cube, cube, [0.0, 0.0, 0.399, 1.0, 0.0, 0.0, 0.0])
    corners = np.array([[sx, sy, 0.199] for sx in (-0.2, 0.2) for sy in (-0.2, 0.2)])
    _assert_same_points(points, corners, 1e-12)
    np.testing.assert_allclose(phi, -0.001, atol=1e-12)
    np.testing.assert_allclose(slots.normals[slots.active].numpy(), [[0, 0, 1]] * 4, atol=1e-15)


def test_flush_overhanging_cube_touches_at_the_overlap_corners() -> None:
    # The upper cube's sides at y = ±0.2 lie in the lower one's: the overlap's corners are two
    # upper corners and two lower corners lying on upper edges.
    cube = Box((0.2, 0.2, 0.2))
    points, phi, _ = _stacked(cube, cube, [0.2, 0.0, 0.399, 1.0, 0.0, 0.0, 0.0])
    expected = np.array([[x, y, 0.199] for x in (0.0, 0.2) for y in (-0.2, 0.2)])
    _assert_same_points(points, expected, 1e-12)
    np.testing.assert_allclose(phi, -0.001, atol=1e-12)


def test_cube_turned_45_degrees_touches_at_the_octagon() -> None:
    cube = Box((1.0, 1.0, 0.5))
    c, s = math.cos(math.pi / 8), math.sin(math.pi / 8)
    points, phi, _ = _stacked(cube, cube, [0.0, 0.0, 0.99, c, 0.0, 0.0, s])
    r = math.sqrt(2) - 1
    octagon = [(1, r), (1, -r), (-1, r), (-1, -r), (r, 1), (-r, 1), (r, -1), (-r, -1)]
    expected = np.array([[x, y, 0.49] for x, y in octagon])
    _assert_same_points(points, expected, 1e-12)
    np.testing.assert_allclose(phi, -0.01, atol=1e-12)


@pytest.mark.parametrize("gap", [-0.001, 0.001])
def test_crossed_edges_give_one_active_slot(gap: float) -> None:
    # Two cubes turned 45 degrees about x and about y: their edges cross, 1 mm deep or apart
    # (within the margin).
    cube = Box((0.2, 0.2, 0.2))
    edge = 0.2 * math.sqrt(2)
    c, s = math.cos(math.pi / 8), math.sin(math.pi / 8)
    poses = torch.tensor(
        [[0.0, 0.0, 2 * edge + gap, c, s, 0.0, 0.0], [0.0, 0.0, 0.0, c, 0.0, s, 0.0]],
        dtype=torch.float64,
    )
    slots = spatial_slots(spatial_slot_table([cube, cube], [(0, 1)], margin=0.002), poses)
    assert int(slots.active.sum()) == 1
    k = int(slots.active.nonzero()[0, 0])
    assert float(slots.phi[k]) == pytest.approx(gap, abs=1e-12)
    np.testing.assert_allclose(slots.normals[k].numpy(), [0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(slots.points[k].numpy(), [0.0, 0.0, edge + gap], atol=1e-12)


def test_capsule_lying_on_a_box_touches_at_both_ends_of_the_face() -> None:
    # Lying along x across a box narrower than it: the two slots are where the axis leaves
    # the top face (x = ±0.5), not the overhanging ends.
    capsule, box = Capsule(0.1, 0.8), BOX
    c = math.cos(math.pi / 4)
    poses = torch.tensor(
        [[0.05, 0.0, 0.399, c, 0.0, c, 0.0], [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]],
        dtype=torch.float64,
    )
    slots = spatial_slots(spatial_slot_table([capsule, box], [(0, 1)], margin=0.0), poses)
    points = slots.points[slots.active].numpy()
    _assert_same_points(points, np.array([[-0.5, 0.0, 0.299], [0.5, 0.0, 0.299]]), 1e-12)
    np.testing.assert_allclose(slots.phi[slots.active].numpy(), [-0.001, -0.001], atol=1e-12)


def test_capsule_on_a_wide_face_touches_at_its_end_balls_and_standing_at_its_tip() -> None:
    capsule, box = Capsule(0.1, 0.2), BOX
    c = math.cos(math.pi / 4)
    poses = torch.tensor(
        [
            [[0.1, 0.1, 0.399, c, 0.0, c, 0.0], [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]],  # lying
            [[0.1, 0.1, 0.599, 1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]],  # up
        ],
        dtype=torch.float64,
    )
    slots = spatial_slots(spatial_slot_table([capsule, box], [(0, 1)], margin=0.0), poses)
    lying = slots.points[0][slots.active[0]].numpy()
    _assert_same_points(lying, np.array([[-0.1, 0.1, 0.299], [0.3, 0.1, 0.299]]), 1e-12)
    standing = slots.points[1][slots.active[1]].numpy()
    _assert_same_points(standing, np.array([[0.1, 0.1, 0.299]]), 1e-12)


def test_parallel_capsules_touch_along_their_overlap() -> None:
    # Two capsules along x, one above the other, 1 mm into each other, overlapping on
    # x in [-0.1, 0.3]: the slots are at the overlap's ends.
    c = math.cos(math.pi / 4)
    poses = torch.tensor(
        [[0.0, 0.0, 0.249, c, 0.0, c, 0.0], [0.2, 0.0, 0.0, c, 0.0, c, 0.0]], dtype=torch.float64
    )
    table = spatial_slot_table([Capsule(0.1, 0.3), Capsule(0.15, 0.3)], [(0, 1)], margin=0.0)
    slots = spatial_slots(table, poses)
    points = slots.points[slots.active].numpy()
    _assert_same_points(points, np.array([[-0.1, 0.0, 0.149], [0.3, 0.0, 0.149]]), 1e-12)
    np.testing.assert_allclose(slots.phi[slots.active].numpy(), [-0.001, -0.001], atol=1e-12)


# --- tables, batching, gradients, validation ---------------------------------------------------


def test_table_lays_slots_out_group_by_group_and_batches() -> None:
    shapes = [Box((0.1, 0.2, 0.3)), HalfSpace.ground(), Sphere(0.1), Capsule(0.05, 0.2), BOX]
    groups = [(0, 1), (2, 4), (3, 1), (4, 0), (3, 4), (2, 1), (3, 2), (2, 3)]
    table = spatial_slot_table(shapes, groups, margin=0.01)
    names = [type(s).__name__ for s in shapes]
    counts = [
        SPATIAL_SLOT_COUNTS.get((names[a], names[b]), SPATIAL_SLOT_COUNTS.get((names[b], names[a])))
        for a, b in groups
    ]
    assert table.num_slots == sum(counts) == 8 + 1 + 2 + 8 + 3 + 1 + 1 + 1
    expected_group = np.repeat(np.arange(len(groups)), counts)
    assert (table.slot_group.numpy() == expected_group).all()
    assert (table.slot_receiver.numpy() == np.array(groups)[expected_group, 0]).all()
    rng = np.random.default_rng(2)
    poses = rng.normal(size=(2, 3, 5, 7)) * 0.3
    poses[..., 3:] /= np.linalg.norm(poses[..., 3:], axis=-1, keepdims=True)
    poses[..., 1, :] = [0, 0, 0, 1, 0, 0, 0]
    batched = spatial_slots(table, torch.tensor(poses))
    assert batched.points.shape == (2, 3, table.num_slots, 3)
    assert batched.active.shape == (2, 3, table.num_slots)
    # Each group alone, scene by scene, gives the same slots.
    start = 0
    for g, pair in enumerate(groups):
        alone = spatial_slot_table(shapes, [pair], margin=0.01)
        for b in np.ndindex(2, 3):
            single = spatial_slots(alone, torch.tensor(poses[b]))
            span = slice(start, start + counts[g])
            torch.testing.assert_close(single.phi, batched.phi[b][span])
            torch.testing.assert_close(single.points, batched.points[b][span])
            assert (single.active == batched.active[b][span]).all()
        start += counts[g]


def _phi_of(shapes, groups, positions, rotation_vectors):
    table = spatial_slot_table(shapes, groups, margin=1.0)

    def phi(position: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
        poses = torch.cat([position, quat_exp(rotation)], -1)
        slots = spatial_slots(table, poses)
        return torch.where(slots.active, slots.phi, 0.0)

    return phi, (positions, rotation_vectors)


@pytest.mark.parametrize(
    ("shapes", "positions", "rotations"),
    [
        # A tilted small box pressed into a turned large one (a face contact).
        ([Box((0.2, 0.3, 0.1)), BOX], [[0.1, 0.05, 0.38], [0.0, 0.0, 0.0]],
         [[0.05, -0.08, 0.3], [0.0, 0.0, 0.2]]),
        # Crossed edges.
        ([Box((0.2, 0.2, 0.2)), Box((0.2, 0.2, 0.2))], [[0.01, 0.02, 0.56], [0.0, 0.0, 0.0]],
         [[0.8, 0.03, 0.0], [0.0, 0.75, 0.02]]),
        # Separated askew (the exact closest points).
        ([Box((0.2, 0.3, 0.1)), BOX], [[0.615, 0.5084, 0.4264], [0.0, 0.0, 0.0]],
         [[0.5, -0.7, 0.3], [0.0, 0.0, 0.2]]),
        ([Capsule(0.1, 0.3), BOX], [[0.2, 0.1, 0.39], [0.0, 0.0, 0.0]],
         [[0.2, 1.3, 0.1], [0.0, 0.0, 0.1]]),
        ([Capsule(0.1, 0.3), Capsule(0.15, 0.2)], [[0.05, 0.1, 0.2], [0.0, 0.0, 0.0]],
         [[0.3, 1.2, 0.1], [0.2, 0.0, 0.4]]),
        ([Sphere(0.1), Capsule(0.15, 0.2)], [[0.05, 0.1, 0.2], [0.0, 0.0, 0.0]],
         [[0.0, 0.0, 0.0], [0.2, 0.3, 0.4]]),
        ([Sphere(0.1), BOX], [[0.5, 0.45, 0.2], [0.0, 0.0, 0.0]],
         [[0.0, 0.0, 0.0], [0.1, 0.2, 0.3]]),
        ([Box((0.2, 0.3, 0.1)), HalfSpace.ground()], [[0.1, 0.2, 0.1], [0.0, 0.0, 0.0]],
         [[0.1, 0.2, 0.3], [0.0, 0.0, 0.0]]),
    ],
)  # fmt: skip
def test_gaps_have_the_gradients_of_finite_differences(shapes, positions, rotations) -> None:
    position = torch.tensor(positions, dtype=torch.float64, requires_grad=True)
    rotation = torch.tensor(rotations, dtype=torch.float64, requires_grad=True)
    phi, inputs = _phi_of(shapes, [(0, 1)], position, rotation)
    poses = torch.cat([position, quat_exp(rotation)], -1)
    touching = spatial_slots(spatial_slot_table(shapes, [(0, 1)], margin=0.05), poses).active
    assert bool(touching.any())
    assert torch.autograd.gradcheck(phi, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_gradients_are_finite_at_the_identity_and_in_float32() -> None:
    shapes = [Box((0.2, 0.2, 0.2)), Box((0.2, 0.2, 0.2)), Sphere(0.1), Capsule(0.1, 0.2)]
    groups = [(0, 1), (2, 1), (3, 1), (2, 0)]
    table = spatial_slot_table(shapes, groups, margin=1.0)
    for dtype in (torch.float32, torch.float64):
        poses = torch.zeros(4, 7, dtype=dtype)
        poses[:, 3] = 1.0
        poses[0, 2], poses[2, 2], poses[3, 2] = 0.4, 0.0, 0.1  # stacked, sphere at a centre
        poses.requires_grad_(True)
        slots = spatial_slots(table, poses)
        (slots.phi * slots.active).sum().backward()
        assert poses.grad is not None
        assert bool(torch.isfinite(poses.grad).all())


@pytest.mark.parametrize(
    ("shapes", "groups", "margin", "name"),
    [
        ([], [], 0.0, "shapes"),
        ([Box((1.0, 1.0, 1.0)), "box"], [(0, 1)], 0.0, "shapes"),
        ([HalfSpace.ground(), HalfSpace.ground(1.0)], [(0, 1)], 0.0, "groups"),
        ([Sphere(0.1), HalfSpace.ground()], [(0, 2)], 0.0, "groups"),
        ([Sphere(0.1), HalfSpace.ground()], [(0, 0)], 0.0, "groups"),
        ([Sphere(0.1), HalfSpace.ground()], [(0, 1)], -0.1, "margin"),
        ([Sphere(0.1), HalfSpace.ground()], [(0, 1)], math.nan, "margin"),
    ],
)
def test_bad_tables_raise_value_error_naming_the_argument(shapes, groups, margin, name) -> None:
    with pytest.raises(ValueError, match=name):
        spatial_slot_table(shapes, groups, margin=margin)


@pytest.mark.parametrize(
    ("poses", "message"),
    [
        (torch.tensor([[0.0, 0, 0, 1, 0, 0, 0], [math.nan, 0, 0, 1, 0, 0, 0]]), "poses"),
        (torch.tensor([[0.0, 0, 0, 1, 0, 0, 0], [math.inf, 0, 0, 1, 0, 0, 0]]), "poses"),
        (torch.tensor([[0.0, 0, 0, 1, 0, 0, 0], [0.0, 0, 0, 2, 0, 0, 0]]), "quaternion"),
        (torch.zeros(2, 6), "poses"),
        (torch.zeros(3, 7), "poses"),
        (torch.zeros(2, 7, dtype=torch.int64), "poses"),
    ],
)
def test_bad_poses_raise_value_error(poses: torch.Tensor, message: str) -> None:
    table = spatial_slot_table([Sphere(0.1), HalfSpace.ground()], [(0, 1)], margin=0.0)
    with pytest.raises(ValueError, match=message):
        spatial_slots(table, poses)
