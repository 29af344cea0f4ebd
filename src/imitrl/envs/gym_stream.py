"""Gymnasium-faithful episodes without per-step Python: play a uniform stream in bulk.

A gymnasium toy-text env seeded with ``reset(seed=k)`` consumes its numpy
``Generator`` one uniform per reset and one per step, and reset without a seed
continues the same stream. An experiment that alternates demonstrations,
evaluations and relabel rollouts on one env is therefore a deterministic function of
that single stream.

:class:`GymnasiumStream` draws the stream in bulk (``Generator.random(n)`` yields
the same numbers as ``n`` calls of ``random()``). :func:`play_episodes` then plays a
deterministic tabular policy for ``n`` consecutive episodes: it simulates an episode
starting at *every* stream offset of a window at once, as one batch of lanes through
the same :class:`~imitrl.tabular.OutcomeSampler` that drives :class:`TabularEnv`,
and walks the chain ``offset -> offset + 1 + length`` to pick the episodes gymnasium
would have played. The result equals a step-by-step gymnasium loop (tested), at
batched-tensor speed.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import torch
from gymnasium.utils import seeding
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from imitrl import keys
from imitrl.tabular.finite_horizon import expected_episode_length
from imitrl.tabular.mdp import TabularMDP
from imitrl.tabular.policy import policy_probs
from imitrl.tabular.sampling import OutcomeSampler, play_compacted

__all__ = ["Episodes", "GymnasiumStream", "GymnasiumStreamSource", "StreamWalk", "play_episodes"]


class GymnasiumStream:
    """The uniform stream of one gymnasium toy-text env after ``env.reset(seed=seed)``.

    Constructing it stands for that seeded reset, which consumes the first uniform:
    ``position`` (the uniforms consumed so far) starts at 1, and the next episode's
    ``env.reset()`` draws the second. This is the section's protocol: seed once per
    block, then reset without a seed before every episode.
    """

    def __init__(self, seed: int) -> None:
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        self.seed: int | None = int(seed)  # None: a stream following a generator
        self._generator = seeding.np_random(self.seed)[0]
        self._drawn = torch.empty(0, dtype=torch.float64)  # uniforms drawn so far
        self.position = 1  # the seeded reset's uniform

    @classmethod
    def following(cls, generator: np.random.Generator) -> GymnasiumStream:
        """The uniforms ``generator`` will draw next, read from a copy of it (``generator``
        itself is left as it is): ``position`` 0 is its next draw. Such a stream has no
        seed, so no ``state_dict``."""
        stream = cls.__new__(cls)
        stream.seed = None
        stream._generator = copy.deepcopy(generator)
        stream._drawn = torch.empty(0, dtype=torch.float64)
        stream.position = 0
        return stream

    def window(self, length: int) -> torch.Tensor:
        """The next ``length`` unconsumed uniforms (drawing more as needed)."""
        need = self.position + length - self._drawn.numel()
        if need > 0:
            # Draw in large blocks: bulk draws equal one-at-a-time draws for PCG64.
            block = max(need, self._drawn.numel(), 4096)
            fresh = torch.from_numpy(self._generator.random(block))
            self._drawn = torch.cat([self._drawn, fresh])
        return self._drawn[self.position : self.position + length]

    def advance(self, count: int) -> None:
        self.position += int(count)

    def state_dict(self) -> dict:
        """``{"seed", "position"}``: the stream is a function of its seed, so that is all."""
        if self.seed is None:
            raise ValueError("a stream following a generator (no seed) has no state_dict")
        return {"seed": self.seed, "position": self.position}

    def load_state_dict(self, state: dict) -> None:
        """Continue the stream of ``state`` (its seed must be this stream's)."""
        if state.get("seed") != self.seed or int(state.get("position", -1)) < 1:
            raise ValueError(
                f"stream state {state} does not continue this stream (seed {self.seed})"
            )
        self.position = int(state["position"])


@dataclass(frozen=True)
class Episodes:
    """Consecutive episodes of one policy on a stream.

    Attributes:
        returns: ``[n]`` float64 undiscounted returns.
        lengths: ``[n]`` int64 numbers of steps.
        success: ``[n]`` bool, the episode ended in a goal state.
        truncated: ``[n]`` bool, the episode hit the time limit (gymnasium's flag: set
            after ``max_steps`` steps even if the last step also terminated).
        offsets: ``[n]`` stream positions of the episodes' resets.
        transitions: with ``record=True``, ``[sum(lengths)]`` tensors, episodes back
            to back: ``observation``, ``action``, ``next_observation``, ``reward``,
            ``terminated``, ``step`` (time index), ``episode`` (0-based index).
    """

    returns: torch.Tensor
    lengths: torch.Tensor
    success: torch.Tensor
    truncated: torch.Tensor
    offsets: torch.Tensor
    transitions: dict[str, torch.Tensor] | None = None

    @property
    def observations(self) -> torch.Tensor:
        if self.transitions is None:
            raise ValueError("play_episodes(..., record=True) keeps the visited states")
        return self.transitions["observation"]

    @property
    def actions(self) -> torch.Tensor:
        if self.transitions is None:
            raise ValueError("play_episodes(..., record=True) keeps the actions")
        return self.transitions["action"]

    @property
    def num_episodes(self) -> int:
        return int(self.lengths.numel())


def _deterministic_table(mdp: TabularMDP, policy: torch.Tensor) -> torch.Tensor:
    table = torch.as_tensor(policy)
    probs = policy_probs(table, mdp.num_states, mdp.num_actions)  # validates
    if table.ndim == 2:
        if not ((probs == 0) | (probs == 1)).all():
            raise ValueError(
                "play_episodes needs a deterministic policy ([S] actions or one-hot rows); "
                "a stochastic policy would need its own random stream"
            )
        table = probs.argmax(dim=1)
    return table.long()


def _simulate_offsets(
    sampler: OutcomeSampler,
    table: torch.Tensor,
    uniforms: torch.Tensor,
    num_offsets: int,
    max_steps: int,
    goal: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Play one episode from each of the first ``num_offsets`` stream offsets.

    Offset ``j`` resets with ``uniforms[j]`` and steps with ``uniforms[j + 1 + t]``.
    Lanes are compacted as they finish, so the cost is the total number of steps.

    Returns:
        lengths ``[M]`` int64, returns ``[M]`` float64, success ``[M]`` bool.
    """
    start = sampler.initial(uniforms[:num_offsets])
    composed = sampler.compose(table[None], goal)

    def draw(lane: torch.Tensor, t: int) -> torch.Tensor:
        return uniforms.index_select(0, lane + (1 + t))  # lane j = offset j

    lengths, returns, success, _ = play_compacted(composed, start, draw, max_steps)
    return lengths, returns, success


def _record(
    sampler: OutcomeSampler,
    table: torch.Tensor,
    uniforms: torch.Tensor,
    starts: torch.Tensor,
    lengths: torch.Tensor,
) -> dict[str, torch.Tensor]:
    """Replay the chosen episodes, keeping every transition (episodes back to back)."""
    n, T = starts.numel(), int(lengths.max()) if lengths.numel() else 0
    obs = torch.zeros(n, T, dtype=torch.int64)
    nxt = torch.zeros(n, T, dtype=torch.int64)
    rew = torch.zeros(n, T, dtype=torch.float32)
    term = torch.zeros(n, T, dtype=torch.bool)
    state = sampler.initial(uniforms.take(starts))
    for t in range(T):
        obs[:, t] = state
        state, rew[:, t], term[:, t] = sampler.step(
            state, table.take(state), uniforms.take(starts + 1 + t)
        )
        nxt[:, t] = state
    mask = torch.arange(T)[None, :] < lengths[:, None]
    step = torch.arange(T).expand(n, T)
    return {
        "observation": obs[mask],
        "action": table.take(obs[mask]),
        "next_observation": nxt[mask],
        "reward": rew[mask],
        "terminated": term[mask],
        "step": step[mask],
        "episode": torch.arange(n)[:, None].expand(n, T)[mask],
    }


def play_episodes(
    mdp: TabularMDP,
    policy: torch.Tensor,
    stream: GymnasiumStream,
    num_episodes: int,
    *,
    max_steps: int | None = None,
    record: bool = False,
) -> Episodes:
    """Play ``num_episodes`` consecutive episodes of a deterministic tabular policy.

    Equivalent to ``for _ in range(n): s = env.reset()[0]; step until done`` on the
    gymnasium env whose stream is ``stream``; the stream is advanced past them.

    Args:
        mdp: the MDP (its outcome lists are sampled, in list order).
        policy: ``[S]`` int actions (or one-hot ``[S, A]`` rows).
        stream: the env's uniform stream, shared by consecutive calls.
        num_episodes: how many episodes.
        max_steps: time limit; defaults to ``mdp.max_steps`` (required: an episode
            must end).
        record: also return the visited states and actions taken.
    """
    if int(num_episodes) != num_episodes or num_episodes < 0:
        raise ValueError(f"num_episodes must be a non-negative integer, got {num_episodes!r}")
    T = mdp.max_steps if max_steps is None else max_steps
    if T is None:
        raise ValueError(
            f"{mdp.name!r} has no time limit: pass max_steps so that every episode ends"
        )
    table = _deterministic_table(mdp, policy)
    sampler = OutcomeSampler(mdp)
    n = int(num_episodes)
    mean_len = expected_episode_length(mdp, table, T)
    base = stream.position
    if n * (1.0 + mean_len) <= _SCALAR_LIMIT:
        return _play_scalar(sampler, table, stream, n, T, mdp.goal, record)
    starts: list[int] = []
    lengths: list[torch.Tensor] = []
    returns: list[torch.Tensor] = []
    success: list[torch.Tensor] = []
    pos = 0  # offset of the next episode's reset, relative to the stream's position
    while len(starts) < n:
        # Simulate one episode from every offset of a window sized by the exact expected
        # length; if the walk runs past it, the next window starts where the walk stopped.
        window = math.ceil((n - len(starts)) * (1.0 + mean_len) * 1.05) + 64
        uniforms = stream.window(pos + window + T + 1)[pos:]
        lens, rets, succ = _simulate_offsets(sampler, table, uniforms, window, T, mdp.goal)
        lens_list, local = lens.tolist(), 0
        chosen: list[int] = []
        while len(starts) + len(chosen) < n and local < window:
            chosen.append(local)
            local += 1 + lens_list[local]
        idx = torch.tensor(chosen, dtype=torch.int64)
        starts += [pos + c for c in chosen]
        lengths.append(lens[idx])
        returns.append(rets[idx])
        success.append(succ[idx])
        pos += local
    idx = torch.tensor(starts, dtype=torch.int64)
    ep_len = torch.cat(lengths)
    transitions = (
        _record(sampler, table, stream.window(pos + T + 1), idx, ep_len) if record else None
    )
    stream.advance(pos)
    return Episodes(
        returns=torch.cat(returns),
        lengths=ep_len,
        success=torch.cat(success),
        truncated=ep_len == T,
        offsets=idx + base,
        transitions=transitions,
    )


_SCALAR_LIMIT = 2500
"""Below this many expected uniforms a plain scalar walk beats simulating every offset."""


_SCALAR_KEYS = (
    "observation",
    "action",
    "next_observation",
    "reward",
    "terminated",
    "step",
    "episode",
)


def _scalar_episode(
    lists: dict, shape: tuple[int, int, int], act: list, buf: list, i: int, T: int, e: int, out
) -> tuple[int, float, int, bool, int]:
    """Episode ``e`` from stream position ``i`` -> (last state, return, length, done, new i).

    Appends each transition to ``out`` (a dict of lists) unless ``out`` is None.
    """
    A, K, S = shape
    cdf, nxt, rew, term = lists["cdf"], lists["next_state"], lists["reward"], lists["terminated"]
    u = buf[i]
    s = sum(1 for c in lists["initial_cdf"] if c <= u)
    s = 0 if s >= S else s
    i += 1
    ret, t, done = 0.0, 0, False
    while not done and t < T:
        a = act[s]
        u = buf[i]
        i += 1
        sa = s * A + a
        k = 0
        row = cdf[sa]
        while k < K and row[k] <= u:
            k += 1
        flat = sa * K + (0 if k == K else k)
        s2, r, done = nxt[flat], rew[flat], term[flat]
        if out is not None:
            for key, v in zip(_SCALAR_KEYS, (s, a, s2, r, done, t, e)):
                out[key].append(v)
        ret += r
        t += 1
        s = s2
    return s, ret, t, bool(done), i


def _play_scalar(
    sampler: OutcomeSampler,
    table: torch.Tensor,
    stream: GymnasiumStream,
    n: int,
    T: int,
    goal: torch.Tensor,
    record: bool,
) -> Episodes:
    """The same episodes, stepped one at a time in Python (for a handful of episodes).

    Uses the same float64 comparisons as :class:`OutcomeSampler` (count of CDF
    entries <= u, all-below mapping to outcome 0), so both paths agree exactly.
    """
    lists = sampler.as_lists()
    shape = (sampler.num_actions, sampler.num_outcomes, sampler.num_states)
    act, is_goal = table.tolist(), goal.tolist()
    buf: list[float] = stream.window(max(64, 64 * n)).tolist()
    i = 0
    out: dict[str, list] | None = {k: [] for k in _SCALAR_KEYS} if record else None
    starts: list[int] = []
    lengths: list[int] = []
    returns: list[float] = []
    success: list[bool] = []
    for e in range(n):
        starts.append(i)
        if i + T + 1 >= len(buf):
            buf = stream.window(2 * len(buf) + T + 1).tolist()
        s, ret, t, done, i = _scalar_episode(lists, shape, act, buf, i, T, e, out)
        lengths.append(t)
        returns.append(ret)
        success.append(bool(done and is_goal[s]))
    stream.advance(i)
    ep_len = torch.tensor(lengths, dtype=torch.int64)
    transitions = None
    if out is not None:  # record
        dtypes = {"reward": torch.float32, "terminated": torch.bool}
        transitions = {k: torch.tensor(v, dtype=dtypes.get(k, torch.int64)) for k, v in out.items()}
    base = stream.position - i
    return Episodes(
        returns=torch.tensor(returns, dtype=torch.float64),
        lengths=ep_len,
        success=torch.tensor(success, dtype=torch.bool),
        truncated=ep_len == T,
        offsets=torch.tensor(starts, dtype=torch.int64) + base,
        transitions=transitions,
    )


class StreamWalk:
    """Episodes of one deterministic table walked step by step on a stream, one per call.

    The scalar path of :func:`play_episodes` (the same float64 comparisons), for a caller
    that decides episode by episode how many to play: the stream itself is not advanced.

    Args:
        sampler: the MDP's :class:`OutcomeSampler`; ``lists`` its ``as_lists()``.
        table: ``[S]`` int64 action of each state.
        stream: where the first episode's reset draws.
        max_steps: the time limit.
    """

    def __init__(
        self,
        sampler: OutcomeSampler,
        lists: dict,
        table: torch.Tensor,
        stream: GymnasiumStream,
        max_steps: int,
    ) -> None:
        self._lists = lists
        self._shape = (sampler.num_actions, sampler.num_outcomes, sampler.num_states)
        self._act, self._stream, self._T = table.tolist(), stream, int(max_steps)
        self._buf: list[float] = stream.window(64 * (self._T + 1)).tolist()
        self._i = 0  # uniforms of the buffer consumed

    def episode(self) -> tuple[float, int]:
        """The next episode's (return, length)."""
        if self._i + self._T + 1 >= len(self._buf):
            self._buf = self._stream.window(2 * len(self._buf) + self._T + 1).tolist()
        _, ret, length, _, self._i = _scalar_episode(
            self._lists, self._shape, self._act, self._buf, self._i, self._T, 0, None
        )
        return ret, length


class GymnasiumStreamSource:
    """A DAgger episode source that plays gymnasium's own stream (see :func:`play_episodes`).

    The behaviour policy is read as a table on every state in deterministic mode, so
    the learner acts greedily and the mixture's beta must be 0 or 1 (a coin per step
    would need a random stream of its own, which gymnasium's env does not have).

    Args:
        mdp: the tabular MDP of the env.
        stream: the env's uniform stream (shared with evaluations on the same env).
    """

    def __init__(self, mdp: TabularMDP, stream: GymnasiumStream) -> None:
        self.mdp, self.stream = mdp, stream

    def state_dict(self) -> dict:
        """The stream's position (see :meth:`GymnasiumStream.state_dict`)."""
        return {"stream": self.stream.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        """Continue from :meth:`state_dict`."""
        self.stream.load_state_dict(state["stream"])

    def check(self, expert, learner) -> None:
        """Refuse a learner that does not act on the MDP's states and actions (the expert's
        table is read on every state directly: nothing to bind)."""
        from imitrl.envs.tabular_env import TabularEnv  # the MDP's own spaces, as an env

        learner.check_env(TabularEnv(self.mdp, batch_size=(), seed=0))

    def collect(
        self,
        behaviour: TensorDictModuleBase,
        num_episodes: int,
        *,
        round_index: int,
        first_episode: int,
    ) -> TensorDict:
        """Play ``num_episodes`` episodes of ``behaviour`` on the stream; buffer rows.

        Rows as :func:`imitrl.runtime.rollout_episodes` returns them (every transition,
        episodes back to back, ids from ``first_episode``, ``ROUND = round_index``).
        """
        S = self.mdp.num_states
        td = TensorDict({keys.OBSERVATION: torch.arange(S)}, batch_size=[S])
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            out = behaviour(td)
        executed = out.get(keys.EXPERT_EXECUTED)
        if executed.any() and not executed.all():
            raise ValueError(
                "the gymnasium stream source needs beta in {0, 1}: a per-step coin flip "
                "has no place in gymnasium's random stream"
            )
        action_table, expert_table = out.get(keys.ACTION).long(), out.get(keys.EXPERT_ACTION).long()
        eps = play_episodes(self.mdp, action_table, self.stream, num_episodes, record=True)
        tr = eps.transitions
        assert tr is not None  # record=True
        n = tr["observation"].numel()
        T = self.mdp.max_steps
        assert T is not None  # play_episodes refused an MDP without a time limit
        truncated = (tr["step"] + 1) == T
        return TensorDict(
            {
                keys.OBSERVATION: tr["observation"],
                keys.ACTION: tr["action"],
                keys.EXPERT_ACTION: expert_table[tr["observation"]],
                keys.EXPERT_EXECUTED: torch.full((n,), bool(executed.all()), dtype=torch.bool),
                keys.EPISODE: first_episode + tr["episode"],
                keys.ROUND: torch.full((n,), int(round_index), dtype=torch.int64),
                keys.STEP: tr["step"],
                keys.NEXT: {
                    keys.REWARD: tr["reward"][:, None],
                    keys.DONE: (tr["terminated"] | truncated)[:, None],
                    keys.TERMINATED: tr["terminated"][:, None],
                    keys.TRUNCATED: truncated[:, None],
                },
            },
            batch_size=[n],
        )
