"""Reinforcement learning on manipulation states and beliefs.

* :class:`DynaQ` learns a tabular Q function over hashable (manipulation) states together with
  its model, a :class:`~torchcontact.states.ManipulationGraph`, and plans with the model.
* :func:`qmdp_values` / :func:`qmdp_action` act on a belief over discrete states with the
  Q values of the fully observed problem: ``a* = argmax_a Σᵢ pᵢ Q(mᵢ, a)``.
* :func:`greedy_action` is the argmax of batched action values with one tie rule (the lowest
  index, or uniformly at random from an explicit generator), for every greedy policy.
* :class:`QNetwork` is a neural Q function on belief features: a QMDP head plus an MLP
  residual that starts at zero, trained DQN-style with :class:`ReplayBuffer`,
  :class:`EpsilonSchedule`, :func:`dqn_loss` and :func:`update_target`.
"""

from torchcontact.rl._dqn import dqn_loss, update_target
from torchcontact.rl._dyna_q import DynaQ, Exploration, Sampler, StepSize, SweepResult
from torchcontact.rl._greedy import greedy_action
from torchcontact.rl._q_network import QNetwork
from torchcontact.rl._qmdp import qmdp_action, qmdp_values
from torchcontact.rl._replay import ReplayBuffer, Transitions
from torchcontact.rl._schedule import EpsilonSchedule

__all__ = [
    "DynaQ",
    "EpsilonSchedule",
    "Exploration",
    "QNetwork",
    "ReplayBuffer",
    "Sampler",
    "StepSize",
    "SweepResult",
    "Transitions",
    "dqn_loss",
    "greedy_action",
    "qmdp_action",
    "qmdp_values",
    "update_target",
]
