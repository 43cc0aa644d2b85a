"""The spatial contact model as a switching model: a box's pose and twist on SE(3), its contact
modes against a table and a kinematic robot, linearized per mode in the tangent space."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from torchcontact._checks import FLOAT_DTYPES, check_real, describe
from torchcontact._compiled import kernel
from torchcontact.contact import (
    SEPARATED,
    SLIDING,
    ContactProblem,
    Solution,
    is_consistent,
    is_sliding,
    num_modes,
    redistribute_impulses,
    relative_residual,
    solve_lemke,
    solve_mode,
    solve_mode_unchecked,
    update_mode,
)
from torchcontact.filters._contact_model import ContactModelFields, rollout_modes
from torchcontact.filters._manifold import SE3, Manifold
from torchcontact.filters._mode_gate import check_gate, gate_log_weight
from torchcontact.filters._rbpf_belief import RBPFBelief
from torchcontact.filters._switching import LinearSwitchingModel, ModeDynamics
from torchcontact.geometry import Box, Capsule, SlotGeometry, Sphere, quat_to_matrix
from torchcontact.sim import Rollout, Scene, SceneState, contact_problem, integrate_poses
from torchcontact.states import ContactSet, PartnerKind, TactileArray

STATE_DIM = 13  # position, quaternion (w, x, y, z), linear and angular velocity
TANGENT_DIM = 12  # (δp, δθ, δv, δω)
OBS_DIM = 7  # the camera's pose: position and quaternion
OBS_TANGENT_DIM = 6  # its residual (δp, δθ)


@dataclass(frozen=True, eq=False)
class RobotControl:
    """The measured motion of a spatial scene's robots (and kinematic bodies) over one filter
    step, world frame.

    Robots whose joints are all kinematic move as measured: ``v_robot`` is their motion over
    the step. Robots with servo joints (``RobotMember(mode="servo")``, a hand whose fingers
    yield to the object) are stepped with the object: ``v_robot`` is then the joints'
    velocity at the start of the step and ``joint_command`` what the robot was commanded, as
    in :meth:`~torchcontact.sim.Simulator.step`.

    Attributes:
        q_robot: ``(*B, Nj)`` joint positions at the start of the step, robots in scene order
            (rad or m).
        v_robot: ``(*B, Nj)`` joint velocities: during the step (kinematic robots), at its
            start (scenes with servo joints).
        robot_base: ``(*B, R, 7)`` the robots' base poses (position and unit quaternion
            ``(w, x, y, z)``), or None: each member's ``base_pose``.
        base_twist: ``(*B, R, 6)`` the bases' twists ``(v, ω)`` during the step (at the base
            frame's origin), or None: at rest.
        q_kinematic: ``(*B, Nk, 7)`` poses of the scene's kinematic bodies, or None (required
            when it has some).
        v_kinematic: ``(*B, Nk, 6)`` their twists, or None (at rest).
        joint_command: ``(*B, Nj)`` the joints' commands over the step (servo targets,
            kinematic joints' velocities: :meth:`~torchcontact.sim.Simulator.step`'s
            ``joint_command``), required where the scene has servo joints; None otherwise.
        v_robot_next: ``(*B, Nj)`` the joints' measured velocities at the end of the step,
            or None: with servo joints, a measurement that each particle's child conditions
            on (see :attr:`SpatialContactModel.joint_velocity_sigma`).
    """

    q_robot: Tensor
    v_robot: Tensor
    robot_base: Tensor | None = None
    base_twist: Tensor | None = None
    q_kinematic: Tensor | None = None
    v_kinematic: Tensor | None = None
    joint_command: Tensor | None = None
    v_robot_next: Tensor | None = None


@dataclass(frozen=True, eq=False)
class _Control:
    """A :class:`RobotControl` checked and broadcast to a flat batch ``(P,)``, float64."""

    q_robot: Tensor
    v_robot: Tensor
    robot_base: Tensor
    base_twist: Tensor | None
    q_kinematic: Tensor
    v_kinematic: Tensor | None
    joint_command: Tensor | None
    v_robot_next: Tensor | None

    def expand(self, repeat: int) -> _Control:
        """Each entry repeated ``repeat`` times, consecutively: ``(P · repeat, ...)``."""
        return self._map(lambda t: t.repeat_interleave(repeat, dim=0))

    def select(self, index: Tensor) -> _Control:
        """The entries ``index (Q,)`` (long): ``(Q, ...)``."""
        return self._map(lambda t: t.index_select(0, index))

    def _map(self, fn: Callable[[Tensor], Tensor]) -> _Control:
        """Every field through ``fn`` (the optional ones where given)."""

        def each(t: Tensor | None) -> Tensor | None:
            return None if t is None else fn(t)

        return _Control(
            q_robot=fn(self.q_robot),
            v_robot=fn(self.v_robot),
            robot_base=fn(self.robot_base),
            base_twist=each(self.base_twist),
            q_kinematic=fn(self.q_kinematic),
            v_kinematic=each(self.v_kinematic),
            joint_command=each(self.joint_command),
            v_robot_next=each(self.v_robot_next),
        )


@dataclass(frozen=True, eq=False)
class _Linearization:
    """Every mode's step at one point, flat batch ``(P, K)``.

    Attributes:
        F: ``(P, K, 12, 12)`` tangent Jacobians (chart of each row: see ``_linearize``).
        f: ``(P, K, 13)`` the steps ``f_k(x̄)``.
        c: ``(P, K, 12)`` ``local(chart, f_k(x̄))`` (zero with the per-mode charts).
        chart: ``(P, 13)`` the chart's point (with per-mode charts: the first mode's).
        converged: ``(P, K)`` bool, the mode's equalities were solved at ``x̄``.
        consistent: ``(P, K)`` bool, the gate's verdict (True where it is off).
        nearly: ``(P, K)`` bool, the verdict with ten times the tolerance.
        held: ``(P, 1)`` bool, the point holds its state for the step (no mode usable; every
            mode's ``F``, ``f`` and ``c`` are the identity's).
        v_servo: ``(P, K, J)`` the servo joints' velocities at the end of each mode's step
            (``J = scene.num_servo_joints``, robots in scene order).
        G: ``(P, K, J', 12)`` their Jacobians in the tangent at ``x̄`` (``J' = J`` where the
            step conditions on the measured joint velocities, else 0; zero where not solved).
        touching: ``(P, K, S_a)`` bool, the acting slots each mode closes at ``x̄`` (its
            resolved slots).
        phi: ``(P, S_a)`` the acting slots' gaps at ``x̄``; Jn: ``(P, S_a, 6)`` their normal
            rows (gap rate per world-frame twist of the body); candidate: ``(P, S_a)`` bool,
            the slot is a contact candidate at ``x̄``.
    """

    F: Tensor
    f: Tensor
    c: Tensor
    chart: Tensor
    converged: Tensor
    consistent: Tensor
    nearly: Tensor
    held: Tensor
    v_servo: Tensor
    G: Tensor
    touching: Tensor
    phi: Tensor
    Jn: Tensor
    candidate: Tensor


@dataclass(frozen=True, eq=False, kw_only=True)
class SpatialContactModel(ContactModelFields):
    r"""The one dynamic body of a spatial scene (a box on a table, grasped by a robot), its
    contact modes, a camera and tactile pads, as a switching model for the
    :class:`~torchcontact.filters.RBPF`, on the SE(3) manifold.

    The state is the body's pose and twist, :math:`x = (p, q, v, \omega)` (13 numbers:
    world-frame position, unit quaternion ``(w, x, y, z)`` body to world, world-frame linear
    and angular velocity), with covariances in the 12-dim tangent space of
    :data:`~torchcontact.filters.SE3` (error-state form: :math:`x = \mathrm{retract}(\mu,
    \delta)`, :math:`\delta = (\delta p, \delta\theta, \delta v, \delta\omega)` with
    :math:`\delta\theta` in the body frame). Mode :math:`k` fixes the contact mode of every
    slot of the scene, ``modes[k]`` (box–table, then each robot collision primitive against
    the box), and the step is the simulator's with that mode:

    .. math::

        f_k(x, u) = \big(p + h v^+_k,\ \mathrm{Exp}(h\,\omega^+_k) \otimes q,\ v^+_k,
        \omega^+_k\big), \qquad
        (v^+_k, \omega^+_k) = \mathrm{solve\_mode}(\mathrm{problem}(x, u), \mathrm{modes}[k])

    where the robots' joint angles and velocities are the measured control :math:`u`
    (:class:`RobotControl`). Kinematic robots (:class:`~torchcontact.sim.RobotMember` with
    ``mode="kinematic"``) enter the problem through its known velocity terms. A robot's servo
    joints (a hand whose fingers yield) are stepped with the body from their measured state
    under their known commands, as in the simulator, and only the body's part of the step
    is kept: a grasp of several fingers then constrains the body through fingers that give
    way, whereas kinematic fingers impose their measured motion on it, which contradicts
    itself wherever the body's pose is not exactly the true one (three sticking fingers fix
    nine rows of the body's six velocities).

    Linearization. Every mode's step is linearized at the belief's mixture mean
    :math:`\bar x` (:meth:`RBPFBelief.mean`, a weighted Karcher mean on SE(3)), shared by
    the particles: in tangent coordinates,

    .. math::

        F_k = \frac{\partial}{\partial \delta}\,
            \mathrm{local}\big(z, f_k(\mathrm{retract}(\bar x, \delta))\big)\Big|_{\delta=0},
        \qquad c_k = \mathrm{local}(z, f_k(\bar x)),

    with :math:`z` the step of the most probable mode (every mode's prediction in one chart),
    so that particle :math:`i` with mean :math:`\mu_i` predicts
    :math:`\mathrm{retract}(z, F_k\, \mathrm{local}(\bar x, \mu_i) + c_k)`
    (:class:`~torchcontact.filters.ModeDynamics` with ``origin`` :math:`\bar x` and ``chart``
    :math:`z`). The Jacobian is exact (float64, automatic differentiation of the
    step through :func:`~torchcontact.sim.contact_problem` and
    :func:`~torchcontact.contact.solve_mode`, the twelve tangent directions of every mode
    solved at :math:`\bar x` in one batch; the others' Jacobians are placeholders, see Modes
    ruled out): the mode solve is differentiated from its converged impulses
    (``initial_impulses``), where its iterated Tikhonov iterations are a fixed point, so the
    derivative is that of the converged system (the implicit-function derivative, whose
    iterates converge as the solve's own), not that of a finite number of iterations from
    zero, which differs at redundant contacts. This is exact wherever the mode's equalities
    fix the step (sticking redundant corners, a box sliding on four corners: the friction rows
    share the normal rows' redundancy; tested against finite differences). Where they do
    not, i.e. the step depends on how ``solve_mode`` splits the impulses among redundant
    rows (a finger's sticking friction that could carry part of the weight of a box sliding
    on its corners), the Jacobian is that of the steps whose split stays nearest the
    converged one, not of ``solve_mode``'s own split rule. The discrete choices of the
    geometry (each slot's closest features, the candidate slots, the friction directions'
    hemisphere of :func:`~torchcontact.sim.tangent_basis`) are held.

    Gaps closed. The mixture mean is an estimate: a box resting on the table may have a mean
    a few millimetres above or inside it. Mode :math:`k` says which contacts touch, so its
    step at :math:`\bar x` is taken with the gaps of those contacts closed up to
    ``consistency_gap`` (a gap :math:`\phi` becomes :math:`\phi - \mathrm{clip}(\phi,
    \pm\,\mathrm{gap})`), and the penetrations of the slots it separates are taken as
    touching up to the same depth (:math:`\phi - \mathrm{clip}(\phi, -\mathrm{gap}, 0)`):
    the mean's error along a contact normal is neither turned into a velocity that closes it
    within one step nor, at a contact the mode separates, into a penetration that rules the
    mode out (on the Barrett box grasp, a box lifted by the fingers whose mean lies a fraction
    of a millimetre inside the table). The Jacobian holds that shift fixed (the derivative
    of the gaps is kept). With ``consistency_gap = 0`` the linearization is that
    of :meth:`step`.

    Contacts resolved at the mean. A rollout's contacts fix which corners of a box touch
    and along which of ``D`` directions (or a face between two) each slides; modes that
    differ only there multiply the table (a finger pushing a box over the table: every
    corner's direction), and a table of a few rollouts misses most of them. With
    ``resolve_slots`` a mode fixes only the state of each slot group (the slots of one
    shape pair: the box and the table, the box and one finger link): separated, sticking or
    sliding. At :math:`\bar x` the group's slots within ``consistency_gap`` of touching take
    its state and the others separate; one :func:`~torchcontact.contact.update_mode` round
    separates those that would pull; each sliding slot's friction takes the direction most
    opposed to its slip in the step with the sliding slots frictionless (maximal
    dissipation), then one more round moves it between an edge and the adjacent faces of
    the cone. A mode none of whose slots of a touching group lies within the gap is ruled
    out. With ``exact_resolution`` (the default), the contact problem at :math:`\bar x` is
    also solved exactly (Lemke, with penetrations taken as touching: the gaps clamped at
    zero), and the mode whose group states are those of that solution takes its slots and
    directions instead: the physics' own mode at the mean is then in the table whenever its
    group states are, and it passes the gate by construction (the rules above are a
    heuristic: at 12 of 48 true states of Barrett box grasps they made the simulator's own
    mode inconsistent, the exact resolution at 3). The step, its Jacobian, the gate and the
    tactile evidence are those of the resolved slots (:meth:`slot_modes`).

    Modes ruled out. A mode whose equalities contradict each other at :math:`\bar x` (its
    ``solve_mode`` does not converge and its answer does not solve the contact problem
    within :data:`SOLVED_RESIDUAL` of its scales, as the simulator's retry rule: a grasp's
    redundant rows stall the equality residual above the solver's tolerance while the impulses are
    consistent and solve the problem) gets the log-weight :math:`-\infty` for the step
    (``ModeDynamics.mode_log_weight``; its ``F`` and ``c`` are placeholders, the identity
    and the chart's origin). A mode that converges but contradicts itself (a separated slot
    that would penetrate, friction that would reverse the slip, a contact that would pull)
    gets ``-inconsistency_penalty``, judged by :func:`~torchcontact.contact.is_consistent`
    with the relative tolerance ``consistency_tolerance`` after closing the gaps of the mode's
    contacts up to ``consistency_gap``, as :class:`~torchcontact.filters.PlanarContactModel`
    does (the shared gate), on a split of its impulses that satisfies the mode where one
    exists (:func:`~torchcontact.contact.redistribute_impulses`: the redundant rows of a
    grasp by kinematic fingers fix the step but not how the impulse is shared, and the mode
    solve's least-norm split pulled at a finger or left a cone at 192 of 1,280 true states
    of 16 Barrett box trials, with their true mass and friction, while the truth's own split
    satisfies the mode). A mode whose Jacobian has an entry above ``max_gain`` (default
    1e6; a legitimate step amplifies a gap over a lever arm r by about 1 / (h r), 1e4 at
    h = 10 ms and r = 1 cm) counts as not solved: its system is nearly singular at the point
    (on the Barrett box, a finger sticking while the table's contacts slide gave entries of
    5e9 with respect to the box's height), so its derivative describes no nearby step, and a
    particle a millimetre from the mean would be carried at hundreds of metres per second.
    A mode whose step at :math:`\bar x` changes the velocity of some point of the body by
    more than ``max_speed_change`` (bounded by :math:`|\Delta v| + |\Delta\omega|\, r`,
    :math:`r` the body's bounding radius) counts as not solved either: no contact of the
    scene delivers such an impulse in one step (on the Barrett box grasp the true steps
    change point velocities by at most 0.22 m/s, while modes that pass the loose
    consistency check below with a nearly singular system spun the box at 50 rad/s, a
    third of a turn in 10 ms, and carried the belief away while the camera was occluded).
    A point at which no mode is solved (with ``inconsistency_penalty = inf``: none that
    passes even a ten times looser consistency check) holds its state for the step (every
    mode the identity, log-weight 0) rather than losing every mode: the step of a mode that
    contradicts itself extrapolates its Jacobian, and the mixture's spread would carry its
    particles away.

    Particles checked. The modes are resolved and gated at :math:`\bar x`, but each
    particle predicts from its own mean :math:`\mu_i`; where the particles spread, a mode
    that closes a contact at :math:`\bar x` may hold a particle centimetres away, and its
    linearized step then carries that particle along the contact's lever arm (a gap
    :math:`\phi` closed about a pivot at distance :math:`r` turns the body by
    :math:`\phi / r`). With ``particle_penalty`` :math:`> 0`, child :math:`(i, k)` gets the
    log-weight :math:`-`\ ``particle_penalty`` (``ModeDynamics.particle_log_weight``) where
    the gaps at :math:`\mu_i`, to first order :math:`\phi_i = \phi(\bar x) + J_n
    (\delta p, R\,\delta\theta)` with :math:`\delta = \mathrm{local}(\bar x, \mu_i)`,
    contradict mode :math:`k`: a slot it closes is more than ``consistency_gap`` apart, or
    a candidate slot it separates penetrates by more. A particle that every mode
    contradicts loses weight against the others; the penalty is finite, so that a belief
    all of whose particles are contradicted keeps them.

    Measurements. The camera measures the pose, :math:`y = \mathrm{retract}(p, q;\ n)`,
    :math:`n \sim N(0, R)` in the 6-dim tangent (``y`` is ``(7,)``, NaN where occluded);
    tactile pads on the robot's links read binary contacts
    (:meth:`tactile_log_likelihood`, per mode, the RBPF step's ``extra_log_likelihood``).

    Proprioception. With servo joints, a finite ``joint_velocity_sigma`` :math:`\sigma_j` and
    the joints' measured velocities at the end of the step :math:`u` (``RobotControl.
    v_robot_next``), each child conditions on them. The servo joints' velocities are an
    output of each mode's step, linearized at the mean with the step,
    :math:`u = G_k \delta + g_k + e`, :math:`e \sim N(0, \sigma_j^2 I)` (:math:`G_k` exact,
    from the same differentiated replicas as :math:`F_k`). Child :math:`(i, k)` is weighted by
    its likelihood :math:`N(u;\ G_k \delta_i + g_k,\ G_k P_i G_k^\top + \sigma_j^2 I)`
    (``particle_log_weight``: a finger that mode :math:`k` lets close freely while the box
    slowed it counts against the mode), and its state at the start of the step is updated
    with the gain :math:`K_k = \bar P G_k^\top (G_k \bar P G_k^\top + \sigma_j^2 I)^{-1}` of
    the belief's mixture covariance :math:`\bar P` (one gain per mode, so that the update
    folds into the step: :math:`F_k (I - K_k G_k)`, offset :math:`c_k + F_k K_k (u - g_k)`,
    noise :math:`Q_k + F_k K_k \sigma_j^2 K_k^\top F_k^\top`, the Joseph form's covariance
    of that estimate). The servoed fingers then yield where the filter's box is, and what the
    measured fingers did still tells the filter where the box is.

    Attributes:
        scene: a spatial scene with exactly one dynamic body (the tracked object), static
            bodies, kinematic bodies and robots: kinematic (``RobotMember(mode="kinematic")``)
            or servoed (their joint states measured, see :class:`RobotControl`).
        modes: ``(K, S)`` long table of per-slot modes (``S = scene.num_slots``; values in
            ``[0, num_modes(D))``), e.g. from :func:`collect_modes` over simulated rollouts.
        Q: ``(12, 12)`` or ``(K, 12, 12)`` process noise covariance of a step in the tangent,
            symmetric PSD. Its dtype is the filter's.
        R: ``(6, 6)`` camera noise covariance in the pose's tangent ``(δp, δθ)``, symmetric
            positive definite.
        transition: ``(K, K)`` row-stochastic mode transition, or ``(A, K, K)`` per action.
        initial: ``(K,)`` distribution of the first mode; default uniform.
        tactile: tactile pads by link name of the scene's robots, each a
            :class:`~torchcontact.states.TactileArray` in that link's frame (``d = 3``); the
            readings of :meth:`tactile_log_likelihood` are theirs concatenated in this order.
        inconsistency_penalty: log-weight penalty (nats, ``>= 0``; ``inf`` rules such modes
            out) of modes inconsistent at the linearization point; ``0`` disables the gate.
        consistency_tolerance: relative tolerance of the consistency check.
        consistency_gap: gaps (metres) of a mode's contacts that the linearized step and the
            consistency check treat as closed, and depths of the penetrations of its
            separated slots that they treat as touching.
        resolve_slots: a mode fixes the state of each slot group; its slots and sliding
            directions are resolved at the linearization point (see the class docstring).
            :meth:`from_rollout` then merges the modes with the same group states.
        exact_resolution: with :attr:`resolve_slots`, the mode whose group states are
            those of the exact solution at the linearization point takes its slots (see
            the class docstring; one Lemke solve per point and step).
        max_gain: the largest entry of a mode's tangent Jacobian that is taken as a step;
            a mode whose Jacobian exceeds it at the linearization point counts as not solved
            there (see the class docstring). ``inf`` disables the check.
        max_speed_change: the largest velocity change (m/s) of a point of the body that a
            mode's step at the linearization point may make; a mode whose step exceeds it
            counts as not solved there (see Modes ruled out). ``inf`` disables the check.
        particle_penalty: log-weight penalty (nats, ``>= 0``; ``0`` disables it) of a
            particle's child under a mode whose contacts that particle contradicts: a slot the
            mode closes lies more than ``consistency_gap`` from touching at the particle's
            mean, or a candidate slot the mode separates penetrates it by more (see Particles
            checked in the class docstring).
        joint_velocity_sigma: the standard deviation (rad/s, m/s for prismatic joints) of
            the measured velocities of the robots' servo joints at the end of a step
            (``RobotControl.v_robot_next``) about each mode's linearized step; finite, each
            child conditions on them (see Proprioception in the class docstring); ``inf``
            (the default) ignores them.
        compiled: run the linearization's contact assembly through :func:`torch.compile`
            (one graph and its backward; see
            ``torchcontact._compiled``): the first step compiles (minutes on a CPU
            for the BarrettHand scene; cached on disk for later processes), later steps take
            a fraction of the eager time; the results agree with the eager ones to rounding.

    Construction validates every field and raises ``ValueError`` naming the field at fault.
    """

    scene: Scene
    modes: Tensor
    Q: Tensor
    R: Tensor
    transition: Tensor
    initial: Tensor | None = None
    tactile: Mapping[str, TactileArray] = field(default_factory=dict)
    inconsistency_penalty: float = 5.0
    consistency_tolerance: float = 0.05
    consistency_gap: float = 0.003
    resolve_slots: bool = False
    max_gain: float = 1e6
    exact_resolution: bool = True
    particle_penalty: float = 0.0
    max_speed_change: float = math.inf
    joint_velocity_sigma: float = math.inf
    compiled: bool = False

    def __post_init__(self) -> None:
        scene = self.scene
        if self.max_gain != math.inf:  # inf disables the check
            check_real("max_gain", self.max_gain, low=0.0, low_open=True)
        check_real("particle_penalty", self.particle_penalty, low=0.0)
        if self.joint_velocity_sigma != math.inf:  # inf ignores the measured velocities
            check_real("joint_velocity_sigma", self.joint_velocity_sigma, low=0.0, low_open=True)
        if self.max_speed_change != math.inf:  # inf disables the check
            check_real("max_speed_change", self.max_speed_change, low=0.0, low_open=True)
        for name in ("compiled", "exact_resolution"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}: expected a bool, got {getattr(self, name)!r}")
        if not isinstance(scene, Scene) or scene.dimension != 3:
            raise ValueError(f"scene: expected a spatial Scene, got {describe(scene)}")
        if len(scene.dynamic) != 1:
            raise ValueError(
                f"scene: expected exactly one dynamic body (the tracked object), got "
                f"{len(scene.dynamic)}"
            )
        modes, S = self.modes, scene.num_slots
        if (
            not isinstance(modes, Tensor)
            or modes.dtype != torch.long
            or modes.ndim != 2
            or modes.shape[1] != S
            or modes.shape[0] < 1
        ):
            raise ValueError(f"modes: expected a long (K, {S}) tensor, got {describe(modes)}")
        codes = num_modes(scene.friction_directions)
        if bool(((modes < 0) | (modes >= codes)).any()):
            raise ValueError(f"modes: values must lie in [0, {codes})")
        check_gate(
            penalty=self.inconsistency_penalty,
            tolerance=self.consistency_tolerance,
            gap=self.consistency_gap,
        )
        K = int(modes.shape[0])
        for name, value, shapes in (
            ("Q", self.Q, ((TANGENT_DIM, TANGENT_DIM), (K, TANGENT_DIM, TANGENT_DIM))),
            ("R", self.R, ((OBS_TANGENT_DIM, OBS_TANGENT_DIM),)),
        ):
            if not isinstance(value, Tensor) or tuple(value.shape) not in shapes:
                raise ValueError(
                    f"{name}: expected shape {' or '.join(map(str, shapes))}, got {describe(value)}"
                )
            if value.dtype not in FLOAT_DTYPES:
                raise ValueError(f"{name}: expected float32 or float64, got dtype {value.dtype}")
        if self.initial is None:
            uniform = torch.full((K,), 1.0 / K, dtype=self.Q.dtype, device=self.Q.device)
            object.__setattr__(self, "initial", uniform)
        links = {link for member in scene.robots for link in member.robot.link_names}
        if not isinstance(self.tactile, Mapping):
            raise ValueError(
                f"tactile: expected a mapping link -> TactileArray, got {describe(self.tactile)}"
            )
        for link, pads in self.tactile.items():
            if link not in links:
                raise ValueError(f"tactile: {link!r} is not a link of the scene's robots")
            if not isinstance(pads, TactileArray) or pads.dim != 3:
                raise ValueError(
                    f"tactile[{link!r}]: expected a spatial TactileArray, got {describe(pads)}"
                )
        # The remaining checks (dtypes, finiteness, PSD noise, stochastic transition and
        # initial) are those of a linear switching model with the same noise and transition.
        dtype, device = self.Q.dtype, self.Q.device
        LinearSwitchingModel(
            F=torch.zeros(K, TANGENT_DIM, TANGENT_DIM, dtype=dtype, device=device),
            c=torch.zeros(K, TANGENT_DIM, dtype=dtype, device=device),
            Q=self.Q.expand(K, TANGENT_DIM, TANGENT_DIM),
            H=self._H(),
            d=torch.zeros(K, OBS_TANGENT_DIM, dtype=dtype, device=device),
            R=self.R.expand(K, OBS_TANGENT_DIM, OBS_TANGENT_DIM),
            transition=self.transition,
            initial=self.initial,  # type: ignore[arg-type]  # set above
        )

    # ------------------------------------------------------------------------------------------
    # construction from simulated data

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
    ) -> SpatialContactModel:
        """The model of the modes that simulated rollouts of ``scene`` visit.

        The mode table is :func:`collect_modes` of ``rollout.mode``, the transition
        :func:`empirical_transition` of its mode ids, and the first mode's distribution the
        ids' frequencies at the first step, with the same additive ``smoothing`` (with
        ``resolve_slots=True`` among the options, of the slot groups' states: every slot of
        a group takes the group's state, the largest of its slots' states, separated 0,
        sticking 1, sliding 2). The
        rollouts may come from a scene whose robots are servoed (the simulator's); ``scene``
        is the filter's, with the same slots.

        Args:
            scene: the filter's scene (one dynamic body).
            rollout: rollouts with ``rollout.mode`` of shape ``(T, *B, S)``.
            Q: ``(12, 12)`` process noise covariance (or ``(K, 12, 12)``).
            R: ``(6, 6)`` camera noise covariance.
            smoothing: pseudo-count of the transition and first-mode estimates, ``> 0``.
            **options: the model's other fields (``tactile``, ``inconsistency_penalty``, ...).

        Raises:
            ValueError: naming ``rollout`` if it is not a :class:`~torchcontact.sim.Rollout`
                of at least one step, or the field at fault.
        """
        if options.get("resolve_slots", False) and isinstance(rollout, Rollout):
            rollout = dataclasses.replace(rollout, mode=group_states(scene, rollout.mode))
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

    # ------------------------------------------------------------------------------------------
    # the SwitchingModel protocol

    @property
    def state_dim(self) -> int:
        """``13``: position, quaternion, twist."""
        return STATE_DIM

    @property
    def obs_dim(self) -> int:
        """``7``: the camera's pose."""
        return OBS_DIM

    @property
    def manifold(self) -> Manifold:
        """:data:`~torchcontact.filters.SE3`: the state's manifold (12-dim tangent)."""
        return SE3

    @property
    def measurement_manifold(self) -> Manifold:
        """:data:`~torchcontact.filters.SE3`: the camera pose's manifold (6-dim tangent)."""
        return SE3

    def mode_dynamics(self, belief: RBPFBelief, control: RobotControl | None) -> ModeDynamics:
        """Every mode's step linearized at the belief's mixture mean, in tangent coordinates.

        Args:
            belief: the belief at the start of the step, batch ``*B``.
            control: a :class:`RobotControl` with batch ``*B`` (broadcastable), or None when
                the scene has no robot and no kinematic body.

        Returns:
            The :class:`ModeDynamics` with ``F (*B, K, 12, 12)``, ``c (*B, K, 12)``, ``origin``
            the mixture mean ``(*B, 13)``, ``chart`` the most probable mode's step ``(*B, 13)``
            (the mean where that mode is not solved or the point holds),
            ``measurement_chart`` its pose ``(*B, 7)``, the constant noise and camera model
            and the modes' log-weights (see the class docstring).
        """
        mean = belief.mean()
        batch = mean.shape[:-1]
        flat = mean.reshape(-1, STATE_DIM).detach().to(torch.float64)
        ctrl = check_control(self.scene, control, batch, device=self.device)
        likely = belief.mode_marginals().reshape(-1, self.num_modes).argmax(-1)
        lin = self._linearize(flat, ctrl, chart_mode=likely)
        K, dtype = self.num_modes, self.dtype
        chart = lin.chart
        log_weight = gate_log_weight(
            lin.consistent,
            penalty=self.inconsistency_penalty,
            dtype=dtype,
            converged=lin.converged,
            nearly=lin.nearly,
        )
        log_weight = log_weight.masked_fill(lin.held, 0.0)
        noise = self._noise
        F, c, Q = lin.F, lin.c, noise["Q"].to(torch.float64).expand(flat.shape[0], K, -1, -1)
        particle_log_weight = None
        if self.particle_penalty > 0:
            violated = self._contradicted(belief.gaussians.mean, flat, lin)  # (P, N, K)
            particle_log_weight = torch.zeros(violated.shape, dtype=dtype, device=self.device)
            particle_log_weight = particle_log_weight.masked_fill(violated, -self.particle_penalty)
        if self._conditions_on_joints(ctrl):
            assert ctrl.v_robot_next is not None
            F, c, Q, evidence = self._joint_conditioning(belief, flat, ctrl.v_robot_next, lin, Q)
            evidence = evidence.to(dtype)
            particle_log_weight = (
                evidence if particle_log_weight is None else particle_log_weight + evidence
            )
        if particle_log_weight is not None:
            particle_log_weight = particle_log_weight.reshape(
                *batch, *particle_log_weight.shape[1:]
            )
        return ModeDynamics(
            F=F.to(dtype).reshape(*batch, K, TANGENT_DIM, TANGENT_DIM),
            c=c.to(dtype).reshape(*batch, K, TANGENT_DIM),
            Q=Q.to(dtype).reshape(*batch, K, TANGENT_DIM, TANGENT_DIM),
            H=noise["H"],
            d=noise["d"],
            R=noise["R"],
            mode_log_weight=log_weight.reshape(*batch, K),
            particle_log_weight=particle_log_weight,
            origin=mean.detach().reshape(*batch, STATE_DIM),
            chart=chart.to(dtype).reshape(*batch, STATE_DIM),
            measurement_chart=chart[:, :OBS_DIM].to(dtype).reshape(*batch, OBS_DIM),
        )

    # ------------------------------------------------------------------------------------------
    # the step and its linearization

    def step(self, x: Tensor, *, mode: Tensor, control: RobotControl | None = None) -> Tensor:
        """The mode-decoupled step ``f_k(x, u)``, differentiable.

        Args:
            x: ``(*B, 13)`` pose (position, unit quaternion) and twist of the tracked body.
            mode: ``(*B,)`` long mode ids into :attr:`modes`.
            control: the robots' measured motion, batch broadcastable to ``*B``.

        Returns:
            ``(*B, 13)`` the state after the step (in ``x``'s dtype).
        """
        _check_state(x)
        if not isinstance(mode, Tensor) or mode.dtype != torch.long:
            raise ValueError(f"mode: expected a long (*B,) tensor, got {describe(mode)}")
        if bool(((mode < 0) | (mode >= self.num_modes)).any()):
            raise ValueError(f"mode: ids must lie in [0, {self.num_modes})")
        batch = torch.broadcast_shapes(x.shape[:-1], mode.shape)
        ctrl = check_control(self.scene, control, batch, x.dtype, self.device)
        modes = self.modes[mode.expand(batch)].reshape(-1, self.scene.num_slots)
        flat = x.expand(*batch, STATE_DIM).reshape(-1, STATE_DIM)
        v_next = solve_mode(robot_contact_problem(self.scene, flat, ctrl)[0], modes).v_next
        return self._advance(flat, v_next).reshape(*batch, STATE_DIM)

    def linearize(
        self, x: Tensor, *, control: RobotControl | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Every mode's step at ``x``: ``f_k(retract(x, δ)) ≈ retract(f_k(x), F_k δ)``.

        Args:
            x: ``(*B, 13)`` linearization point (pose and twist, world frame).
            control: the robots' measured motion, batch broadcastable to ``*B``.

        Returns:
            ``F (*B, K, 12, 12)`` (each mode's Jacobian in the tangents at ``x`` and at
            ``f_k(x)``), ``f (*B, K, 13)`` the steps and ``(*B, K)`` bool, the mode's
            equalities were solved (its step and Jacobian mean something); float64.
        """
        _check_state(x)
        batch = x.shape[:-1]
        ctrl = check_control(self.scene, control, batch, device=self.device)
        lin = self._linearize(x.reshape(-1, STATE_DIM).detach().to(torch.float64), ctrl)
        K = self.num_modes
        return (
            lin.F.reshape(*batch, K, TANGENT_DIM, TANGENT_DIM),
            lin.f.reshape(*batch, K, STATE_DIM),
            lin.converged.reshape(*batch, K),
        )

    def slot_modes(self, x: Tensor, *, control: RobotControl | None = None) -> Tensor:
        """Every mode's per-slot modes at ``x``: the table's rows, or, with
        :attr:`resolve_slots`, their slots and sliding directions resolved at ``x`` (see the
        class docstring), the contacts each mode's step closes there.

        Args:
            x: ``(*B, 13)`` pose and twist (world frame).
            control: the robots' measured motion, batch broadcastable to ``*B``.

        Returns:
            ``(*B, K, S)`` long per-slot modes (``S = scene.num_slots``).
        """
        _check_state(x)
        batch, K, S = x.shape[:-1], self.num_modes, self.scene.num_slots
        if not self.resolve_slots:
            return self.modes.to(x.device).expand(*batch, K, S)
        ctrl = check_control(self.scene, control, batch, device=self.device)
        flat = x.reshape(-1, STATE_DIM).detach().to(torch.float64)
        _, resolved, _, slots = self._modes_at(flat, ctrl)
        out = torch.zeros(flat.shape[0], K, S, dtype=torch.long, device=x.device)
        out[..., slots] = resolved
        return out.reshape(*batch, K, S)

    def _modes_at(
        self, x: Tensor, control: _Control
    ) -> tuple[ContactProblem, Tensor, Tensor, Tensor]:
        """At ``x (P, 13)``: the contact problem on the slots that some mode activates, per
        mode ``(P, K)``; every mode's slots there ``(P, K, S_a)`` (resolved with
        :attr:`resolve_slots`); ``(P, K)`` bool, the mode is reachable there; and the acting
        slots ``(S_a,)``. Eager, the assembly also reads the scene's bodies into the
        simulator's cached layout before the compiled replicas' (building it there would split
        the graph)."""
        P, K = x.shape[0], self.num_modes
        slots = self._acting_slots.to(x.device)
        modes = self.modes.to(x.device).index_select(1, slots).expand(P, K, -1)
        with torch.no_grad():
            at_x = _per_mode(
                _select_slots(robot_contact_problem(self.scene, x, control)[0], slots), K
            )
            reachable = torch.ones(P, K, dtype=torch.bool, device=x.device)
            if self.resolve_slots and slots.numel() > 0:
                modes, reachable = self._resolved(at_x, modes, slots)
        return at_x, modes, reachable, slots

    def _linearize(
        self, x: Tensor, control: _Control, chart_mode: Tensor | None = None
    ) -> _Linearization:
        """Every mode at ``x (P, 13)`` (float64): the steps, the Jacobians and the gate.

        ``chart_mode (P,)``: express every mode's step in the tangent at the step of that
        mode (``c`` its offsets); None: each mode's in its own (``c = 0``). The contact
        problem is assembled once per point (it does not depend on the mode) and reduced to
        the slots that some mode activates (the others are separated in every mode and carry
        no impulse: the same steps); every mode is resolved, solved and gated there. Only the
        solved modes are differentiated (the others' ``F`` and ``c`` are placeholders): their
        tangent replicas are assembled by :func:`_replica_problems` and stepped by
        :func:`_tangent_steps`. With :attr:`compiled`, the replicas' assembly runs as a
        compiled graph and its derivative as its compiled backward; the mode solves run
        eagerly.
        """
        P, K, D = x.shape[0], self.num_modes, TANGENT_DIM
        at_x, modes, reachable, slots = self._modes_at(x, control)
        with torch.no_grad():
            # (P, K) at x with the gaps of each mode's contacts closed: the step and the check
            problem = self._closed_gaps(at_x, modes)
            solution = solve_mode_unchecked(problem, modes)
            if self.inconsistency_penalty > 0:
                # Judged on the split of the impulses that satisfies the mode, where the
                # redundant rows of a grasp leave one (the kinematic fingers take any).
                split = redistribute_impulses(problem, solution, atol=self.consistency_tolerance)
                consistent = is_consistent(problem, split, atol=self.consistency_tolerance)
                loose = min(10 * self.consistency_tolerance, 1.0)
                nearly = is_consistent(problem, split, atol=loose)
            else:
                consistent = torch.ones_like(solution.status.converged)
                nearly = consistent
            f = self._advance(x.unsqueeze(1), solution.v_next)  # (P, K, 13)
            # Solved: converged, or consistent and solving the contact problem (a grasp's
            # redundant rows stall the equality residual above the solver's tolerance).
            residual = relative_residual(
                problem, v_next=solution.v_next, pn=solution.pn, pt=solution.pt
            )
            converged = solution.status.converged | (consistent & (residual <= SOLVED_RESIDUAL))
            converged = converged & reachable & self._plausible(x, solution.v_next)
        if chart_mode is None:
            chart = f
        else:
            # The chart mode's step, or the point itself where that mode is not solved (its
            # step means nothing and would carry every mode's offset c with it).
            index = chart_mode.to(x.device)[:, None]
            chart_point = torch.where(
                converged.gather(1, index),
                f.gather(1, index[..., None].expand(P, 1, STATE_DIM))[:, 0],
                x,
            )
            chart = chart_point[:, None].expand(P, K, STATE_DIM)
        # The solved (point, mode) pairs, the only ones whose Jacobian is used.
        point, mode = converged.nonzero(as_tuple=True)  # (Q,), (Q,)
        F = torch.eye(D, dtype=x.dtype, device=x.device).repeat(P, K, 1, 1)
        c = x.new_zeros(P, K, D)
        J = self.scene.num_servo_joints if self._conditions_on_joints(control) else 0
        G = x.new_zeros(P, K, J, D)
        if point.numel() > 0:
            F[point, mode], c[point, mode], G[point, mode] = self._solved_jacobians(
                x, control, slots, (point, mode), problem, solution, modes, chart
            )
        # A mode whose derivative is singular at the point is not solved there.
        converged = converged & (F.abs().amax((-2, -1)) <= self.max_gain)
        # A point with no solved mode (with the inconsistent modes ruled out: none that passes
        # even the loose check) holds its state for the step: every mode the identity. The
        # step of a mode that contradicts itself extrapolates its Jacobian, which a nearly
        # singular system makes arbitrarily large.
        usable = converged & nearly if math.isinf(self.inconsistency_penalty) else converged
        stranded = ~usable.any(-1, keepdim=True)  # (P, 1)
        kept = converged & ~stranded
        # Placeholders where the mode is ruled out (its weight is -inf) or the point holds.
        eye = torch.eye(D, dtype=x.dtype, device=x.device)
        F = torch.where(
            kept[..., None, None] & F.isfinite().all(-1).all(-1)[..., None, None], F, eye
        )
        c = torch.where(kept[..., None] & c.isfinite().all(-1, keepdim=True), c, 0.0)
        f = torch.where(kept[..., None], f, x.unsqueeze(1))
        chart = torch.where(stranded[..., None], x.unsqueeze(1), chart)
        return _Linearization(
            F=F,
            f=f,
            c=c,
            chart=chart[:, 0],
            converged=converged,
            consistent=consistent,
            nearly=nearly,
            held=stranded,
            v_servo=solution.v_next[..., 6:],
            G=G,
            touching=modes >= 1,
            phi=at_x.phi[:, 0],
            Jn=at_x.Jn[:, 0, :, :6],  # the body's columns (servo joints after)
            candidate=at_x.slot_mask[:, 0],
        )

    def _conditions_on_joints(self, control: _Control) -> bool:
        """Whether the step conditions on the servo joints' measured velocities (see
        Proprioception in the class docstring)."""
        return (
            self.joint_velocity_sigma != math.inf
            and self.scene.num_servo_joints > 0
            and control.v_robot_next is not None
        )

    def _joint_conditioning(
        self, belief: RBPFBelief, x: Tensor, v_robot_next: Tensor, lin: _Linearization, Q: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Every mode's step conditioned on the servo joints' measured velocities
        ``v_robot_next (P, Nj)``: ``F (P, K, 12, 12)``, ``c (P, K, 12)``, ``Q (P, K, 12, 12)``
        (from ``lin`` and ``Q``), and ``(P, N, K)`` each child's log-likelihood of the
        measurement (see Proprioception in the class docstring); float64."""
        P, J = x.shape[0], self.scene.num_servo_joints
        G, g = lin.G, lin.v_servo  # (P, K, J, 12), (P, K, J)
        R = (self.joint_velocity_sigma**2) * torch.eye(J, dtype=x.dtype, device=x.device)
        cov = belief.cov().detach().reshape(P, 1, TANGENT_DIM, TANGENT_DIM).to(x.dtype)
        S = G @ cov @ G.transpose(-1, -2) + R  # (P, K, J, J)
        gain = torch.linalg.solve(S, G @ cov).transpose(-1, -2)  # (P, K, 12, J)
        residual = servo_velocities(self.scene, v_robot_next)[:, None] - g  # (P, K, J)
        eye = torch.eye(TANGENT_DIM, dtype=x.dtype, device=x.device)
        solved = (lin.converged & ~lin.held)[..., None, None]
        F = torch.where(solved, lin.F @ (eye - gain @ G), lin.F)
        c = torch.where(
            solved[..., 0], lin.c + (lin.F @ (gain @ residual[..., None]))[..., 0], lin.c
        )
        spread = lin.F @ gain
        Q = torch.where(solved, Q + spread @ R @ spread.transpose(-1, -2), Q)
        # each child's likelihood with its own mean and covariance (tangent at the mean)
        means = belief.gaussians.mean.detach().reshape(P, -1, STATE_DIM).to(x.dtype)
        offset = SE3.local(x[:, None].expand_as(means), means)  # (P, N, 12)
        covs = belief.gaussians.cov.detach().reshape(P, -1, TANGENT_DIM, TANGENT_DIM)
        G_n = G[:, None]  # (P, 1, K, J, 12)
        S_n = G_n @ covs.to(x.dtype)[:, :, None] @ G_n.transpose(-1, -2) + R  # (P, N, K, J, J)
        r = residual[:, None] - (G_n @ offset[:, :, None, :, None])[..., 0]  # (P, N, K, J)
        chol = torch.linalg.cholesky(S_n)
        white = torch.linalg.solve_triangular(chol, r[..., None], upper=False)[..., 0]
        log_det = 2 * chol.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        evidence = -0.5 * (white.pow(2).sum(-1) + log_det + J * math.log(2 * math.pi))
        # where the mode is not solved its velocities mean nothing (and it is ruled out)
        evidence = torch.where(solved[..., 0, 0][:, None], evidence, 0.0)
        return F, c, Q, evidence

    def _plausible(self, x: Tensor, v_next: Tensor) -> Tensor:
        """``(P, K)`` bool: no point of the body changes its velocity by more than
        :attr:`max_speed_change` in the step from ``x (P, 13)`` to the twists ``v_next
        (P, K, 6)`` (bounded by ``|Δv| + |Δω| r``, ``r`` the body's bounding radius)."""
        if self.max_speed_change == math.inf:
            return torch.ones(v_next.shape[:-1], dtype=torch.bool, device=v_next.device)
        change = v_next[..., :6] - x[:, None, 7:]  # the body's twist (servo joints after)
        shape: object = self.scene.bodies[self.scene.dynamic[0]].shape
        assert isinstance(shape, Box | Sphere | Capsule)  # a spatial scene's dynamic body
        radius = shape.bounding_radius
        speed: Tensor = change[..., :3].norm(dim=-1) + radius * change[..., 3:].norm(dim=-1)
        return speed.le(self.max_speed_change)

    def _contradicted(self, particles: Tensor, x: Tensor, lin: _Linearization) -> Tensor:
        """``(P, N, K)`` bool: mode ``k``'s contacts at ``x (P, 13)`` contradict particle
        ``i``'s mean ``particles (*B, N, 13)`` (see :attr:`particle_penalty`); False where
        the point holds its state."""
        P = x.shape[0]
        mu = particles.detach().reshape(P, -1, STATE_DIM).to(x.dtype)
        delta = SE3.local(x[:, None].expand_as(mu), mu)  # (P, N, 12)
        turn = torch.einsum("pij,pnj->pni", quat_to_matrix(x[:, 3:7]), delta[..., 3:6])
        offset = torch.cat([delta[..., :3], turn], dim=-1)  # (P, N, 6), world frame
        phi = lin.phi[:, None] + torch.einsum("psj,pnj->pns", lin.Jn, offset)  # (P, N, S_a)
        gap = self.consistency_gap
        apart = (phi > gap)[:, :, None] & lin.touching[:, None]  # (P, N, K, S_a)
        inside = ((phi < -gap) & lin.candidate[:, None])[:, :, None] & ~lin.touching[:, None]
        return (apart | inside).any(-1) & ~lin.held[:, None]

    def _solved_jacobians(
        self,
        x: Tensor,
        control: _Control,
        slots: Tensor,
        pairs: tuple[Tensor, Tensor],
        problem: ContactProblem,
        solution: Solution,
        modes: Tensor,
        chart: Tensor,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """The Jacobians ``F (Q, 12, 12)`` and offsets ``c (Q, 12)`` of the ``pairs`` of
        :meth:`_linearize`, ``(Q,)`` point and ``(Q,)`` mode indices (non-empty), from its
        closed-gap ``problem`` and ``solution`` at ``x``, batch ``(P, K)``, its resolved
        ``modes (P, K, S_a)`` and charts ``(P, K, 13)``; and ``G (Q, J, 12)``, the Jacobians
        of the servo joints' velocities at the end of the step (``J = 0`` unless
        :meth:`_conditions_on_joints`).

        One assembly: a batch of Q·(12 + J) points retract(x, δ), δ = 0 requiring grad, whose
        values are the problems at x and whose derivatives along δ are taken by reverse-mode
        differentiation (faster here than forward mode): replica (q, i) yields row i of pair
        q's Jacobian, replica (q, 12 + j) row j of its joint velocities' Jacobian.
        """
        D, Q = TANGENT_DIM, pairs[0].numel()
        J = self.scene.num_servo_joints if self._conditions_on_joints(control) else 0
        if self.compiled:
            # Compiled with static shapes, each new number of pairs would compile anew (about
            # a minute on a CPU): the pairs are padded (repeating the first) to the next power
            # of two, at most P·K, so that a filter compiles at most log2(P·K) + 1 variants,
            # each once per process (cached on disk for later ones). All P·K pairs, one
            # variant, would assemble and differentiate every mode at every step.
            size = min(x.shape[0] * self.num_modes, 1 << (Q - 1).bit_length())
            take = torch.arange(size, device=x.device)
            take[Q:] = 0
            pairs = (pairs[0][take], pairs[1][take])
        point = pairs[0]
        ctrl = control.select(point)
        # Static shapes (a filter's K and batch do not change; the pairs are padded), the
        # Python wrapper (the C++ one takes about 1.7 times as long to compile).
        assemble = kernel(
            _replica_problems, compiled=self.compiled, cpp_wrapper=False, dynamic=False
        )
        with torch.enable_grad():
            delta = x.new_zeros(point.numel(), 1, D + J, D).requires_grad_()
            moved, fields = assemble(
                self.scene,
                x.index_select(0, point),
                delta,
                slots,
                q_robot=ctrl.q_robot,
                v_robot=ctrl.v_robot,
                robot_base=ctrl.robot_base,
                base_twist=ctrl.base_twist,
                q_kinematic=ctrl.q_kinematic,
                v_kinematic=ctrl.v_kinematic,
                joint_command=ctrl.joint_command,
                v_robot_next=ctrl.v_robot_next,
            )
            # Eager: compiled, its backward through the Tikhonov iterations' LU solves runs as
            # triangular solves on every replica's full system, slower than eager with many
            # modes (BarrettHand, K = 16: 133 ms per backward against ~40 ms eager).
            local, joints = _tangent_steps(
                self,
                moved,
                fields,
                problem.phi[pairs][:, None],
                modes[pairs][:, None],
                chart[pairs][:, None],
                solution.pn[pairs][:, None],
                solution.pt[pairs][:, None],
            )
            rows = local[:, :, :D].diagonal(dim1=-2, dim2=-1).sum()
            if J:
                rows = rows + joints[:, :, D:].diagonal(dim1=-2, dim2=-1).sum()
            (grad,) = torch.autograd.grad(rows, delta)
        return grad[:Q, 0, :D], local.detach()[:Q, 0, 0], grad[:Q, 0, D:]

    def _closed_gaps(self, problem: ContactProblem, modes: Tensor) -> ContactProblem:
        """The problem of the consistency check: the gaps of the mode's contacts closed up to
        ``consistency_gap``, the penetrations of its separated slots up to that depth taken
        as touching (see the class docstring). It runs on the slots that some mode
        activates (a slot that none does would make every mode inconsistent alike)."""
        gap, phi = self.consistency_gap, problem.phi
        return _with_phi(
            problem, torch.where(modes >= 1, phi - phi.clamp(-gap, gap), phi - phi.clamp(-gap, 0.0))
        )

    def _resolved(
        self, problem: ContactProblem, modes: Tensor, slots: Tensor
    ) -> tuple[Tensor, Tensor]:
        """The slots and sliding directions of group-state ``modes (P, K, S_a)`` resolved
        at ``problem`` (on the acting ``slots``), and ``(P, K)`` bool, every touching group
        has a slot within the gap (see the class docstring)."""
        groups = slot_group_ids(self.scene).to(modes.device).index_select(0, slots)  # (S_a,)
        near = problem.phi <= self.consistency_gap
        touching = modes >= 1
        resolved = torch.where(touching & near, modes, SEPARATED)
        wanted = _group_max(touching.long(), groups) > 0
        found = _group_max((touching & near).long(), groups) > 0
        reachable = (found | ~wanted).all(-1)
        # one round: the slots that would pull separate
        closed = self._closed_gaps(problem, resolved)
        corrected = update_mode(closed, solve_mode_unchecked(closed, resolved))
        resolved = torch.where((resolved >= 1) & (corrected == SEPARATED), SEPARATED, resolved)
        resolved = _resolved_sliding(self._closed_gaps(problem, resolved), resolved)
        if not self.exact_resolution:
            return resolved, reachable
        exact, solved = _physics_modes(problem[:, 0])  # (P, S_a), (P,)
        # the modes whose group states are those of the physics' answer take its slots
        wanted_states = _group_max(modes.clamp(max=SLIDING), groups)  # (P, K, G)
        exact_states = _group_max(exact.clamp(max=SLIDING), groups)  # (P, G)
        match = (wanted_states == exact_states[:, None]).all(-1) & solved[:, None]  # (P, K)
        resolved = torch.where(match[..., None], exact[:, None], resolved)
        return resolved, reachable | match

    def _advance(self, x: Tensor, v_next: Tensor) -> Tensor:
        """``(*P, 13)``: the pose integrated over the step with the twist ``v_next (*P, 6)``
        (``x (*P', 13)`` broadcast against it)."""
        batch = torch.broadcast_shapes(x.shape[:-1], v_next.shape[:-1])
        x = x.expand(*batch, STATE_DIM)
        pose = integrate_poses(x[..., None, :7], v_next[..., None, :6], self.scene.h)[..., 0, :]
        return torch.cat([pose, v_next[..., :6]], dim=-1)

    @property
    def _acting_slots(self) -> Tensor:
        """``(S_a,)`` long: the slots that some mode activates."""
        return (self.modes >= 1).any(0).nonzero().squeeze(-1)

    # ------------------------------------------------------------------------------------------
    # tactile evidence

    def tactile_log_likelihood(
        self, readings: Tensor, *, pose: Tensor, control: RobotControl | None = None
    ) -> Tensor:
        """``log p(readings | mode k)`` of the pads on the robot's links, for every mode.

        Mode ``k`` touches at its active robot slots (``modes[k] >= 1`` and a candidate slot
        at ``pose``); a pad is triggered when such a contact point lies within its radius and
        the contact normal within its cone (:class:`~torchcontact.states.TactileArray`, every
        active contact taken to carry load), and reads ``True`` up to the array's
        false-positive and false-negative rates, independently across pads.

        Args:
            readings: ``(*B, S_t)`` bool readings, the arrays of :attr:`tactile` concatenated
                in order.
            pose: ``(*B, 7)`` the tracked body's pose at which the contacts are placed (e.g.
                the belief's mean pose before the step).
            control: the robots' joint positions and base poses.

        Returns:
            ``(*B, K)`` log-likelihoods, the filter's dtype; pass as the RBPF step's
            ``extra_log_likelihood``.
        """
        total = sum(pads.num_sensors for pads in self.tactile.values())
        if not isinstance(pose, Tensor) or not pose.is_floating_point() or pose.shape[-1:] != (7,):
            raise ValueError(f"pose: expected a floating (*B, 7) tensor, got {describe(pose)}")
        if not bool(torch.isfinite(pose).all()):
            raise ValueError("pose: contains NaN or inf")
        if (
            not isinstance(readings, Tensor)
            or readings.dtype != torch.bool
            or readings.shape[-1:] != (total,)
        ):
            raise ValueError(
                f"readings: expected a bool (*B, {total}) tensor, got {describe(readings)}"
            )
        batch = torch.broadcast_shapes(pose.shape[:-1], readings.shape[:-1])
        P = math.prod(batch)
        ctrl = check_control(self.scene, control, batch, device=self.device)
        x = torch.cat(
            [pose.to(torch.float64).expand(*batch, 7).reshape(P, 7), pose.new_zeros(P, 6).double()],
            dim=-1,
        )
        _, geometry = robot_contact_problem(self.scene, x, ctrl)
        acting, which = self._acting_sets  # (U, S), (K,)
        U = acting.shape[0]
        # the slots each set activates at this pose: resolved slots are within the gap
        near = (geometry.phi <= self.consistency_gap) | (not self.resolve_slots)  # (P, S)
        acting = acting * near[:, None].long()  # (P, U, S)
        log_lik = x.new_zeros(P, U)
        flat_readings = readings.expand(*batch, total).reshape(P, total)
        start = 0
        for pads, slots, (member, frame) in self._pad_slots:
            origin, rotation = self._link_frame(ctrl, member, frame)  # (P, 3), (P, 3, 3)
            # In the link's frame: robot slots' normals point from the box into the link's
            # primitive, i.e. into the body that carries the pads, as TactileArray expects.
            points = (geometry.points[:, slots] - origin[:, None]) @ rotation
            normals = geometry.normals[:, slots] @ rotation
            L, dtype = len(slots), pads.positions.dtype
            contacts = ContactSet(
                points=points.unsqueeze(1).expand(P, U, L, 3).to(dtype),
                normals=normals.unsqueeze(1).expand(P, U, L, 3).to(dtype),
                pn=torch.ones(P, U, L, dtype=dtype, device=x.device),
                mode=acting[..., slots],
                partner=torch.zeros(L, dtype=torch.long, device=x.device),
                partner_kind=[PartnerKind.ENVIRONMENT],
                mask=geometry.active[:, slots].unsqueeze(1).expand(P, U, L),
            )
            triggers = pads.triggered(contacts)  # (P, U, S_l)
            read = flat_readings[:, start : start + pads.num_sensors].unsqueeze(1)
            start += pads.num_sensors
            log_lik = log_lik + pads.reading_log_likelihood(read, triggers).to(log_lik.dtype)
        return log_lik.index_select(-1, which).reshape(*batch, self.num_modes).to(self.dtype)

    # ------------------------------------------------------------------------------------------

    def _H(self) -> Tensor:
        """``(K, 6, 12)``: the camera measures the pose's tangent, in every mode."""
        H = self.Q.new_zeros(OBS_TANGENT_DIM, TANGENT_DIM)
        H[:, :OBS_TANGENT_DIM] = torch.eye(
            OBS_TANGENT_DIM, dtype=self.Q.dtype, device=self.Q.device
        )
        return H.expand(self.num_modes, OBS_TANGENT_DIM, TANGENT_DIM)

    @property
    def _noise(self) -> dict[str, Tensor]:
        K = self.num_modes
        return {
            "Q": self.Q.expand(K, TANGENT_DIM, TANGENT_DIM),
            "H": self._H(),
            "d": self.Q.new_zeros(OBS_TANGENT_DIM).expand(K, OBS_TANGENT_DIM),
            "R": self.R.expand(K, OBS_TANGENT_DIM, OBS_TANGENT_DIM),
        }

    @property
    def _acting_sets(self) -> tuple[Tensor, Tensor]:
        """The distinct sets of slots the modes activate ``(U, S)`` long, and each mode's."""
        sets, which = torch.unique((self.modes >= 1).to(torch.long), dim=0, return_inverse=True)
        return sets, which

    @property
    def _pad_slots(self) -> list[tuple[TactileArray, list[int], tuple[int, int]]]:
        """Per tactile link: its pads, the slots of its collision primitives against the
        tracked body, and ``(robot index, link index)``."""
        out = []
        for link, pads in self.tactile.items():
            robot = next(r for r, m in enumerate(self.scene.robots) if link in m.robot.link_names)
            shapes = self.scene.robots[robot].robot.collision_shapes
            slots = [
                slot
                for group in self.scene.robot_slot_groups
                if group.robot == robot and shapes[group.shape].link == link
                for slot in range(group.start, group.start + group.count)
            ]
            out.append(
                (pads, slots, (robot, self.scene.robots[robot].robot.link_names.index(link)))
            )
        return out

    def _link_frame(self, control: _Control, member: int, frame: int) -> tuple[Tensor, Tensor]:
        """``(P, 3)`` origin and ``(P, 3, 3)`` rotation (link to world) of a robot's link."""
        robot = self.scene.robots[member].robot
        start = sum(m.dof for m in self.scene.robots[:member])
        q = control.q_robot[:, start : start + robot.dof]
        transform = robot.forward_kinematics(q, robot.link_names[frame])  # (P, 4, 4)
        base = control.robot_base[:, member]
        turn = quat_to_matrix(base[:, 3:])
        origin = (turn @ transform[:, :3, 3:]).squeeze(-1) + base[:, :3]
        return origin, turn @ transform[:, :3, :3]


def slot_group_ids(scene: Scene) -> Tensor:
    """``(S,)`` long: the index of each slot's group, the scene's
    :attr:`~torchcontact.sim.Scene.slot_groups` then its robots' groups in order."""
    ids = torch.empty(scene.num_slots, dtype=torch.long)
    spans = [(g.start, g.count) for g in scene.slot_groups]
    spans += [(g.start, g.count) for g in scene.robot_slot_groups]
    for index, (start, count) in enumerate(spans):
        ids[start : start + count] = index
    return ids


def group_states(scene: Scene, modes: Tensor) -> Tensor:
    """``modes (..., S)`` with every slot set to its group's state: the largest of the
    group's slots' states (separated 0, sticking 1, sliding 2: every sliding code is 2).

    Args:
        scene: the scene whose slots ``modes`` encodes.
        modes: ``(..., S)`` long per-slot modes.

    Returns:
        ``(..., S)`` long.
    """
    ids = slot_group_ids(scene).to(modes.device)
    return _group_max(modes.clamp(max=SLIDING), ids).index_select(-1, ids)


def _group_max(values: Tensor, groups: Tensor) -> Tensor:
    """``(..., G)`` the largest of ``values (..., S)`` (non-negative integers) over each
    group's slots, ``groups (S,)`` their group ids (0 for a group without slots here)."""
    G = int(groups.max()) + 1 if groups.numel() else 0
    per_group = values.new_zeros(*values.shape[:-1], G)
    return per_group.scatter_reduce(-1, groups.expand_as(values), values, "amax")


def _physics_modes(problem: ContactProblem) -> tuple[Tensor, Tensor]:
    """The contact modes ``(P, S)`` of the exact (Lemke) solutions of ``problem (P,)`` with
    its penetrations taken as touching (gaps clamped at zero), and ``(P,)`` bool, solved."""
    solution = solve_lemke(_with_phi(problem, problem.phi.clamp(min=0.0)))
    return solution.mode, solution.status.converged


def _resolved_sliding(problem: ContactProblem, modes: Tensor) -> Tensor:
    """``modes (*B, S)`` with each sliding slot's friction direction resolved at ``problem``
    (see the class docstring: the direction most opposed to the slip of the step with the
    sliding slots frictionless, then one edge/face correction)."""
    sliding = is_sliding(modes)
    frictionless = _with_mu(problem, torch.where(sliding, 0.0, problem.mu))
    v_next = solve_mode_unchecked(frictionless, modes).v_next
    slip = (problem.Jt @ v_next[..., None, :, None]).squeeze(-1) + problem.b_tangent
    modes = torch.where(sliding, SLIDING + slip.argmin(-1), modes)
    corrected = update_mode(problem, solve_mode_unchecked(problem, modes))
    return torch.where(sliding & is_sliding(corrected), corrected, modes)


#: Largest relative LCP residual (:func:`~torchcontact.contact.relative_residual`) of a mode
#: solve that did not converge but is consistent and taken as solved: the step's velocities
#: and impulses are off by at most that share of the problem's scales. Equalities that
#: contradict each other leave residuals of the order of the scales; a grasp's redundant rows
#: stall the iterations at 1e-5 to 1e-2 of them (BarrettHand on a box).
SOLVED_RESIDUAL = 1e-2


def _select_slots(problem: ContactProblem, slots: Tensor) -> ContactProblem:
    """The problem ``(*B,)`` restricted to ``slots (S_a,)``."""
    return ContactProblem.unchecked(
        M=problem.M,
        v=problem.v,
        f=problem.f,
        Jn=problem.Jn.index_select(-2, slots),
        Jt=problem.Jt.index_select(-3, slots),
        phi=problem.phi.index_select(-1, slots),
        mu=problem.mu.index_select(-1, slots),
        h=problem.h,
        mask=problem.slot_mask.index_select(-1, slots),
        bn=problem.b_normal.index_select(-1, slots),
        bt=problem.b_tangent.index_select(-2, slots),
    )


def _per_mode(problem: ContactProblem, K: int) -> ContactProblem:
    """A problem ``(P,)`` repeated for ``K`` modes: ``(P, K)`` (views)."""
    return problem.map_tensors(lambda t: t.unsqueeze(1).expand(t.shape[0], K, *t.shape[1:]))


def _with_phi(problem: ContactProblem, phi: Tensor) -> ContactProblem:
    """The problem with the gaps ``phi``."""
    return _replaced(problem, phi=phi, mu=problem.mu)


def _with_mu(problem: ContactProblem, mu: Tensor) -> ContactProblem:
    """The problem with the friction coefficients ``mu``."""
    return _replaced(problem, phi=problem.phi, mu=mu)


def _replaced(problem: ContactProblem, *, phi: Tensor, mu: Tensor) -> ContactProblem:
    """The problem with the gaps ``phi`` and friction coefficients ``mu``."""
    return ContactProblem.unchecked(
        M=problem.M,
        v=problem.v,
        f=problem.f,
        Jn=problem.Jn,
        Jt=problem.Jt,
        phi=phi,
        mu=mu,
        h=problem.h,
        mask=problem.slot_mask,
        bn=problem.b_normal,
        bt=problem.b_tangent,
    )


def _replica_problems(
    scene: Scene, x: Tensor, delta: Tensor, slots: Tensor, **control: Tensor | None
) -> tuple[Tensor, dict[str, Tensor]]:
    """The points ``retract(x, δ)`` ``(P, K, 12, 13)`` and the fields of their contact
    problems on the acting ``slots``, batch ``(P, K, 12)`` (``ContactProblem.unchecked``'s
    keywords): the first differentiated part of ``SpatialContactModel._solved_jacobians``.

    Args:
        scene: the model's scene.
        x: ``(P, 13)`` the linearization points.
        delta: ``(P, K, 12, 12)`` tangent displacements (zeros that require grad).
        slots: ``(S_a,)`` long, the acting slots.
        **control: the fields of :class:`_Control`, flat batch ``(P, ...)``.
    """
    P, K, D = delta.shape[:3]
    moved = SE3.retract(x[:, None, None, :].expand(P, K, D, STATE_DIM), delta)
    assembled, _ = robot_contact_problem(
        scene,
        moved.reshape(-1, STATE_DIM),
        _Control(**control).expand(K * D),  # type: ignore[arg-type]  # the fields
    )
    problem = _select_slots(assembled, slots).reshape(P, K, D)
    names = ("M", "v", "f", "Jn", "Jt", "phi", "mu", "mask", "bn", "bt")
    return moved, {name: getattr(problem, name) for name in names}


def _tangent_steps(
    model: SpatialContactModel,
    moved: Tensor,
    fields: dict[str, Tensor],
    closed_phi: Tensor,
    modes: Tensor,
    chart: Tensor,
    pn: Tensor,
    pt: Tensor,
) -> tuple[Tensor, Tensor]:
    """``local(chart, f_k(retract(x, δ)))`` ``(P, K, R, 12)``: every mode's step from the
    ``R`` replicas, in the tangent at the chart, the mode solves warm-started at the
    converged impulses at ``x`` (see the class docstring), and ``(P, K, R, J)`` the servo
    joints' velocities at the end of those steps: the second differentiated part of
    ``SpatialContactModel._solved_jacobians`` (eager in both modes).

    Args:
        model: the model (its scene).
        moved: ``(P, K, R, 13)`` the replicas' points.
        fields: their problems' fields (:func:`_replica_problems`).
        closed_phi: ``(P, K, S_a)`` the gaps at ``x`` with the mode's contacts closed (the
            replicas' gaps are shifted by the closing at ``x``, held: no derivative).
        modes: ``(P, K, S_a)`` long, the modes on the acting slots.
        chart: ``(P, K, 13)`` each mode's chart.
        pn: ``(P, K, S_a)``, ``pt (P, K, S_a, D)`` the converged impulses at ``x``.
    """
    P, K, D = moved.shape[:3]
    problem_d = ContactProblem.unchecked(h=model.scene.h, **fields)
    closing = (closed_phi - problem_d.phi[:, :, 0].detach()).unsqueeze(2)
    start = (pn.unsqueeze(2).expand(P, K, D, -1), pt.unsqueeze(2).expand(P, K, D, *pt.shape[-2:]))
    v_next = solve_mode_unchecked(
        _with_phi(problem_d, problem_d.phi + closing),
        modes.unsqueeze(2).expand(P, K, D, -1),
        initial_impulses=start,
    ).v_next
    stepped = model._advance(moved, v_next)  # (P, K, R, 13)
    return SE3.local(chart.unsqueeze(2).expand_as(stepped), stepped), v_next[..., 6:]


def _check_state(x: object) -> None:
    """Raise unless ``x`` is a finite floating ``(*B, 13)`` pose-and-twist tensor."""
    if not isinstance(x, Tensor) or not x.is_floating_point() or x.shape[-1:] != (STATE_DIM,):
        raise ValueError(f"x: expected a floating (*B, {STATE_DIM}) tensor, got {describe(x)}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError("x: contains NaN or inf")
    norm = torch.linalg.vector_norm(x[..., 3:7], dim=-1)
    if bool(((norm - 1).abs() > 1e-6).any()):
        raise ValueError("x: the quaternion x[..., 3:7] must have unit norm")


def robot_contact_problem(
    scene: Scene, x: Tensor, control: _Control
) -> tuple[ContactProblem, SlotGeometry]:
    """The contact problem ``(P,)`` of the tracked body's flat states ``x (P, 13)`` in
    ``scene`` under ``control``, and its slot geometry (unclamped gaps)."""
    P = x.shape[0]
    state = SceneState(
        q=x[:, None, :7],
        v=x[:, None, 7:],
        q_kinematic=control.q_kinematic.to(x.dtype),
        mode=torch.zeros(P, scene.num_slots, dtype=torch.long, device=x.device),
        q_robot=control.q_robot.to(x.dtype),
        v_robot=control.v_robot.to(x.dtype),
        robot_base=control.robot_base.to(x.dtype),
    )
    return contact_problem(
        scene,
        state,
        control=None if control.v_kinematic is None else control.v_kinematic.to(x.dtype),
        joint_command=(
            (control.v_robot if control.joint_command is None else control.joint_command).to(
                x.dtype
            )
            if scene.robots
            else None
        ),
        base_twist=None if control.base_twist is None else control.base_twist.to(x.dtype),
    )


def servo_velocities(scene: Scene, v_robot: Tensor) -> Tensor:
    """``(*B, J)``: the servo joints' entries of the robots' joint velocities ``v_robot
    (*B, Nj)`` (robots in scene order), in the order of the contact problem's columns after
    the dynamic bodies' twists."""
    columns = torch.tensor(scene.servo_columns, dtype=torch.long, device=v_robot.device)
    return v_robot.index_select(-1, columns)


def check_control(
    scene: Scene,
    control: RobotControl | None,
    batch: torch.Size,
    dtype: torch.dtype = torch.float64,
    device: torch.device | None = None,
) -> _Control:
    """A :class:`RobotControl` of ``scene`` checked and broadcast to the flat batch
    ``(prod(batch),)``, in ``dtype`` (``ValueError`` naming the field at fault)."""
    Nj, R, Nk = scene.num_robot_joints, len(scene.robots), len(scene.kinematic)
    P = math.prod(batch)
    if control is None:
        if Nj or Nk:
            raise ValueError("control: required, the scene has robots or kinematic bodies")
        empty = torch.zeros(0, dtype=dtype, device=device)
        control = RobotControl(q_robot=empty, v_robot=empty)
    if not isinstance(control, RobotControl):
        raise ValueError(f"control: expected a RobotControl, got {type(control).__name__}")
    bases = [member.base_pose for member in scene.robots]
    default_base = (
        torch.stack([b for b in bases if b is not None]) if R else torch.zeros(0, 7)
    ).to(dtype=dtype, device=device)
    fields: dict[str, tuple[Tensor | None, tuple[int, ...], bool]] = {
        "q_robot": (control.q_robot, (Nj,), True),
        "v_robot": (control.v_robot, (Nj,), True),
        "robot_base": (control.robot_base, (R, 7), False),
        "base_twist": (control.base_twist, (R, 6), False),
        "q_kinematic": (control.q_kinematic, (Nk, 7), Nk > 0),
        "v_kinematic": (control.v_kinematic, (Nk, 6), False),
        "joint_command": (control.joint_command, (Nj,), scene.num_servo_joints > 0),
        "v_robot_next": (control.v_robot_next, (Nj,), False),
    }
    out: dict[str, Tensor | None] = {}
    for name, (value, event, required) in fields.items():
        if value is None:
            if required:
                raise ValueError(f"control.{name}: required for this scene")
            out[name] = None
            continue
        if (
            not isinstance(value, Tensor)
            or not value.is_floating_point()
            or tuple(value.shape[value.ndim - len(event) :]) != event
            or value.ndim < len(event)
        ):
            raise ValueError(
                f"control.{name}: expected a floating (*B, {', '.join(map(str, event))}) "
                f"tensor, got {describe(value)}"
            )
        if not bool(torch.isfinite(value).all()):
            raise ValueError(f"control.{name}: contains NaN or inf")
        try:
            out[name] = value.to(dtype).expand(*batch, *event).reshape(P, *event)
        except RuntimeError as err:
            raise ValueError(
                f"control.{name}: batch {tuple(value.shape[: value.ndim - len(event)])} "
                f"does not broadcast to {tuple(batch)}"
            ) from err
    robot_base = out["robot_base"]
    if robot_base is None:
        robot_base = default_base.expand(P, R, 7)
    q_kinematic = out["q_kinematic"]
    if q_kinematic is None:
        q_kinematic = torch.zeros(P, 0, 7, dtype=dtype, device=device)
    q_robot, v_robot = out["q_robot"], out["v_robot"]
    assert q_robot is not None
    assert v_robot is not None
    return _Control(
        q_robot=q_robot,
        v_robot=v_robot,
        robot_base=robot_base,
        base_twist=out["base_twist"],
        q_kinematic=q_kinematic,
        v_kinematic=out["v_kinematic"],
        joint_command=out["joint_command"] if scene.num_servo_joints else None,
        v_robot_next=out["v_robot_next"],
    )
