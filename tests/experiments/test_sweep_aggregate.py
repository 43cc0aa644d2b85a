"""Seed statistics against hand-computed Student-t intervals, and the sweep tables.

The t quantiles of the references are closed forms (not scipy): with ``ν`` degrees of freedom
and ``α = 4 p (1 − p)``, ``t = tan(π (p − ½))`` for ``ν = 1``, ``t = (2p − 1) / √(α / 2)`` for
``ν = 2`` and ``t = 2 √(cos(⅓ arccos √α) / √α − 1)`` for ``ν = 4`` and ``p > ½`` (W. T. Shaw,
"Sampling Student's T distribution", J. Computational Finance 9(4), 2006).
"""

from __future__ import annotations

import csv
import json
import math
import random
from pathlib import Path

import pytest
from scipy import stats

from torchcontact.experiments import (
    STATISTICS_COLUMNS,
    SweepRow,
    aggregate_seeds,
    scalar_metrics,
    seed_statistics,
    statistics_table,
    write_statistics,
)


def t_quantile(p: float, dof: int) -> float:
    """The ``p`` quantile (``p > ½``) of Student's t with 1, 2 or 4 degrees of freedom."""
    alpha = 4 * p * (1 - p)
    if dof == 1:
        return math.tan(math.pi * (p - 0.5))
    if dof == 2:
        return (2 * p - 1) / math.sqrt(alpha / 2)
    assert dof == 4
    return 2 * math.sqrt(math.cos(math.acos(math.sqrt(alpha)) / 3) / math.sqrt(alpha) - 1)


def test_the_closed_form_quantiles_match_printed_tables() -> None:
    """The references themselves, against the 3-decimal two-sided 95 % column of a t table."""
    for dof, printed in ((1, 12.706), (2, 4.303), (4, 2.776)):
        assert t_quantile(0.975, dof) == pytest.approx(printed, abs=5e-4)


@pytest.mark.parametrize("confidence", [0.95, 0.9, 0.5])
def test_five_seeds_give_the_hand_computed_interval(confidence: float) -> None:
    """``1, 2, 3, 4, 10``: mean 4, squared deviations 9 + 4 + 1 + 0 + 36 = 50, so
    ``s = √(50/4)`` and ``s/√5 = √2.5``; the interval is ``4 ± t_{(1+c)/2, 4} √2.5``."""
    result = seed_statistics([1.0, 2.0, 3.0, 4.0, 10.0], confidence=confidence)
    half = t_quantile(0.5 + confidence / 2, 4) * math.sqrt(2.5)
    # The quantile's closed form and scipy's inversion agree to ~1e-12; the sums are exact.
    assert result.n == 5
    assert result.mean == pytest.approx(4.0, rel=1e-15)
    assert result.std == pytest.approx(math.sqrt(12.5), rel=1e-14)
    assert (result.min, result.max) == (1.0, 10.0)  # exact: two of the inputs
    assert result.ci_low == pytest.approx(4.0 - half, rel=1e-10)
    assert result.ci_high == pytest.approx(4.0 + half, rel=1e-10)
    assert result.confidence == confidence


def test_two_and_three_seeds() -> None:
    """Two seeds ``3, 5``: ``s/√2 = |5 − 3|/2 = 1`` and ``ν = 1``, ``4 ± tan(0.475 π)``.
    Three seeds ``−1, 0, 4``: mean 1, ``s² = (4 + 1 + 9)/2 = 7``, ``ν = 2``."""
    two = seed_statistics([3.0, 5.0])
    assert two.ci_low == pytest.approx(4.0 - math.tan(0.475 * math.pi), rel=1e-10)
    assert two.ci_high == pytest.approx(4.0 + math.tan(0.475 * math.pi), rel=1e-10)
    three = seed_statistics([-1, 0, 4], confidence=0.99)
    half = t_quantile(0.995, 2) * math.sqrt(7 / 3)
    assert three.std == pytest.approx(math.sqrt(7), rel=1e-14)
    assert (three.ci_low, three.ci_high) == pytest.approx((1 - half, 1 + half), rel=1e-10)


def test_matches_scipy_interval_on_random_values() -> None:
    """scipy's own ``t.interval`` with loc = mean and scale = the standard error."""
    rng = random.Random(3)
    for n in (2, 5, 17, 100):
        values = [rng.gauss(2.0, 0.3) for _ in range(n)]
        result = seed_statistics(values, confidence=0.95)
        low, high = stats.t.interval(0.95, n - 1, loc=stats.tmean(values), scale=stats.sem(values))
        assert (result.ci_low, result.ci_high) == pytest.approx((low, high), rel=1e-12)


def test_one_seed_has_no_interval() -> None:
    result = seed_statistics([0.25])
    assert (result.n, result.mean, result.min, result.max) == (1, 0.25, 0.25, 0.25)
    assert math.isnan(result.std)
    assert math.isnan(result.ci_low)
    assert math.isnan(result.ci_high)


@pytest.mark.parametrize(
    ("values", "confidence", "message"),
    [
        ([], 0.95, "values: expected at least one value"),
        ([1.0, math.nan], 0.95, r"values\[1\]: expected a finite number, got nan"),
        ([math.inf], 0.95, r"values\[0\]: expected a finite number, got inf"),
        ([True, 2.0], 0.95, r"values\[0\]: expected a number, got True"),
        (["1"], 0.95, r"values\[0\]: expected a number"),
        ([1.0, 2.0], 1.0, r"confidence: expected a finite number in \(0.0, 1.0\), got 1.0"),
        ([1.0, 2.0], 0.0, "confidence"),
        ([1.0, 2.0], math.nan, "confidence"),
    ],
)
def test_bad_input_is_named(values: list[object], confidence: float, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        seed_statistics(values, confidence=confidence)  # type: ignore[arg-type]


def test_aggregate_by_setting_and_metric() -> None:
    results = {
        "particles=8": [{"error": 1.0, "seconds": 3.0}, {"error": 3.0, "seconds": math.nan}],
        "particles=16": [{"error": 0.5}, {"error": 0.25, "extra": 7}],
    }
    rows = aggregate_seeds(results)
    table = {(row.setting, row.metric): row for row in rows}
    assert list(table) == [
        ("particles=8", "error"),
        ("particles=8", "seconds"),
        ("particles=16", "error"),
        ("particles=16", "extra"),
    ]
    assert table["particles=8", "error"].statistics.mean == pytest.approx(2.0, rel=1e-15)
    # ν = 1, s/√n = |3 − 1|/2 = 1
    assert table["particles=8", "error"].statistics.ci_high == pytest.approx(
        2.0 + math.tan(0.475 * math.pi), rel=1e-10
    )
    seconds = table["particles=8", "seconds"]
    assert (seconds.statistics.n, seconds.left_out, seconds.statistics.mean) == (1, 1, 3.0)
    assert table["particles=16", "extra"].statistics.n == 1
    chosen = aggregate_seeds(results, metrics=["seconds"], confidence=0.9)
    assert [(row.setting, row.metric) for row in chosen] == [("particles=8", "seconds")]
    with pytest.raises(ValueError, match="setting 'a' has no seeds"):
        aggregate_seeds({"a": []})
    with pytest.raises(ValueError, match="'a' 'x': expected numbers, got 'no'"):
        aggregate_seeds({"a": [{"x": "no"}]})  # type: ignore[dict-item]
    with pytest.raises(ValueError, match="confidence"):
        aggregate_seeds(results, confidence=95)


def test_scalar_metrics_flattens_nested_results() -> None:
    result = {
        "run_dir": "runs/x",
        "num_states": 12,
        "ok": True,
        "history": [{"a": 1.0}],
        "summary": {"grid": {"seconds": 2.5, "mu": math.inf}, "n": 3},
    }
    flat = scalar_metrics(result)
    assert flat == {
        "num_states": 12.0,
        "summary/grid/seconds": 2.5,
        "summary/grid/mu": math.inf,
        "summary/n": 3.0,
    }


def test_tables_and_files(tmp_path: Path) -> None:
    rows = aggregate_seeds({"": [{"error": 1.0}, {"error": 3.0}], "b=1": [{"error": 0.5}]})
    text = statistics_table(rows, digits=3)
    lines = text.splitlines()
    assert lines[0] == "| setting | metric | seeds | mean | min – max | 95 % interval |"
    assert lines[2] == "| – | error | 2 | 2 | 1 – 3 | -10.7 – 14.7 |"  # 2 ± 12.706
    assert lines[3] == "| b=1 | error | 1 | 0.5 | 0.5 – 0.5 | – – – |"
    write_statistics(rows, tmp_path, stem="stats")
    assert (tmp_path / "stats.md").read_text() == statistics_table(rows)
    records = json.loads((tmp_path / "stats.json").read_text())
    assert records[1]["ci_low"] is None  # nan as null
    assert records[0]["ci_high"] == pytest.approx(2.0 + math.tan(0.475 * math.pi), rel=1e-10)
    with (tmp_path / "stats.csv").open() as file:
        read = list(csv.DictReader(file))
    assert tuple(read[0]) == STATISTICS_COLUMNS
    assert float(read[0]["ci_high"]) == pytest.approx(records[0]["ci_high"], rel=1e-15)
    assert math.isnan(float(read[1]["std"]))
    mixed = [rows[0], SweepRow("c", "error", seed_statistics([1.0, 2.0], confidence=0.9))]
    with pytest.raises(ValueError, match="one confidence"):
        statistics_table(mixed)
    with pytest.raises(ValueError, match="digits"):
        statistics_table(rows, digits=0)
