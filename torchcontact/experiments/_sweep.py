"""Many-seed results as tables: mean, range and Student-t interval of every metric.

A sweep (``train/sweep.py``) or a many-seed experiment runs the same setting with several
seeds and gets one scalar per seed and metric. :func:`seed_statistics` summarizes the values
of one metric; :func:`aggregate_seeds` does it for every setting and metric of a sweep, and
:func:`statistics_table` and :func:`write_statistics` write the result as Markdown, JSON and
CSV. :func:`scalar_metrics` picks the scalars out of a script's nested result.
"""

from __future__ import annotations

import csv
import json
import math
import statistics
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from torchcontact._checks import check_real

#: The columns of :func:`write_statistics`' CSV file, in order.
STATISTICS_COLUMNS = (
    "setting",
    "metric",
    "n",
    "left_out",
    "mean",
    "std",
    "min",
    "max",
    "ci_low",
    "ci_high",
    "confidence",
)


@dataclass(frozen=True)
class SeedStatistics:
    r"""Mean, range and Student-t confidence interval of one metric over ``n`` seeds.

    With the sample mean :math:`\bar x` and the sample standard deviation
    :math:`s = \sqrt{\sum_i (x_i - \bar x)^2 / (n - 1)}`, the interval for the mean is

    .. math:: \bar x \pm t_{(1 + c)/2,\; n - 1}\, s / \sqrt{n},

    with :math:`t_{p, \nu}` the ``p`` quantile of Student's t distribution with ``ν`` degrees
    of freedom and ``c`` the confidence (W. S. Gosset, "The probable error of a mean",
    Biometrika 6, 1908). It assumes the seeds' values are independent draws of a normal
    variable; for a few seeds of a skewed metric it is a rough guide.

    Attributes:
        n: number of values (seeds).
        mean: their mean.
        std: their sample standard deviation (``n − 1`` in the denominator); ``nan`` for one
            value.
        min: the smallest value.
        max: the largest value.
        ci_low: lower end of the interval; ``nan`` for one value.
        ci_high: upper end of the interval; ``nan`` for one value.
        confidence: the interval's confidence ``c``, in (0, 1).
    """

    n: int
    mean: float
    std: float
    min: float
    max: float
    ci_low: float
    ci_high: float
    confidence: float


@dataclass(frozen=True)
class SweepRow:
    """The statistics of one metric of one setting of a sweep.

    Attributes:
        setting: the setting's label (e.g. ``"particles=8"``; empty for a single setting).
        metric: the metric's name.
        statistics: its statistics over the seeds whose value is finite.
        left_out: number of seeds whose value was not finite (nan, ±inf) and is left out of
            ``statistics``.
    """

    setting: str
    metric: str
    statistics: SeedStatistics
    left_out: int = 0


def _check_confidence(confidence: float) -> float:
    return check_real("confidence", confidence, low=0.0, high=1.0, low_open=True, high_open=True)


def seed_statistics(values: Sequence[float], *, confidence: float = 0.95) -> SeedStatistics:
    """Mean, range and Student-t interval of one metric's values over seeds.

    Args:
        values: one finite value per seed (at least one).
        confidence: the interval's confidence, in (0, 1).

    Returns:
        The :class:`SeedStatistics`; with one value its standard deviation and interval are
        ``nan`` (a single seed says nothing of the spread).

    Raises:
        ValueError: naming ``values`` (empty, or a value not a finite number) or
            ``confidence``.
    """
    confidence = _check_confidence(confidence)
    floats = []
    for index, value in enumerate(values):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"values[{index}]: expected a number, got {value!r}")
        if not math.isfinite(value):
            raise ValueError(f"values[{index}]: expected a finite number, got {value!r}")
        floats.append(float(value))
    n = len(floats)
    if n == 0:
        raise ValueError("values: expected at least one value")
    mean = math.fsum(floats) / n
    if n == 1:
        std = ci_low = ci_high = math.nan
    else:
        from scipy import stats  # here: importing scipy.stats takes a while, needed only here

        std = statistics.stdev(floats, mean)
        half = float(stats.t.ppf(0.5 + confidence / 2, n - 1)) * std / math.sqrt(n)
        ci_low, ci_high = mean - half, mean + half
    return SeedStatistics(
        n=n,
        mean=mean,
        std=std,
        min=min(floats),
        max=max(floats),
        ci_low=ci_low,
        ci_high=ci_high,
        confidence=confidence,
    )


def aggregate_seeds(
    results: Mapping[str, Sequence[Mapping[str, float]]],
    *,
    confidence: float = 0.95,
    metrics: Sequence[str] | None = None,
) -> list[SweepRow]:
    """The statistics of every metric of every setting over its seeds.

    Args:
        results: per setting label, one ``{metric: value}`` per seed. A metric missing from
            some seeds is summarized over those that have it; non-finite values are left out
            and counted (:attr:`SweepRow.left_out`).
        confidence: the intervals' confidence, in (0, 1).
        metrics: the metrics to summarize, in table order; ``None``: every metric, in the
            order they first appear.

    Returns:
        One :class:`SweepRow` per setting (in ``results``' order) and metric (a metric no
        seed of a setting has a finite value of is skipped for that setting).

    Raises:
        ValueError: naming ``confidence``, or ``results`` (a setting with no seeds, a value
            not a number).
    """
    _check_confidence(confidence)
    rows = []
    for setting, runs in results.items():
        if not runs:
            raise ValueError(f"results: setting {setting!r} has no seeds")
        names = list(metrics) if metrics is not None else _first_seen(runs)
        for metric in names:
            values = [run[metric] for run in runs if metric in run]
            for value in values:
                if isinstance(value, bool) or not isinstance(value, int | float):
                    raise ValueError(
                        f"results: {setting!r} {metric!r}: expected numbers, got {value!r}"
                    )
            finite = [value for value in values if math.isfinite(value)]
            if finite:
                rows.append(
                    SweepRow(
                        setting=setting,
                        metric=metric,
                        statistics=seed_statistics(finite, confidence=confidence),
                        left_out=len(values) - len(finite),
                    )
                )
    return rows


def _first_seen(runs: Iterable[Mapping[str, float]]) -> list[str]:
    names: dict[str, None] = {}
    for run in runs:
        names.update(dict.fromkeys(run))
    return list(names)


def scalar_metrics(result: Mapping[str, Any]) -> dict[str, float]:
    """The scalars of a nested result, by their ``/``-joined keys.

    Ints and floats are kept (as floats, nan and inf included), nested mappings are entered
    (``{"summary": {"grid": {"seconds": 3.0}}}`` gives ``{"summary/grid/seconds": 3.0}``);
    booleans, strings, sequences and everything else are left out.

    Args:
        result: a script's result (the dict ``run(args)`` returns).
    """
    flat: dict[str, float] = {}
    for key, value in result.items():
        if isinstance(value, Mapping):
            for inner, number in scalar_metrics(value).items():
                flat[f"{key}/{inner}"] = number
        elif isinstance(value, int | float) and not isinstance(value, bool):
            flat[str(key)] = float(value)
    return flat


def statistics_records(rows: Sequence[SweepRow]) -> list[dict[str, Any]]:
    """The rows as flat dicts with the keys :data:`STATISTICS_COLUMNS` (JSON, CSV)."""
    return [
        {"setting": row.setting, "metric": row.metric, "left_out": row.left_out}
        | asdict(row.statistics)
        for row in rows
    ]


def statistics_table(rows: Sequence[SweepRow], *, digits: int = 4) -> str:
    """The rows as a Markdown table: setting, metric, seeds, mean, range and interval.

    Args:
        rows: from :func:`aggregate_seeds`.
        digits: significant digits of the numbers.

    Raises:
        ValueError: ``digits`` is not an int >= 1, or the rows' confidences differ.
    """
    if isinstance(digits, bool) or not isinstance(digits, int) or digits < 1:
        raise ValueError(f"digits: expected an int >= 1, got {digits!r}")
    confidences = {row.statistics.confidence for row in rows}
    if len(confidences) > 1:
        raise ValueError(f"rows: expected one confidence, got {sorted(confidences)}")
    level = f"{100 * confidences.pop():g} %" if confidences else "95 %"

    def number(value: float) -> str:
        return "–" if math.isnan(value) else f"{value:.{digits}g}"

    lines = [
        f"| setting | metric | seeds | mean | min – max | {level} interval |",
        "|---|---|--:|--:|--:|--:|",
    ]
    for row in rows:
        s = row.statistics
        seeds = f"{s.n}" + (f" (+{row.left_out} non-finite)" if row.left_out else "")
        lines.append(
            f"| {row.setting or '–'} | {row.metric} | {seeds} | {number(s.mean)} "
            f"| {number(s.min)} – {number(s.max)} | {number(s.ci_low)} – {number(s.ci_high)} |"
        )
    return "\n".join(lines) + "\n"


def write_statistics(rows: Sequence[SweepRow], folder: Path, *, stem: str = "statistics") -> None:
    """Write the rows to ``folder/<stem>.json`` (a list of records, ``null`` for nan),
    ``<stem>.csv`` (the columns :data:`STATISTICS_COLUMNS`, ``nan`` for nan) and ``<stem>.md``
    (:func:`statistics_table`).

    Args:
        rows: from :func:`aggregate_seeds`.
        folder: an existing folder.
        stem: the files' name without suffix.
    """
    records = statistics_records(rows)
    strict = [
        {key: None if isinstance(v, float) and math.isnan(v) else v for key, v in record.items()}
        for record in records
    ]
    (folder / f"{stem}.json").write_text(json.dumps(strict, indent=2, allow_nan=False) + "\n")
    with (folder / f"{stem}.csv").open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=STATISTICS_COLUMNS)
        writer.writeheader()
        writer.writerows(records)
    (folder / f"{stem}.md").write_text(statistics_table(rows))
