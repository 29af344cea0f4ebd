"""`ForkingCorridorEnv`: a corridor that forks twice, and an expert that commits to one of four routes.

A point moves right at constant speed and steers laterally (the mechanics of
:class:`~imitrl.envs.multimodal.SteeringEnv`) inside a corridor ``|y| < half_width = 1.5`` (wide: only the dividers are meant to
matter). A divider
(a wall of half-thickness ``divider``) splits it along ``y = 0`` from ``fork1_x`` on,
and each branch is split again along ``y = +-branch`` from ``fork2_x`` on: four lanes
reach the goal line, centred at ``y = -0.75, -0.25, 0.25, 0.75``, and all four are
equally good (success: reach the goal line without touching a wall). The expert draws
its *route* ``r in {0, 1, 2, 3}`` (the lane, numbered from below) once per episode,
a hidden variable, and drives it:

* fork 1: from its start ``y0 ~ U(-band, band)`` it steers to the centre line of its
  branch, ``y = +-branch`` (up for routes 2, 3), and holds it;
* fork 2: from ``turn2_x`` on it steers to its lane, ``+-lane`` off the branch's
  centre line (up for routes 1, 3).

It steers proportionally: ``a = clip(expert_gain * (target - y) / dx, +-expert_speed)``,
at full speed far from the target, settling on it smoothly.

Inside a decision band (``|y - c| <= band`` around the fork's centre line ``c``) it
follows its route; outside it keeps to the side it is on, as the two-way expert does
(:mod:`imitrl.envs.multimodal`), so it labels any state DAgger visits with an action
that leads to a lane. At the two decision points the demonstrations hold two labels
for one observation, ``+expert_speed`` and ``-expert_speed``. Two ways to fail,
for different reasons:

* **mode averaging** (a loss that regresses the mean): it predicts about 0 in the band
  and drives straight into the tip of the divider ahead; from its start the divider
  is ``fork1_x / dx`` steps away and ``divider`` wide, wider than the band, so not
  steering is fatal (:func:`averaging_policy` is that policy, exactly);
* **per-step mode switching** (a generative policy sampled afresh every step): it
  picks a side at random each step while in the band, a random walk that takes far
  longer to leave the band than the ``fork1_x / dx`` steps the expert needs, and hits
  the tip as well (:func:`switching_policy`: the expert with a fresh route every step).

A policy that commits (the expert; a chunked learner executing several actions of
one sample) passes. :func:`outcomes` says per episode which lane it reached or where
it failed; :func:`mode_fractions` measures where a policy's actions fall at each
fork's decision states (:func:`decision_states`), :func:`reversals` how often it
turned back inside the decision windows.

Geometry (defaults, one length unit): ``dx = 0.05``, so the goal line ``x = 2`` is 40
steps away; the expert moves at most ``dx * 0.5 = 0.025`` sideways per step; the band
is 0.05, the dividers are 0.1 thick on each side; fork 1 at ``x = 0.4`` (8 steps: the
expert clears the tip by 0.05 from its worst start), fork 2 at ``x = 1.6`` with the turn
at ``x = 1.2`` (again 8 steps).

Keys: those of :class:`~imitrl.envs.multimodal.SteeringEnv`, with ``"route"`` int64
``[*batch]`` the hidden variable (read only by the expert, never by a learner).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from imitrl import keys
from imitrl.envs.multimodal import SteeringEnv
from imitrl.policies.experts import Expert

__all__ = [
    "OUTCOMES",
    "ROUTE",
    "CorridorGeometry",
    "ForkingCorridorEnv",
    "averaging_policy",
    "corridor_expert",
    "corridor_outcome",
    "corridor_probe",
    "decision_states",
    "mode_fractions",
    "outcomes",
    "reversals",
    "switching_policy",
]

ROUTE = "route"
"""key of the expert's hidden route (0..3, the lane from below); learners never read it"""

ROUTES = 4
DECISION_STATES = 1000
"""decision states per fork that :func:`corridor_probe` measures a policy at"""
OUTCOMES = ("lane_0", "lane_1", "lane_2", "lane_3", "hit_fork1", "hit_fork2", "hit_wall")
"""what :func:`outcomes` codes 0..6 mean: the lane reached, or the wall hit"""


@dataclass(frozen=True)
class CorridorGeometry:
    """The corridor's layout (see the module docstring)."""

    dx: float = 0.05
    """forward distance per step; also the largest lateral move (action 1)"""
    band: float = 0.05
    """decision band: within ``band`` of a fork's centre line the expert follows its route"""
    expert_speed: float = 0.5
    """the expert's largest ``|action|``: its modes sit inside the action bounds"""
    expert_gain: float = 0.25
    """the expert closes this fraction of its distance to the target per step (within
    its speed): it settles on a lane smoothly instead of stopping dead"""
    divider: float = 0.1
    """half-thickness of each divider (wider than the band: not steering hits it)"""
    fork1_x: float = 0.4
    """where the divider along ``y = 0`` begins"""
    branch: float = 0.5
    """the branches' centre lines ``y = +-branch``, where the second dividers lie"""
    turn2_x: float = 1.2
    """the expert holds its branch's centre line until here, then turns to its lane"""
    fork2_x: float = 1.6
    """where the dividers along ``y = +-branch`` begin"""
    lane: float = 0.25
    """the lanes' centres lie ``+-lane`` off their branch's centre line"""
    half_width: float = 1.5
    """the corridor's walls at ``|y| = half_width`` (far from the outer lanes, whose
    centres lie at ``+-(branch + lane)``: a clone that overshoots its lane is not what
    this task measures)"""
    goal_x: float = 2.0
    """the episode ends (success if no wall was touched) when ``x >= goal_x``"""

    def __post_init__(self) -> None:
        for name in ("dx", "band", "divider", "branch", "lane", "half_width", "expert_speed"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if not 0 < self.expert_gain <= 1:
            raise ValueError(f"expert_gain must be in (0, 1], got {self.expert_gain}")
        if self.expert_speed > 1:
            raise ValueError(f"expert_speed must be at most 1, got {self.expert_speed}")
        if self.band >= self.divider:
            raise ValueError(
                f"band ({self.band}) must be narrower than the divider ({self.divider}): "
                "otherwise a policy that does not steer may slip past the tip"
            )
        if not 0 < self.fork1_x < self.turn2_x < self.fork2_x < self.goal_x:
            raise ValueError("need 0 < fork1_x < turn2_x < fork2_x < goal_x")
        if not self.divider < self.branch - self.lane - self.divider:
            raise ValueError("the inner lanes must clear the dividers on both sides")
        if not self.branch + self.lane + self.divider < self.half_width:
            raise ValueError("the outer lanes must clear the corridor's walls")
        # the expert reaches its branch's centre line before turn2_x from its worst start
        reach = (self.branch + self.band) / (self.dx * self.expert_speed)
        if reach * self.dx > self.turn2_x + 1e-9:
            raise ValueError(
                f"turn2_x={self.turn2_x} comes before the expert reaches its branch "
                f"(x = {reach * self.dx:.2f})"
            )

    @property
    def steps(self) -> int:
        """steps from the start to the goal line"""
        return math.ceil(self.goal_x / self.dx - 1e-9)


class ForkingCorridorEnv(SteeringEnv):
    """Batched simulator of the forking corridor (torch only, no gymnasium).

    The hidden variable is the expert's route under ``"route"`` (0..3, each with
    probability 1/4); see :class:`~imitrl.envs.multimodal.SteeringEnv` for the keys.

    Args:
        batch_size: ``()`` for one episode or ``(N,)`` for N independent lanes.
        geometry: the layout.
        seed: seed of the env's ``torch.Generator`` (start positions and routes).
    """

    hidden_key = ROUTE

    def __init__(
        self,
        *,
        batch_size: Sequence[int] | torch.Size = (),
        geometry: CorridorGeometry = CorridorGeometry(),
        seed: int = 0,
    ) -> None:
        super().__init__(batch_size=batch_size, geometry=geometry, seed=seed)

    def _start(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        y0 = ((2 * u[:, 0] - 1) * self.geometry.band).float()
        return y0, (u[:, 1] * ROUTES).long().clamp(max=ROUTES - 1)

    def _outcome(self, x, y, t):
        hit = wall_hit(x, y, self.geometry) > 0
        arrived = (t >= self.geometry.steps) & ~hit
        return hit, arrived, arrived


def wall_hit(x: torch.Tensor, y: torch.Tensor, geometry: CorridorGeometry) -> torch.Tensor:
    """``[n]`` int64: 0 no wall, 1 the first divider, 2 a second divider, 3 a corridor wall."""
    g = geometry
    fork1 = (x >= g.fork1_x - 1e-6) & (y.abs() < g.divider)
    fork2 = (x >= g.fork2_x - 1e-6) & ((y.abs() - g.branch).abs() < g.divider)
    wall = y.abs() >= g.half_width
    code = torch.zeros(x.shape, dtype=torch.int64)
    code = torch.where(wall, 3, code)
    code = torch.where(fork2, 2, code)
    return torch.where(fork1, 1, code)


def _route_bits(route: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Route 0..3 -> (side at fork 1, side at fork 2), each -1 (down) or +1 (up)."""
    up1 = torch.where(route >= 2, 1.0, -1.0)
    up2 = torch.where(route % 2 == 1, 1.0, -1.0)
    return up1, up2


class _CorridorExpert(nn.Module):
    """``(observation [..., 2], route [...]) -> action [..., 1]`` (see :func:`corridor_expert`)."""

    def __init__(self, geometry: CorridorGeometry) -> None:
        super().__init__()
        self.geometry = geometry

    def forward(self, obs: torch.Tensor, route: torch.Tensor) -> torch.Tensor:
        if obs.shape[-1:] != (2,):
            raise ValueError(f"observations must be (x, y) [..., 2], got {tuple(obs.shape)}")
        if route.shape != obs.shape[:-1]:
            raise ValueError(
                f"one route per observation: route {tuple(route.shape)}, "
                f"observation {tuple(obs.shape)}"
            )
        if not bool(((route >= 0) & (route < ROUTES)).all()):
            raise ValueError(f"route must be in 0..{ROUTES - 1}")
        g = self.geometry
        x, y = obs[..., 0].float(), obs[..., 1].float()
        up1, up2 = _route_bits(route)
        # fork 1: the route's side inside the band, else the side it is on
        side1 = torch.where(y.abs() <= g.band, up1, torch.sign(y))
        centre = side1 * g.branch
        # fork 2 (from turn2_x): the same rule around the branch's centre line
        off = y - centre
        side2 = torch.where(off.abs() <= g.band, up2, torch.sign(off))
        target = torch.where(x < g.turn2_x - 1e-6, centre, centre + side2 * g.lane)
        # close expert_gain of the distance to the target, at most expert_speed per step
        step = g.expert_gain * (target - y) / g.dx
        return step.clamp(-g.expert_speed, g.expert_speed).unsqueeze(-1)


def corridor_expert(geometry: CorridorGeometry = CorridorGeometry()) -> Expert:
    """The task's queryable expert: reads ``"observation"`` and ``"route"``, writes ``"expert_action"``.

    It labels any state with the action its route asks for there (module docstring):
    DAgger queries it at the learner's states with the episode's route.
    """
    return Expert(_CorridorExpert(geometry), in_keys=[keys.OBSERVATION, ROUTE])


class _RoutePolicy(TensorDictModuleBase):
    """``OBSERVATION -> ACTION``: the expert's action under routes drawn by ``mix``."""

    def __init__(self, geometry: CorridorGeometry, mix: str, seed: int) -> None:
        super().__init__()
        self.net = _CorridorExpert(geometry)
        self.mix = mix
        self.in_keys, self.out_keys = [keys.OBSERVATION], [keys.ACTION]
        self.generator = torch.Generator().manual_seed(int(seed))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict.get(keys.OBSERVATION)
        shape = obs.shape[:-1]
        if self.mix == "mean":  # the mean of the four routes' actions
            each = [self.net(obs, torch.full(shape, r, dtype=torch.int64)) for r in range(ROUTES)]
            action = torch.stack(each).mean(0)
        else:  # a route drawn afresh at every step, in every lane
            route = torch.randint(ROUTES, shape, generator=self.generator)
            action = self.net(obs, route)
        tensordict.set(keys.ACTION, action)
        return tensordict


def averaging_policy(geometry: CorridorGeometry = CorridorGeometry()) -> TensorDictModuleBase:
    """The mean of the expert's actions over the four routes: what a mean regressor learns."""
    return _RoutePolicy(geometry, "mean", 0)


def switching_policy(
    geometry: CorridorGeometry = CorridorGeometry(), *, seed: int = 0
) -> TensorDictModuleBase:
    """The expert with a route drawn afresh at every step: an ideal per-step sampler.

    At every state it acts as the expert under a route drawn uniformly (from its own
    generator seeded with ``seed``), so its actions have exactly the expert's modes.
    """
    return _RoutePolicy(geometry, "switch", seed)


def decision_states(
    num: int, *, fork: int, geometry: CorridorGeometry = CorridorGeometry(), seed: int = 0
) -> torch.Tensor:
    """``[num, 2]`` observations where the expert is bimodal: at fork ``1`` or ``2``.

    Fork 1: ``(0, y0)``, ``y0 ~ U(-band, band)``, the starts. Fork 2: ``(turn2_x,
    +-branch + u)``, ``u ~ U(-band, band)``, the branch (either, half each) drawn with
    the same generator: where the expert turns to its lane.
    """
    if num < 1:
        raise ValueError(f"num must be positive, got {num}")
    if fork not in (1, 2):
        raise ValueError(f"fork must be 1 or 2, got {fork!r}")
    g = torch.Generator().manual_seed(int(seed))
    u = (2 * torch.rand(num, generator=g, dtype=torch.float64) - 1) * geometry.band
    if fork == 1:
        return torch.stack([torch.zeros(num), u.float()], dim=-1)
    side = torch.where(torch.rand(num, generator=g) < 0.5, 1.0, -1.0)
    return torch.stack(
        [torch.full((num,), geometry.turn2_x), (side * geometry.branch + u).float()], -1
    )


def expert_modes(
    obs: torch.Tensor, geometry: CorridorGeometry = CorridorGeometry()
) -> torch.Tensor:
    """``[N, 2]``: the expert's action at ``obs`` ``[N, 2]`` going down (column 0) and up (column 1)
    at the fork ahead (routes 0/2 vs 1/3 at fork 2 within the branch; 0/1 vs 2/3 at fork 1)."""
    net = _CorridorExpert(geometry)
    n = obs.shape[0]
    second = obs[:, 0] >= geometry.turn2_x - 1e-6
    upper = obs[:, 1] > 0
    # down / up at the fork ahead, the other fork's bit as the branch the state is in
    down = torch.where(second, torch.where(upper, 2, 0), torch.zeros(n, dtype=torch.int64))
    up = torch.where(second, torch.where(upper, 3, 1), torch.full((n,), 2, dtype=torch.int64))
    return torch.cat([net(obs, down), net(obs, up)], dim=-1)


def mode_fractions(
    obs: torch.Tensor,
    actions: torch.Tensor,
    *,
    tol: float = 0.25,
    geometry: CorridorGeometry = CorridorGeometry(),
) -> dict[str, float]:
    """Where a policy's actions at decision states ``obs [N, 2]`` fall, ``actions [N, 1]``.

    ``down`` / ``up``: within ``tol`` of the expert's action towards the lower / upper
    side at the fork ahead; ``neither`` (the three sum to 1); ``middle``: the part of
    ``neither`` within ``tol`` of the two modes' mean (a mean regressor's action).
    """
    if obs.ndim != 2 or obs.shape[-1] != 2 or actions.shape != (obs.shape[0], 1):
        raise ValueError(
            f"need obs [N, 2] and actions [N, 1], got {tuple(obs.shape)} and {tuple(actions.shape)}"
        )
    modes = expert_modes(obs, geometry)
    if bool(((modes[:, 1] - modes[:, 0]).abs() <= 2 * tol).any()):
        raise ValueError(f"tol={tol} is too wide: the two modes overlap at some states")
    a = actions[:, 0].float()
    down = (a - modes[:, 0]).abs() <= tol
    up = (a - modes[:, 1]).abs() <= tol
    return {
        "down": float(down.float().mean()),
        "up": float(up.float().mean()),
        "neither": float((~(down | up)).float().mean()),
        "middle": float(((a - modes.mean(-1)).abs() <= tol).float().mean()),
    }


def outcomes(rows: TensorDictBase, geometry: CorridorGeometry = CorridorGeometry()) -> torch.Tensor:
    """Per episode in ``rows`` (from :func:`imitrl.runtime.rollout_episodes`): its :data:`OUTCOMES` code.

    0..3: the lane it reached the goal line in (from below); 4: it hit the first
    divider; 5: a second divider; 6: a corridor wall. ``[E]`` int64 in episode id order.
    """
    episode = rows.get(keys.EPISODE)
    done = rows.get((keys.NEXT, keys.DONE)).reshape(-1)
    ids = torch.unique(episode)
    if int(done.sum()) != ids.numel():
        raise ValueError("every episode in the rows must be complete (one done row each)")
    # rows hold no next observation: the final position is the last row's stepped once
    last = rows[done][torch.argsort(episode[done])]
    y = last.get(keys.OBSERVATION)[:, 1] + geometry.dx * last.get(keys.ACTION)[:, 0].clamp(-1, 1)
    x = (last.get(keys.STEP) + 1).float() * geometry.dx
    hit = wall_hit(x, y, geometry)
    bounds = torch.tensor([-geometry.branch, 0.0, geometry.branch])
    lane = torch.bucketize(y.contiguous(), bounds)  # 0..3 from below
    return torch.where(hit > 0, 3 + hit, lane)


def reversals(rows: TensorDictBase, geometry: CorridorGeometry = CorridorGeometry()) -> float:
    """Mean number of turn-backs per episode inside the decision windows.

    A turn-back: a step whose action points the other way from the previous step's,
    both at least ``expert_speed / 2`` in size, while ``x < fork1_x`` or ``turn2_x <=
    x < fork2_x``. The expert never turns back there; a per-step sampler does.
    """
    g = geometry
    episode, step = rows.get(keys.EPISODE), rows.get(keys.STEP)
    x = rows.get(keys.OBSERVATION)[:, 0]
    a = rows.get(keys.ACTION).reshape(-1)
    window = (x < g.fork1_x - 1e-6) | ((x >= g.turn2_x - 1e-6) & (x < g.fork2_x - 1e-6))
    firm = torch.sign(a) * (a.abs() >= g.expert_speed / 2)  # -1, 0 or +1
    ids = torch.unique(episode)
    total = 0
    for e in ids.tolist():
        idx = torch.nonzero(episode == e).squeeze(-1)
        idx = idx[torch.argsort(step[idx])]  # in time order
        s, w = firm[idx], window[idx]
        total += int(((s[1:] * s[:-1] < 0) & w[1:] & w[:-1]).sum())
    return total / ids.numel()


def corridor_probe(act: Callable[[torch.Tensor], torch.Tensor], seed: int) -> dict[str, float]:
    """:func:`mode_fractions` of ``act(obs [N, 2]) -> actions [N, 1]`` at each fork's
    :data:`DECISION_STATES` decision states, as ``fork1_up``, ``fork2_middle``, ...
    (a benchmark's probe)."""
    out = {}
    for fork in (1, 2):
        obs = decision_states(DECISION_STATES, fork=fork, seed=seed)
        out.update({f"fork{fork}_{k}": v for k, v in mode_fractions(obs, act(obs)).items()})
    return out


def corridor_outcome(rows: TensorDictBase) -> dict[str, float]:
    """The fraction of the episodes in ``rows`` with each of :data:`OUTCOMES`, and the
    mean :func:`reversals` per episode (a benchmark's outcome)."""
    codes = outcomes(rows)
    counts = torch.bincount(codes, minlength=len(OUTCOMES)).double() / codes.numel()
    return {**dict(zip(OUTCOMES, counts.tolist())), "reversals": reversals(rows)}
