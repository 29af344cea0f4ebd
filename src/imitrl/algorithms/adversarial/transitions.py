"""Transitions ``(s, a, s', terminated)``: what both discriminators read, from either side.

* :func:`expert_transitions`: the demonstrations' rows (a ``DemonstrationBuffer``, a
  LeRobot or Minari dataset loaded into one). ``s'`` of a row is the observation of the
  next row of its episode (``STEP + 1``). An episode's last row has no successor: kept
  when it terminated (its ``s'`` is the end: the absorbing state, or zeroed in AIRL's
  ``h(s')``; never read, it is set to ``s``); when the episode was cut by a time limit,
  kept where the data recorded its ``s'`` (``("next", OBSERVATION)``, as a Minari
  dataset does; it must agree with the next rows elsewhere), dropped otherwise (rollouts
  and LeRobot datasets record none: :mod:`imitrl.runtime.rollout`).
  Every row must have executed the expert's action (``EXPERT_EXECUTED``): adversarial
  imitation matches the expert's state-action occupancy, which only its own
  trajectories sample.
* :func:`policy_transitions`: a round's batch ``[*B, T]`` flattened to rows.
* :func:`action_features`: the float ``[N, k]`` action a discriminator network reads.

Every returned TensorDict holds ``OBSERVATION [N, d]``, ``ACTION [N, ...]``,
``("next", OBSERVATION) [N, d]``, ``("next", TERMINATED) [N, 1]`` bool (the env's
``terminated``: a time limit's ``truncated`` is not an end), and ``ABSORBING`` /
``("next", ABSORBING) [N, 1]`` bool, all False: no state is the absorbing one until
:func:`~imitrl.algorithms.adversarial.absorbing.with_absorbing` adds it.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase

from imitrl import keys
from imitrl.algorithms.adversarial.keys import ABSORBING
from imitrl.policies.specs import ActionSpace

__all__ = [
    "action_features",
    "expert_transitions",
    "policy_transitions",
    "rows_terminated",
    "sample_rows",
]

NEXT_OBS = (keys.NEXT, keys.OBSERVATION)
NEXT_TERMINATED = (keys.NEXT, keys.TERMINATED)
NEXT_ABSORBING = (keys.NEXT, ABSORBING)


def rows_terminated(rows: TensorDictBase) -> torch.Tensor:
    """``[N]`` bool: the row's episode terminated there (False where the data says nothing)."""
    if NEXT_TERMINATED in rows.keys(include_nested=True):
        return rows.get(NEXT_TERMINATED).reshape(rows.shape[0], -1).any(-1)
    return torch.zeros(rows.shape[0], dtype=torch.bool, device=rows.device)


def expert_transitions(rows: TensorDictBase) -> TensorDict:
    """Demonstration rows ``[N]`` (episodes back to back) -> transitions ``[M]``, ``M <= N``
    (module docstring: which rows are kept).

    Raises:
        ValueError: no rows, a missing key, a row where the expert's action was not
            executed, or no row with a known successor.
    """
    if not isinstance(rows, TensorDictBase) or rows.batch_dims != 1 or rows.shape[0] == 0:
        raise ValueError("expert_transitions needs demonstration rows: a TensorDict [N], N >= 1")
    need = (keys.OBSERVATION, keys.ACTION, keys.EPISODE, keys.STEP, keys.EXPERT_EXECUTED)
    missing = [k for k in need if k not in rows.keys()]
    if missing:
        raise ValueError(
            f"demonstration rows lack {missing} (a DemonstrationBuffer's rows have them)"
        )
    executed = rows.get(keys.EXPERT_EXECUTED)
    if not bool(executed.all()):
        raise ValueError(
            f"{int((~executed).sum())} demonstration rows executed another action than the "
            "expert's: adversarial imitation needs the expert's own trajectories"
        )
    obs, episode, step = rows.get(keys.OBSERVATION), rows.get(keys.EPISODE), rows.get(keys.STEP)
    terminated = rows_terminated(rows)
    has_next = torch.zeros_like(terminated)
    has_next[:-1] = (episode[1:] == episode[:-1]) & (step[1:] == step[:-1] + 1)
    next_obs = obs.clone()  # terminal rows keep s' = s, never read (module docstring)
    next_obs[:-1][has_next[:-1]] = obs[1:][has_next[:-1]]
    keep = has_next | terminated
    if (keys.NEXT, keys.OBSERVATION) in rows.keys(include_nested=True):
        keep = keep | _stored_successors(rows, next_obs, has_next, terminated)
    if not bool(keep.any()):
        raise ValueError("no demonstration row has a known next observation")
    return _transitions(
        obs[keep], rows.get(keys.ACTION)[keep], next_obs[keep], terminated[keep].unsqueeze(-1)
    )


def _stored_successors(rows, next_obs, has_next, terminated) -> torch.Tensor:
    """Rows whose ``s'`` the data recorded (``("next", OBSERVATION)``: a Minari dataset)
    where no next row gives it, an episode cut by a time limit: their ``s'`` is written
    into ``next_obs``. Where the next row gives it too, the two must agree (ValueError
    naming the row otherwise)."""
    stored = rows.get((keys.NEXT, keys.OBSERVATION))
    if stored.shape != next_obs.shape:
        raise ValueError(
            f"rows' ('next', 'observation') is {list(stored.shape)}, their observation "
            f"{list(next_obs.shape)}"
        )
    close = torch.isclose(stored.double(), next_obs.double())  # (a dataset's dtype, as read)
    both = has_next & ~close.reshape(len(stored), -1).all(-1)
    if bool(both.any()):
        i = int(torch.nonzero(both)[0, 0])
        raise ValueError(
            f"row {i} (episode {int(rows.get(keys.EPISODE)[i])}, step "
            f"{int(rows.get(keys.STEP)[i])}): its recorded next observation differs from "
            "the next row's observation"
        )
    cut = ~has_next & ~terminated
    next_obs[cut] = stored[cut].to(next_obs.dtype)
    return cut


def policy_transitions(batch: TensorDictBase) -> TensorDict:
    """A round's batch ``[*B, T]`` -> transitions ``[N]``, ``N = prod(B) * T``, same order."""
    flat = batch.reshape(-1)
    return _transitions(
        flat.get(keys.OBSERVATION),
        flat.get(keys.ACTION),
        flat.get(NEXT_OBS),
        flat.get(NEXT_TERMINATED).reshape(flat.shape[0], 1),
    )


def _transitions(obs, action, next_obs, terminated) -> TensorDict:
    """The transition keys (module docstring), no absorbing state."""
    n = obs.shape[0]
    return TensorDict(
        {
            keys.OBSERVATION: obs,
            keys.ACTION: action,
            NEXT_OBS: next_obs,
            NEXT_TERMINATED: terminated,
            ABSORBING: torch.zeros(n, 1, dtype=torch.bool, device=obs.device),
            NEXT_ABSORBING: torch.zeros(n, 1, dtype=torch.bool, device=obs.device),
        },
        batch_size=[n],
    )


def learner_inputs(learner) -> tuple[int, ActionSpace]:
    """``(d, action space)`` of an ``ActorCritic`` a discriminator pairs with: its flat
    vector observations ``[d]`` and the action space it writes (refused otherwise, by name)."""
    shape, space = learner.observation_shape, learner.action_space
    if shape is None or len(shape) != 1:
        raise ValueError(
            "a discriminator reads flat vector observations [d]; this learner reads "
            + ("integer states" if shape is None else f"observations {tuple(shape)}")
        )
    if space is None:
        raise ValueError(
            "a discriminator needs the learner's action space: build the learner from the "
            "env or a TaskSpec (imitrl.learners.build)"
        )
    return int(shape[0]), space


def action_features(action: torch.Tensor, space: ActionSpace) -> torch.Tensor:
    """Actions ``[N, ...]`` -> float ``[N, k]``: one-hot ``k = n`` (discrete), ``k = dim``
    (continuous)."""
    if space.kind == "discrete":
        if space.one_hot:
            return action.to(torch.float32)
        assert space.n is not None  # a discrete ActionSpace always has its n
        return torch.nn.functional.one_hot(action.long().reshape(-1), space.n).to(torch.float32)
    if space.kind == "continuous":
        assert space.dim is not None  # a continuous ActionSpace always has its dim
        return action.to(torch.float32).reshape(action.shape[0], space.dim)
    raise ValueError(
        f"adversarial imitation supports discrete or continuous actions, got {space.kind}"
    )


def sample_rows(td: TensorDictBase, n: int, generator: torch.Generator) -> TensorDictBase:
    """``n`` rows of ``td [N]`` drawn uniformly with replacement from ``generator``."""
    return td[torch.randint(td.shape[0], (n,), generator=generator)]
