"""The peg-in-hole belief model on the contact physics: the peg between the fingers and against
the hole, stepped per contact mode by the one engine.

The RBPF's state is the peg's world pose and twist; a mode is a vector of per-slot contact
modes of the peg's slots (table, blocks, fingers) and its dynamics are
:class:`~torchcontact.filters.PlanarContactModel`'s mode-decoupled step, linearized at the
belief's mean. The fingers are kinematic in the filter's scene: they move with the gripper,
whose pose before and after the step is known, and their pads are placed on the estimated
peg. The mode transition is the learned manipulation graph's transition between contact
classes (:class:`~torchcontact.envs.GraphClassTransition`), spread over the modes of each class
in proportion to how often they were seen.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor

from torchcontact.envs._belief_model import (
    GraphClassTransition,
    PegControl,
    class_rows,
    compose,
)
from torchcontact.envs._states import GRASP_SLIDE, HELD_FREE, NUM_CONTACT_CLASSES
from torchcontact.envs._task import ACTION_NAMES, PegInHoleTask
from torchcontact.filters import (
    Gaussian,
    KinematicControl,
    ModeDynamics,
    PlanarContactModel,
    RBPFBelief,
    collect_modes,
    kf_update,
)
from torchcontact.geometry import rotation_matrix, wrap_angle
from torchcontact.sim import Body, Scene
from torchcontact.states import ManipulationGraph

_F64 = torch.float64
#: Default process noise std of one filter step: pose (m, m, rad) and twist (m/s, m/s, rad/s).
POSE_NOISE = (3e-4, 3e-4, 3e-3)
TWIST_NOISE = (0.02, 0.02, 0.3)
#: Std of the peg's twist at the start of an episode (the grasp has settled): m/s, m/s, rad/s.
_START_TWIST = (0.01, 0.01, 0.1)
_FINGERS = ("finger_left", "finger_right")


def filter_scene(task: PegInHoleTask) -> Scene:
    """The task's scene as the filter sees it: the fingers kinematic, one step per action.

    Same bodies, shapes, friction, gravity and margin as ``task.scene``; the fingers are
    kinematic (their twist is the gripper's, known), and the time step is that of one
    environment step, ``substeps · h``.
    """
    scene = task.scene
    bodies = tuple(
        Body(body.name, body.shape, kind="kinematic") if body.name in _FINGERS else body
        for body in scene.bodies
    )
    return replace(scene, bodies=bodies, h=task.config.substeps * task.config.h)


def slot_map(scene: Scene, filtered: Scene) -> Tensor:
    """``(S_f,)`` long: the slot of ``scene`` that is each slot of ``filtered``.

    Slot groups are matched by their (receiver, other) body names; ``filtered`` must have a
    subset of ``scene``'s groups (e.g. :func:`filter_scene` of a task's scene).

    Raises:
        ValueError: a group of ``filtered`` is not one of ``scene``'s.
    """

    def names(s: Scene) -> dict[tuple[str, str], tuple[int, int]]:
        return {
            (s.bodies[g.receiver].name, s.bodies[g.other].name): (g.start, g.count)
            for g in s.slot_groups
        }

    source = names(scene)
    index: list[int] = []
    for pair, (_, count) in names(filtered).items():
        if pair not in source or source[pair][1] != count:
            raise ValueError(f"filtered: slot group {pair} is not one of the scene's")
        start = source[pair][0]
        index.extend(range(start, start + count))
    return torch.tensor(index, dtype=torch.long)


def grasp_of(gripper: Tensor, pose: Tensor) -> Tensor:
    """``(*B, 3)`` grasp poses ``g⁻¹ ⊕ q`` of world poses ``pose`` held by grippers ``gripper``
    (the inverse of :func:`~torchcontact.envs.compose`; angle not wrapped)."""
    R = rotation_matrix(gripper[..., 2])
    offset = (pose[..., :2] - gripper[..., :2]).unsqueeze(-1)
    uw = (R.transpose(-1, -2) @ offset).squeeze(-1)
    return torch.cat([uw, (pose[..., 2] - gripper[..., 2]).unsqueeze(-1)], -1)


@dataclass(frozen=True, eq=False, kw_only=True)
class PegPhysicsModel:
    r"""Switching model of the peg on the contact physics, for the :class:`RBPF`.

    State :math:`x = (x, y, θ, v_x, v_y, ω)`: the peg's world pose and twist. Mode :math:`k`:
    a row of ``contact.modes``, the contact mode of every slot of the peg in
    :func:`filter_scene` (against the table, the blocks and the two fingers), with its
    contact class ``mode_class[k]``. For the gripper moving from :math:`g` to :math:`g′`
    (the action, clamped to the workspace; known):

    * dynamics: :math:`x′ = f_k(x, u) + w`, :math:`w \sim N(0, Q)`, the mode-decoupled step of
      :class:`~torchcontact.filters.PlanarContactModel` (one engine: the scene's slot
      geometry, contact problem and ``solve_mode``) over one environment step, with the
      fingers kinematic: each pad is placed on the side of the peg at the belief's mean grasp
      :math:`g^{-1} \oplus \bar x` (where its corners touch, like the environment's reset) and
      the fingers move rigidly with the gripper at the twist :math:`(g′ - g) / (\mathrm{substeps}
      \cdot h)`; linearized per mode at the belief's mean (the contact model's penalty on
      modes that contradict their own step is off by default: at the camera noise of the
      task the mean is too far from the particles for that test, and it cost the true class
      most of its probability);
    * vision: :math:`y = (x, y, θ) + v`, :math:`v \sim N(0, \mathrm{diag}(σ^2))`, the task's
      camera;
    * tactile: the sensors that mode :math:`k`'s contacts trigger at the mean pose carried
      rigidly by the gripper to the end of the step
      (:meth:`~torchcontact.filters.PlanarContactModel.tactile_log_likelihood`);
    * mode transition of particle :math:`i` in manipulation state :math:`m_i` (its mean pose's
      cell and its mode's class): :math:`p(k \mid m_i, a) \propto p(c_k \mid m_i, a)\,
      π_k`, the graph's class row (:class:`~torchcontact.envs.GraphClassTransition`) times
      ``within_class``, the share :math:`π_k` of mode :math:`k` among the recorded steps of
      its class.

    Build it with :meth:`fit`.

    Attributes:
        task: the task (geometry, sensors, state discretization).
        contact: the contact model over :func:`filter_scene` (mode table, noise, class-level
            transition ``(A, K, K)``, initial distribution).
        mode_class: ``(K,)`` long contact class of each mode.
        within_class: ``(K,)`` share of each mode among the modes of its class (the shares of
            one class sum to 1).
        graph: the graph's class transition by manipulation state.
        grasp_prior: ``(3,)`` Gaussian over the peg's pose in the gripper frame at the start
            of an episode (before vision).
        twist_prior: ``(3, 3)`` covariance of the peg's twist at the start (mean zero).
    """

    task: PegInHoleTask
    contact: PlanarContactModel
    mode_class: Tensor
    within_class: Tensor
    graph: GraphClassTransition
    grasp_prior: Gaussian
    twist_prior: Tensor

    def __post_init__(self) -> None:
        K = self.contact.num_modes
        if not isinstance(self.mode_class, Tensor) or tuple(self.mode_class.shape) != (K,):
            raise ValueError(f"mode_class must be a ({K},) long tensor")
        if bool(((self.mode_class < 0) | (self.mode_class >= NUM_CONTACT_CLASSES)).any()):
            raise ValueError(f"mode_class: values must lie in [0, {NUM_CONTACT_CLASSES})")
        share = self.within_class
        if not isinstance(share, Tensor) or tuple(share.shape) != (K,) or bool((share < 0).any()):
            raise ValueError(f"within_class must be a non-negative ({K},) tensor")
        total = torch.zeros(NUM_CONTACT_CLASSES, dtype=share.dtype).index_add_(
            0, self.mode_class, share
        )
        present = torch.zeros(NUM_CONTACT_CLASSES, dtype=torch.bool)
        present[self.mode_class] = True
        if bool(((total[present] - 1).abs() > 1e-9).any()):
            raise ValueError("within_class: the shares of each class must sum to 1")

    # -- the SwitchingModel protocol -------------------------------------------------------

    @property
    def num_modes(self) -> int:
        """``K``, the rows of the mode table."""
        return self.contact.num_modes

    @property
    def state_dim(self) -> int:
        """``n = 6``: the peg's pose and twist."""
        return self.contact.state_dim

    @property
    def obs_dim(self) -> int:
        """``m = 3``: the camera's peg pose."""
        return self.contact.obs_dim

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
        """``(A, K, K)`` class-level transition spread over the modes (the per-particle rows
        refine it)."""
        return self.contact.transition

    @property
    def initial(self) -> Tensor:
        """``(K,)`` mode distribution at the start of an episode."""
        return self.contact.initial

    def mode_dynamics(self, belief: RBPFBelief, control: Any) -> ModeDynamics:
        """Every mode's step linearized at the belief's mean, and per-particle mode rows.

        Args:
            belief: the belief before the step, batch ``(B,)``.
            control: a :class:`PegControl` with batch ``(B,)`` and ``gripper_before``.
        """
        if not isinstance(control, PegControl) or control.gripper_before is None:
            raise ValueError("control must be a PegControl with gripper_before")
        fingers = self.finger_control(
            control.gripper_before, control.gripper_after, belief.mean()[..., :3]
        )
        dynamics = _rule_out_unstable(self.contact.mode_dynamics(belief, fingers))
        rows = class_rows(
            self.graph.state_transition, self.graph.state_row, control.state_ids, control.actions
        )
        rows = rows[..., self.mode_class] * self.within_class
        return replace(dynamics, transition_rows=rows / rows.sum(-1, keepdim=True))

    # -- the fingers -----------------------------------------------------------------------

    def finger_poses(self, gripper: Tensor, peg: Tensor) -> Tensor:
        """``(B, 2, 3)`` world poses of the fingers of grippers ``gripper (B, 3)`` with their
        pads on the sides of pegs at world poses ``peg (B, 3)``.

        Each pad faces the peg's side at the side's outermost point over the pad's extent
        (the pads' corners touch), as :meth:`PegInHoleTask.initial_state` places them.
        """
        c = self.task.config
        grasp = grasp_of(gripper, peg)
        cx, cy, tilt = grasp.unbind(-1)
        half_w, half_pad = c.peg_width / 2, c.pad_length / 2
        cos, sin = torch.cos(tilt), torch.sin(tilt)
        pads = []
        for side in (-1.0, 1.0):
            xs = []
            for y in (-half_pad, half_pad):
                t = (y - cy - side * half_w * sin) / cos
                xs.append(cx + side * half_w * cos - t * sin)
            extreme = torch.maximum(*xs) if side > 0 else torch.minimum(*xs)
            pads.append(extreme + side * self.task.pad_offset)
        zero = torch.zeros_like(cx)
        local = torch.stack([torch.stack([x, zero, zero], -1) for x in pads], -2)
        return compose(gripper.unsqueeze(-2), local)

    def finger_control(self, before: Tensor, after: Tensor, peg: Tensor) -> KinematicControl:
        """The fingers' poses at the start of the step and their twist over it.

        Args:
            before: ``(B, 3)`` gripper poses before the step.
            after: ``(B, 3)`` gripper poses after it.
            peg: ``(B, 3)`` the peg's (estimated) world pose before it.
        """
        q = self.finger_poses(before, peg)
        h = self.contact.scene.h
        twist = torch.cat(
            [after[:, :2] - before[:, :2], wrap_angle(after[:, 2:] - before[:, 2:])], -1
        )
        twist = twist / h
        arm = q[..., :2] - before[:, None, :2]
        omega = twist[:, None, 2]
        linear = twist[:, None, :2] + omega[..., None] * torch.stack(
            [-arm[..., 1], arm[..., 0]], -1
        )
        v = torch.cat([linear, omega[..., None].expand(-1, 2, 1)], -1)
        return KinematicControl(q=q, v=v)

    # -- what the filter and the policies ask ----------------------------------------------

    @property
    def vision_cov(self) -> Tensor:
        """``(3, 3)`` covariance of the camera's peg pose."""
        return self.contact.R

    def initial_gaussian(self, y: Tensor, gripper: Tensor) -> Gaussian:
        """The belief over pose and twist at the start of episodes: the grasp prior carried by
        grippers ``gripper (B, 3)`` to the world, zero twist, updated with the first camera
        poses ``y (B, 3)``; batch ``(B,)``."""
        B = y.shape[0]
        prior = self.grasp_prior
        mean = torch.cat([compose(gripper, prior.mean.expand(B, 3)), y.new_zeros(B, 3)], -1)
        J = torch.zeros(B, 3, 3, dtype=_F64)
        J[:, :2, :2] = rotation_matrix(gripper[:, 2])
        J[:, 2, 2] = 1.0
        cov = torch.zeros(B, 6, 6, dtype=_F64)
        cov[:, :3, :3] = J @ prior.cov @ J.transpose(-1, -2)
        cov[:, 3:, 3:] = self.twist_prior
        H = torch.eye(3, 6, dtype=_F64).expand(B, 3, 6)
        posterior, _ = kf_update(
            Gaussian(mean, cov), y, H=H, d=y.new_zeros(B, 3), R=self.vision_cov
        )
        return posterior

    def particle_poses(self, belief: RBPFBelief, gripper: Tensor) -> Tensor:
        """``(B, N, 3)`` each particle's mean world pose (``gripper`` is not needed)."""
        return belief.gaussians.mean[..., :3]

    def particle_classes(self, belief: RBPFBelief) -> Tensor:
        """``(B, N)`` long contact class of each particle: its mode's class."""
        return self.mode_class[belief.modes]

    def particle_state_ids(self, belief: RBPFBelief, gripper: Tensor) -> Tensor:
        """Manipulation-state ids of the particles: their mean pose and their mode's class;
        ``(B, N)`` long."""
        return self.task.states.ids(belief.gaussians.mean[..., :3], self.particle_classes(belief))

    def tactile_evidence(self, readings: Tensor, belief: RBPFBelief, control: PegControl) -> Tensor:
        """``(B, K)`` log-likelihood of the tactile readings ``(B, S)`` after the step under
        each mode: its contacts placed at the mean pose carried rigidly by the gripper to the
        end of the step, with the fingers there."""
        if control.gripper_before is None:
            raise ValueError("control must have gripper_before")
        grasp = grasp_of(control.gripper_before, belief.mean()[..., :3])
        pose = compose(control.gripper_after, grasp)
        fingers = self.finger_control(control.gripper_after, control.gripper_after, pose)
        return self.contact.tactile_log_likelihood(
            self.task.sensors, readings, pose=pose, control=fingers
        )

    # -- building --------------------------------------------------------------------------

    @classmethod
    def fit(
        cls,
        slot_modes: Tensor,
        classes: Tensor,
        graph: ManipulationGraph,
        *,
        task: PegInHoleTask,
        graph_prior: float = 1.0,
        max_modes: int = 32,
        pose_noise: tuple[float, float, float] = POSE_NOISE,
        twist_noise: tuple[float, float, float] = TWIST_NOISE,
        inconsistency_penalty: float = 0.0,
        **options: Any,
    ) -> PegPhysicsModel:
        """The model of the modes seen in simulated steps, with the graph's class transition.

        A mode is a pair of a vector of the peg's per-slot modes (``slot_modes`` mapped to
        :func:`filter_scene`'s slots by :func:`slot_map`) and the contact class it was seen
        with; the table holds the ``max_modes`` most frequent pairs plus the most frequent
        one of every class none of those has. The kinematic pads of the filter's scene cannot
        squeeze the peg, so they hold it only while they stick: in steps where the grasp
        slips and nothing else touches the peg (a small slip in the environment, held by the
        grip's friction) the pads' sliding modes are taken as sticking.

        Args:
            slot_modes: ``(T, S)`` long per-slot modes of ``task.scene`` (e.g.
                :attr:`~torchcontact.experiments.RoundResult.slot_modes`).
            classes: ``(T,)`` long contact class of each step (after it).
            graph: the manipulation graph (e.g. ``DynaQ.graph``).
            task: the task (its ``pose_noise_std`` is the camera's).
            graph_prior: see :class:`~torchcontact.envs.GraphClassTransition`.
            max_modes: modes kept by frequency, ``>= 1``.
            pose_noise: process noise std of the pose per step (m, m, rad).
            twist_noise: process noise std of the twist per step (m/s, m/s, rad/s).
            inconsistency_penalty: the contact model's log-weight penalty of modes
                inconsistent at the belief's mean (``0``: off).
            **options: further fields of the :class:`~torchcontact.filters.PlanarContactModel`
                (``inconsistency_penalty``, ...).

        Raises:
            ValueError: an argument is invalid.
        """
        if not isinstance(task, PegInHoleTask):
            raise ValueError(f"task must be a PegInHoleTask, got {type(task).__name__}")
        S = task.scene.num_slots
        if not isinstance(slot_modes, Tensor) or slot_modes.ndim != 2 or slot_modes.shape[1] != S:
            raise ValueError(f"slot_modes must be a (T, {S}) long tensor")
        T = slot_modes.shape[0]
        if T == 0 or not isinstance(classes, Tensor) or tuple(classes.shape) != (T,):
            raise ValueError(f"classes must be a ({T},) long tensor and T >= 1")
        if not (isinstance(max_modes, int) and max_modes >= 1):
            raise ValueError(f"max_modes must be an int >= 1, got {max_modes!r}")
        for name, value in (("pose_noise", pose_noise), ("twist_noise", twist_noise)):
            if len(value) != 3 or not all(math.isfinite(v) and v > 0 for v in value):
                raise ValueError(f"{name} must be three finite numbers > 0, got {value!r}")
        graph_rows = GraphClassTransition.fit(graph, task=task, graph_prior=graph_prior)
        scene = filter_scene(task)
        modes = slot_modes[:, slot_map(task.scene, scene)]
        # Kinematic pads cannot hold a peg that slides between them (the squeeze of the grip
        # is not part of their contact problem): a slipping grasp without other contact is
        # stepped as a held one, and keeps its class.
        pads = _finger_slots(scene)
        free_slip = (classes % 8 == 0) & (classes // 8 == GRASP_SLIDE)
        slipping = free_slip[:, None] & pads & (modes >= 2)
        modes = torch.where(slipping, 1, modes)
        # A mode is a (slot-mode vector, class) pair.
        rows, _, counts = collect_modes(torch.cat([modes, classes[:, None]], -1))
        keep = torch.zeros(len(rows), dtype=torch.bool)
        keep[:max_modes] = True
        C = NUM_CONTACT_CLASSES
        for c in range(C):
            of_class = rows[:, -1] == c
            if bool(of_class.any()) and not bool((of_class & keep).any()):
                keep[int(torch.nonzero(of_class)[0])] = True  # rows are by frequency
        table, mode_class = rows[keep, :-1], rows[keep, -1]
        count = counts[keep].to(_F64)
        class_total = torch.zeros(C, dtype=_F64).index_add_(0, mode_class, count)
        within = count / class_total[mode_class]
        transition = graph_rows.class_transition[:, mode_class][:, :, mode_class] * within
        transition = transition / transition.sum(-1, keepdim=True)
        held = mode_class == HELD_FREE
        initial = count * held if bool(held.any()) else count
        std = torch.tensor([*pose_noise, *twist_noise], dtype=_F64)
        contact = PlanarContactModel(
            scene=scene,
            modes=table,
            Q=torch.diag(std**2),
            R=torch.diag(torch.tensor(task.config.pose_noise_std, dtype=_F64) ** 2),
            transition=transition,
            initial=initial / initial.sum(),
            inconsistency_penalty=inconsistency_penalty,
            **options,
        )
        return cls(
            task=task,
            contact=contact,
            mode_class=mode_class,
            within_class=within,
            graph=graph_rows,
            grasp_prior=grasp_prior(task),
            twist_prior=torch.diag(torch.tensor(_START_TWIST, dtype=_F64) ** 2),
        )


#: Largest entry of a mode's step Jacobian that the filter accepts (a contradictory mode's
#: regularized solve can amplify round-off without bound).
_MAX_JACOBIAN = 1e4


def _rule_out_unstable(dynamics: ModeDynamics) -> ModeDynamics:
    """``dynamics`` with every mode whose linearization is not finite or has an entry above
    :data:`_MAX_JACOBIAN` ruled out (log-weight ``-inf``, identity dynamics in its place)."""
    F, c = dynamics.F, dynamics.c
    finite = torch.isfinite(F).all(-1).all(-1) & torch.isfinite(c).all(-1)
    bad = ~finite | (torch.nan_to_num(F).abs().amax((-2, -1)) > _MAX_JACOBIAN)
    if not bool(bad.any()):
        return dynamics
    eye = torch.eye(F.shape[-1], dtype=F.dtype).expand_as(F)
    weight = dynamics.mode_log_weight
    weight = torch.zeros_like(c[..., 0]) if weight is None else weight.expand_as(c[..., 0])
    return replace(
        dynamics,
        F=torch.where(bad[..., None, None], eye, F),
        c=torch.where(bad[..., None], 0.0, c),
        mode_log_weight=torch.where(bad, -math.inf, weight),
    )


def _finger_slots(scene: Scene) -> Tensor:
    """``(S,)`` bool: the slot is between the peg and a finger."""
    pads = torch.zeros(scene.num_slots, dtype=torch.bool)
    for group in scene.slot_groups:
        names = {scene.bodies[group.receiver].name, scene.bodies[group.other].name}
        if names & set(_FINGERS):
            pads[group.start : group.start + group.count] = True
    return pads


def grasp_prior(task: PegInHoleTask) -> Gaussian:
    r"""The moments of the peg's pose in the gripper frame at reset, from the task's ranges.

    Reset draws the offset :math:`o` from the pads down to the peg's centre and the peg's tilt
    :math:`τ` in the grasp uniformly (``grasp_offset``, ``grasp_angle``) and places the centre
    at :math:`(o \sin τ, -o \cos τ)` with angle :math:`τ`. To first order in :math:`τ`:
    mean :math:`(\bar o\, \bar τ, -\bar o, \bar τ)`, variances :math:`(E[o^2] E[τ^2] - \bar o^2
    \bar τ^2, \mathrm{Var}\,o, \mathrm{Var}\,τ)`, with the covariance :math:`\bar o\,
    \mathrm{Var}\,τ` of :math:`u` and :math:`τ`; plus a floor of (0.5 mm, 0.5 mm, 5 mrad)² for
    the settling of the grasp.
    """
    (o0, o1), (t0, t1) = task.config.grasp_offset, task.config.grasp_angle
    o, t = (o0 + o1) / 2, (t0 + t1) / 2
    var_o, var_t = (o1 - o0) ** 2 / 12, (t1 - t0) ** 2 / 12
    var_u = (var_o + o**2) * (var_t + t**2) - (o * t) ** 2
    cov = torch.tensor(
        [[var_u, 0.0, o * var_t], [0.0, var_o, 0.0], [o * var_t, 0.0, var_t]], dtype=_F64
    )
    floor = torch.diag(torch.tensor([5e-4**2, 5e-4**2, 5e-3**2], dtype=_F64))
    return Gaussian(torch.tensor([o * t, -o, t], dtype=_F64), cov + floor)


__all__ = ["PegPhysicsModel", "filter_scene", "grasp_of", "grasp_prior", "slot_map"]
