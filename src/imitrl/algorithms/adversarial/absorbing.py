"""Absorbing states (Kostrikov et al. 2019, "Discriminator-Actor-Critic"): a
learned reward for what follows the end of an episode.

Why. When an episode *terminates* (a FrozenLake hole or goal, a fallen pole) the learned
reward ends with it: the generator's return is the sum of the rewards of the steps it
lived, so ending means a reward of 0 for ever after, whatever the discriminator thinks
of ending. GAIL's reward ``-log(1 - D) > 0`` is positive at every step, so a policy that
never terminates wins (on FrozenLake: walking into walls rather than to the goal); a
reward negative everywhere biases the other way. A *truncated* episode (a time limit)
is not an end of the MDP and is not treated as one.

The fix (DAC; its code: ``add_absorbing_states`` and ``AbsorbingWrapper`` in
google-research's ``dac/``): after a terminal transition the MDP goes on in one
absorbing state ``s_abs`` with a single action, which loops on itself for ever; the
discriminator learns its reward ``r_abs`` like any other:

* data (:func:`with_absorbing`): a terminated transition's next state becomes ``s_abs``
  (``("next", ABSORBING)``; no transition terminates any more), and each one adds a row
  ``(s_abs, a_0, s_abs)`` (``ABSORBING``) to its side, expert or policy;
* features (:func:`state_features`): a state is read as ``[normalise(s), 0]``, ``s_abs``
  as ``[0, ..., 0, 1]`` (DAC's indicator dimension, here after normalisation); the
  absorbing row's action features are zeros (DAC's zero action) and, for AIRL, its
  single action has ``pi = 1`` (``log pi = 0``);
* the generator (:func:`absorbing_tail`): ``V(s_abs) = r_abs / (1 - gamma)`` in closed
  form, so a terminated step's reward becomes ``r_t + gamma * r_abs / (1 - gamma)``,
  and GAE does not bootstrap there (TorchRL's ``GAE`` zeroes the next value where
  ``("next", "terminated")`` and cuts the trace where ``("next", "done")``); at a
  truncated step (done, not terminated) it bootstraps the critic's ``V(s')``, as before.

When (``AdversarialConfig.absorbing``, off by default). DAC itself notes that the living
bonus of ``-log(1 - D)`` is a prior that helps where the only end is failure (a fallen
pole). Measured with this library's on-policy loop (``benchmarks/beyond_cloning.py``),
absorbing states lift GAIL on FrozenLake, whose demonstrations end at the goal, a little
above the random policy, and break it on InvertedPendulum: there the expert never
terminates, yet the discriminator (a few steps per round) scores ``s_abs``, whose
features sit at the normalised demonstrations' mean, as expert-like, so ending an
episode pays and the learner learns to drop the pole.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn

from imitrl.algorithms.adversarial.keys import ABSORBING
from imitrl.algorithms.adversarial.transitions import (
    NEXT_ABSORBING,
    NEXT_TERMINATED,
    rows_terminated,
)

__all__ = [
    "absorbing_rows",
    "absorbing_tail",
    "demonstrations_terminate",
    "state_features",
    "with_absorbing",
]


def demonstrations_terminate(rows: TensorDictBase) -> bool:
    """Whether any demonstrated episode ends by termination (``("next", "terminated")``):
    a goal reached (Acrobot, FrozenLake, MountainCar), where the expert's episodes end
    and absorbing states price that end; False where every one is truncated (CartPole,
    Pendulum, InvertedPendulum: the expert survives to the time limit), where GAIL's
    living bonus is the right prior (module docstring)."""
    return bool(rows_terminated(rows).any())


def absorbing_rows(template: TensorDictBase, n: int) -> TensorDict:
    """``n`` transitions ``(s_abs, a_0, s_abs)``: every entry of ``template [N]``'s keys zero
    (observations and action are placeholders), ``ABSORBING`` and ``("next", ABSORBING)``
    True, ``("next", TERMINATED)`` False (the absorbing state never ends)."""
    rows = TensorDict(
        {
            key: torch.zeros((n, *value.shape[1:]), dtype=value.dtype, device=value.device)
            for key, value in template.items(include_nested=True, leaves_only=True)
        },
        batch_size=[n],
    )
    rows.get(ABSORBING).fill_(True)
    rows.get(NEXT_ABSORBING).fill_(True)
    return rows


def with_absorbing(transitions: TensorDictBase) -> TensorDict:
    """Transitions ``[N]`` -> ``[N + K]``, ``K`` = rows with ``("next", TERMINATED)``: the ``N``
    rows in their order, a terminated row's next state made absorbing (``("next",
    ABSORBING)`` True, ``("next", TERMINATED)`` False), then ``K`` absorbing rows (DAC:
    one per terminated episode). ``transitions`` is not modified."""
    terminated = transitions.get(NEXT_TERMINATED).reshape(-1, 1)
    out = transitions.clone()
    out.set(NEXT_ABSORBING, transitions.get(NEXT_ABSORBING) | terminated)
    out.set(NEXT_TERMINATED, torch.zeros_like(terminated))
    return torch.cat([out, absorbing_rows(out, int(terminated.sum()))])


def state_features(
    obs: torch.Tensor, absorbing: torch.Tensor, normalizer: nn.Module
) -> torch.Tensor:
    """``obs [N, d]``, ``absorbing [N, 1]`` bool -> ``[N, d + 1]``: ``[normalizer(obs), 0]``, or
    ``[0, ..., 0, 1]`` where ``absorbing`` (the observation is not read there)."""
    x = normalizer(obs)
    x = torch.where(absorbing, torch.zeros_like(x), x)
    return torch.cat([x, absorbing.to(x.dtype)], dim=-1)


def absorbing_tail(
    reward: torch.Tensor, terminated: torch.Tensor, absorbing_reward: torch.Tensor, gamma: float
) -> torch.Tensor:
    """``r_t + [terminated] * gamma * r_abs / (1 - gamma)``: the discounted rewards of the
    absorbing state after a terminal step, ``sum_{k >= 1} gamma^k r_abs``, added to it.

    ``reward [N, 1]``, ``terminated [N, 1]`` bool, ``absorbing_reward`` ``[]`` or ``[1, 1]``;
    ``gamma < 1``."""
    if not 0.0 <= gamma < 1.0:
        raise ValueError(f"the absorbing state's value needs gamma in [0, 1), got {gamma}")
    tail = gamma / (1.0 - gamma) * absorbing_reward.reshape(())
    return reward + terminated.to(reward.dtype) * tail
