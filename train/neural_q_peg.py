"""A neural Q function on the RBPF belief for the peg-in-hole task, by fitted Q iteration.

    python train/dyna_q_peg.py            # first: the tabular Q, graph and belief model
    python train/neural_q_peg.py --tabular-run runs/dyna_q_peg__0__<unix time> --rounds 8
    python train/neural_q_peg.py --tabular-run <that run> --occlusion-radius 0.05 \
        --probe-episodes 0.5 --targets monte_carlo --residual-penalty 0.1
    python train/neural_q_peg.py --tabular-run <that run> --occlusion-radius 0.05 \
        --shift-episodes 0.75 --targets monte_carlo --residual-penalty 0.1

Starts from a finished ``dyna_q_peg`` run (``--tabular-run``, its run folder): its Q table,
manipulation graph and fitted belief model. ``--occlusion-radius`` (and ``--vision-sigma``) run
the same task with another camera (:attr:`~torchcontact.envs.PegInHoleConfig.occlusion_radius`:
the camera loses the peg near the hole, and only touch tells where it is); the task's physics,
so the tabular Q and the belief model's dynamics, are the same.

The network (:class:`~torchcontact.rl.QNetwork`) is QMDP plus a residual on the compact belief
features (the tail of :func:`~torchcontact.experiments.belief_features`: pose mean and spread,
class entropy, ESS, class marginals, and the latest touch: blind camera, which bottom half
touches): ``Q(b, a) = Σ_i p_i Q_tab(m_i, a) + g(z, a)``. The QMDP
head is frozen; ``g`` starts at zero, so before any update the network acts exactly as QMDP.
Each round plays ``--num-envs`` episodes with the filter in the loop, ε-greedy on the network
(ε decays linearly over the transitions), storing belief transitions (features, action, shaped
reward with the tabular agent's shaping and discount, next features); then fitted Q
iteration: ``--fitted-iterations`` times, freeze a copy as the target and take
``--updates-per-iteration`` Adam steps of the double-DQN Huber loss on replayed batches, plus a
trust region around QMDP's policy: ``--residual-penalty`` times the mean square of the
residual's action-dependent part ``g(z, a) − mean_b g(z, b)`` (the part common to all
actions, QMDP's optimism about the belief's value, changes no decision and is free). The buffer
stores the QMDP values of each belief (``A``) with its compact features (``F``), not the
probabilities over all states: with a frozen head they are all the network needs. Where the
camera is blind, QMDP never acts to find out where the peg is: ``--probe-episodes`` lets a
fraction of the training episodes probe first (press the peg down while blind and laterally
uncertain until a bottom sensor fires, :func:`~torchcontact.experiments.probe_presses`), so
the data hold what probing leads to; ``--shift-episodes`` lets a fraction follow the
touch-and-shift probe instead (:func:`~torchcontact.experiments.shift_actions` on the
network's greedy action: move away from a bottom corner that touches alone, press while
blind and uncertain), the probe that reads a touch as a lateral position; and ``--targets
monte_carlo`` fits each step's discounted return to the end of its episode instead of the
bootstrapped target (a Q evaluation of that behaviour; the greedy network is one step of
policy improvement over it). ``--blind-only`` multiplies the residual by the blind-camera
feature (the network is QMDP wherever the camera sees). The greedy network is evaluated every
few rounds on validation episodes; the best (the untrained network, i.e. QMDP, included) is
kept. Finally the settings are compared on the same fresh episodes (oracle, raw on the
standard camera, QMDP, press-then-QMDP and the touch-and-shift probe on the occluded variant,
neural; seeded by ``--final-seed``, so runs of other training seeds can share them).
``--belief physics`` (or ``both``) runs the final QMDP and neural rows on the contact
physics' belief model (:class:`~torchcontact.envs.PegPhysicsModel`, built as ``dyna_q_peg``
builds it; the features, with the class marginals summed over its modes, mean the same);
``--final-settings`` picks the rows (``raw`` on the occluded variant holds the last camera
pose in the gripper). A finished run resumed with other values of these, ``--final-episodes``,
``--final-seed`` or ``--mode-episodes`` only evaluates again.
Writes TensorBoard logs, checkpoints, ``network.pt`` and ``results.md`` to a new run folder,
``runs/neural_q_peg__<seed>__<unix time>``; a killed run continues where its last checkpoint
left it, to the same result, with ``--resume <that folder>`` (the same arguments; ``--rounds``
may grow).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
import tyro
from tqdm import tqdm

from torchcontact.envs import (
    PegInHole2DVector,
    PegInHoleBeliefModel,
    PegInHoleFilter,
    PegInHoleTask,
    PegPhysicsModel,
)
from torchcontact.experiments import (
    CHECKPOINT,
    NUM_BELIEF_FEATURES,
    PRESS,
    PROBE_THRESHOLD,
    SETTINGS,
    PotentialShaping,
    QLookup,
    RunLog,
    Setting,
    belief_features,
    bottom_sides,
    bottom_touch,
    check_choice,
    check_int,
    check_name,
    check_real,
    evaluate,
    evaluate_settings,
    lateral_spread,
    open_run,
    probe_presses,
    read_checkpoint,
    results_table,
    round_seed,
    run_round,
    save_checkpoint,
    scalar_metrics,
    shift_actions,
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
#: The targets of ``--targets``.
_TARGETS = ("td", "monte_carlo")
#: The belief models of ``--belief``, by name.
_BELIEFS = ("fitted", "physics", "both")
#: Arguments used only by the final comparison: a finished run resumes with other values of
#: these and only evaluates again.
_EVALUATION = ("final_episodes", "final_seed", "belief", "mode_episodes", "final_settings")
#: The checkpoint's entries besides ``"args"``.
#: Index of the blind-camera flag among the compact features (see ``belief_features``).
BLIND_FEATURE = NUM_BELIEF_FEATURES - 3
_SAVED = ("round", "online", "optimizer", "buffer", "counters", "history", "best")


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
    """seed of the episodes, network and buffer"""
    occlusion_radius: float = 0.0
    """the camera loses the peg within this distance of the hole's mouth, m (0: never)"""
    vision_sigma: float = 0.0
    """camera position noise std, m (angle: 10x, rad); 0: the tabular run's camera"""
    num_envs: int = 32
    """episodes per round"""
    rounds: int = 8
    """training rounds"""
    particles: int = 64
    """RBPF particles"""
    hidden: int = 64
    """width of the residual's 2 hidden layers"""
    learning_rate: float = 1e-3
    """Adam step size"""
    residual_penalty: float = 10.0
    """trust region around QMDP's policy: this times the mean square of the residual's
    action-dependent part (its deviation from its mean over actions) joins the loss"""
    buffer_size: int = 100_000
    """replay capacity (transitions)"""
    batch_size: int = 256
    """replay batch size"""
    learning_starts: int = 1_000
    """transitions stored before the first fitted iteration"""
    fitted_iterations: int = 10
    """fitted Q iterations (target-network copies) after each round"""
    updates_per_iteration: int = 200
    """Adam steps per fitted iteration"""
    epsilon_start: float = 0.2
    """initial ε of the training episodes"""
    epsilon_end: float = 0.05
    """final ε"""
    epsilon_steps: int = 20_000
    """transitions over which ε decays"""
    eval_every: int = 1
    """rounds between validations"""
    eval_episodes: int = 64
    """validation episodes (the same every time)"""
    final_episodes: int = 200
    """episodes per setting in the final comparison"""
    final_seed: int | None = None
    """seed of the final comparison's episodes (None: --seed + 104729); runs with other
    --seed values compare on the same episodes when they share it"""
    probe_episodes: float = 0.0
    """fraction of the training episodes whose behaviour probes: presses the peg down while
    the camera is blind and the belief's lateral spread exceeds --probe-threshold, until a
    bottom sensor fires (the scripted probe-then-insert policy on the network)"""
    shift_episodes: float = 0.0
    """fraction of the training episodes (drawn after --probe-episodes, among the others)
    whose behaviour is the touch-and-shift probe on the network's greedy action"""
    probe_threshold: float = PROBE_THRESHOLD
    """lateral spread of the belief above which probing presses, m (also the probe and shift
    settings of the final comparison)"""
    belief: str = "fitted"
    """the belief model of the final comparison's qmdp and neural rows: fitted, physics or
    both (training and validation always run on the fitted one; the network's features are
    the same under either)"""
    mode_episodes: int = 64
    """greedy episodes on the true state whose contact modes make the physics model's table
    (as in dyna_q_peg: the same episodes for the same tabular run)"""
    final_settings: tuple[str, ...] = ()
    """the settings of the final comparison (empty: oracle, raw, qmdp, neural on a camera
    that always sees; oracle, qmdp, probe, shift, neural on the occluded variant)"""
    press_penalty: float | None = None
    """with a value: the trust region measures advantages from the mean residual of the
    actions other than pressing ("-y"), weighs pressing's by this value and the others' by
    --residual-penalty (a large one keeps their order QMDP's: the residual then learns when
    to press, the probing decision); None: every action's by --residual-penalty"""
    blind_only: bool = False
    """gate the residual by the blind-camera feature: the network is QMDP wherever the camera
    sees the peg, and learns only what to do while blind"""
    targets: str = "td"
    """td: double-DQN targets bootstrapped from a frozen copy; monte_carlo: each step's
    discounted shaped return to the end of its episode (fitted Q evaluation of the
    behaviour, whose greedy policy is one step of policy improvement)"""


@dataclasses.dataclass
class _Tabular:
    """What the neural run takes from the tabular one (the model on this run's camera)."""

    agent: DynaQ
    model: PegInHoleBeliefModel
    shaping: PotentialShaping
    seed: int
    """the tabular run's seed (its physics model's greedy episodes)"""


def _load_tabular(args: Args) -> _Tabular:
    folder = Path(args.tabular_run)
    checkpoint, model_path = folder / CHECKPOINT, folder / "belief_model.pt"
    for path in (checkpoint, model_path):
        if not path.is_file():
            raise ValueError(
                f"tabular_run {str(folder)!r} has no {path.name}: run train/dyna_q_peg.py first"
            )
    saved = read_checkpoint(checkpoint, keys=("args", "agent", "round"))
    if saved["round"] < saved["args"]["rounds"]:
        raise ValueError(f"tabular_run {str(folder)!r} has not finished its rounds")
    model: PegInHoleBeliefModel = torch.load(model_path, weights_only=False)
    config = model.task.config
    sigma = args.vision_sigma
    camera = (sigma, sigma, 10 * sigma) if sigma > 0 else config.pose_noise_std
    config = dataclasses.replace(
        config, occlusion_radius=args.occlusion_radius, pose_noise_std=camera
    )
    model = dataclasses.replace(model, task=PegInHoleTask(config))
    return _Tabular(
        DynaQ.from_state_dict(saved["agent"]),
        model,
        PotentialShaping(saved["args"]["shaping"]),
        saved["args"]["seed"],
    )


def check_args(args: Args) -> _Tabular:
    """Check every argument (before any work) and return what the tabular run gives.

    Raises:
        ValueError: an argument is out of range (the message names it and its range), or
            ``tabular_run`` is not a finished ``dyna_q_peg`` run.
    """
    check_name("name", args.name)
    for name in ("num_envs", "rounds", "hidden", "buffer_size", "batch_size"):
        check_int(name, getattr(args, name), low=1)
    for name in ("eval_every", "eval_episodes", "final_episodes", "mode_episodes"):
        check_int(name, getattr(args, name), low=1)
    for name in ("seed", "learning_starts", "fitted_iterations", "updates_per_iteration"):
        check_int(name, getattr(args, name), low=0)
    check_int("epsilon_steps", args.epsilon_steps, low=0)
    if args.final_seed is not None:
        check_int("final_seed", args.final_seed, low=0)
    check_real("learning_rate", args.learning_rate, low=0.0, low_open=True)
    check_real("residual_penalty", args.residual_penalty, low=0.0)
    check_real("occlusion_radius", args.occlusion_radius, low=0.0)
    check_real("vision_sigma", args.vision_sigma, low=0.0)
    check_real("epsilon_start", args.epsilon_start, low=0.0, high=1.0)
    check_real("epsilon_end", args.epsilon_end, low=0.0, high=1.0)
    check_real("probe_episodes", args.probe_episodes, low=0.0, high=1.0)
    check_real("shift_episodes", args.shift_episodes, low=0.0, high=1.0)
    check_real("probe_threshold", args.probe_threshold, low=0.0)
    if args.press_penalty is not None:
        check_real("press_penalty", args.press_penalty, low=0.0)
    check_choice("targets", args.targets, _TARGETS)
    check_choice("belief", args.belief, _BELIEFS)
    for setting in args.final_settings:
        check_choice("final_settings", setting, SETTINGS)
    tabular = _load_tabular(args)
    K = tabular.model.num_modes
    check_int("particles", args.particles, low=K, why="the belief model's number of modes K")
    return tabular


def compact_network(args: Args, num_actions: int) -> QNetwork:
    """The network the buffer trains: input the QMDP values ``(A)`` then the compact features
    ``(F)``; its head is the identity, so its values are those of :func:`deployed_network`
    with the same residual on the full features."""
    network = QNetwork.from_table(
        torch.eye(num_actions, dtype=DTYPE),
        NUM_BELIEF_FEATURES,
        hidden=(args.hidden, args.hidden),
        residual_on_probabilities=False,
        gate=BLIND_FEATURE if args.blind_only else None,
    )
    network.table.requires_grad_(False)
    return network


def deployed_network(table: torch.Tensor, compact: QNetwork) -> QNetwork:
    """The network on :func:`~torchcontact.experiments.belief_features`: QMDP head ``table
    (M, A)`` and the residual of ``compact``."""
    network = QNetwork.from_table(
        table.to(DTYPE),
        compact.num_features,
        hidden=[m.out_features for m in compact.residual if isinstance(m, torch.nn.Linear)][:-1],
        residual_on_probabilities=False,
        gate=compact.gate,
    )
    network.residual.load_state_dict(compact.residual.state_dict())
    return network


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
    run_dir, saved = open_run(args, keys=_SAVED, free=_EVALUATION)
    agent, model = tabular.agent, tabular.model
    config = model.task.config
    lookup = QLookup(agent, model.task.states)
    filt = PegInHoleFilter(model, num_particles=args.particles)
    torch.manual_seed(args.seed)  # the residual's hidden layers start random
    online = compact_network(args, model.num_actions)
    target = compact_network(args, model.num_actions)
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
        optimizer.load_state_dict(saved["optimizer"])
        buffer.load_state_dict(saved["buffer"])
        start, counters = saved["round"], saved["counters"]
        history, best = saved["history"], saved["best"]
    else:
        best = _validate(args, eval_env, lookup, filt, online, round_index=-1)
    log = RunLog(run_dir, args)
    writer = log.writer
    first_step = counters["transitions"]
    for r in tqdm(range(start, args.rounds), desc="fqi rounds", initial=start, total=args.rounds):
        row = _collect(
            args,
            env,
            filt,
            lookup,
            tabular,
            online=online,
            buffer=buffer,
            schedule=schedule,
            counters=counters,
            round_index=r,
        )
        if len(buffer) >= args.learning_starts:
            row |= _fit(
                args, online, target, optimizer, buffer, counters, gamma=tabular.agent.gamma
            )
        step = counters["transitions"]
        log.steps_per_second(step - first_step, step)
        writer.add_scalar("charts/episodic_return", row["episodic_return"], step)
        writer.add_scalar("charts/episode_length", row["episode_length"], step)
        writer.add_scalar("charts/success_rate", row["success_rate"], step)
        writer.add_scalar("charts/epsilon", row["epsilon"], step)
        if "loss" in row:
            writer.add_scalar("losses/td_loss", row["loss"], step)
            writer.add_scalar("losses/advantage_rms", row["advantage_rms"], step)
        if (r + 1) % args.eval_every == 0 or r + 1 == args.rounds:
            candidate = _validate(args, eval_env, lookup, filt, online, round_index=r)
            row["eval_success"] = candidate["success"]
            writer.add_scalar("eval/neural_success", candidate["success"], step)
            if candidate["success"] > best["success"]:
                best = candidate
        history.append(row)
        save_checkpoint(
            run_dir / CHECKPOINT,
            {
                "args": dataclasses.asdict(args),
                "round": r + 1,
                "online": online.state_dict(),
                "optimizer": optimizer.state_dict(),
                "buffer": buffer.state_dict(),
                "counters": counters,
                "history": history,
                "best": best,
            },
        )
    online.load_state_dict(best["state"])
    network = deployed_network(lookup.table, online)
    settings = final_settings(args, config.occlusion_radius)
    filters, physics = None, None
    if args.belief != "fitted":
        physics = _physics_model(args, tabular, model.task)
        filters = {"physics": PegInHoleFilter(physics, num_particles=args.particles)}
        if args.belief == "both":
            filters = {"fitted": filt, **filters}
    evaluations = evaluate_settings(
        settings,
        num_episodes=args.final_episodes,
        config=config,
        lookup=lookup,
        seed=final_seed(args),
        filt=filt,
        network=network,
        filters=filters,
        probe_threshold=args.probe_threshold,
    )
    for e in evaluations:
        tag = e.setting.replace(" + ", "_")
        writer.add_scalar(f"eval/final_{tag}_success", e.success_rate, counters["transitions"])
    log.close()
    torch.save(network.state_dict(), run_dir / "network.pt")
    for e in evaluations:
        tag = e.setting.replace(" + ", "_")
        np.save(run_dir / f"successes_{tag}.npy", e.successes)
        np.save(run_dir / f"lengths_{tag}.npy", e.lengths)
    sigma = config.pose_noise_std
    text = (
        f"# Neural Q on the RBPF belief, peg-in-hole ({counters['transitions']} training "
        f"transitions; kept: {_kept(best['round'])})\n\n"
        f"Camera noise σ = {1e3 * sigma[0]:.1f} mm, {sigma[2]:.3f} rad, occlusion radius "
        f"{1e3 * config.occlusion_radius:.0f} mm; {args.particles} particles; tabular Q from "
        f"{args.tabular_run} ({agent.num_states} states)"
        + (f"; physics model: {physics.num_modes} contact modes" if physics else "")
        + f"; {args.final_episodes} final episodes, seed {final_seed(args)}.\n\n"
        f"{results_table(evaluations)}\n"
    )
    (run_dir / "results.md").write_text(text)
    result = {
        "run_dir": str(run_dir),
        "history": history,
        "best_round": best["round"],
        "evaluations": {e.setting: e.success_rate for e in evaluations},
        "execution": {e.setting: e.metrics() for e in evaluations},
    }
    metrics = scalar_metrics(result)
    (run_dir / "metrics.json").write_text(json.dumps(metrics, indent=1) + "\n")
    return result


def final_settings(args: Args, occlusion_radius: float) -> tuple[Setting, ...]:
    """The final comparison's settings: ``--final-settings``, else the task's defaults."""
    if args.final_settings:
        return tuple(args.final_settings)  # type: ignore[arg-type]
    if occlusion_radius == 0:
        return ("oracle", "raw", "qmdp", "neural")
    return ("oracle", "qmdp", "probe", "shift", "neural")


def _physics_model(args: Args, tabular: _Tabular, task: PegInHoleTask) -> PegPhysicsModel:
    """The physics belief model on this run's camera, as ``dyna_q_peg`` builds it: the contact
    modes of ``--mode-episodes`` greedy episodes on the true state (seeded by the tabular run's
    seed), the graph's class transition."""
    true_state = dataclasses.replace(task.config, occlusion_radius=0.0)
    greedy = run_round(
        PegInHole2DVector(num_envs=args.mode_episodes, config=true_state),
        tabular.agent,
        seed=tabular.seed * 1_000_003 + 900_000,
        shaping=tabular.shaping,
        learn=False,
    )
    return PegPhysicsModel.fit(
        greedy.slot_modes, greedy.transitions.next_classes, tabular.agent.graph, task=task
    )


def final_seed(args: Args) -> int:
    """The seed of the final comparison's episodes: ``--final-seed``, else ``--seed + 104729``."""
    return args.seed + 104_729 if args.final_seed is None else args.final_seed


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
    compact: QNetwork,
    *,
    round_index: int,
) -> dict[str, Any]:
    """Greedy success of the network on the validation episodes (the same every time)."""
    network = deployed_network(lookup.table, compact)
    result = evaluate(
        env, "neural", lookup=lookup, seed=args.seed + 7_919, filt=filt, network=network
    )
    state = {k: v.detach().clone() for k, v in compact.state_dict().items()}
    return {"success": result.success_rate, "round": round_index, "state": state}


def _inputs(
    filt: PegInHoleFilter, belief: Any, lookup: QLookup, observation: dict[str, Any]
) -> torch.Tensor:
    """``(B, A + F)`` the compact network's input: QMDP values, then the compact features."""
    features = belief_features(filt, belief, lookup, observation)
    M = lookup.table.shape[0]
    qmdp = features[:, :M] @ lookup.table
    return torch.cat([qmdp, features[:, M:]], -1).to(DTYPE)


def _collect(
    args: Args,
    env: PegInHole2DVector,
    filt: PegInHoleFilter,
    lookup: QLookup,
    tabular: _Tabular,
    *,
    online: QNetwork,
    buffer: ReplayBuffer,
    schedule: EpsilonSchedule,
    counters: dict[str, int],
    round_index: int,
) -> dict[str, float]:
    """One ε-greedy episode per environment with the filter in the loop, into the buffer.

    A fraction ``args.probe_episodes`` of the episodes (drawn per round) probes first
    (:func:`~torchcontact.experiments.probe_presses`); with ``args.targets ==
    "monte_carlo"`` each step is stored with its discounted shaped return to the episode's end
    as reward, and as terminal.

    Everything random in a round (episodes, filter, exploration) is seeded by the round's
    index, and the buffer's sampler is checkpointed, so a resumed run equals a straight one.
    """
    gamma, shaping, depth = tabular.agent.gamma, tabular.shaping, env.config.insertion_depth
    seed = round_seed(args.seed * 1_000_003, round_index, num_envs=env.num_envs)
    generator = torch.Generator().manual_seed(seed)
    observation, info = env.reset(seed=seed)
    belief = filt.init(observation)
    inputs = _inputs(filt, belief, lookup, observation)
    potential = shaping.potential(env.states, info["peg_pose"], depth)
    B = env.num_envs
    live = np.ones(B, dtype=bool)
    returns, lengths = np.zeros(B), np.zeros(B, dtype=np.int64)
    successes = np.zeros(B, dtype=bool)
    draw = torch.rand(B, generator=generator)
    probing = draw < args.probe_episodes
    shifting = ~probing & (draw < args.probe_episodes + args.shift_episodes)
    touched = torch.zeros(B, dtype=torch.bool)
    steps: list[dict[str, torch.Tensor]] = []
    epsilon = schedule(counters["transitions"])
    while live.any():
        epsilon = schedule(counters["transitions"])
        with torch.no_grad():
            values = online(inputs)
        noise = 1e-6 * torch.rand(values.shape, generator=generator, dtype=values.dtype)
        greedy = (values + noise).argmax(-1)
        random = torch.randint(filt.model.num_actions, (B,), generator=generator)
        explore = torch.rand(B, generator=generator) < epsilon
        blind = torch.as_tensor(np.isnan(observation["peg_pose"]).all(-1))
        spread = lateral_spread(filt, belief)
        press = probing & probe_presses(
            blind=blind, spread=spread, touched=touched, threshold=args.probe_threshold
        )
        sides = bottom_sides(filt.model.task, torch.as_tensor(observation["tactile"]).bool())
        shift = shift_actions(
            greedy, blind=blind, spread=spread, sides=sides, threshold=args.probe_threshold
        )
        behaviour = torch.where(shifting, shift, greedy)
        actions = torch.where(press, PRESS, torch.where(explore, random, behaviour)).numpy()
        observation, reward, terminated, truncated, info = env.step(actions)
        touched |= press & bottom_touch(filt.model.task, torch.as_tensor(observation["tactile"]))
        belief = filt.step(belief, actions, observation, generator=generator)
        next_inputs = _inputs(filt, belief, lookup, observation)
        next_potential = shaping.potential(env.states, info["peg_pose"], depth)
        shaped = shaping.shaped(
            reward,
            potential=potential,
            next_potential=next_potential,
            terminated=terminated,
            gamma=gamma,
        )
        steps.append(
            {
                "observation": inputs,
                "action": torch.as_tensor(actions),
                "reward": torch.as_tensor(shaped),
                "next_observation": next_inputs,
                "terminal": torch.as_tensor(terminated),
                "live": torch.as_tensor(live),
            }
        )
        counters["transitions"] += int(live.sum())
        returns[live] += reward[live]
        lengths[live] += 1
        successes |= live & info["success"]
        live = live & ~(terminated | truncated)
        inputs, potential = next_inputs, next_potential
    if args.targets == "monte_carlo":  # each step's discounted return to its episode's end
        to_go = torch.zeros(B, dtype=torch.float64)
        for step in reversed(steps):
            to_go = torch.where(step["live"], step["reward"] + gamma * to_go, 0.0)
            step["reward"], step["terminal"] = to_go.clone(), torch.ones(B, dtype=torch.bool)
    for step in steps:
        index = torch.nonzero(step["live"]).squeeze(-1)
        buffer.add(**{k: v[index] for k, v in step.items() if k != "live"})
    return {
        "round": round_index,
        "transitions": counters["transitions"],
        "success_rate": float(successes.mean()),
        "episodic_return": float(returns.mean()),
        "episode_length": float(lengths.mean()),
        "epsilon": epsilon,
    }


def _fit(
    args: Args,
    online: QNetwork,
    target: QNetwork,
    optimizer: torch.optim.Optimizer,
    buffer: ReplayBuffer,
    counters: dict[str, int],
    *,
    gamma: float,
) -> dict[str, float]:
    """Fitted Q iteration on the buffer: per iteration a frozen target and Adam steps on the
    double-DQN loss (or the Monte Carlo regression: terminal rows) plus the trust-region
    penalty, ``residual_penalty`` on every action's advantage, or with ``press_penalty`` that
    weight on pressing's advantage over the other actions' mean residual."""
    losses, residuals = [], []
    A = online.num_actions
    others = torch.arange(A) != PRESS
    weights = torch.where(others, args.residual_penalty, args.press_penalty or 0.0).to(DTYPE)
    for _ in range(args.fitted_iterations):
        update_target(target=target, online=online)
        for _ in range(args.updates_per_iteration):
            batch = buffer.sample(args.batch_size)
            residual = online.residual_values(batch.observations)
            # Only the part that differs between actions changes decisions: the common part
            # (QMDP's optimism about the value of the belief) is free.
            if args.press_penalty is None:
                advantage = residual - residual.mean(-1, keepdim=True)
                trust = args.residual_penalty * advantage.square().mean()
            else:  # the other actions' mean is the common part; pressing has its own weight
                common = residual[:, others].mean(-1, keepdim=True)
                advantage = residual - common
                trust = (weights * advantage.square()).mean()
            penalty = advantage.square().mean()
            loss = dqn_loss(online, target, batch, gamma, double=True)
            optimizer.zero_grad()
            (loss + trust).backward()
            optimizer.step()
            counters["updates"] += 1
            losses.append(float(loss.detach()))
            residuals.append(float(penalty.detach()))
    if not losses:  # no NaN placeholders: the history must compare equal after a resume
        return {}
    return {"loss": float(np.mean(losses)), "advantage_rms": float(np.sqrt(np.mean(residuals)))}


def main(argv: list[str] | None = None) -> None:
    """Parse the command line and run."""
    result = run(tyro.cli(Args, args=argv, description=__doc__.splitlines()[0]))
    print(Path(result["run_dir"], "results.md").read_text())


if __name__ == "__main__":
    main()
