"""The planar contact model as a switching model: the mode-decoupled step, linearized per mode."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import torch
from torch import Tensor

from torchcontact._checks import FLOAT_DTYPES, describe
from torchcontact._compiled import kernel
from torchcontact.contact import solve_mode
from torchcontact.filters._mode_gate import check_gate, gate_log_weight
from torchcontact.filters._planar_linearization import ModeTable, linearize_modes, mode_table
from torchcontact.filters._planar_slots import SlotLayout, slot_layout
from torchcontact.filters._rbpf_belief import RBPFBelief
from torchcontact.filters._switching import LinearSwitchingModel, ModeDynamics
from torchcontact.sim import Rollout, Scene, SceneState, contact_problem, slot_friction
from torchcontact.states import TactileArray, object_contacts

STATE_DIM = 6  # (x, y, θ, vx, vy, ω)
OBS_DIM = 3  # (x, y, θ) from vision
PLANAR_MODES = 4  # separated, sticking, sliding along +t, sliding along −t


@dataclass(frozen=True, eq=False)
class KinematicControl:
    """The known motion of a scene's kinematic bodies (robot fingers) over one filter step.

    Attributes:
        q: ``(*B, Nk, 3)`` poses ``(x, y, θ)`` at the start of the step, world frame.
        v: ``(*B, Nk, 3)`` twists ``(vx, vy, ω)`` during the step, world frame.
    """

    q: Tensor
    v: Tensor


@dataclass(frozen=True, eq=False)
class _ConstantDynamics:
    """The per-step constants of :meth:`PlanarContactModel.mode_dynamics`.

    Attributes:
        Q: ``(K, 6, 6)`` process noise.
        H: ``(K, 3, 6)`` vision's measurement matrix.
        d: ``(K, 3)`` zero measurement offset.
        R: ``(K, 3, 3)`` vision noise.
    """

    Q: Tensor
    H: Tensor
    d: Tensor
    R: Tensor


class ContactModelFields:
    """What the planar and spatial contact models share: ``K`` from the mode table, the
    action count, dtype and device of the filter, and the tracked body's name (a mixin of
    frozen dataclasses with the fields ``scene``, ``modes``, ``Q`` and ``transition``)."""

    scene: Scene
    modes: Tensor
    Q: Tensor
    transition: Tensor

    @property
    def num_modes(self) -> int:
        """``K``."""
        return int(self.modes.shape[0])

    @property
    def num_actions(self) -> int | None:
        """``A`` of an action-dependent transition, else None."""
        return int(self.transition.shape[0]) if self.transition.ndim == 3 else None

    @property
    def dtype(self) -> torch.dtype:
        """The filter's dtype (that of ``Q``)."""
        return self.Q.dtype

    @property
    def device(self) -> torch.device:
        """The filter's device."""
        return self.Q.device

    @property
    def body(self) -> str:
        """Name of the tracked body."""
        return self.scene.bodies[self.scene.dynamic[0]].name


def rollout_modes(rollout: object, *, R: object, smoothing: float) -> tuple[Tensor, Tensor, Tensor]:
    """The mode table, transition and first-mode distribution of simulated rollouts.

    Args:
        rollout: a :class:`~torchcontact.sim.Rollout` of at least one step, ``mode`` of shape
            ``(T, *B, S)``.
        R: the model's measurement noise; its dtype (float64 if it is not a tensor) is that of
            the estimates.
        smoothing: pseudo-count of the transition and first-mode estimates, ``> 0``.

    Returns:
        The ``(K, S)`` table of :func:`collect_modes`, the ``(K, K)`` transition of
        :func:`empirical_transition` and the ``(K,)`` smoothed frequencies of the first modes.

    Raises:
        ValueError: naming ``rollout`` if it is not a Rollout of at least one step.
    """
    if not isinstance(rollout, Rollout) or rollout.mode.shape[0] == 0:
        raise ValueError(f"rollout: expected a Rollout of >= 1 step, got {describe(rollout)}")
    table, ids, _ = collect_modes(rollout.mode)
    K = len(table)
    dtype = R.dtype if isinstance(R, Tensor) else torch.float64
    first = torch.bincount(ids[0].reshape(-1), minlength=K).to(dtype) + smoothing
    transition = empirical_transition(ids, K, smoothing=smoothing, dtype=dtype)
    return table, transition, first / first.sum()


@dataclass(frozen=True, eq=False, kw_only=True)
class PlanarContactModel(ContactModelFields):
    r"""One body of a planar scene, its contact modes and a vision sensor, as a switching model
    for the :class:`~torchcontact.filters.RBPF`.

    The state is the tracked body's pose and twist, :math:`x = (x, y, \theta, v_x, v_y,
    \omega)` (world frame). Mode :math:`k` fixes the contact mode of every slot of the scene,
    ``modes[k]`` (DESIGN: discrete filter modes are ids into a table of per-slot mode vectors),
    and the step is the simulator's semi-implicit Euler step with that mode:

    .. math::

        f_k(x, u) = \begin{pmatrix} q + h\, v^+_k \\ v^+_k \end{pmatrix}, \qquad
        v^+_k = \mathrm{solve\_mode}(\mathrm{problem}(q, v, u), \mathrm{modes}[k])

    where the contact problem holds the slots' gaps and Jacobians at the pose :math:`q` and the
    fingers' known motion :math:`u` (:class:`KinematicControl`). Given the mode the step is
    smooth, so the filter's Kalman predict uses its linearization at the belief's mixture mean
    :math:`\bar x` (one per mode and batch entry, shared by the particles):
    :math:`F_k = \partial f_k / \partial x (\bar x)`, :math:`c_k = f_k(\bar x) - F_k \bar x`,
    plus the process noise :math:`Q_k`. Vision measures the pose: :math:`y = (x, y, \theta)
    + N(0, R)` (the angle must be continuous, not wrapped, like the simulator's).

    The Jacobian is exact, in float64: the derivative of the mode-fixed step at :math:`\bar x`
    with the discrete choices of the geometry held (each slot's closest edge, the candidate
    slots): the slots' gaps, rows and known velocities are differentiated along the pose in
    closed form, and the derivative of the impulses follows from that of the mode's
    constraint system, solved with the step's own (iterated Tikhonov) solve; on a box pushed by
    a finger it matches forward-mode automatic differentiation of the step to 1e-10 of the
    largest entry. All modes are linearized in one batch, with each mode's constraint system
    reduced to the slots it activates (a few hundred small tensor operations, whatever the
    batch). Where a slot's closest edge switches at :math:`\bar x` itself (a kink of the
    geometry) the derivative is the one-sided one of the edge chosen there. A mode whose
    active slots are not candidates at :math:`\bar x` (out of the scene's margin) acts as if
    those slots were separated. Where a mode's
    equalities contradict each other at :math:`\bar x` (a finger sticking to a box that slides
    on the ground), its step is ``solve_mode``'s regularised answer, which amplifies round-off:
    its linearization is reproducible to about 1e-3 only (such modes are usually inconsistent,
    see below).

    Physics as evidence: a mode's step at :math:`\bar x` may contradict the mode itself (a
    finger that stopped would have to pull the box it was pushing, friction of a sliding
    slot would reverse the slip, a separated slot would penetrate). Such modes get the
    log-weight ``-inconsistency_penalty`` in the step (``ModeDynamics.mode_log_weight``),
    judged by :func:`~torchcontact.contact.is_consistent` with the relative tolerance
    ``consistency_tolerance`` after closing the gaps of the mode's contacts up to
    ``consistency_gap`` (the mean's position error): a soft gate, since the mean is only an
    estimate.

    Attributes:
        scene: the planar scene; exactly one dynamic body (the tracked object), any kinematic
            bodies (fingers, driven by the control) and static bodies.
        modes: ``(K, S)`` long table of per-slot modes (``S = scene.num_slots``; values in
            ``[0, 4)``), e.g. from :func:`collect_modes` over simulated rollouts.
        Q: ``(6, 6)`` or ``(K, 6, 6)`` process noise covariance of a step, symmetric PSD. Its
            dtype is the filter's.
        R: ``(3, 3)`` vision noise covariance, symmetric positive definite.
        transition: ``(K, K)`` row-stochastic mode transition, or ``(A, K, K)`` per action
            (e.g. from a :class:`~torchcontact.states.ManipulationGraph` or
            :func:`empirical_transition`).
        initial: ``(K,)`` distribution of the first mode.
        inconsistency_penalty: log-weight penalty (nats, ``>= 0``; ``inf`` rules such modes
            out) of modes inconsistent at the linearization point; ``0`` disables the gate.
        consistency_tolerance: relative tolerance of the consistency check.
        consistency_gap: gaps (metres) of a mode's contacts that the check treats as closed.
        compiled: run the linearization through :func:`torch.compile` (see
            ``torchcontact._compiled``; the first call compiles, tens of seconds, then
            a call takes a third to a quarter of the eager time), with every mode's system laid
            out over the most slots any mode activates, so that its shapes do not depend on the
            linearization point (the same results to rounding).

    Construction validates every field and raises ``ValueError`` naming the field at fault.
    """

    scene: Scene
    modes: Tensor
    Q: Tensor
    R: Tensor
    transition: Tensor
    initial: Tensor
    inconsistency_penalty: float = 5.0
    consistency_tolerance: float = 0.05
    consistency_gap: float = 0.003
    compiled: bool = False

    def __post_init__(self) -> None:
        scene = self.scene
        if not isinstance(scene, Scene):
            raise ValueError(f"scene: expected a Scene, got {type(scene).__name__}")
        if len(scene.dynamic) != 1:
            raise ValueError(
                f"scene: expected exactly one dynamic body (the tracked object), got "
                f"{len(scene.dynamic)}"
            )
        modes = self.modes
        S = scene.num_slots
        if (
            not isinstance(modes, Tensor)
            or modes.dtype != torch.long
            or modes.ndim != 2
            or modes.shape[1] != S
            or modes.shape[0] < 1
        ):
            raise ValueError(
                f"modes: expected a long (K, {S}) tensor of per-slot modes, got "
                f"{getattr(modes, 'dtype', type(modes).__name__)} "
                f"{tuple(getattr(modes, 'shape', ()))}"
            )
        if bool(((modes < 0) | (modes >= PLANAR_MODES)).any()):
            raise ValueError(f"modes: values must lie in [0, {PLANAR_MODES})")
        check_gate(
            penalty=self.inconsistency_penalty,
            tolerance=self.consistency_tolerance,
            gap=self.consistency_gap,
        )
        if not isinstance(self.compiled, bool):
            raise ValueError(f"compiled: expected a bool, got {self.compiled!r}")
        K = int(modes.shape[0])
        for name, value, shapes in (
            ("Q", self.Q, ((STATE_DIM, STATE_DIM), (K, STATE_DIM, STATE_DIM))),
            ("R", self.R, ((OBS_DIM, OBS_DIM),)),
        ):
            if not isinstance(value, Tensor) or tuple(value.shape) not in shapes:
                raise ValueError(
                    f"{name}: expected shape {' or '.join(map(str, shapes))}, got "
                    f"{tuple(getattr(value, 'shape', ()))}"
                )
            if value.dtype not in FLOAT_DTYPES:  # before F's zeros take Q's dtype below
                raise ValueError(f"{name}: expected float32 or float64, got dtype {value.dtype}")
        # The remaining checks (dtypes, finiteness, PSD noise, stochastic transition and
        # initial) are those of a linear switching model with the same noise and transition.
        dtype = self.Q.dtype
        LinearSwitchingModel(
            F=torch.zeros(K, STATE_DIM, STATE_DIM, dtype=dtype, device=self.Q.device),
            c=torch.zeros(K, STATE_DIM, dtype=dtype, device=self.Q.device),
            Q=self.Q.expand(K, STATE_DIM, STATE_DIM),
            H=self._H(),
            d=torch.zeros(K, OBS_DIM, dtype=dtype, device=self.Q.device),
            R=self.R.expand(K, OBS_DIM, OBS_DIM),
            transition=self.transition,
            initial=self.initial,
        )

    # ------------------------------------------------------------------------------------------
    # the SwitchingModel protocol

    @classmethod
    def from_rollout(
        cls,
        scene: Scene,
        rollout: Rollout,
        *,
        Q: Tensor,
        R: Tensor,
        smoothing: float = 0.1,
        **options: Any,
    ) -> PlanarContactModel:
        """The model of the modes that simulated rollouts of ``scene`` visit.

        The mode table is :func:`collect_modes` of ``rollout.mode``, the transition
        :func:`empirical_transition` of its mode ids, and the first mode's distribution the
        ids' frequencies at the first step, with the same additive ``smoothing``.

        Args:
            scene: the scene (exactly one dynamic body).
            rollout: rollouts of ``scene``, ``rollout.mode`` of shape ``(T, *B, S)``.
            Q: ``(6, 6)`` process noise covariance (or ``(K, 6, 6)`` when the number of modes
                is known).
            R: ``(3, 3)`` vision noise covariance.
            smoothing: pseudo-count of the transition and first-mode estimates, ``> 0``.
            **options: the model's other fields (``inconsistency_penalty``, ``compiled``, ...).

        Raises:
            ValueError: naming ``rollout`` if it is not a :class:`~torchcontact.sim.Rollout`
                of at least one step, or the field at fault.
        """
        table, transition, initial = rollout_modes(rollout, R=R, smoothing=smoothing)
        return cls(
            scene=scene,
            modes=table,
            Q=Q,
            R=R,
            transition=transition,
            initial=initial,
            **options,
        )

    @property
    def state_dim(self) -> int:
        """``6``: pose and twist."""
        return STATE_DIM

    @property
    def obs_dim(self) -> int:
        """``3``: the vision pose."""
        return OBS_DIM

    def mode_dynamics(self, belief: RBPFBelief, control: Any) -> ModeDynamics:
        """Every mode's step linearized at the belief's mixture mean.

        Args:
            belief: the belief at the start of the step, batch ``*B``.
            control: a :class:`KinematicControl` with batch ``*B`` (broadcastable), or None
                when the scene has no kinematic body.

        Returns:
            The :class:`ModeDynamics` with ``F (*B, K, 6, 6)``, ``c (*B, K, 6)`` and the
            constant noise and vision model.
        """
        # A belief's mean is finite (the filter checks what it is built from): no check here.
        F, c, consistent = self._linearize(belief.mean(), control, self.dtype)
        noise = self._noise
        log_weight = None
        if self.inconsistency_penalty > 0:
            log_weight = gate_log_weight(
                consistent, penalty=self.inconsistency_penalty, dtype=self.dtype
            )
        return ModeDynamics(
            mode_log_weight=log_weight,
            F=F,
            c=c,
            Q=noise.Q,
            H=noise.H,
            d=noise.d,
            R=noise.R,
        )

    # ------------------------------------------------------------------------------------------
    # the step and its linearization

    def step(self, x: Tensor, *, mode: Tensor, control: KinematicControl | None = None) -> Tensor:
        """The mode-decoupled step ``f_k(x, u)``, differentiable.

        Args:
            x: ``(*B, 6)`` pose and twist of the tracked body.
            mode: ``(*B,)`` long mode ids into :attr:`modes`.
            control: the kinematic bodies' motion, batch broadcastable to ``*B``.

        Returns:
            ``(*B, 6)`` the state after the step (in ``x``'s dtype).
        """
        _check_state(x)
        if not isinstance(mode, Tensor) or mode.dtype != torch.long:
            raise ValueError(f"mode: expected a long (*B,) tensor, got {describe(mode)}")
        if bool(((mode < 0) | (mode >= self.num_modes)).any()):
            raise ValueError(f"mode: ids must lie in [0, {self.num_modes})")
        batch = torch.broadcast_shapes(x.shape[:-1], mode.shape)
        q_kin, v_kin = self._control(control, batch, x.dtype)
        modes = self.modes[mode.expand(batch)]
        return self._step(x.expand(*batch, 6), modes, q_kin, v_kin)

    def linearize(
        self, x: Tensor, *, control: KinematicControl | None = None
    ) -> tuple[Tensor, Tensor]:
        """Every mode's step linearized at ``x``: ``f_k(x + δ) ≈ F_k (x + δ) + c_k``.

        Args:
            x: ``(*B, 6)`` linearization point (pose and twist, world frame).
            control: the kinematic bodies' motion, batch broadcastable to ``*B``.

        Returns:
            ``F (*B, K, 6, 6)`` and ``c (*B, K, 6)``, float64.
        """
        _check_state(x)
        F, c, _ = self._linearize(x, control, torch.float64)
        return F, c

    def _linearize(
        self, x: Tensor, control: KinematicControl | None, dtype: torch.dtype
    ) -> tuple[Tensor, Tensor, Tensor]:
        """``F`` and ``c`` in ``dtype``, and ``(*B, K)`` bool: the mode is consistent at ``x``
        (finite)."""
        batch = x.shape[:-1]
        q_kin, v_kin = self._control(control, batch, torch.float64)
        flat = x.reshape(-1, STATE_DIM).to(torch.float64)
        kinematic = (flat.shape[0], q_kin.shape[-2], 3)
        # Without gradients to carry, inference mode spares every small operation autograd's
        # bookkeeping; F and c leave it as ordinary tensors (copies of a few numbers).
        mu, inverse_mass = self._physics()
        tracked = torch.is_grad_enabled() and any(
            t.requires_grad for t in (flat, q_kin, v_kin, mu, inverse_mass)
        )
        layout, table = self._layout, self._mode_table  # built (once) outside inference mode
        linearize = kernel(linearize_modes, compiled=self.compiled)
        with torch.inference_mode(not tracked):
            F, c, consistent = linearize(
                layout,
                table,
                flat,
                q_kin.reshape(kinematic),
                v_kin.reshape(kinematic),
                mu=mu,
                inverse_mass=inverse_mass,
                consistency_gap=self.consistency_gap,
                consistency_tolerance=self.consistency_tolerance,
                for_compile=self.compiled,
            )
        K = self.num_modes
        return (
            F.to(dtype, copy=True).view(*batch, K, STATE_DIM, STATE_DIM),
            c.to(dtype, copy=True).view(*batch, K, STATE_DIM),
            consistent.view(*batch, K),
        )

    def _physics(self) -> tuple[Tensor, Tensor]:
        """``(S,)`` friction of every slot and ``(3,)`` ``(1/m, 1/m, 1/I)`` of the tracked body,
        float64, from the scene's values: tensors that require grad keep their graph (a model
        of a scene with such parameters is differentiable with respect to them)."""
        if not self._parameters_require_grad:
            return self._constant_physics
        return _physics_of(self.scene, self.device)

    @cached_property
    def _parameters_require_grad(self) -> bool:
        scene, body = self.scene, self.scene.bodies[self.scene.dynamic[0]]
        values = [scene.friction, *scene.pair_friction.values(), body.mass, body.inertia]
        return any(isinstance(value, Tensor) and value.requires_grad for value in values)

    @cached_property
    def _constant_physics(self) -> tuple[Tensor, Tensor]:
        with torch.no_grad():
            return _physics_of(self.scene, self.device)

    def _step(self, x: Tensor, modes: Tensor, q_kin: Tensor, v_kin: Tensor) -> Tensor:
        """``f`` on batches: x ``(*P, 6)``, modes ``(*P, S)``, q/v_kin ``(*P, Nk, 3)``."""
        batch = x.shape[:-1]
        flat = x.reshape(-1, 6)
        P = flat.shape[0]
        state = SceneState(
            q=flat[:, None, :3],
            v=flat[:, None, 3:],
            q_kinematic=q_kin.reshape(P, *q_kin.shape[-2:]).to(x.dtype),
            mode=modes.reshape(P, modes.shape[-1]),
        )
        problem, _ = contact_problem(
            self.scene, state, control=v_kin.reshape(P, *v_kin.shape[-2:]).to(x.dtype)
        )
        v_next = solve_mode(problem, state.mode).v_next
        x_next = torch.cat([flat[:, :3] + self.scene.h * v_next, v_next], -1)
        return x_next.reshape(*batch, 6)

    # ------------------------------------------------------------------------------------------
    # tactile evidence

    def tactile_log_likelihood(
        self,
        tactile: TactileArray,
        readings: Tensor,
        *,
        pose: Tensor,
        control: KinematicControl | None = None,
    ) -> Tensor:
        """``log p(readings | mode k)`` of sensors on the tracked body, for every mode.

        Mode ``k`` touches at its active slots (``modes[k] >= 1`` and a candidate slot of the
        scene at ``pose``); the sensors those contact points trigger (``tactile.triggered``,
        every active contact taken to carry load) read ``True`` up to the array's false-
        positive and false-negative rates.

        Args:
            tactile: the sensor array, in the tracked body's frame (float64 or the filter's
                dtype).
            readings: ``(*B, S_s)`` bool readings of the step.
            pose: ``(*B, 3)`` pose at which the contacts are placed (e.g. the belief's mean
                pose before the step).
            control: the kinematic bodies' poses (their twists are not used).

        Returns:
            ``(*B, K)`` log-likelihoods, the filter's dtype; pass as the RBPF step's
            ``extra_log_likelihood``.
        """
        if not isinstance(pose, Tensor) or not pose.is_floating_point() or pose.shape[-1:] != (3,):
            raise ValueError(f"pose: expected a floating (*B, 3) tensor, got {describe(pose)}")
        if not isinstance(readings, Tensor) or readings.dtype != torch.bool:
            raise ValueError(f"readings: expected a bool (*B, S) tensor, got {describe(readings)}")
        dtype = tactile.positions.dtype
        batch = pose.shape[:-1]
        q_kin, v_kin = self._control(control, batch, dtype)
        pose = pose.to(dtype)
        state = SceneState(
            q=pose[..., None, :],
            v=torch.zeros_like(pose)[..., None, :],
            q_kinematic=q_kin,
            mode=torch.zeros(*batch, self.scene.num_slots, dtype=torch.long, device=pose.device),
        )
        _, geometry = contact_problem(self.scene, state, control=v_kin)
        # The readings depend on a mode only through the slots it activates: evaluate each
        # distinct set once (U of them) and hand every mode its set's log-likelihood.
        acting, which = self._acting_sets
        expand = (*batch, acting.shape[0])
        active = geometry.active.unsqueeze(-2).expand(*expand, -1)
        contacts = object_contacts(
            self.scene,
            body=self.body,
            q=pose[..., None, None, :].expand(*expand, 1, 3),
            points=geometry.points.unsqueeze(-3).expand(*expand, -1, 2),
            normals=geometry.normals.unsqueeze(-3).expand(*expand, -1, 2),
            pn=torch.ones(*expand, self.scene.num_slots, dtype=dtype, device=pose.device),
            mode=acting.expand(*expand, -1),
            active=active,
        )
        triggers = tactile.triggered(contacts)  # (*B, U, S_s)
        log_lik = tactile.reading_log_likelihood(readings.unsqueeze(-2), triggers)
        return log_lik.index_select(-1, which).to(self.dtype)

    # ------------------------------------------------------------------------------------------

    def _H(self) -> Tensor:
        """``(K, 3, 6)``: vision measures the pose, in every mode (one matrix, expanded)."""
        H = self.Q.new_zeros(OBS_DIM, STATE_DIM)
        H[:, :OBS_DIM] = torch.eye(OBS_DIM, dtype=self.Q.dtype, device=self.Q.device)
        return H.expand(self.num_modes, OBS_DIM, STATE_DIM)

    @cached_property
    def _noise(self) -> _ConstantDynamics:
        """The parts of :meth:`mode_dynamics` that do not change, built at its first use."""
        K = self.num_modes
        return _ConstantDynamics(
            Q=self.Q.expand(K, STATE_DIM, STATE_DIM),
            H=self._H(),
            d=self.Q.new_zeros(OBS_DIM).expand(K, OBS_DIM),
            R=self.R.expand(K, OBS_DIM, OBS_DIM),
        )

    @cached_property
    def _acting_sets(self) -> tuple[Tensor, Tensor]:
        """The distinct sets of slots that the modes activate, ``(U, S)`` long (1 = acting),
        and each mode's set, ``(K,)`` long; built at their first use."""
        sets, which = torch.unique((self.modes >= 1).to(torch.long), dim=0, return_inverse=True)
        return sets, which

    @cached_property
    def _layout(self) -> SlotLayout:
        """The scene's slot tables for the linearization, built at its first use."""
        return slot_layout(self.scene, self.device)

    @cached_property
    def _mode_table(self) -> ModeTable:
        """:attr:`modes` as the linearization uses them, built at its first use."""
        return mode_table(self._layout, self.modes)

    def _control(
        self, control: KinematicControl | None, batch: torch.Size, dtype: torch.dtype
    ) -> tuple[Tensor, Tensor]:
        """Kinematic poses and twists ``(*B, Nk, 3)`` of the control, checked."""
        Nk = len(self.scene.kinematic)
        if control is None:
            if Nk:
                raise ValueError(f"control: required, the scene has {Nk} kinematic bodies")
            empty = torch.zeros(*batch, 0, 3, dtype=dtype, device=self.device)
            return empty, empty
        if not isinstance(control, KinematicControl):
            raise ValueError(f"control: expected a KinematicControl, got {type(control).__name__}")
        values = {"control.q": control.q, "control.v": control.v}
        for name, value in values.items():
            if not isinstance(value, Tensor) or value.shape[-2:] != (Nk, 3):
                raise ValueError(f"{name}: expected a (*B, {Nk}, 3) tensor, got {describe(value)}")
        if not bool(torch.isfinite(control.q).all() & torch.isfinite(control.v).all()):
            name = next(name for name, value in values.items() if not value.isfinite().all())
            raise ValueError(f"{name}: contains NaN or inf")
        out = []
        for name, value in values.items():
            try:
                out.append(value.to(dtype).expand(*batch, Nk, 3))
            except RuntimeError as err:
                raise ValueError(
                    f"{name}: batch {tuple(value.shape[:-2])} does not broadcast to {tuple(batch)}"
                ) from err
        return out[0], out[1]


def _physics_of(scene: Scene, device: torch.device) -> tuple[Tensor, Tensor]:
    """See :meth:`PlanarContactModel._physics`."""
    mu = slot_friction(scene, dtype=torch.float64, device=device)
    if mu.dim() != 1:
        raise ValueError(
            "scene: the linearization needs scalar friction coefficients, got per-slot "
            f"frictions of shape {tuple(mu.shape)}"
        )
    # One dynamic body: the mass matrix is diag(m, m, I).
    return mu, scene.mass_matrix().to(device).diagonal().reciprocal()


def _check_state(x: object) -> None:
    """Raise unless ``x`` is a finite floating ``(*B, 6)`` pose-and-twist tensor."""
    if not isinstance(x, Tensor) or not x.is_floating_point() or x.shape[-1:] != (6,):
        raise ValueError(f"x: expected a floating (*B, 6) tensor, got {describe(x)}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError("x: contains NaN or inf")


def collect_modes(modes: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The table of distinct per-slot mode vectors seen in simulated data.

    Args:
        modes: ``(T, *B, S)`` long per-slot modes, time first, e.g. ``Rollout.mode`` of
            training rollouts (any leading shape is accepted).

    Returns:
        ``table (K, S)`` (most frequent first), ``ids (T, *B)`` long, each entry's row in the
        table, and ``counts (K,)``.
    """
    if not isinstance(modes, Tensor) or modes.dtype != torch.long or modes.ndim < 1:
        raise ValueError(f"modes: expected a long (..., S) tensor, got {describe(modes)}")
    flat = modes.reshape(-1, modes.shape[-1])
    table, inverse, counts = torch.unique(flat, dim=0, return_inverse=True, return_counts=True)
    order = torch.argsort(counts, descending=True, stable=True)
    rank = torch.empty_like(order)
    rank[order] = torch.arange(len(order), device=order.device)
    return table[order], rank[inverse].reshape(modes.shape[:-1]), counts[order]


def empirical_transition(
    ids: Tensor, num_modes: int, *, smoothing: float = 1.0, dtype: torch.dtype = torch.float64
) -> Tensor:
    """Row-stochastic mode transition estimated from mode-id sequences.

    ``P[i, j] = (n_ij + smoothing) / (Σ_j n_ij + K · smoothing)`` with ``n_ij`` the number of
    steps from ``i`` to ``j`` (additive smoothing keeps unseen transitions possible, so the
    filter can recover from them).

    Args:
        ids: ``(T, *B)`` long mode ids in ``[0, num_modes)``, time first (as
            :func:`collect_modes` returns them for ``Rollout.mode``).
        num_modes: ``K``.
        smoothing: pseudo-count added to every entry, ``> 0``.
        dtype: floating dtype of the result.

    Returns:
        ``(K, K)`` transition matrix, row = from.
    """
    if not isinstance(num_modes, int) or num_modes < 1:
        raise ValueError(f"num_modes: expected an int >= 1, got {num_modes!r}")
    if not isinstance(ids, Tensor) or ids.dtype != torch.long or ids.ndim < 1:
        raise ValueError(f"ids: expected a long (T, *B) tensor, got {describe(ids)}")
    if bool(((ids < 0) | (ids >= num_modes)).any()):
        raise ValueError(f"ids: values must lie in [0, {num_modes})")
    if not smoothing > 0:
        raise ValueError(f"smoothing: expected > 0, got {smoothing!r}")
    pairs = ids[:-1] * num_modes + ids[1:]
    counts = torch.bincount(pairs.reshape(-1), minlength=num_modes * num_modes)
    counts = counts.reshape(num_modes, num_modes).to(dtype) + smoothing
    return counts / counts.sum(-1, keepdim=True)
