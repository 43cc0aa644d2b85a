"""Manipulation states of the peg-in-hole task: cells, contact classes, ids and keys."""

from __future__ import annotations

import math

import pytest
import torch

from torchcontact.envs import (
    CONTACT_TABLE,
    ENV_BELOW,
    ENV_LEFT,
    ENV_RIGHT,
    GRASP_NONE,
    GRASP_SLIDE,
    GRASP_STICK,
    HELD_FREE,
    NUM_CONTACT_CLASSES,
    PegInHoleStates,
    contact_classes,
    manipulation_state,
)
from torchcontact.states import ContactSet, PartnerKind

HEIGHT, DEPTH = 0.16, 0.06


def grid() -> PegInHoleStates:
    return PegInHoleStates(
        peg_height=HEIGHT,
        hole_depth=DEPTH,
        x_edges=(-0.05, -0.01, 0.01, 0.05),
        y_edges=(-0.02, 0.0, 0.02),
        angle_edges=(-0.1, 0.1),
    )


def pose_with_bottom(x: float, y: float, theta: float = 0.0) -> torch.Tensor:
    """The peg pose whose bottom centre sits at ``(x, DEPTH + y)`` (relative to the mouth)."""
    half = HEIGHT / 2
    return torch.tensor(
        [x - half * math.sin(theta), DEPTH + y + half * math.cos(theta), theta],
        dtype=torch.float64,
    )


def test_relative_pose_is_the_bottom_centre_relative_to_the_mouth() -> None:
    pose = pose_with_bottom(0.013, -0.004, 0.3)
    relative = grid().relative_pose(pose)
    torch.testing.assert_close(
        relative, torch.tensor([0.013, -0.004, 0.3], dtype=torch.float64), atol=1e-15, rtol=0
    )
    turn = torch.tensor([0.0, 0.0, 4 * math.pi], dtype=torch.float64)
    wrapped = grid().relative_pose(pose + turn)
    assert abs(float(wrapped[2]) - 0.3) < 1e-12


def test_cells_are_half_open_and_unbounded_outside() -> None:
    states = grid()
    assert states.shape == (5, 4, 3)
    cases = {
        (-0.3, 0.5, 0.0): (0, 3, 1),  # far left, far above: outermost cells
        (-0.01, 0.0, 0.0): (2, 2, 1),  # on edges: the upper cell
        (0.0099, -0.0001, -0.1): (2, 1, 1),
        (0.3, -0.5, 0.5): (4, 0, 2),
    }
    for (x, y, theta), expected in cases.items():
        index = states.cell_indices(pose_with_bottom(x, y, theta))
        assert tuple(index.tolist()) == expected, (x, y, theta)


def test_away_from_contact_the_cell_tells_where_the_peg_is() -> None:
    """Left of, right of, above and inside the hole are different cells."""
    states = grid()
    where = {
        "left": pose_with_bottom(-0.03, 0.01),
        "right": pose_with_bottom(0.03, 0.01),
        "above": pose_with_bottom(0.0, 0.01),
        "high above": pose_with_bottom(0.0, 0.1),
        "inside": pose_with_bottom(0.0, -0.01),
        "tilted above": pose_with_bottom(0.0, 0.01, 0.2),
    }
    cells = {name: int(states.cells(pose)) for name, pose in where.items()}
    assert len(set(cells.values())) == len(cells)


def test_ids_are_vectorized_and_invert_through_keys() -> None:
    states = grid()
    generator = torch.Generator().manual_seed(0)
    N = 400
    bottoms = torch.rand(N, 3, generator=generator, dtype=torch.float64) - 0.5
    bottoms = bottoms * torch.tensor([0.2, 0.1, 0.6], dtype=torch.float64)
    poses = torch.stack([pose_with_bottom(*row.tolist()) for row in bottoms])
    classes = torch.randint(0, NUM_CONTACT_CLASSES, (N,), generator=generator)
    ids = states.ids(poses, classes)
    assert ids.shape == (N,)
    assert torch.equal(ids, manipulation_state(poses, states=states, contacts=classes))
    nx, ny, na = states.shape
    for i in range(N):
        key = states.key(int(ids[i]))
        assert key.pose == tuple(states.cell_indices(poses[i]).tolist())
        assert key.contact == CONTACT_TABLE[int(classes[i])]
        assert states.index(key) == int(ids[i])
        assert int(states.ids(poses[i], int(classes[i]))) == int(ids[i])  # one pose at a time
    assert int(ids.max()) < states.num_states == nx * ny * na * NUM_CONTACT_CLASSES
    index, contact = states.unravel(ids.reshape(20, 20))
    assert torch.equal(index.reshape(N, 3), states.cell_indices(poses))
    assert torch.equal(contact.reshape(N), classes)
    # Particles of a filter: (batch, particles, 3) poses, no contacts -> a firm grasp.
    particles = poses.reshape(20, 20, 3)
    held = states.ids(particles)
    assert held.shape == (20, 20)
    assert torch.equal(held % NUM_CONTACT_CLASSES, torch.full((20, 20), HELD_FREE))


def peg_contacts(
    rows: list[tuple[str, tuple[float, float], int]], pose: torch.Tensor
) -> ContactSet:
    """Contacts of a peg from ``(partner kind, normal in the peg frame, mode)`` rows."""
    c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
    rotation = torch.tensor([[c, -s], [s, c]], dtype=torch.float64)
    normals = torch.tensor([row[1] for row in rows], dtype=torch.float64) @ rotation.T
    points = pose[:2] + torch.zeros(len(rows), 2, dtype=torch.float64)
    return ContactSet(
        points=points,
        normals=normals,
        pn=torch.ones(len(rows), dtype=torch.float64),
        mode=torch.tensor([row[2] for row in rows], dtype=torch.long),
        partner=torch.tensor([0 if row[0] == "environment" else 1 for row in rows]),
        partner_kind=(PartnerKind.ENVIRONMENT, PartnerKind.ROBOT),
        pose=pose,
    )


def test_contact_classes_follow_normals_in_the_peg_frame() -> None:
    pose = torch.tensor([0.3, 0.2, 0.7], dtype=torch.float64)  # rotated: classes are peg-frame
    grasp = [("robot", (1.0, 0.0), 1), ("robot", (-1.0, 0.0), 1)]
    cases = [
        ([], GRASP_NONE * 8),
        (grasp, GRASP_STICK * 8),
        ([*grasp[:1], ("robot", (-1.0, 0.0), 2)], GRASP_SLIDE * 8),
        ([*grasp, ("environment", (0.0, 1.0), 1)], GRASP_STICK * 8 + ENV_BELOW),
        ([*grasp, ("environment", (0.7, 0.7), 3)], GRASP_STICK * 8 + ENV_BELOW),  # chamfer
        ([*grasp, ("environment", (1.0, 0.1), 1)], GRASP_STICK * 8 + ENV_LEFT),
        (
            [("environment", (-1.0, 0.0), 1), ("environment", (1.0, 0.0), 2)],
            ENV_LEFT + ENV_RIGHT,
        ),
        ([*grasp, ("environment", (0.0, -1.0), 1)], GRASP_STICK * 8),  # from above: ignored
        ([*grasp, ("environment", (0.0, 1.0), 0)], GRASP_STICK * 8),  # separated slot
    ]
    for rows, expected in cases:
        contacts = peg_contacts(rows or [("robot", (1.0, 0.0), 0)], pose)
        assert int(contact_classes(contacts)) == expected, rows
    table = CONTACT_TABLE[GRASP_SLIDE * 8 + ENV_RIGHT + ENV_BELOW]
    assert len(table.robot) == 2
    assert all(f.sliding for f in table.robot)
    assert {f.direction for f in table.environment} == {(1, 0), (2, 0)}
    assert len(set(CONTACT_TABLE)) == NUM_CONTACT_CLASSES


def test_bad_inputs_raise_value_errors_naming_the_argument() -> None:
    states = grid()
    with pytest.raises(ValueError, match="peg_pose"):
        states.ids(torch.zeros(4, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="peg_pose"):
        states.ids(torch.full((3,), math.nan, dtype=torch.float64))
    with pytest.raises(ValueError, match="contacts"):
        states.ids(torch.zeros(4, 3, dtype=torch.float64), torch.tensor([0, 1, 2, 24]))
    with pytest.raises(ValueError, match="contacts"):
        states.ids(torch.zeros(4, 3, dtype=torch.float64), torch.zeros(3, dtype=torch.long))
    with pytest.raises(ValueError, match="state_id"):
        states.key(states.num_states)
    with pytest.raises(ValueError, match="x_edges"):
        PegInHoleStates(
            peg_height=HEIGHT,
            hole_depth=DEPTH,
            x_edges=(0.1, 0.0),
            y_edges=(0.0,),
            angle_edges=(0.0,),
        )
    with pytest.raises(ValueError, match="states"):
        manipulation_state(torch.zeros(3, dtype=torch.float64), states="grid")  # type: ignore[arg-type]
