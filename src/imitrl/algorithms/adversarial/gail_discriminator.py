"""GAIL's discriminator (Ho & Ermon 2016): ``D(s, a)`` = P(the pair is the expert's), trained
with TorchRL's ``GAILLoss``, and the reward it hands the generator.

``GAILLoss`` (torchrl 0.14.1, ``objectives/gail.py``) labels its ``expert_*`` inputs 1 and
its ``collector_*`` inputs 0 and applies ``BCELoss`` to what the discriminator writes under
``discriminator_pred``: a probability, not a logit, whatever its default key name
(``"d_logits"``) suggests. So ``D`` is the probability of "expert", and the reward that
is large on expert-like pairs is (Ho & Ermon's cost ``log D`` with the labels swapped)::

    r(s, a) = -log(1 - D(s, a)) = softplus(logit(s, a))            (computed from the logit)

The network reads ``(STATE_FEATURES, ACTION_FEATURES)``: the observation through the
learner's own :class:`~imitrl.policies.normalization.ObservationNormalizer` (the same
module, fitted to the demonstrations; it has no parameters, so nothing the discriminator
learns moves it) with the absorbing indicator appended
(:func:`~imitrl.algorithms.adversarial.absorbing.state_features`), and the action as float
:func:`~imitrl.algorithms.adversarial.transitions.action_features` (one-hot for discrete
actions; zeros at the absorbing state). Its gradient penalty (``use_grad_penalty``,
weight ``gp_lambda``) is ``lambda * mean((|grad_x D(x_mix)| - 1)^2)`` at random
per-entry interpolations ``x_mix`` of the expert and policy feature pairs (so in
normalised coordinates; float features are what it can interpolate).

A step (:meth:`GAILDiscriminator.update`) computes ``GAILLoss`` through the seam
(:func:`imitrl.runtime.paths.gail_loss`: without a penalty, its arithmetic on the four
feature tensors, the same bits), steps Adam through it too, then reports each side's
accuracy on the same pairs after the step.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.objectives import GAILLoss

from imitrl import keys
from imitrl.algorithms.adversarial.absorbing import state_features
from imitrl.algorithms.adversarial.keys import (
    ABSORBING,
    ACTION_FEATURES,
    DISCRIMINATOR_LOGIT,
    EXPERT_PROBABILITY,
    POLICY,
    STATE_FEATURES,
)
from imitrl.algorithms.adversarial.transitions import action_features, learner_inputs
from imitrl.configs.adversarial import ADVERSARIAL_LR, DISCRIMINATOR_HIDDEN
from imitrl.learners.actor_critic import ActorCritic
from imitrl.policies.heads import mlp
from imitrl.policies.modules import Module
from imitrl.runtime import paths
from imitrl.system.ranks import DataParallel

__all__ = ["GAILDiscriminator", "PairNetwork", "gail_reward"]


def gail_reward(logit: torch.Tensor) -> torch.Tensor:
    """``-log(1 - sigmoid(logit)) = softplus(logit)``, elementwise (finite for any logit)."""
    return nn.functional.softplus(logit)


class PairNetwork(nn.Module):
    """``(state [N, d + 1], action [N, k]) features -> (logit [N, 1], sigmoid(logit) [N, 1])``:
    an MLP over their concatenation."""

    def __init__(self, state_dim: int, action_dim: int, hidden: Sequence[int]) -> None:
        super().__init__()
        self.body = mlp([state_dim + action_dim, *hidden, 1], nn.Tanh)

    def forward(self, state: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, ...]:
        logit = self.body(torch.cat([state, action], dim=-1))
        return logit, torch.sigmoid(logit)


class GAILDiscriminator:
    """``D(s, a)``, its ``GAILLoss`` and Adam optimizer (module docstring).

    Args:
        learner: the generator (its action space sizes the network, its normaliser
            is reused).
        hidden: hidden layer sizes of the discriminator's MLP.
        lr: Adam learning rate of the discriminator.
        grad_penalty: ``GAILLoss``'s ``gp_lambda``; 0 disables the penalty.
        seed: initialisation seed (the global RNG is left untouched).
    """

    def __init__(
        self,
        learner: ActorCritic,
        *,
        hidden: Sequence[int] = DISCRIMINATOR_HIDDEN,
        lr: float = ADVERSARIAL_LR,
        grad_penalty: float = 0.0,
        seed: int = 0,
    ) -> None:
        if grad_penalty < 0:
            raise ValueError(f"grad_penalty must be >= 0, got {grad_penalty}")
        obs_dim, self.space = learner_inputs(learner)
        features = action_features(_probe_action(self.space), self.space).shape[-1]
        self.normalizer = learner.normalizer if learner.normalizer is not None else nn.Identity()
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            net = PairNetwork(obs_dim + 1, features, hidden)
        net.to(learner.device)  # initialised on the CPU: the same weights on every device
        self.module = Module(
            net,
            in_keys=[STATE_FEATURES, ACTION_FEATURES],
            out_keys=[DISCRIMINATOR_LOGIT, EXPERT_PROBABILITY],
        )
        self.loss = GAILLoss(self.module, use_grad_penalty=grad_penalty > 0, gp_lambda=grad_penalty)
        self.loss.set_keys(
            expert_observation=STATE_FEATURES,
            expert_action=ACTION_FEATURES,
            collector_observation=(POLICY, STATE_FEATURES),
            collector_action=(POLICY, ACTION_FEATURES),
            discriminator_pred=EXPERT_PROBABILITY,
        )
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=lr)
        self.params = [p for g in self.optimizer.param_groups for p in g["params"]]
        self._calls: dict[tuple[str, bool], Callable[[], None]] = {}

    def pairs(self, transitions: TensorDictBase) -> TensorDict:
        """``STATE_FEATURES`` and ``ACTION_FEATURES`` ``[N]`` of transitions ``[N]``."""
        absorbing = transitions.get(ABSORBING)
        act = action_features(transitions.get(keys.ACTION), self.space)
        return TensorDict(
            {
                STATE_FEATURES: state_features(
                    transitions.get(keys.OBSERVATION), absorbing, self.normalizer
                ),
                ACTION_FEATURES: torch.where(absorbing, torch.zeros_like(act), act),
            },
            batch_size=transitions.shape,
        )

    def batch(self, expert: TensorDictBase, policy: TensorDictBase) -> TensorDict:
        """The ``GAILLoss`` input: expert pairs at the root, the policy's under ``POLICY``."""
        if expert.shape != policy.shape:
            raise ValueError(
                f"GAILLoss pairs expert and policy rows one to one: got {tuple(expert.shape)} "
                f"expert and {tuple(policy.shape)} policy rows"
            )
        out = self.pairs(expert)
        out.set(POLICY, self.pairs(policy))
        return out

    def logits(self, transitions: TensorDictBase) -> torch.Tensor:
        """``[N, 1]`` logit of ``D`` (keeps the graph)."""
        return self.module(self.pairs(transitions)).get(DISCRIMINATOR_LOGIT)

    def update(self, expert: TensorDictBase, policy: TensorDictBase) -> dict[str, float]:
        """One Adam step on ``GAILLoss`` over ``[B]`` expert and ``[B]`` policy transitions;
        returns the loss (penalty included), the penalty and each side's accuracy."""
        batch = self.batch(expert, policy)
        sides = (batch.exclude(POLICY), batch.get(POLICY))  # each side's pairs
        gail_loss = paths.gail_loss(self.loss, batch)  # on the batch's tensors (same bits)
        loss, gp = gail_loss.loss_and_penalty(batch, sides)
        self._optimizer_call("zero_grad")()
        loss.backward()
        dp = DataParallel.of(self.optimizer)  # ranks (--nproc): each holds B of N B pairs
        if dp is not None:
            loss = dp.mean(loss)
        self._optimizer_call("optimizer_step")()
        with torch.no_grad():  # each side's pairs through D after the step
            logits = gail_loss.logits(sides, DISCRIMINATOR_LOGIT)
            expert_acc = (logits[0] > 0).float().mean()
            policy_acc = (logits[1] < 0).float().mean()
        return {
            "loss": float(loss.detach()),
            "grad_penalty": float(gp),
            "expert_accuracy": float(expert_acc),
            "policy_accuracy": float(policy_acc),
        }

    def _optimizer_call(self, piece: str) -> Callable[[], None]:
        """The optimizer's ``zero_grad`` or ``step`` through the seam (``piece``: the
        parameters' assignment, Adam's functional form on the CPU; the same bits), made
        once per path."""
        key = (piece, paths.fast_enabled(piece))
        if key not in self._calls:
            make = paths.zero_grad if piece == "zero_grad" else paths.optimizer_step
            self._calls[key] = make(self.optimizer)
        return self._calls[key]

    def reward(self, transitions: TensorDictBase) -> torch.Tensor:
        """``[N, 1]`` ``-log(1 - D(s, a))``, without gradient."""
        with torch.no_grad():
            return gail_reward(self.logits(transitions))


def _probe_action(space) -> torch.Tensor:
    """One action of ``space`` (to size the action features)."""
    if space is None:
        raise ValueError("the learner has no action space (build it with imitrl.learners.build)")
    if space.kind == "discrete":
        return torch.zeros((1, space.n) if space.one_hot else (1,), dtype=torch.int64)
    if space.kind == "continuous":
        return torch.zeros(1, space.dim)
    raise ValueError(
        f"adversarial imitation supports discrete or continuous actions, got {space.kind}"
    )
