"""Regularised behaviour cloning: a :class:`BehaviorCloningLoss` plus entropy and L2 terms.

``loss = mean_i l_i - entropy_coef * mean_i H(pi(.|s_i)) + l2_coef * sum_W ||W||^2``

* ``l_i`` is the per-row loss of :class:`~imitrl.objectives.BehaviorCloningLoss`
  (``nll``, ``mse``, ``l1``, ``smooth_l1``);
* the entropy bonus (probabilistic heads only) keeps the clone from becoming
  over-confident on the few states it saw: exact for a categorical policy
  (``-sum_a pi log pi``), a one-sample reparameterised estimate ``-log pi(a~|s)``
  for a tanh-normal one;
* the L2 penalty is on the weight matrices (biases are not decayed).

Each term is its own ``loss_*`` entry, so a trainer that sums the ``loss_*`` entries
(``fit_bc(..., loss_module=...)``) minimises the total.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule

from imitrl import keys
from imitrl.objectives.base import InnerBCLoss
from imitrl.objectives.bc import BehaviorCloningLoss
from imitrl.rng import SavedGenerator, rng_from

__all__ = ["RegularizedBCLoss"]


class RegularizedBCLoss(SavedGenerator, InnerBCLoss):
    """Behaviour cloning with an entropy bonus and an L2 penalty (see the module docstring).

    Args:
        actor: the policy (as for :class:`BehaviorCloningLoss`).
        loss_type: the data term, one of ``imitrl.objectives.LOSS_TYPES``.
        entropy_coef: weight of the entropy bonus (>= 0; needs a probabilistic actor).
        l2_coef: weight of the squared L2 norm of the actor's weight matrices (>= 0).
        seed: seed of the generator behind the one-sample entropy estimate of
            continuous policies (categorical entropies are exact and draw nothing).

    Keys: as :class:`BehaviorCloningLoss` (remap with ``set_keys`` on this module).
    Returns ``loss_bc``, ``loss_entropy`` (if ``entropy_coef > 0``), ``loss_l2`` (if
    ``l2_coef > 0``) and the detached metrics ``entropy`` / ``l2``.
    """

    out_keys = ["loss_bc", "loss_entropy", "loss_l2"]

    def __init__(
        self,
        actor: TensorDictModule,
        *,
        loss_type: str = "nll",
        entropy_coef: float = 0.0,
        l2_coef: float = 0.0,
        seed: int = 0,
    ) -> None:
        if entropy_coef < 0 or l2_coef < 0:
            raise ValueError(
                f"entropy_coef and l2_coef must be >= 0, got {entropy_coef} and {l2_coef}"
            )
        if entropy_coef > 0 and not hasattr(actor, "get_dist"):
            raise ValueError("an entropy bonus needs a probabilistic actor (with get_dist)")
        super().__init__()
        self.bc = BehaviorCloningLoss(actor, loss_type=loss_type)
        self.actor = actor
        self.entropy_coef = float(entropy_coef)
        self.l2_coef = float(l2_coef)
        self.generator = torch.Generator().manual_seed(int(seed))

    def _entropy(self, out: TensorDictBase) -> torch.Tensor:
        if keys.LOGITS in out.keys():
            logp = torch.log_softmax(out.get(keys.LOGITS), dim=-1)
            return -(logp.exp() * logp).sum(-1)
        dist = self.actor.get_dist(out)
        with rng_from(self.generator):
            if hasattr(dist, "rsample_and_log_prob"):
                _, logp = dist.rsample_and_log_prob()
            else:
                logp = dist.log_prob(dist.rsample())
        return -logp

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        losses, out = self.bc.per_row(tensordict)
        result = {"loss_bc": losses.mean(), self.bc.loss_type: losses.detach().mean()}
        if self.entropy_coef > 0:
            entropy = self._entropy(out).mean()
            result["loss_entropy"] = -self.entropy_coef * entropy
            result["entropy"] = entropy.detach()
        if self.l2_coef > 0:
            l2 = sum(p.pow(2).sum() for p in self.actor.parameters() if p.ndim > 1)
            result["loss_l2"] = self.l2_coef * l2
            result["l2"] = l2.detach()
        return TensorDict(result, batch_size=[])
