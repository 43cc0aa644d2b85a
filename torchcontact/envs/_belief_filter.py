"""The peg-in-hole filter: the RBPF of a belief model, on the environment's observations.

:class:`PegInHoleFilter` holds no fitted data: it unpacks the noisy observations of
``PegInHole2D`` (camera pose, gripper pose, tactile readings), starts, steps and restarts the
:class:`~torchcontact.filters.RBPF` of a belief model (the fitted
:class:`~torchcontact.envs.PegInHoleBeliefModel` or the contact physics'
:class:`~torchcontact.envs.PegPhysicsModel`), and keeps each particle's manipulation-state id
with the belief (:class:`PegBelief`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

from torchcontact.envs._belief_model import PegControl, PegInHoleBeliefModel
from torchcontact.envs._physics_model import PegPhysicsModel
from torchcontact.envs._states import NUM_CONTACT_CLASSES
from torchcontact.envs._transitions import as_tensor
from torchcontact.filters import RBPF, Gaussian, Proposal, RBPFBelief, ResamplingMethod

_F64 = torch.float64


@dataclass(frozen=True, eq=False)
class PegBelief:
    """The filter's belief over a batch of ``B`` episodes.

    Attributes:
        rbpf: the particles (contact class + Gaussian over the grasp), batch ``(B,)``.
        gripper: ``(B, 3)`` the gripper poses (world) the belief refers to.
        state_ids: ``(B, N)`` long manipulation-state id of each particle
            (:meth:`~torchcontact.envs.PegInHoleBeliefModel.particle_state_ids` of ``rbpf``
            and ``gripper``), computed once when the belief is made: the policies read them
            and the next filter step's mode transition reuses them.
    """

    rbpf: RBPFBelief
    gripper: Tensor
    state_ids: Tensor


#: The belief models the filter runs on.
PegBeliefModel = PegInHoleBeliefModel | PegPhysicsModel


class PegInHoleFilter:
    """The RBPF of a peg belief model over a batch of episodes, on observations.

    Observations are those of ``PegInHole2D(observation="noisy")`` (or the vector version):
    mappings with ``peg_pose (B, 3)``, ``gripper_pose (B, 3)`` and ``tactile (B, S)``; a row
    of ``peg_pose`` that is all NaN (the camera lost the peg) is no measurement.

    Args:
        model: the fitted model (:class:`PegInHoleBeliefModel`) or the physics model
            (:class:`PegPhysicsModel`).
        num_particles: particles per episode.
        proposal: ``"bootstrap"`` or ``"all_modes"`` (see :class:`RBPF`).
        resampling: the resampling scheme.
        ess_threshold: resample when the ESS falls below this fraction of ``num_particles``.
    """

    def __init__(
        self,
        model: PegBeliefModel,
        *,
        num_particles: int = 64,
        proposal: Proposal = "bootstrap",
        resampling: ResamplingMethod = "systematic",
        ess_threshold: float = 0.5,
    ) -> None:
        if not isinstance(model, (PegInHoleBeliefModel, PegPhysicsModel)):
            raise ValueError(
                f"model must be a PegInHoleBeliefModel or PegPhysicsModel, got "
                f"{type(model).__name__}"
            )
        self.model: PegBeliefModel = model
        self.rbpf = RBPF(
            model,
            num_particles,
            proposal=proposal,
            resampling=resampling,
            ess_threshold=ess_threshold,
        )

    @property
    def num_particles(self) -> int:
        """``N``."""
        return self.rbpf.num_particles

    def init(self, observation: Mapping[str, Any]) -> PegBelief:
        """The belief at the start of episodes: the grasp prior updated with the first image.

        Args:
            observation: the first observation of each episode (batch ``B``).
        """
        y, gripper, _ = self._unpack(observation)
        return self._belief(self.rbpf.init(self.model.initial_gaussian(y, gripper)), gripper)

    def step(
        self,
        belief: PegBelief,
        actions: Tensor | NDArray[np.int64],
        observation: Mapping[str, Any],
        *,
        generator: torch.Generator | None = None,
    ) -> PegBelief:
        """Advance the belief over one environment step.

        Args:
            belief: the belief before the step.
            actions: ``(B,)`` actions taken.
            observation: the observation after the step.
            generator: random source of the particle filter.
        """
        y, gripper, readings = self._unpack(observation)
        actions = as_tensor(actions, torch.long)
        control = PegControl(
            state_ids=belief.state_ids,
            gripper_after=gripper,
            actions=actions,
            gripper_before=belief.gripper,
        )
        rbpf = self.rbpf.step(
            belief.rbpf,
            y,
            action=actions,
            extra_log_likelihood=self.model.tactile_evidence(readings, belief.rbpf, control),
            control=control,
            generator=generator,
        )
        return self._belief(rbpf, gripper)

    def restart(
        self, belief: PegBelief, where: Tensor | NDArray[np.bool_], observation: Mapping[str, Any]
    ) -> PegBelief:
        """Restart the entries ``where (B,)`` (new episodes) from ``observation``."""
        where = as_tensor(where, torch.bool)
        if not bool(where.any()):
            return belief
        fresh = self.init(observation)

        def pick(new: Tensor, old: Tensor) -> Tensor:
            mask = where.reshape(-1, *(1,) * (old.ndim - 1))
            return torch.where(mask, new, old)

        def merge(new: Any, old: Any) -> Any:
            if isinstance(old, Tensor):
                return pick(new, old)
            if isinstance(old, Gaussian):
                return Gaussian(pick(new.mean, old.mean), pick(new.cov, old.cov))
            return old  # the number of modes

        old, new = belief.rbpf, fresh.rbpf
        merged = {f.name: merge(getattr(new, f.name), getattr(old, f.name)) for f in fields(old)}
        return PegBelief(
            replace(old, **merged),
            pick(fresh.gripper, belief.gripper),
            pick(fresh.state_ids, belief.state_ids),
        )

    def particle_poses(self, belief: PegBelief) -> Tensor:
        """``(B, N, 3)`` each particle's mean peg pose in the world frame."""
        return self.model.particle_poses(belief.rbpf, belief.gripper)

    def particle_states(self, belief: PegBelief) -> tuple[Tensor, Tensor]:
        """Each particle's manipulation-state id ``(B, N)`` (:attr:`PegBelief.state_ids`, not
        computed again) and weight ``(B, N)``."""
        return belief.state_ids, belief.rbpf.log_weights.exp()

    def class_marginals(self, belief: PegBelief) -> Tensor:
        """``(B, C)`` the belief's probability of each of the ``C = 24`` contact classes."""
        classes = self.model.particle_classes(belief.rbpf)
        weights = belief.rbpf.log_weights.exp()
        out = weights.new_zeros(weights.shape[0], NUM_CONTACT_CLASSES)
        return out.scatter_add_(1, classes, weights)

    def pose_mean(self, belief: PegBelief) -> Tensor:
        """``(B, 3)`` the weighted mean of the peg's world pose."""
        weights = belief.rbpf.log_weights.exp().unsqueeze(-1)
        return (weights * self.particle_poses(belief)).sum(1)

    def _belief(self, rbpf: RBPFBelief, gripper: Tensor) -> PegBelief:
        """The belief of particles ``rbpf`` held by grippers ``gripper``, with their state ids."""
        return PegBelief(rbpf, gripper, self.model.particle_state_ids(rbpf, gripper))

    def _unpack(self, observation: Mapping[str, Any]) -> tuple[Tensor, Tensor, Tensor]:
        try:
            y = as_tensor(observation["peg_pose"], _F64)
            gripper = as_tensor(observation["gripper_pose"], _F64)
            readings = as_tensor(observation["tactile"], torch.bool)
        except (KeyError, TypeError) as err:
            raise ValueError(
                "observation must map peg_pose, gripper_pose and tactile to arrays "
                "(PegInHole2D(observation='noisy'))"
            ) from err
        if y.ndim != 2 or y.shape[1] != 3 or gripper.shape != y.shape:
            raise ValueError(
                f"observation: peg_pose and gripper_pose must be (B, 3), got "
                f"{tuple(y.shape)} and {tuple(gripper.shape)}"
            )
        if readings.ndim != 2 or readings.shape[0] != y.shape[0]:
            raise ValueError(f"observation: tactile must be (B, S), got {tuple(readings.shape)}")
        # A peg the camera lost (PegInHoleConfig.occlusion_radius) is an all-NaN row: no
        # measurement for the RBPF.
        seen = torch.isfinite(y).all(-1) | torch.isnan(y).all(-1)
        if not bool(seen.all() and torch.isfinite(gripper).all()):
            raise ValueError(
                "observation: gripper_pose must be finite, peg_pose finite or all-NaN per row"
            )
        return y, gripper, readings


__all__ = ["PegBelief", "PegBeliefModel", "PegInHoleFilter"]
