"""The neural-Q peg script trains from a tabular run on a tiny budget (standard camera and the
occluded variant), keeps QMDP as its head, and resumes exactly."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest
import torch

from tests.train import assert_logged, load_script
from torchcontact.envs import PegInHole2DVector, PegInHoleFilter
from torchcontact.experiments import NUM_BELIEF_FEATURES, QLookup
from torchcontact.rl import DynaQ, EpsilonSchedule, ReplayBuffer


@pytest.fixture(scope="module")
def module() -> ModuleType:
    return load_script("neural_q_peg")


def _tiny(module: ModuleType, out: Path, tabular: Path, **changes: object) -> object:
    args = module.Args(
        out_dir=str(out),
        tabular_run=str(tabular),
        num_envs=3,
        rounds=2,
        particles=24,
        hidden=8,
        buffer_size=64,
        batch_size=8,
        learning_starts=6,
        fitted_iterations=2,
        updates_per_iteration=3,
        epsilon_steps=20,
        eval_every=1,
        eval_episodes=2,
        final_episodes=3,
    )
    return dataclasses.replace(args, **changes)


@pytest.fixture(scope="module")
def straight(
    module: ModuleType, tabular_run: Path, tmp_path_factory: pytest.TempPathFactory
) -> dict[str, Any]:
    """A tiny run without interruption."""
    result: dict[str, Any] = module.run(
        _tiny(module, tmp_path_factory.mktemp("straight"), tabular_run)
    )
    return result


def test_trains_from_the_tabular_run_and_writes_its_artefacts(
    module: ModuleType, straight: dict[str, Any], tabular_run: Path
) -> None:
    result = straight
    run_dir = Path(result["run_dir"])
    args = _tiny(module, run_dir.parent, tabular_run)
    assert_logged(run_dir, [f.name for f in dataclasses.fields(args)], dataclasses.asdict(args))
    for name in ("results.md", "network.pt", "checkpoint.pt"):
        assert (run_dir / name).is_file(), name
    assert list(run_dir.glob("events.out.tfevents.*"))
    assert set(result["evaluations"]) == {"oracle", "raw", "qmdp", "neural"}
    history = result["history"]
    assert len(history) == 2
    assert "loss" in history[-1]  # updates happened
    assert history[-1]["transitions"] > history[0]["transitions"] > 0
    assert "| neural | 3 |" in (run_dir / "results.md").read_text()
    state = torch.load(run_dir / "network.pt")
    assert state["table"].shape[1] == 7


@pytest.mark.bitwise("the head is never trained: it holds a copy of the tabular Q")
def test_the_network_is_the_tabular_qmdp_head_plus_the_residual(
    module: ModuleType, tabular_run: Path, straight: dict[str, Any]
) -> None:
    """The saved network's head is the tabular Q; its values on belief features equal the
    QMDP values of the probabilities plus the residual of the compact features, which is how
    the buffer's compact network (QMDP values, then the features) was trained."""
    saved = torch.load(tabular_run / "checkpoint.pt", weights_only=False)
    table = DynaQ.from_state_dict(saved["agent"]).q_table(dtype=torch.float32)
    state = torch.load(Path(straight["run_dir"]) / "network.pt")
    assert torch.equal(state["table"], table)
    args = _tiny(module, Path(straight["run_dir"]).parent, tabular_run)
    compact = module.compact_network(args, 7)
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for parameter in compact.residual.parameters():
            parameter.copy_(torch.randn(parameter.shape, generator=generator))
    network = module.deployed_network(table, compact)
    M = table.shape[0]
    p = torch.softmax(torch.randn(5, M, generator=generator), -1)
    z = torch.randn(5, NUM_BELIEF_FEATURES, generator=generator)
    expected = p @ table + compact.residual(z)
    values = network(torch.cat([p, z], -1))
    torch.testing.assert_close(values, expected, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(compact(torch.cat([p @ table, z], -1)), expected)


def test_blind_only_keeps_qmdp_wherever_the_camera_sees(
    module: ModuleType, tabular_run: Path, tmp_path: Path
) -> None:
    """``--blind-only``: the residual of the compact and of the deployed network is zero on
    features whose blind flag (third from the end) is 0, whatever the weights."""
    args = _tiny(module, tmp_path, tabular_run, blind_only=True)
    compact = module.compact_network(args, 7)
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for parameter in compact.residual.parameters():
            parameter.copy_(torch.randn(parameter.shape, generator=generator))
    z = torch.randn(4, NUM_BELIEF_FEATURES, generator=generator)
    z[:, -3] = torch.tensor([0.0, 1.0, 0.0, 1.0])
    inputs = torch.cat([torch.randn(4, 7, generator=generator), z], -1)
    residual = compact.residual_values(inputs)
    assert (residual[::2] == 0).all()  # 0 times a finite value: exactly 0
    assert (residual[1::2].abs() > 0).any()
    table = torch.randn(3, 7, generator=generator)
    deployed = module.deployed_network(table, compact)
    p = torch.softmax(torch.randn(4, 3, generator=generator), -1)
    expected = p @ table + residual
    torch.testing.assert_close(deployed(torch.cat([p, z], -1)), expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("behaviour", [{"probe_episodes": 1.0}, {"shift_episodes": 1.0}])
def test_the_occluded_variant_trains_and_skips_the_raw_setting(
    module: ModuleType, tabular_run: Path, tmp_path: Path, behaviour: dict[str, float]
) -> None:
    """The camera of the variant returns NaN near the hole: the filter runs on touch there,
    and the raw setting (which reads the camera's pose) is left out of the comparison, the
    two probing ones join it. Probing or touch-and-shift behaviour and Monte Carlo targets
    train too."""
    result = module.run(
        _tiny(
            module,
            tmp_path,
            tabular_run,
            rounds=1,
            occlusion_radius=0.05,
            targets="monte_carlo",
            **behaviour,
        )
    )
    assert set(result["evaluations"]) == {"oracle", "qmdp", "probe", "shift", "neural"}
    text = (Path(result["run_dir"]) / "results.md").read_text()
    assert "occlusion radius 50 mm" in text


@pytest.mark.bitwise("a resumed run runs the same code on the same inputs in the same process")
def test_resuming_from_a_checkpoint_reproduces_the_uninterrupted_run(
    module: ModuleType, tabular_run: Path, straight: dict[str, Any], tmp_path: Path
) -> None:
    stopped = module.run(_tiny(module, tmp_path, tabular_run, rounds=1))
    resumed = module.run(_tiny(module, tmp_path, tabular_run, resume=stopped["run_dir"]))
    assert resumed["run_dir"] == stopped["run_dir"]
    assert resumed["history"] == straight["history"]
    assert resumed["best_round"] == straight["best_round"]
    assert resumed["evaluations"] == straight["evaluations"]
    a = torch.load(Path(straight["run_dir"]) / "network.pt")
    b = torch.load(Path(resumed["run_dir"]) / "network.pt")
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)
    refused = (
        r"other arguments \(rounds may grow; final_episodes, final_seed, belief, mode_episodes, "
        r"final_settings may differ\): learning_rate: checkpoint 0\.001, now 0\.01$"
    )
    with pytest.raises(ValueError, match=refused):
        module.run(
            _tiny(module, tmp_path, tabular_run, learning_rate=1e-2, resume=stopped["run_dir"])
        )


@pytest.mark.parametrize(
    ("change", "expected"), [({}, 3 + 104_729), ({"final_seed": 104_729}, 104_729)]
)
def test_the_final_comparison_is_seeded_by_final_seed(
    module: ModuleType,
    tabular_run: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    change: dict[str, int],
    expected: int,
) -> None:
    """The final episodes' seed is ``--final-seed`` when given (so runs of other training
    seeds share seed 0's episodes), else the documented ``--seed + 104729``."""
    seeds: list[int] = []
    original = module.evaluate_settings

    def recording(*args: Any, **kwargs: Any) -> Any:
        seeds.append(kwargs["seed"])
        return original(*args, **kwargs)

    monkeypatch.setattr(module, "evaluate_settings", recording)
    module.run(_tiny(module, tmp_path, tabular_run, rounds=1, seed=3, **change))
    assert seeds == [expected]


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"particles": 16}, r"particles: expected an int >= 24 \(the belief model's number of "),
        ({"rounds": -1}, r"rounds: expected an int >= 1, got -1"),
        ({"batch_size": 0}, r"batch_size: expected an int >= 1"),
        ({"learning_starts": -1}, r"learning_starts: expected an int >= 0"),
        ({"learning_rate": 0.0}, r"learning_rate: expected a finite number > 0"),
        ({"epsilon_start": 1.5}, r"epsilon_start: expected a finite number in \[0.0, 1.0\]"),
        ({"final_episodes": 0}, r"final_episodes: expected an int >= 1"),
        ({"residual_penalty": -1.0}, r"residual_penalty: expected a finite number >= 0"),
        ({"occlusion_radius": -0.1}, r"occlusion_radius: expected a finite number >= 0"),
        ({"name": ""}, r"name: expected a non-empty name"),
        ({"probe_episodes": 1.5}, r"probe_episodes: expected a finite number in \[0.0, 1.0\]"),
        ({"press_penalty": -1.0}, r"press_penalty: expected a finite number >= 0"),
        ({"shift_episodes": 1.5}, r"shift_episodes: expected a finite number in \[0.0, 1.0\]"),
        ({"targets": "mc"}, r"targets: expected one of \('td', 'monte_carlo'\)"),
        ({"final_seed": -1}, r"final_seed: expected an int >= 0, got -1"),
    ],
)
def test_bad_arguments_fail_before_any_work(
    module: ModuleType, tabular_run: Path, tmp_path: Path, change: dict[str, object], message: str
) -> None:
    clock = time.perf_counter()
    with pytest.raises(ValueError, match=message):
        module.run(_tiny(module, tmp_path / "runs", tabular_run, **change))
    assert time.perf_counter() - clock < 5.0
    assert not (tmp_path / "runs").exists()  # no run folder


def test_help_lists_the_arguments(module: ModuleType, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        module.main(["--help"])
    text = capsys.readouterr().out
    for flag in ("--tabular-run STR", "(required)", "--resume", "--occlusion-radius"):
        assert flag in text


def test_a_missing_tabular_run_is_named(module: ModuleType, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"tabular_run .* run train/dyna_q_peg\.py first"):
        module.run(_tiny(module, tmp_path / "runs", tmp_path / "nothing"))
    assert not (tmp_path / "runs").exists()


@pytest.mark.bitwise("a stored input is a copy of the next step's: rows are matched exactly")
def test_monte_carlo_targets_are_the_discounted_returns_of_the_shaped_rewards(
    module: ModuleType, tabular_run: Path, tmp_path: Path
) -> None:
    """One round collected twice from the same seed (the same episodes and actions): with
    Monte Carlo targets each row's reward is the step's shaped reward (the TD buffer's) plus
    γ times the target of the same episode's next step (the row whose input is this row's
    next input), the last step's its shaped reward alone; every row is terminal."""
    stored = {}
    for targets in ("td", "monte_carlo"):
        args = _tiny(
            module, tmp_path, tabular_run, targets=targets, probe_episodes=0.5, buffer_size=4096
        )
        tabular = module.check_args(args)
        lookup = QLookup(tabular.agent, tabular.model.task.states)
        filt = PegInHoleFilter(tabular.model, num_particles=args.particles)
        config = dataclasses.replace(tabular.model.task.config, occlusion_radius=0.05)
        env = PegInHole2DVector(num_envs=3, config=config, observation="noisy")
        online = module.compact_network(args, 7)
        buffer = ReplayBuffer(args.buffer_size, online.input_size, dtype=torch.float32, seed=0)
        module._collect(
            args,
            env,
            filt,
            lookup,
            tabular,
            online=online,
            buffer=buffer,
            schedule=EpsilonSchedule(0.2, 0.05, 20),
            counters={"transitions": 0, "updates": 0},
            round_index=0,
        )
        state = buffer.state_dict()
        stored[targets] = {
            k: state[k][: state["size"]]
            for k in ("observations", "actions", "rewards", "next_observations", "terminals")
        }
    td, mc = stored["td"], stored["monte_carlo"]
    assert (td["actions"] == mc["actions"]).all()
    assert (td["observations"] == mc["observations"]).all()
    assert mc["terminals"].all()
    gamma = DynaQ.from_state_dict(
        torch.load(tabular_run / "checkpoint.pt", weights_only=False)["agent"]
    ).gamma
    rows = td["observations"].shape[0]
    same = (td["next_observations"][:, None] == td["observations"][None]).all(-1)  # (R, R)
    later = torch.arange(rows)[None] > torch.arange(rows)[:, None]
    follows = same & later
    ends = 0
    for j in range(rows):
        following = torch.nonzero(follows[j]).flatten()
        expected = float(td["rewards"][j])
        if following.numel():
            expected += gamma * float(mc["rewards"][following[0]])
        else:
            ends += 1
        assert float(mc["rewards"][j]) == pytest.approx(expected, rel=1e-5, abs=1e-6)
    assert ends == 3  # one end per episode


def test_the_press_trust_region_leaves_the_other_actions_in_qmdp_order(module: ModuleType) -> None:
    """Monte Carlo rows whose targets favour pressing ("-y") by 0.3 and another action by
    0.2 on half the beliefs: with a heavy penalty on every advantage but pressing's, the
    fitted residual raises pressing there, and the other actions' residuals stay within a
    small fraction of that gap of their common mean (the regression alone would lift the
    other action too, by about 0.2)."""
    args = module.Args(
        tabular_run="unused",
        hidden=16,
        learning_rate=1e-2,
        fitted_iterations=1,
        updates_per_iteration=400,
        batch_size=128,
        residual_penalty=100.0,
        press_penalty=0.0,
        targets="monte_carlo",
    )
    generator = torch.Generator().manual_seed(0)
    online = module.compact_network(args, 7)
    target = module.compact_network(args, 7)
    R = 2048
    inputs = torch.randn(R, online.input_size, generator=generator)
    inputs[:, :7] = 0.0  # QMDP values 0: the residual is the whole value
    actions = torch.randint(7, (R,), generator=generator)
    favoured = inputs[:, 7] > 0  # half the beliefs
    press, other = 4, 1
    rewards = torch.where(favoured & (actions == press), 0.3, 0.0)
    rewards = rewards + torch.where(favoured & (actions == other), 0.2, 0.0)
    buffer = ReplayBuffer(R, online.input_size, dtype=torch.float32, seed=0)
    buffer.add(
        observation=inputs,
        action=actions,
        reward=rewards,
        next_observation=inputs,
        terminal=torch.ones(R, dtype=torch.bool),
    )
    optimizer = torch.optim.Adam(
        [p for p in online.parameters() if p.requires_grad], lr=args.learning_rate
    )
    counters = {"transitions": R, "updates": 0}
    module._fit(args, online, target, optimizer, buffer, counters, gamma=0.99)
    assert counters["updates"] == 400
    with torch.no_grad():
        residual = online.residual_values(inputs[favoured])
    rest = torch.arange(7) != press
    common = residual[:, rest].mean(-1)
    lift = float((residual[:, press] - common).mean())
    assert lift > 0.15  # pressing's advantage is learned where it pays
    assert float((residual[:, rest] - common[:, None]).abs().max()) < 0.2 * lift
