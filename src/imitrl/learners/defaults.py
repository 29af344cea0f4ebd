"""What an unset choice means: ``--loss default`` and an unset learning rate, in one place.

Every learner the command line builds for integer states or vector observations is a
loss-registry entry (:mod:`imitrl.learners.registry`). ``--loss default`` is not a
builder of its own: it is resolved here, for the task, to an entry's name, and the name
is what a run records (its ``results.json``, its checkpoint):

========== ================ ===========================================
actions    ``default``      ``default`` where the job needs ``log pi``
                            (``imitrl gail``, ``imitrl airl``: PPO)
========== ================ ===========================================
discrete   ``cross_entropy`` ``cross_entropy``
continuous ``mse``           ``gaussian_nll``
========== ================ ===========================================

``cross_entropy`` is a logits table on integer states (FrozenLake) and an MLP on vector
observations, like every discrete entry. Where the registry builds nothing (image
observations, with or without a state beside them; multi-discrete, one-hot or unbounded
actions) ``default`` is ``for_env``:
:func:`~imitrl.learners.actor_critic.entries.for_env`'s network (a CNN on images)
(:func:`imitrl.jobs.resolve.resolve_loss`).

Adam's learning rate when none is given (``LearnerConfig.lr`` None, no ``--lr``), one
per kind of network:

========================================= ============================================
network                                   rate
========================================= ============================================
logits table (integer states)             :data:`TABLE_LR` 0.1
MLP, diffusion and flow networks          :data:`NETWORK_LR` 1e-3
an entry with its recipe's own rate       ``LossEntry.own_lr`` (ACT's, diffusion_unet's:
                                          :mod:`~imitrl.learners.catalogue`);
                                          the CLI refuses another ``--lr``
========================================= ============================================

``TABLE_LR``: a table's logits start at 0 and Adam moves each by about ``lr`` a step.
Greedy actions do not depend on it (the first step already ranks the demonstrated
action first), but how sure the table becomes does. On the loss benchmark's FrozenLake
task, fitted on 5 expert episodes (1000 steps of 256 rows, 3 seeds), the mean
probability of the demonstrated action is 0.645 at 1e-3, 0.987 at 1e-2 and 1.000 at
0.1; under the benchmark's protocol (1 episode, 4 DAgger rounds, 5 seeds, 200 or 1000
steps a fit) the exact greedy success of BC and of DAgger is the same at every rate
from 1e-3 to 0.5.
A table fitted at 1e-3 acts far from its data when it samples (PPO, a ``RANDOM``
evaluation). 0.1 is the FrozenLake study's rate and the loss benchmark's.
The GAIL/AIRL generator's PPO rate is the job's own (``imitrl gail --lr``:
:data:`imitrl.configs.adversarial.ADVERSARIAL_LR`).
"""

from __future__ import annotations

__all__ = [
    "DEFAULT_LOSS",
    "HIDDEN",
    "NETWORK_LR",
    "PIXEL_CHANNELS",
    "PIXEL_HIDDEN",
    "PROBABILISTIC_LOSS",
    "TABLE_LR",
    "default_loss",
    "learning_rate",
]

HIDDEN = (64, 64)
"""hidden layers of every MLP the registry builds (policy heads, the diffusion score
network, the flow velocity network): one width for all, so that objectives are compared
at equal capacity"""
PIXEL_CHANNELS = (32, 64, 64)
"""the convolutions of a CNN learner (``for_env`` on images): the Nature CNN's"""
PIXEL_HIDDEN = (256,)
"""the MLP after a CNN learner's convolutions"""
TABLE_LR = 0.1
"""Adam's rate for a logits table (integer states) when none is given"""
NETWORK_LR = 1e-3
"""Adam's rate for an MLP, diffusion or flow network when none is given"""
DEFAULT_LOSS = {"discrete": "cross_entropy", "continuous": "mse"}
"""``--loss default`` by action kind"""
PROBABILISTIC_LOSS = {"discrete": "cross_entropy", "continuous": "gaussian_nll"}
"""``--loss default`` by action kind where the job needs ``log pi`` (GAIL, AIRL)"""


def default_loss(actions: str, *, probabilistic: bool = False) -> str:
    """The registry entry ``--loss default`` names for ``actions`` (``"discrete"`` or
    ``"continuous"``); ``probabilistic``: the job needs an action distribution."""
    table = PROBABILISTIC_LOSS if probabilistic else DEFAULT_LOSS
    if actions not in table:
        raise ValueError(f"actions must be one of {tuple(table)}, got {actions!r}")
    return table[actions]


def learning_rate(own_lr: float | None, num_states: int | None, lr: float | None) -> float:
    """The rate an entry trains at: its recipe's own (``own_lr``) if it has one, else
    ``lr`` if given, else the network's default (a table on integer states, when
    ``num_states`` is set: :data:`TABLE_LR`; any other network: :data:`NETWORK_LR`)."""
    if own_lr is not None:
        return float(own_lr)
    if lr is not None:
        if not lr > 0:
            raise ValueError(f"a learning rate must be positive, got {lr!r}")
        return float(lr)
    return TABLE_LR if num_states is not None else NETWORK_LR
