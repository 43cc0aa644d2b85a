"""Run folders, their logs and checkpoints of the experiment scripts.

Every run gets its own folder, ``<out_dir>/<name>__<seed>__<unix seconds>`` (CleanRL's
convention; :func:`new_run_dir`). :class:`RunLog` opens the run's TensorBoard log there,
records the arguments (``args.json`` and a text table) and logs the throughput
(``charts/SPS``). A run writes ``checkpoint.pt`` there after every round with
:func:`save_checkpoint`, atomically, so a kill at any point leaves the previous checkpoint
whole; ``--resume <run folder>`` continues that run in its folder (:func:`open_run`), after
:func:`load_checkpoint` has checked that the arguments are the checkpoint's.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

if TYPE_CHECKING:
    from torch.utils.tensorboard import SummaryWriter

#: The checkpoint's file name in a run folder.
CHECKPOINT = "checkpoint.pt"
#: The arguments' file name in a run folder.
ARGUMENTS = "args.json"
#: Arguments that only say where a run's folder is: never compared with a checkpoint's.
LOCATION = ("name", "out_dir", "resume")
_NONE = object()  # an argument the checkpoint or the script lacks


def new_run_dir(*, out_dir: str | Path, name: str, seed: int) -> Path:
    """Create and return a new run folder ``<out_dir>/<name>__<seed>__<unix seconds>``.

    Two runs started in the same second never share a folder: the second one gets the
    suffix ``_1`` (then ``_2``, ...). The folder is created with ``exist_ok=False``, so this
    holds across processes too.

    Args:
        out_dir: the parent folder (created if missing).
        name: the experiment's name.
        seed: the run's seed.
    """
    stem = f"{name}__{seed}__{int(time.time())}"
    suffix = 0
    while True:
        path = Path(out_dir) / (f"{stem}_{suffix}" if suffix else stem)
        try:
            path.mkdir(parents=True)
        except FileExistsError:
            suffix += 1
        else:
            return path


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """Write ``payload`` to ``path`` with ``torch.save``, atomically.

    The data go to a temporary file in the same folder, are flushed and synced to disk, and
    the file then replaces ``path`` (``os.replace``, atomic on POSIX and Windows): a kill at
    any point leaves either the previous checkpoint or the new one, never a truncated file.

    Args:
        path: the checkpoint file.
        payload: what to save (a dict with an ``"args"`` entry for :func:`load_checkpoint`).
    """
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as file:
            torch.save(payload, file)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    if hasattr(os, "O_DIRECTORY"):  # make the rename itself durable (POSIX)
        folder = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(folder)
        finally:
            os.close(folder)


def read_checkpoint(path: Path, *, keys: tuple[str, ...]) -> dict[str, Any]:
    """The checkpoint at ``path``, a dict with (at least) the entries ``keys``.

    Args:
        path: the checkpoint file.
        keys: the entries the caller reads.

    Raises:
        ValueError: the file is missing, unreadable or damaged (truncated, corrupt), or does
            not hold a dict with the entries ``keys``; the message names the file.
    """
    if not path.is_file():
        raise ValueError(f"{path}: no checkpoint there")
    try:
        saved = torch.load(path, weights_only=False)
    # A truncated file fails in the zip reader (RuntimeError, OSError); corrupt bytes fail
    # wherever the unpickler happens to be (UnpicklingError, UnicodeDecodeError, EOFError,
    # AttributeError or ImportError for a garbled name, MemoryError for a garbled size, ...).
    except Exception as error:  # any of them: a damaged file, named below
        raise ValueError(f"{path}: unreadable or damaged checkpoint ({error!r})") from error
    if not isinstance(saved, dict):
        raise ValueError(f"{path}: expected a dict checkpoint, got {type(saved).__name__}")
    missing = [key for key in keys if key not in saved]
    if missing:
        raise ValueError(f"{path}: checkpoint lacks the entries {missing}")
    return saved


def load_checkpoint(
    path: Path, args: Any, *, keys: tuple[str, ...], free: tuple[str, ...] = ()
) -> dict[str, Any]:
    """The checkpoint at ``path`` (see :func:`read_checkpoint`), checked against ``args``.

    A run is extended by resuming with a larger ``rounds``; every other argument must equal
    the one the checkpoint was written with (its ``"args"`` entry, ``dataclasses.asdict``
    of the script's argument dataclass), except those that locate the run folder
    (:data:`LOCATION`) and those named in ``free``: arguments that only act after training
    (a final evaluation's budget or noise level), so a finished run can be evaluated again
    without training again.

    Args:
        path: the checkpoint file (``torch.save`` of a dict with an ``"args"`` entry).
        args: the script's arguments, a dataclass instance with a ``rounds`` field.
        keys: further entries the caller reads.
        free: names of further fields that may differ from the checkpoint's.

    Raises:
        ValueError: the checkpoint is unreadable (:func:`read_checkpoint`), or was written
            with other arguments: the message names each one with both values.
    """
    current = dataclasses.asdict(args)
    unknown = set(free) - set(current)
    if unknown:
        raise ValueError(f"free names fields that args lacks: {sorted(unknown)}")
    saved = read_checkpoint(path, keys=("args", *keys))
    written = saved["args"]
    if not isinstance(written, dict):
        raise ValueError(f"{path}: checkpoint entry 'args' is not a dict")
    skipped = {*LOCATION, *free}
    if current["rounds"] >= written.get("rounds", 0):
        skipped.add("rounds")
    names = [*current, *(name for name in written if name not in current)]
    differences = [
        f"{name}: checkpoint {_shown(written, name)}, now {_shown(current, name)}"
        for name in names
        if name not in skipped and written.get(name, _NONE) != current.get(name, _NONE)
    ]
    if differences:
        allowed = "rounds may grow" + (f"; {', '.join(free)} may differ" if free else "")
        raise ValueError(
            f"{path} was written with other arguments ({allowed}): " + "; ".join(differences)
        )
    return saved


def _shown(values: dict[str, Any], name: str) -> str:
    return repr(values[name]) if name in values else "(none)"


def open_run(
    args: Any, *, keys: tuple[str, ...], free: tuple[str, ...] = ()
) -> tuple[Path, dict[str, Any] | None]:
    """The run folder of ``args`` and the checkpoint to continue from (``None``: a new run).

    ``args.resume`` unset: a new folder (:func:`new_run_dir` of ``args.out_dir``,
    ``args.name`` and ``args.seed``). Set: that run folder, with its checkpoint checked by
    :func:`load_checkpoint`.

    Args:
        args: the script's arguments, a dataclass instance with the fields ``resume``,
            ``out_dir``, ``name``, ``seed`` and ``rounds``.
        keys: the checkpoint's entries the caller reads, besides ``"args"``.
        free: fields that may differ from the checkpoint's (see :func:`load_checkpoint`).

    Raises:
        ValueError: ``args.resume`` names no folder with a readable checkpoint written with
            the same arguments.
    """
    if args.resume is None:
        return new_run_dir(out_dir=args.out_dir, name=args.name, seed=args.seed), None
    run_dir = Path(args.resume)
    if not (run_dir / CHECKPOINT).is_file():
        raise ValueError(f"resume: {str(run_dir)!r} is not a run folder with a {CHECKPOINT}")
    return run_dir, load_checkpoint(run_dir / CHECKPOINT, args, keys=keys, free=free)


class RunLog:
    """The TensorBoard log of a run folder, with the run's arguments and its throughput.

    Opening it writes the arguments (``dataclasses.asdict(args)``) to :data:`ARGUMENTS` in
    the folder, as JSON (values JSON lacks, e.g. paths, as their ``str``), and logs them as
    the TensorBoard text ``hyperparameters``, a Markdown table (CleanRL's convention); a
    resumed run writes them again. :meth:`steps_per_second` logs ``charts/SPS``.

    Args:
        run_dir: the run folder.
        args: the script's arguments, a dataclass instance.

    Raises:
        ValueError: ``args`` is not a dataclass instance.
    """

    def __init__(self, run_dir: Path, args: Any) -> None:
        if not dataclasses.is_dataclass(args) or isinstance(args, type):
            raise ValueError(f"args must be a dataclass instance, got {type(args).__name__}")
        from torch.utils.tensorboard import SummaryWriter  # loads tensorboard: only when logging

        values = dataclasses.asdict(args)
        (Path(run_dir) / ARGUMENTS).write_text(json.dumps(values, indent=2, default=str) + "\n")
        self.writer: SummaryWriter = SummaryWriter(str(run_dir))
        rows = "\n".join(f"| {name} | {_cell(value)} |" for name, value in values.items())
        self.writer.add_text("hyperparameters", f"| argument | value |\n|---|---|\n{rows}")
        self._start = time.perf_counter()

    def steps_per_second(self, steps: int, global_step: int) -> float:
        """Log and return ``charts/SPS``: ``steps`` done since the log opened, per second.

        Args:
            steps: the steps (environment steps, or the script's unit of work) this process
                has done since it opened the log.
            global_step: the point on the logs' step axis to log it at.
        """
        rate = steps / max(time.perf_counter() - self._start, 1e-9)
        self.writer.add_scalar("charts/SPS", rate, global_step)
        return rate

    def close(self) -> None:
        """Flush and close the TensorBoard writer."""
        self.writer.close()


def _cell(value: Any) -> str:
    """A value as the text of a Markdown table cell (``|`` escaped)."""
    return str(value).replace("|", "\\|")
