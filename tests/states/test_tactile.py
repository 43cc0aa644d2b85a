"""Tactile sensors: trigger geometry, noise model, likelihoods (Fig. 2 of the seed paper)."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import matplotlib
import pytest
import torch

from torchcontact.states import (
    ContactSet,
    ContactStateRegistry,
    FeatureGrid,
    TactileArray,
    contact_states,
    rectangle_sensors,
)

matplotlib.use("Agg")

HALF = (0.5, 0.25)
FP, FN = 0.05, 0.1
GRID = FeatureGrid(dim=2, radius=0.05, angle=math.radians(15))


def _rectangle(**kwargs: float) -> TactileArray:
    options = {"radius": 0.08, "half_angle": math.radians(30)} | kwargs
    return rectangle_sensors(half_extents=HALF, counts=(3, 2, 3, 2), **options)


def _contacts(points: list[list[float]], normals: list[list[float]], kind: str) -> ContactSet:
    K = len(points)
    return ContactSet(
        points=torch.tensor(points, dtype=torch.float64),
        normals=torch.tensor(normals, dtype=torch.float64),
        pn=torch.ones(K, dtype=torch.float64),
        mode=torch.ones(K, dtype=torch.long),
        partner=torch.zeros(K, dtype=torch.long),
        partner_kind=(kind,),
    )


# c1: resting on a support under the three bottom sensors; c2: two robot contacts on the right.
C1 = _contacts([[-1 / 3, -0.25], [0.0, -0.25], [1 / 3, -0.25]], [[0.0, 1.0]] * 3, "environment")
C2 = _contacts([[0.5, -0.125], [0.5, 0.125]], [[-1.0, 0.0]] * 2, "robot")


def test_rectangle_layout() -> None:
    array = _rectangle()
    expected = [
        (-1 / 3, -0.25), (0.0, -0.25), (1 / 3, -0.25),  # bottom, left to right
        (0.5, -0.125), (0.5, 0.125),  # right, bottom to top
        (1 / 3, 0.25), (0.0, 0.25), (-1 / 3, 0.25),  # top, right to left
        (-0.5, 0.125), (-0.5, -0.125),  # left, top to bottom
    ]  # fmt: skip
    torch.testing.assert_close(array.positions, torch.tensor(expected), rtol=0, atol=1e-15)
    assert array.normals[:3].tolist() == [[0.0, -1.0]] * 3
    assert array.normals[3:5].tolist() == [[1.0, 0.0]] * 2


def test_fig2_example_c1_and_c2() -> None:
    """c1 triggers the three bottom (green) sensors, c2 the two right (red) ones."""
    array = _rectangle(false_positive=FP, false_negative=FN)
    registry = ContactStateRegistry(GRID)
    c1, c2 = contact_states(C1, GRID)[0], contact_states(C2, GRID)[0]
    registry.add(c1)
    registry.add(c2)
    table = array.trigger_table(registry.states, GRID)
    green = [1, 1, 1, 0, 0, 0, 0, 0, 0, 0]
    red = [0, 0, 0, 1, 1, 0, 0, 0, 0, 0]
    assert table.tolist() == [green, red]
    # The contacts themselves trigger the same sensors as the states' features.
    assert array.triggered(C1).long().tolist() == green
    assert array.triggered(C2).long().tolist() == red

    readings = torch.tensor([green, red]).bool()
    log_likelihood = array.log_likelihood(readings, table)
    hit, miss, quiet, false_alarm = math.log(1 - FN), math.log(FN), math.log(1 - FP), math.log(FP)
    expected = [
        [3 * hit + 7 * quiet, 3 * false_alarm + 2 * miss + 5 * quiet],
        [2 * false_alarm + 3 * miss + 5 * quiet, 2 * hit + 8 * quiet],
    ]
    torch.testing.assert_close(log_likelihood, torch.tensor(expected), rtol=1e-14, atol=0)
    # One missed green sensor and one false alarm elsewhere: still far more likely under c1.
    noisy = torch.tensor(green).bool()
    noisy[1], noisy[7] = False, True
    ll = array.log_likelihood(noisy, table)
    torch.testing.assert_close(
        ll,
        torch.tensor(
            [2 * hit + miss + false_alarm + 6 * quiet, 3 * false_alarm + 2 * miss + 5 * quiet]
        ),
        rtol=1e-14,
        atol=0,
    )
    assert float(ll[0] - ll[1]) > 8.0  # a likelihood ratio above e⁸ ≈ 3000 for c1


def test_likelihood_normalizes_over_all_readings() -> None:
    gen = torch.Generator().manual_seed(1)
    S = 8
    array = rectangle_sensors(
        half_extents=HALF,
        counts=(2, 2, 2, 2),
        radius=0.1,
        half_angle=0.5,
        false_positive=0.0,
        false_negative=0.0,
    )
    array = replace(
        array,
        false_positive=0.3 * torch.rand(S, generator=gen),
        false_negative=0.3 * torch.rand(S, generator=gen),
    )
    table = torch.rand(6, S, generator=gen)
    table[0] = 0.0
    table[1] = 1.0
    table[2, ::2] = 1.0
    readings = torch.tensor(list(itertools.product([False, True], repeat=S)))  # (256, 8)
    ll = array.log_likelihood(readings, table)
    assert ll.shape == (2**S, 6)
    torch.testing.assert_close(ll.exp().sum(0), torch.ones(6), rtol=0, atol=1e-10)
    # A reading-by-reading product of per-sensor probabilities, written out.
    fp, fn = array.false_positive, array.false_negative
    assert isinstance(fp, torch.Tensor)
    assert isinstance(fn, torch.Tensor)
    for r in (0, 37, 255):
        for i in range(6):
            p = 1.0
            for s in range(S):
                on = float(table[i, s]) * (1 - float(fn[s])) + (1 - float(table[i, s])) * float(
                    fp[s]
                )
                p *= on if bool(readings[r, s]) else 1 - on
            assert math.isclose(float(ll[r, i].exp()), p, rel_tol=1e-12)


def test_impossible_readings_have_minus_infinite_log_likelihood() -> None:
    array = _rectangle()  # noise-free
    table = torch.tensor([[1.0] * 3 + [0.0] * 7])
    readings = torch.zeros(10, dtype=torch.bool)
    assert float(array.log_likelihood(readings, table)[0]) == -math.inf
    readings[:3] = True
    assert float(array.log_likelihood(readings, table)[0]) == 0.0


def test_sampled_trigger_frequencies_match_the_model() -> None:
    array = _rectangle(false_positive=FP, false_negative=FN)
    triggers = torch.tensor([1, 1, 1, 0, 0, 0, 0, 0, 0, 0]).bool()
    n = 20_000
    gen = torch.Generator().manual_seed(7)
    samples = array.sample(triggers.expand(n, 10), generator=gen)
    frequency = samples.double().mean(0)
    p = array.reading_probability(triggers)
    torch.testing.assert_close(p, torch.tensor([1 - FN] * 3 + [FP] * 7), rtol=0, atol=1e-15)
    sigma = (p * (1 - p) / n).sqrt()
    assert bool(((frequency - p).abs() <= 5 * sigma).all()), (frequency, p)
    # Whole readings: the frequency of the noise-free pattern is its likelihood.
    likelihood = float(array.log_likelihood(triggers, triggers.double().unsqueeze(0)).exp())
    assert likelihood == pytest.approx(0.9**3 * 0.95**7, rel=1e-12)
    exact = float((samples == triggers).all(-1).double().mean())
    assert abs(exact - likelihood) <= 5 * math.sqrt(likelihood * (1 - likelihood) / n)


def test_triggers_match_a_contact_by_contact_reference() -> None:
    array = _rectangle()
    gen = torch.Generator().manual_seed(3)
    B, K = 64, 4
    # Contacts scattered around random sensors, with normals scattered around their cones.
    sensor = torch.randint(0, 10, (B, K), generator=gen)
    points = array.positions[sensor] + 0.06 * torch.randn(B, K, 2, generator=gen)
    inward = -array.normals[sensor]
    angles = torch.atan2(inward[..., 1], inward[..., 0]) + 0.6 * torch.randn(B, K, generator=gen)
    normals = torch.stack([angles.cos(), angles.sin()], -1)
    mode = torch.randint(0, 3, (B, K), generator=gen)
    pn = torch.rand(B, K, generator=gen)
    contacts = ContactSet(
        points=points,
        normals=normals,
        pn=pn,
        mode=mode,
        partner=torch.zeros(K, dtype=torch.long),
        partner_kind=("robot",),
    )
    array = replace(array, min_impulse=0.2)
    triggered = array.triggered(contacts)
    count = 0
    for b, s in itertools.product(range(B), range(10)):
        expected = False
        for k in range(K):
            px, py = points[b, k].tolist()
            sx, sy = array.positions[s].tolist()
            nx, ny = array.normals[s].tolist()
            cx, cy = normals[b, k].tolist()
            close = math.hypot(px - sx, py - sy) <= 0.08
            within = math.acos(max(-1.0, min(1.0, -(cx * nx + cy * ny)))) <= math.radians(30)
            active = int(mode[b, k]) >= 1 and float(pn[b, k]) >= 0.2
            expected |= close and within and active
        assert bool(triggered[b, s]) == expected
        count += expected
    assert count > 30  # the reference saw triggers, not only misses


def test_trigger_boundaries_are_inclusive() -> None:
    array = _rectangle()
    sensor = array.positions[1]  # bottom centre, outward normal -y
    for offset, expected in [(0.08 - 1e-9, True), (0.08 + 1e-9, False)]:
        point = sensor + torch.tensor([offset, 0.0])
        assert bool(array.triggered(_contacts([point.tolist()], [[0.0, 1.0]], "robot"))[1]) is (
            expected
        )
    for angle, expected in [(math.radians(30) - 1e-6, True), (math.radians(30) + 1e-6, False)]:
        normal = [math.sin(angle), math.cos(angle)]
        assert bool(array.triggered(_contacts([sensor.tolist()], [normal], "robot"))[1]) is (
            expected
        )


def test_readings_do_not_change_when_the_scene_moves() -> None:
    array = _rectangle()
    pose = torch.tensor([1.5, -0.3, 2.0])
    c, s = math.cos(2.0), math.sin(2.0)
    R = torch.tensor([[c, -s], [s, c]])
    moved = replace(C1, points=C1.points @ R.T + pose[:2], normals=C1.normals @ R.T, pose=pose)
    assert torch.equal(array.triggered(moved), array.triggered(C1))
    unmoved = replace(moved, pose=None)
    assert not torch.equal(array.triggered(unmoved), array.triggered(C1))


def test_separated_and_padding_slots_do_not_trigger() -> None:
    array = _rectangle()
    assert array.triggered(replace(C1, mode=torch.zeros(3, dtype=torch.long))).sum() == 0
    mask = torch.tensor([True, False, True])
    assert array.triggered(replace(C1, mask=mask)).long().tolist()[:3] == [1, 0, 1]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"radius": -1.0}, r"radius must lie in \(0.0, inf\]"),
        ({"half_angle": 4.0}, r"half_angle must lie in \[0.0, 3.14"),
        ({"false_positive": 1.5}, r"false_positive must lie in \[0.0, 1.0\]"),
        (
            {"false_negative": torch.zeros(3, dtype=torch.float64)},
            r"false_negative must have shape \(10,\)",
        ),
        (
            {"positions": torch.zeros(10, 4, dtype=torch.float64)},
            r"positions.shape\[-1\] must be 2",
        ),
        ({"normals": torch.zeros(10, 2, dtype=torch.float64)}, "normals must be non-zero"),
        ({"min_impulse": -1.0}, "min_impulse must be a finite number >= 0"),
    ],
)
def test_array_validation(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        replace(_rectangle(), **kwargs)


def test_likelihood_validation() -> None:
    array = _rectangle()
    with pytest.raises(ValueError, match=r"readings must be a torch\.bool tensor"):
        array.log_likelihood(torch.zeros(10), torch.zeros(1, 10))
    with pytest.raises(ValueError, match=r"triggers must have shape \(N, 10\)"):
        array.log_likelihood(torch.zeros(10, dtype=torch.bool), torch.zeros(10))
    with pytest.raises(ValueError, match=r"triggers probabilities must lie in \[0, 1\]"):
        array.log_likelihood(torch.zeros(10, dtype=torch.bool), 2 * torch.ones(1, 10))


def test_draw_writes_a_png(tmp_path) -> None:
    import matplotlib.pyplot as plt

    array = _rectangle()
    fig, ax = plt.subplots()
    array.draw(ax, array.triggered(C1), pose=torch.tensor([0.2, 0.25, 0.3]))
    path = tmp_path / "sensors.png"
    fig.savefig(path)
    plt.close(fig)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(ax.patches) == 20  # a pad and a cone per sensor


def test_per_entry_log_likelihood_is_the_product_of_the_sensor_probabilities() -> None:
    array = _rectangle(false_positive=FP, false_negative=FN)
    gen = torch.Generator().manual_seed(3)
    triggers = torch.rand(4, 5, 10, generator=gen, dtype=torch.float64) < 0.4  # one per entry
    readings = torch.rand(4, 1, 10, generator=gen, dtype=torch.float64) < 0.5  # broadcast
    # written out sensor by sensor: P(r = 1 | t) = 1 - FN if t else FP
    expected = torch.zeros(4, 5, dtype=torch.float64)
    for b, n, s in itertools.product(range(4), range(5), range(10)):
        on = (1 - FN) if bool(triggers[b, n, s]) else FP
        expected[b, n] += math.log(on if bool(readings[b, 0, s]) else 1 - on)
    got = array.reading_log_likelihood(readings, triggers.double())
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="readings"):
        array.reading_log_likelihood(readings.double(), triggers)
