"""``imitrl compare``: two policies on paired episodes of one env, in one function.

``run_compare(CompareJob(...)) -> dict``: each side (``--a``, ``--b``) is a checkpoint
(the ``--out`` of imitrl bc, dagger, gail or airl), ``expert`` (``--expert``: the env's
built-in expert, or one of yours) or ``random`` (uniform random actions); both play
episode ``j`` from the env seeded ``--seed + j`` (:mod:`imitrl.evaluation.compare`), and
the paired differences of their success (or return) give the mean difference, its
interval and the decision, after ``--episodes`` pairs or, with ``--sequential``, as soon
as the anytime-valid interval excludes 0. Bad input (a side that does not fit the env,
an env that does not replay its seeds, ``--alpha`` outside (0, 1), fewer than 2
episodes) is one line, and nothing is written.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from imitrl.limits import MAX_EPISODE_STEPS, MAX_EVAL_EPISODES, MAX_SEED, MIN_ALPHA, bounded

__all__ = ["CompareJob", "report", "run_compare"]

SIDES = ("expert", "random")
"""what ``--a`` / ``--b`` may name besides a checkpoint folder"""


@dataclass(frozen=True)
class CompareJob:
    """Compare two policies on paired episodes of one env."""

    a: str
    """a checkpoint folder (imitrl bc/dagger/gail/airl --out), expert (the env's built-in
    expert) or random (uniform random actions)"""
    b: str
    """the other side, as --a"""
    env: str | None = None
    """gymnasium id (metaworld/<task>-v3 included); none = the checkpoints' env (both
    must name the same)"""
    episodes: int = bounded(100, 2, MAX_EVAL_EPISODES)
    """pairs of episodes: all of them with a fixed comparison, the most a --sequential
    one plays"""
    sequential: bool = False
    """stop as soon as the anytime-valid confidence sequence of the difference excludes 0
    (Waudby-Smith & Ramdas 2024); its error rate is at most --alpha whenever it stops"""
    alpha: float = bounded(0.05, MIN_ALPHA, 1, integer=False, high_open=True)
    """error rate of the decision (the intervals are at 1 - alpha)"""
    metric: str = "auto"
    """success, return, or auto (success where the env reports it, return elsewhere)"""
    return_range: tuple[float, ...] | None = None
    """low,high bounds of an episode's return (a --sequential comparison of returns needs
    them); a negative low is written with an equals sign, --return-range=-1700,0"""
    seed: int = bounded(10_000, 0, MAX_SEED)
    """episode j of both sides starts from the env seeded seed + j"""
    max_episode_steps: int | None = bounded(None, 1, MAX_EPISODE_STEPS, none_ok=True)
    """override the env's time limit; none = the checkpoints' (which must agree), or the
    env's own"""
    env_kwargs: tuple[tuple[str, object], ...] = field(
        default=(), metadata={"repeat": "--env-kwarg"}
    )
    """a keyword argument of the env's constructor, name=value"""
    loss: str | None = None
    """a checkpoint side's loss when it is your own, module:name (importing module
    registers it), as imitrl eval --loss: imitrl imports only the modules you name here;
    none = registry losses"""
    expert: str = "auto"
    """the policy of the side named expert: auto = the built-in expert of --env (as imitrl
    bc --expert auto); a built-in name; or module:function (imitrl imports the module
    you name here)"""
    expert_kind: str = "builder"
    """what the function of --expert module:function is: builder (function() returns an
    expert module writing expert_action) or callable (function(obs [N, d]) -> action,
    batched)"""
    out: Path | None = None
    """also write compare.json into this directory; none = print only"""

    def __post_init__(self) -> None:
        from imitrl.limits import check_bounds

        check_bounds(self)
        if self.metric not in ("auto", "success", "return"):
            raise ValueError(f"--metric must be auto, success or return, got {self.metric!r}")
        if self.return_range is not None:
            from imitrl.evaluation.compare import check_return_range

            if len(self.return_range) != 2:
                raise ValueError(f"--return-range must be low,high, got {self.return_range}")
            low, high = self.return_range
            try:
                check_return_range((low, high))
            except ValueError as err:
                raise ValueError(f"--return-range {low:g},{high:g}: {err}") from None
        for flag, side in (("--a", self.a), ("--b", self.b)):
            if side not in SIDES and not (Path(side) / "config.json").is_file():
                raise ValueError(
                    f"{flag} {side}: not a checkpoint folder (no config.json), expert or random"
                )
        if self.env is None and self.a in SIDES and self.b in SIDES:  # no checkpoint names one
            raise ValueError("--env names the env for expert or random")
        from imitrl.jobs.names import EXPERT_KINDS

        if self.expert_kind not in EXPERT_KINDS:
            raise ValueError(
                f"--expert-kind must be one of {EXPERT_KINDS}, got {self.expert_kind!r}"
            )
        if self.expert != "auto" and "expert" not in (self.a, self.b):
            raise ValueError(
                f"--expert {self.expert} names the side expert: pass --a or --b expert"
            )
        if self.loss is not None and ":" not in self.loss:
            raise ValueError(f"--loss {self.loss}: name your own loss, module:name")
        if self.out is not None and (Path(self.out) / "compare.json").exists():
            raise ValueError(f"--out {self.out} holds a compare.json: give another --out")


def run_compare(config: CompareJob) -> dict:
    """Compare as ``config`` says (module docstring); returns what compare.json holds."""
    from imitrl.envs import make_env
    from imitrl.evaluation.compare import compare
    from imitrl.jobs.resolve import played_limit, time_limit

    env_id, steps, kwargs = _env_of(config)
    time_limit(env_id, steps)  # an env registered without one: --max-episode-steps, named
    env = make_env(env_id, seed=config.seed, max_episode_steps=steps, env_kwargs=kwargs)
    try:
        a = _side(config.a, "--a", env, env_id, config, kwargs)
        b = _side(config.b, "--b", env, env_id, config, kwargs)
        _check_loss_named(config)
        metric = None if config.metric == "auto" else config.metric
        bounds = config.return_range  # low, high (CompareJob's check)
        result = compare(
            env, a, b, config.episodes, seed=config.seed, alpha=config.alpha,
            sequential=config.sequential, metric=metric,
            return_range=None if bounds is None else (float(bounds[0]), float(bounds[1])),
            max_steps=steps,
        )  # fmt: skip
    finally:
        env.close()
    results = {
        "env": env_id,
        "env_kwargs": kwargs,
        "seed": config.seed,
        "max_episode_steps": played_limit(env_id, steps),
        "comparison": result.as_dict(),
    }
    if config.out is not None:  # written whole, never through a link (imitrl.fs.files)
        from imitrl.fs.files import make_folder, replace_file
        from imitrl.fs.write_errors import reporting_disk_full

        with reporting_disk_full(config.out, what="compare.json", left="--out is as it was"):
            make_folder(config.out)
            replace_file(config.out / "compare.json", json.dumps(results, indent=2) + "\n")
    return results


def _env_of(config: CompareJob) -> tuple[str, int | None, dict]:
    """The env both sides play: ``--env``, or the checkpoints' (the same one)."""
    from imitrl.jobs.checkpoint import checkpoint_env, checkpoint_env_kwargs, read_config

    saved = {s: read_config(Path(s)) for s in (config.a, config.b) if s not in SIDES}
    # --env names the env: a checkpoint of a dataset alone (env None) or of an env whose
    # id would import code is played there (as imitrl eval --env does)
    envs = {s: config.env if config.env else checkpoint_env(Path(s), c) for s, c in saved.items()}
    if config.env is None and len(set(envs.values())) > 1:
        raise ValueError(
            "the checkpoints were trained on different envs ("
            + ", ".join(f"{s}: {e}" for s, e in envs.items())
            + "): name the one to compare them on with --env"
        )
    env_id = config.env or next(iter(envs.values()))
    steps = config.max_episode_steps
    if steps is None:  # the checkpoints' own, which must agree: --a and --b play alike
        limits = {s: c.get("max_episode_steps") for s, c in saved.items()}
        if len(set(limits.values())) > 1:
            raise ValueError(
                "the checkpoints were trained with different time limits ("
                + ", ".join(f"{s}: {'the env' + chr(39) + 's own' if v is None else v}"
                            for s, v in limits.items())
                + "): name the one to compare them with, --max-episode-steps N"
            )  # fmt: skip
        steps = next(iter(limits.values()), None)
    given = dict(config.env_kwargs)
    # each checkpoint's env arguments, where it is played in its own env, under --env-kwarg's
    each = {s: checkpoint_env_kwargs(c, s, given) for s, c in saved.items() if envs[s] == env_id}
    if len({json.dumps(k, sort_keys=True) for k in each.values()}) > 1:
        raise ValueError(
            "the checkpoints were trained with different env arguments ("
            + ", ".join(f"{s}: {k}" for s, k in each.items())
            + "): name the ones to compare them with, --env-kwarg NAME=VALUE (each "
            "overrides the checkpoints' own)"
        )
    return env_id, steps, next(iter(each.values()), given)


def _check_loss_named(config: CompareJob) -> None:
    """``--loss`` must be the loss of a checkpoint side (it was imported for it)."""
    from imitrl.jobs.checkpoint import read_config

    if config.loss is None:
        return
    saved = {read_config(Path(s))["loss"] for s in (config.a, config.b) if s not in SIDES}
    if config.loss not in saved:
        raise ValueError(f"--loss {config.loss}: neither checkpoint was trained with it")


def _side(side: str, flag: str, env, env_id: str, config: CompareJob, kwargs: dict):
    """A :class:`~imitrl.evaluation.compare.PolicySpec` of ``side`` on ``env`` (made as
    ``env_id`` with ``kwargs``)."""
    from torchrl.envs.utils import ExplorationType

    from imitrl.evaluation.compare import PolicySpec
    from imitrl.jobs.checkpoint import build_learner, read_checkpoint
    from imitrl.jobs.resolve import resolved_expert
    from imitrl.policies import as_actor
    from imitrl.policies.random_actions import RandomActions

    if side == "expert":
        expert = resolved_expert(
            config.expert, config.expert_kind, env_id=env_id, env=env, env_kwargs=kwargs,
            where=f"{flag} expert: ",
        )  # fmt: skip
        return PolicySpec(as_actor(expert), ExplorationType.DETERMINISTIC, "expert")
    if side == "random":
        return PolicySpec(
            RandomActions(env.action_spec_unbatched), ExplorationType.RANDOM, "random"
        )
    saved = read_checkpoint(Path(side))
    loss = config.loss
    if loss is not None and saved.config["loss"] == loss:  # a module the user named
        from imitrl.jobs.resolve import registered_loss

        registered_loss(loss)
    try:
        learner = build_learner(saved, env)
        learner.check_env(env)
    except ValueError as err:
        trained = saved.config.get("env")
        if trained == env_id:  # its own env: the checkpoint itself is at fault (NaN weights)
            raise ValueError(f"{flag} {side}: {err}") from None
        raise ValueError(
            f"{flag} {side} (trained on {trained}) does not fit {env_id}'s observations and "
            f"actions: {err}"
        ) from None
    return PolicySpec(learner.policy, learner.exploration, str(side))


def report(results: dict) -> list[str]:
    """What ``imitrl compare`` prints."""
    from imitrl.jobs.evaluate import env_arguments

    c = results["comparison"]
    lo, hi = (-math.inf if c["interval"][0] is None else c["interval"][0],
              math.inf if c["interval"][1] is None else c["interval"][1])  # fmt: skip
    level = f"{100 * (1 - c['alpha']):.10g}"
    limit = results.get("max_episode_steps")
    steps = "" if limit is None else f" of at most {limit} steps"
    return [
        f"{c['a']} vs {c['b']} on {results['env']}{env_arguments(results.get('env_kwargs'))}: "
        f"{c['episodes']} paired episodes{steps} "
        f"(seeds {results['seed']}..{results['seed'] + c['episodes'] - 1})",
        f"{c['metric']}: a {c['mean_a']:.4g}, b {c['mean_b']:.4g}; difference a - b "
        f"{c['difference']:+.4g}, {level}% interval [{lo:+.4g}, {hi:+.4g}]",
        f"decision: {c['decision']} ({c['rule']}"
        + (", stopped early" if c["stopped_early"] else "")
        + ")",
    ]
