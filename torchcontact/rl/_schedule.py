"""Exploration schedules."""

from __future__ import annotations

from dataclasses import dataclass

from torchcontact._checks import check_int, check_real


@dataclass(frozen=True)
class EpsilonSchedule:
    """Linear decay of the exploration probability: ``start`` at step 0, ``end`` from step
    ``steps`` on.

    ``ε(t) = start + (end − start) · min(t, steps) / steps`` (``end`` for every ``t`` when
    ``steps = 0``).

    Attributes:
        start: ε at step 0, in ``[0, 1]``.
        end: ε after the decay, in ``[0, 1]``.
        steps: length of the decay, ``>= 0``.

    Raises:
        ValueError: a field is out of range.
    """

    start: float = 1.0
    end: float = 0.05
    steps: int = 10_000

    def __post_init__(self) -> None:
        object.__setattr__(self, "start", check_real("start", self.start, low=0.0, high=1.0))
        object.__setattr__(self, "end", check_real("end", self.end, low=0.0, high=1.0))
        object.__setattr__(self, "steps", check_int("steps", self.steps, low=0))

    def __call__(self, step: int) -> float:
        """ε at ``step`` (an int ``>= 0``)."""
        step = check_int("step", step, low=0)
        if step >= self.steps:
            return self.end
        return self.start + (self.end - self.start) * (step / self.steps)
