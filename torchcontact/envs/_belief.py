"""Belief tracking for the peg-in-hole task: an RBPF over contact classes, fed by the graph.

The filter tracks the peg's pose *in the gripper frame* (the gripper's pose is known, the
fingers' servo sets it), so that the measurement of a camera that sees the peg in the world is
linear, and the peg's motion in the grasp, given its contact class, is a constant displacement
plus noise: it stays put while held without other contact, it slides up the pads when pushed
onto a surface, and so on. Each particle carries a contact class (the RBPF's mode) and a
Gaussian over that pose; the mode transition of a particle comes from the manipulation graph
at the particle's own manipulation state (its pose cell and contact class).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

from torchcontact.envs._states import NUM_CONTACT_CLASSES
from torchcontact.envs._task import ACTION_NAMES, PegInHoleTask
from torchcontact.filters import (
    RBPF,
    Gaussian,
    ModeDynamics,
    Proposal,
    RBPFBelief,
    ResamplingMethod,
    kf_update,
)
from torchcontact.geometry import rotation_matrix, wrap_angle
from torchcontact.states import ManipulationGraph

_F64 = torch.float64
#: Floor of the per-step process noise of the peg in the grasp: (0.2 mm, 0.2 mm, 3 mrad)².
_NOISE_FLOOR = (2e-4**2, 2e-4**2, 3e-3**2)
#: Process noise of a (action, class) pair never seen in the data: (5 mm, 5 mm, 0.05 rad)².
_UNSEEN_NOISE = (5e-3**2, 5e-3**2, 0.05**2)


def _tensor(value: Any, dtype: torch.dtype) -> Tensor:
    return torch.as_tensor(np.asarray(value), dtype=dtype)


@dataclass(frozen=True, kw_only=True)
class PegTransitions:
    """Recorded environment steps of the peg-in-hole task (what the filter model is fit on).

    Attributes:
        grasp: ``(T, 3)`` the peg's pose in the gripper frame before the step.
        next_grasp: ``(T, 3)`` the same after the step.
        actions: ``(T,)`` long actions.
        classes: ``(T,)`` long contact classes before the step.
        next_classes: ``(T,)`` long contact classes after it.
        next_triggered: ``(T, S)`` bool noise-free tactile readings after it.
        first: ``(T,)`` bool, the step is the first of its episode (its ``grasp`` is a reset).
    """

    grasp: Tensor
    next_grasp: Tensor
    actions: Tensor
    classes: Tensor
    next_classes: Tensor
    next_triggered: Tensor
    first: Tensor

    def __post_init__(self) -> None:
        T = self.actions.shape[0]
        expected = {
            "grasp": (T, 3),
            "next_grasp": (T, 3),
            "actions": (T,),
            "classes": (T,),
            "next_classes": (T,),
            "first": (T,),
        }
        for name, shape in expected.items():
            value = getattr(self, name)
            if not isinstance(value, Tensor) or tuple(value.shape) != shape:
                raise ValueError(f"{name} must be a {shape} tensor, got {_shape(value)}")
        if self.next_triggered.ndim != 2 or self.next_triggered.shape[0] != T:
            raise ValueError(f"next_triggered must be (T, S), got {_shape(self.next_triggered)}")
        if not bool(torch.isfinite(self.grasp).all() and torch.isfinite(self.next_grasp).all()):
            raise ValueError("grasp and next_grasp must be finite")

    @property
    def num_steps(self) -> int:
        """``T``, the number of recorded steps."""
        return int(self.actions.shape[0])

    @classmethod
    def from_infos(
        cls,
        before: Mapping[str, NDArray[Any]],
        actions: NDArray[np.int64],
        after: Mapping[str, NDArray[Any]],
        *,
        valid: NDArray[np.bool_],
        first: NDArray[np.bool_],
    ) -> PegTransitions:
        """The steps of a vector environment between two of its ``infos``.

        Args:
            before: infos before the step (keys ``peg_in_gripper``, ``contact_class``).
            actions: ``(B,)`` actions taken.
            after: infos after the step (also ``tactile_triggered``).
            valid: ``(B,)`` entries that really stepped (not an auto-reset).
            first: ``(B,)`` entries whose ``before`` is the first state of an episode.
        """
        keep = np.flatnonzero(valid)

        def take(info: Mapping[str, NDArray[Any]], key: str) -> NDArray[Any]:
            return np.asarray(info[key])[keep]

        return cls(
            grasp=_tensor(take(before, "peg_in_gripper"), _F64),
            next_grasp=_tensor(take(after, "peg_in_gripper"), _F64),
            actions=_tensor(np.asarray(actions)[keep], torch.long),
            classes=_tensor(take(before, "contact_class"), torch.long),
            next_classes=_tensor(take(after, "contact_class"), torch.long),
            next_triggered=_tensor(take(after, "tactile_triggered"), torch.bool),
            first=_tensor(np.asarray(first)[keep], torch.bool),
        )

    @classmethod
    def concat(cls, parts: Sequence[PegTransitions]) -> PegTransitions:
        """All steps of ``parts``, in order."""
        if not parts:
            raise ValueError("parts must hold at least one PegTransitions")
        return cls(**{f.name: torch.cat([getattr(p, f.name) for p in parts]) for f in fields(cls)})


def _shape(value: object) -> object:
    return tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__


@dataclass(frozen=True, kw_only=True)
class PegControl:
    """The known inputs of one filter step.

    Attributes:
        gripper_before: ``(B, 3)`` gripper poses (world) before the step.
        gripper_after: ``(B, 3)`` gripper poses after it.
        actions: ``(B,)`` long actions of the step.
    """

    gripper_before: Tensor
    gripper_after: Tensor
    actions: Tensor


@dataclass(frozen=True, eq=False, kw_only=True)
class PegInHoleBeliefModel:
    r"""Switching linear-Gaussian model of the peg in the grasp, for the :class:`RBPF`.

    State ``x = (u, w, φ)``: the peg's pose in the gripper frame. Mode ``k``: the peg's contact
    class at the end of the step (:func:`~torchcontact.envs.contact_classes`, ``K = 24``).
    For action ``a`` and new class ``k``:

    * dynamics: :math:`x_t = x_{t-1} + b_{a,k} + w`, :math:`w \sim N(0, Q_{a,k})`, the mean and
      covariance of the grasp displacement observed in ``(a, k)`` in training data (with a noise
      floor; pairs never seen get zero mean and a broad covariance): contact-state-conditioned
      linear dynamics identified from data;
    * vision: :math:`y_t = g_t \oplus x_t + v`, i.e. :math:`y = R(g_θ)\,(u, w) + g_{xy}` and
      :math:`y_θ = g_θ + φ`, linear given the gripper pose :math:`g_t`, :math:`v \sim N(0,
      \mathrm{diag}(σ^2))` with the camera's known noise;
    * tactile: :math:`\log p(r \mid k) = \sum_s \log P(r_s \mid k)` with the per-class trigger
      probability of each sensor (training frequency, Laplace-smoothed) pushed through the
      sensors' false-positive and false-negative rates (:meth:`tactile_log_likelihood`);
    * mode transition of particle ``i``: :math:`p(k \mid m_i, a)` where
      :math:`m_i = (\mathrm{cell}(g_{t-1} \oplus \hat x_i), k_i)` is the particle's
      manipulation state, from the manipulation graph's counts aggregated by next class and
      shrunk toward the class-level transition: :math:`p = (N(m_i, a, k) + β\,
      p_c(k \mid k_i, a)) / (N(m_i, a) + β)` (``β = graph_prior``).

    Build it with :meth:`fit`.

    Attributes:
        task: the task (geometry, sensors, state discretization).
        displacement: ``(A, K, 3)`` mean grasp displacement per step.
        process_cov: ``(A, K, 3, 3)`` its covariance.
        trigger: ``(K, S)`` probability that each sensor is touched in each class.
        class_transition: ``(A, K, K)`` class-level transition ``p_c(k′ | k, a)``.
        state_transition: ``(M + K, A, K)`` next-class distributions: one row per manipulation
            state the graph saw as a source, then the class-level row of each class (for the
            states it did not).
        state_row: ``(num_states,)`` long row of each manipulation state id in
            ``state_transition``.
        initial: ``(K,)`` class distribution at the start of an episode.
        class_prior: ``(K,)`` frequency of each class over all training steps (smoothed).
        grasp_prior: the Gaussian over the grasp at the start of an episode (before vision).
    """

    task: PegInHoleTask
    displacement: Tensor
    process_cov: Tensor
    trigger: Tensor
    class_transition: Tensor
    state_transition: Tensor
    state_row: Tensor
    initial: Tensor
    class_prior: Tensor
    grasp_prior: Gaussian

    # -- the SwitchingModel protocol -------------------------------------------------------

    @property
    def num_modes(self) -> int:
        """``K = 24`` contact classes."""
        return NUM_CONTACT_CLASSES

    @property
    def state_dim(self) -> int:
        """``n = 3``: the peg's pose in the gripper frame."""
        return 3

    @property
    def obs_dim(self) -> int:
        """``m = 3``: the camera's peg pose."""
        return 3

    @property
    def num_actions(self) -> int:
        """``A``, the task's actions."""
        return len(ACTION_NAMES)

    @property
    def dtype(self) -> torch.dtype:
        """float64."""
        return _F64

    @property
    def device(self) -> torch.device:
        """The CPU."""
        return torch.device("cpu")

    @property
    def transition(self) -> Tensor:
        """``(A, K, K)`` class-level transition (the per-particle rows refine it)."""
        return self.class_transition

    def mode_dynamics(self, belief: RBPFBelief, control: Any) -> ModeDynamics:
        """Per-mode dynamics and per-particle transition rows of one step.

        Args:
            belief: the belief before the step, batch ``(B,)``.
            control: a :class:`PegControl` with batch ``(B,)``.
        """
        if not isinstance(control, PegControl):
            raise ValueError(f"control must be a PegControl, got {type(control).__name__}")
        K = NUM_CONTACT_CLASSES
        actions = control.actions
        B = actions.shape[0]
        gripper = control.gripper_after
        H = _vision_matrix(gripper)
        ids = self.particle_state_ids(belief, control.gripper_before)
        rows = self.state_transition[self.state_row[ids], actions[:, None]]  # (B, N, K)
        return ModeDynamics(
            F=torch.eye(3, dtype=_F64).expand(K, 3, 3),
            c=self.displacement[actions],
            Q=self.process_cov[actions],
            H=H.unsqueeze(1).expand(B, K, 3, 3),
            d=gripper.unsqueeze(1).expand(B, K, 3),
            R=self.vision_cov.expand(K, 3, 3),
            transition_rows=rows,
        )

    # -- what the filter and the policies ask ----------------------------------------------

    @property
    def vision_cov(self) -> Tensor:
        """``(3, 3)`` covariance of the camera's peg pose, ``diag(σ²)`` of the task."""
        return torch.diag(_tensor(self.task.config.pose_noise_std, _F64) ** 2)

    def particle_state_ids(self, belief: RBPFBelief, gripper: Tensor) -> Tensor:
        """Manipulation-state ids of the particles: their mean grasp placed in the gripper
        ``gripper (B, 3)`` and their contact class; ``(B, N)`` long."""
        pose = compose(gripper.unsqueeze(1), belief.gaussians.mean)
        return self.task.states.ids(pose, belief.modes)

    def tactile_log_likelihood(self, readings: Tensor) -> Tensor:
        """``(B, K)`` log-likelihood of tactile readings ``(B, S)`` (bool) under each class."""
        sensors = self.task.sensors
        return sensors.log_likelihood(readings, self.trigger.to(sensors.positions.dtype)).to(_F64)

    def most_likely_classes(self, readings: Tensor) -> Tensor:
        """``(B,)`` the class of highest posterior given tactile readings ``(B, S)`` alone,
        under :attr:`class_prior` (what a policy without a filter can read off the sensors)."""
        return (self.tactile_log_likelihood(readings) + torch.log(self.class_prior)).argmax(-1)

    # -- fitting ---------------------------------------------------------------------------

    @classmethod
    def fit(
        cls,
        transitions: PegTransitions,
        graph: ManipulationGraph,
        *,
        task: PegInHoleTask,
        graph_prior: float = 1.0,
        min_samples: int = 5,
    ) -> PegInHoleBeliefModel:
        """Fit the motion and tactile models on recorded steps, the transition on a graph.

        Args:
            transitions: recorded steps (e.g. of Dyna-Q's training episodes).
            graph: the manipulation graph over the task's manipulation states (e.g.
                ``DynaQ.graph``); a state must be a key of ``task.states``.
            task: the task.
            graph_prior: ``β``, the weight of the class-level transition in each state's row.
            min_samples: fewest steps of an ``(action, class)`` pair for its own displacement
                statistics; rarer pairs pool their class over actions, or are "unseen".

        Raises:
            ValueError: an argument is invalid.
        """
        if not isinstance(transitions, PegTransitions) or transitions.num_steps == 0:
            raise ValueError("transitions must be a non-empty PegTransitions")
        if not isinstance(graph, ManipulationGraph) or graph.num_actions != len(ACTION_NAMES):
            raise ValueError(f"graph must be a ManipulationGraph with {len(ACTION_NAMES)} actions")
        if not (isinstance(graph_prior, (int, float)) and graph_prior > 0):
            raise ValueError(f"graph_prior must be > 0, got {graph_prior!r}")
        if not (isinstance(min_samples, int) and min_samples >= 2):
            raise ValueError(f"min_samples must be an int >= 2, got {min_samples!r}")
        displacement, process_cov = _fit_motion(transitions, min_samples)
        trigger = _fit_trigger(transitions)
        source_ids, per_state = _class_counts(graph, task)  # (M,), (M, A, K)
        A, K = len(ACTION_NAMES), NUM_CONTACT_CLASSES
        by_class = torch.zeros(A, K, K, dtype=_F64)
        by_class.index_add_(1, source_ids % K, per_state.transpose(0, 1))
        class_transition = (by_class + 1e-3) / (by_class + 1e-3).sum(-1, keepdim=True)
        prior = class_transition[:, source_ids % K].transpose(0, 1)  # (M, A, K)
        rows = (per_state + graph_prior * prior) / (per_state.sum(-1, keepdim=True) + graph_prior)
        M = source_ids.shape[0]
        state_row = M + torch.arange(task.states.num_states) % K  # the class-level rows
        state_row[source_ids] = torch.arange(M)
        state_transition = torch.cat([rows, class_transition.transpose(0, 1)])
        start = transitions.first
        initial = torch.bincount(transitions.classes[start], minlength=K).to(_F64) + 1e-3
        frequency = torch.bincount(transitions.next_classes, minlength=K).to(_F64) + 1e-3
        grasp0 = transitions.grasp[start] if bool(start.any()) else transitions.grasp
        mean = grasp0.mean(0)
        cov = (
            torch.cov(grasp0.T) if grasp0.shape[0] > 3 else torch.diag(_tensor(_UNSEEN_NOISE, _F64))
        )
        cov = cov + torch.diag(_tensor(_NOISE_FLOOR, _F64))
        return cls(
            task=task,
            displacement=displacement,
            process_cov=process_cov,
            trigger=trigger,
            class_transition=class_transition,
            state_transition=state_transition,
            state_row=state_row,
            initial=initial / initial.sum(),
            class_prior=frequency / frequency.sum(),
            grasp_prior=Gaussian(mean, cov),
        )


def compose(gripper: Tensor, grasp: Tensor) -> Tensor:
    """World poses ``g ⊕ x`` of grasp poses ``x (*B, 3)`` held by grippers ``g (*B, 3)``."""
    cos, sin = torch.cos(gripper[..., 2]), torch.sin(gripper[..., 2])
    u, w, phi = grasp.unbind(-1)
    return torch.stack(
        [
            gripper[..., 0] + cos * u - sin * w,
            gripper[..., 1] + sin * u + cos * w,
            gripper[..., 2] + phi,
        ],
        -1,
    )


def _vision_matrix(gripper: Tensor) -> Tensor:
    """``(B, 3, 3)`` ``H`` with ``H x + g = g ⊕ x`` for grippers ``g (B, 3)``: the rotation by
    the gripper's angle on ``(u, w)``, identity on the angle."""
    H = torch.zeros(gripper.shape[0], 3, 3, dtype=_F64)
    H[:, :2, :2] = rotation_matrix(gripper[:, 2])
    H[:, 2, 2] = 1.0
    return H


def _fit_motion(data: PegTransitions, min_samples: int) -> tuple[Tensor, Tensor]:
    """Mean ``(A, K, 3)`` and covariance ``(A, K, 3, 3)`` of the grasp displacement."""
    A, K = len(ACTION_NAMES), NUM_CONTACT_CLASSES
    delta = data.next_grasp - data.grasp
    delta[:, 2] = wrap_angle(delta[:, 2])
    floor = torch.diag(_tensor(_NOISE_FLOOR, _F64))
    mean = torch.zeros(A, K, 3, dtype=_F64)
    cov = torch.diag(_tensor(_UNSEEN_NOISE, _F64)).expand(A, K, 3, 3).clone()
    for k in range(K):
        in_class = data.next_classes == k
        if int(in_class.sum()) >= min_samples:
            pooled = delta[in_class]
            mean[:, k] = pooled.mean(0)
            cov[:, k] = torch.cov(pooled.T) + floor
        for a in range(A):
            pair = in_class & (data.actions == a)
            if int(pair.sum()) >= min_samples:
                mean[a, k] = delta[pair].mean(0)
                cov[a, k] = torch.cov(delta[pair].T) + floor
    return mean, cov


def _fit_trigger(data: PegTransitions) -> Tensor:
    """``(K, S)`` Laplace-smoothed frequency of each sensor being touched in each class."""
    K = NUM_CONTACT_CLASSES
    S = data.next_triggered.shape[1]
    hits = torch.zeros(K, S, dtype=_F64)
    hits.index_add_(0, data.next_classes, data.next_triggered.to(_F64))
    total = torch.bincount(data.next_classes, minlength=K).to(_F64)
    return (hits + 1.0) / (total[:, None] + 2.0)


def _class_counts(graph: ManipulationGraph, task: PegInHoleTask) -> tuple[Tensor, Tensor]:
    """Source state ids ``(M,)`` and their counts by action and next class ``(M, A, K)``."""
    K = NUM_CONTACT_CLASSES
    states = task.states
    index, counts = graph.count_entries()
    graph_ids = torch.tensor([states.index(s) for s in graph.states], dtype=torch.long)
    source, action, target = index
    sources, rows = torch.unique(graph_ids[source], return_inverse=True)
    per_state = torch.zeros(sources.shape[0], len(ACTION_NAMES), K, dtype=_F64)
    per_state.index_put_((rows, action, graph_ids[target] % K), counts.to(_F64), accumulate=True)
    return sources, per_state


@dataclass(frozen=True, eq=False)
class PegBelief:
    """The filter's belief over a batch of ``B`` episodes.

    Attributes:
        rbpf: the particles (contact class + Gaussian over the grasp), batch ``(B,)``.
        gripper: ``(B, 3)`` the gripper poses (world) the belief refers to.
    """

    rbpf: RBPFBelief
    gripper: Tensor


class PegInHoleFilter:
    """The RBPF of :class:`PegInHoleBeliefModel` over a batch of episodes, on observations.

    Observations are those of ``PegInHole2D(observation="noisy")`` (or the vector version):
    mappings with ``peg_pose (B, 3)``, ``gripper_pose (B, 3)`` and ``tactile (B, S)``.

    Args:
        model: the fitted model.
        num_particles: particles per episode.
        proposal: ``"bootstrap"`` or ``"all_modes"`` (see :class:`RBPF`).
        resampling: the resampling scheme.
        ess_threshold: resample when the ESS falls below this fraction of ``num_particles``.
    """

    def __init__(
        self,
        model: PegInHoleBeliefModel,
        *,
        num_particles: int = 64,
        proposal: Proposal = "bootstrap",
        resampling: ResamplingMethod = "systematic",
        ess_threshold: float = 0.5,
    ) -> None:
        if not isinstance(model, PegInHoleBeliefModel):
            raise ValueError(f"model must be a PegInHoleBeliefModel, got {type(model).__name__}")
        self.model = model
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
        prior = self.model.grasp_prior
        B = y.shape[0]
        start = Gaussian(prior.mean.expand(B, 3), prior.cov.expand(B, 3, 3))
        H, R = _vision_matrix(gripper), self.model.vision_cov
        posterior, _ = kf_update(start, y, H=H, d=gripper, R=R)
        return PegBelief(self.rbpf.init(posterior), gripper)

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
        actions = _tensor(actions, torch.long)
        control = PegControl(gripper_before=belief.gripper, gripper_after=gripper, actions=actions)
        rbpf = self.rbpf.step(
            belief.rbpf,
            y,
            action=actions,
            extra_log_likelihood=self.model.tactile_log_likelihood(readings),
            control=control,
            generator=generator,
        )
        return PegBelief(rbpf, gripper)

    def restart(
        self, belief: PegBelief, where: Tensor | NDArray[np.bool_], observation: Mapping[str, Any]
    ) -> PegBelief:
        """Restart the entries ``where (B,)`` (new episodes) from ``observation``."""
        where = _tensor(where, torch.bool)
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
        return PegBelief(replace(old, **merged), pick(fresh.gripper, belief.gripper))

    def particle_poses(self, belief: PegBelief) -> Tensor:
        """``(B, N, 3)`` each particle's mean peg pose in the world frame."""
        return compose(belief.gripper.unsqueeze(1), belief.rbpf.gaussians.mean)

    def particle_states(self, belief: PegBelief) -> tuple[Tensor, Tensor]:
        """Each particle's manipulation-state id ``(B, N)`` and weight ``(B, N)``."""
        ids = self.model.particle_state_ids(belief.rbpf, belief.gripper)
        return ids, belief.rbpf.log_weights.exp()

    def pose_mean(self, belief: PegBelief) -> Tensor:
        """``(B, 3)`` the weighted mean of the peg's world pose."""
        weights = belief.rbpf.log_weights.exp().unsqueeze(-1)
        return (weights * self.particle_poses(belief)).sum(1)

    def _unpack(self, observation: Mapping[str, Any]) -> tuple[Tensor, Tensor, Tensor]:
        try:
            y = _tensor(observation["peg_pose"], _F64)
            gripper = _tensor(observation["gripper_pose"], _F64)
            readings = _tensor(observation["tactile"], torch.bool)
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
        if not bool(torch.isfinite(y).all() and torch.isfinite(gripper).all()):
            raise ValueError("observation: peg_pose and gripper_pose must be finite")
        return y, gripper, readings


__all__ = [
    "PegBelief",
    "PegControl",
    "PegInHoleBeliefModel",
    "PegInHoleFilter",
    "PegTransitions",
    "compose",
]
