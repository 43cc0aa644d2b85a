"""A faster stepper for the planar simulator: one vectorized assembly, active slots only.

:class:`torchcontact.sim.Simulator` assembles a scene's contact problem one slot group at a time
(a Python loop over shape pairs) and hands every slot, candidate or not, to the solvers, whose
dense systems grow with the total slot count ``K``. A gripper scene has about a hundred slots of
which a dozen are candidates, so both costs dominate an environment step. :class:`CompactSimulator`
computes the same step:

* the slot geometry of all polygon pairs at once, on vertex tables padded to the largest
  polygon, with the tie rule and candidate test of :func:`~torchcontact.geometry.polygon_slots`;
* the Jacobian rows of all slots at once;
* the solve on a *compacted* problem that keeps the candidate slots of each batch entry (plus
  padding taken from the non-candidates), running the simulator's own sequence: active-set
  iterations from the previous modes, the exact fallback solvers for the entries left, a
  ``solve_mode`` re-solve at the exact modes, canonical modes.

The padding keeps the solvers' tolerance scales unchanged: those take the largest ``|φ| / h`` and
``|bn|`` over *all* slots, so the non-candidate slot with the largest of them is always kept.
Non-candidate slots carry no impulse, so the scattered-back solution is the full one; the test
suite checks it against :meth:`Simulator.step` to round-off.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace

import torch
from torch import Tensor

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
from torchcontact.geometry import (
    TIE_TOLERANCE,
    HalfPlane,
    Polygon,
    SlotGeometry,
    cross2,
    perpendicular,
)
from torchcontact.sim import (
    SOLVED_BY_EXACT_MODE,
    SOLVED_BY_GUESS,
    SOLVED_RAW,
    UNSOLVED,
    Scene,
    SceneState,
    StepResult,
)


@dataclass(frozen=True)
class _Layout:
    """Index tables of a scene, built once (all tensors on the CPU, float64 / long)."""

    vertices: Tensor  # (P, V, 2) padded polygon vertices, body frame
    next_vertex: Tensor  # (P, V) index of the following vertex (padding points at itself)
    vertex_valid: Tensor  # (P, V) bool
    vertex_count: Tensor  # (P,) float64 number of real vertices
    pose_source: Tensor  # (P,) index into [q, q_kinematic, static poses]
    static_poses: Tensor  # (S, 3) poses of static polygons
    pair_receiver: Tensor  # (Gp,) polygon index of each polygon-polygon group's receiver
    pair_other: Tensor  # (Gp,) polygon index of its other polygon
    plane_receiver: Tensor  # (Gh,) polygon index of each polygon-half-plane group's receiver
    plane_point: Tensor  # (Gh, 2)
    plane_normal: Tensor  # (Gh, 2)
    slot_source: Tensor  # (K,) index into the flattened [pair slots; plane slots]
    receiver_polygon: Tensor  # (K,) polygon index of each slot's receiver
    other_polygon: Tensor  # (K,) polygon index of each slot's other body (0 for half-planes)
    receiver_dynamic: Tensor  # (K, Nd) one-hot dynamic column of the receiver
    other_dynamic: Tensor  # (K, Nd) one-hot dynamic column of the other body
    receiver_kinematic: Tensor  # (K, Nk) one-hot kinematic column of the receiver
    other_kinematic: Tensor  # (K, Nk) one-hot kinematic column of the other body
    mu: Tensor  # (K,) friction coefficient of each slot


def _build_layout(scene: Scene) -> _Layout:
    polygons = [i for i, body in enumerate(scene.bodies) if isinstance(body.shape, Polygon)]
    polygon_index = {body: p for p, body in enumerate(polygons)}
    width = max(body.shape.num_vertices for body in scene.bodies if isinstance(body.shape, Polygon))
    P = len(polygons)
    vertices = torch.zeros(P, width, 2, dtype=torch.float64)
    next_vertex = torch.zeros(P, width, dtype=torch.long)
    valid = torch.zeros(P, width, dtype=torch.bool)
    count = torch.zeros(P, dtype=torch.float64)
    num_dynamic, num_kinematic = len(scene.dynamic), len(scene.kinematic)
    static: list[Tensor] = []
    source: list[int] = []
    for p, body_index in enumerate(polygons):
        body = scene.bodies[body_index]
        assert isinstance(body.shape, Polygon)
        local = body.shape.vertices.to(torch.float64)
        V = local.shape[0]
        vertices[p, :V] = local
        vertices[p, V:] = local[0]
        next_vertex[p] = torch.arange(width)
        next_vertex[p, :V] = (torch.arange(V) + 1) % V
        valid[p, :V] = True
        count[p] = V
        if body.kind == "dynamic":
            source.append(scene.dynamic.index(body_index))
        elif body.kind == "kinematic":
            source.append(num_dynamic + scene.kinematic.index(body_index))
        else:
            assert body.pose is not None
            source.append(num_dynamic + num_kinematic + len(static))
            static.append(body.pose.to(torch.float64))

    pair_receiver: list[int] = []
    pair_other: list[int] = []
    plane_receiver: list[int] = []
    plane_point: list[Tensor] = []
    plane_normal: list[Tensor] = []
    located: list[tuple[bool, int]] = []  # per group: (is plane group, its index)
    for group in scene.slot_groups:
        other_shape = scene.bodies[group.other].shape
        if isinstance(other_shape, HalfPlane):
            located.append((True, len(plane_receiver)))
            plane_receiver.append(polygon_index[group.receiver])
            plane_point.append(other_shape.point.to(torch.float64))
            plane_normal.append(other_shape.normal.to(torch.float64))
        else:
            located.append((False, len(pair_receiver)))
            pair_receiver.append(polygon_index[group.receiver])
            pair_other.append(polygon_index[group.other])

    slot_source: list[int] = []
    receiver_polygon: list[int] = []
    other_polygon: list[int] = []
    K = scene.num_slots
    receiver_dynamic = torch.zeros(K, num_dynamic, dtype=torch.float64)
    other_dynamic = torch.zeros(K, num_dynamic, dtype=torch.float64)
    receiver_kinematic = torch.zeros(K, num_kinematic, dtype=torch.float64)
    other_kinematic = torch.zeros(K, num_kinematic, dtype=torch.float64)
    mu: list[float] = []
    for group, (is_plane, g) in zip(scene.slot_groups, located, strict=True):
        base = (len(pair_receiver) + g) * width if is_plane else g * width
        friction = scene.pair_mu(group.receiver, group.other)
        if isinstance(friction, Tensor) and friction.numel() != 1:
            raise ValueError(
                "scene.friction and scene.pair_friction must be scalars for CompactSimulator, "
                f"got a tensor of shape {tuple(friction.shape)}"
            )
        for j in range(group.count):
            k = group.start + j
            slot_source.append(base + j)
            receiver_polygon.append(polygon_index[group.receiver])
            other_polygon.append(polygon_index.get(group.other, 0))
            mu.append(float(friction))
            for member, dynamic, kinematic in (
                (group.receiver, receiver_dynamic, receiver_kinematic),
                (group.other, other_dynamic, other_kinematic),
            ):
                kind = scene.bodies[member].kind
                if kind == "dynamic":
                    dynamic[k, scene.dynamic.index(member)] = 1.0
                elif kind == "kinematic":
                    kinematic[k, scene.kinematic.index(member)] = 1.0

    def long(values: list[int]) -> Tensor:
        return torch.tensor(values, dtype=torch.long)

    def stack(values: list[Tensor], size: int) -> Tensor:
        if values:
            return torch.stack(values)
        return torch.zeros(0, size, dtype=torch.float64)

    return _Layout(
        vertices=vertices,
        next_vertex=next_vertex,
        vertex_valid=valid,
        vertex_count=count,
        pose_source=long(source),
        static_poses=stack(static, 3),
        pair_receiver=long(pair_receiver),
        pair_other=long(pair_other),
        plane_receiver=long(plane_receiver),
        plane_point=stack(plane_point, 2),
        plane_normal=stack(plane_normal, 2),
        slot_source=long(slot_source),
        receiver_polygon=long(receiver_polygon),
        other_polygon=long(other_polygon),
        receiver_dynamic=receiver_dynamic,
        other_dynamic=other_dynamic,
        receiver_kinematic=receiver_kinematic,
        other_kinematic=other_kinematic,
        mu=torch.tensor(mu, dtype=torch.float64),
    )


@dataclass(frozen=True, eq=False)
class CompactSimulator:
    """A drop-in, faster :meth:`~torchcontact.sim.Simulator.step` for scenes with many slots.

    It computes the step of :class:`torchcontact.sim.Simulator` (same slots, same solvers, same
    mode sequence) without autograd, and returns the same :class:`~torchcontact.sim.StepResult`
    with full ``(*B, K)`` slot tensors; see the module docstring for how. Only scalar friction
    coefficients are supported (no per-batch or per-slot friction tensors).

    Grasps make degenerate contact problems (two pads pressing one body from both sides give
    redundant rows), on which Lemke's pivoting can stop with an inaccurate answer and the QP
    fallback, though accurate, is slow. There, ``solve_mode`` at the right modes typically
    returns impulses consistent with them and an LCP residual near 1e-8, but reports no
    convergence (its equality residual stalls above the float64 tolerance on the redundant
    rows). With ``retry_sticking`` the entries that the first fallback solver leaves unsolved
    are tried once more by the batched active-set iteration started from "every candidate
    slot sticking" (the mode of a firm grasp) before the next fallback solver; its answer is
    accepted when it is consistent with its modes and either converged or within
    ``retry_residual`` of solving the LCP. With ``retry_sticking=False`` the step is exactly
    the simulator's.

    Attributes:
        scene: the scene.
        fallback: exact solvers tried in order for entries whose guessed modes fail.
        active_set_iterations: mode corrections tried before the exact solvers.
        retry_sticking: retry from all-sticking modes after the first fallback solver.
        retry_residual: largest LCP residual (:func:`~torchcontact.contact.lcp_residual`) of
            an accepted, unconverged retry.
    """

    scene: Scene
    fallback: tuple[Method, ...] = ("lemke", "qp")
    active_set_iterations: int = 4
    retry_sticking: bool = True
    retry_residual: float = 1e-6
    _layout: _Layout = field(init=False, repr=False)
    _mass_matrix: Tensor = field(init=False, repr=False)
    _gravity_force: Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.scene, Scene):
            raise ValueError(f"scene must be a Scene, got {type(self.scene).__name__}")
        object.__setattr__(self, "_layout", _build_layout(self.scene))
        with torch.no_grad():
            mass_matrix = self.scene.mass_matrix().detach().to(torch.float64)
            masses = self.scene.masses().detach().to(torch.float64)
        gravity = torch.tensor([*self.scene.gravity, 0.0], dtype=torch.float64)
        object.__setattr__(self, "_mass_matrix", mass_matrix)
        object.__setattr__(self, "_gravity_force", masses[:, None] * gravity)

    def geometry(self, state: SceneState) -> SlotGeometry:
        """The slot geometry of every scene of the batch (as the simulator's assembly finds it).

        Args:
            state: the batched state ``*B`` (float64).

        Returns:
            Slot points, normals (world frame), gaps and candidate flags, each ``(*B, K, ...)``.
        """
        return self._geometry(self._polygon_poses(state))

    def step(
        self,
        state: SceneState,
        control: Tensor | None = None,
        *,
        force: Tensor | None = None,
    ) -> StepResult:
        """Advance every scene of a flat batch by one time step.

        Args:
            state: the state, batch ``(B,)``, float64.
            control: ``(B, Nk, 3)`` kinematic-body twists over the step (world frame).
            force: ``(B, Nd, 3)`` applied generalized forces on the dynamic bodies.

        Returns:
            The :class:`~torchcontact.sim.StepResult`, as :meth:`Simulator.step` returns it.

        Raises:
            ValueError: the state is not a flat float64 batch, or ``control`` / ``force`` have
                the wrong shape.
        """
        scene = self.scene
        num_dynamic, num_kinematic = len(scene.dynamic), len(scene.kinematic)
        if state.q.dim() != 3 or state.q.dtype != torch.float64:
            raise ValueError(
                f"state.q must be a float64 tensor of shape (B, {num_dynamic}, 3), "
                f"got {tuple(state.q.shape)} {state.q.dtype}"
            )
        B = state.q.shape[0]
        if control is None:
            control = torch.zeros(B, num_kinematic, 3, dtype=torch.float64)
        if control.shape != (B, num_kinematic, 3):
            raise ValueError(
                f"control must have shape {(B, num_kinematic, 3)}, got {tuple(control.shape)}"
            )
        if force is not None and force.shape != (B, num_dynamic, 3):
            raise ValueError(
                f"force must have shape {(B, num_dynamic, 3)}, got {tuple(force.shape)}"
            )
        with torch.no_grad():
            return self._step(state, control, force)

    # -- assembly ---------------------------------------------------------------------------

    def _polygon_poses(self, state: SceneState) -> Tensor:
        layout = self._layout
        B = state.q.shape[0]
        static = layout.static_poses.expand(B, -1, 3)
        poses = torch.cat([state.q, state.q_kinematic, static], dim=-2)
        return poses[:, layout.pose_source]  # (B, P, 3)

    def _geometry(self, poses: Tensor) -> SlotGeometry:
        layout = self._layout
        cos, sin = torch.cos(poses[..., 2]), torch.sin(poses[..., 2])
        rotation = torch.stack([torch.stack([cos, -sin], -1), torch.stack([sin, cos], -1)], -2)
        world = layout.vertices @ rotation.transpose(-1, -2) + poses[..., None, :2]  # (B,P,V,2)
        margin = self.scene.margin
        parts_points, parts_normals, parts_phi, parts_active = [], [], [], []

        if layout.pair_receiver.numel():
            vertices = world[:, layout.pair_receiver]  # (B, Gp, V, 2)
            other = world[:, layout.pair_other]  # (B, Gp, E, 2)
            following = layout.next_vertex[layout.pair_other]  # (Gp, E)
            valid = layout.vertex_valid[layout.pair_other]  # (Gp, E)
            index = following.unsqueeze(-1).expand(other.shape)
            edge = other.gather(-2, index) - other
            length = edge.norm(dim=-1, keepdim=True)
            safe = torch.where(valid.unsqueeze(-1), length, torch.ones_like(length))
            direction = edge / safe
            outward = -perpendicular(direction)
            relative = vertices.unsqueeze(-2) - other.unsqueeze(-3)  # (B, Gp, V, E, 2)
            distance = (relative * outward.unsqueeze(-3)).sum(-1)  # (B, Gp, V, E)
            lowest = torch.finfo(distance.dtype).min
            distance = torch.where(valid.unsqueeze(-2), distance, lowest)
            phi = distance.amax(dim=-1)
            longest = torch.where(valid, length.squeeze(-1), 0.0).amax(-1, keepdim=True)
            tie = distance >= phi.unsqueeze(-1) - TIE_TOLERANCE * longest.unsqueeze(-1)
            tie = tie & valid.unsqueeze(-2)
            count = layout.vertex_count[layout.pair_other]  # (Gp,)
            masked = torch.where(valid.unsqueeze(-1), other, 0.0)
            center = masked.sum(dim=-2, keepdim=True) / count[:, None, None]
            facing = (vertices - center) @ outward.transpose(-1, -2)  # (B, Gp, V, E)
            closest = torch.where(tie, facing, lowest).argmax(dim=-1)  # (B, Gp, V)
            pick = closest.unsqueeze(-1).expand(*closest.shape, 2)
            normals = outward.gather(-2, pick)
            chosen = relative.gather(-2, pick.unsqueeze(-2)).squeeze(-2)
            along = (chosen * direction.gather(-2, pick)).sum(-1)
            extent = length.squeeze(-1).gather(-1, closest)
            within = (along >= -margin) & (along <= extent + margin)
            parts_points.append(vertices.flatten(1, 2))
            parts_normals.append(normals.flatten(1, 2))
            parts_phi.append(phi.flatten(1, 2))
            parts_active.append(((phi <= margin) & within).flatten(1, 2))

        if layout.plane_receiver.numel():
            vertices = world[:, layout.plane_receiver]  # (B, Gh, V, 2)
            normal = layout.plane_normal[:, None, :]  # (Gh, 1, 2)
            phi = ((vertices - layout.plane_point[:, None, :]) * normal).sum(-1)
            parts_points.append(vertices.flatten(1, 2))
            parts_normals.append(normal.expand(vertices.shape).flatten(1, 2))
            parts_phi.append(phi.flatten(1, 2))
            parts_active.append((phi <= margin).flatten(1, 2))

        source = layout.slot_source
        return SlotGeometry(
            points=torch.cat(parts_points, dim=1)[:, source],
            normals=torch.cat(parts_normals, dim=1)[:, source],
            phi=torch.cat(parts_phi, dim=1)[:, source],
            active=torch.cat(parts_active, dim=1)[:, source],
        )

    def _problem(
        self, state: SceneState, control: Tensor, force: Tensor | None
    ) -> tuple[dict[str, Tensor], SlotGeometry]:
        layout = self._layout
        poses = self._polygon_poses(state)
        geometry = self._geometry(poses)
        normal = geometry.normals
        tangent = perpendicular(normal)
        rows_n, rows_t = [], []
        known_n = torch.zeros_like(geometry.phi)
        known_t = torch.zeros_like(geometry.phi)
        members = (
            (layout.receiver_polygon, layout.receiver_dynamic, layout.receiver_kinematic, 1.0),
            (layout.other_polygon, layout.other_dynamic, layout.other_kinematic, -1.0),
        )
        for polygon, dynamic, kinematic, sign in members:
            offset = geometry.points - poses[:, polygon, :2]  # (B, K, 2)
            row_n = torch.cat([normal, cross2(offset, normal).unsqueeze(-1)], dim=-1)
            row_t = torch.cat([tangent, cross2(offset, tangent).unsqueeze(-1)], dim=-1)
            rows_n.append(sign * dynamic.unsqueeze(-1) * row_n.unsqueeze(-2))  # (B, K, Nd, 3)
            rows_t.append(sign * dynamic.unsqueeze(-1) * row_t.unsqueeze(-2))
            if kinematic.shape[-1]:
                twist = kinematic @ control  # (B, K, 3)
                velocity = twist[..., :2] + twist[..., 2:3] * perpendicular(offset)
                known_n = known_n + sign * (velocity * normal).sum(-1)
                known_t = known_t + sign * (velocity * tangent).sum(-1)
        Jn = (rows_n[0] + rows_n[1]).flatten(-2)
        Jt_row = (rows_t[0] + rows_t[1]).flatten(-2)
        B = state.q.shape[0]
        f = self._gravity_force.expand(B, -1, 3)
        if force is not None:
            f = f + force
        fields = {
            "v": state.v.flatten(-2),
            "f": f.flatten(-2),
            "Jn": Jn,
            "Jt": torch.stack([Jt_row, -Jt_row], dim=-2),
            "phi": geometry.phi,
            "mu": layout.mu.expand(B, -1),
            "mask": geometry.active,
            "bn": known_n,
            "bt": torch.stack([known_t, -known_t], dim=-1),
        }
        return fields, geometry

    # -- solve ------------------------------------------------------------------------------

    def _step(self, state: SceneState, control: Tensor, force: Tensor | None) -> StepResult:
        h = self.scene.h
        fields, geometry = self._problem(state, control, force)
        mask = fields["mask"]
        B, K = mask.shape
        # Candidates first (in slot order), then the non-candidates by decreasing velocity
        # scale, so that the slot that sets the solvers' tolerance scale stays in.
        scale = torch.maximum(fields["phi"].abs() / h, fields["bn"].abs())
        score = torch.where(mask, math.inf, scale)
        order = torch.argsort(score, dim=-1, descending=True, stable=True)
        width = min(K, int(mask.sum(-1).max()) + 1)
        keep = order[:, :width]  # (B, Kc)

        def gather(t: Tensor) -> Tensor:
            index = keep.reshape(B, width, *([1] * (t.dim() - 2)))
            return t.gather(1, index.expand(B, width, *t.shape[2:]))

        problem = ContactProblem(
            M=self._mass_matrix,
            v=fields["v"],
            f=fields["f"],
            Jn=gather(fields["Jn"]),
            Jt=gather(fields["Jt"]),
            phi=gather(fields["phi"]),
            mu=gather(fields["mu"]),
            h=h,
            mask=gather(mask),
            bn=gather(fields["bn"]),
            bt=gather(fields["bt"]),
        )
        solution, solver = self._solve(problem, gather(state.mode))

        def scatter(t: Tensor) -> Tensor:
            full = torch.zeros(B, K, *t.shape[2:], dtype=t.dtype)
            index = keep.reshape(B, width, *([1] * (t.dim() - 2))).expand(t.shape)
            return full.scatter(1, index, t)

        pn, pt, mode = scatter(solution.pn), scatter(solution.pt), scatter(solution.mode)
        v_next = solution.v_next.unflatten(-1, (len(self.scene.dynamic), 3))
        next_state = SceneState(
            q=state.q + h * v_next,
            v=v_next,
            q_kinematic=state.q_kinematic + h * control,
            mode=mode,
        )
        return StepResult(
            state=next_state,
            pn=pn,
            pt=pt,
            mode=mode,
            geometry=geometry,
            solver=solver,
            residual=solution.status.residual,
        )

    def _solve(self, problem: ContactProblem, guess: Tensor) -> tuple[Solution, Tensor]:
        """The simulator's solve sequence (mode guess, exact fallback, canonical modes).

        With ``retry_sticking``, the entries that the first fallback solver leaves unsolved
        are tried once more by the active-set iteration, started from every candidate slot
        sticking, before the remaining fallback solvers.
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
                sticking = subset.slot_mask.long()
                retry = solve_active_set(
                    subset, sticking, max_iterations=self.active_set_iterations
                )
                close = retry.status.residual <= self.retry_residual
                converged = is_consistent(subset, retry) & (retry.status.converged | close)
                if bool(converged.any()):
                    done = pending[converged]
                    solution = solution.scatter(
                        done, retry.map_tensors(lambda t, c=converged: t[c])
                    )
                    solver = solver.index_put((done,), torch.full_like(done, SOLVED_BY_GUESS))
                pending = pending[~converged]
                if pending.numel() == 0:
                    break
            with warnings.catch_warnings():
                # OSQP's "solved inaccurate" is reported through the status already.
                warnings.filterwarnings("ignore", message="OSQP exited", category=UserWarning)
                exact = solve(problem[pending], method)
            converged = exact.status.converged
            done = pending[converged]
            if done.numel():
                exact_done = exact.map_tensors(lambda t, c=converged: t[c])
                again = solve_mode(
                    problem[done],
                    exact_done.mode,
                    initial_impulses=(exact_done.pn, exact_done.pt),
                )
                reproduced = is_consistent(problem[done], again) & again.status.converged
                solution = solution.scatter(done, again.where(reproduced, exact_done))
                codes = torch.where(reproduced, SOLVED_BY_EXACT_MODE, SOLVED_RAW)
                solver = solver.index_put((done,), codes)
            pending = pending[~converged]
        canonical = contact_mode(problem, v_next=solution.v_next, pn=solution.pn, pt=solution.pt)
        return replace(solution, mode=canonical), solver
