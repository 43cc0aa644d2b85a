"""Run folders, atomic checkpoints and argument checks shared by the train scripts."""

from __future__ import annotations

import dataclasses
import json
import pickle
import re
import time
from pathlib import Path
from typing import Any

import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from torchcontact.experiments import (
    ARGUMENTS,
    CHECKPOINT,
    RunLog,
    check_choice,
    check_int,
    check_name,
    check_real,
    load_checkpoint,
    new_run_dir,
    open_run,
    read_checkpoint,
    save_checkpoint,
)


@dataclasses.dataclass(frozen=True)
class _Args:
    name: str = "exp"
    out_dir: str = "runs"
    resume: str | None = None
    seed: int = 0
    rounds: int = 2
    alpha: float = 0.1
    particles: int = 64


def _payload(args: _Args) -> dict[str, Any]:
    return {"args": dataclasses.asdict(args), "round": 2, "table": torch.arange(1000.0)}


@pytest.fixture
def checkpoint(tmp_path: Path) -> Path:
    path = tmp_path / CHECKPOINT
    save_checkpoint(path, _payload(_Args()))
    return path


@pytest.mark.bitwise("a checkpoint reads back the bits it stored")
def test_save_checkpoint_writes_atomically_and_leaves_no_temporary_file(
    checkpoint: Path,
) -> None:
    saved = read_checkpoint(checkpoint, keys=("args", "round", "table"))
    assert torch.equal(saved["table"], torch.arange(1000.0))
    save_checkpoint(checkpoint, _payload(_Args(rounds=3)))  # replaces the previous one
    assert read_checkpoint(checkpoint, keys=("args",))["args"]["rounds"] == 3
    assert [p.name for p in checkpoint.parent.iterdir()] == [CHECKPOINT]


def test_a_failed_write_keeps_the_previous_checkpoint(
    checkpoint: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    before = checkpoint.read_bytes()

    def killed(payload: object, file: Any) -> None:  # half the bytes, then the kill
        file.write(before[: len(before) // 2])
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", killed)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(checkpoint, _payload(_Args(rounds=3)))
    assert checkpoint.read_bytes() == before
    assert [p.name for p in checkpoint.parent.iterdir()] == [CHECKPOINT]


def test_a_damaged_checkpoint_is_a_value_error_naming_the_file(checkpoint: Path) -> None:
    data = checkpoint.read_bytes()
    named = re.escape(str(checkpoint))
    checkpoint.write_bytes(data[: len(data) // 2])  # truncated by a kill during torch.save
    with pytest.raises(ValueError, match=f"{named}: unreadable or damaged checkpoint"):
        read_checkpoint(checkpoint, keys=())
    checkpoint.write_bytes(b"\x00" * 64 + data[64:])  # corrupt bytes: the zip header
    with pytest.raises(ValueError, match=f"{named}: unreadable or damaged checkpoint"):
        read_checkpoint(checkpoint, keys=())
    checkpoint.write_bytes(data.replace(b"_rebuild_tensor_v2", b"_rebuild_tensor_v9"))  # a name
    with pytest.raises(ValueError, match=f"{named}: unreadable or damaged checkpoint"):
        read_checkpoint(checkpoint, keys=())
    checkpoint.write_bytes(pickle.dumps(["not", "a", "dict"]))
    with pytest.raises(ValueError, match=f"{named}: unreadable or damaged checkpoint"):
        read_checkpoint(checkpoint, keys=())
    torch.save([1, 2], checkpoint)  # readable, not a dict
    with pytest.raises(ValueError, match=f"{named}: expected a dict checkpoint, got list"):
        read_checkpoint(checkpoint, keys=())
    torch.save({"args": {}}, checkpoint)
    with pytest.raises(ValueError, match=rf"{named}: checkpoint lacks the entries \['round'\]"):
        read_checkpoint(checkpoint, keys=("args", "round"))
    with pytest.raises(ValueError, match="no checkpoint there"):
        read_checkpoint(checkpoint.parent / "missing.pt", keys=())


def test_a_refused_resume_names_every_differing_argument(checkpoint: Path) -> None:
    args = _Args(name="other", out_dir="elsewhere", resume=str(checkpoint.parent), rounds=5)
    assert load_checkpoint(checkpoint, args, keys=("round",))["round"] == 2  # rounds may grow
    with pytest.raises(ValueError, match="other arguments") as refused:
        load_checkpoint(checkpoint, dataclasses.replace(args, seed=3, alpha=0.5), keys=())
    assert str(refused.value) == (
        f"{checkpoint} was written with other arguments (rounds may grow): "
        "seed: checkpoint 0, now 3; alpha: checkpoint 0.1, now 0.5"
    )
    with pytest.raises(ValueError, match="rounds: checkpoint 2, now 1"):  # rounds may not shrink
        load_checkpoint(checkpoint, dataclasses.replace(args, rounds=1), keys=())
    fewer = dataclasses.replace(args, particles=32)
    free = load_checkpoint(checkpoint, fewer, keys=(), free=("particles",))
    assert free["args"]["particles"] == 64
    with pytest.raises(ValueError, match=r"particles may differ\): alpha"):
        load_checkpoint(
            checkpoint, dataclasses.replace(fewer, alpha=0.2), keys=(), free=("particles",)
        )
    with pytest.raises(ValueError, match="free names fields that args lacks"):
        load_checkpoint(checkpoint, args, keys=(), free=("sigma",))


def test_each_run_gets_its_own_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("time.time", lambda: 1_700_000_000.7)
    first = new_run_dir(out_dir=tmp_path / "runs", name="exp", seed=3)
    second = new_run_dir(out_dir=tmp_path / "runs", name="exp", seed=3)  # the same second
    third = new_run_dir(out_dir=tmp_path / "runs", name="exp", seed=3)
    assert [first.name, second.name, third.name] == [
        "exp__3__1700000000",
        "exp__3__1700000000_1",
        "exp__3__1700000000_2",
    ]
    assert all(p.is_dir() for p in (first, second, third))


def test_open_run_makes_a_folder_or_resumes_one(checkpoint: Path, tmp_path: Path) -> None:
    run_dir, saved = open_run(_Args(out_dir=str(tmp_path / "runs")), keys=())
    assert saved is None
    assert run_dir.parent == tmp_path / "runs"
    assert re.fullmatch(r"exp__0__\d+", run_dir.name)
    resumed, saved = open_run(_Args(resume=str(checkpoint.parent)), keys=("round",))
    assert resumed == checkpoint.parent
    assert saved is not None
    assert saved["round"] == 2
    with pytest.raises(ValueError, match=r"resume: .* is not a run folder with a checkpoint\.pt"):
        open_run(_Args(resume=str(run_dir)), keys=())


def test_argument_checks_name_the_argument_and_the_range() -> None:
    assert check_int("rounds", 3, low=1) == 3
    with pytest.raises(ValueError, match=r"^rounds: expected an int >= 1, got -1$"):
        check_int("rounds", -1, low=1)
    with pytest.raises(ValueError, match=r"particles: expected an int >= 24 \(K\), got 16"):
        check_int("particles", 16, low=24, why="K")
    with pytest.raises(ValueError, match="expected an int"):
        check_int("rounds", True, low=0)
    assert check_real("alpha", 1, low=0.0, high=1.0, low_open=True) == 1.0
    with pytest.raises(ValueError, match=r"alpha: expected a finite number in \(0.0, 1.0\]"):
        check_real("alpha", 0.0, low=0.0, high=1.0, low_open=True)
    with pytest.raises(ValueError, match="sigma: expected a finite number"):
        check_real("sigma", float("nan"))
    with pytest.raises(ValueError, match=r"mode: expected one of \('a', 'b'\), got 'c'"):
        check_choice("mode", "c", ("a", "b"))
    assert check_name("name", "run") == "run"
    for bad in ("", "a/b"):
        with pytest.raises(ValueError, match="name: expected a non-empty name"):
            check_name("name", bad)


def test_run_log_writes_the_arguments_and_the_steps_per_second(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """args.json and the text table hold the arguments; SPS is steps over the clock's time."""
    readings = [100.0, 102.5]  # when the log opens, then ever after
    monkeypatch.setattr(time, "perf_counter", lambda: readings.pop(0) if readings[1:] else 102.5)
    args = _Args(out_dir="a|b")  # a pipe, escaped in the table
    log = RunLog(tmp_path, args)
    assert log.steps_per_second(50, 7) == pytest.approx(20.0, rel=1e-15)  # 50 steps in 2.5 s
    log.close()
    saved = json.loads((tmp_path / ARGUMENTS).read_text())
    assert saved == dataclasses.asdict(args)
    events = EventAccumulator(str(tmp_path))
    events.Reload()
    (sps,) = events.Scalars("charts/SPS")
    assert (sps.step, sps.value) == (7, pytest.approx(20.0, rel=1e-6))  # stored as float32
    (text,) = events.Tensors("hyperparameters/text_summary")
    table = text.tensor_proto.string_val[0].decode()
    assert "| out_dir | a\\|b |" in table
    assert "| particles | 64 |" in table
    with pytest.raises(ValueError, match="args"):
        RunLog(tmp_path, _Args)
