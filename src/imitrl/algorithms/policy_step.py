"""`policy_step`: one ascent step on the advantage-weighted log-likelihood.

``E_t[A_t log pi(a_t | s_t)]`` with the weights ``A_t`` treated as data: they are
converted to a detached tensor before they meet the log-probabilities, so no
gradient can flow through them. Behaviour cloning is the special case ``A_t = 1``
with ``a_t`` the expert's label.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase

from imitrl import keys
from imitrl.learners.actor_critic import ActorCritic
from imitrl.objectives.bc import BehaviorCloningLoss

__all__ = ["policy_step"]


def _as_batch(batch: Any, action_key) -> TensorDictBase:
    if isinstance(batch, TensorDictBase):
        return batch
    obs, act = getattr(batch, "obs", None), getattr(batch, "act", None)
    if obs is None or act is None:
        raise ValueError("batch must be a TensorDict or carry `obs` and `act` arrays")
    obs = torch.as_tensor(np.asarray(obs) if not isinstance(obs, torch.Tensor) else obs)
    act = torch.as_tensor(np.asarray(act) if not isinstance(act, torch.Tensor) else act)
    return TensorDict({keys.OBSERVATION: obs, action_key: act}, batch_size=[obs.shape[0]])


def policy_step(ac: ActorCritic, batch: Any, advantage: Any, *, action_key=keys.ACTION) -> float:
    """One optimizer step of ``ac.opt_pi`` on ``-mean_t(A_t log pi(a_t|s_t))``.

    Args:
        ac: the actor-critic whose policy is updated (probabilistic head).
        batch: a TensorDict with ``OBSERVATION`` and ``action_key`` entries, or any
            object with ``obs`` and ``act`` arrays (``[N]`` / ``[N, ...]``).
        advantage: ``[N]`` weights (numpy or tensor); used as data, never differentiated.
        action_key: where the taken actions live (``"action"``; pass
            ``"expert_action"`` to clone an expert).

    Returns:
        the loss before the step, as a float.
    """
    td = _as_batch(batch, action_key)
    n = td.shape[0] if td.batch_dims else 1
    weight = torch.as_tensor(
        np.asarray(advantage) if not isinstance(advantage, torch.Tensor) else advantage
    )
    weight = weight.detach().to(torch.float32)
    if weight.shape != (n,):
        raise ValueError(
            f"advantage must have one weight per row, shape ({n},), got {tuple(weight.shape)}"
        )
    if not torch.isfinite(weight).all():
        raise ValueError("advantage contains NaN or inf")
    loss_module = BehaviorCloningLoss(ac.policy, loss_type="nll", weighted=True)
    loss_module.set_keys(label=action_key)
    data = td.select(keys.OBSERVATION, action_key).set(keys.WEIGHT, weight)
    loss = loss_module(data)["loss_bc"]
    ac.opt_pi.zero_grad()
    loss.backward()
    ac.opt_pi.step()
    return float(loss.detach())
