"""Experiment pipelines shared by the ``train/`` scripts, the demo and the tutorials.

Peg-in-hole (:mod:`torchcontact.envs`): :func:`run_round` trains (or evaluates) a
:class:`~torchcontact.rl.DynaQ` agent on rounds of batched episodes with
:class:`PotentialShaping` and records the steps (:class:`PegLearning` holds the settings
that learn the task); :func:`evaluate` executes the learned policy under uncertainty (oracle,
raw observation, QMDP over the RBPF belief, neural Q on :func:`belief_features`), with
:class:`QLookup` mapping manipulation states to Q values. Scripts read their command line
with :func:`parse_dataclass` and resume with :func:`load_checkpoint`.
"""

from torchcontact.experiments._checkpoint import load_checkpoint
from torchcontact.experiments._cli import parse_dataclass
from torchcontact.experiments._peg_execution import (
    NUM_BELIEF_FEATURES,
    SETTINGS,
    Evaluation,
    Setting,
    belief_features,
    evaluate,
    evaluate_settings,
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
    "NUM_BELIEF_FEATURES",
    "SETTINGS",
    "Evaluation",
    "PegLearning",
    "PotentialShaping",
    "QLookup",
    "RoundResult",
    "Setting",
    "belief_features",
    "evaluate",
    "evaluate_settings",
    "load_checkpoint",
    "parse_dataclass",
    "results_table",
    "round_seed",
    "run_round",
]
