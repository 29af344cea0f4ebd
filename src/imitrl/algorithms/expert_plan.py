"""Chunk-aware DAgger's labels: at every state the behaviour policy visits, the expert's
own next ``H`` actions from that state (:class:`ExpertPlanner`).

A chunked learner (ACT, Diffusion Policy, a flow over chunks) learns ``H`` actions per
state. Relabelled rows of a learner-driven round can only give it one of them by
windowing (:mod:`imitrl.data.chunks`: the label at a later visited state answers "what
would the expert do from there", not "what would it have done next"). The planner answers
the second question directly: before the env takes the behaviour policy's step, it takes
the simulator's state (:class:`~imitrl.envs.snapshot.Snapshot`), lets the expert drive the
env ``H`` steps from there (TorchRL's ``env.rollout`` from the current observation, its
episode's step count and time limit included), records the actions it executed, and
puts the state back: the episode then goes on exactly as it would have. The plan is
written under ``EXPERT_PLAN`` ``[H, *action]`` with ``EXPERT_PLAN_PAD`` (True past the
episode's end within the plan, where the plan repeats its last action, as windowing pads);
its first action is the row's own label.

Cost: ``H`` expert steps per visited state. Envs whose state can be taken in this process
(gymnasium envs through ``make_env``, imitrl's own envs; one lane) plan; others are
refused by :meth:`ExpertPlanner.check`.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl import keys
from imitrl.envs.snapshot import Snapshot
from imitrl.policies.experts import Expert, as_actor

__all__ = ["ExpertPlanner", "with_plans"]


class ExpertPlanner(TensorDictModuleBase):
    """Writes ``EXPERT_PLAN`` and ``EXPERT_PLAN_PAD`` for the state ``td`` holds, by
    letting ``expert`` drive ``env`` ``horizon`` steps from it and undoing them (module
    docstring). ``env`` is the env being played, at that state, with one lane."""

    def __init__(self, expert: Expert, env: EnvBase, horizon: int) -> None:
        super().__init__()
        if int(horizon) != horizon or horizon < 1:
            raise ValueError(f"horizon must be a positive integer, got {horizon!r}")
        self.check(env)
        self.expert, self.env, self.horizon = expert, env, int(horizon)
        self.actor = as_actor(expert)
        self.in_keys = list(expert.in_keys)
        self.out_keys = [keys.EXPERT_PLAN, keys.EXPERT_PLAN_PAD]
        self._observed = [k for k in env.observation_spec.keys(True, True)]

    @staticmethod
    def check(env: EnvBase) -> None:
        """ValueError unless the planner can play ``env`` (one lane, its state here)."""
        if env.batch_size.numel() != 1 or len(env.batch_size) > 0:
            raise ValueError(
                f"the expert plans on an env with one lane; this one has batch size "
                f"{tuple(env.batch_size)} (play the relabel rounds with --num-envs 1)"
            )
        Snapshot.take(env)  # refuses what cannot be taken, naming it

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        snapshot = Snapshot.take(self.env)
        start = tensordict.select(*self._observed, strict=False).clone()
        try:
            with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
                played = self.env.rollout(
                    self.horizon,
                    self.actor,
                    tensordict=start,
                    auto_reset=False,
                    break_when_any_done=True,
                )
        finally:
            snapshot.restore()
        actions = played.get(keys.ACTION)  # [T <= H, *action]: up to the episode's end
        steps = actions.shape[0]
        plan = torch.cat([actions, actions[-1:].expand(self.horizon - steps, *actions.shape[1:])])
        pad = torch.arange(self.horizon) >= steps
        tensordict.set(keys.EXPERT_PLAN, plan)
        tensordict.set(keys.EXPERT_PLAN_PAD, pad)
        return tensordict


def with_plans(rows: TensorDictBase, horizon: int) -> TensorDictBase:
    """Demonstration rows (the expert drove every step) with ``EXPERT_PLAN`` and
    ``EXPERT_PLAN_PAD``: the expert's next ``horizon`` labels within the episode, which
    are its plan from each row's state (what the planner records in a relabel round, so
    that both share one buffer schema). ValueError where a row's executed action was not
    the expert's: that row's plan was not recorded."""
    from imitrl.data.chunks import chunk_labels

    executed = rows.get(keys.EXPERT_EXECUTED, None)
    if executed is not None and not bool(executed.all()):
        raise ValueError(
            "with_plans takes rows where the expert drove (every expert_executed True): "
            "a relabelled row's plan comes from ExpertPlanner during its round"
        )
    plan, pad = chunk_labels(
        rows.get(keys.EXPERT_ACTION), rows.get(keys.EPISODE), rows.get(keys.STEP), horizon
    )
    out = rows.clone(recurse=False)
    out.set(keys.EXPERT_PLAN, plan)
    out.set(keys.EXPERT_PLAN_PAD, pad)
    return out
