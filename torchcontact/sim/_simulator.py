"""The time-stepping simulator: mode guess, consistency check, exact fallback."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace
from typing import get_args

import torch
from torch import Tensor

from torchcontact._checks import (
    check_batched,
    check_float,
    check_int,
    check_real,
    check_unit_rows,
)
from torchcontact._compiled import kernel
from torchcontact.contact import (
    SEPARATED,
    ContactProblem,
    Method,
    Solution,
    SolveStatus,
    consistent_with_mode,
    contact_mode,
    default_tolerance,
    is_consistent,
    lcp_residual,
    solve,
    solve_active_set,
    solve_mode,
    solve_mode_unchecked,
    update_mode,
)
from torchcontact.geometry import SlotGeometry
from torchcontact.sim._assemble import assemble, robot_inputs, scene_layout, slot_state
from torchcontact.sim._rigid_body import integrate_poses
from torchcontact.sim._scene import Scene
from torchcontact.sim._state import SceneState

#: ``StepResult.solver`` codes.
SOLVED_BY_GUESS = 0
SOLVED_BY_EXACT_MODE = 1
SOLVED_RAW = 2
UNSOLVED = -1


@dataclass(frozen=True, eq=False)
class StepResult:
    """One simulator step of a batch of scenes.

    Attributes:
        state: the state after the step (its ``mode`` is this step's modes).
        pn: ``(*B, K)`` normal impulses.
        pt: ``(*B, K, D)`` friction impulses along the friction directions (planar: ``+t``, ``−t``).
        mode: ``(*B, K)`` ground-truth contact modes.
        geometry: slot points, normals (world frame), gaps and candidate flags at the start.
        solver: ``(*B,)`` long: 0 the previous modes (after active-set corrections) were
            consistent, 1 an exact solver's
            modes re-solved by ``solve_mode`` (differentiable), 2 the exact solver's raw
            impulses (not differentiable), −1 no solver converged.
        residual: ``(*B,)`` LCP residual of the accepted solution.
    """

    state: SceneState
    pn: Tensor
    pt: Tensor
    mode: Tensor
    geometry: SlotGeometry
    solver: Tensor
    residual: Tensor


@dataclass(frozen=True, eq=False)
class Rollout:
    """A simulated trajectory, time leading: ``T`` steps of a batch ``*B``.

    Attributes:
        q: ``(T + 1, *B, Nd, 3)`` poses of the dynamic bodies (``(…, 7)`` spatial).
        v: ``(T + 1, *B, Nd, 3)`` twists of the dynamic bodies (``(…, 6)`` spatial).
        q_kinematic: ``(T + 1, *B, Nk, 3)`` poses of the kinematic bodies (``(…, 7)``
            spatial).
        pn: ``(T, *B, K)`` normal impulses.
        pt: ``(T, *B, K, D)`` friction impulses.
        mode: ``(T, *B, K)`` contact modes.
        points: ``(T, *B, K, d)`` slot points at the start of each step (``d = 2`` or 3).
        normals: ``(T, *B, K, d)`` slot normals at the start of each step.
        active: ``(T, *B, K)`` slot candidate flags.
        solver: ``(T, *B)`` solver codes (see :class:`StepResult`).
        q_robot: ``(T + 1, *B, Nj)`` the robots' joint positions (empty without robots).
        v_robot: ``(T + 1, *B, Nj)`` their joint velocities.
        robot_base: ``(T + 1, *B, R, 7)`` their base poses.
    """

    q: Tensor
    v: Tensor
    q_kinematic: Tensor
    pn: Tensor
    pt: Tensor
    mode: Tensor
    points: Tensor
    normals: Tensor
    active: Tensor
    solver: Tensor
    q_robot: Tensor | None = None
    v_robot: Tensor | None = None
    robot_base: Tensor | None = None


@dataclass(frozen=True, eq=False)
class Simulator:
    """Batched planar and spatial contact simulation with the Stewart–Trinkle LCP.

    Each step (semi-implicit Euler: ``q⁺ = q + h v⁺``, kinematic bodies ``q⁺ = q + h u``):

    1. compute the slot geometry of every scene of the batch (all slot groups at once);
    2. keep, per scene, only its candidate slots (``geometry.active``), padded to the most
       candidates of any scene of the batch plus one by the non-candidates with the largest
       ``max(|φ| / h, |bn|)``: the solvers' tolerance scales are maxima of these over all
       slots, so the slot that sets them is always kept; assemble the contact problem on
       those slots (the rows :func:`~torchcontact.sim.contact_problem` gives them).
       Non-candidate slots carry no impulse, so the solution of this compacted problem,
       scattered back to the ``K`` slots, is that of the full problem;
    3. solve all of them with one :func:`~torchcontact.contact.solve_mode` at the previous
       step's modes (contact modes rarely change between steps), and correct the modes of
       the inconsistent ones by a few batched active-set iterations
       (:func:`~torchcontact.contact.solve_active_set`);
    4. send only the entries still inconsistent to the exact solvers in ``fallback`` order
       (Lemke, then the QP fallback); with ``retry_sticking``, the entries that the first
       of them leaves unsolved are first tried once more by the active-set iteration started
       from every candidate slot sticking;
    5. re-solve the exact solvers' answers with ``solve_mode`` at their modes, so that every
       accepted step is differentiable through its active modes; an entry whose re-solve is
       not consistent keeps the exact solver's raw impulses (``solver == 2``).

    Robots (:class:`~torchcontact.sim.RobotMember`): before step 1 their links' world frames,
    Jacobians and collision primitives are computed from ``q_robot`` and ``robot_base``; a
    servo robot's joints are solved with the bodies (``q_robot⁺ = q_robot + h q̇⁺``), a
    kinematic robot's follow the commanded velocities, and every base moves with its
    commanded twist (``robot_base⁺`` integrated as a kinematic body's pose).

    The retry is for grasps: two pads pressing one body from both sides make redundant rows,
    on which Lemke's pivoting can stop with an inaccurate answer and the QP fallback, though
    accurate, is slow. There ``solve_mode`` at the right modes (typically every candidate
    sticking) returns impulses consistent with them and an LCP residual near 1e-8, but reports
    no convergence (its equality residual stalls above the float64 tolerance on the redundant
    rows). A retry is accepted when it is consistent with its modes and either converged or
    within ``retry_residual`` of solving the LCP (``solver == 0``).

    Attributes:
        scene: the scene.
        fallback: exact solvers tried in order for entries whose guessed mode fails.
        active_set_iterations: mode corrections tried before the exact solvers (0 disables).
        retry_sticking: retry from all-sticking modes after the first fallback solver.
        retry_residual: largest LCP residual (:func:`~torchcontact.contact.lcp_residual`) of
            an accepted answer that did not converge: a retry, or an exact solver's answer
            (on a BarrettHand grasp Lemke's pivoting stopped at a residual of 2.5e-9).
        compiled: first try each step of a planar scene without robots as one
            :func:`torch.compile` kernel (see ``torchcontact._compiled``; the first step
            compiles, tens of seconds, and each new number of active slots once more): the
            slot geometry and the problem on all ``K`` slots, the mode solve at the previous
            step's modes on the slots they activate (at least two), the consistency check, the
            canonical modes and the active set's next modes
            (:func:`~torchcontact.contact.update_mode`), with no host synchronisation; then
            one synchronisation: the entries that are consistent (``solver == 0``) are done,
            the others are corrected as the eager step's active set does
            (``active_set_iterations`` times at most), each correction one call of the kernel
            on those entries alone (a second batch size compiles once more, with dynamic
            sizes); the entries still inconsistent take steps 1–5 as a
            batch of their own, from their previous modes. The mode solve's systems and the
            mass matrix (up to 16 rows) are solved by Gaussian elimination with partial
            pivoting written out in the kernel, so that the step runs as fused loops without
            LAPACK calls. The results equal those of ``compiled=False`` to rounding. Spatial
            scenes, scenes with robots and steps that record gradients (an input, or a scene
            mass, inertia or friction, that requires grad) run eagerly.
    """

    scene: Scene
    fallback: tuple[Method, ...] = ("lemke", "qp")
    active_set_iterations: int = 4
    retry_sticking: bool = True
    retry_residual: float = 1e-6
    compiled: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.scene, Scene):
            raise ValueError(f"scene must be a Scene, got {type(self.scene).__name__}")
        methods = get_args(Method)
        if not isinstance(self.fallback, tuple) or not all(m in methods for m in self.fallback):
            raise ValueError(
                f"fallback must be a tuple of methods among {methods}, got {self.fallback!r}"
            )
        check_int("active_set_iterations", self.active_set_iterations, low=0)
        if not isinstance(self.retry_sticking, bool):
            raise ValueError(f"retry_sticking must be a bool, got {self.retry_sticking!r}")
        check_real("retry_residual", self.retry_residual, low=0.0)
        if not isinstance(self.compiled, bool):
            raise ValueError(f"compiled must be a bool, got {self.compiled!r}")

    def initial_state(
        self,
        *,
        q: Tensor,
        v: Tensor | None = None,
        q_kinematic: Tensor | None = None,
        q_robot: Tensor | None = None,
        v_robot: Tensor | None = None,
        robot_base: Tensor | None = None,
    ) -> SceneState:
        """A state from poses (twists default to zero, modes to separated).

        The last two dimensions are always the scene's bodies and their pose: one scene of a
        one-body planar scene is ``q`` of shape ``(1, 3)`` (no batch), a batch of ``B`` of
        them ``(B, 1, 3)``. (:func:`~torchcontact.contact.planar_box_problem`, a single box's
        problem, reads ``(B, 3)`` as a batch of ``B`` boxes instead.)

        Args:
            q: ``(*B, Nd, 3)`` dynamic-body poses ``(x, y, θ)`` (planar) or ``(*B, Nd, 7)``
                positions and unit quaternions ``(w, x, y, z)`` (spatial), world frame.
            v: ``(*B, Nd, 3)`` or ``(*B, Nd, 6)`` twists, default zero.
            q_kinematic: kinematic-body poses shaped like ``q`` with ``Nk`` bodies (required
                if there are any).
            q_robot: ``(*B, Nj)`` the robots' actuated joint positions, robots in scene
                order (required if there are robots).
            v_robot: ``(*B, Nj)`` their joint velocities, default zero.
            robot_base: ``(*B, R, 7)`` world poses of the robots' base frames, default each
                :attr:`RobotMember.base_pose`.

        Raises:
            ValueError: naming the argument that is not a finite float32/float64 tensor of
                its shape, or whose dtype differs from ``q``'s, or whose quaternions are not
                of unit norm.
        """
        scene = self.scene
        num_dynamic, num_kinematic = len(scene.dynamic), len(scene.kinematic)
        pose, twist = scene.pose_size, scene.twist_size
        names = ", ".join(scene.bodies[i].name for i in scene.dynamic)
        layout = "(x, y, θ)" if scene.dimension == 2 else "(x, y, z, qw, qx, qy, qz)"
        what = (
            f"(*B, {num_dynamic}, {pose}): batch, then the dynamic bodies ({names}), then {layout}"
        )
        q = check_float("q", q, trailing=(num_dynamic, pose), min_ndim=2, what=what)
        batch = q.shape[:-2]
        if v is None:
            v = q.new_zeros(*batch, num_dynamic, twist)
        v = check_batched("v", v, shape=(*batch, num_dynamic, twist), like=q, like_name="q")
        if q_kinematic is None:
            if num_kinematic:
                raise ValueError(f"q_kinematic of shape (*B, {num_kinematic}, {pose}) is required")
            q_kinematic = q.new_zeros(*batch, 0, pose)
        q_kinematic = check_batched(
            "q_kinematic", q_kinematic, shape=(*batch, num_kinematic, pose), like=q, like_name="q"
        )
        if scene.dimension == 3:
            for name, value in (("q", q), ("q_kinematic", q_kinematic)):
                check_unit_rows(f"{name}[..., 3:] (quaternions)", value[..., 3:])
        mode = torch.zeros(*batch, scene.num_slots, dtype=torch.long, device=q.device)
        joints, robots = scene.num_robot_joints, len(scene.robots)
        if q_robot is None:
            if joints:
                raise ValueError(f"q_robot of shape (*B, {joints}) is required")
            q_robot = q.new_zeros(*batch, 0)
        q_robot = check_batched("q_robot", q_robot, shape=(*batch, joints), like=q, like_name="q")
        if v_robot is None:
            v_robot = torch.zeros_like(q_robot)
        v_robot = check_batched("v_robot", v_robot, shape=(*batch, joints), like=q, like_name="q")
        if robot_base is None:
            poses = [member.base_pose for member in scene.robots]
            stacked = torch.stack(poses) if poses else torch.zeros(0, 7)  # type: ignore[arg-type]
            robot_base = stacked.to(q).expand(*batch, robots, 7)
        robot_base = check_batched(
            "robot_base", robot_base, shape=(*batch, robots, 7), like=q, like_name="q"
        )
        check_unit_rows("robot_base[..., 3:] (quaternions)", robot_base[..., 3:])
        return SceneState(
            q=q,
            v=v,
            q_kinematic=q_kinematic,
            mode=mode,
            q_robot=q_robot,
            v_robot=v_robot,
            robot_base=robot_base,
        )

    def step(
        self,
        state: SceneState,
        control: Tensor | None = None,
        *,
        force: Tensor | None = None,
        friction: Tensor | None = None,
        joint_command: Tensor | None = None,
        base_twist: Tensor | None = None,
    ) -> StepResult:
        """Advance every scene of the batch by one time step.

        Args:
            state: the batched state ``*B``.
            control: ``(*B, Nk, 3)`` (planar) or ``(*B, Nk, 6)`` (spatial) kinematic-body
                twists over the step (world frame).
            force: ``(*B, Nd, 3)`` or ``(*B, Nd, 6)`` applied generalized forces on dynamic
                bodies.
            friction: ``(*B, K)`` per-slot friction overriding the scene's, ``>= 0``.
            joint_command: ``(*B, Nj)`` the robots' joint commands, robots in scene order: a
                servo robot's target positions ``q*``, a kinematic robot's joint velocities;
                default: the servo targets are the current positions (the servo then only
                damps the joints, it does not pull them back under a load) and kinematic
                joints rest.
            base_twist: ``(*B, R, 6)`` the robots' base twists ``(v, ω)`` over the step
                (world frame, at the base frame's origin); default at rest.

        Returns:
            The :class:`StepResult`.

        Raises:
            ValueError: naming ``state``, ``control``, ``force``, ``friction``,
                ``joint_command`` or ``base_twist`` when it is not a finite tensor of its shape
                with the state's dtype (or friction is negative).
        """
        if not isinstance(state, SceneState):
            raise ValueError(f"state must be a SceneState, got {type(state).__name__}")
        batch, K = state.batch_shape, self.scene.num_slots
        num_dynamic, num_kinematic = len(self.scene.dynamic), len(self.scene.kinematic)
        twist = self.scene.twist_size
        if control is not None:
            check_batched(
                "control",
                control,
                shape=(*batch, num_kinematic, twist),
                like=state.q,
                like_name="q",
            )
        if force is not None:
            check_batched(
                "force", force, shape=(*batch, num_dynamic, twist), like=state.q, like_name="q"
            )
        if friction is not None:
            check_batched("friction", friction, shape=(*batch, K), like=state.q, like_name="q")
            if friction.numel() and float(friction.detach().min()) < 0:
                raise ValueError(
                    f"friction must be >= 0, got minimum {float(friction.detach().min())}"
                )
        scene = self.scene
        for name, value, shape in (
            ("joint_command", joint_command, (*batch, scene.num_robot_joints)),
            ("base_twist", base_twist, (*batch, len(scene.robots), 6)),
        ):
            if value is not None:
                check_batched(name, value, shape=shape, like=state.q, like_name="q")
        if self._compiled_step_applies(state, control, force, friction):
            solution, solver, geometry = self._step_at_modes(state, control, force, friction)
        else:
            solution, solver, geometry = self._step_compacted(
                state, control, force, friction, joint_command, base_twist
            )
        h = self.scene.h
        body_dofs = num_dynamic * twist
        v_next = solution.v_next[..., :body_dofs].unflatten(-1, (num_dynamic, twist))
        q_robot, v_robot, robot_base = self._robot_next(
            state, solution.v_next[..., body_dofs:], joint_command, base_twist
        )
        q_kinematic = state.q_kinematic
        if self.scene.dimension == 2:
            q_next = state.q + h * v_next
            if control is not None:
                q_kinematic = q_kinematic + h * control
        else:
            q_next = integrate_poses(state.q, v_next, h)
            if control is not None:
                q_kinematic = integrate_poses(q_kinematic, control, h)
        next_state = SceneState(
            q=q_next,
            v=v_next,
            q_kinematic=q_kinematic,
            mode=solution.mode,
            q_robot=q_robot,
            v_robot=v_robot,
            robot_base=robot_base,
        )
        return StepResult(
            state=next_state,
            pn=solution.pn,
            pt=solution.pt,
            mode=solution.mode,
            geometry=geometry,
            solver=solver,
            residual=solution.status.residual,
        )

    def _robot_next(
        self,
        state: SceneState,
        servo_velocity: Tensor,
        joint_command: Tensor | None,
        base_twist: Tensor | None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """The robots' joint positions, velocities and base poses after a step, from the servo
        joints' solved velocities ``(*B, Ns)``."""
        assert state.q_robot is not None
        assert state.robot_base is not None
        if not self.scene.robots:
            assert state.v_robot is not None
            return state.q_robot, state.v_robot, state.robot_base
        h = self.scene.h
        # the driven joints as commanded (at rest without a command), the servo joints solved
        driven = (
            state.q_robot.new_zeros(state.q_robot.shape) if joint_command is None else joint_command
        )
        servo = torch.tensor(self.scene.servo_columns, dtype=torch.long, device=driven.device)
        v_robot = driven.index_copy(-1, servo, servo_velocity)
        robot_base = state.robot_base
        if base_twist is not None:
            robot_base = integrate_poses(robot_base, base_twist, h)
        return state.q_robot + h * v_robot, v_robot, robot_base

    def rollout(
        self,
        state: SceneState,
        *,
        steps: int,
        controls: Tensor | None = None,
        forces: Tensor | None = None,
        strict: bool = True,
        joint_commands: Tensor | None = None,
        base_twists: Tensor | None = None,
    ) -> Rollout:
        """Simulate ``steps`` steps.

        Args:
            state: initial state, batch ``*B``.
            steps: number of steps ``T``.
            controls: ``(T, *B, Nk, 3)`` (planar) or ``(T, *B, Nk, 6)`` (spatial)
                kinematic-body twists per step, or ``None``.
            forces: ``(T, *B, Nd, 3)`` or ``(T, *B, Nd, 6)`` applied generalized forces per
                step, or ``None``.
            strict: raise ``RuntimeError`` if some entry could not be solved.
            joint_commands: ``(T, *B, Nj)`` the robots' joint commands per step (see
                :meth:`step`), or ``None``.
            base_twists: ``(T, *B, R, 6)`` the robots' base twists per step, or ``None``.

        Returns:
            The :class:`Rollout` (with ``steps == 0``: the initial state and empty per-step
            fields).

        Raises:
            ValueError: naming ``state``, ``steps``, ``strict``, ``controls`` or ``forces``
                when it is not of its documented type, shape or range.
        """
        if not isinstance(state, SceneState):
            raise ValueError(f"state must be a SceneState, got {type(state).__name__}")
        steps = check_int("steps", steps, low=0)
        if not isinstance(strict, bool):
            raise ValueError(f"strict must be a bool, got {strict!r}")
        batch = state.batch_shape
        for name, value, count in (
            ("controls", controls, len(self.scene.kinematic)),
            ("forces", forces, len(self.scene.dynamic)),
        ):
            if value is not None:
                check_batched(
                    name,
                    value,
                    shape=(steps, *batch, count, self.scene.twist_size),
                    like=state.q,
                    like_name="q",
                )
        for name, value, shape in (
            ("joint_commands", joint_commands, (steps, *batch, self.scene.num_robot_joints)),
            ("base_twists", base_twists, (steps, *batch, len(self.scene.robots), 6)),
        ):
            if value is not None:
                check_batched(name, value, shape=shape, like=state.q, like_name="q")
        if steps == 0:
            return self._empty_rollout(state)
        states, results = [state], []
        for t in range(steps):
            result = self.step(
                states[-1],
                None if controls is None else controls[t],
                force=None if forces is None else forces[t],
                joint_command=None if joint_commands is None else joint_commands[t],
                base_twist=None if base_twists is None else base_twists[t],
            )
            if strict and bool((result.solver == UNSOLVED).any()):
                raise RuntimeError(f"no contact solver converged at step {t}")
            states.append(result.state)
            results.append(result)
        return Rollout(
            q=torch.stack([s.q for s in states]),
            v=torch.stack([s.v for s in states]),
            q_kinematic=torch.stack([s.q_kinematic for s in states]),
            pn=torch.stack([r.pn for r in results]),
            pt=torch.stack([r.pt for r in results]),
            mode=torch.stack([r.mode for r in results]),
            points=torch.stack([r.geometry.points for r in results]),
            normals=torch.stack([r.geometry.normals for r in results]),
            active=torch.stack([r.geometry.active for r in results]),
            solver=torch.stack([r.solver for r in results]),
            q_robot=torch.stack([s.q_robot for s in states]),  # type: ignore[misc]
            v_robot=torch.stack([s.v_robot for s in states]),  # type: ignore[misc]
            robot_base=torch.stack([s.robot_base for s in states]),  # type: ignore[misc]
        )

    def _empty_rollout(self, state: SceneState) -> Rollout:
        """The :class:`Rollout` of zero steps from ``state``."""
        batch, K = state.batch_shape, self.scene.num_slots
        q = state.q

        def empty(*shape: int, dtype: torch.dtype = q.dtype) -> Tensor:
            return torch.empty(0, *batch, *shape, dtype=dtype, device=q.device)

        return Rollout(
            q=q.unsqueeze(0),
            v=state.v.unsqueeze(0),
            q_kinematic=state.q_kinematic.unsqueeze(0),
            pn=empty(K),
            pt=empty(K, 2 if self.scene.dimension == 2 else self.scene.friction_directions),
            mode=empty(K, dtype=torch.long),
            points=empty(K, self.scene.dimension),
            normals=empty(K, self.scene.dimension),
            active=empty(K, dtype=torch.bool),
            solver=empty(dtype=torch.long),
            q_robot=state.q_robot.unsqueeze(0),  # type: ignore[union-attr]
            v_robot=state.v_robot.unsqueeze(0),  # type: ignore[union-attr]
            robot_base=state.robot_base.unsqueeze(0),  # type: ignore[union-attr]
        )

    def _compiled_step_applies(
        self,
        state: SceneState,
        control: Tensor | None,
        force: Tensor | None,
        friction: Tensor | None,
    ) -> bool:
        """Whether :meth:`_step_at_modes` takes this step (see ``compiled``)."""
        scene = self.scene
        if not self.compiled or scene.dimension != 2 or scene.robots or state.q.numel() == 0:
            return False
        layout = scene_layout(scene, state.q.dtype, state.q.device)
        if layout.mass_matrix is None or layout.gravity_force is None or layout.mu is None:
            return False  # masses or friction that require grad
        inputs = (state.q, state.v, state.q_kinematic, control, force, friction)
        return not (
            torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in inputs)
        )

    def _step_at_modes(
        self,
        state: SceneState,
        control: Tensor | None,
        force: Tensor | None,
        friction: Tensor | None,
    ) -> tuple[Solution, Tensor, SlotGeometry]:
        """The compiled step at the previous modes, corrected by the active-set iteration's
        kernel calls on the inconsistent entries, then :meth:`_step_compacted` for the entries
        still inconsistent; the returns of :meth:`_step_compacted`."""
        batch, K = state.batch_shape, self.scene.num_slots
        P = math.prod(batch)
        unflattened = len(batch) != 1

        def flat(t: Tensor) -> Tensor:
            return t.reshape(P, *t.shape[len(batch) :]) if unflattened else t

        q, v, q_kinematic, mode = map(flat, (state.q, state.v, state.q_kinematic, state.mode))
        control, force, friction = (
            None if t is None else flat(t) for t in (control, force, friction)
        )
        # Scalar loops: the kernel's innermost dimensions are slots and rows (see kernel).
        step = kernel(_step_at_modes, compiled=True, vectorize=False)

        def run(index: Tensor | None, guess: Tensor) -> _KernelStep:
            # The mode solve's slots: as many as the most non-separated slots of an entry, at
            # least two (so that the first step, from separated modes, shares the later steps'
            # graph): a read of the modes (SEPARATED is 0), which are on the host. A separated
            # slot more would only add identity rows to the systems (a third more rows for
            # boxes on the ground, and 1.5 times the kernel's time at B = 1,024).
            width = min(K, max(2, int(torch.count_nonzero(guess, dim=-1).max())))

            def pick(t: Tensor) -> Tensor:
                return t if index is None else t[index]

            def pick_optional(t: Tensor | None) -> Tensor | None:
                return None if t is None else pick(t)

            optional = map(pick_optional, (control, force, friction))
            return _KernelStep(
                *step(self.scene, pick(q), pick(v), pick(q_kinematic), guess, width, *optional)
            )

        # Nothing requires grad here: one compiled variant whatever the grad mode.
        with torch.no_grad():
            out = run(None, mode)
            redo = torch.nonzero(~out.good).squeeze(-1)  # a host synchronisation
            # The active-set iteration of the eager step (``solve_active_set``), each
            # correction of the inconsistent entries' modes one more kernel call on them.
            for _ in range(self.active_set_iterations):
                if redo.numel() == 0:
                    break
                out.scatter(redo, run(redo, out.proposal[redo]))
                redo = torch.nonzero(~out.good).squeeze(-1)
        status = SolveStatus(
            converged=out.good, residual=out.residual, iterations=torch.ones_like(mode[:, 0])
        )
        solution = Solution(
            v_next=out.v_next, pn=out.pn, pt=out.pt, mode=out.canonical, status=status
        )
        solver = torch.zeros_like(mode[:, 0])  # SOLVED_BY_GUESS
        if redo.numel():
            # Entries the corrections leave inconsistent take the eager step, as a batch of
            # their own, from their previous modes (so the same iterations, then the exact
            # solvers).
            def pick(t: Tensor | None) -> Tensor | None:
                return None if t is None else t[redo]

            subset = SceneState(
                q=q[redo], v=v[redo], q_kinematic=q_kinematic[redo], mode=mode[redo]
            )
            eager, codes, _ = self._step_compacted(
                subset, pick(control), pick(force), pick(friction)
            )
            solution = solution.scatter(redo, eager)
            solver = solver.index_put((redo,), codes)
        geometry = out.geometry
        if unflattened:
            geometry = SlotGeometry(
                points=geometry.points.reshape(*batch, K, 2),
                normals=geometry.normals.reshape(*batch, K, 2),
                phi=geometry.phi.reshape(*batch, K),
                active=geometry.active.reshape(*batch, K),
            )
            solution = solution.map_tensors(lambda t: t.reshape((*batch, *t.shape[1:])))
            solver = solver.reshape(batch)
        return solution, solver, geometry

    def _step_compacted(
        self,
        state: SceneState,
        control: Tensor | None,
        force: Tensor | None,
        friction: Tensor | None,
        joint_command: Tensor | None = None,
        base_twist: Tensor | None = None,
    ) -> tuple[Solution, Tensor, SlotGeometry]:
        """Assemble and solve on the candidate slots (step 2 of the class docstring), scatter
        back.

        Returns:
            The solution with ``(*B, K)`` slot fields, the ``(*B,)`` solver codes and the
            slot geometry of the ``K`` slots.
        """
        batch, K, h = state.batch_shape, self.scene.num_slots, self.scene.h
        P, Nd, Nk = math.prod(batch), len(self.scene.dynamic), len(self.scene.kinematic)
        pose, twist, d = self.scene.pose_size, self.scene.twist_size, self.scene.dimension

        def flat(t: Tensor | None) -> Tensor | None:
            return None if t is None else t.reshape(P, *t.shape[len(batch) :])

        q, q_kinematic = state.q.reshape(P, Nd, pose), state.q_kinematic.reshape(P, Nk, pose)
        robots = robot_inputs(self.scene, state, flat(joint_command), flat(base_twist))
        slots = slot_state(self.scene, q, q_kinematic, flat(control), robots)
        geometry = slots.geometry
        mask = geometry.active
        # Candidates first (in slot order), then the non-candidates by decreasing velocity
        # scale, so that the slot that sets the solvers' tolerance scale stays in.
        scale = torch.maximum(geometry.phi.detach().abs() / h, slots.known[..., 0].detach().abs())
        order = torch.argsort(
            torch.where(mask, math.inf, scale), dim=-1, descending=True, stable=True
        )
        width = min(K, int(mask.sum(-1).max()) + 1) if P else 0
        keep = order[:, :width]  # (P, W)
        problem = assemble(
            self.scene,
            slots,
            state.v.reshape(P, Nd, twist),
            keep,
            force=flat(force),
            friction=flat(friction),
        )
        guess = state.mode.reshape(P, K).gather(1, keep)
        solution, solver = self._solve(problem, guess)

        def scatter(t: Tensor) -> Tensor:
            index = keep.view(P, width, *([1] * (t.dim() - 2))).expand(t.shape)
            full = t.new_zeros(P, K, *t.shape[2:]).scatter(1, index, t)
            return full.reshape(*batch, *full.shape[1:])

        full = replace(
            solution,
            v_next=solution.v_next.reshape(*batch, solution.v_next.shape[-1]),
            pn=scatter(solution.pn),
            pt=scatter(solution.pt),
            mode=scatter(solution.mode),
            status=solution.status.map_tensors(lambda t: t.reshape(batch)),
        )
        geometry = SlotGeometry(
            points=geometry.points.reshape(*batch, K, d),
            normals=geometry.normals.reshape(*batch, K, d),
            phi=geometry.phi.reshape(*batch, K),
            active=mask.reshape(*batch, K),
        )
        return full, solver.reshape(batch), geometry

    def _solve(self, problem: ContactProblem, guess: Tensor) -> tuple[Solution, Tensor]:
        """Mode guess first, exact fallback for the failing entries; see the class docstring.

        Args:
            problem: the (compacted) problem of a flat batch ``(B,)``.
            guess: ``(B, K)`` mode guess.
        """
        guess = torch.where(problem.slot_mask, guess, 0)
        solution = solve_active_set(problem, guess, max_iterations=self.active_set_iterations)
        good = solution.status.converged
        solver = torch.where(good, SOLVED_BY_GUESS, UNSOLVED)
        pending = torch.nonzero(~good).squeeze(-1)
        for position, method in enumerate(self.fallback):
            if pending.numel() == 0:
                break
            if position == 1 and self.retry_sticking:
                subset = problem[pending]
                retry = solve_active_set(
                    subset, subset.slot_mask.long(), max_iterations=self.active_set_iterations
                )
                close = retry.status.residual <= self.retry_residual
                accepted = is_consistent(subset, retry) & (retry.status.converged | close)
                if bool(accepted.any()):
                    done = pending[accepted]
                    solution = solution.scatter(done, retry.map_tensors(lambda t, a=accepted: t[a]))
                    solver = solver.index_put((done,), torch.full_like(done, SOLVED_BY_GUESS))
                pending = pending[~accepted]
                if pending.numel() == 0:
                    break
            with warnings.catch_warnings():
                # OSQP's "solved inaccurate" is reported through the status already.
                warnings.filterwarnings("ignore", message="OSQP exited", category=UserWarning)
                exact = solve(problem[pending], method)
            # An answer within retry_residual of solving the LCP is one, whatever the solver's
            # own verdict (Lemke's pivoting on a grasp's redundant rows can stop there).
            converged = exact.status.converged | (exact.status.residual <= self.retry_residual)
            done = pending[converged]
            if done.numel():
                exact_done = exact.map_tensors(lambda t, c=converged: t[c])
                again = solve_mode(
                    problem[done], exact_done.mode, initial_impulses=(exact_done.pn, exact_done.pt)
                )
                reproduced = is_consistent(problem[done], again) & again.status.converged
                solution = solution.scatter(done, again.where(reproduced, exact_done))
                codes = torch.where(reproduced, SOLVED_BY_EXACT_MODE, SOLVED_RAW)
                solver = solver.index_put((done,), codes)
            pending = pending[~converged]
        # Report canonical modes: a slot that slides at zero slip, or carries no impulse in an
        # active mode, is labelled as the solution shows it (sticking, separated).
        canonical = contact_mode(
            problem,
            v_next=solution.v_next.detach(),
            pn=solution.pn.detach(),
            pt=solution.pt.detach(),
        )
        return replace(solution, mode=canonical), solver


def _step_at_modes(
    scene: Scene,
    q: Tensor,
    v: Tensor,
    q_kinematic: Tensor,
    mode: Tensor,
    width: int,
    control: Tensor | None,
    force: Tensor | None,
    friction: Tensor | None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, SlotGeometry]:
    """A step of a flat batch of a planar scene at given modes, with no host synchronisation
    (the kernel of ``Simulator(compiled=True)``).

    The problem is assembled on all ``K`` slots, where the solution is checked; the mode solve
    runs on ``width`` slots alone: each entry's non-separated slots first, then separated ones
    (a separated slot carries no impulse and adds only an identity row to the Schur system, so
    the solve is the same as on all ``K`` slots).

    Args:
        scene: the scene (planar, without robots).
        q: ``(P, Nd, 3)`` dynamic-body poses.
        v: ``(P, Nd, 3)`` their twists.
        q_kinematic: ``(P, Nk, 3)`` kinematic-body poses.
        mode: ``(P, K)`` long modes to solve at.
        width: the number of slots of the mode solve, at least the most non-separated slots
            of an entry.
        control: ``(P, Nk, 3)`` kinematic-body twists, or ``None``.
        force: ``(P, Nd, 3)`` applied forces, or ``None``.
        friction: ``(P, K)`` per-slot friction, or ``None``.

    Returns:
        ``v_next (P, 3 Nd)``, ``pn (P, K)``, ``pt (P, K, 2)``, the canonical modes ``(P, K)``,
        the LCP residual ``(P,)``, ``(P,)`` bool: the solution is consistent with ``mode`` and
        converged, the ``(P, K)`` modes of the next active-set iteration
        (:func:`~torchcontact.contact.update_mode`), and the slot geometry (batch ``(P,)``).
    """
    slots = slot_state(scene, q, q_kinematic, control)
    P, K = mode.shape
    separated = (mode == SEPARATED).to(torch.uint8)
    solved = torch.argsort(separated, dim=-1, stable=True)[:, :width]
    every = torch.arange(K, device=q.device).expand(P, K)
    problem = assemble(scene, slots, v, every, force=force, friction=friction)
    mode = torch.where(problem.slot_mask, mode, 0)
    compact = assemble(scene, slots, v, solved, force=force, friction=friction)
    solution = solve_mode_unchecked(compact, mode.gather(1, solved), sync_free=True)
    v_next = solution.v_next
    pn = torch.zeros_like(problem.phi).scatter(1, solved, solution.pn)
    index = solved.unsqueeze(-1).expand(solution.pt.shape)
    pt = torch.zeros_like(problem.b_tangent).scatter(1, index, solution.pt)
    consistent = consistent_with_mode(
        problem, v_next=v_next, pn=pn, pt=pt, mode=mode, atol=10 * default_tolerance(q.dtype)
    )
    canonical = contact_mode(problem, v_next=v_next, pn=pn, pt=pt)
    residual = lcp_residual(problem, v_next=v_next, pn=pn, pt=pt)
    good = consistent & solution.status.converged
    at_mode = Solution(
        v_next=v_next,
        pn=pn,
        pt=pt,
        mode=mode,
        status=replace(solution.status, residual=residual),
    )
    proposal = update_mode(problem, at_mode)
    return v_next, pn, pt, canonical, residual, good, proposal, slots.geometry


@dataclass(eq=False)
class _KernelStep:
    """The outputs of :func:`_step_at_modes` (flat batch ``(P,)``), updated in place where
    the active-set iteration re-runs it on some entries."""

    v_next: Tensor
    pn: Tensor
    pt: Tensor
    canonical: Tensor
    residual: Tensor
    good: Tensor
    proposal: Tensor
    geometry: SlotGeometry

    def scatter(self, index: Tensor, other: _KernelStep) -> None:
        """Write ``other``'s entries (its slot geometry excepted: the poses are the same) at
        ``index``."""
        for name in ("v_next", "pn", "pt", "canonical", "residual", "good", "proposal"):
            getattr(self, name).index_copy_(0, index, getattr(other, name))
