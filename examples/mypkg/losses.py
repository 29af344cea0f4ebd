"""A loss of the user's own, registered under a name the command line takes: the
"Adding a loss" block of CONTRIBUTING.md, as a module.

``imitrl bc --loss mypkg.losses:l1_l2`` imports this module (code you named, as
``--expert mypkg.experts:mountain_car`` is), which registers ``l1_l2`` in the loss
registry; the run records ``mypkg.losses:l1_l2``, and ``imitrl eval --checkpoint OUT
--loss mypkg.losses:l1_l2`` rebuilds it (imitrl never imports a module a checkpoint
names by itself). ``imitrl bench loss_functions --losses l1_l2 --import mypkg.losses``
compares it with the built-in losses.
"""

from __future__ import annotations

from imitrl.learners import Learner
from imitrl.learners.actor_critic.entries import mlp
from imitrl.learners.registry import LearnerConfig, register
from imitrl.learners.task import TaskSpec
from imitrl.objectives import RegularizedBCLoss


@register("l1_l2", actions="continuous", summary="L1 + 1e-3 x squared L2 norm of the weights")
def l1_l2(task: TaskSpec, config: LearnerConfig) -> Learner:
    """The task's MLP, tanh-squashed into the bounds, fitted by L1 plus weight decay."""
    ac = mlp(task, config, head="deterministic")
    loss = RegularizedBCLoss(ac.policy, loss_type="l1", l2_coef=1e-3)
    return Learner(ac.policy, loss, ac.opt_pi, normalizer=ac.normalizer)
