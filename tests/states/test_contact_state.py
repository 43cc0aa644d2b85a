"""Contact states: quantization guarantees, invariances, tolerance crossings, registry."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.states.scenes import reference_keys, reference_rotation, reference_state
from torchcontact.states import (
    ContactFeature,
    ContactSet,
    ContactState,
    ContactStateRegistry,
    FeatureGrid,
    PartnerKind,
    contact_states,
)

RADIUS, ANGLE = 0.05, math.radians(15)
GRIDS = {d: FeatureGrid(dim=d, radius=RADIUS, angle=ANGLE) for d in (2, 3)}
ENV, ROBOT = PartnerKind.ENVIRONMENT, PartnerKind.ROBOT


def _interior_scene(dim: int, K: int, seed: int, margin: float = 0.4) -> ContactSet:
    """Object-frame contacts placed strictly inside their cells and direction bins.

    Every coordinate sits within ``margin`` cell sides of its cell centre, every gnomonic
    coordinate within ``margin`` bin widths of its bin centre, so perturbations smaller than
    ``(0.5 − margin)`` of a cell or bin cannot change a key.
    """
    grid = GRIDS[dim]
    gen = torch.Generator().manual_seed(seed)
    cells = torch.randint(-4, 5, (K, dim), generator=gen)
    faces = torch.randint(0, 2 * dim, (K, 1), generator=gen)
    bins = torch.randint(0, grid.bins, (K, dim - 1), generator=gen)
    points = grid.location(cells) + margin * grid.cell_size * (
        2 * torch.rand(K, dim, generator=gen) - 1
    )
    normals = _inside_bin(grid, torch.cat([faces, bins], -1), gen, margin)
    mode = torch.randint(0, 4, (K,), generator=gen)
    return ContactSet(
        points=points,
        normals=normals,
        pn=(mode > 0).double(),
        mode=mode,
        partner=torch.randint(0, 3, (K,), generator=gen),
        partner_kind=("environment", "robot", "environment"),
        mask=torch.rand(K, generator=gen) < 0.9,
    )


def _inside_bin(
    grid: FeatureGrid, keys: torch.Tensor, gen: torch.Generator, margin: float
) -> torch.Tensor:
    """Unit normals whose gnomonic coordinates lie within ``margin`` bins of the bin centre."""
    d, width = grid.dim, 2.0 / grid.bins
    centre = grid.direction(keys)
    axis = keys[:, 0] // 2
    major = centre.gather(-1, axis.unsqueeze(-1))
    gnomonic = centre / major.abs()  # the major coordinate is ±1, the others bin centres
    jitter = margin * width * (2 * torch.rand(keys.shape[0], d, generator=gen) - 1)
    jitter = jitter.scatter(-1, axis.unsqueeze(-1), 0.0)
    normals = gnomonic + jitter
    return normals / torch.linalg.vector_norm(normals, dim=-1, keepdim=True)


def _move(contacts: ContactSet, pose: torch.Tensor) -> ContactSet:
    """The same contacts with the object moved to ``pose`` (world-frame points and normals)."""
    R = torch.from_numpy(reference_rotation(pose.numpy()))
    points = contacts.points @ R.T + pose[: contacts.dim]
    return replace(contacts, points=points, normals=contacts.normals @ R.T, pose=pose)


def _permute(contacts: ContactSet, order: list[int]) -> ContactSet:
    index = torch.tensor(order)
    assert contacts.mask is not None
    return ContactSet(
        points=contacts.points[..., index, :],
        normals=contacts.normals[..., index, :],
        pn=contacts.pn[..., index],
        mode=contacts.mode[..., index],
        partner=contacts.partner[index],
        partner_kind=contacts.partner_kind,
        mask=contacts.mask[..., index],
        pose=contacts.pose,
    )


def _pose(dim: int, values: list[float]) -> torch.Tensor:
    if dim == 2:
        return torch.tensor(values[:3])
    quaternion = torch.tensor(values[3:7])
    quaternion = quaternion / quaternion.norm()
    return torch.cat([torch.tensor(values[:3]), quaternion])


def _state(contacts: ContactSet) -> ContactState:
    (state,) = contact_states(contacts, GRIDS[contacts.dim])
    return state


@pytest.mark.parametrize("dim", [2, 3])
@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    data=st.data(),
    values=st.lists(st.floats(-3.0, 3.0), min_size=7, max_size=7).filter(
        lambda v: sum(x * x for x in v[3:]) > 1e-2
    ),
)
def test_invariant_to_permutation_rigid_motion_and_small_perturbations(
    dim: int, seed: int, data: st.DataObject, values: list[float]
) -> None:
    K = 6
    contacts = _interior_scene(dim, K, seed)
    state = _state(contacts)
    assert state == reference_state(contacts, (), radius=RADIUS, angle=ANGLE)

    order = data.draw(st.permutations(range(K)))
    assert _state(_permute(contacts, order)) == state
    assert hash(_state(_permute(contacts, order))) == hash(state)

    moved = _move(contacts, _pose(dim, values))
    assert _state(moved) == state
    assert _state(_permute(moved, order)) == state

    # Each contact moved within 0.09 of a cell / bin: still inside (margin 0.4 + 0.09 < 0.5).
    gen = torch.Generator().manual_seed(seed + 1)
    grid = GRIDS[dim]
    shift = 0.09 * grid.cell_size * (2 * torch.rand(K, dim, generator=gen) - 1)
    turn = 0.09 * (2.0 / grid.bins) * (2 * torch.rand(K, dim, generator=gen) - 1)
    _, keys = grid.quantize(contacts.points, contacts.normals)
    major = contacts.normals.gather(-1, (keys[:, :1] // 2)).abs()
    turn = turn.scatter(-1, keys[:, :1] // 2, 0.0)
    normals = contacts.normals / major + turn
    normals = normals / normals.norm(dim=-1, keepdim=True)
    perturbed = replace(contacts, points=contacts.points + shift, normals=normals)
    assert _state(perturbed) == state


@pytest.mark.parametrize("dim", [2, 3])
@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_features_lie_within_the_tolerances_of_their_canonical_location_and_normal(
    dim: int, seed: int
) -> None:
    grid = GRIDS[dim]
    gen = torch.Generator().manual_seed(seed)
    points = 0.7 * torch.randn(500, dim, generator=gen)
    normals = torch.randn(500, dim, generator=gen)
    normals = normals / normals.norm(dim=-1, keepdim=True)
    cells, keys = grid.quantize(points, normals)
    distance = (points - grid.location(cells)).norm(dim=-1)
    assert float(distance.max()) <= RADIUS * (1 + 1e-12)
    cosine = (normals * grid.direction(keys)).sum(-1).clamp(-1.0, 1.0)
    assert float(torch.acos(cosine).max()) <= ANGLE + 1e-12
    for k in range(0, 500, 7):
        cell, key = reference_keys(
            points[k].numpy(), normals[k].numpy(), radius=RADIUS, angle=ANGLE
        )
        assert tuple(cells[k].tolist()) == cell
        assert tuple(keys[k].tolist()) == key


@pytest.mark.parametrize("dim", [2, 3])
def test_batched_states_match_the_one_contact_at_a_time_reference(dim: int) -> None:
    gen = torch.Generator().manual_seed(3)
    batch, K = (2, 3), 5
    size = 3 if dim == 2 else 7
    pose = torch.randn(*batch, size, generator=gen)
    if dim == 3:
        pose[..., 3:] = pose[..., 3:] / pose[..., 3:].norm(dim=-1, keepdim=True)
    normals = torch.randn(*batch, K, dim, generator=gen)
    contacts = ContactSet(
        # Few cells, so that several contacts share one and their sliding flags merge.
        points=0.05 * torch.randn(*batch, K, dim, generator=gen),
        normals=normals / normals.norm(dim=-1, keepdim=True),
        pn=torch.rand(*batch, K, generator=gen),
        mode=torch.randint(0, 4, (*batch, K), generator=gen),
        partner=torch.tensor([0, 1, 0, 1, 1]),
        partner_kind=("environment", "robot"),
        mask=torch.rand(*batch, K, generator=gen) < 0.8,
        pose=pose,
    )
    states = contact_states(contacts, GRIDS[dim])
    assert len(states) == 6
    indices = [(i, j) for i in range(2) for j in range(3)]
    for state, index in zip(states, indices, strict=True):
        assert state == reference_state(contacts, index, radius=RADIUS, angle=ANGLE)


def _one_contact(point: list[float], normal: list[float], mode: int = 1) -> ContactSet:
    return ContactSet(
        points=torch.tensor([point]),
        normals=torch.tensor([normal]),
        pn=torch.ones(1),
        mode=torch.tensor([mode]),
        partner=torch.tensor([0]),
        partner_kind=("environment",),
    )


def test_crossing_the_location_tolerance_changes_the_state() -> None:
    s = GRIDS[2].cell_size  # 2 δ_r / √2 = 0.0707…
    assert s == pytest.approx(2 * RADIUS / math.sqrt(2), rel=1e-15)
    base = _state(_one_contact([3 * s, 0.0], [0.0, 1.0]))
    assert base.features[0].cell == (3, 0)
    assert _state(_one_contact([3.49 * s, -0.49 * s], [0.0, 1.0])) == base
    assert _state(_one_contact([3.51 * s, 0.0], [0.0, 1.0])).features[0].cell == (4, 0)
    assert _state(_one_contact([3 * s, -0.51 * s], [0.0, 1.0])).features[0].cell == (3, -1)
    # The half-open convention: a coordinate on the boundary goes to the upper cell.
    assert 2.5 * s / s == 2.5
    assert -1.5 * s / s == -1.5
    assert _state(_one_contact([2.5 * s, -1.5 * s], [0.0, 1.0])).features[0].cell == (3, -1)


def test_crossing_the_angle_tolerance_changes_the_state() -> None:
    grid = GRIDS[2]
    assert grid.bins == 5  # ⌈1 / 15°⌉ = 4, made odd: bins of width 0.4 in tan(angle)
    half = math.atan(0.2)  # edge of the central bin of a face
    base = _state(_one_contact([0.0, 0.0], [0.0, 1.0]))
    assert base.features[0].direction == (2, 2)  # face +y, central bin
    for angle, expected in [(half - 1e-6, (2, 2)), (half + 1e-6, (2, 3)), (-half - 1e-6, (2, 1))]:
        normal = [math.sin(angle), math.cos(angle)]
        assert _state(_one_contact([0.0, 0.0], normal)).features[0].direction == expected
    # Ties between axes go to the lowest axis: (1, 1)/√2 lies on face +x, last bin.
    tie = _state(_one_contact([0.0, 0.0], [1.0, 1.0]))
    assert tie.features[0].direction == (0, 4)


def test_sticking_sliding_and_partner_kind_change_the_state() -> None:
    sticking = _state(_one_contact([0.0, 0.0], [0.0, 1.0], mode=1))
    sliding = _state(_one_contact([0.0, 0.0], [0.0, 1.0], mode=3))
    assert sticking != sliding
    assert sliding.features[0].sliding
    robot = ContactSet(
        points=torch.zeros(1, 2),
        normals=torch.tensor([[0.0, 1.0]]),
        pn=torch.ones(1),
        mode=torch.tensor([1]),
        partner=torch.tensor([0]),
        partner_kind=("robot",),
    )
    assert _state(robot).robot == (ContactFeature(ROBOT, (0, 0), (2, 2), False),)
    assert not _state(robot).environment
    assert _state(robot) != sticking
    separated = _state(_one_contact([0.0, 0.0], [0.0, 1.0], mode=0))
    assert separated == ContactState()
    assert str(separated) == "free"


def test_one_sliding_contact_makes_its_feature_slide() -> None:
    s = GRIDS[2].cell_size
    contacts = ContactSet(
        points=torch.tensor([[0.1 * s, 0.0], [-0.1 * s, 0.0], [5 * s, 0.0]]),
        normals=torch.tensor([[0.0, 1.0]] * 3),
        pn=torch.ones(3),
        mode=torch.tensor([1, 2, 1]),
        partner=torch.tensor([0, 0, 0]),
        partner_kind=("environment",),
    )
    state = _state(contacts)
    expected = ContactState(
        (ContactFeature(ENV, (5, 0), (2, 2), False), ContactFeature(ENV, (0, 0), (2, 2), True))
    )
    assert state == expected
    assert [f.cell for f in state.features] == [(0, 0), (5, 0)]  # sorted canonically
    assert str(state) == "E1st1sl"


def test_contact_state_rejects_duplicate_features() -> None:
    feature = ContactFeature(ROBOT, (0, 0), (2, 2), False)
    with pytest.raises(ValueError, match="at most one feature"):
        ContactState((feature, ContactFeature(ROBOT, (0, 0), (2, 2), True)))
    with pytest.raises(ValueError, match="cell and direction"):
        ContactFeature(ROBOT, (0, 0), (2, 2, 0), False)


def test_registry_ids_in_first_seen_order_and_json_round_trip(tmp_path) -> None:
    grid = GRIDS[2]
    s = grid.cell_size
    points = torch.tensor([[[0.0, 0.0]], [[5 * s, 0.0]], [[0.0, 0.0]], [[9 * s, 0.0]]])
    contacts = ContactSet(
        points=points,
        normals=torch.tensor([0.0, 1.0]).expand(4, 1, 2),
        pn=torch.ones(4, 1),
        mode=torch.tensor([[1], [1], [1], [0]]),
        partner=torch.tensor([0]),
        partner_kind=("environment",),
    )
    registry = ContactStateRegistry(grid)
    assert registry.ids(contacts).tolist() == [0, 1, 0, 2]
    assert registry[2] == ContactState()
    assert registry.index(registry[1]) == 1
    assert len(registry) == 3
    sliding = replace(contacts, mode=2 * contacts.mode)
    assert registry.ids(sliding, add=False).tolist() == [-1, -1, -1, 2]
    assert len(registry) == 3
    path = tmp_path / "registry.json"
    registry.save(path)
    loaded = ContactStateRegistry.load(path)
    assert loaded.grid == grid
    assert loaded.states == registry.states
    assert loaded.to_json() == registry.to_json()
    with pytest.raises(KeyError, match="unknown state"):
        registry.index(ContactState((ContactFeature(ENV, (1, 1), (0, 2), False),)))
    with pytest.raises(ValueError, match=r"not a torchcontact\.ContactStateRegistry"):
        ContactStateRegistry.from_json('{"format": "other"}')


@pytest.mark.parametrize(
    ("name", "value", "message"),
    [
        ("points", torch.zeros(2, 4), r"points.shape\[-1\] must be 2 \(planar\) or 3"),
        ("points", torch.full((2, 2), math.nan), "points contains NaN or inf"),
        ("normals", torch.zeros(2, 3), r"normals must have shape \(\*B, 2, 2\)"),
        ("pn", -torch.ones(2), "pn must be >= 0"),
        ("pn", torch.ones(3), r"pn must have shape"),
        ("mode", torch.ones(2), "mode must be a torch.int64 tensor"),
        ("mode", -torch.ones(2, dtype=torch.long), "mode must be >= 0"),
        ("partner", torch.tensor([0, 2]), r"partner ids must lie in \[0, 2\)"),
        ("partner_kind", ("environment", "table"), "partner_kind must hold"),
        ("mask", torch.ones(2), "mask must be a torch.bool tensor"),
        ("pose", torch.zeros(4), r"pose must have shape \(\*B, 3\) planar"),
        ("pose", torch.zeros(2, 3), "pose must have batch shape"),
    ],
)
def test_contact_set_validation_names_the_field(name: str, value: object, message: str) -> None:
    fields = {
        "points": torch.zeros(2, 2),
        "normals": torch.tensor([[0.0, 1.0], [0.0, 1.0]]),
        "pn": torch.ones(2),
        "mode": torch.ones(2, dtype=torch.long),
        "partner": torch.tensor([0, 1]),
        "partner_kind": ("environment", "robot"),
        name: value,
    }
    with pytest.raises(ValueError, match=message):
        ContactSet(**fields)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"dim": 4, "radius": 0.1, "angle": 0.1}, "dim must be 2"),
        ({"dim": 2, "radius": 0.0, "angle": 0.1}, "radius: expected a finite number > 0"),
        ({"dim": 2, "radius": 0.1, "angle": math.inf}, "angle: expected a finite number > 0"),
    ],
)
def test_grid_validation(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        FeatureGrid(**kwargs)


def test_grid_dimension_must_match_contacts() -> None:
    with pytest.raises(ValueError, match=r"grid\.dim must equal contacts\.dim = 2"):
        contact_states(_one_contact([0.0, 0.0], [0.0, 1.0]), GRIDS[3])


def test_spatial_direction_bins_count() -> None:
    grid = GRIDS[3]
    # N = ⌈√2 / 15°⌉ = 6 → 7 (odd); 6 faces × 7².
    assert grid.bins == 7
    assert grid.num_directions == 6 * 49
    directions = grid.direction(
        torch.cartesian_prod(torch.arange(6), torch.arange(7), torch.arange(7))
    )
    assert np.allclose(directions.norm(dim=-1).numpy(), 1.0)
    assert len({tuple(np.round(v, 12)) for v in directions.numpy()}) == 6 * 49


@pytest.mark.parametrize("dim", [2, 3])
def test_float32_contacts_give_the_float64_states(dim: int) -> None:
    contacts = _interior_scene(dim, 8, seed=5)
    single = replace(
        contacts,
        points=contacts.points.float(),
        normals=contacts.normals.float(),
        pn=contacts.pn.float(),
    )
    assert _state(single) == _state(contacts)
