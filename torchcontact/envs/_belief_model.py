"""The peg-in-hole belief model: a switching linear-Gaussian model fitted on recorded steps.

The model the RBPF of :class:`~torchcontact.envs.PegInHoleFilter` runs on. Its state is the
peg's pose *in the gripper frame* (the gripper's pose is known, the fingers' servo sets it), so
that the measurement of a camera that sees the peg in the world is linear, and the peg's motion
in the grasp, given its contact class, is a constant displacement plus noise: it stays put
while held without other contact, it slides up the pads when pushed onto a surface, and so on.
Each particle carries a contact class (the RBPF's mode) and a Gaussian over that pose; the mode
transition of a particle comes from the manipulation graph at the particle's own manipulation
state (its pose cell and contact class).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from torchcontact.envs._states import NUM_CONTACT_CLASSES
from torchcontact.envs._task import ACTION_NAMES, PegInHoleTask
from torchcontact.envs._transitions import PegTransitions, as_tensor
from torchcontact.filters import Gaussian, ModeDynamics, RBPFBelief, kf_update
from torchcontact.geometry import rotation_matrix, wrap_angle
from torchcontact.states import ManipulationGraph

_F64 = torch.float64
#: Floor of the per-step process noise of the peg in the grasp: (0.2 mm, 0.2 mm, 3 mrad)².
_NOISE_FLOOR = (2e-4**2, 2e-4**2, 3e-3**2)
#: Process noise of a (action, class) pair never seen in the data: (5 mm, 5 mm, 0.05 rad)².
_UNSEEN_NOISE = (5e-3**2, 5e-3**2, 0.05**2)


@dataclass(frozen=True, kw_only=True)
class PegControl:
    """The known inputs of one filter step.

    Attributes:
        state_ids: ``(B, N)`` long manipulation-state ids of the particles before the step
            (:meth:`PegInHoleBeliefModel.particle_state_ids` of the belief and the gripper
            poses before the step; :class:`~torchcontact.envs.PegInHoleFilter` computes them
            once per step and keeps them in its belief).
        gripper_after: ``(B, 3)`` gripper poses (world) after the step.
        actions: ``(B,)`` long actions of the step.
        gripper_before: ``(B, 3)`` gripper poses (world) before the step (the fingers' motion
            of :class:`~torchcontact.envs.PegPhysicsModel`; the fitted model needs none).
    """

    state_ids: Tensor
    gripper_after: Tensor
    actions: Tensor
    gripper_before: Tensor | None = None


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
            control: a :class:`PegControl` with batch ``(B,)``; its ``state_ids`` (the
                particles' manipulation states before the step) select the transition rows.
        """
        if not isinstance(control, PegControl):
            raise ValueError(f"control must be a PegControl, got {type(control).__name__}")
        K = NUM_CONTACT_CLASSES
        actions = control.actions
        B = actions.shape[0]
        gripper = control.gripper_after
        H = _vision_matrix(gripper)
        rows = class_rows(self.state_transition, self.state_row, control.state_ids, actions)
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
        return torch.diag(as_tensor(self.task.config.pose_noise_std, _F64) ** 2)

    def grasp_posterior(self, y: Tensor, gripper: Tensor) -> Gaussian:
        """The belief over the grasp at the start of episodes: :attr:`grasp_prior` updated with
        the first camera poses ``y (B, 3)`` of the peg held by grippers ``gripper (B, 3)``;
        batch ``(B,)``."""
        prior = self.grasp_prior
        B = y.shape[0]
        start = Gaussian(prior.mean.expand(B, 3), prior.cov.expand(B, 3, 3))
        posterior, _ = kf_update(start, y, H=_vision_matrix(gripper), d=gripper, R=self.vision_cov)
        return posterior

    def initial_gaussian(self, y: Tensor, gripper: Tensor) -> Gaussian:
        """The filter's belief at the start of episodes, :meth:`grasp_posterior`."""
        return self.grasp_posterior(y, gripper)

    def particle_poses(self, belief: RBPFBelief, gripper: Tensor) -> Tensor:
        """``(B, N, 3)`` each particle's mean grasp placed in the gripper ``gripper (B, 3)``
        (world frame)."""
        return compose(gripper.unsqueeze(1), belief.gaussians.mean)

    def particle_classes(self, belief: RBPFBelief) -> Tensor:
        """``(B, N)`` long contact class of each particle: its mode."""
        return belief.modes

    def particle_state_ids(self, belief: RBPFBelief, gripper: Tensor) -> Tensor:
        """Manipulation-state ids of the particles: their mean grasp placed in the gripper
        ``gripper (B, 3)`` and their contact class; ``(B, N)`` long."""
        return self.task.states.ids(self.particle_poses(belief, gripper), belief.modes)

    def tactile_evidence(self, readings: Tensor, belief: RBPFBelief, control: PegControl) -> Tensor:
        """``(B, K)`` :meth:`tactile_log_likelihood` of the readings ``(B, S)`` after a step
        (the belief and control are not needed: the classes' trigger rates are fitted)."""
        return self.tactile_log_likelihood(readings)

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
        if not (isinstance(min_samples, int) and min_samples >= 2):
            raise ValueError(f"min_samples must be an int >= 2, got {min_samples!r}")
        displacement, process_cov = _fit_motion(transitions, min_samples)
        trigger = _fit_trigger(transitions)
        graph_rows = GraphClassTransition.fit(graph, task=task, graph_prior=graph_prior)
        K = NUM_CONTACT_CLASSES
        start = transitions.first
        initial = torch.bincount(transitions.classes[start], minlength=K).to(_F64) + 1e-3
        frequency = torch.bincount(transitions.next_classes, minlength=K).to(_F64) + 1e-3
        grasp0 = transitions.grasp[start] if bool(start.any()) else transitions.grasp
        mean = grasp0.mean(0)
        unseen = torch.diag(as_tensor(_UNSEEN_NOISE, _F64))
        cov = torch.cov(grasp0.T) if grasp0.shape[0] > 3 else unseen
        cov = cov + torch.diag(as_tensor(_NOISE_FLOOR, _F64))
        return cls(
            task=task,
            displacement=displacement,
            process_cov=process_cov,
            trigger=trigger,
            class_transition=graph_rows.class_transition,
            state_transition=graph_rows.state_transition,
            state_row=graph_rows.state_row,
            initial=initial / initial.sum(),
            class_prior=frequency / frequency.sum(),
            grasp_prior=Gaussian(mean, cov),
        )


@dataclass(frozen=True, eq=False, kw_only=True)
class GraphClassTransition:
    r"""The manipulation graph as a transition between contact classes, per manipulation state.

    For a particle in manipulation state :math:`m = (\mathrm{cell}, k)` taking action
    :math:`a`, the next class's distribution is the graph's counts :math:`N(m, a, k′)`
    (aggregated over the next states' cells) shrunk toward the class-level transition
    :math:`p_c(k′ \mid k, a)` (the counts of every state of class :math:`k`, plus
    :math:`10^{-3}`): :math:`p(k′ \mid m, a) = (N(m, a, k′) + β\, p_c(k′ \mid k, a)) /
    (N(m, a) + β)` with :math:`β` = ``graph_prior``. States the graph never left get the
    class-level row. Both belief models of the peg task
    (:class:`PegInHoleBeliefModel`, :class:`~torchcontact.envs.PegPhysicsModel`) take their
    mode transition from it.

    Attributes:
        class_transition: ``(A, K, K)`` class-level transition ``p_c(k′ | k, a)``.
        state_transition: ``(M + K, A, K)`` next-class distributions: one row per manipulation
            state the graph saw as a source, then the class-level row of each class.
        state_row: ``(num_states,)`` long row of each manipulation state id in
            ``state_transition``.
    """

    class_transition: Tensor
    state_transition: Tensor
    state_row: Tensor

    @classmethod
    def fit(
        cls, graph: ManipulationGraph, *, task: PegInHoleTask, graph_prior: float = 1.0
    ) -> GraphClassTransition:
        """The rows of a graph over the task's manipulation states.

        Args:
            graph: the manipulation graph (e.g. ``DynaQ.graph``); its states must be keys of
                ``task.states``.
            task: the task.
            graph_prior: ``β > 0``.

        Raises:
            ValueError: an argument is invalid.
        """
        if not isinstance(graph, ManipulationGraph) or graph.num_actions != len(ACTION_NAMES):
            raise ValueError(f"graph must be a ManipulationGraph with {len(ACTION_NAMES)} actions")
        if not (isinstance(graph_prior, (int, float)) and graph_prior > 0):
            raise ValueError(f"graph_prior must be > 0, got {graph_prior!r}")
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
        return cls(
            class_transition=class_transition,
            state_transition=torch.cat([rows, class_transition.transpose(0, 1)]),
            state_row=state_row,
        )


def class_rows(state_transition: Tensor, state_row: Tensor, ids: Tensor, actions: Tensor) -> Tensor:
    """``(B, N, K)`` next-class distributions of particles in states ``ids (B, N)`` taking
    actions ``(B,)`` (rows of :class:`GraphClassTransition`)."""
    return state_transition[state_row[ids], actions[:, None]]


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
    floor = torch.diag(as_tensor(_NOISE_FLOOR, _F64))
    mean = torch.zeros(A, K, 3, dtype=_F64)
    cov = torch.diag(as_tensor(_UNSEEN_NOISE, _F64)).expand(A, K, 3, 3).clone()
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


__all__ = ["GraphClassTransition", "PegControl", "PegInHoleBeliefModel", "class_rows", "compose"]
