"""A neural Q function on the RBPF belief for the peg-in-hole task, trained DQN-style.

    python train/dyna_q_peg.py            # first: the tabular Q, graph and belief model
    python train/neural_q_peg.py --rounds 20

Starts from a finished ``dyna_q_peg`` run (``--tabular-run``): its Q table, manipulation
graph and fitted belief model. The network (:class:`~torchcontact.rl.QNetwork`) reads
:func:`~torchcontact.experiments.belief_features` of the filter's belief; its QMDP head is the
Q table and its residual MLP starts at zero, so before any update it acts exactly as QMDP over
the RBPF belief. It is then trained with double DQN (replay buffer, target network, Huber
loss, linearly decaying ε) on rounds of noisy-observation episodes with the filter in the
loop, on the same shaped reward and discount factor as the tabular agent. Only the residual
learns unless ``--train-table``: the head stays the tabular Q, so the network learns what the
belief's spread and pose add to QMDP. The greedy network
is evaluated every few rounds on validation episodes; the best one (the untrained network
included) is kept. Finally oracle, raw, QMDP and neural Q are compared on the same fresh
episodes. Writes TensorBoard logs, checkpoints (resumed exactly), ``network.pt`` and
``results.md`` to ``runs/<name>``.
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from torchcontact.envs import PegInHole2DVector, PegInHoleBeliefModel, PegInHoleFilter
from torchcontact.experiments import (
    NUM_BELIEF_FEATURES,
    PotentialShaping,
    QLookup,
    belief_features,
    evaluate,
    evaluate_settings,
    load_checkpoint,
    parse_dataclass,
    results_table,
    round_seed,
)
from torchcontact.rl import (
    DynaQ,
    EpsilonSchedule,
    QNetwork,
    ReplayBuffer,
    dqn_loss,
    update_target,
)

DTYPE = torch.float32


@dataclasses.dataclass(frozen=True)
class Args:
    """Arguments of the neural-Q peg-in-hole experiment."""

    name: str = dataclasses.field(default="neural_q_peg", metadata={"help": "run name"})
    out_dir: str = dataclasses.field(default="runs", metadata={"help": "parent of the run folder"})
    tabular_run: str = dataclasses.field(
        default="runs/dyna_q_peg",
        metadata={"help": "folder of a finished dyna_q_peg run (checkpoint, belief model)"},
    )
    seed: int = dataclasses.field(default=0, metadata={"help": "seed of the episodes and buffer"})
    num_envs: int = dataclasses.field(default=16, metadata={"help": "episodes per round"})
    rounds: int = dataclasses.field(default=20, metadata={"help": "training rounds"})
    particles: int = dataclasses.field(default=64, metadata={"help": "RBPF particles"})
    hidden: int = dataclasses.field(default=64, metadata={"help": "width of the 2 hidden layers"})
    learning_rate: float = dataclasses.field(default=1e-4, metadata={"help": "Adam step size"})
    train_table: bool = dataclasses.field(
        default=False,
        metadata={"help": "also train the QMDP head (default: frozen; only the residual learns)"},
    )
    buffer_size: int = dataclasses.field(default=10_000, metadata={"help": "replay capacity"})
    batch_size: int = dataclasses.field(default=128, metadata={"help": "replay batch size"})
    learning_starts: int = dataclasses.field(
        default=1_000, metadata={"help": "transitions stored before the first update"}
    )
    updates_per_step: int = dataclasses.field(
        default=1, metadata={"help": "gradient steps per batched environment step"}
    )
    target_every: int = dataclasses.field(
        default=250, metadata={"help": "gradient steps between target-network copies"}
    )
    epsilon_start: float = dataclasses.field(default=0.1, metadata={"help": "initial ε"})
    epsilon_end: float = dataclasses.field(default=0.02, metadata={"help": "final ε"})
    epsilon_steps: int = dataclasses.field(
        default=20_000, metadata={"help": "transitions over which ε decays"}
    )
    eval_every: int = dataclasses.field(default=4, metadata={"help": "rounds between evals"})
    eval_episodes: int = dataclasses.field(
        default=48, metadata={"help": "validation episodes per evaluation"}
    )
    final_episodes: int = dataclasses.field(
        default=100, metadata={"help": "episodes per setting in the final comparison"}
    )
    resume: bool = dataclasses.field(
        default=True, metadata={"help": "continue from the run folder's checkpoint"}
    )


@dataclasses.dataclass
class _Tabular:
    """What the neural run takes from the tabular one."""

    agent: DynaQ
    model: PegInHoleBeliefModel
    shaping: PotentialShaping


def _load_tabular(folder: Path) -> _Tabular:
    checkpoint, model_path = folder / "checkpoint.pt", folder / "belief_model.pt"
    for path in (checkpoint, model_path):
        if not path.is_file():
            raise ValueError(
                f"tabular_run {str(folder)!r} has no {path.name}: run train/dyna_q_peg.py first"
            )
    saved = torch.load(checkpoint, weights_only=False)
    if saved["round"] < saved["args"]["rounds"]:
        raise ValueError(f"tabular_run {str(folder)!r} has not finished its rounds")
    model = torch.load(model_path, weights_only=False)
    return _Tabular(
        DynaQ.from_state_dict(saved["agent"]), model, PotentialShaping(saved["args"]["shaping"])
    )


def run(args: Args) -> dict[str, Any]:
    """Train the network from the tabular run, evaluate, write the artefacts; return metrics."""
    torch.set_num_threads(1)
    run_dir = Path(args.out_dir) / args.name
    run_dir.mkdir(parents=True, exist_ok=True)
    checkpoint_path = run_dir / "checkpoint.pt"
    tabular = _load_tabular(Path(args.tabular_run))
    agent, model = tabular.agent, tabular.model
    config = model.task.config
    lookup = QLookup(agent, model.task.states)
    filt = PegInHoleFilter(model, num_particles=args.particles)
    torch.manual_seed(args.seed)  # the residual's hidden layers start random
    online = QNetwork.from_table(
        lookup.table.to(DTYPE), NUM_BELIEF_FEATURES, hidden=(args.hidden, args.hidden)
    )
    online.table.requires_grad_(args.train_table)
    target = copy.deepcopy(online)
    trained = [p for p in online.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(trained, lr=args.learning_rate)
    buffer = ReplayBuffer(args.buffer_size, online.input_size, dtype=DTYPE, seed=args.seed)
    schedule = EpsilonSchedule(args.epsilon_start, args.epsilon_end, args.epsilon_steps)
    env = PegInHole2DVector(num_envs=args.num_envs, config=config, observation="noisy")
    eval_env = PegInHole2DVector(num_envs=args.eval_episodes, config=config, observation="noisy")
    start, counters, history = 0, {"transitions": 0, "updates": 0}, []
    best: dict[str, Any] = {}
    saved = load_checkpoint(checkpoint_path, args) if args.resume else None
    if saved is not None:
        online.load_state_dict(saved["online"])
        target.load_state_dict(saved["target"])
        optimizer.load_state_dict(saved["optimizer"])
        buffer.load_state_dict(saved["buffer"])
        start, counters = saved["round"], saved["counters"]
        history, best = saved["history"], saved["best"]
    else:
        best = _validate(args, eval_env, lookup, filt, online, round_index=-1)
    writer = SummaryWriter(str(run_dir))
    for r in tqdm(range(start, args.rounds), desc="dqn rounds", initial=start, total=args.rounds):
        row = _train_round(
            args,
            env,
            filt,
            lookup,
            tabular,
            online=online,
            target=target,
            optimizer=optimizer,
            buffer=buffer,
            schedule=schedule,
            counters=counters,
            round_index=r,
        )
        step = counters["transitions"]
        writer.add_scalar("charts/episodic_return", row["episodic_return"], step)
        writer.add_scalar("charts/episode_length", row["episode_length"], step)
        writer.add_scalar("charts/success_rate", row["success_rate"], step)
        writer.add_scalar("charts/epsilon", row["epsilon"], step)
        if "loss" in row:
            writer.add_scalar("losses/td_loss", row["loss"], step)
            writer.add_scalar("losses/q_values", row["q_mean"], step)
        if (r + 1) % args.eval_every == 0 or r + 1 == args.rounds:
            candidate = _validate(args, eval_env, lookup, filt, online, round_index=r)
            row["eval_success"] = candidate["success"]
            writer.add_scalar("eval/neural_success", candidate["success"], step)
            if candidate["success"] > best["success"]:
                best = candidate
        history.append(row)
        torch.save(
            {
                "args": dataclasses.asdict(args),
                "round": r + 1,
                "online": online.state_dict(),
                "target": target.state_dict(),
                "optimizer": optimizer.state_dict(),
                "buffer": buffer.state_dict(),
                "counters": counters,
                "history": history,
                "best": best,
            },
            checkpoint_path,
        )
    online.load_state_dict(best["state"])
    evaluations = evaluate_settings(
        ("oracle", "raw", "qmdp", "neural"),
        num_episodes=args.final_episodes,
        config=config,
        lookup=lookup,
        seed=args.seed + 104_729,
        filt=filt,
        network=online,
    )
    for e in evaluations:
        writer.add_scalar(
            f"eval/final_{e.setting}_success", e.success_rate, counters["transitions"]
        )
    writer.close()
    torch.save(online.state_dict(), run_dir / "network.pt")
    sigma = config.pose_noise_std
    text = (
        f"# Neural Q on the RBPF belief, peg-in-hole ({counters['transitions']} training "
        f"transitions; kept: {_kept(best['round'])})\n\n"
        f"Camera noise σ = {1e3 * sigma[0]:.1f} mm, {sigma[2]:.3f} rad; {args.particles} "
        f"particles; tabular Q from {args.tabular_run} ({agent.num_states} states).\n\n"
        f"{results_table(evaluations)}\n"
    )
    (run_dir / "results.md").write_text(text)
    return {
        "run_dir": str(run_dir),
        "history": history,
        "best_round": best["round"],
        "evaluations": {e.setting: e.success_rate for e in evaluations},
    }


def _kept(round_index: int) -> str:
    """Which network the validation kept, in words (round ``-1`` is the untrained one)."""
    if round_index < 0:
        return "the untrained network, i.e. QMDP"
    return f"the network after round {round_index + 1}"


def _validate(
    args: Args,
    env: PegInHole2DVector,
    lookup: QLookup,
    filt: PegInHoleFilter,
    network: QNetwork,
    *,
    round_index: int,
) -> dict[str, Any]:
    """Greedy success of ``network`` on the validation episodes (the same every time)."""
    result = evaluate(
        env, "neural", lookup=lookup, seed=args.seed + 7_919, filt=filt, network=network
    )
    state = {k: v.detach().clone() for k, v in network.state_dict().items()}
    return {"success": result.success_rate, "round": round_index, "state": state}


def _train_round(
    args: Args,
    env: PegInHole2DVector,
    filt: PegInHoleFilter,
    lookup: QLookup,
    tabular: _Tabular,
    *,
    online: QNetwork,
    target: QNetwork,
    optimizer: torch.optim.Optimizer,
    buffer: ReplayBuffer,
    schedule: EpsilonSchedule,
    counters: dict[str, int],
    round_index: int,
) -> dict[str, float]:
    """One episode per environment with the filter in the loop; DQN updates as it goes.

    Everything random in a round (episodes, filter, exploration) is seeded by the round's
    index, and the buffer's sampler is checkpointed, so a resumed run equals a straight one.
    """
    gamma, shaping, depth = tabular.agent.gamma, tabular.shaping, env.config.insertion_depth
    seed = round_seed(args.seed * 1_000_003, round_index, num_envs=env.num_envs)
    generator = torch.Generator().manual_seed(seed)
    observation, info = env.reset(seed=seed)
    belief = filt.init(observation)
    features = belief_features(filt, belief, lookup).to(DTYPE)
    potential = shaping.potential(env.states, info["peg_pose"], depth)
    B = env.num_envs
    live = np.ones(B, dtype=bool)
    returns, lengths = np.zeros(B), np.zeros(B, dtype=np.int64)
    successes = np.zeros(B, dtype=bool)
    losses: list[float] = []
    q_means: list[float] = []
    while live.any():
        epsilon = schedule(counters["transitions"])
        with torch.no_grad():
            values = online(features)
        noise = 1e-6 * torch.rand(values.shape, generator=generator, dtype=values.dtype)
        greedy = (values + noise).argmax(-1)
        random = torch.randint(filt.model.num_actions, (B,), generator=generator)
        explore = torch.rand(B, generator=generator) < epsilon
        actions = torch.where(explore, random, greedy).numpy()
        observation, reward, terminated, truncated, info = env.step(actions)
        belief = filt.step(belief, actions, observation, generator=generator)
        next_features = belief_features(filt, belief, lookup).to(DTYPE)
        next_potential = shaping.potential(env.states, info["peg_pose"], depth)
        shaped = shaping.shaped(
            reward,
            potential=potential,
            next_potential=next_potential,
            terminated=terminated,
            gamma=gamma,
        )
        index = torch.as_tensor(np.flatnonzero(live))
        buffer.add(
            observation=features[index],
            action=torch.as_tensor(actions)[index],
            reward=torch.as_tensor(shaped)[index],
            next_observation=next_features[index],
            terminal=torch.as_tensor(terminated)[index],
        )
        counters["transitions"] += int(live.sum())
        if len(buffer) >= args.learning_starts:
            for _ in range(args.updates_per_step):
                batch = buffer.sample(args.batch_size)
                loss = dqn_loss(online, target, batch, gamma, double=True)
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                counters["updates"] += 1
                if counters["updates"] % args.target_every == 0:
                    update_target(target=target, online=online)
                losses.append(float(loss.detach()))
            q_means.append(float(values.mean()))
        returns[live] += reward[live]
        lengths[live] += 1
        successes |= live & info["success"]
        live = live & ~(terminated | truncated)
        features, potential = next_features, next_potential
    row = {
        "round": round_index,
        "transitions": counters["transitions"],
        "success_rate": float(successes.mean()),
        "episodic_return": float(returns.mean()),
        "episode_length": float(lengths.mean()),
        "epsilon": epsilon,
    }
    if losses:  # no NaN placeholders: the history must compare equal after a resume
        row |= {"loss": float(np.mean(losses)), "q_mean": float(np.mean(q_means))}
    return row


def main(argv: list[str] | None = None) -> None:
    """Parse the command line and run."""
    result = run(parse_dataclass(Args, argv, __doc__.splitlines()[0]))
    print(Path(result["run_dir"], "results.md").read_text())


if __name__ == "__main__":
    main()
