"""`TwoWayObstacleEnv`: two equally good ways around an obstacle, and an expert that picks one.

A point moves right at constant speed and steers laterally; a disc blocks the
straight line between the start and the goal, so it must pass either above or below.
Both ways are equally good (the task is symmetric in ``y``). The expert carries a
latent *intent* (+1 above, -1 below) drawn per episode: near the centre line it follows
its intent, elsewhere it keeps to the side it is already on. Demonstrations near the
centre line therefore hold two labels for one observation, ``+0.5`` and ``-0.5``:

* a loss that regresses the mean (MSE) predicts about ``0`` there, an action no
  demonstrator took, and a clone that follows it goes straight at the obstacle until
  it drifts off the centre line (too late, from starts near it);
* a generative policy (diffusion) can keep both modes, but one that samples each
  step afresh may switch between them before it has left the centre line.

``benchmarks/loss_functions.py`` measures both effects for every registered loss.

:func:`mode_fractions` measures which: the fraction of a policy's actions at the
decision states (:func:`decision_states`) within ``tol`` of each of the expert's two
actions, and the fraction near neither.

Geometry (defaults, one length unit): start at ``x = 0``, ``y ~ U(-band, band)`` with
``band = 0.05``; each step ``x += dx = 0.05`` and ``y += dx * a`` with ``a in [-1, 1]``;
a disc of radius ``0.3`` at ``(0.8, 0)``; the episode ends on entering the disc
(reward 0) or at the goal line ``x = 2`` after 40 steps (reward 1 if ``|y| <= 0.1``,
else 0). Success is reward 1. From its start the expert steers with ``a = +-0.5`` to
the lane ``|y| = 0.35``, which clears the disc by 0.013 from the worst start; after
the disc it returns to the centre line. It succeeds from every start, and a policy
that hesitates at the start for three steps hits the disc. The expert's modes, ``+-0.5``, sit inside the action bounds, so a noisy
policy clipped to the bounds is not mistaken for one that picked a mode.

Keys: ``"observation"`` float32 ``[*batch, 2]`` = ``(x, y)``; ``"intent"`` int64
``[*batch]`` (+1/-1, read only by the expert, never by a learner); ``"action"``
float32 ``[*batch, 1]``; ``("next", "reward")`` float32 ``[*batch, 1]``;
``("next", "done"|"terminated"|"truncated")`` bool ``[*batch, 1]``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from imitrl import keys
from imitrl.policies.experts import Expert

__all__ = [
    "INTENT",
    "ObstacleGeometry",
    "SteeringEnv",
    "TwoWayObstacleEnv",
    "decision_states",
    "expert_modes",
    "mode_fractions",
    "passing_side",
    "two_way_expert",
    "two_way_outcome",
    "two_way_probe",
]

DECISION_STATES = 1000
"""decision states :func:`two_way_probe` measures a policy at"""

INTENT = "intent"
"""key of the expert's latent intent (+1 pass above, -1 pass below); learners never read it"""


@dataclass(frozen=True)
class ObstacleGeometry:
    """The task's layout (see the module docstring)."""

    dx: float = 0.05
    """forward distance per step; also the largest lateral move (action 1)"""
    band: float = 0.05
    """start ``y ~ U(-band, band)``; inside ``|y| <= band`` the expert follows its intent"""
    decision_x: float = 0.0
    """the expert flies straight until here, then steers to its side (0: from the start)"""
    expert_speed: float = 0.5
    """the expert's largest ``|action|`` (the env allows 1): its two modes sit inside the bounds"""
    obstacle_x: float = 0.8
    """centre of the disc on the ``x`` axis"""
    radius: float = 0.3
    """radius of the disc"""
    margin: float = 0.05
    """the expert passes at ``|y| = radius + margin``"""
    goal_x: float = 2.0
    """the episode ends when ``x >= goal_x``"""
    goal_halfwidth: float = 0.1
    """success needs ``|y| <= goal_halfwidth`` at the goal line"""

    def __post_init__(self) -> None:
        for name in ("dx", "band", "radius", "margin", "goal_x", "goal_halfwidth", "expert_speed"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if not 0 < self.obstacle_x - self.radius < self.obstacle_x + self.radius < self.goal_x:
            raise ValueError("the disc must lie strictly between the start (x=0) and the goal")
        if not 0 <= self.decision_x < self.obstacle_x - self.radius:
            raise ValueError(
                f"decision_x must lie between the start and the disc, got {self.decision_x}"
            )
        if self.expert_speed > 1:
            raise ValueError(f"expert_speed must be at most 1, got {self.expert_speed}")
        if self.band >= self.radius:
            raise ValueError(f"band ({self.band}) must be smaller than the radius ({self.radius})")

    @property
    def steps(self) -> int:
        """steps from the start to the goal line"""
        return math.ceil(self.goal_x / self.dx - 1e-9)


class SteeringEnv(EnvBase):
    """A point that moves right ``dx`` per step and steers laterally, in torch lanes.

    The mechanics the two-way task and the corridor (:mod:`imitrl.envs.corridor`)
    share: ``x = t * dx`` (from the step count: no accumulated rounding), ``y += dx * a``
    with ``a`` clipped to ``[-1, 1]``; at each reset a lane draws ``u ~ U[0, 1)^2`` from
    the env's generator (one draw per lane, reset or not, so a lane's stream is fixed)
    and a subclass turns it into the start ``y0`` and the expert's hidden variable
    (:meth:`_start`); after each step a subclass says which lanes hit a wall, arrived
    and succeeded (:meth:`_outcome`). Reward 1 on success, else 0; the episode ends on
    a hit or on arrival.

    Keys: ``"observation"`` float32 ``[*batch, 2]`` = ``(x, y)``; ``hidden_key`` int64
    ``[*batch]`` (read only by the expert); ``"action"`` float32 ``[*batch, 1]``;
    ``("next", "reward")`` float32 ``[*batch, 1]``; ``("next", "done"|"terminated"|
    "truncated")`` bool ``[*batch, 1]``.

    Args:
        batch_size: ``()`` for one episode or ``(N,)`` for N independent lanes.
        geometry: the layout (it has ``dx``).
        seed: seed of the env's ``torch.Generator`` (starts and hidden variables).
    """

    hidden_key: str

    def __init__(
        self, *, batch_size: Sequence[int] | torch.Size = (), geometry, seed: int = 0
    ) -> None:
        batch_size = torch.Size(batch_size)
        if len(batch_size) > 1:
            raise ValueError(f"batch_size must be () or (N,), got {tuple(batch_size)}")
        super().__init__(device="cpu", batch_size=batch_size)
        self.geometry = geometry
        self._n = int(batch_size.numel())
        self.observation_spec = Composite(
            {
                keys.OBSERVATION: Unbounded(shape=(*batch_size, 2), dtype=torch.float32),
                self.hidden_key: Unbounded(shape=batch_size, dtype=torch.int64),
            },
            shape=batch_size,
        )
        self.action_spec = Bounded(-1.0, 1.0, shape=(*batch_size, 1), dtype=torch.float32)
        self.reward_spec = Unbounded(shape=(*batch_size, 1), dtype=torch.float32)
        self.done_spec = Composite(
            {
                key: Categorical(2, shape=(*batch_size, 1), dtype=torch.bool)
                for key in (keys.DONE, keys.TERMINATED, keys.TRUNCATED)
            },
            shape=batch_size,
        )
        self._pos = torch.zeros(self._n, 2)
        self._t = torch.zeros(self._n, dtype=torch.int64)
        self._hidden = torch.ones(self._n, dtype=torch.int64)
        self._generator = torch.Generator().manual_seed(int(seed))

    def _start(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``u [n, 2]`` float64 uniforms -> start ``y0 [n]`` float32, hidden variable ``[n]`` int64."""
        raise NotImplementedError

    def _outcome(
        self, x: torch.Tensor, y: torch.Tensor, t: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(hit, arrived, success)`` ``[n]`` bool after a step to ``(x, y)`` at step ``t``."""
        raise NotImplementedError

    def _set_seed(self, seed: int | None) -> None:
        self._generator = torch.Generator().manual_seed(0 if seed is None else int(seed))

    def _td(self, extra: dict) -> TensorDict:
        return TensorDict(
            {
                keys.OBSERVATION: self._pos.reshape(*self.batch_size, 2).clone(),
                self.hidden_key: self._hidden.reshape(self.batch_size).clone(),
                **extra,
            },
            batch_size=self.batch_size,
        )

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        lanes = torch.ones(self._n, dtype=torch.bool)
        if tensordict is not None and "_reset" in tensordict.keys():
            lanes = tensordict.get("_reset").reshape(self._n)
        # one draw of each kind per lane, reset or not, so a lane's stream is fixed
        u = torch.rand(self._n, 2, generator=self._generator, dtype=torch.float64)
        y0, hidden = self._start(u)
        start = torch.stack([torch.zeros_like(y0), y0], dim=-1)
        self._pos = torch.where(lanes[:, None], start, self._pos)
        self._t = self._t.masked_fill(lanes, 0)
        self._hidden = torch.where(lanes, hidden, self._hidden)
        false = torch.zeros((*self.batch_size, 1), dtype=torch.bool)
        return self._td(
            {keys.DONE: false, keys.TERMINATED: false.clone(), keys.TRUNCATED: false.clone()}
        )

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(keys.ACTION)
        if not action.dtype.is_floating_point or action.numel() != self._n:
            raise ValueError(
                f"{type(self).__name__} expects float actions of shape {(*self.batch_size, 1)}, "
                f"got {action.dtype} {tuple(action.shape)}"
            )
        if torch.isnan(action).any():
            raise ValueError(f"NaN action given to {type(self).__name__}")
        a = action.reshape(self._n).float().clamp(-1.0, 1.0)
        self._t = self._t + 1
        x = self._t.float() * self.geometry.dx  # from the step count: no accumulated rounding
        y = self._pos[:, 1] + self.geometry.dx * a
        self._pos = torch.stack([x, y], dim=-1)
        hit, arrived, success = self._outcome(x, y, self._t)
        terminated = hit | arrived
        shape1 = (*self.batch_size, 1)
        return self._td(
            {
                keys.REWARD: success.float().reshape(shape1),
                keys.DONE: terminated.reshape(shape1),
                keys.TERMINATED: terminated.reshape(shape1).clone(),
                keys.TRUNCATED: torch.zeros(shape1, dtype=torch.bool),
            }
        )


class TwoWayObstacleEnv(SteeringEnv):
    """Batched simulator of the two-way obstacle task (torch only, no gymnasium).

    The hidden variable is the expert's intent under ``"intent"`` (+1 above, -1 below,
    each with probability 1/2); see :class:`SteeringEnv` for the keys and mechanics.

    Args:
        batch_size: ``()`` for one episode or ``(N,)`` for N independent lanes.
        geometry: the layout.
        seed: seed of the env's ``torch.Generator`` (start positions and intents).
    """

    hidden_key = INTENT

    def __init__(
        self,
        *,
        batch_size: Sequence[int] | torch.Size = (),
        geometry: ObstacleGeometry = ObstacleGeometry(),
        seed: int = 0,
    ) -> None:
        super().__init__(batch_size=batch_size, geometry=geometry, seed=seed)

    def _start(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        y0 = ((2 * u[:, 0] - 1) * self.geometry.band).float()
        return y0, torch.where(u[:, 1] < 0.5, 1, -1)

    def _outcome(self, x, y, t):
        g = self.geometry
        hit = (x - g.obstacle_x) ** 2 + y**2 < g.radius**2
        arrived = (t >= g.steps) & ~hit
        return hit, arrived, arrived & (y.abs() <= g.goal_halfwidth)


class _TwoWayExpert(nn.Module):
    """``(observation [..., 2], intent [...]) -> action [..., 1]`` (see :func:`two_way_expert`)."""

    def __init__(self, geometry: ObstacleGeometry) -> None:
        super().__init__()
        self.geometry = geometry

    def forward(self, obs: torch.Tensor, intent: torch.Tensor) -> torch.Tensor:
        if obs.shape[-1:] != (2,):
            raise ValueError(f"observations must be (x, y) [..., 2], got {tuple(obs.shape)}")
        if intent.shape != obs.shape[:-1]:
            raise ValueError(
                f"one intent per observation: intent {tuple(intent.shape)}, observation {tuple(obs.shape)}"
            )
        if not bool(((intent == 1) | (intent == -1)).all()):
            raise ValueError("intent must be +1 (above) or -1 (below)")
        g = self.geometry
        x, y = obs[..., 0].float(), obs[..., 1].float()
        side = torch.where(y.abs() <= g.band, intent.float(), torch.sign(y))
        # straight on until decision_x; then to the chosen side's lane until past the
        # disc; then back to the centre line. Deadbeat: reach the target in one step
        # when it is within reach.
        lane = torch.where(x < g.obstacle_x + g.radius, side * (g.radius + g.margin), 0.0)
        target = torch.where(x < g.decision_x - 1e-6, y, lane)
        return ((target - y) / g.dx).clamp(-g.expert_speed, g.expert_speed).unsqueeze(-1)


def two_way_expert(geometry: ObstacleGeometry = ObstacleGeometry()) -> Expert:
    """The task's queryable expert: reads ``"observation"`` and ``"intent"``, writes ``"expert_action"``.

    Inside the band ``|y| <= band`` it steers towards the side of its intent, outside
    it keeps to the side it is on (``sign(y)``); it holds the lane ``|y| = radius +
    margin`` until past the disc, then returns to the centre line. It labels any
    state: DAgger queries it at the learner's states with the episode's intent.
    """
    return Expert(_TwoWayExpert(geometry), in_keys=[keys.OBSERVATION, INTENT])


def decision_states(
    num: int, *, geometry: ObstacleGeometry = ObstacleGeometry(), seed: int = 0
) -> torch.Tensor:
    """``[num, 2]`` observations ``(decision_x, y0)``, ``y0 ~ U(-band, band)``: where the expert is bimodal.

    The expert flies straight from its start ``(0, y0)`` and reaches these states at its
    decision step; with intent +1 it then steers up at full speed, with -1 down.
    """
    if num < 1:
        raise ValueError(f"num must be positive, got {num}")
    g = torch.Generator().manual_seed(int(seed))
    y0 = (2 * torch.rand(num, generator=g, dtype=torch.float64) - 1) * geometry.band
    return torch.stack([torch.full((num,), geometry.decision_x), y0.float()], dim=-1)


def expert_modes(
    obs: torch.Tensor, geometry: ObstacleGeometry = ObstacleGeometry()
) -> torch.Tensor:
    """``[..., 2]`` the expert's action at ``obs`` with intent below (column 0) and above (column 1)."""
    net = _TwoWayExpert(geometry)
    shape = obs.shape[:-1]
    below = net(obs, torch.full(shape, -1, dtype=torch.int64))
    above = net(obs, torch.full(shape, 1, dtype=torch.int64))
    return torch.cat([below, above], dim=-1)


def mode_fractions(
    obs: torch.Tensor,
    actions: torch.Tensor,
    *,
    tol: float = 0.25,
    geometry: ObstacleGeometry = ObstacleGeometry(),
) -> dict[str, float]:
    """Where a policy's actions at ``obs [N, 2]`` fall, ``actions [N, 1]``.

    Returns the fractions ``above`` (within ``tol`` of the expert's pass-above action),
    ``below`` (within ``tol`` of its pass-below action) and ``neither`` (they sum to
    1), and ``middle``, the part of ``neither`` within ``tol`` of the two modes' mean
    (the action a mean-regressing loss predicts).
    """
    if obs.ndim != 2 or obs.shape[-1] != 2 or actions.shape != (obs.shape[0], 1):
        raise ValueError(
            f"need obs [N, 2] and actions [N, 1], got {tuple(obs.shape)} and {tuple(actions.shape)}"
        )
    modes = expert_modes(obs, geometry)  # [N, 2]
    a = actions[:, 0].float()
    below = (a - modes[:, 0]).abs() <= tol
    above = (a - modes[:, 1]).abs() <= tol
    if bool(((modes[:, 1] - modes[:, 0]).abs() <= 2 * tol).any()):
        raise ValueError(f"tol={tol} is too wide: the two modes overlap at some states")
    return {
        "above": float(above.float().mean()),
        "below": float(below.float().mean()),
        "neither": float((~(above | below)).float().mean()),
        "middle": float(((a - modes.mean(-1)).abs() <= tol).float().mean()),
    }


def passing_side(
    rows: TensorDictBase, geometry: ObstacleGeometry = ObstacleGeometry()
) -> torch.Tensor:
    """Per episode in ``rows`` (from :func:`imitrl.runtime.rollout_episodes`): +1 passed above, -1 below, 0 hit.

    Read at the first step at or beyond the disc's centre (``x >= obstacle_x``);
    episodes that end before it (in the disc) get 0. Returns ``[E]`` int64 in episode id order.
    """
    episode = rows.get(keys.EPISODE)
    obs = rows.get(keys.OBSERVATION)
    ids = torch.unique(episode)
    side = torch.zeros(ids.numel(), dtype=torch.int64)
    for i, e in enumerate(ids.tolist()):
        ep = obs[episode == e]
        past = ep[:, 0] >= geometry.obstacle_x - 1e-6
        if bool(past.any()):
            side[i] = int(torch.sign(ep[past][0, 1]))
    return side


def two_way_probe(act: Callable[[torch.Tensor], torch.Tensor], seed: int) -> dict[str, float]:
    """:func:`mode_fractions` of ``act(obs [N, 2]) -> actions [N, 1]`` at
    :data:`DECISION_STATES` decision states drawn with ``seed`` (a benchmark's probe)."""
    obs = decision_states(DECISION_STATES, seed=seed)
    return mode_fractions(obs, act(obs))


def two_way_outcome(rows: TensorDictBase) -> dict[str, float | None]:
    """``{"passed_above": fraction of the successful episodes in rows that passed above}``
    (None without a success; a benchmark's outcome)."""
    side = passing_side(rows)
    episode = rows.get(keys.EPISODE)
    reward = rows.get((keys.NEXT, keys.REWARD)).reshape(-1)
    won = torch.stack([(reward[episode == e] > 0).any() for e in torch.unique(episode)])
    wins = int(won.sum())
    return {"passed_above": int(((side > 0) & won).sum()) / wins if wins else None}
