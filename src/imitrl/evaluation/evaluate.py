"""Monte Carlo evaluation with confidence intervals; exact values for tabular MDPs.

Every evaluation states its exploration type (``DETERMINISTIC``: the greedy action;
``RANDOM``: sampled). On a :class:`~imitrl.envs.TabularEnv` the exact finite-horizon
success probability and return of the same policy are reported next to the
estimates, so a Monte Carlo number can always be checked.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.envs.success import SUCCESS, reported_success
from imitrl.envs.tabular_env import TabularEnv
from imitrl.evaluation.statistics import t_interval
from imitrl.evaluation.tabular import exact_values
from imitrl.learners.learner import Learner
from imitrl.policies.experts import Expert
from imitrl.runtime.returns import SuccessFn, episode_returns
from imitrl.runtime.rollout import policy_errors_named, rollout_policy

__all__ = ["Evaluation", "evaluate", "mean_ci", "tabular_success", "wilson_interval"]


def _z(confidence: float) -> float:
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    return float(torch.special.ndtri(torch.tensor(0.5 + confidence / 2, dtype=torch.float64)))


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion."""
    if n <= 0:
        raise ValueError("need at least one trial")
    z = _z(confidence)
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    # the bounds at k = 0 and k = n are exactly 0 and 1; centre -+ half rounds to 2e-19 off
    lo = 0.0 if successes == 0 else max(0.0, centre - half)
    hi = 1.0 if successes == n else min(1.0, centre + half)
    return lo, hi


def mean_ci(x: torch.Tensor, confidence: float = 0.95) -> tuple[float, float, float]:
    """Mean and Student-t interval ``mean +- t_{(1+c)/2, n-1} * sd / sqrt(n)``.

    The t quantile keeps the coverage at small episode counts (a normal z covers 71%
    at n = 2, 94% at n = 16). One value gives NaN bounds: no interval exists.
    """
    x = x.double().reshape(-1)
    if x.numel() == 0:
        raise ValueError("need at least one value")
    _z(confidence)  # validates the level
    mean, lo, hi = t_interval(x.tolist(), confidence)
    return mean, lo, hi


@dataclass(frozen=True)
class Evaluation:
    """A Monte Carlo evaluation (and, on tabular MDPs, the exact values beside it)."""

    num_episodes: int
    exploration: str
    mean_return: float
    return_ci: tuple[float, float]
    mean_length: float
    success_rate: float | None = None
    success_ci: tuple[float, float] | None = None
    exact_success: float | None = None
    exact_return: float | None = None
    confidence: float = 0.95

    def summary(self) -> str:
        """One line: episodes, exploration, success and return with intervals and exact values."""
        parts = [f"{self.num_episodes} episodes ({self.exploration})"]
        if self.success_rate is not None:
            assert self.success_ci is not None  # evaluate() sets both or neither
            lo, hi = self.success_ci
            s = f"success {self.success_rate:.1%} [{lo:.1%}, {hi:.1%}]"
            if self.exact_success is not None:
                s += f" (exact {self.exact_success:.2%})"
            parts.append(s)
        lo, hi = self.return_ci
        r = f"return {self.mean_return:.3f} [{lo:.3f}, {hi:.3f}]"
        if self.exact_return is not None:
            r += f" (exact {self.exact_return:.4f})"
        parts.append(r)
        return ", ".join(parts)


def tabular_success(env: TabularEnv) -> SuccessFn:
    """Success on a :class:`~imitrl.envs.TabularEnv`: the episode ended in a goal state."""
    goal = env.mdp.goal

    def success(out) -> torch.Tensor:
        nxt = out.get(keys.NEXT)
        return goal[nxt.get(keys.OBSERVATION).reshape(-1)] & nxt.get(keys.TERMINATED).reshape(-1)

    return success


def evaluate(
    env: EnvBase,
    policy: Learner | Expert | TensorDictModuleBase,
    num_episodes: int,
    *,
    exploration: ExplorationType | None = None,
    max_steps: int | None = None,
    seed: int | None = None,
    success_fn: SuccessFn | None = None,
    confidence: float = 0.95,
    generator: torch.Generator | None = None,
    progress: bool = False,
) -> Evaluation:
    """Evaluate ``policy`` over ``num_episodes`` whole episodes.

    Args:
        env: any TorchRL env (batched envs play ``num_episodes / lanes`` episodes per lane).
        policy: a :class:`~imitrl.learners.Learner` (its ``policy`` acts), an
            :class:`~imitrl.policies.Expert` (drives the env, its labels cast to the
            env's action spec), or a module writing ``ACTION``.
        exploration: ``DETERMINISTIC`` (greedy) or ``RANDOM`` (sampled). None: the
            learner's ``exploration``, ``DETERMINISTIC`` for an expert; required for a
            bare policy module.
        max_steps: most steps one episode may take; None: the env's own time limit
            (gymnasium ``TimeLimit``, ``StepCounter``, ``TabularEnv.max_steps``),
            refused when the env has none.
        seed: seeds the env (``env.set_seed(seed)``) and, unless ``generator`` is
            given, the policy's sampling: two policies evaluated with one seed start
            from the same initial states, on envs of the same number of lanes (each lane
            is seeded on from ``seed``, so another number of lanes plays other episodes;
            ``imitrl.evaluation.compare`` seeds each episode itself).
        success_fn: end-of-episode success criterion; defaults to "entered a goal
            state" on a TabularEnv, the env's own ``("next", "success")`` where it
            reports one (``make_env``'s ``success``, on for Meta-World), none elsewhere.
        confidence: level of the intervals.
        generator: source of the policy's sampling in ``RANDOM`` mode (seed it for
            reproducible sampled evaluations); None: torch's global RNG (or ``seed``'s).
            A policy with its own generator (:class:`~imitrl.rng.SavedGenerator`: the
            flow and diffusion policies) draws from that one instead, which advances:
            evaluate it in :func:`~imitrl.rng.generators_kept` to replay its draws.
        progress: a progress bar over the episodes on stderr.
    """
    if num_episodes < 1:
        raise ValueError(f"num_episodes must be positive, got {num_episodes}")
    if isinstance(policy, Learner):
        policy.check_env(env)  # before the first step, naming both spaces
        exploration = policy.exploration if exploration is None else exploration
        policy = policy.policy
    actor, exploration = rollout_policy(env, policy, exploration)
    tabular = isinstance(env, TabularEnv)
    if success_fn is None and tabular:
        success_fn = tabular_success(env)
    elif success_fn is None and SUCCESS in env.observation_spec.keys():
        success_fn = reported_success
    with policy_errors_named(env, actor):
        summary = episode_returns(
            env,
            actor,
            num_episodes,
            exploration=exploration,
            max_steps=max_steps,
            seed=seed,
            success_fn=success_fn,
            generator=generator,
            progress=progress,
        )
    mean, lo, hi = mean_ci(summary.returns, confidence)
    result: dict[str, Any] = {
        "num_episodes": int(num_episodes),
        "exploration": str(exploration).split(".")[-1].lower(),
        "mean_return": mean,
        "return_ci": (lo, hi),
        "mean_length": float(summary.lengths.double().mean()),
        "confidence": confidence,
    }
    if summary.success is not None:
        k = int(summary.success.sum())
        result["success_rate"] = k / num_episodes
        result["success_ci"] = wilson_interval(k, num_episodes, confidence)
    if tabular and env.max_steps is not None:
        exact = exact_values(
            env.mdp,
            actor,
            exploration,
            env.max_steps,
            initial=env.start_distribution(num_episodes),
        )
        result["exact_success"], result["exact_return"] = exact["success"], exact["return"]
    return Evaluation(**result)
