"""`TabularEnv`: a TorchRL `EnvBase` simulating a :class:`TabularMDP` for N lanes at once.

Each lane is an independent episode. Observations and actions are int64 scalars per
lane (like ``GymEnv(..., categorical_action_encoding=True)``); rewards are float32
``[*batch, 1]``; ``terminated`` comes from the MDP's outcome, ``truncated`` from the
time limit exactly as gymnasium's ``TimeLimit`` sets it (after ``max_steps`` steps,
whether or not the last step also terminated), ``done = terminated | truncated``.

Randomness comes from one of two sources, chosen by ``rng``:

* ``"torch"`` (default): one explicit ``torch.Generator`` for the whole batch; every
  step draws one float64 uniform per lane, and so does every reset unless the start
  state is fixed. Fast and reproducible, but a different stream than gymnasium's.
* ``"gymnasium"``: lane ``i`` owns a numpy ``Generator`` seeded as gymnasium's
  ``reset(seed=seed + i)`` seeds it, and draws one uniform per reset and per step of
  that lane, used by inverse CDF over the env's own outcome list. At batch size 1
  this reproduces ``gym.make(env_id)`` step for step under the same seed. It costs a
  Python call per lane per step: use it for fidelity, not speed.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from gymnasium.utils import seeding
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.tabular.mdp import TabularMDP
from imitrl.tabular.sampling import OutcomeSampler, play_compacted

__all__ = ["TabularEnv"]

_RNG_KINDS = ("torch", "gymnasium")


class TabularEnv(EnvBase):
    """Batched simulator of a tabular MDP.

    Args:
        mdp: the MDP to simulate (its outcome lists, not the aggregated kernel).
        batch_size: ``()`` for one episode or ``(N,)`` for N independent lanes.
        max_steps: time limit per episode; ``"mdp"`` (default) uses ``mdp.max_steps``
            (100 for FrozenLake 4x4, as gymnasium's registry sets it), None disables it.
        rng: ``"torch"`` or ``"gymnasium"`` (see the module docstring).
        seed: seed of the random source; ``None`` leaves it unseeded until
            :meth:`set_seed` (``"torch"`` then starts from seed 0).
        initial_state: optional ``batch_size``-shaped int64 start state of every lane,
            replacing draws from ``mdp.initial`` (e.g. lanes pinned to the copies of a
            :meth:`TabularMDP.replicate` product, or starts from every state).

    Keys: observation ``"observation"`` (int64), action ``"action"`` (int64),
    ``("next", "reward")`` float32, ``("next", "done"|"terminated"|"truncated")`` bool.
    """

    def __init__(
        self,
        mdp: TabularMDP,
        *,
        batch_size: Sequence[int] | torch.Size = (),
        max_steps: int | str | None = "mdp",
        rng: str = "torch",
        seed: int | None = None,
        initial_state: torch.Tensor | None = None,
    ) -> None:
        batch_size = torch.Size(batch_size)
        if len(batch_size) > 1:
            raise ValueError(f"TabularEnv batch_size must be () or (N,), got {tuple(batch_size)}")
        if rng not in _RNG_KINDS:
            raise ValueError(f"rng must be one of {_RNG_KINDS}, got {rng!r}")
        if max_steps == "mdp":
            max_steps = mdp.max_steps
        if max_steps is not None and (
            isinstance(max_steps, str) or int(max_steps) != max_steps or max_steps < 1
        ):
            raise ValueError(
                f"max_steps must be a positive integer, None or 'mdp', got {max_steps!r}"
            )
        super().__init__(device="cpu", batch_size=batch_size)
        self.mdp = mdp
        self.max_steps = None if max_steps is None else int(max_steps)
        self.rng_kind = rng
        self._sampler = OutcomeSampler(mdp)
        support = torch.nonzero(mdp.initial > 0).view(-1)
        self._point_start = int(support[0]) if support.numel() == 1 else None
        self._lane_start: torch.Tensor | None = None
        if initial_state is not None:
            if rng == "gymnasium":
                raise ValueError(
                    "initial_state cannot be combined with rng='gymnasium' (gymnasium draws every start)"
                )
            start = torch.as_tensor(initial_state)
            if (
                start.shape != batch_size
                or start.dtype.is_floating_point
                or start.dtype == torch.bool
            ):
                raise ValueError(
                    f"initial_state must be an integer tensor of shape {tuple(batch_size)}, "
                    f"got {start.dtype} {tuple(start.shape)}"
                )
            if start.numel() and (int(start.min()) < 0 or int(start.max()) >= mdp.num_states):
                raise ValueError(f"initial_state entries must lie in [0, {mdp.num_states})")
            self._lane_start = start.reshape(-1).long().clone()
        self._n = int(batch_size.numel())
        S, A = mdp.num_states, mdp.num_actions
        self.observation_spec = Composite(
            {keys.OBSERVATION: Categorical(S, shape=batch_size, dtype=torch.int64)},
            shape=batch_size,
        )
        self.action_spec = Categorical(A, shape=batch_size, dtype=torch.int64)
        self.reward_spec = Unbounded(shape=(*batch_size, 1), dtype=torch.float32)
        self.done_spec = Composite(
            {
                key: Categorical(2, shape=(*batch_size, 1), dtype=torch.bool)
                for key in (keys.DONE, keys.TERMINATED, keys.TRUNCATED)
            },
            shape=batch_size,
        )
        self._state = torch.zeros(self._n, dtype=torch.int64)
        self._elapsed = torch.zeros(self._n, dtype=torch.int64)
        self._generator: torch.Generator | None = None
        self._np_generators: list[np.random.Generator] | None = None
        self._set_seed(seed)

    # ----------------------------------------------------------------- random
    def _set_seed(self, seed: int | None) -> None:
        if self.rng_kind == "torch":
            self._generator = torch.Generator().manual_seed(0 if seed is None else int(seed))
        else:
            base = None if seed is None else int(seed)
            self._np_generators = [
                seeding.np_random(None if base is None else base + i)[0] for i in range(self._n)
            ]

    def random_state(self) -> dict:
        """The lanes' random state (JSON-able): what the next ``reset``/``step`` will draw."""
        if self.rng_kind == "torch":
            assert self._generator is not None  # _set_seed made it
            return {"torch": self._generator.get_state().tolist()}
        assert self._np_generators is not None  # _set_seed made them
        return {"numpy": [g.bit_generator.state for g in self._np_generators]}

    def set_random_state(self, state: dict) -> None:
        """Restore a :meth:`random_state` (ValueError if it is of another kind or size)."""
        if self.rng_kind == "torch" and "torch" in state:
            assert self._generator is not None  # _set_seed made it
            self._generator.set_state(torch.tensor(state["torch"], dtype=torch.uint8))
            return
        if self.rng_kind == "gymnasium" and len(state.get("numpy", ())) == self._n:
            assert self._np_generators is not None  # _set_seed made them
            for g, st in zip(self._np_generators, state["numpy"]):
                g.bit_generator.state = st
            return
        raise ValueError(
            f"random state {sorted(state)} does not fit a TabularEnv with rng={self.rng_kind!r} "
            f"and {self._n} lanes"
        )

    def _uniforms(self, lanes: torch.Tensor | None) -> torch.Tensor:
        """float64 uniforms for ``lanes`` (bool mask ``[n]``, None = all lanes)."""
        if self.rng_kind == "torch":
            u = torch.rand(self._n, generator=self._generator, dtype=torch.float64)
            return u if lanes is None else u[lanes]
        assert self._np_generators is not None
        idx = range(self._n) if lanes is None else torch.nonzero(lanes).view(-1).tolist()
        return torch.tensor([self._np_generators[i].random() for i in idx], dtype=torch.float64)

    # ------------------------------------------------------------------- core
    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        lanes = None
        if tensordict is not None and "_reset" in tensordict.keys():
            lanes = tensordict.get("_reset").reshape(self._n)
        state = self.reset_lanes(lanes)
        false = torch.zeros((*self.batch_size, 1), dtype=torch.bool)
        return TensorDict(
            {
                keys.OBSERVATION: state.reshape(self.batch_size),
                keys.DONE: false,
                keys.TERMINATED: false.clone(),
                keys.TRUNCATED: false.clone(),
            },
            batch_size=self.batch_size,
        )

    def reset_lanes(self, lanes: torch.Tensor | None) -> torch.Tensor:
        """Reset the lanes of the bool mask ``lanes`` ``[n]`` (None: every lane).

        What ``reset`` runs, on tensors: the rollouts' direct path
        (:mod:`imitrl.runtime.fast.env_steps`) calls it instead of ``EnvBase.reset``.

        Returns:
            ``[n]`` int64 state of every lane after the reset.
        """
        if self.rng_kind == "gymnasium":
            # Only the lanes being reset draw from their streams, as gymnasium would.
            if lanes is None:
                state = self._sampler.initial(self._uniforms(None))
            else:
                state = self._state.clone()
                state[lanes] = self._sampler.initial(self._uniforms(lanes))
        elif self._lane_start is not None:
            state = (
                self._lane_start.clone()
                if lanes is None
                else torch.where(lanes, self._lane_start, self._state)
            )
        elif self._point_start is not None:
            # A single start state needs no draw (the torch stream is ours to define).
            state = (
                torch.full((self._n,), self._point_start, dtype=torch.int64)
                if lanes is None
                else self._state.masked_fill(lanes, self._point_start)
            )
        else:
            state = self._sampler.initial(self._uniforms(None))
            if lanes is not None:
                state = torch.where(lanes, state, self._state)
        self._state = state
        self._elapsed = (
            torch.zeros(self._n, dtype=torch.int64)
            if lanes is None
            else self._elapsed.masked_fill(lanes, 0)
        )
        return state

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        next_state, reward, terminated, truncated = self.step_lanes(tensordict.get(keys.ACTION))
        shape1 = (*self.batch_size, 1)
        return TensorDict(
            {
                keys.OBSERVATION: next_state.reshape(self.batch_size),
                keys.REWARD: reward.reshape(shape1),
                keys.DONE: (terminated | truncated).reshape(shape1),
                keys.TERMINATED: terminated.reshape(shape1),
                keys.TRUNCATED: truncated.reshape(shape1),
            },
            batch_size=self.batch_size,
        )

    def step_lanes(
        self, action: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """One step of every lane: what ``step`` runs, on tensors (see :meth:`reset_lanes`).

        Args:
            action: int ``[*batch]`` (checked: integer, one per lane, in range).

        Returns:
            ``[n]`` next state (int64), reward (float32), terminated and truncated (bool).
        """
        action = self._check_action(action)
        next_state, reward, terminated = self._sampler.step(
            self._state, action, self._uniforms(None)
        )
        self._state = next_state
        self._elapsed = self._elapsed + 1
        if self.max_steps is None:
            truncated = torch.zeros_like(terminated)
        else:
            truncated = self._elapsed >= self.max_steps
        return next_state, reward, terminated, truncated

    def _check_action(self, action: torch.Tensor) -> torch.Tensor:
        if action.dtype.is_floating_point or action.dtype == torch.bool or action.is_complex():
            raise ValueError(
                f"TabularEnv expects integer actions in [0, {self.mdp.num_actions}), got dtype {action.dtype}"
            )
        if action.numel() != self._n:
            raise ValueError(
                f"TabularEnv expects one action per lane, shape {tuple(self.batch_size)}, "
                f"got shape {tuple(action.shape)}"
            )
        action = action.reshape(self._n).long()
        lo, hi = action.aminmax()
        if lo < 0 or hi >= self.mdp.num_actions:
            bad = int(lo) if lo < 0 else int(hi)
            raise ValueError(f"TabularEnv action {bad} is outside [0, {self.mdp.num_actions})")
        return action

    def start_distribution(self, num_episodes: int) -> torch.Tensor:
        """``[S]`` start distribution of ``num_episodes`` whole episodes played round-robin over the lanes.

        ``mdp.initial`` unless lanes are pinned, in which case lane ``i`` plays
        ``ceil((n - i) / lanes)`` of the episodes from its own start state.
        """
        if self._lane_start is None:
            return self.mdp.initial
        lanes = self._n
        quota = ((num_episodes - torch.arange(lanes) + lanes - 1) // lanes).clamp_min(0)
        counts = torch.zeros(self.mdp.num_states, dtype=torch.float64)
        counts.index_add_(0, self._lane_start, quota.double())
        return counts / counts.sum()

    # --------------------------------------------------------------- fast path
    def play_tables(self, tables: torch.Tensor, episodes_per_table: int) -> dict[str, torch.Tensor]:
        """Play whole episodes of deterministic tabular policies, lanes compacted as they end.

        The fast path for evaluating many table policies: the same simulator
        (:class:`OutcomeSampler`), time limit and ``torch.Generator`` as :meth:`step`,
        but finished episodes leave the batch instead of being stepped on, so the
        cost is the number of steps actually played. Does not touch the env's lanes.

        Args:
            tables: ``[K, S]`` int64 actions (or ``[S]`` for one policy).
            episodes_per_table: episodes per policy.

        Returns:
            ``returns`` (float64), ``lengths`` (int64), ``success`` (bool, entered a goal
            state), ``truncated`` (bool), each ``[K, episodes_per_table]``.
        """
        if self.rng_kind != "torch":
            raise ValueError(
                "play_tables draws from the torch generator; use imitrl.envs.play_episodes for gymnasium's stream"
            )
        if self.max_steps is None:
            raise ValueError(
                "play_tables needs a time limit (max_steps) so that every episode ends"
            )
        if self._lane_start is not None:
            raise ValueError(
                "play_tables starts every episode from mdp.initial; this env pins its lanes with "
                "initial_state (evaluate through step(), or replicate the MDP)"
            )
        tables = torch.as_tensor(tables)
        if tables.ndim == 1:
            tables = tables[None]
        S, A = self.mdp.num_states, self.mdp.num_actions
        if tables.ndim != 2 or tables.shape[1] != S or tables.dtype.is_floating_point:
            raise ValueError(
                f"tables must be integer actions of shape [K, {S}], got {tables.dtype} {tuple(tables.shape)}"
            )
        if (tables < 0).any() or (tables >= A).any():
            raise ValueError(f"table actions must lie in [0, {A})")
        K, E = tables.shape[0], int(episodes_per_table)
        if E < 1:
            raise ValueError(f"episodes_per_table must be positive, got {episodes_per_table}")
        composed = self._sampler.compose(tables, self.mdp.goal)
        N = K * E
        if self._point_start is not None:
            start = torch.full((N,), self._point_start, dtype=torch.int64)
        else:
            start = self._sampler.initial(
                torch.rand(N, generator=self._generator, dtype=torch.float64)
            )
        start = start + torch.arange(K).repeat_interleave(E) * S

        def draw(lane: torch.Tensor, t: int) -> torch.Tensor:
            return torch.rand(lane.numel(), generator=self._generator, dtype=torch.float64)

        lengths, returns, success, truncated = play_compacted(composed, start, draw, self.max_steps)
        shape = (K, E)
        return {
            "returns": returns.reshape(shape),
            "lengths": lengths.reshape(shape),
            "success": success.reshape(shape),
            "truncated": truncated.reshape(shape),
        }
