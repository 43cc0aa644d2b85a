"""Tactile sensor arrays: geometric trigger model, false-positive/negative noise, likelihoods."""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from torchcontact._checks import (
    FLOAT_DTYPES,
    check_dim,
    check_dtype,
    check_float,
    check_instance,
    check_real,
)
from torchcontact.states._contact_set import ContactSet
from torchcontact.states._contact_state import ContactState
from torchcontact.states._frames import check_pose, rotation_matrix
from torchcontact.states._grid import FeatureGrid

# Corners of a unit pad in (tangent, normal) coordinates.
_SQUARE = ((-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0))


@dataclass(frozen=True, eq=False)
class TactileArray:
    """An array of ``S`` binary contact sensors on a body's boundary (Fig. 2 of the seed paper).

    Sensor ``s`` sits at ``positions[s]`` with outward normal ``normals[s]`` (body frame). A
    contact *triggers* it when the contact is active (mode ``>= 1``) with normal impulse
    ``pn >= min_impulse``, lies within ``radius[s]`` of the sensor, and its contact normal —
    which points into the body — is within ``half_angle[s]`` of the inward sensor normal
    ``−normals[s]`` (the "triangle" of directions in Fig. 2). Both bounds are inclusive.

    The reading of a sensor flips with the noise model: a triggered sensor reads ``False`` with
    probability ``false_negative``, an untriggered one reads ``True`` with probability
    ``false_positive``, independently across sensors and time steps given the contacts.

    Scalars given for ``radius``, ``half_angle``, ``false_positive`` and ``false_negative`` are
    broadcast to ``(S,)`` tensors at construction.

    Attributes:
        positions: ``(S, d)`` sensor positions in the body frame, metres.
        normals: ``(S, d)`` outward unit normals in the body frame (normalized here).
        radius: ``(S,)`` sensing radius, metres, ``> 0``.
        half_angle: ``(S,)`` half-angle of the cone of triggering normals, radians, in
            ``[0, π]``.
        false_positive: ``(S,)`` probability of reading ``True`` when not triggered.
        false_negative: ``(S,)`` probability of reading ``False`` when triggered.
        min_impulse: least normal impulse of a triggering contact, ``>= 0``.
    """

    positions: Tensor
    normals: Tensor
    radius: Tensor | float
    half_angle: Tensor | float
    false_positive: Tensor | float = 0.0
    false_negative: Tensor | float = 0.0
    min_impulse: float = 0.0

    def __post_init__(self) -> None:
        positions = check_float("positions", self.positions, trailing=(-1, -1), what="(S, d)")
        if positions.ndim != 2:
            raise ValueError(f"positions must have shape (S, d), got {tuple(positions.shape)}")
        S, d = positions.shape
        check_dim("positions.shape[-1]", d)
        normals = check_float("normals", self.normals, trailing=(S, d), what=f"({S}, {d})")
        if normals.shape != positions.shape or normals.dtype != positions.dtype:
            raise ValueError(
                f"normals must match positions ({S}, {d}) {positions.dtype}, "
                f"got {tuple(normals.shape)} {normals.dtype}"
            )
        norms = torch.linalg.vector_norm(normals, dim=-1, keepdim=True)
        if bool((norms == 0).any()):
            raise ValueError("normals must be non-zero")
        object.__setattr__(self, "normals", normals / norms)
        bounds = {
            "radius": (0.0, math.inf, False),
            "half_angle": (0.0, math.pi, True),
            "false_positive": (0.0, 1.0, True),
            "false_negative": (0.0, 1.0, True),
        }
        for name, (low, high, closed) in bounds.items():
            value = getattr(self, name)
            if not isinstance(value, Tensor):
                number = check_real(name, value)
                value = torch.full((S,), number, dtype=positions.dtype)
            value = check_float(name, value, trailing=(S,), what=f"({S},) or a float")
            if value.shape != (S,) or value.dtype != positions.dtype:
                raise ValueError(
                    f"{name} must be a float or a ({S},) {positions.dtype} tensor, "
                    f"got {tuple(value.shape)} {value.dtype}"
                )
            above = value >= low if closed else value > low
            if not bool((above & (value <= high)).all()):
                interval = f"{'[' if closed else '('}{low}, {high}]"
                raise ValueError(f"{name} must lie in {interval}, got {value.tolist()}")
            object.__setattr__(self, name, value.to(positions.device))
        impulse: object = self.min_impulse
        if (
            isinstance(impulse, bool)
            or not isinstance(impulse, numbers.Real)
            or not math.isfinite(impulse)
            or impulse < 0
        ):
            raise ValueError(f"min_impulse must be a finite number >= 0, got {impulse!r}")
        object.__setattr__(self, "min_impulse", float(impulse))

    @property
    def num_sensors(self) -> int:
        """``S``, the number of sensors."""
        return int(self.positions.shape[0])

    @property
    def dim(self) -> int:
        """Spatial dimension ``d``."""
        return int(self.positions.shape[1])

    def _tensor(self, name: str) -> Tensor:
        value = getattr(self, name)
        assert isinstance(value, Tensor)
        return value

    def _hits(self, points: Tensor, normals: Tensor, active: Tensor) -> Tensor:
        """``(*B, S)`` bool: some active contact of ``(*B, K, d)`` triggers each sensor."""
        offset = points.unsqueeze(-2) - self.positions  # (*B, K, S, d)
        near = torch.linalg.vector_norm(offset, dim=-1) <= self._tensor("radius")
        cosine = (normals.unsqueeze(-2) * -self.normals).sum(-1)
        inside = cosine >= torch.cos(self._tensor("half_angle"))
        hits: Tensor = (active.unsqueeze(-1) & near & inside).any(dim=-2)
        return hits

    def triggered(self, contacts: ContactSet) -> Tensor:
        """Noise-free readings: which sensors the contacts trigger.

        Args:
            contacts: contacts of the body that carries the sensors, batch shape ``*B``
                (expressed in the body frame via :meth:`ContactSet.object_frame`).

        Returns:
            ``(*B, S)`` bool.

        Raises:
            ValueError: the contacts' dimension or dtype differs from the array's.
        """
        check_instance("contacts", contacts, ContactSet)
        if contacts.dim != self.dim or contacts.points.dtype != self.positions.dtype:
            raise ValueError(
                f"contacts must have d = {self.dim} and dtype {self.positions.dtype}, "
                f"got d = {contacts.dim} and {contacts.points.dtype}"
            )
        points, normals = contacts.object_frame()
        active = contacts.active & (contacts.pn >= self.min_impulse)
        return self._hits(points, normals, active)

    def trigger_table(self, states: Sequence[ContactState], grid: FeatureGrid) -> Tensor:
        """Noise-free readings expected in each contact state, from its features' centres.

        Each feature stands for one contact at its canonical location with its canonical
        normal (:meth:`FeatureGrid.location`, :meth:`FeatureGrid.direction`); features of both
        partner kinds touch the body and trigger sensors. The centres are within ``δ_r`` and
        ``δ_θ`` of the real contacts, so sensors whose region or cone ends closer than that to
        a contact may disagree with :meth:`triggered`; an empirical table (the frequency with
        which each sensor was triggered in each state) can replace this one in
        :meth:`log_likelihood`.

        Args:
            states: ``N`` contact states, e.g. ``registry.states``.
            grid: the grid that defined the states.

        Returns:
            ``(N, S)`` table of 0.0 / 1.0 in the array's dtype.

        Raises:
            ValueError: the grid's dimension differs from the array's.
        """
        check_instance("grid", grid, FeatureGrid)
        if not isinstance(states, Sequence) or not all(
            isinstance(state, ContactState) for state in states
        ):
            raise ValueError("states must be a sequence of ContactState objects")
        if grid.dim != self.dim:
            raise ValueError(f"grid.dim must equal the array's d = {self.dim}, got {grid.dim}")
        if any(len(f.cell) != self.dim for state in states for f in state.features):
            raise ValueError(f"states must have features of dimension d = {self.dim}")
        N, F, d = len(states), max([len(s.features) for s in states] + [1]), self.dim
        cells = torch.zeros((N, F, d), dtype=torch.long)
        directions = torch.zeros((N, F, d), dtype=torch.long)
        mask = torch.zeros((N, F), dtype=torch.bool)
        for i, state in enumerate(states):
            for j, feature in enumerate(state.features):
                cells[i, j] = torch.tensor(feature.cell)
                directions[i, j] = torch.tensor(feature.direction)
                mask[i, j] = True
        dtype, device = self.positions.dtype, self.positions.device
        points = grid.location(cells, dtype=dtype).to(device)
        normals = grid.direction(directions, dtype=dtype).to(device)
        return self._hits(points, normals, mask.to(device)).to(dtype)

    def reading_probability(self, triggers: Tensor) -> Tensor:
        """Probability that each sensor reads ``True``.

        Args:
            triggers: ``(*B, S)`` bool noise-free readings, or the probability in ``[0, 1]``
                that each sensor is triggered.

        Returns:
            ``(*B, S)`` ``triggers (1 − false_negative) + (1 − triggers) false_positive``.
        """
        triggers = self._check_triggers("triggers", triggers)
        fn, fp = self._tensor("false_negative"), self._tensor("false_positive")
        return triggers * (1 - fn) + (1 - triggers) * fp

    def sample(self, triggers: Tensor, *, generator: torch.Generator | None = None) -> Tensor:
        """Noisy readings drawn from the noise model.

        Args:
            triggers: ``(*B, S)`` bool noise-free readings or trigger probabilities.
            generator: source of randomness (on the array's device); ``None`` uses torch's
                global generator.

        Returns:
            ``(*B, S)`` bool readings.
        """
        probability = self.reading_probability(triggers)
        if generator is not None and not isinstance(generator, torch.Generator):
            raise ValueError(f"generator must be a torch.Generator, got {type(generator).__name__}")
        uniform = torch.rand(
            probability.shape,
            generator=generator,
            dtype=probability.dtype,
            device=probability.device,
        )
        return uniform < probability

    def log_likelihood(self, readings: Tensor, triggers: Tensor) -> Tensor:
        """Log-likelihood of readings under each state of a table.

        ``log p(r | state i) = Σ_s log P(r_s | state i)`` with the independent per-sensor
        noise model; ``-inf`` where a reading is impossible (e.g. a triggered reading when
        ``false_positive = 0`` and the state triggers nothing there).

        Args:
            readings: ``(*B, S)`` bool readings.
            triggers: ``(N, S)`` trigger table, bool or probabilities (e.g.
                :meth:`trigger_table`), one row per state.

        Returns:
            ``(*B, N)`` log-likelihoods in the array's dtype.

        Raises:
            ValueError: wrong shapes or dtypes.
        """
        S = self.num_sensors
        check_dtype("readings", readings, torch.bool, f"(*B, {S})")
        if readings.ndim < 1 or readings.shape[-1] != S:
            raise ValueError(f"readings must have shape (*B, {S}), got {tuple(readings.shape)}")
        if not isinstance(triggers, Tensor) or triggers.ndim != 2:
            shape = tuple(triggers.shape) if isinstance(triggers, Tensor) else triggers
            raise ValueError(f"triggers must have shape (N, {S}), got {shape}")
        return self.reading_log_likelihood(readings.unsqueeze(-2), triggers)  # (*B, N)

    def reading_log_likelihood(self, readings: Tensor, triggers: Tensor) -> Tensor:
        """Log-likelihood of readings given triggers, both broadcast (one state per entry).

        ``Σ_s [r_s log P(r_s = 1 | t_s) + (1 − r_s) log P(r_s = 0 | t_s)]`` with
        :meth:`reading_probability` per sensor: the noise model that :meth:`log_likelihood`
        applies to a table of states, for triggers that differ per batch entry (e.g. the
        simulated contacts of each particle).

        Args:
            readings: ``(..., S)`` bool readings.
            triggers: ``(..., S)`` bool noise-free readings or trigger probabilities,
                broadcastable with ``readings``.

        Returns:
            The broadcast batch shape, log-likelihoods in the triggers' dtype.

        Raises:
            ValueError: ``readings`` is not bool.
        """
        check_dtype("readings", readings, torch.bool, "(..., S)")
        on = self.reading_probability(triggers)
        return torch.where(readings, torch.log(on), torch.log1p(-on)).sum(-1)

    def draw(
        self,
        ax: Any,
        readings: Tensor | None = None,
        *,
        pose: Tensor | None = None,
        color: str = "tab:green",
        length: float | None = None,
    ) -> Any:
        """Draw a planar array: each sensor as a pad with its cone of triggering directions.

        The cone (the "triangle" of Fig. 2) opens outward from the sensor with half-angle
        ``half_angle``: a partner pushing from inside it triggers the sensor. Triggered sensors
        (``readings`` true) are filled with ``color``, the others grey.

        Args:
            ax: matplotlib ``Axes``.
            readings: ``(S,)`` bool readings, or ``None`` (nothing triggered).
            pose: ``(3,)`` planar pose of the body in the world frame (default: body frame).
            color: fill of triggered sensors.
            length: length of the cones, metres (default: twice the largest radius).

        Returns:
            ``ax``.

        Raises:
            ValueError: the array is not planar or the arguments have the wrong shapes.
        """
        from matplotlib.patches import Polygon

        S = self.num_sensors
        if self.dim != 2:
            raise ValueError(f"only planar arrays (d = 2) can be drawn, got d = {self.dim}")
        on = torch.zeros(S, dtype=torch.bool) if readings is None else readings.cpu()
        if on.dtype != torch.bool or on.shape != (S,):
            raise ValueError(f"readings must be a ({S},) bool tensor")
        positions, normals = self.positions.cpu(), self.normals.cpu()
        if pose is not None:
            pose = check_pose("pose", pose, 2).cpu().to(positions.dtype)
            if pose.shape != (3,):
                raise ValueError(f"pose must have shape (3,), got {tuple(pose.shape)}")
            R = rotation_matrix(pose, 2)
            positions, normals = positions @ R.T + pose[:2], normals @ R.T
        radius = self._tensor("radius").cpu()
        half_angle = self._tensor("half_angle").cpu()
        cone = 2.0 * float(radius.max()) if length is None else length
        for s in range(S):
            p, n = positions[s], normals[s]
            t = torch.stack([-n[1], n[0]])
            pad = [p + 0.5 * radius[s] * t * u + 0.08 * radius[s] * n * v for u, v in _SQUARE]
            fill = color if bool(on[s]) else "0.8"
            ax.add_patch(Polygon(torch.stack(pad).tolist(), closed=True, fc=fill, ec="k", lw=0.8))
            c, si = torch.cos(half_angle[s]), torch.sin(half_angle[s])
            sides = [n * c + t * si, n * c - t * si]
            triangle = [p, p + cone * sides[0], p + cone * sides[1]]
            ax.add_patch(
                Polygon(
                    torch.stack(triangle).tolist(), closed=True, fc=fill, ec="k", lw=0.5, alpha=0.5
                )
            )
        ax.set_aspect("equal")
        ax.autoscale_view()
        return ax

    def _check_triggers(self, name: str, triggers: Tensor) -> Tensor:
        S = self.num_sensors
        if not isinstance(triggers, Tensor) or triggers.ndim < 1 or triggers.shape[-1] != S:
            shape = tuple(triggers.shape) if isinstance(triggers, Tensor) else triggers
            raise ValueError(f"{name} must be a (*B, {S}) tensor, got {shape}")
        if triggers.dtype == torch.bool:
            return triggers.to(self.positions.dtype)
        check_float(name, triggers, trailing=(S,), what=f"(*B, {S})")
        if triggers.dtype != self.positions.dtype:
            raise ValueError(f"{name} must be bool or {self.positions.dtype}, got {triggers.dtype}")
        if bool(((triggers < 0) | (triggers > 1)).any()):
            raise ValueError(f"{name} probabilities must lie in [0, 1]")
        return triggers


def rectangle_sensors(
    *,
    half_extents: tuple[float, float],
    counts: tuple[int, int, int, int],
    radius: float,
    half_angle: float,
    false_positive: float = 0.0,
    false_negative: float = 0.0,
    dtype: torch.dtype | None = None,
) -> TactileArray:
    """Sensors evenly spaced along the sides of a rectangle centred at its body origin.

    Sides are visited counter-clockwise: bottom (``−y``, left to right), right (``+x``, bottom
    to top), top (``+y``, right to left), left (``−x``, top to bottom). A side of length ``L``
    with ``n`` sensors carries them at the centres of ``n`` equal segments, ``L (i + ½) / n``
    from the side's start; sensor indices follow that order.

    Args:
        half_extents: ``(a, b)`` half width and half height, metres.
        counts: number of sensors on the bottom, right, top and left sides.
        radius: sensing radius of every sensor, metres.
        half_angle: cone half-angle of every sensor, radians.
        false_positive: false-positive rate of every sensor.
        false_negative: false-negative rate of every sensor.
        dtype: floating dtype (default: torch's default dtype).

    Returns:
        The planar :class:`TactileArray` with ``S = sum(counts)`` sensors.
    """
    if not isinstance(half_extents, (tuple, list)) or len(half_extents) != 2:
        raise ValueError(f"half_extents must be a pair (a, b), got {half_extents!r}")
    a = check_real("half_extents", half_extents[0], low=0.0, low_open=True)
    b = check_real("half_extents", half_extents[1], low=0.0, low_open=True)
    if (
        not isinstance(counts, (tuple, list))
        or len(counts) != 4
        or any(isinstance(n, bool) or not isinstance(n, int) or n < 0 for n in counts)
    ):
        raise ValueError(f"counts must be four ints >= 0, got {counts!r}")
    if dtype is not None and dtype not in FLOAT_DTYPES:
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    corners = [(-a, -b), (a, -b), (a, b), (-a, b)]
    outward = [(0.0, -1.0), (1.0, 0.0), (0.0, 1.0), (-1.0, 0.0)]
    positions, normals = [], []
    for side, n in enumerate(counts):
        (x0, y0), (x1, y1) = corners[side], corners[(side + 1) % 4]
        for i in range(n):
            t = (i + 0.5) / n
            positions.append((x0 + t * (x1 - x0), y0 + t * (y1 - y0)))
            normals.append(outward[side])
    dtype = dtype or torch.get_default_dtype()
    return TactileArray(
        positions=torch.tensor(positions, dtype=dtype).reshape(-1, 2),
        normals=torch.tensor(normals, dtype=dtype).reshape(-1, 2),
        radius=radius,
        half_angle=half_angle,
        false_positive=false_positive,
        false_negative=false_negative,
    )
