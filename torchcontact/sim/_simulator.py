"""The time-stepping simulator: mode guess, consistency check, exact fallback."""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import Tensor

from torchcontact._checks import check_batched, check_float, check_int
from torchcontact.contact import (
    ContactProblem,
    Method,
    Solution,
    contact_mode,
    is_consistent,
    solve,
    solve_active_set,
    solve_mode,
)
from torchcontact.geometry import SlotGeometry
from torchcontact.sim._assemble import contact_problem
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
        pt: ``(*B, K, 2)`` friction impulses along ``+t`` and ``−t``.
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
        q: ``(T + 1, *B, Nd, 3)`` poses of the dynamic bodies.
        v: ``(T + 1, *B, Nd, 3)`` twists of the dynamic bodies.
        q_kinematic: ``(T + 1, *B, Nk, 3)`` poses of the kinematic bodies.
        pn: ``(T, *B, K)`` normal impulses.
        pt: ``(T, *B, K, 2)`` friction impulses.
        mode: ``(T, *B, K)`` contact modes.
        points: ``(T, *B, K, 2)`` slot points at the start of each step.
        normals: ``(T, *B, K, 2)`` slot normals at the start of each step.
        active: ``(T, *B, K)`` slot candidate flags.
        solver: ``(T, *B)`` solver codes (see :class:`StepResult`).
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


@dataclass(frozen=True, eq=False)
class Simulator:
    """Batched planar contact simulation with the Stewart–Trinkle LCP.

    Each step (semi-implicit Euler: ``q⁺ = q + h v⁺``, kinematic bodies ``q⁺ = q + h u``):

    1. assemble the contact problem of every scene of the batch;
    2. solve all of them with one :func:`~torchcontact.contact.solve_mode` at the previous
       step's modes (contact modes rarely change between steps), and correct the modes of
       the inconsistent ones by a few batched active-set iterations
       (:func:`~torchcontact.contact.solve_active_set`);
    3. send only the entries still inconsistent to the exact solvers in ``fallback`` order
       (Lemke, then the QP fallback);
    4. re-solve those with ``solve_mode`` at the exact modes, so that every accepted step is
       differentiable through its active modes; an entry whose re-solve is not consistent
       keeps the exact solver's raw impulses (``solver == 2``).

    Attributes:
        scene: the scene.
        fallback: exact solvers tried in order for entries whose guessed mode fails.
        active_set_iterations: mode corrections tried before the exact solvers (0 disables).
    """

    scene: Scene
    fallback: tuple[Method, ...] = ("lemke", "qp")
    active_set_iterations: int = 4

    def initial_state(
        self,
        *,
        q: Tensor,
        v: Tensor | None = None,
        q_kinematic: Tensor | None = None,
    ) -> SceneState:
        """A state from poses (twists default to zero, modes to separated).

        Args:
            q: ``(*B, Nd, 3)`` dynamic-body poses.
            v: ``(*B, Nd, 3)`` twists, default zero.
            q_kinematic: ``(*B, Nk, 3)`` kinematic-body poses (required if there are any).

        Raises:
            ValueError: naming the argument that is not a finite float32/float64 tensor of
                its shape, or whose dtype differs from ``q``'s.
        """
        num_dynamic, num_kinematic = len(self.scene.dynamic), len(self.scene.kinematic)
        what = f"(*B, {num_dynamic}, 3)"
        q = check_float("q", q, trailing=(num_dynamic, 3), min_ndim=2, what=what)
        batch = q.shape[:-2]
        if v is None:
            v = torch.zeros_like(q)
        v = check_batched("v", v, shape=q.shape, like=q, like_name="q")
        if q_kinematic is None:
            if num_kinematic:
                raise ValueError(f"q_kinematic of shape (*B, {num_kinematic}, 3) is required")
            q_kinematic = torch.zeros(*batch, 0, 3, dtype=q.dtype, device=q.device)
        q_kinematic = check_batched(
            "q_kinematic", q_kinematic, shape=(*batch, num_kinematic, 3), like=q, like_name="q"
        )
        mode = torch.zeros(*batch, self.scene.num_slots, dtype=torch.long)
        return SceneState(q=q, v=v, q_kinematic=q_kinematic, mode=mode)

    def step(
        self,
        state: SceneState,
        control: Tensor | None = None,
        *,
        force: Tensor | None = None,
        friction: Tensor | None = None,
    ) -> StepResult:
        """Advance every scene of the batch by one time step.

        Args:
            state: the batched state ``*B``.
            control: ``(*B, Nk, 3)`` kinematic-body twists over the step (world frame).
            force: ``(*B, Nd, 3)`` applied generalized forces on dynamic bodies.
            friction: ``(*B, K)`` per-slot friction overriding the scene's, ``>= 0``.

        Returns:
            The :class:`StepResult`.

        Raises:
            ValueError: naming ``state``, ``control``, ``force`` or ``friction`` when it is not
                a finite tensor of its shape with the state's dtype (or friction is negative).
        """
        if not isinstance(state, SceneState):
            raise ValueError(f"state must be a SceneState, got {type(state).__name__}")
        batch, K = state.batch_shape, self.scene.num_slots
        num_dynamic, num_kinematic = len(self.scene.dynamic), len(self.scene.kinematic)
        if control is not None:
            check_batched(
                "control", control, shape=(*batch, num_kinematic, 3), like=state.q, like_name="q"
            )
        if force is not None:
            check_batched(
                "force", force, shape=(*batch, num_dynamic, 3), like=state.q, like_name="q"
            )
        if friction is not None:
            check_batched("friction", friction, shape=(*batch, K), like=state.q, like_name="q")
            if friction.numel() and float(friction.min()) < 0:
                raise ValueError(f"friction must be >= 0, got minimum {float(friction.min())}")
        problem, geometry = contact_problem(
            self.scene, state, control=control, force=force, friction=friction
        )
        solution, solver = self._solve(problem, state.mode)
        h = self.scene.h
        v_next = solution.v_next.unflatten(-1, (len(self.scene.dynamic), 3))
        q_kinematic = state.q_kinematic
        if control is not None:
            q_kinematic = q_kinematic + h * control
        next_state = SceneState(
            q=state.q + h * v_next, v=v_next, q_kinematic=q_kinematic, mode=solution.mode
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

    def rollout(
        self,
        state: SceneState,
        *,
        steps: int,
        controls: Tensor | None = None,
        forces: Tensor | None = None,
        strict: bool = True,
    ) -> Rollout:
        """Simulate ``steps`` steps.

        Args:
            state: initial state, batch ``*B``.
            steps: number of steps ``T``.
            controls: ``(T, *B, Nk, 3)`` kinematic-body twists per step, or ``None``.
            forces: ``(T, *B, Nd, 3)`` applied generalized forces per step, or ``None``.
            strict: raise ``RuntimeError`` if some entry could not be solved.

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
                    name, value, shape=(steps, *batch, count, 3), like=state.q, like_name="q"
                )
        if steps == 0:
            return self._empty_rollout(state)
        states, results = [state], []
        for t in range(steps):
            result = self.step(
                states[-1],
                None if controls is None else controls[t],
                force=None if forces is None else forces[t],
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
            pt=empty(K, 2),
            mode=empty(K, dtype=torch.long),
            points=empty(K, 2),
            normals=empty(K, 2),
            active=empty(K, dtype=torch.bool),
            solver=empty(dtype=torch.long),
        )

    def _solve(self, problem: ContactProblem, guess: Tensor) -> tuple[Solution, Tensor]:
        """Mode guess first, exact fallback for the failing entries; see the class docstring."""
        batch = problem.batch_shape
        flat = problem.flatten()
        guess = torch.where(flat.slot_mask, guess.reshape(flat.slot_mask.shape), 0)
        solution = solve_active_set(flat, guess, max_iterations=self.active_set_iterations)
        good = solution.status.converged
        solver = torch.where(good, SOLVED_BY_GUESS, UNSOLVED)
        pending = torch.nonzero(~good).squeeze(-1)
        for method in self.fallback:
            if pending.numel() == 0:
                break
            exact = solve(flat[pending], method)
            converged = exact.status.converged
            done = pending[converged]
            if done.numel():
                exact_done = exact.map_tensors(lambda t, c=converged: t[c])
                again = solve_mode(
                    flat[done], exact_done.mode, initial_impulses=(exact_done.pn, exact_done.pt)
                )
                reproduced = is_consistent(flat[done], again) & again.status.converged
                solution = solution.scatter(done, again.where(reproduced, exact_done))
                codes = torch.where(reproduced, SOLVED_BY_EXACT_MODE, SOLVED_RAW)
                solver = solver.index_put((done,), codes)
            pending = pending[~converged]
        # Report canonical modes: a slot that slides at zero slip, or carries no impulse in an
        # active mode, is labelled as the solution shows it (sticking, separated).
        canonical = contact_mode(
            flat, v_next=solution.v_next.detach(), pn=solution.pn.detach(), pt=solution.pt.detach()
        )
        merged = replace(solution, mode=canonical)
        return merged.map_tensors(lambda t: t.reshape((*batch, *t.shape[1:]))), solver.reshape(
            batch
        )
