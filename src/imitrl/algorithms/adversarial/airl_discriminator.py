"""AIRL's discriminator (Fu, Luo & Levine 2018) and its reward, as exact formulas first.

The discriminator is structured by the generator's own policy (eq. 2 of the paper)::

    D(s, a, s') = exp(f(s, a, s')) / (exp(f(s, a, s')) + pi(a|s))
                = sigmoid(f(s, a, s') - log pi(a|s))                     (logit = f - log pi)

with the shaped f of section 5 (the disentangled reward)::

    f(s, a, s') = g(s) + gamma * (1 - terminated) * h(s') - h(s)

``g`` is a *state-only* reward (what the paper needs for the recovered reward to transfer
to other dynamics; we use that variant), ``h`` a shaping potential; at a terminal
transition there is no next state and ``h(s')`` is zeroed. With absorbing states
(:mod:`~imitrl.algorithms.adversarial.absorbing`) nothing terminates: a terminal
transition's ``s'`` is the absorbing state, read like any other (``g``, ``h`` read
:func:`~imitrl.algorithms.adversarial.absorbing.state_features`), and the absorbing
state's single action has ``pi = 1``, ``log pi = 0``. The generator's reward is::

    r(s, a, s') = log D - log(1 - D) = f(s, a, s') - log pi(a|s)

``log pi`` is the current policy's, always detached: the discriminator's loss moves only
``g`` and ``h``, never the policy. The loss is the same binary cross-entropy as GAIL's
(expert pairs labelled 1, the policy's 0, summed per pair and averaged), written on the
logit; the optional gradient penalty mirrors ``GAILLoss``'s: ``lambda * mean((|grad f| -
1)^2)`` at per-row interpolations of the expert and policy ``(s, s')`` state features.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn

from imitrl import keys
from imitrl.algorithms.adversarial.absorbing import state_features
from imitrl.algorithms.adversarial.keys import ABSORBING
from imitrl.algorithms.adversarial.transitions import (
    NEXT_ABSORBING,
    NEXT_OBS,
    NEXT_TERMINATED,
    learner_inputs,
)
from imitrl.configs.adversarial import ADVERSARIAL_LR, DISCRIMINATOR_HIDDEN
from imitrl.learners.actor_critic import ActorCritic
from imitrl.policies.heads import mlp
from imitrl.system.ranks import DataParallel

__all__ = ["AIRLDiscriminator", "ShapedReward", "airl_reward", "shaped_f"]


def shaped_f(
    g: torch.Tensor, h: torch.Tensor, h_next: torch.Tensor, terminated: torch.Tensor, gamma: float
) -> torch.Tensor:
    """``f = g(s) + gamma * (1 - terminated) * h(s') - h(s)``; every input ``[N, 1]``."""
    return g + gamma * (~terminated).to(h_next.dtype) * h_next - h


def airl_reward(f: torch.Tensor, log_pi: torch.Tensor, entropy_weight: float = 1.0) -> torch.Tensor:
    """``f - w log pi(a|s)``; at ``w = 1`` it is ``log D - log(1 - D)``, the logit of
    ``D``; inputs ``[N, 1]``."""
    return f - entropy_weight * log_pi


class ShapedReward(nn.Module):
    """``g(s)`` and ``h(s)``: two MLPs over state features ``[N, k]`` (``k = d + 1``:
    :func:`~imitrl.algorithms.adversarial.absorbing.state_features`).

    ``forward(x [N, k], x_next [N, k], terminated [N, 1] bool) -> f, g, h(s), h(s')``,
    each ``[N, 1]``.
    """

    def __init__(self, state_dim: int, hidden: Sequence[int], gamma: float) -> None:
        super().__init__()
        self.gamma = float(gamma)
        self.g = mlp([state_dim, *hidden, 1], nn.Tanh)
        self.h = mlp([state_dim, *hidden, 1], nn.Tanh)

    def forward(self, x, x_next, terminated) -> tuple[torch.Tensor, ...]:
        g, h, h_next = self.g(x), self.h(x), self.h(x_next)
        return shaped_f(g, h, h_next, terminated, self.gamma), g, h, h_next


class AIRLDiscriminator:
    """``D = sigmoid(f - log pi)`` over transitions, its loss and Adam optimizer (module
    docstring).

    Args:
        learner: the generator, whose ``log pi(a|s)`` structures ``D`` (a probabilistic
            head: categorical, normal or tanh_normal).
        gamma: the discount of ``f``'s shaping (the generator's own).
        hidden: hidden layer sizes of ``g`` and ``h``.
        lr: Adam learning rate.
        grad_penalty: weight of the gradient penalty; 0 disables it.
        seed: initialisation seed (the global RNG is left untouched).
        entropy_weight: ``w`` of the generator's reward ``f - w log pi`` (1: the paper's).
    """

    def __init__(
        self,
        learner: ActorCritic,
        *,
        gamma: float,
        hidden: Sequence[int] = DISCRIMINATOR_HIDDEN,
        lr: float = ADVERSARIAL_LR,
        grad_penalty: float = 0.0,
        seed: int = 0,
        entropy_weight: float = 1.0,
    ) -> None:
        if not 0.0 <= gamma <= 1.0:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        if grad_penalty < 0:
            raise ValueError(f"grad_penalty must be >= 0, got {grad_penalty}")
        if learner.head == "deterministic":
            raise ValueError("AIRL needs log pi(a|s): build the learner with a probabilistic head")
        self.learner, self.grad_penalty = learner, float(grad_penalty)
        self.entropy_weight = float(entropy_weight)
        obs_dim, _ = learner_inputs(learner)
        self.normalizer = learner.normalizer if learner.normalizer is not None else nn.Identity()
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.network = ShapedReward(obs_dim + 1, hidden, gamma)
        self.network.to(learner.device)  # initialised on the CPU: the same weights anywhere
        self.optimizer = torch.optim.Adam(self.network.parameters(), lr=lr)

    def log_pi(self, transitions: TensorDictBase) -> torch.Tensor:
        """``[N, 1]`` ``log pi(a|s)`` of the current policy, detached; 0 at the absorbing
        state (its single action)."""
        td = TensorDict({keys.OBSERVATION: transitions.get(keys.OBSERVATION)}, transitions.shape)
        with torch.no_grad():
            lp = self.learner.get_dist(td).log_prob(transitions.get(keys.ACTION))
        lp = lp.reshape(transitions.shape[0], 1)
        return torch.where(transitions.get(ABSORBING), torch.zeros_like(lp), lp)

    def features(self, transitions: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """State features ``[N, d + 1]`` of ``s`` and of ``s'``."""
        obs, next_obs = transitions.get(keys.OBSERVATION), transitions.get(NEXT_OBS)
        return (
            state_features(obs, transitions.get(ABSORBING), self.normalizer),
            state_features(next_obs, transitions.get(NEXT_ABSORBING), self.normalizer),
        )

    def f(self, transitions: TensorDictBase) -> torch.Tensor:
        """``[N, 1]`` shaped ``f(s, a, s')`` (keeps the graph)."""
        return self.network(*self.features(transitions), transitions.get(NEXT_TERMINATED))[0]

    def logits(self, transitions: TensorDictBase) -> torch.Tensor:
        """``[N, 1]`` logit of ``D``: ``f - log pi`` (graph through ``f`` only)."""
        return airl_reward(self.f(transitions), self.log_pi(transitions))

    def loss(self, expert: TensorDictBase, policy: TensorDictBase) -> dict[str, torch.Tensor]:
        """``{"loss", "grad_penalty"}``: the BCE of ``[B]`` expert (label 1) and ``[B]``
        policy (label 0) transitions, plus the penalty (included in ``loss``)."""
        if expert.shape != policy.shape:
            raise ValueError(
                f"the AIRL loss pairs expert and policy rows one to one: got "
                f"{tuple(expert.shape)} and {tuple(policy.shape)}"
            )
        bce = nn.functional.binary_cross_entropy_with_logits
        le, lp = self.logits(expert), self.logits(policy)
        loss = (
            bce(le, torch.ones_like(le), reduction="none")
            + bce(lp, torch.zeros_like(lp), reduction="none")
        ).mean()
        gp = self._penalty(expert, policy) if self.grad_penalty > 0 else torch.zeros(())
        return {"loss": loss + gp, "grad_penalty": gp.detach()}

    def _penalty(self, expert: TensorDictBase, policy: TensorDictBase) -> torch.Tensor:
        alpha = torch.rand(expert.shape[0], 1).to(expert.device)  # global CPU RNG: seeded
        mix = [
            (alpha * p + (1 - alpha) * e).requires_grad_(True)
            for p, e in zip(self.features(policy), self.features(expert))
        ]
        f = self.network(*mix, expert.get(NEXT_TERMINATED))[0]
        grads = torch.autograd.grad(f.sum(), mix, create_graph=True)
        norm = torch.cat(grads, dim=-1).norm(dim=-1)
        return self.grad_penalty * ((norm - 1) ** 2).mean()

    def update(self, expert: TensorDictBase, policy: TensorDictBase) -> dict[str, float]:
        """One Adam step on :meth:`loss`; returns it and each side's accuracy."""
        out = self.loss(expert, policy)
        self.optimizer.zero_grad(set_to_none=True)
        out["loss"].backward()
        dp = DataParallel.of(self.optimizer)  # ranks (--nproc): each holds B of N B pairs
        if dp is not None:
            out["loss"] = dp.mean(out["loss"])
        self.optimizer.step()
        with torch.no_grad():
            expert_acc = (self.logits(expert) > 0).float().mean()
            policy_acc = (self.logits(policy) < 0).float().mean()
        return {
            "loss": float(out["loss"].detach()),
            "grad_penalty": float(out["grad_penalty"]),
            "expert_accuracy": float(expert_acc),
            "policy_accuracy": float(policy_acc),
        }

    def reward(self, transitions: TensorDictBase) -> torch.Tensor:
        """``[N, 1]`` the generator's reward ``f - w log pi``, without gradient."""
        with torch.no_grad():
            return airl_reward(self.f(transitions), self.log_pi(transitions), self.entropy_weight)
