"""The generator: the learner's policy trained by TorchRL's ``ClipPPOLoss`` with ``GAE`` on
the discriminator's reward.

Why PPO, not SAC, for discrete *and* continuous actions: the reward is re-learned every
round (GAIL's ``D`` moves; AIRL's reward contains ``-log pi`` of the current policy), so
an off-policy learner would have to relabel its whole replay buffer each round, and the
learner (:class:`~imitrl.learners.ActorCritic`) carries a state-value head ``V(s)``, what
GAE needs, not the twin ``Q(s, a)`` heads SAC needs. PPO trains the same object
:func:`~imitrl.evaluation.evaluate` evaluates and the checkpoint saves. (This choice was
made on these grounds, not measured against SAC.)

One update (:meth:`PPOGenerator.update`) on a round's batch ``[*B, T]`` carrying
``("next", LEARNED_REWARD)``:

1. ``log pi_old(a|s)`` of the collected actions, written under the loss's
   ``sample_log_prob`` key (the heads do not return it; the policy has not changed since
   it acted, so this is the behaviour policy's);
2. ``epochs`` times: GAE (``gamma``, ``lambda``) on the whole batch with the current value
   head, then minibatches of ``minibatch_size`` rows in an order drawn from ``generator``;
   each step minimises ``loss_objective + loss_entropy + loss_critic`` with the learner's
   own ``opt_pi`` and ``opt_v``, gradients clipped to ``max_grad_norm``; the loop may
   scale their learning rates for the round (:meth:`PPOGenerator.learning_rates`:
   ``AdversarialConfig.anneal_lr``).

Episode ends: TorchRL's GAE reads the env's ``("next", "terminated")`` and ``("next",
"done")`` (``torchrl.objectives.value.functional.generalized_advantage_estimate``:
``delta = r + gamma * (1 - terminated) * V(s') - V(s)``, trace ``lambda * gamma * (1 -
done)``): a terminated step is not bootstrapped (with absorbing states its reward
carries the absorbing state's value instead), a truncated one (done, not terminated)
bootstraps the critic's ``V(s')`` of the final observation, and the trace stops at both.

On data-parallel ranks (``--nproc``) each rank holds its own round's batch (its own env
lanes): GAE runs on it, the minibatch order is the same draw on every rank, and each
step's gradients are averaged over the ranks (:class:`~imitrl.system.ranks.DataParallel`),
so a step is one over ``N`` minibatches; advantages are normalised within each rank's
minibatch, as the multi-GPU PPO of CleanRL does (a data-parallel PPO, not one process's
bit for bit).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import cast

import torch
from tensordict import TensorDictBase
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from imitrl import keys
from imitrl.algorithms.adversarial.keys import LEARNED_REWARD
from imitrl.learners.actor_critic import ActorCritic
from imitrl.runtime import paths
from imitrl.system.ranks import DataParallel

__all__ = ["PPOGenerator"]


class PPOGenerator:
    """``ClipPPOLoss`` + ``GAE`` over an :class:`ActorCritic`'s policy and value head.

    Args:
        learner: a probabilistic-head ``ActorCritic`` (categorical, normal, tanh_normal).
        gamma, gae_lambda: GAE's discount and trace parameter.
        clip_epsilon: PPO's ratio clip.
        entropy_coeff: weight of the entropy bonus (0: none).
        epochs, minibatch_size: passes over each batch, rows per gradient step.
        max_grad_norm: gradient-norm clip of each step.
    """

    def __init__(
        self,
        learner: ActorCritic,
        *,
        gamma: float,
        gae_lambda: float,
        clip_epsilon: float,
        entropy_coeff: float,
        epochs: int,
        minibatch_size: int,
        max_grad_norm: float,
    ) -> None:
        if learner.head == "deterministic":
            raise ValueError(
                "PPO needs a probabilistic policy: build the learner with head categorical, "
                "normal or tanh_normal (a deterministic head has no log pi)"
            )
        if learner.value is None or learner.opt_v is None:
            raise ValueError(
                "PPO needs a value head: build the learner with value=True "
                "(build('default', env, value=True))"
            )
        self.learner, self.epochs, self.minibatch_size = learner, epochs, minibatch_size
        self.value, self.opts = learner.value, (learner.opt_pi, learner.opt_v)
        self.max_grad_norm = max_grad_norm
        self.loss = ClipPPOLoss(
            learner.policy,
            self.value,
            clip_epsilon=clip_epsilon,
            entropy_bonus=entropy_coeff > 0,
            entropy_coeff=entropy_coeff if entropy_coeff > 0 else None,
            normalize_advantage=True,
            # the networks called as they are: the same numbers as the functional copies
            # (checked: identical weights after a run), a seventh less time per step
            functional=False,
        )
        self.loss.set_keys(reward=LEARNED_REWARD)
        self.gae = GAE(gamma=gamma, lmbda=gae_lambda, value_network=self.value)
        self.gae.set_keys(reward=LEARNED_REWARD)
        self.params = [*learner.policy.parameters(), *self.value.parameters()]

    def update(self, batch: TensorDictBase, generator: torch.Generator) -> dict[str, float]:
        """PPO epochs on ``batch`` (module docstring); returns the last epoch's mean losses."""
        with torch.no_grad():
            log_prob = self.learner.get_dist(batch).log_prob(batch.get(keys.ACTION))
        batch.set(self.loss.tensor_keys.sample_log_prob, log_prob)
        n = batch.numel()
        sums: dict[str, float] = {}
        opts = self.opts
        # Adam's step through the seam (its functional form on the CPU, both optimizers
        # in one call: the same bits), the clip likewise
        optimizer_step = paths.optimizer_step(*opts)
        zero_grad = paths.zero_grad(*opts)  # both optimizers' zero_grad(set_to_none=True)
        ppo_loss = paths.ppo_loss(self.loss, batch)  # on the batch's tensors (same bits)
        dp = DataParallel.of(*opts)  # None in a single process
        for _ in range(self.epochs):
            with torch.no_grad():
                self.gae(batch)
            flat = batch.reshape(-1)
            prepared = ppo_loss.prepare(flat)
            order = torch.randperm(n, generator=generator)
            sums = {}
            for start in range(0, n, self.minibatch_size):
                rows = order[start : start + self.minibatch_size]
                losses = ppo_loss.on_rows(prepared, rows)
                total = cast(torch.Tensor, sum(losses.values()))
                zero_grad()
                total.backward()
                if dp is not None:  # ranks: the mean over every rank's minibatch
                    dp.mean(total)
                paths.clip_grad_norm(self.params, self.max_grad_norm)
                optimizer_step()
                for k, v in losses.items():
                    sums[k] = sums.get(k, 0.0) + float(v.detach())
        steps = -(-n // self.minibatch_size)
        return {k: v / steps for k, v in sums.items()}

    @contextlib.contextmanager
    def learning_rates(self, scale: float) -> Iterator[None]:
        """Within the block, every parameter group of ``opt_pi`` and ``opt_v`` steps at
        ``scale`` times its own learning rate (the annealing of
        ``AdversarialConfig.anneal_lr``); the learner's own rates are back after it, even
        on an error."""
        groups = [g for o in self.opts for g in o.param_groups]
        own = [g["lr"] for g in groups]
        for g, lr in zip(groups, own):
            g["lr"] = lr * scale
        try:
            yield
        finally:
            for g, lr in zip(groups, own):
                g["lr"] = lr
