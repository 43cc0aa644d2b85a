"""Experiment pipelines shared by the ``train/`` scripts, the demo and the tutorials.

Peg-in-hole (:mod:`torchcontact.envs`): :func:`run_round` trains (or evaluates) a
:class:`~torchcontact.rl.DynaQ` agent on rounds of batched episodes with
:class:`PotentialShaping` and records the steps (:class:`PegLearning` holds the settings that
learn the task); :func:`evaluate` executes the learned policy under uncertainty (oracle, raw
observation, QMDP over the RBPF belief with :func:`qmdp_actions`, neural Q on
:func:`belief_features`), with :class:`QLookup` mapping manipulation-state ids to Q rows.
Scripts check their arguments with :func:`check_int`, :func:`check_real`, :func:`check_choice`
and :func:`check_name` before any work, get a new run folder or the one to resume with
:func:`open_run`, and write checkpoints atomically with :func:`save_checkpoint`.
"""

from torchcontact._checks import check_choice, check_int, check_name, check_real
from torchcontact.experiments._checkpoint import (
    CHECKPOINT,
    LOCATION,
    load_checkpoint,
    new_run_dir,
    open_run,
    read_checkpoint,
    save_checkpoint,
)
from torchcontact.experiments._peg_execution import (
    NUM_BELIEF_FEATURES,
    SETTINGS,
    Evaluation,
    Setting,
    belief_features,
    evaluate,
    evaluate_settings,
    qmdp_actions,
    results_table,
)
from torchcontact.experiments._peg_learning import (
    PegLearning,
    PotentialShaping,
    RoundResult,
    round_seed,
    run_round,
)
from torchcontact.experiments._q_lookup import QLookup

__all__ = [
    "CHECKPOINT",
    "LOCATION",
    "NUM_BELIEF_FEATURES",
    "SETTINGS",
    "Evaluation",
    "PegLearning",
    "PotentialShaping",
    "QLookup",
    "RoundResult",
    "Setting",
    "belief_features",
    "check_choice",
    "check_int",
    "check_name",
    "check_real",
    "evaluate",
    "evaluate_settings",
    "load_checkpoint",
    "new_run_dir",
    "open_run",
    "qmdp_actions",
    "read_checkpoint",
    "results_table",
    "round_seed",
    "run_round",
    "save_checkpoint",
]
