"""PPO's clipped loss on a minibatch's tensors: ``ClipPPOLoss``'s arithmetic, without its TensorDicts.

Accelerated internals of :mod:`imitrl.runtime.paths` (import them from there, nowhere else).

On the generator's small networks a ``ClipPPOLoss`` call costs about 4 ms, most of it
TensorDict bookkeeping (cloning the minibatch, building the distribution through the
actor's modules, named applies over the outputs) around networks that compute in a
tenth of that. :class:`TensorPPO` computes what ``ClipPPOLoss.forward`` computes for the
configuration imitrl's generator builds (modules called as they are, no delayed actor,
no value clipping, no entropy bonus, advantages standardised over the minibatch, a
smooth-L1 critic, mean reduction, no loss masks in the batch), on the same tensors with
the same operations in the same order: the same losses and gradients, to the bit
(``tests/algorithms/adversarial/test_loop_lanes.py`` trains GAIL and AIRL on both paths and compares
every weight; ``tests/runtime/fast/test_ppo_step.py`` compares losses and gradients for every
probabilistic head). The log-probability of a tanh-normal or a categorical head is
computed without building its distribution
(:class:`~imitrl.runtime.fast.tanh_normal.TanhNormalLogProb`,
:func:`~imitrl.runtime.fast.categorical.log_prob`: its operations on the same tensors),
other heads build theirs. Any other configuration returns None from
:meth:`TensorPPO.of`, and the seam hands out the loss module itself
(:class:`~imitrl.runtime.losses.PPOReference`, the same methods).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import ProbabilisticTensorDictModule, TensorDictModule
from torch.nn import functional as F
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import ClipPPOLoss

from imitrl.compat import forward_hooked, plain_clip_ppo, plain_sampler, ppo_clip_bounds
from imitrl.runtime.fast import categorical
from imitrl.runtime.fast.policy_call import direct_call
from imitrl.runtime.fast.tanh_normal import TanhNormalLogProb

__all__ = ["TensorPPO"]

_RESOLUTION = torch.finfo(torch.float).resolution
"""``torchrl._utils._standardize``'s epsilon for floating inputs"""


class TensorPPO:
    """``ClipPPOLoss``'s ``loss_objective`` and ``loss_critic`` on tensors (module docstring)."""

    accelerated = True
    """the accelerated path (:class:`~imitrl.runtime.losses.PPOReference` says False)"""

    def __init__(self, loss: ClipPPOLoss) -> None:
        actor, critic = loss.actor_network, loss.critic_network
        params, last = list(actor.module)
        # the networks without nn.Module.__call__ per layer (direct_call: the same
        # operations; decided here, so build a TensorPPO per update, as the generator does)
        self.net, self.value_net = direct_call(params.module), direct_call(critic.module)
        self.dist_class, self.dist_kwargs = last.distribution_class, last.distribution_kwargs
        self.names = [k[-1] if isinstance(k, tuple) else k for k in last.dist_keys]
        self.loss = loss
        self.tanh_normal = TanhNormalLogProb.of(self.dist_class, self.names, self.dist_kwargs)
        self.categorical = categorical.replays(self.dist_class, self.names, self.dist_kwargs)

    @classmethod
    def of(cls, loss: ClipPPOLoss, batch: TensorDictBase | None = None) -> TensorPPO | None:
        """A :class:`TensorPPO` of ``loss``, or None where it would compute anything else
        (also when ``batch`` carries an entry ``ClipPPOLoss`` reads as a loss mask)."""
        if type(loss) is not ClipPPOLoss or not plain_clip_ppo(loss, batch):
            return None
        actor, critic = loss.actor_network, loss.critic_network
        if type(actor) is not ProbabilisticActor or not isinstance(critic, TensorDictModule):
            return None
        modules = list(actor.module)
        if len(modules) != 2 or not isinstance(modules[1], ProbabilisticTensorDictModule):
            return None
        params, last = modules
        if not (
            isinstance(params, TensorDictModule)
            and len(params.in_keys) == 1
            and len(critic.in_keys) == 1
            and params.in_keys == critic.in_keys
            and len(critic.out_keys) == 1
            and isinstance(last.distribution_kwargs, dict)
            and plain_sampler(last, actor)
            and list(last.in_keys) == list(params.out_keys)
            and not forward_hooked(actor, params, last, critic, params.module, critic.module)
        ):
            return None
        return cls(loss)

    def columns(self, flat: TensorDictBase) -> tuple[torch.Tensor, ...]:
        """What :meth:`__call__` reads of a batch's rows (index each by the minibatch's
        rows): the observation, action, behaviour log-probability, advantage and value
        target."""
        k = self.loss.tensor_keys
        return tuple(
            flat.get(key)
            for key in (self.loss.actor_network.in_keys[0], k.action, k.sample_log_prob,
                        k.advantage, k.value_target)
        )  # fmt: skip

    def prepare(self, flat: TensorDictBase) -> tuple[torch.Tensor, ...]:
        """What :meth:`on_rows` indexes: :meth:`columns` of ``flat``."""
        return self.columns(flat)

    def on_rows(
        self, prepared: tuple[torch.Tensor, ...], rows: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """:meth:`__call__` on the minibatch ``rows`` of :meth:`prepare`'s columns."""
        obs, action, old_log_prob, advantage, value_target = (c[rows] for c in prepared)
        return self(obs, action, old_log_prob, advantage, value_target)

    def __call__(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        old_log_prob: torch.Tensor,
        advantage: torch.Tensor,
        value_target: torch.Tensor,
    ) -> dict[str, torch.Tensor]:
        """``{"loss_objective", "loss_critic"}`` of one minibatch, as ``ClipPPOLoss`` returns them."""
        # _maybe_normalize_advantage -> torchrl._utils._standardize (no excluded dims); as
        # there, a minibatch of one row is left as it is (its std is NaN: a review found
        # every weight NaN after a round whose rollout left one row over)
        if advantage.numel() > 1:
            advantage = (advantage - advantage.mean()) / advantage.std().clamp_min(_RESOLUTION)
        net_out = self.net(obs)
        out: tuple[torch.Tensor, ...] = net_out if isinstance(net_out, tuple) else (net_out,)
        if self.tanh_normal is not None:  # its log-probability without the distribution
            loc, scale = out
            log_prob = self.tanh_normal(loc, scale, action)
        elif self.categorical:
            (logits,) = out
            log_prob = categorical.log_prob(logits, action)
        else:
            dist = self.dist_class(**dict(zip(self.names, out)), **self.dist_kwargs)
            log_prob = dist.log_prob(action)
        log_weight = (log_prob - old_log_prob).unsqueeze(-1)  # _log_weight
        gain1 = log_weight.exp() * advantage
        log_weight_clip = log_weight.clamp(*ppo_clip_bounds(self.loss))
        gain2 = log_weight_clip.exp() * advantage
        gain = torch.stack([gain1, gain2], -1).min(dim=-1).values
        value = self.value_net(obs)  # loss_critic: distance_loss, then critic_coeff
        critic = self.loss.critic_coeff * F.smooth_l1_loss(value_target, value, reduction="none")
        return {"loss_objective": (-gain).mean(), "loss_critic": critic.mean()}
