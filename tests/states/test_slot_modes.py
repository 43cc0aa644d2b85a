"""Labels, touch codes and table rows of the simulator's per-slot mode vectors."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import Body, Scene
from torchcontact.states import mode_ids, mode_label, touch_codes


def _grasp_scene() -> Scene:
    """A table, a triangle and two kinematic fingers (the triangle-grasp experiment's bodies)."""
    return Scene(
        bodies=(
            Body("table", HalfPlane.ground(), kind="static"),
            Body("triangle", Polygon.triangle(0.08, 0.04 * math.sqrt(3.0)), mass=0.2),
            Body("left", Polygon.box(0.01, 0.03), kind="kinematic"),
            Body("right", Polygon.box(0.01, 0.03), kind="kinematic"),
        ),
        friction=0.5,
        h=0.01,
    )


def _group(scene: Scene, receiver: str, other: str) -> int:
    """First slot of the group of ``receiver``'s vertices against ``other``."""
    return next(
        g.start
        for g in scene.slot_groups
        if scene.bodies[g.receiver].name == receiver and scene.bodies[g.other].name == other
    )


def test_labels_name_each_partner_and_its_contact_states() -> None:
    scene = _grasp_scene()
    table, right = _group(scene, "triangle", "table"), _group(scene, "right", "triangle")
    mode = torch.zeros(scene.num_slots, dtype=torch.long)
    assert mode_label(scene, mode, body="triangle") == "free"
    mode[table], mode[table + 1] = 1, 1  # two triangle vertices stick on the table
    assert mode_label(scene, mode, body="triangle") == "table 2 stick"
    mode[right] = 3  # a right-finger corner slides on the triangle
    assert mode_label(scene, mode, body="triangle") == "table 2 stick, right 1 slide"
    # On the ground (normal +y, tangent t = -x) friction along +t (mode 2) opposes a slip
    # towards +x; along -t (mode 3) one towards -x.
    mode[table], mode[table + 1] = 2, 2
    assert mode_label(scene, mode, body="triangle").startswith("table 2 slide→,")
    mode[table + 1] = 3
    assert mode_label(scene, mode, body="triangle").startswith("table slide←+slide→,")
    # The fingers' labels name only the triangle.
    assert mode_label(scene, mode, body="right") == "triangle 1 slide"
    assert mode_label(scene, mode, body="left") == "free"


def test_touch_codes_match_a_slot_by_slot_enumeration() -> None:
    scene = _grasp_scene()
    L = scene.num_slots
    generator = torch.Generator().manual_seed(0)
    modes = torch.randint(0, 4, (64, L), generator=generator)
    modes[torch.rand(64, L, generator=generator) < 0.7] = 0
    codes = touch_codes(scene, modes.view(8, 8, L), body="triangle")
    names = [b.name for b in scene.bodies]
    for row, code in zip(modes, codes.flatten().tolist(), strict=True):
        expected = 0
        for group, slot in itertools.product(scene.slot_groups, range(L)):
            inside = group.start <= slot < group.start + group.count
            if inside and int(row[slot]) > 0:
                partner = group.other if names[group.receiver] == "triangle" else group.receiver
                expected |= 1 << partner
        assert code == expected


def test_mode_ids_find_each_row_or_report_its_absence() -> None:
    table = torch.tensor([[0, 0, 0], [1, 1, 0], [2, 1, 0]])
    modes = torch.tensor([[[1, 1, 0], [0, 0, 0]], [[3, 0, 0], [2, 1, 0]]])
    expected = [
        [next((k for k, r in enumerate(table.tolist()) if r == m), 3) for m in pair]
        for pair in modes.tolist()
    ]
    assert mode_ids(modes, table).tolist() == expected == [[1, 0], [3, 2]]


def test_bad_arguments_name_the_argument() -> None:
    scene = _grasp_scene()
    mode = torch.zeros(scene.num_slots, dtype=torch.long)
    with pytest.raises(ValueError, match=r"^body: "):
        mode_label(scene, mode, body="cup")
    with pytest.raises(ValueError, match=r"^mode: "):
        mode_label(scene, mode[None], body="triangle")
    with pytest.raises(ValueError, match=r"^mode: "):
        touch_codes(scene, mode.double(), body="triangle")
    with pytest.raises(ValueError, match=r"^table: "):
        mode_ids(mode[None], torch.zeros(2, 3, dtype=torch.long))
