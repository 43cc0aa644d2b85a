"""A neural Q function on the RBPF belief for the peg-in-hole task, trained DQN-style.

    python train/dyna_q_peg.py            # first: the tabular Q, graph and belief model
    python train/neural_q_peg.py --tabular-run runs/dyna_q_peg__0__<unix time> --rounds 20

Starts from a finished ``dyna_q_peg`` run (``--tabular-run``, its run folder): its Q table,
manipulation graph and fitted belief model. The network (:class:`~torchcontact.rl.QNetwork`) reads
:func:`~torchcontact.experiments.belief_features` of the filter's belief; its QMDP head is the
Q table and its residual MLP starts at zero, so before any update it acts exactly as QMDP over
the RBPF belief. It is then trained with double DQN (replay buffer, target network, Huber
loss, linearly decaying ε) on rounds of noisy-observation episodes with the filter in the
loop, on the same shaped reward and discount factor as the tabular agent. Only the residual
learns unless ``--train-table``: the head stays the tabular Q, so the network learns what the
belief's spread and pose add to QMDP. The greedy network
is evaluated every few rounds on validation episodes; the best one (the untrained network
included) is kept. Finally oracle, raw, QMDP and neural Q are compared on the same fresh
episodes. Writes TensorBoard logs, checkpoints, ``network.pt`` and ``results.md`` to a new
run folder, ``runs/neural_q_peg__<seed>__<unix time>``; a killed run continues where its last
checkpoint left it, to the same result, with ``--resume <that folder>`` (the same arguments;
``--rounds`` may grow).
"""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import torch
import tyro
from tqdm import tqdm

from torchcontact.envs import PegInHole2DVector, PegInHoleBeliefModel, PegInHoleFilter
from torchcontact.experiments import (
    CHECKPOINT,
    NUM_BELIEF_FEATURES,
    PotentialShaping,
    QLookup,
    RunLog,
    belief_features,
    check_int,
    check_name,
    check_real,
    evaluate,
    evaluate_settings,
    open_run,
    read_checkpoint,
    results_table,
    round_seed,
    save_checkpoint,
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
#: The checkpoint's entries besides ``"args"``.
_SAVED = ("round", "online", "target", "optimizer", "buffer", "counters", "history", "best")


@dataclasses.dataclass(frozen=True)
class Args:
    """Arguments of the neural-Q peg-in-hole experiment."""

    tabular_run: str
    """folder of a finished dyna_q_peg run (checkpoint, belief model), e.g.
    runs/dyna_q_peg__0__<unix time>"""
    name: str = "neural_q_peg"
    """experiment name: a new run writes to <out-dir>/<name>__<seed>__<unix time>"""
    out_dir: str = "runs"
    """parent of the new run folders"""
    resume: str | None = None
    """a run folder to continue from its checkpoint (the same arguments; rounds may grow)"""
    seed: int = 0
    """seed of the episodes and buffer"""
    num_envs: int = 16
    """episodes per round"""
    rounds: int = 20
    """training rounds"""
    particles: int = 64
    """RBPF particles"""
    hidden: int = 64
    """width of the 2 hidden layers"""
    learning_rate: float = 1e-4
    """Adam step size"""
    train_table: bool = False
    """also train the QMDP head (default: frozen; only the residual learns)"""
    buffer_size: int = 10_000
    """replay capacity"""
    batch_size: int = 128
    """replay batch size"""
    learning_starts: int = 1_000
    """transitions stored before the first update"""
    updates_per_step: int = 1
    """gradient steps per batched environment step"""
    target_every: int = 250
    """gradient steps between target-network copies"""
    epsilon_start: float = 0.1
    """initial ε"""
    epsilon_end: float = 0.02
    """final ε"""
    epsilon_steps: int = 20_000
    """transitions over which ε decays"""
    eval_every: int = 4
    """rounds between evals"""
    eval_episodes: int = 48
    """validation episodes per evaluation"""
    final_episodes: int = 100
    """episodes per setting in the final comparison"""


@dataclasses.dataclass
class _Tabular:
    """What the neural run takes from the tabular one."""

    agent: DynaQ
    model: PegInHoleBeliefModel
    shaping: PotentialShaping


def _load_tabular(folder: Path) -> _Tabular:
    checkpoint, model_path = folder / CHECKPOINT, folder / "belief_model.pt"
    for path in (checkpoint, model_path):
        if not path.is_file():
            raise ValueError(
                f"tabular_run {str(folder)!r} has no {path.name}: run train/dyna_q_peg.py first"
            )
    saved = read_checkpoint(checkpoint, keys=("args", "agent", "round"))
    if saved["round"] < saved["args"]["rounds"]:
        raise ValueError(f"tabular_run {str(folder)!r} has not finished its rounds")
    model = torch.load(model_path, weights_only=False)
    return _Tabular(
        DynaQ.from_state_dict(saved["agent"]), model, PotentialShaping(saved["args"]["shaping"])
    )


def check_args(args: Args) -> _Tabular:
    """Check every argument (before any work) and return what the tabular run gives.

    Raises:
        ValueError: an argument is out of range (the message names it and its range), or
            ``tabular_run`` is not a finished ``dyna_q_peg`` run.
    """
    check_name("name", args.name)
    for name in ("num_envs", "rounds", "hidden", "buffer_size", "batch_size", "target_every"):
        check_int(name, getattr(args, name), low=1)
    for name in ("eval_every", "eval_episodes", "final_episodes"):
        check_int(name, getattr(args, name), low=1)
    for name in ("seed", "learning_starts", "updates_per_step", "epsilon_steps"):
        check_int(name, getattr(args, name), low=0)
    check_real("learning_rate", args.learning_rate, low=0.0, low_open=True)
    check_real("epsilon_start", args.epsilon_start, low=0.0, high=1.0)
    check_real("epsilon_end", args.epsilon_end, low=0.0, high=1.0)
    tabular = _load_tabular(Path(args.tabular_run))
    K = tabular.model.num_modes
    check_int("particles", args.particles, low=K, why="the belief model's number of modes K")
    return tabular


def run(args: Args) -> dict[str, Any]:
    """Train the network from the tabular run, evaluate, write the artefacts; return metrics.

    A new run gets a new folder (:func:`~torchcontact.experiments.new_run_dir`); with
    ``args.resume`` the run continues in that folder from its checkpoint.

    Raises:
        ValueError: an argument is out of range (before any work), or the checkpoint to resume
            is damaged or was written with other arguments.
    """
    tabular = check_args(args)
    torch.set_num_threads(1)
    run_dir, saved = open_run(args, keys=_SAVED)
    checkpoint_path = run_dir / CHECKPOINT
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
    if saved is not None:
        online.load_state_dict(saved["online"])
        target.load_state_dict(saved["target"])
        optimizer.load_state_dict(saved["optimizer"])
        buffer.load_state_dict(saved["buffer"])
        start, counters = saved["round"], saved["counters"]
        history, best = saved["history"], saved["best"]
    else:
        best = _validate(args, eval_env, lookup, filt, online, round_index=-1)
    log = RunLog(run_dir, args)
    writer = log.writer
    first_step = counters["transitions"]
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
        log.steps_per_second(step - first_step, step)
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
        save_checkpoint(
            checkpoint_path,
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
    log.close()
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
    result = run(tyro.cli(Args, args=argv, description=__doc__.splitlines()[0]))
    print(Path(result["run_dir"], "results.md").read_text())


if __name__ == "__main__":
    main()
