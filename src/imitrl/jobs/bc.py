"""``imitrl bc``: behaviour cloning on expert demonstrations or a dataset, in one function.

``run_bc(BCJob(...)) -> dict`` is the whole job (tests and benchmarks call it
directly):

1. resolve every flag (env, expert, loss, dataset, logger): bad input fails here;
2. demonstrations: ``--demos`` greedy expert episodes on the env seeded ``--seed``,
   or the rows of ``--dataset``, into a ``DemonstrationBuffer``;
3. ``fit_bc`` the learner (``--steps`` Adam steps, minibatches of ``--batch-size``),
   its loss logged per step;
4. save the checkpoint (``config.json`` + ``learner.pt``), then evaluate the expert and
   the learner on the same ``--eval-episodes`` initial states (an evaluation that fails
   or is interrupted keeps the fitted learner: :mod:`imitrl.fs.run_folder`);
5. write ``results.json`` and ``curves.png``, and publish the run as ``--out``.

:func:`prepare`, :func:`demonstrations`, :func:`evaluate_learner` and :func:`finish`
are shared with ``imitrl dagger``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType
from torchrl.record.loggers import Logger

from imitrl.algorithms import BCConfig, fit_bc
from imitrl.algorithms.expert_plan import with_plans
from imitrl.data import DemonstrationBuffer
from imitrl.envs import make_env
from imitrl.jobs.checkpoint import save_checkpoint, save_run
from imitrl.jobs.configs import BCJob, GAILJob
from imitrl.jobs.curves import make_logger, plot_curves, scalars_dir
from imitrl.jobs.evaluate import evaluate_returns, format_return
from imitrl.jobs.ranks import evaluating, lead, rows_digest, run_folder
from imitrl.jobs.resolve import (
    choose_learner,
    dataset_format,
    expert_for_env,
    load_dataset,
    make_expert,
    no_expert_message,
    time_limit,
)
from imitrl.learners import Learner, TaskSpec, registry
from imitrl.policies import as_actor
from imitrl.policies.random_actions import RandomActions
from imitrl.runtime import rollout_episodes
from imitrl.system.ranks import check_same

__all__ = [
    "BCJob",
    "Setup",
    "at_random_level",
    "bc_config",
    "below_expert",
    "compounding_hint",
    "demonstrations",
    "evaluate_expert",
    "evaluate_learner",
    "evaluate_policy",
    "evaluate_random",
    "finish",
    "log_evaluation",
    "prepare",
    "report",
    "run_bc",
]

DETERMINISTIC = ExplorationType.DETERMINISTIC


@dataclass
class Setup:
    """Everything a job's flags name, resolved and checked."""

    env: EnvBase | None
    """plays the demonstrations (and DAgger's rounds): ``--num-envs`` lanes, seed
    ``--seed``; None for a run on a dataset alone (``--env none``: nothing is played or
    evaluated)"""
    limit: int | None
    """steps per episode (the time limit); None without an env"""
    expert: TensorDictModuleBase | None
    """writes ``expert_action``"""
    make_learner: Callable[[], Learner]
    """a fresh learner, same initialisation each call"""
    logger: Logger
    """the run's TorchRL logger"""
    loss: str
    """what ``--loss`` resolved to for the env (:func:`~imitrl.jobs.resolve.resolve_loss`:
    a registry entry, or ``for_env``): what the run records and a checkpoint rebuilds"""
    recipe: Callable[[BCConfig], BCConfig] | None
    """the loss's fit schedule, where its recipe has one (:func:`bc_config`)"""
    folder: Path
    """where the run writes until it finishes (staged beside ``--out``, which it then
    replaces: :mod:`imitrl.fs.run_folder`)"""
    task: TaskSpec
    """what the learner is built for: the env's specs, or (``--env none``) the dataset's
    observations and the range of its actions (:meth:`TaskSpec.from_rows`)"""
    rows: TensorDictBase | None = None
    """the dataset's rows when they were read to learn the task (``--env none``)"""

    def close(self) -> None:
        """Close the env and shut the logger down (its files closed); a second call does
        nothing."""
        if not getattr(self, "_closed", False):
            self._closed = True
            if self.env is not None:
                self.env.close()
            self.logger.shutdown()

    def playing(self) -> EnvBase:
        """The env, for a job that plays in it (DAgger, GAIL: their flags refuse ``--env
        none``)."""
        if self.env is None:
            raise ValueError("this job plays in an env: --env none is for imitrl bc --dataset")
        return self.env


def prepare(
    config: BCJob,
    name: str,
    folder: Path,
    *,
    keep_logs: bool = False,
    probabilistic: bool = False,
) -> Setup:
    """Resolve and check every flag of ``config`` before any work (ValueError otherwise);
    the run will write into ``folder`` (:func:`imitrl.fs.run_folder.claimed`'s).

    ``keep_logs``: append to the command's earlier CSV logs (a resumed run) instead of
    starting them afresh; ``probabilistic``: the job needs ``log pi`` and a value head
    (GAIL's and AIRL's PPO generator: ``--loss default`` resolves to a head with an action
    distribution, and the learner is built with ``value=True``)."""
    if config.env is None:  # BCJob's checks: a dataset, no expert
        return _prepare_offline(config, name, folder, keep_logs=keep_logs)
    env = make_env(
        config.env,
        seed=config.seed,
        num_envs=config.num_envs,
        max_episode_steps=config.max_episode_steps,
        env_kwargs=dict(config.env_kwargs),
    )
    limit = time_limit(config.env, config.max_episode_steps)
    expert = None
    expert_name = expert_for_env(config.expert, config.env)
    if expert_name is None and config.expert is not None and config.dataset is None:
        raise ValueError(no_expert_message(config.env))
    if expert_name is not None:
        expert = make_expert(
            expert_name, config.expert_kind, env_id=config.env, env=env,
            env_kwargs=dict(config.env_kwargs),
        )  # fmt: skip
    if config.dataset is not None:
        dataset_format(config.dataset)
    task = TaskSpec.from_env(env)
    learner = choose_learner(
        config.loss, task, hidden=config.hidden, lr=config.lr, seed=config.seed,
        device=config.device, probabilistic=probabilistic,
    )  # fmt: skip
    logger = make_logger(config.logger, folder, name, fresh=not keep_logs)
    return Setup(
        env, limit, expert, learner.make, logger, learner.loss, learner.recipe, folder, task
    )


def _prepare_offline(config: BCJob, name: str, folder: Path, *, keep_logs: bool) -> Setup:
    """A run on ``--dataset`` alone (``--env none``): the rows are read first, and the
    learner is built for their observations and the range of their actions."""
    assert config.dataset is not None  # BCJob's checks
    rows = load_dataset(config.dataset, None, config.dataset_frames)
    try:
        task = TaskSpec.from_rows(rows)
    except ValueError as err:  # the dataset's observations or actions: name it
        raise ValueError(f"--dataset {config.dataset}: {err}") from None
    learner = choose_learner(
        config.loss, task, hidden=config.hidden, lr=config.lr, seed=config.seed,
        device=config.device,
    )  # fmt: skip
    logger = make_logger(config.logger, folder, name, fresh=not keep_logs)
    return Setup(
        None, None, None, learner.make, logger, learner.loss, learner.recipe, folder, task, rows
    )


def demonstrations(
    config: BCJob, setup: Setup, plan_horizon: int | None = None, *, successors: bool = False
) -> DemonstrationBuffer:
    """The rows of ``--dataset``, or ``--demos`` greedy expert episodes, in a buffer
    (``plan_horizon``: with the expert's plans, :func:`~imitrl.algorithms.expert_plan.with_plans`,
    for ``imitrl dagger --chunk-labels plan``; ``successors``: each row's next observation
    kept, a dataset's as recorded (:func:`~imitrl.jobs.resolve.load_dataset`), an expert
    episode's as played, so an episode a time limit cut keeps its last transition)."""
    if setup.rows is not None:
        rows = setup.rows
    elif config.dataset is not None:
        from imitrl.datasets import EnvMismatchError  # needs the datasets extra

        try:
            rows = load_dataset(
                config.dataset, setup.env, config.dataset_frames, successors=successors
            )
        except EnvMismatchError as err:  # most often the wrong env: name the flag
            default = " (the default)" if config.env == type(config).env else ""
            raise ValueError(
                f"{err}; --env is {config.env}{default}: pass the env the dataset was recorded on"
            ) from None
    else:
        rows = rollout_episodes(  # greedy, whole episodes
            setup.playing(), setup.expert, config.demos, next_observation=successors
        )
    check_same(
        rows_digest(rows), "demonstrations (rows, sha256)"
    )  # --nproc: each rank reads its own
    buffer = DemonstrationBuffer(action_spec=setup.task.env_specs()[1])
    buffer.extend(rows if plan_horizon is None else with_plans(rows, plan_horizon))
    return buffer


def bc_config(config: BCJob, setup: Setup) -> BCConfig:
    """The behaviour-cloning fit the flags describe, on the loss's own schedule where its
    recipe has one (``setup.recipe``, the entry's ``LossEntry.recipe``: Diffusion
    Policy's warm-up and cosine decay); ``--batch-size`` is kept as given."""
    bc = config.fit()
    return bc if setup.recipe is None else setup.recipe(bc)


def evaluate_policy(
    config: BCJob, policy: TensorDictModuleBase, exploration: ExplorationType
) -> dict:
    """``policy``'s evaluation on the run's ``--eval-episodes`` initial states (seed
    ``--eval-seed``, the env as the flags make it): every policy of a run plays the same
    states (:func:`~imitrl.jobs.evaluate.evaluate_returns`)."""
    return evaluate_returns(
        config.played_env(),
        policy,
        exploration=exploration,
        episodes=config.eval_episodes,
        seed=config.eval_seed,
        max_episode_steps=config.max_episode_steps,
        env_kwargs=dict(config.env_kwargs),
        progress=config.progress,
    )


def evaluate_learner(config: BCJob, learner: Learner) -> dict:
    """The learner's evaluation, acting as it says (``learner.exploration``)."""
    return evaluate_policy(config, learner.policy, learner.exploration)


def evaluate_expert(config: BCJob, setup: Setup) -> dict | None:
    """The expert's greedy evaluation on the learner's initial states (None without one)."""
    if setup.expert is None:
        return None
    return evaluate_policy(config, as_actor(setup.expert), DETERMINISTIC)


def evaluate_random(config: BCJob, setup: Setup) -> dict:
    """Uniform random actions' evaluation on the learner's initial states
    (:class:`~imitrl.policies.random_actions.RandomActions`, seeded by ``--eval-seed``)."""
    actions = RandomActions(setup.task.env_specs()[1])
    return evaluate_policy(config, actions, ExplorationType.RANDOM)


def log_evaluation(logger: Logger, round_index: int, ev: dict, expert: dict | None) -> None:
    """``eval/return`` (and its interval) at step ``round_index``; the expert's at step 0;
    ``eval/success`` (and its interval, and the expert's) where the env reports success
    (Meta-World: a failing learner can return more than the expert, issue 44)."""
    logger.log_scalar("eval/return", ev["mean_return"], step=round_index)
    lo, hi = (math.nan if x is None else x for x in ev["return_ci"])  # None: one episode
    logger.log_scalar("eval/return_lo", lo, step=round_index)
    logger.log_scalar("eval/return_hi", hi, step=round_index)
    if ev.get("success_rate") is not None:
        logger.log_scalar("eval/success", ev["success_rate"], step=round_index)
        s_lo, s_hi = ev["success_ci"]
        logger.log_scalar("eval/success_lo", s_lo, step=round_index)
        logger.log_scalar("eval/success_hi", s_hi, step=round_index)
    if expert is not None:
        logger.log_scalar("eval/expert_return", expert["mean_return"], step=0)
        if expert.get("success_rate") is not None:
            logger.log_scalar("eval/expert_success", expert["success_rate"], step=0)


def finish(
    config: BCJob | GAILJob,
    name: str,
    learner: Learner,
    results: dict,
    setup: Setup,
    *,
    saved: bool = False,
) -> None:
    """Write results.json, the checkpoint (unless the job ``saved`` it when the fit
    ended: :func:`~imitrl.jobs.checkpoint.save_run`) and curves.png into the run's
    folder (they name their place in ``--out``, where the run is published); close the
    env and the logger."""
    setup.close()  # the logger's files complete before they are plotted
    curves = plot_curves(
        scalars_dir(setup.folder, name),
        setup.folder / "curves.png",
        title=f"imitrl {name} on {config.env or config.dataset} (loss {config.loss}, seed {config.seed})",
    )
    results["files"] = {
        "curves": str(config.out / curves.name),
        "logs": str(config.out / "logs"),
    }
    save_run(setup.folder, name, config, learner, results, saved=saved)


def run_bc(config: BCJob) -> dict:
    """Behaviour cloning as ``config`` says (module docstring); returns what results.json holds.

    ``--out`` follows :mod:`imitrl.fs.run_folder`'s rule: a previous run there is refused
    unless ``--overwrite``, and a second run writing it meanwhile is refused at once."""
    config = lead(config)  # as this rank runs it
    with run_folder(config) as folder:
        return _run_bc(config, folder)


def _run_bc(config: BCJob, folder: Path) -> dict:
    start = time.perf_counter()
    setup = prepare(config, "bc", folder)
    try:
        config = replace(config, loss=setup.loss)  # recorded as resolved: --loss default's entry
        buffer = demonstrations(config, setup)
        learner = setup.make_learner()
        fit = fit_bc(
            learner, buffer, bc_config(config, setup), progress=config.progress, logger=setup.logger
        )
        save_checkpoint(folder, "bc", config, learner)  # kept if the evaluation fails
        expert_ev = learner_ev = random_ev = None
        if setup.env is not None and evaluating():  # --env none: the dataset alone
            expert_ev = evaluate_expert(config, setup)
            learner_ev = evaluate_learner(config, learner)
            log_evaluation(setup.logger, 0, learner_ev, expert_ev)
            if below_expert(expert_ev, learner_ev):  # what acting at random scores there
                random_ev = evaluate_random(config, setup)
        results = {
            "command": "bc",
            "env": config.env,
            "learner_loss": setup.loss,
            "demonstrations": {
                "source": str(config.dataset) if config.dataset else f"expert {config.expert}",
                "episodes": buffer.num_episodes,
                "rows": len(buffer),
            },
            "final_loss": fit.final_loss,
            "expert": expert_ev,
            "learner": learner_ev,
            "random": random_ev,
            "seconds": time.perf_counter() - start,
        }
        finish(config, "bc", learner, results, setup, saved=True)
        return results
    finally:
        setup.close()  # the env and the logger, whatever happened


def report(results: dict) -> list[str]:
    """What ``imitrl bc`` prints."""
    demos = results["demonstrations"]
    lines = [
        f"demonstrations: {demos['episodes']} episodes, {demos['rows']} rows ({demos['source']})",
        f"final training loss: {results['final_loss']:.4g}",
    ]
    if results["expert"] is not None:
        lines.append(format_return("expert", results["expert"]))
    if results["learner"] is None:
        out = Path(results["files"]["curves"]).parent
        lines.append(
            f"learner: not evaluated (--env none); imitrl eval --checkpoint {out} --env ENV "
            "evaluates it in an env with the dataset's observations and actions"
        )
    else:
        lines.append(format_return("learner", results["learner"]))
        if results.get("random") is not None:
            lines.append(format_return("random actions", results["random"]))
        hint = compounding_hint(
            results["expert"], results["learner"], results.get("random"),
            chunked=_chunked(results["learner_loss"]),
        )  # fmt: skip
        if hint:
            lines.append(hint)
    lines.append(f"wrote {Path(results['files']['curves']).parent}")
    return lines


def below_expert(expert: dict | None, learner: dict | None) -> bool:
    """Whether the learner scores clearly below the expert on the same initial states
    (their 95% intervals apart; False without an expert, or with one episode)."""
    if expert is None or learner is None:
        return False
    if None in (*expert["return_ci"], *learner["return_ci"]):
        return False
    return learner["return_ci"][1] < expert["return_ci"][0]


def at_random_level(learner: dict, random: dict | None) -> bool:
    """Whether the learner scores no better than random actions (its 95% interval
    reaches theirs), on the same initial states."""
    if random is None or None in (*random["return_ci"], *learner["return_ci"]):
        return False
    return learner["return_ci"][0] <= random["return_ci"][1]


def compounding_hint(
    expert: dict | None, learner: dict, random: dict | None = None, *, chunked: bool = False
) -> str:
    """A line saying what to try when the cloned learner scores clearly below the expert
    on the same initial states (their 95% intervals apart), else ``""`` (issue 44:
    InvertedDoublePendulum's clone reached 1.3% of the expert, ACT and Diffusion Policy
    scored at random level on Pendulum, and nothing said why). ``random``: random
    actions' evaluation on the same states (:func:`evaluate_random`): a learner at their
    level has either not fitted (more steps) or left the expert's states at once, which
    DAgger mends (a newcomer's review: "DAgger does not mend" turned them from the fix
    that took InvertedPendulum from 6 to 1000 in one round); ``chunked``: the learner
    plays predicted chunks (its registry entry's ``horizon``), which can fail a task that
    needs feedback at every step however well it fits (ACT on Pendulum reproduces the
    expert's actions on its demonstration states, R^2 0.996 at 10,000 steps, and still
    scores below random actions)."""
    if not below_expert(expert, learner):
        return ""
    if at_random_level(learner, random):
        assert random is not None  # at_random_level
        head = (
            f"hint: the learner scores at the level of random actions (return "
            f"{random['mean_return']:.2f} on the same initial states). If its training "
            "loss (curves.png) is still high, it has not fitted the demonstrations: more "
            "--steps first. If the loss is low, it leaves the expert's states at once, "
            "which `imitrl dagger` with the same flags mends by labelling the states it "
            "visits. "
        )
        if chunked:
            return head + (
                "Check the fit (more --steps) and how it acts: it plays predicted chunks "
                "(act averages the last queries' predictions of each step, diffusion_unet "
                "plays 8 of 16 actions before it replans), which a task that needs feedback "
                "at every step can defeat however well it fits; compare an unchunked --loss"
            )
        return head + "More --demos or another --loss help either way"
    return (
        "hint: the learner scores below the expert. Cloning is trained on the expert's "
        "states only, and its errors take it to states the expert never showed (the "
        "compounding error of the FrozenLake study); `imitrl dagger` with the same flags "
        "relabels the learner's own states, and more --demos or --steps help a clone "
        "that has not fitted"
    )


def _chunked(loss: str) -> bool:
    """Whether registry entry ``loss`` plays predicted chunks (``for_env``: no)."""
    return loss in registry.names() and registry.get(loss).horizon is not None
