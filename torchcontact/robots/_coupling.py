"""Linear joint coupling: the map from actuated coordinates to the full joint vector.

pytorch-kinematics ignores URDF ``<mimic>`` tags and treats every non-fixed joint as independent.
Mechanisms that drive several joints from one motor (the BarrettHand's spread and its TorqueSwitch
finger coupling, a symmetric parallel-jaw gripper) are therefore expressed here as an affine map

    q_full = C q + c,

with ``C`` ``(n_full, n)`` and ``c`` ``(n_full,)``, built from the mimic tags. Velocities map by
``C`` alone, so a Jacobian in actuated coordinates is ``J_full C``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from torchcontact._checks import check_float
from torchcontact.robots._urdf import UrdfMimic


@dataclass(frozen=True, eq=False)
class JointCoupling:
    """Affine map from actuated joint coordinates to the full joint vector.

    Attributes:
        full_names: Names of all non-fixed joints, in the kinematic chain's order (length n_full).
        actuated_names: Names of the independent (actuated) joints, a subsequence of ``full_names``
            (length n).
        matrix: ``C``, float64 ``(n_full, n)``: column k says how actuated joint k drives each
            joint.
        offset: ``c``, float64 ``(n_full,)`` (rad or m).
    """

    full_names: tuple[str, ...]
    actuated_names: tuple[str, ...]
    matrix: Tensor
    offset: Tensor

    @classmethod
    def from_mimic(
        cls, full_names: Sequence[str], mimic: Mapping[str, UrdfMimic | None]
    ) -> JointCoupling:
        """Build the coupling that URDF mimic tags describe.

        Args:
            full_names: All non-fixed joint names, in chain order.
            mimic: Joint name -> its mimic tag (or None for an independent joint).

        Returns:
            The coupling; joints without a mimic tag are the actuated ones, in chain order.

        Raises:
            ValueError: ``full_names`` is not a sequence of distinct strings, ``mimic`` is not a
                mapping, or a joint mimics an unknown joint or a joint that itself mimics
                another.
        """
        names = _check_names(full_names)
        if not isinstance(mimic, Mapping):
            raise ValueError(f"mimic must be a mapping, got {type(mimic).__name__}")
        actuated = tuple(name for name in names if mimic.get(name) is None)
        matrix = torch.zeros(len(names), len(actuated), dtype=torch.float64)
        offset = torch.zeros(len(names), dtype=torch.float64)
        for row, name in enumerate(names):
            tag = mimic.get(name)
            if tag is None:
                matrix[row, actuated.index(name)] = 1.0
                continue
            if tag.joint not in actuated:
                raise ValueError(
                    f"joint {name!r} mimics {tag.joint!r}, which is not an independent joint"
                )
            matrix[row, actuated.index(tag.joint)] = tag.multiplier
            offset[row] = tag.offset
        return cls(full_names=names, actuated_names=actuated, matrix=matrix, offset=offset)

    @classmethod
    def identity(cls, full_names: Sequence[str]) -> JointCoupling:
        """The coupling in which every joint is actuated independently (C = I, c = 0).

        Args:
            full_names: All non-fixed joint names, in chain order.

        Returns:
            The identity coupling.

        Raises:
            ValueError: ``full_names`` is not a sequence of distinct strings.
        """
        names = _check_names(full_names)
        return cls(
            full_names=names,
            actuated_names=names,
            matrix=torch.eye(len(names), dtype=torch.float64),
            offset=torch.zeros(len(names), dtype=torch.float64),
        )

    @property
    def is_identity(self) -> bool:
        """Whether every joint is actuated (no coupling)."""
        return self.actuated_names == self.full_names and bool(
            (self.offset == 0).all() and (self.matrix == torch.eye(len(self.full_names))).all()
        )

    def to_full(self, q: Tensor) -> Tensor:
        """Full joint vector from actuated coordinates: ``q_full = C q + c``.

        Args:
            q: Actuated coordinates ``(*B, n)`` (float32 or float64; any device).

        Returns:
            ``(*B, n_full)`` in ``q``'s dtype and device.

        Raises:
            ValueError: ``q`` is not a finite float32/float64 tensor or its last dimension is
                not n.
        """
        n = len(self.actuated_names)
        q = check_float("q", q)
        if q.ndim < 1 or q.shape[-1] != n:
            raise ValueError(f"q must have shape (*B, {n}), got {tuple(q.shape)}")
        matrix = self.matrix.to(dtype=q.dtype, device=q.device)
        offset = self.offset.to(dtype=q.dtype, device=q.device)
        return q @ matrix.T + offset


def _check_names(full_names: object) -> tuple[str, ...]:
    """``full_names`` as a tuple of distinct strings."""
    if (
        isinstance(full_names, str)
        or not isinstance(full_names, Sequence)
        or not all(isinstance(name, str) for name in full_names)
        or len(set(full_names)) != len(full_names)
    ):
        raise ValueError(f"full_names must be a sequence of distinct strings, got {full_names!r}")
    return tuple(full_names)
