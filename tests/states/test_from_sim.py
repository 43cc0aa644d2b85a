"""Contact states and the manipulation graph from simulator rollouts of a pushed box."""

from __future__ import annotations

import math

import torch

from torchcontact.geometry import HalfPlane, Polygon
from torchcontact.sim import Body, Scene, Simulator
from torchcontact.states import (
    FeatureGrid,
    ManipulationGraph,
    PoseGrid,
    manipulation_states,
    object_contacts,
)


def test_pushed_box_rests_slides_or_tips_and_the_graph_records_it() -> None:
    """A finger pushes a tall box low (it slides) or high (it tips over its front corner).

    Sliding needs the friction force μ m g; it tips instead when μ m g · height > m g a, i.e.
    for push heights above a / μ = 0.33 m: the low push (0.1 m) slides, the high one (0.9 m)
    tips.
    """
    scene = Scene(
        bodies=(
            Body("ground", HalfPlane.ground(), kind="static"),
            Body("box", Polygon.box(0.4, 1.0), mass=2.0),
            Body("finger", Polygon.box(0.1, 0.1), kind="kinematic"),
        ),
        friction=0.6,
        h=0.01,
    )
    sim = Simulator(scene)
    q = torch.tensor([[[0.0, 0.5, 0.0]], [[0.0, 0.5, 0.0]]], dtype=torch.float64)
    finger = torch.tensor([[[-0.3, 0.1, 0.0]], [[-0.3, 0.9, 0.0]]], dtype=torch.float64)
    steps = 60
    controls = torch.tensor([0.3, 0.0, 0.0], dtype=torch.float64).expand(steps, 2, 1, 3)
    run = sim.rollout(sim.initial_state(q=q, q_kinematic=finger), steps=steps, controls=controls)

    contact_grid = FeatureGrid(dim=2, radius=0.05, angle=math.radians(15))
    pose_grid = PoseGrid(dim=2, position_step=0.5, angle_step=math.pi)
    graph = ManipulationGraph(1)
    episodes: list[list[str]] = [[], []]
    previous = None
    for t in range(steps):
        contacts = object_contacts(
            scene,
            body="box",
            q=run.q[t],
            points=run.points[t],
            normals=run.normals[t],
            pn=run.pn[t],
            mode=run.mode[t],
            active=run.active[t],
        )
        states = manipulation_states(
            contacts,
            robot_pose=run.q_kinematic[t, :, 0],
            contact_grid=contact_grid,
            pose_grid=pose_grid,
        )
        for episode, state in zip(episodes, states, strict=True):
            episode.append(str(state.contact))
        if previous is not None:
            for before, after in zip(previous, states, strict=True):
                graph.observe(before, 0, after, 0.0)
        previous = states

    low, high = episodes
    assert low[0] == high[0] == "E2st"  # resting on both bottom corners, no finger
    # Sliding on both corners, pushed by a sticking finger whose face is flat on the box's:
    # the push is shared by its two corners (the split between them is not unique; the mode
    # solve's shares the load).
    assert low[-1] == "E2sl R2st"
    assert high[-1] == "E1st R1sl"  # tipping on one corner, the finger sliding up its face
    assert run.q[-1, 1, 0, 2].item() < -0.1  # the high push rotated the box clockwise
    assert abs(run.q[-1, 0, 0, 2].item()) < 1e-9  # the low push did not
    labels = {str(state.contact) for state in graph.states}
    assert {"E2st", "E2sl R2st", "E1st R1sl"} <= labels
    # The resting state leads (possibly through a transient) to sliding and to tipping, and
    # the final states are absorbing in these rollouts.
    for final in (low[-1], high[-1]):
        state = next(s for s in graph.states if str(s.contact) == final)
        row = graph.transition_probabilities(state, 0)
        assert row[graph.index(state)].item() > 0.9
