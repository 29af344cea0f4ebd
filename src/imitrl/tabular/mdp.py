"""`TabularMDP`: a finite MDP as dense float64 tensors, plus the sampling model.

Two views of the same MDP live side by side:

* the *dense* view used by exact math: kernel ``P[s, a, s']``, expected reward
  ``r[s, a]``, initial distribution ``initial[s]``, ``terminal[s]`` (absorbing,
  zero reward once entered), ``goal[s]`` (terminal states entered with positive
  reward), discount ``gamma``;
* the *outcome* view used by simulators (:class:`Outcomes`): for every ``(s, a)``
  the env's own ordered list of outcomes ``(p, s', reward, terminated)``, padded to
  ``K`` entries. Sampling by inverse CDF over this list, in list order, is what
  gymnasium's toy-text envs do, and it differs from sampling the aggregated kernel
  whenever two outcomes share a next state (a wall bounce on FrozenLake).

Termination is a property of the state entered: a gymnasium outcome flagged
``terminated`` makes its next state terminal. The dense view makes every terminal
state absorbing with zero reward (gymnasium's own model does not always: Taxi
continues past a drop-off), so that value iteration and finite-horizon evolution
price exactly the episodes gymnasium runs.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from imitrl.limits import MAX_KERNEL_ENTRIES
from imitrl.tabular.bellman import backup_dense
from imitrl.tabular.gym_model import make_env, read_gym_model, terminal_states
from imitrl.tabular.validation import as_float64, check_gamma, check_probabilities

__all__ = ["Outcomes", "TabularMDP"]


@dataclass(frozen=True, eq=False)
class Outcomes:
    """Ordered outcome lists of a tabular env, padded to ``K`` outcomes per pair.

    Padding entries have probability 0, next state equal to the pair's first
    outcome, reward 0 and ``terminated`` False; they are never selected.
    """

    next_state: torch.Tensor  # [S, A, K] int64
    prob: torch.Tensor  # [S, A, K] float64
    cdf: torch.Tensor  # [S, A, K] float64: np.cumsum of prob in list order
    reward: torch.Tensor  # [S, A, K] float64
    terminated: torch.Tensor  # [S, A, K] bool
    size: torch.Tensor  # [S, A] int64: number of real (unpadded) outcomes

    @property
    def num_outcomes(self) -> int:
        return int(self.next_state.shape[-1])


@dataclass(frozen=True, eq=False)
class TabularMDP:
    """A finite MDP. Build it with :meth:`from_gym` or :meth:`from_arrays`.

    Attributes:
        P: ``[S, A, S]`` float64 transition kernel; terminal rows are self-loops.
        r: ``[S, A]`` float64 expected immediate reward; zero on terminal rows.
        gamma: discount in ``[0, 1]``.
        initial: ``[S]`` float64 initial state distribution.
        terminal: ``[S]`` bool, states whose entry ends the episode.
        goal: ``[S]`` bool, the terminal states whose entering reward is the highest
            among terminal states: reaching one is a success. On a grid map that
            names its goal cells (FrozenLake's ``G``), the terminal ones among them
            (none when no ``G`` can be reached).
        outcomes: the sampling model (see :class:`Outcomes`).
        max_steps: time limit of an episode (gymnasium's ``max_episode_steps``) or None.
        desc: the grid map for grid worlds (``[rows, cols]`` of single bytes) or None.
        name: a label for reports.
    """

    P: torch.Tensor
    r: torch.Tensor
    gamma: float
    initial: torch.Tensor
    terminal: torch.Tensor
    goal: torch.Tensor
    outcomes: Outcomes = field(repr=False)
    max_steps: int | None = None
    desc: np.ndarray | None = field(default=None, repr=False)
    name: str = "tabular"

    # ------------------------------------------------------------------ shape
    @property
    def num_states(self) -> int:
        return int(self.P.shape[0])

    @property
    def num_actions(self) -> int:
        return int(self.P.shape[1])

    @property
    def initial_cdf(self) -> torch.Tensor:
        """``[S]`` float64 cumulative initial distribution, in state order (as gymnasium)."""
        return torch.from_numpy(np.cumsum(self.initial.numpy()))

    def backup(self, V: torch.Tensor) -> torch.Tensor:
        """Bellman backup ``Q[s, a] = r[s, a] + gamma * sum_s' P[s, a, s'] V[s']``.

        Args:
            V: ``[S]`` state values.

        Returns:
            ``[S, A]`` float64 action values (:func:`imitrl.tabular.dp.backup`).
        """
        return backup_dense(self.P, self.r, self.gamma, V)

    def with_gamma(self, gamma: float) -> TabularMDP:
        """The same MDP with another discount."""
        check_gamma(gamma)
        return TabularMDP(
            P=self.P,
            r=self.r,
            gamma=float(gamma),
            initial=self.initial,
            terminal=self.terminal,
            goal=self.goal,
            outcomes=self.outcomes,
            max_steps=self.max_steps,
            desc=self.desc,
            name=self.name,
        )

    def replicate(self, copies: int) -> TabularMDP:
        """``copies`` independent copies of this MDP as one MDP on ``copies * S`` states.

        State ``k * S + s`` is state ``s`` of copy ``k``; the kernel is block diagonal,
        the initial distribution puts ``1 / copies`` of the mass on each copy. K
        independent tabular experiments (datasets, seeds) run as one batched experiment
        on the product MDP: pin each env lane to a copy with
        ``TabularEnv(..., initial_state=...)`` and give the learner ``copies * S`` rows.
        """
        K, S = int(copies), self.num_states
        if K < 1:
            raise ValueError(f"copies must be a positive integer, got {copies!r}")
        P = torch.zeros(K * S, self.num_actions, K * S, dtype=torch.float64)
        for k in range(K):
            P[k * S : (k + 1) * S, :, k * S : (k + 1) * S] = self.P
        out = self.outcomes
        shift = (torch.arange(K) * S).repeat_interleave(S)[:, None, None]  # [K*S, 1, 1]
        return TabularMDP(
            P=P,
            r=self.r.repeat(K, 1),
            gamma=self.gamma,
            initial=self.initial.repeat(K) / K,
            terminal=self.terminal.repeat(K),
            goal=self.goal.repeat(K),
            outcomes=Outcomes(
                next_state=out.next_state.repeat(K, 1, 1) + shift,
                prob=out.prob.repeat(K, 1, 1),
                cdf=out.cdf.repeat(K, 1, 1),
                reward=out.reward.repeat(K, 1, 1),
                terminated=out.terminated.repeat(K, 1, 1),
                size=out.size.repeat(K, 1),
            ),
            max_steps=self.max_steps,
            desc=None,
            name=f"{self.name} x{K}",
        )

    # ----------------------------------------------------------- constructors
    @classmethod
    def from_gym(
        cls,
        env: str | gym.Env,
        gamma: float,
        *,
        make_kwargs: Mapping[str, Any] | None = None,
        max_steps: int | None = None,
    ) -> TabularMDP:
        """Read the model of a gymnasium toy-text env (anything with ``unwrapped.P``).

        The model is exactly ``unwrapped.P``: dynamics an env applies outside it (Taxi's
        ``fickle_passenger``) are not in the kernel, and its exact values do not
        describe that env.

        Args:
            env: an env id (``"FrozenLake-v1"``) or a gymnasium env instance.
            gamma: discount.
            make_kwargs: keyword arguments for ``gym.make`` when ``env`` is an id
                (``{"map_name": "8x8"}``, ``{"desc": [...]}``, ``{"is_slippery": False}``).
            max_steps: episode time limit; defaults to the env spec's
                ``max_episode_steps`` (100 for FrozenLake 4x4, None for CliffWalking).

        Raises:
            ValueError: unknown env id, env without a tabular model, or a model that
                is malformed (probabilities, shapes, non-finite rewards).
        """
        check_gamma(gamma)
        env = make_env(env, make_kwargs)
        spec_steps = env.spec.max_episode_steps if env.spec is not None else None
        name = env.spec.id if env.spec is not None else type(env.unwrapped).__name__
        unwrapped = env.unwrapped
        model = getattr(unwrapped, "P", None)
        if not isinstance(model, Mapping):
            raise ValueError(
                f"env {name!r} has no tabular model: expected `env.unwrapped.P`, a dict "
                "s -> a -> [(prob, next_state, reward, terminated), ...] as in gymnasium's "
                "toy-text envs"
            )
        obs_space, act_space = unwrapped.observation_space, unwrapped.action_space
        if not isinstance(obs_space, gym.spaces.Discrete) or not isinstance(
            act_space, gym.spaces.Discrete
        ):
            raise ValueError(
                f"env {name!r} needs Discrete observation and action spaces, got "
                f"{obs_space} and {act_space}"
            )
        S, A = int(obs_space.n), int(act_space.n)
        if S * A * S > MAX_KERNEL_ENTRIES:
            raise ValueError(
                f"env {name!r} has {S} states and {A} actions: its dense model would hold "
                f"S x A x S = {S * A * S:.3g} entries, past imitrl.limits.MAX_KERNEL_ENTRIES "
                f"({MAX_KERNEL_ENTRIES:.3g}, {MAX_KERNEL_ENTRIES * 8 >> 20} MiB of float64)"
            )
        initial = getattr(unwrapped, "initial_state_distrib", None)
        if initial is None:
            raise ValueError(
                f"env {name!r} has no `initial_state_distrib`: cannot build the initial distribution"
            )
        outcome_lists = read_gym_model(model, S, A, name)
        desc = getattr(unwrapped, "desc", None)
        if desc is not None and np.asarray(desc).size != S:
            desc = None  # a picture of the world (Taxi's), not one cell per state
        # FrozenLake's G cells are its goals: with no G reachable the holes' 0 is the best entry
        is_g = None if desc is None else np.asarray(desc).ravel() == b"G"
        goal_cells = is_g if is_g is not None and is_g.any() else None
        return cls._build(
            outcome_lists,
            S=S,
            A=A,
            gamma=gamma,
            initial=np.asarray(initial, dtype=np.float64),
            max_steps=max_steps if max_steps is not None else spec_steps,
            desc=None if desc is None else np.asarray(desc).copy(),
            name=name,
            goal_cells=goal_cells,
        )

    @classmethod
    def from_arrays(
        cls,
        P: Any,
        r: Any,
        gamma: float,
        *,
        initial: Any | None = None,
        terminal: Any | None = None,
        max_steps: int | None = None,
        name: str = "tabular",
    ) -> TabularMDP:
        """Build from dense arrays.

        Args:
            P: ``[S, A, S]`` kernel, each row a probability vector.
            r: ``[S, A]`` expected reward, or ``[S, A, S]`` reward by transition.
            gamma: discount.
            initial: ``[S]`` initial distribution; default: all mass on state 0.
            terminal: ``[S]`` bool; entering one ends the episode (made absorbing).
            max_steps: episode time limit, or None.

        The sampling model lists the next states in index order (zero-probability
        states included, never drawn), so inverse-CDF sampling is over the kernel rows.

        Raises:
            ValueError: shape mismatch, negative or non-finite probabilities, rows not
                summing to 1, non-finite rewards.
        """
        check_gamma(gamma)
        P = as_float64(P, "P")
        if P.ndim != 3 or P.shape[0] != P.shape[2]:
            raise ValueError(f"P must have shape [S, A, S], got {tuple(P.shape)}")
        S, A = P.shape[0], P.shape[1]
        r = as_float64(r, "r")
        if r.shape == (S, A):
            R = np.broadcast_to(r[:, :, None], (S, A, S))
        elif r.shape == (S, A, S):
            R = r
        else:
            raise ValueError(
                f"r must have shape [S, A] = {(S, A)} or [S, A, S], got {tuple(r.shape)}"
            )
        check_probabilities(P, "P", axis=-1)
        if initial is None:
            initial = np.zeros(S)
            initial[0] = 1.0
        initial = as_float64(initial, "initial")
        if terminal is None:
            terminal = np.zeros(S, dtype=bool)
        terminal = np.asarray(terminal)
        if terminal.shape != (S,) or terminal.dtype != np.bool_:
            raise ValueError(
                f"terminal must be a bool array of shape [{S}], got {terminal.dtype} {terminal.shape}"
            )
        return cls._build(
            _kernel_outcome_lists(P, R, terminal),
            S=S,
            A=A,
            gamma=gamma,
            initial=initial,
            max_steps=max_steps,
            desc=None,
            name=name,
            terminal=terminal,
        )

    @classmethod
    def _build(
        cls,
        outcome_lists: list[list[list[tuple[float, int, float, bool]]]],
        *,
        S: int,
        A: int,
        gamma: float,
        initial: np.ndarray,
        max_steps: int | None,
        desc: np.ndarray | None,
        name: str,
        terminal: np.ndarray | None = None,
        goal_cells: np.ndarray | None = None,
    ) -> TabularMDP:
        if initial.shape != (S,):
            raise ValueError(f"initial distribution must have shape [{S}], got {initial.shape}")
        if not np.isfinite(initial).all():
            raise ValueError("initial distribution must be finite")
        check_probabilities(initial, "initial distribution", axis=-1)
        if max_steps is not None and (int(max_steps) != max_steps or max_steps < 1):
            raise ValueError(f"max_steps must be a positive integer or None, got {max_steps!r}")
        next_state, prob, reward, terminated, size = _pad_outcome_lists(outcome_lists, S, A)
        if terminal is None:
            terminal = terminal_states(next_state, prob, terminated, size, initial, name)
        # Read before the terminal rows become zero-reward self-loops below.
        goal = (
            _goal_states(next_state, prob, reward, terminal)
            if goal_cells is None
            else terminal & goal_cells
        )
        term_idx = np.flatnonzero(terminal)
        # A terminal state is absorbing in the sampling model too (an episode never
        # steps from one; gymnasium's own lists there are arbitrary, e.g. CliffWalking's).
        next_state[term_idx] = term_idx[:, None, None]
        prob[term_idx] = 0.0
        prob[term_idx, :, 0] = 1.0
        reward[term_idx] = 0.0
        terminated[term_idx] = True
        size[term_idx] = 1
        # Dense view: aggregate outcomes, then make terminal states absorbing.
        P = np.zeros((S, A, S))
        np.add.at(P, (np.arange(S)[:, None, None], np.arange(A)[None, :, None], next_state), prob)
        r = (prob * reward).sum(-1)
        P[term_idx] = 0.0
        P[term_idx, :, term_idx] = 1.0  # pairs (t, :, t): absorbing self-loops
        r[term_idx] = 0.0
        cdf = np.cumsum(prob, axis=-1)
        return cls(
            P=torch.from_numpy(P),
            r=torch.from_numpy(r),
            gamma=float(gamma),
            initial=torch.from_numpy(initial.copy()),
            terminal=torch.from_numpy(terminal.copy()),
            goal=torch.from_numpy(goal),
            outcomes=Outcomes(
                next_state=torch.from_numpy(next_state),
                prob=torch.from_numpy(prob),
                cdf=torch.from_numpy(cdf),
                reward=torch.from_numpy(reward),
                terminated=torch.from_numpy(terminated),
                size=torch.from_numpy(size),
            ),
            max_steps=None if max_steps is None else int(max_steps),
            desc=desc,
            name=name,
        )


# ---------------------------------------------------------------------- helpers
def _kernel_outcome_lists(
    P: np.ndarray, R: np.ndarray, terminal: np.ndarray
) -> list[list[list[tuple[float, int, float, bool]]]]:
    """``lists[s][a]``: every next state ``t`` in index order, ``(P[s, a, t], t, R[s, a, t], terminal[t])``."""
    S, A = P.shape[0], P.shape[1]
    return [
        [
            [(float(P[s, a, t]), t, float(R[s, a, t]), bool(terminal[t])) for t in range(S)]
            for a in range(A)
        ]
        for s in range(S)
    ]


def _pad_outcome_lists(
    outcome_lists: list[list[list[tuple[float, int, float, bool]]]], S: int, A: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The lists as ``[S, A, K]`` arrays ``next_state, prob, reward, terminated`` and ``[S, A]`` ``size``.

    ``K`` is the longest list; padding entries are as :class:`Outcomes` describes them.
    """
    K = max(len(outs) for row in outcome_lists for outs in row)
    next_state = np.zeros((S, A, K), dtype=np.int64)
    prob = np.zeros((S, A, K))
    reward = np.zeros((S, A, K))
    terminated = np.zeros((S, A, K), dtype=bool)
    size = np.zeros((S, A), dtype=np.int64)
    for s in range(S):
        for a in range(A):
            outs = outcome_lists[s][a]
            size[s, a] = len(outs)
            for k, (p, t, rew, term) in enumerate(outs):
                next_state[s, a, k], prob[s, a, k] = t, p
                reward[s, a, k], terminated[s, a, k] = rew, term
            next_state[s, a, len(outs) :] = next_state[s, a, 0]
    return next_state, prob, reward, terminated, size


def _goal_states(
    next_state: np.ndarray, prob: np.ndarray, reward: np.ndarray, terminal: np.ndarray
) -> np.ndarray:
    """``[S]`` bool: the terminal states entered with the best entering reward among terminal states."""
    # Success = entering a terminal state with the best entering reward among
    # terminal states (FrozenLake's G over its holes; CliffWalking's and Taxi's
    # only kind of terminal state). Entries are read from non-terminal sources.
    S = terminal.shape[0]
    entering_reward = np.full(S, -np.inf)
    live = (prob > 0) & ~terminal[:, None, None]
    np.maximum.at(entering_reward, next_state[live], reward[live])
    term_idx = np.flatnonzero(terminal)
    goal = np.zeros(S, dtype=bool)
    if term_idx.size:
        goal = terminal & (entering_reward == entering_reward[term_idx].max())
    return goal
