"""Dyna-Q on the planar peg-in-hole task, then execution under uncertainty with the RBPF.

    python train/dyna_q_peg.py --rounds 12 --planning-steps 10

Learns a tabular Q function over manipulation states (pose cell × contact class) and the
manipulation graph with Dyna-Q on rounds of batched episodes (one episode per environment per
round, true state, shaped reward, count-directed ε exploration), with value iteration on the
graph after each round when planning, evaluating the greedy policy every few rounds. Then builds
the RBPF's belief models, the fitted one (contact-class-conditioned grasp motion and tactile
model fitted on the recorded steps) and the physics one (the peg's mode-decoupled contact
dynamics, its mode table from greedy episodes on the true state), both with the graph as
transition, and executes the policy on noisy observations: oracle (true state), greedy on the
raw observation, and QMDP over the RBPF belief of each model. Writes TensorBoard logs,
checkpoints, ``q_table.pt``, ``graph.json``, ``belief_model.pt``, ``physics_model.pt``,
``learning.png``, ``graph.png`` (the graph merged to contact states), ``results.md`` and
``metrics.json`` (every scalar result, as :func:`~torchcontact.experiments.aggregate_seeds`
reads them) to a new run folder, ``runs/dyna_q_peg__<seed>__<unix time>``. A killed run
continues where its last checkpoint left it, to the same result, with ``--resume
runs/dyna_q_peg__<seed>__<unix time>`` (the same arguments; ``--rounds`` may grow;
``--final-episodes``, ``--particles``, ``--vision-sigma``, ``--belief`` and
``--mode-episodes`` may differ, to evaluate a finished run again without training).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any, get_args

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch
import tyro
from tqdm import tqdm

from torchcontact.envs import (
    NUM_CONTACT_CLASSES,
    PegInHole2DVector,
    PegInHoleBeliefModel,
    PegInHoleConfig,
    PegInHoleFilter,
    PegInHoleTask,
    PegPhysicsModel,
    PegTransitions,
)
from torchcontact.experiments import (
    CHECKPOINT,
    PegLearning,
    QLookup,
    RunLog,
    check_choice,
    check_int,
    check_name,
    check_real,
    evaluate_settings,
    open_run,
    results_table,
    round_seed,
    run_round,
    save_checkpoint,
    scalar_metrics,
)
from torchcontact.rl import Exploration, StepSize
from torchcontact.states import ManipulationGraph, ManipulationState

_LEARNING = PegLearning()
#: Arguments used only after training: a finished run resumes with other values of these and
#: only fits the belief model and evaluates again.
_EVALUATION = ("final_episodes", "particles", "vision_sigma", "belief", "mode_episodes")
#: The belief models of ``--belief``, by name.
_BELIEFS = ("both", "fitted", "physics")
#: The checkpoint's entries besides ``"args"``.
_SAVED = ("agent", "round", "transitions", "history")
_MODES = "the belief model's number of modes K"


@dataclasses.dataclass(frozen=True)
class Args:
    """Arguments of the Dyna-Q peg-in-hole experiment."""

    name: str = "dyna_q_peg"
    """experiment name: a new run writes to <out-dir>/<name>__<seed>__<unix time>"""
    out_dir: str = "runs"
    """parent of the new run folders"""
    resume: str | None = None
    """a run folder to continue from its checkpoint (rounds may grow; final-episodes,
    particles and vision-sigma may differ: a finished run is evaluated again)"""
    seed: int = 0
    """seed of the agent and episodes"""
    num_envs: int = 32
    """episodes per round"""
    rounds: int = 12
    """training rounds"""
    max_steps: int = 200
    """steps per episode"""
    planning_steps: int = _LEARNING.planning_steps
    """Dyna-Q planning n"""
    alpha: float = _LEARNING.alpha
    """Q-learning step size (the floor with --step-size visits)"""
    step_size: StepSize = _LEARNING.step_size
    """constant (alpha) or visits (max(alpha, 1/N(s, a)))"""
    planning_penalty: float = _LEARNING.planning_penalty
    """pessimism of planning and sweeps: rewards less this / sqrt(N(s, a))"""
    gamma: float = _LEARNING.gamma
    """discount factor"""
    epsilon: float = _LEARNING.epsilon
    """exploration rate"""
    exploration: Exploration = _LEARNING.exploration
    """ε exploration: uniform or least_tried"""
    sweep: bool = True
    """value iteration on the graph after each round (if planning_steps > 0)"""
    shaping: float = _LEARNING.shaping
    """potential-based shaping scale, reward per metre"""
    eval_every: int = 2
    """rounds between evals"""
    eval_episodes: int = 32
    """greedy episodes per evaluation during training"""
    final_episodes: int = 100
    """episodes per setting in the final evaluation (0: none)"""
    particles: int = 64
    """RBPF particles"""
    vision_sigma: float = 0.002
    """camera position noise std, m (angle: 10x, rad)"""
    belief: str = "both"
    """the RBPF's belief model in QMDP: fitted, physics or both (raw always decodes the
    sensors with the fitted tactile model)"""
    mode_episodes: int = 64
    """greedy episodes on the true state whose contact modes make the physics model's table"""
    x_edges: str = ""
    """grid cell edges along x, m, comma-separated (empty: the default)"""
    y_edges: str = ""
    """grid cell edges along y, m, comma-separated (empty: the default)"""
    angle_edges: str = ""
    """grid cell edges of the angle, rad, comma-separated (empty: default)"""


def _config(args: Args, noisy: bool) -> PegInHoleConfig:
    sigma = args.vision_sigma
    noise = (sigma, sigma, 10 * sigma) if noisy else PegInHoleConfig().pose_noise_std
    grid: dict[str, tuple[float, ...]] = {}
    for name in ("x_edges", "y_edges", "angle_edges"):
        text = getattr(args, name).strip()
        if text:
            try:
                grid[name] = tuple(float(value) for value in text.split(","))
            except ValueError:
                raise ValueError(f"{name} must be comma-separated numbers, got {text!r}") from None
    return PegInHoleConfig(max_steps=args.max_steps, pose_noise_std=noise, **grid)


def check_args(args: Args) -> PegLearning:
    """Check every argument (before any work) and return the learning settings.

    Raises:
        ValueError: an argument is out of range; the message names it and its range.
    """
    check_name("name", args.name)
    for name in ("num_envs", "rounds", "max_steps", "eval_every", "eval_episodes"):
        check_int(name, getattr(args, name), low=1)
    check_int("seed", args.seed, low=0)
    check_int("planning_steps", args.planning_steps, low=0)
    check_int("final_episodes", args.final_episodes, low=0)
    check_int("mode_episodes", args.mode_episodes, low=1)
    check_choice("belief", args.belief, _BELIEFS)
    check_int("particles", args.particles, low=NUM_CONTACT_CLASSES, why=_MODES)
    check_choice("step_size", args.step_size, get_args(StepSize))
    check_choice("exploration", args.exploration, get_args(Exploration))
    check_real("alpha", args.alpha, low=0.0, high=1.0, low_open=True)
    check_real("gamma", args.gamma, low=0.0, high=1.0)
    check_real("epsilon", args.epsilon, low=0.0, high=1.0)
    check_real("planning_penalty", args.planning_penalty, low=0.0)
    check_real("shaping", args.shaping, low=0.0)
    check_real("vision_sigma", args.vision_sigma, low=0.0, low_open=True)
    _config(args, noisy=True)  # the grid edges, checked by PegInHoleConfig
    learning = PegLearning(
        alpha=args.alpha,
        step_size=args.step_size,
        planning_steps=args.planning_steps,
        planning_penalty=args.planning_penalty,
        gamma=args.gamma,
        epsilon=args.epsilon,
        exploration=args.exploration,
        shaping=args.shaping,
    )
    learning.agent(seed=args.seed)  # DynaQ checks the settings too
    return learning


def run(args: Args) -> dict[str, Any]:
    """Train, evaluate, write the artefacts; return the metrics.

    A new run gets a new folder (:func:`~torchcontact.experiments.new_run_dir`); with
    ``args.resume`` the run continues in that folder from its checkpoint.

    Raises:
        ValueError: an argument is out of range (before any work), or the checkpoint to resume
            is damaged or was written with other arguments.
    """
    learning = check_args(args)
    torch.set_num_threads(1)
    run_dir, saved = open_run(args, keys=_SAVED, free=_EVALUATION)
    checkpoint_path = run_dir / CHECKPOINT
    agent = learning.agent(seed=args.seed)
    shaping = learning.potential_shaping()
    start, parts, history = 0, [], []
    if saved is not None:
        agent.load_state_dict(saved["agent"])
        start, parts, history = saved["round"], [saved["transitions"]], saved["history"]
    env = PegInHole2DVector(num_envs=args.num_envs, config=_config(args, noisy=False))
    eval_env = PegInHole2DVector(num_envs=args.eval_episodes, config=_config(args, noisy=False))
    log = RunLog(run_dir, args)
    writer = log.writer
    episodes, env_steps = start * args.num_envs, 0
    for r in tqdm(
        range(start, args.rounds), desc="dyna-q rounds", initial=start, total=args.rounds
    ):
        updates_before, clock = agent.planning_updates, time.perf_counter()
        seed = round_seed(args.seed * 1_000_003, r, num_envs=args.num_envs)
        result = run_round(env, agent, seed=seed, shaping=shaping)
        if args.sweep and args.planning_steps > 0:
            sweep = agent.sweep()
            if not sweep.converged:
                raise RuntimeError(f"value iteration did not converge: {sweep}")
        seconds = time.perf_counter() - clock
        parts.append(result.transitions)
        episodes += args.num_envs
        env_steps += int(result.lengths.sum())
        log.steps_per_second(env_steps, episodes)
        row: dict[str, float] = {
            "round": r,
            "episodes": episodes,
            "success_rate": float(result.successes.mean()),
            "episodic_return": float(result.returns.mean()),
            "episode_length": float(result.lengths.mean()),
            "td_error": result.td_error,
        }
        writer.add_scalar("charts/episodic_return", row["episodic_return"], episodes)
        writer.add_scalar("charts/episode_length", row["episode_length"], episodes)
        writer.add_scalar("charts/success_rate", row["success_rate"], episodes)
        writer.add_scalar("losses/td_error", result.td_error, episodes)
        writer.add_scalar(
            "charts/planning_updates_per_second",
            (agent.planning_updates - updates_before) / seconds,
            episodes,
        )
        if (r + 1) % args.eval_every == 0 or r + 1 == args.rounds:
            greedy = run_round(
                eval_env,
                agent,
                seed=round_seed(args.seed * 1_000_003 + 500_000, r, num_envs=args.eval_episodes),
                shaping=shaping,
                learn=False,
            )
            row["greedy_success"] = float(greedy.successes.mean())
            writer.add_scalar("eval/greedy_success", row["greedy_success"], episodes)
        history.append(row)
        parts = [PegTransitions.concat(parts)]  # one piece: saved now, fitted on at the end
        save_checkpoint(
            checkpoint_path,
            {
                "args": dataclasses.asdict(args),
                "agent": agent.state_dict(),
                "round": r + 1,
                "transitions": parts[0],
                "history": history,
            },
        )
    data = PegTransitions.concat(parts)
    noisy = _config(args, noisy=True)
    task = PegInHoleTask(noisy)
    lookup = QLookup(agent, task.states)
    model = PegInHoleBeliefModel.fit(data, agent.graph, task=task)
    filters = {"fitted": PegInHoleFilter(model, num_particles=args.particles)}
    physics = None
    if args.belief != "fitted":
        greedy = run_round(
            PegInHole2DVector(num_envs=args.mode_episodes, config=_config(args, noisy=False)),
            agent,
            seed=args.seed * 1_000_003 + 900_000,
            shaping=shaping,
            learn=False,
        )
        physics = PegPhysicsModel.fit(
            greedy.slot_modes, greedy.transitions.next_classes, agent.graph, task=task
        )
        filters["physics"] = PegInHoleFilter(physics, num_particles=args.particles)
    if args.belief == "physics":
        del filters["fitted"]
    evaluations = (
        evaluate_settings(
            ("oracle", "raw", "qmdp"),
            num_episodes=args.final_episodes,
            config=noisy,
            lookup=lookup,
            seed=args.seed + 7919,
            filt=PegInHoleFilter(model, num_particles=args.particles),
            filters=filters,
        )
        if args.final_episodes > 0
        else []
    )
    for e in evaluations:
        tag = e.setting.replace(" + ", "_")
        writer.add_scalar(f"eval/{tag}_success", e.success_rate, episodes)
    log.close()
    torch.save(agent.q_table(), run_dir / "q_table.pt")
    agent.graph.save(run_dir / "graph.json")
    torch.save(model, run_dir / "belief_model.pt")
    if physics is not None:
        torch.save(physics, run_dir / "physics_model.pt")
    _plot_learning(history, run_dir / "learning.png")
    _plot_graph(agent.graph, run_dir / "graph.png")
    evaluated = [h for h in history if "greedy_success" in h]
    curve = (
        "| training episodes | "
        + " | ".join(f"{h['episodes']:.0f}" for h in evaluated)
        + " |\n|---|"
        + "--:|" * len(evaluated)
        + "\n| greedy success (true state) | "
        + " | ".join(f"{100 * h['greedy_success']:.1f} %" for h in evaluated)
        + " |\n"
    )
    text = (
        f"# Dyna-Q peg-in-hole ({episodes} training episodes, n = {args.planning_steps}, "
        f"seed {args.seed})\n\n{curve}\n"
        f"Camera noise σ = {1e3 * args.vision_sigma:.1f} mm, {10 * args.vision_sigma:.3f} rad; "
        f"{args.particles} particles; {agent.num_states} manipulation states visited"
        + (f"; physics model: {physics.num_modes} contact modes" if physics else "")
        + ".\n\n"
        f"{results_table(evaluations) if evaluations else 'No final evaluation.'}\n"
    )
    (run_dir / "results.md").write_text(text)
    result = {
        "run_dir": str(run_dir),
        "history": history,
        "evaluations": {e.setting: e.success_rate for e in evaluations},
        "execution": {e.setting: e.metrics() for e in evaluations},
        "learning": {f"greedy_success@{h['episodes']:.0f}": h["greedy_success"] for h in evaluated},
        "num_states": agent.num_states,
    }
    metrics = scalar_metrics(result)
    (run_dir / "metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
    return result


def _plot_learning(history: list[dict[str, float]], path: Path) -> None:
    fig, ax = plt.subplots(figsize=(6, 3.5))
    episodes = np.array([h["episodes"] for h in history])
    ax.plot(episodes, [h["success_rate"] for h in history], label="training (ε-greedy)")
    evaluated = [h for h in history if "greedy_success" in h]
    ax.plot(
        [h["episodes"] for h in evaluated],
        [h["greedy_success"] for h in evaluated],
        "o-",
        label="greedy",
    )
    ax.set_xlabel("training episodes")
    ax.set_ylabel("success rate")
    ax.set_ylim(-0.02, 1.02)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _plot_graph(graph: ManipulationGraph, path: Path) -> None:
    """The manipulation graph merged to contact states (the pose cells are too many to draw)."""
    contact_graph = graph.merged(lambda state: ManipulationState((), state.contact))
    fig, ax = plt.subplots(figsize=(11, 5.5))
    labels = {i: str(state.contact) for i, state in enumerate(contact_graph.states)}
    contact_graph.draw(ax, labels=labels)
    ax.set_title(f"manipulation graph by contact state ({graph.num_states} states merged)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    """Parse the command line and run."""
    result = run(tyro.cli(Args, args=argv, description=__doc__.splitlines()[0]))
    print(Path(result["run_dir"], "results.md").read_text())


if __name__ == "__main__":
    main()
