"""Two policies compared on paired episodes, with a fixed number of episodes or a
sequential stop.

**Pairing.** Episode ``j`` of both policies starts from the env seeded ``seed + j`` (and
the policies' own sampling from the generator of that seed): the same initial state, and
the same draws of the env's randomness for as long as the two play the same actions.
Episodes are played in waves of one episode per lane (lane ``i`` of a wave ``w`` of an
``L``-lane env is seeded ``seed + w L + i``, what ``make_env``'s lanes do), so a greedy
policy's outcomes do not depend on the lane count (a sampling policy draws for its
lanes at once, from the generator of the wave's seed: its outcomes depend on ``L``, the
pairing does not). The outcome of an episode is its success (the
env's reported success, a tabular goal) or its return; the comparison is of the paired
differences ``d_j = a_j - b_j``, whose variance is ``var(a) + var(b) - 2 cov(a, b)``:
where the shared seeds make the outcomes agree, fewer episodes say more. An env whose
reset from one seed does not replay the same observation is refused (:func:`check_replays`).

**Fixed size** (``sequential=False``): ``episodes`` pairs, the mean difference with its
Student-t interval, and the two-sided paired t-test at ``alpha`` (the interval excludes 0).
Where every difference is the same (no spread: a t-interval would be that value alone,
which holds only for differences symmetric about their mean, and 0/1 outcomes are not),
the interval is the betting interval below of the bounded outcomes (success, or returns
within ``return_range``), valid for any distribution within the bounds; returns without
bounds allow any mean, and the interval is unbounded.

Every outcome must be finite, and a return within ``return_range`` where one is given
(either mode): an episode outside it is refused, naming the side and the episode, never
clipped (a sequential comparison's bets read outcomes mapped into the range).

**Sequential** (``sequential=True``): after each wave, an anytime-valid confidence
sequence for the mean difference (the hedged betting confidence sequence of
Waudby-Smith and Ramdas, "Estimating means of bounded random variables by betting",
JRSS-B 2024, with their predictable plug-in bets), and the comparison stops as soon as
it excludes 0, or at ``episodes``. Its error rate is at most ``alpha`` whenever it stops
(a test martingale: Ville's inequality), which is what lets it stop early. It needs
bounded outcomes: success, or returns within a stated ``return_range``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.envs.success import SUCCESS, reported_success
from imitrl.envs.tabular_env import TabularEnv
from imitrl.evaluation.evaluate import tabular_success
from imitrl.evaluation.statistics import t_interval
from imitrl.limits import MIN_ALPHA
from imitrl.runtime.loop import lane_count
from imitrl.runtime.returns import episode_returns
from imitrl.runtime.rollout import rollout_policy

__all__ = [
    "Comparison",
    "PolicySpec",
    "betting_interval",
    "check_replays",
    "check_return_range",
    "compare",
    "log_capital",
]

BET_CAP = 0.5
"""the largest fraction of its capital a bet may stake (the paper's ``c``)"""
GRID = 2001
"""candidate means of the confidence sequence, on [0, 1]"""


@dataclass(frozen=True)
class PolicySpec:
    """A policy to compare: a module writing ``ACTION`` and how it acts."""

    policy: TensorDictModuleBase
    exploration: ExplorationType
    name: str


@dataclass(frozen=True)
class Comparison:
    """What :func:`compare` found."""

    a: str
    b: str
    metric: str
    """``"success"`` or ``"return"``"""
    episodes: int
    """pairs played"""
    mean_a: float
    mean_b: float
    difference: float
    """mean of ``a - b``"""
    interval: tuple[float, float]
    """of the mean difference: Student-t (fixed), the bounded outcomes' betting interval
    (fixed, every difference equal; infinite for returns without bounds), or the
    confidence sequence (sequential)"""
    decision: str
    """``"a better"``, ``"b better"`` or ``"no difference shown"``"""
    rule: str
    alpha: float
    stopped_early: bool

    def as_dict(self) -> dict:
        """The fields as JSON values (an infinite bound of the interval as None)."""
        out = asdict(self)
        out["interval"] = [v if math.isfinite(v) else None for v in self.interval]
        return out


def check_replays(env: EnvBase, seed: int) -> None:
    """ValueError unless two resets from ``seed`` give the same observation (episodes
    can then be paired). Seeded as the paired episodes are (``env.set_seed``, then a reset:
    :func:`~imitrl.runtime.rollout.rollout_episodes`): TorchRL's ``reset(seed=...)`` reaches
    a gymnasium env's own seed but not the generator of an env written on ``EnvBase``."""
    env.set_seed(int(seed))
    first = env.reset().get(keys.OBSERVATION).clone()
    env.set_seed(int(seed))
    again = env.reset().get(keys.OBSERVATION)
    if not torch.equal(first, again):
        raise ValueError(
            f"{type(env).__name__} does not replay its episodes from a seed (two resets from "
            f"seed {seed} differ): its episodes cannot be paired"
        )


def compare(
    env: EnvBase,
    a: PolicySpec,
    b: PolicySpec,
    episodes: int,
    *,
    seed: int = 0,
    alpha: float = 0.05,
    sequential: bool = False,
    metric: str | None = None,
    return_range: tuple[float, float] | None = None,
    max_steps: int | None = None,
) -> Comparison:
    """Compare ``a`` and ``b`` on paired episodes of ``env`` (module docstring).

    Args:
        episodes: pairs in a fixed comparison; the most a sequential one plays.
        metric: ``"success"`` (default where the env reports success or is tabular) or
            ``"return"``.
        return_range: ``(low, high)`` bounds of an episode's return, needed for a
            sequential comparison of returns (its bets need bounded outcomes).
    """
    if not MIN_ALPHA <= alpha < 1.0:
        raise ValueError(f"alpha must be in [{MIN_ALPHA:g}, 1), got {alpha}")
    if int(episodes) != episodes or episodes < 2:
        raise ValueError(f"episodes must be an integer >= 2 (pairs), got {episodes!r}")
    success_fn = _success_fn(env)
    metric = metric or ("success" if success_fn is not None else "return")
    if metric not in ("success", "return"):
        raise ValueError(f"metric must be success or return, got {metric!r}")
    if metric == "success" and success_fn is None:
        raise ValueError(f"{type(env).__name__} reports no success: compare returns instead")
    if return_range is not None:
        check_return_range(return_range)
    bounds = (0.0, 1.0) if metric == "success" else return_range
    if sequential and bounds is None:
        raise ValueError(
            "a sequential comparison of returns needs their bounds (return_range=(low, "
            "high); imitrl compare --return-range LOW,HIGH, the least and most return an "
            "episode can have): its bets are on bounded outcomes"
        )
    check_replays(env, seed)
    lanes = lane_count(env)
    xa: list[float] = []
    xb: list[float] = []
    interval, stopped = (math.nan, math.nan), False
    wave = 0
    while len(xa) < episodes:
        n = min(lanes, episodes - len(xa))
        for spec, out in ((a, xa), (b, xb)):
            got = _wave(env, spec, n, seed + wave * lanes, success_fn, metric, max_steps)
            _check_outcomes(got, spec.name, len(out), seed, metric, return_range)
            out.extend(got)
        wave += 1
        if sequential:
            assert bounds is not None
            interval = betting_interval(_differences(xa, xb), alpha, bounds)
            if (interval[0] > 0 or interval[1] < 0) and len(xa) < episodes:
                stopped = True
                break
    d = _differences(xa, xb)
    if sequential:
        rule = "sequential: hedged betting confidence sequence (Waudby-Smith & Ramdas, JRSS-B 2024)"
    else:
        interval, rule = _fixed_interval(d, alpha, bounds)
    decision = (
        "a better" if interval[0] > 0 else "b better" if interval[1] < 0 else "no difference shown"
    )
    return Comparison(
        a=a.name, b=b.name, metric=metric, episodes=len(xa),
        mean_a=sum(xa) / len(xa), mean_b=sum(xb) / len(xb), difference=float(d.mean()),
        interval=(float(interval[0]), float(interval[1])), decision=decision, rule=rule,
        alpha=alpha, stopped_early=stopped,
    )  # fmt: skip


def _fixed_interval(
    d: torch.Tensor, alpha: float, bounds: tuple[float, float] | None
) -> tuple[tuple[float, float], str]:
    """A fixed comparison's interval of the mean difference, and its rule (module
    docstring): paired Student-t, or where every difference is the same the betting
    interval of the bounded outcomes (none without bounds)."""
    if bool((d == d[0]).all()):
        # a t-interval (or the sign-flip test's, used before) is then the point d[0],
        # which holds only for differences symmetric about their mean (a hostile review:
        # 0/1 outcomes tied in 20 of 20 pairs missed a true -0.05 in 36% of draws)
        if bounds is None:
            rule = "fixed: every difference equal, and returns without bounds allow any mean"
            return (-math.inf, math.inf), rule + " (give their bounds: --return-range)"
        rule = "fixed: hedged betting interval (every difference equal)"
        return betting_interval(d, alpha, bounds), rule
    _, lo, hi = t_interval(d.tolist(), 1 - alpha)
    return (lo, hi), "fixed: paired Student-t"


def _check_outcomes(
    values: list[float], side: str, first: int, seed: int, metric: str,
    return_range: tuple[float, float] | None,
) -> None:  # fmt: skip
    """ValueError naming the first of ``side``'s episodes ``first, first + 1, ...`` whose
    outcome is not finite, or (returns) outside ``return_range``."""
    for j, v in enumerate(values, start=first):
        if not math.isfinite(v):
            raise ValueError(
                f"{side}'s episode {j} (seed {seed + j}) has a {metric} of {v}: a comparison "
                "needs finite outcomes (does the policy act NaN?)"
            )
        if metric == "return" and return_range is not None:
            lo, hi = return_range
            if not lo <= v <= hi:
                raise ValueError(
                    f"{side}'s episode {j} (seed {seed + j}) returned {v:.6g}, outside the "
                    f"return range [{lo:g}, {hi:g}] (--return-range): give bounds that hold "
                    "every episode's return"
                )


def check_return_range(return_range: tuple[float, float]) -> None:
    """ValueError unless ``(low, high)`` are finite, ``low < high``, and twice the
    differences' span, ``4 (high - low)``, is a finite float (the bets map a difference
    ``d`` in ``[-span, span]`` through ``(d + span) / (2 span)``; a hostile review:
    ``0,1e308`` overflowed it to infinity and a sequential comparison decided for the wrong
    side)."""
    low, high = return_range
    if not (math.isfinite(low) and math.isfinite(high) and low < high):
        raise ValueError(f"the return range must be finite with low < high, got {low}, {high}")
    if not math.isfinite(4.0 * (high - low)):
        raise ValueError(
            f"the return range [{low:g}, {high:g}] is too wide for float64 arithmetic on "
            "paired differences: give the least and most return an episode can have"
        )


def _differences(xa: list[float], xb: list[float]) -> torch.Tensor:
    return torch.tensor(xa, dtype=torch.float64) - torch.tensor(xb, dtype=torch.float64)


def _success_fn(env: EnvBase):
    if isinstance(env, TabularEnv):
        return tabular_success(env)
    return reported_success if SUCCESS in env.observation_spec.keys() else None


def _wave(env, spec: PolicySpec, n: int, seed: int, success_fn, metric: str, max_steps):
    """``n`` episodes (one a lane) from the env seeded ``seed``: each one's outcome."""
    actor, exploration = rollout_policy(env, spec.policy, spec.exploration)
    summary = episode_returns(
        env, actor, n, exploration=exploration, max_steps=max_steps, seed=seed,
        success_fn=success_fn if metric == "success" else None,
    )  # fmt: skip
    if metric == "success":
        assert summary.success is not None
        return summary.success.double().tolist()
    return summary.returns.double().tolist()


def betting_interval(
    d: torch.Tensor, alpha: float, bounds: tuple[float, float]
) -> tuple[float, float]:
    """The ``1 - alpha`` hedged betting confidence sequence for the mean of ``d`` (paired
    differences of outcomes within ``bounds``), at its last element: the running
    intersection over every prefix, as Waudby-Smith and Ramdas (2024, Theorem 3 with
    their predictable plug-in bets) build it; valid at any stopping time."""
    span = bounds[1] - bounds[0]
    m = torch.linspace(0, 1, GRID, dtype=torch.float64)[1:-1]  # candidate means of y
    capital = log_capital(_unit(d, span)[None, :], m, alpha)[0]  # [n, G]
    kept = (capital < math.log(1 / alpha)).all(0)  # in every prefix's set
    kept_m = m[kept] if bool(kept.any()) else _unit(d, span).mean().reshape(1)
    # the grid leaves out 0 and 1 (the bets' caps divide by them): a set holding the
    # grid's first or last point reaches the bound (a hostile review: differences all
    # at +span, the truth, were left outside)
    low = 0.0 if bool(kept[0]) else float(kept_m.min())
    high = 1.0 if bool(kept[-1]) else float(kept_m.max())
    return _from_unit(low, span), _from_unit(high, span)


def log_capital(y: torch.Tensor, m: torch.Tensor, alpha: float) -> torch.Tensor:
    """``[K, n, G]`` log of the hedged capital (theta = 1/2) after each of ``n`` outcomes
    ``y [K, n]`` in [0, 1], betting against each candidate mean ``m [G]`` with the
    predictable plug-in bets of Waudby-Smith and Ramdas (2024): the test martingale of
    the hypothesis "the mean is m", which rejects it once it reaches ``1 / alpha``."""
    n = y.shape[1]
    i = torch.arange(1, n + 1, dtype=torch.float64)
    mu = (0.5 + torch.cumsum(y, 1)) / (i + 1)  # their regularised running mean ...
    var = (0.25 + torch.cumsum((y - mu) ** 2, 1)) / (i + 1)  # ... and variance
    prev = torch.cat([torch.full_like(var[:, :1], 0.25), var[:, :-1]], 1)  # predictable
    lam = torch.sqrt(2 * math.log(2 / alpha) / (prev * i * torch.log1p(i)))[:, :, None]
    up = torch.minimum(lam, BET_CAP / m)
    down = torch.minimum(lam, BET_CAP / (1 - m))
    gap = y[:, :, None] - m
    log_up = torch.cumsum(torch.log1p(up * gap), 1)
    log_down = torch.cumsum(torch.log1p(-down * gap), 1)
    return torch.logaddexp(log_up, log_down) - math.log(2)


def _unit(d: torch.Tensor, span: float) -> torch.Tensor:
    """Paired differences within ``[-span, span]`` (:func:`compare` refuses outcomes
    outside their range) mapped to [0, 1] (0 -> 1/2); the clamp only absorbs rounding."""
    return ((d + span) / (2 * span)).clamp(0, 1)


def _from_unit(v: float, span: float) -> float:
    return v * 2 * span - span
