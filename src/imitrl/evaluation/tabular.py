"""Read a policy module as a tabular policy, and price it exactly."""

from __future__ import annotations

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl import keys
from imitrl.tabular.finite_horizon import expected_return, success_probability
from imitrl.tabular.mdp import TabularMDP

__all__ = ["exact_values", "tabulate"]


def tabulate(
    policy: TensorDictModuleBase, num_states: int, exploration: ExplorationType
) -> torch.Tensor:
    """The policy on every state ``0 .. S-1``.

    Returns:
        ``[S]`` int64 actions for ``DETERMINISTIC``/``MODE``; ``[S, A]`` float64
        probabilities for ``RANDOM``: the module's ``get_dist`` logits, normalised in
        float64 (float32 probabilities miss 1 by ~1e-7). A module without ``get_dist``
        (an expert, a table lookup) must act the same sampled as greedy; its action
        is then the policy (checked on every state, else ``ValueError``).
    """
    td = TensorDict({keys.OBSERVATION: torch.arange(num_states)}, batch_size=[num_states])
    with torch.no_grad():
        if exploration in (ExplorationType.DETERMINISTIC, ExplorationType.MODE):
            with set_exploration_type(exploration):
                return policy(td).get(keys.ACTION).long()
        if exploration is ExplorationType.RANDOM:
            get_dist = getattr(policy, "get_dist", None)
            if get_dist is not None:
                return torch.softmax(get_dist(td).logits.double(), dim=-1)
            with set_exploration_type(ExplorationType.DETERMINISTIC):
                greedy = policy(td.clone()).get(keys.ACTION).long()
            with torch.random.fork_rng(devices=[]), set_exploration_type(exploration):
                sampled = policy(td.clone()).get(keys.ACTION).long()
            if not torch.equal(greedy, sampled):
                raise ValueError(
                    "a sampled (RANDOM) policy without get_dist() cannot be tabulated: its "
                    "sampled actions differ from its greedy ones"
                )
            return greedy
    raise ValueError(f"unsupported exploration type {exploration}")


def exact_values(
    mdp: TabularMDP,
    policy: TensorDictModuleBase,
    exploration: ExplorationType,
    horizon: int | None = None,
    *,
    initial: torch.Tensor | None = None,
) -> dict[str, float]:
    """Exact success probability and expected return of a policy module in ``horizon`` steps.

    ``initial`` overrides the MDP's start distribution (e.g. pinned env lanes).
    """
    table = tabulate(policy, mdp.num_states, exploration)
    return {
        "success": success_probability(mdp, table, horizon, initial=initial),
        "return": expected_return(mdp, table, horizon, initial=initial),
    }
