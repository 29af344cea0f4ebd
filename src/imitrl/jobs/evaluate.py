"""``imitrl eval``: the mean return of a saved learner or of an expert, with its interval.

:func:`evaluate_returns` is the one place every job evaluates a policy: a fresh env
seeded ``eval_seed`` (lane ``i`` seeded ``eval_seed + i``, at most
:data:`EVAL_LANES` lanes), so the expert and every learner of a run, and ``imitrl
eval`` on the run's checkpoint with the same ``--eval-episodes`` / ``--eval-seed``,
play the same initial states and give the same digits.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from imitrl.limits import MAX_EPISODE_STEPS, MAX_EVAL_EPISODES, MAX_SEED, bounded, check_bounds

if TYPE_CHECKING:  # torch, TorchRL and the rest are imported where used: see imitrl.cli
    from tensordict.nn import TensorDictModuleBase
    from torchrl.envs.utils import ExplorationType

__all__ = [
    "EVAL_LANES",
    "EvalJob",
    "check_evaluation",
    "delayed",
    "evaluate_returns",
    "format_return",
    "report",
    "run_eval",
]

EVAL_LANES = 16
"""most env copies an evaluation steps together"""


def evaluate_returns(
    env_id: str,
    policy: TensorDictModuleBase,
    *,
    exploration: ExplorationType,
    episodes: int,
    seed: int,
    max_episode_steps: int | None,
    env_kwargs: dict | None = None,
    progress: bool = False,
) -> dict:
    """Mean return of ``policy`` (writes ``action``) over ``episodes`` episodes, 95% interval.

    Returns ``{"mean_return", "return_ci": [lo, hi], "mean_length", "episodes",
    "exploration", "seed"}`` (``[None, None]`` for one episode: no interval), and
    ``"success_rate"``, ``"success_ci"`` (Wilson, 95%) for an env that reports success
    (``make_env``'s ``success``: the Meta-World tasks).
    """
    import torch

    from imitrl.envs import make_env
    from imitrl.evaluation import evaluate
    from imitrl.jobs.resolve import time_limit

    lanes = min(episodes, EVAL_LANES)
    env = make_env(
        env_id,
        seed=seed,
        num_envs=lanes,
        max_episode_steps=max_episode_steps,
        env_kwargs=env_kwargs,
    )
    time_limit(env_id, max_episode_steps)  # an env without a time limit is refused up front
    try:
        ev = evaluate(
            env,
            policy,
            episodes,
            exploration=exploration,
            generator=torch.Generator().manual_seed(seed),  # sampled policies, reproducibly
            progress=progress,
        )
    finally:
        env.close()
    success = {}
    if ev.success_rate is not None:
        assert ev.success_ci is not None  # evaluate() sets both or neither
        success = {"success_rate": ev.success_rate, "success_ci": list(ev.success_ci)}
    return {
        **success,
        "mean_return": ev.mean_return,
        # one episode has no interval: None (JSON null), not NaN (no JSON value)
        "return_ci": [None if math.isnan(x) else x for x in ev.return_ci],
        "mean_length": ev.mean_length,
        "episodes": episodes,
        "exploration": ev.exploration,
        "seed": seed,
    }


def env_arguments(kwargs: dict | None) -> str:
    """`` (name=value, ...)``: the env's arguments as a report names them ('' for none)."""
    return f" ({', '.join(f'{k}={v}' for k, v in kwargs.items())})" if kwargs else ""


def check_evaluation(ev: object, where: str) -> None:
    """ValueError (naming ``where``) unless ``ev`` is an evaluation as
    :func:`evaluate_returns` returns it, as far as a report reads it (a saved one may
    have been edited)."""
    ok = isinstance(ev, dict) and all(
        (
            _real(ev.get("mean_return")) and _real(ev.get("mean_length")),
            type(ev.get("episodes")) is int and ev["episodes"] >= 1,
            isinstance(ev.get("exploration"), str),
            _interval(ev.get("return_ci"), none=True),
            ev.get("success_rate") is None
            or (_real(ev["success_rate"]) and _interval(ev.get("success_ci"), none=False)),
        )
    )
    if not ok:
        raise ValueError(f"{where}: the saved evaluation is not one imitrl wrote: {ev!r}"[:400])


def _real(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _interval(value: object, *, none: bool) -> bool:
    """``[lo, hi]`` of finite numbers (or, with ``none``, ``[None, None]``)."""
    if not (isinstance(value, list) and len(value) == 2):
        return False
    return all(map(_real, value)) or (none and value == [None, None])


def format_return(name: str, ev: dict) -> str:
    """One report line: ``name: return m [lo, hi] over n episodes (exploration)``."""
    lo, hi = ev["return_ci"]
    interval = "[no interval]" if lo is None else f"[{lo:.2f}, {hi:.2f}]"
    success = ""
    if ev.get("success_rate") is not None:
        s_lo, s_hi = ev["success_ci"]
        success = f"success {ev['success_rate']:.0%} [{s_lo:.0%}, {s_hi:.0%}], "
    return (
        f"{name}: {success}return {ev['mean_return']:.2f} {interval} over "
        f"{ev['episodes']} episodes ({ev['exploration']}), mean length {ev['mean_length']:.1f}"
    )


@dataclass(frozen=True)
class EvalJob:
    """Evaluate a saved learner (``--checkpoint``) or an expert (``--expert``)."""

    checkpoint: Path | None = None
    """the --out directory of imitrl bc, dagger, gail or airl (config.json + learner.pt)"""
    expert: str | None = None
    """evaluate this expert instead: auto (the built-in expert of --env), a built-in name
    (cartpole, mountaincar, acrobot, pendulum, inverted_pendulum, inverted_double_pendulum,
    metaworld, value_iteration) or module:function"""
    expert_kind: str = "builder"
    """what the function of --expert module:function is: builder (returns an expert
    module writing expert_action) or callable (a batched obs -> action function)"""
    env: str | None = None
    """gymnasium id or module:Env-v0; none = the checkpoint's env (a checkpoint naming
    module:Env-v0 is refused: imitrl imports only the modules you name here)"""
    max_episode_steps: int | None = bounded(None, 1, MAX_EPISODE_STEPS, none_ok=True)
    """override the env's time limit; none = the checkpoint's (or the env's own limit)"""
    env_kwargs: tuple[tuple[str, object], ...] = field(
        default=(), metadata={"repeat": "--env-kwarg"}
    )
    """a keyword argument of the env's constructor, name=value; none given = the
    checkpoint's"""
    loss: str | None = None
    """the checkpoint's loss when it is your own, module:name (importing module registers
    it): imitrl imports only the modules you name here; none = a registry loss"""
    eval_episodes: int | None = bounded(None, 1, MAX_EVAL_EPISODES, none_ok=True)
    """evaluation episodes; none = the checkpoint's run's own (so every job's numbers
    reproduce: 10 for bc/dagger, 20 for gail/airl by default), 10 for an expert"""
    eval_seed: int | None = bounded(None, 0, MAX_SEED, none_ok=True)
    """seed of the evaluation env; none = the checkpoint's run's own, 10000 for an expert"""
    out: Path | None = None
    """also write eval.json into this directory; none = print only"""
    overwrite: bool = False
    """replace an eval.json already in --out (without it, one there is refused)"""
    progress: bool = True
    """a progress bar over the evaluation episodes on stderr"""
    device: str = "auto"
    """where the saved learner computes: auto, cpu, cuda or cuda:N (a checkpoint saved
    on any device loads on any other)"""
    inference_delay: int = bounded(0, 0, MAX_EPISODE_STEPS)
    """a chunked learner's queries answered this many control steps late, simulated in the
    rollout loop (imitrl.policies.latency); 0 = at once"""
    chunk_mode: str | None = None
    """how a chunked learner executes its chunks under --inference-delay: sync (holds still
    while it waits), naive (asynchronous: the next chunk takes over at its action d), ensemble
    (ACT's temporal ensembling of the chunks that have arrived) or rtc (real-time chunking:
    the next chunk inpainted from the current one; flow and diffusion learners); none = its
    own (its receding horizon as naive, or its ensembling), not delayed when the delay is 0"""

    def __post_init__(self) -> None:
        from imitrl.jobs.resolve import EXPERT_KINDS

        if (self.checkpoint is None) == (self.expert is None):
            raise ValueError("give exactly one of --checkpoint or --expert")
        if self.expert is not None and self.env is None:
            raise ValueError("--expert needs --env (the env to evaluate it on)")
        if self.expert_kind not in EXPERT_KINDS:
            raise ValueError(
                f"--expert-kind must be one of {EXPERT_KINDS}, got {self.expert_kind!r}"
            )
        check_bounds(self)
        from imitrl.jobs.configs import _check_device
        from imitrl.policies.latency import MODES

        if self.chunk_mode is not None and self.chunk_mode not in MODES:
            raise ValueError(
                f"--chunk-mode must be one of {', '.join(MODES)}, got {self.chunk_mode!r}"
            )
        if (self.inference_delay or self.chunk_mode) and self.checkpoint is None:
            raise ValueError(
                "--inference-delay and --chunk-mode execute a chunked learner's chunks: give "
                "--checkpoint"
            )

        _check_device(self.device)
        if self.out is not None and (Path(self.out) / "eval.json").exists() and not self.overwrite:
            raise ValueError(
                f"--out {self.out} holds an eval.json: pass --overwrite to replace it, or "
                "give another --out"
            )


def _import_loss(named: str, saved: str, checkpoint: Path) -> None:
    """Import the module of ``--loss module:name``, which must be the checkpoint's loss."""
    from imitrl.jobs.resolve import registered_loss

    if named != saved:
        raise ValueError(f"--loss {named}: {checkpoint} was trained with loss {saved!r}")
    registered_loss(named)


def run_eval(config: EvalJob) -> dict:
    """Evaluate what ``config`` names; returns ``{"policy", "env", "evaluation"}``."""
    from torchrl.envs.utils import ExplorationType

    from imitrl.envs import make_env
    from imitrl.jobs.checkpoint import (
        build_learner,
        checkpoint_env,
        checkpoint_env_kwargs,
        read_checkpoint,
    )
    from imitrl.jobs.configs import RunFlags
    from imitrl.jobs.resolve import played_limit
    from imitrl.policies import as_actor

    episodes, seed = config.eval_episodes, config.eval_seed
    if config.checkpoint is not None:
        # config.json and learner.pt of one checkpoint, even while a writer replaces it
        saved = read_checkpoint(config.checkpoint)
        if config.loss is not None:
            _import_loss(config.loss, saved.config["loss"], config.checkpoint)
        # the run's own evaluation unless told otherwise: its numbers reproduce
        episodes = episodes or saved.config.get("eval_episodes")
        seed = saved.config.get("eval_seed") if seed is None else seed
        env_id = config.env or checkpoint_env(config.checkpoint, saved.config)
        steps = config.max_episode_steps or saved.config.get("max_episode_steps")
        kwargs = dict(config.env_kwargs)  # over the run's own, for the run's own env
        if env_id == saved.config.get("env"):  # (a hostile review: one --env-kwarg
            # dropped the run's map_name, and another lake was played without a word)
            kwargs = checkpoint_env_kwargs(saved.config, saved.path, given=kwargs)
        # the learner's shapes
        specs = make_env(env_id, seed=0, max_episode_steps=steps, env_kwargs=kwargs)
        try:
            learner = build_learner(saved, specs, device=config.device)
            policy = delayed(learner.policy, config, specs.action_spec_unbatched)
        finally:
            specs.close()
        exploration, name = learner.exploration, "learner"
    else:
        # EvalJob.__post_init__: --expert when no --checkpoint, with --env
        assert config.expert is not None and config.env is not None
        env_id, steps, kwargs = config.env, config.max_episode_steps, dict(config.env_kwargs)
        # the expert reads the env's specs, as bc's and dagger's do: a callable learns the
        # shape of one observation, Meta-World's finds its state under LeRobot's obs types
        expert = _expert(config, env_id, steps, kwargs)
        policy, exploration = as_actor(expert), ExplorationType.DETERMINISTIC
        name = f"expert {config.expert}"
    ev = evaluate_returns(
        env_id,
        policy,
        exploration=exploration,
        # an expert (or a checkpoint that recorded none): imitrl bc's evaluation
        episodes=RunFlags.eval_episodes if episodes is None else int(episodes),
        seed=RunFlags.eval_seed if seed is None else int(seed),
        max_episode_steps=steps,
        env_kwargs=kwargs,
        progress=config.progress,
    )
    results = {
        "policy": name,
        "checkpoint": None if config.checkpoint is None else str(config.checkpoint),
        "env": env_id,
        "env_kwargs": kwargs,
        "max_episode_steps": played_limit(env_id, steps),
        "evaluation": ev,
    }
    if config.inference_delay or config.chunk_mode:
        results["latency"] = {"inference_delay": config.inference_delay, "mode": policy.mode}
    if config.out is not None:  # written whole, never through a link (imitrl.fs.files)
        from imitrl.fs.files import make_folder, replace_file
        from imitrl.fs.write_errors import reporting_disk_full

        with reporting_disk_full(config.out, what="eval.json", left="--out is as it was"):
            make_folder(config.out)
            replace_file(config.out / "eval.json", json.dumps(results, indent=2) + "\n")
    return results


def _expert(config: EvalJob, env_id: str, steps: int | None, kwargs: dict) -> TensorDictModuleBase:
    """``--expert`` for the env (``auto``: the built-in expert of ``--env``, as imitrl bc
    and compare resolve it), built reading the env's specs as bc's and dagger's is."""
    from imitrl.envs import make_env
    from imitrl.jobs.resolve import resolved_expert

    assert config.expert is not None  # EvalJob.__post_init__
    specs = make_env(env_id, seed=0, max_episode_steps=steps, env_kwargs=kwargs)  # the id first
    try:
        return resolved_expert(
            config.expert, config.expert_kind, env_id=env_id, env=specs, env_kwargs=kwargs
        )
    finally:
        specs.close()


def delayed(policy: TensorDictModuleBase, config: EvalJob, spec) -> TensorDictModuleBase:
    """``policy`` as ``--inference-delay`` and ``--chunk-mode`` say: a chunked learner's
    network under the delay (:class:`~imitrl.policies.latency.DelayedChunkPolicy`, holding
    still with :func:`~imitrl.policies.latency.hold_action` of ``spec``), else ``policy``."""
    from imitrl.policies.chunking import ChunkedPolicy
    from imitrl.policies.latency import DelayedChunkPolicy, Latency, hold_action

    if not (config.inference_delay or config.chunk_mode):
        return policy
    if not isinstance(policy, ChunkedPolicy):
        raise ValueError(
            f"--inference-delay and --chunk-mode execute action chunks; {config.checkpoint}'s "
            "learner acts one action per query (its loss predicts no chunk): train a "
            "chunked loss (flow_chunk, mse_chunk, act, ...)"
        )
    mode = config.chunk_mode or ("ensemble" if policy.execution.ensemble is not None else "naive")
    latency = Latency(config.inference_delay, mode)
    return DelayedChunkPolicy.wrapping(policy, latency, hold=hold_action(spec))


def report(results: dict) -> list[str]:
    """What ``imitrl eval`` prints."""
    line = format_return(
        f"{results['policy']} on {results['env']}{env_arguments(results.get('env_kwargs'))}",
        results["evaluation"],
    )
    if "latency" in results:
        lat = results["latency"]
        line += f"; inference delay {lat['inference_delay']} steps, {lat['mode']} execution"
    return [line]
