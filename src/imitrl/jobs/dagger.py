"""``imitrl dagger``: DAgger from the same demonstrations as ``imitrl bc``, in one function.

``run_dagger(DAggerJob(...)) -> dict``: steps 1-2 of ``imitrl bc`` (resolve the
flags, the demonstrations), then :func:`imitrl.algorithms.dagger`: round 0 is BC on
the demonstrations; after each fit the learner is evaluated (logged as
``eval/return`` at step = round) and, but after the last, rolls
``--episodes-per-round`` episodes on the env (the expert's action executed with
probability ``--beta``), every visited state labelled by the expert and added to
the buffer. ``--save-lerobot FPS`` writes the buffer after each fit as a LeRobot v3.0
dataset in LeRobot's DAgger schema, ``OUT/lerobot`` (:func:`save_rounds`); a
``--dataset`` of earlier rounds (one it wrote) is continued: the new rounds come after.
The last round's learner is saved as the checkpoint. After every round
the whole run is checkpointed in ``OUT/run`` (:func:`imitrl.algorithms.dagger`'s
``checkpoint_dir``); ``--resume`` continues an interrupted run from there.

``--workers N`` plays the relabel rounds on N Ray workers
(:class:`~imitrl.algorithms.ray_source.RaySource`: one env and the expert per worker,
the learner's weights sent once per round; needs ``pip install 'imitrl[distributed]'``),
on a local Ray instance or on the cluster at ``--address``. The rows then depend on
``--seed`` and ``--workers`` (not on ``--num-envs``, which still sets the lanes of the
demonstrations); the evaluation stays in this process, so its numbers compare with
``imitrl eval``. With ``--nproc`` too, rank 0 alone holds the workers and every rank
gets each round's rows (:class:`~imitrl.algorithms.lead_source.LeadSource`): the rows of
one process with the same ``--workers``, fitted data-parallel.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from pathlib import Path

import torch
from torchrl.record.loggers import Logger

from imitrl.algorithms import Constant, DAggerConfig, EnvSource, Exponential, dagger
from imitrl.algorithms.beta_schedules import BetaSchedule
from imitrl.algorithms.lead_source import LeadSource
from imitrl.algorithms.ray_source import RaySource
from imitrl.data.provenance import NO_BETA
from imitrl.envs import make_env
from imitrl.jobs.bc import (
    Setup,
    bc_config,
    demonstrations,
    evaluate_expert,
    evaluate_learner,
    finish,
    log_evaluation,
    prepare,
)
from imitrl.jobs.checkpoint import WEIGHTS_FILE, save_checkpoint
from imitrl.jobs.configs import DAggerJob
from imitrl.jobs.curves import rebuild_tensorboard, trim_scalars
from imitrl.jobs.evaluate import check_evaluation, format_return
from imitrl.jobs.ranks import RUN_CHECKPOINT, evaluating, lead, run_folder
from imitrl.jobs.resolve import no_expert_message
from imitrl.learners import Learner
from imitrl.policies.gate import ExpertGate
from imitrl.system.ranks import rank_and_world

__all__ = ["LEROBOT_DIR", "DAggerJob", "beta_schedule", "report", "run_dagger", "save_rounds"]

LEROBOT_DIR = "lerobot"
"""where ``--save-lerobot`` writes the rounds in ``--out``"""


def run_dagger(config: DAggerJob) -> dict:
    """DAgger as ``config`` says (module docstring); returns what results.json holds.

    ``--out`` follows :mod:`imitrl.fs.run_folder`'s rule: a previous run there is refused
    unless ``--overwrite`` or ``--resume``, and a second run writing it meanwhile is
    refused at once."""
    config = lead(config)  # as this rank runs it
    with run_folder(config, resume=config.resume) as folder:
        return _run_dagger(config, folder)


def _run_dagger(config: DAggerJob, folder: Path) -> dict:
    start = time.perf_counter()
    checkpoint = folder / RUN_CHECKPOINT
    setup = prepare(config, "dagger", folder, keep_logs=config.resume)
    try:
        config = dataclasses.replace(config, loss=setup.loss)  # recorded as resolved
        if setup.expert is None:  # --expert auto with a --dataset, on an env without one
            raise ValueError(no_expert_message(config.played_env()))
        if config.workers is not None and config.address is not None and evaluating():
            from imitrl.algorithms.ray_setup import check_address

            check_address(config.address)  # before the demonstrations and the first fit
        buffer = demonstrations(config, setup, plan_horizon=_plan_horizon(config, setup))
        demo_rows, demo_episodes = len(buffer), buffer.num_episodes
        demo_last = max(buffer.rounds())  # a dataset of earlier rounds: this run's come after
        expert_ev = evaluate_expert(config, setup) if evaluating() else None

        def on_fit(round_index: int, learner: Learner) -> dict:
            if not evaluating():  # rank 0 evaluates (--nproc) and writes
                return {}
            # the round's learner as fitted, before its evaluation draws from a sampling
            # policy's generator: the learner.pt imitrl eval replays it from, kept by a kill
            save_checkpoint(folder, "dagger", config, learner)
            if config.save_lerobot is not None:  # every round so far, before anything else
                save_rounds(config, buffer, folder / LEROBOT_DIR, demo_last)
            ev = evaluate_learner(config, learner)
            log_evaluation(setup.logger, round_index, ev, expert_ev if round_index == 0 else None)
            return ev  # kept in the round's record, and so in the checkpoint

        source = episode_source(config, setup)
        resumed = functools.partial(_resumed, folder, setup.logger) if evaluating() else None
        try:
            result = dagger(
                source,
                setup.expert,
                setup.make_learner,
                buffer,
                _dagger_config(config, setup),
                on_fit=on_fit,
                progress=config.progress,
                logger=setup.logger,
                checkpoint_dir=checkpoint,
                resume=config.resume,
                on_resume=resumed,
            )
        finally:
            if isinstance(source, RaySource | LeadSource):
                source.close()  # the Ray workers, and Ray where the source started it
        results = _results(config, setup, result, (demo_episodes, demo_rows), expert_ev)
        results["seconds"] = time.perf_counter() - start
        # the last round's learner.pt, as on_fit saved it (here or before a kill and --resume)
        saved = evaluating() and (folder / WEIGHTS_FILE).is_file()
        finish(config, "dagger", result.learner, results, setup, saved=saved)
        return results
    finally:
        setup.close()  # the env and the logger, whatever happened


def _results(config: DAggerJob, setup: Setup, result, demos: tuple[int, int], expert_ev) -> dict:
    """What results.json holds (its ``seconds`` aside): the demonstrations, each round's
    record and evaluation, the expert's, the last learner's."""
    evaluations = [r.info for r in result.rounds]
    rounds = [
        {
            "round": r.round,
            "rows_trained": r.rows_trained,
            "final_loss": r.bc.final_loss,
            "beta_next": r.beta_next,
            "rows_collected": r.rows_collected,
            "expert_executed_fraction": r.expert_executed_fraction,
            "interventions": r.interventions,
            "evaluation": ev,
        }
        for r, ev in zip(result.rounds, evaluations)
    ]
    return {
        "command": "dagger",
        "env": config.env,
        "learner_loss": setup.loss,
        "demonstrations": {
            "source": str(config.dataset) if config.dataset else f"expert {config.expert}",
            "episodes": demos[0],
            "rows": demos[1],
        },
        "final_loss": result.rounds[-1].bc.final_loss,
        "expert": expert_ev,
        "learner": evaluations[-1],
        "rounds": rounds,
    }


def _resumed(folder: Path, logger: Logger, next_round: int, bc_step: int, records: list) -> None:
    """A resumed run, before it logs anything: each saved round's evaluation checked (the
    checkpoint carried it; a hostile review: an edited one ended the finished run in a
    traceback), and the CSV logs cut back to the checkpoint: the fit losses (``bc/*``,
    step = fit step) before ``bc_step``, the rest (step = round) before ``next_round``;
    the resumed rounds log the rest again (the round a kill interrupted used to appear
    twice in the CSV files and ``curves.png``). A TensorBoard log is written again from
    the cut CSV files (:func:`~imitrl.jobs.curves.rebuild_tensorboard`); wandb's, on its
    server, still shows those steps twice."""
    for record in records:
        check_evaluation(record.info, f"{folder / RUN_CHECKPOINT}: round {record.round}")
    trim_scalars(
        folder,
        "dagger",
        lambda scalar, step: step < (bc_step if scalar.startswith("bc/") else next_round),
    )
    rebuild_tensorboard(logger, folder, "dagger")


def _dagger_config(config: DAggerJob, setup: Setup) -> DAggerConfig:
    """The algorithm's settings the flags give (its fits on the loss's own schedule)."""
    return DAggerConfig(
        rounds=config.rounds,
        episodes_per_round=config.episodes_per_round,
        beta=beta_schedule(config),
        warm_start=config.warm_start,
        bc=bc_config(config, setup),
        seed=config.seed,
        gate=None if config.gate is None else ExpertGate(config.gate),
        label=config.label,
        shared=_shared(config),
    )


def _shared(config: DAggerJob) -> dict:
    """What ``--resume`` must share with the saved run beyond the algorithm's settings: the
    env, how every round is evaluated (one run's rounds are scored alike), the learner
    and the demonstrations (a hostile review: a changed ``--lr`` or ``--demos`` resumed,
    and the run recorded settings its first rounds never had). A run saved before a key
    was shared resumes without comparing it (``dagger_checkpoint._check_state``)."""
    shared = {
        "env": config.env,
        "env_kwargs": config.env_kwargs,
        "max_episode_steps": config.max_episode_steps,
        "eval_episodes": config.eval_episodes,
        "eval_seed": config.eval_seed,
        "loss": config.loss,
        "hidden": config.hidden,
        "lr": config.lr,
        "expert": config.expert,
        "dataset": None if config.dataset is None else str(config.dataset),
        "dataset_frames": config.dataset_frames,
        "demos": config.demos if config.dataset is None else None,
        "chunk_labels": config.chunk_labels,
    }
    return json.loads(json.dumps(shared))  # as the checkpoint's JSON holds it


def beta_schedule(config: DAggerJob) -> BetaSchedule:
    """``--beta-decay P``: Ross et al.'s ``P^(i-1)`` in relabel round ``i``; otherwise the
    constant ``--beta``."""
    if config.beta_decay is not None:
        return Exponential(config.beta_decay)
    return Constant(config.beta)


def save_rounds(config: DAggerJob, buffer, path: Path, demo_last: int) -> None:
    """``--save-lerobot FPS``: the buffer (the demonstrations, whose last round is
    ``demo_last``, and this run's rounds) as a LeRobot dataset in LeRobot's DAgger schema
    (:func:`~imitrl.datasets.save_dagger_lerobot`), replacing the previous round's in one
    step: a later round that fails leaves every earlier one there."""
    from imitrl.datasets import save_dagger_lerobot  # needs the datasets extra

    schedule = beta_schedule(config)
    betas = {
        demo_last + k: NO_BETA if config.gate is not None else schedule(k)
        for k in range(1, config.rounds)
    }
    save_dagger_lerobot(
        buffer, path, fps=int(config.save_lerobot or 0), betas=betas, tasks=str(config.env),
        overwrite=True,
    )  # fmt: skip


def _plan_horizon(config: DAggerJob, setup: Setup) -> int | None:
    """The chunk length the expert plans (``--chunk-labels plan``), None with ``mask``;
    ValueError for a learner that predicts one action."""
    if config.chunk_labels != "plan":
        return None
    horizon = setup.make_learner().horizon
    if horizon is None:
        raise ValueError(
            f"--chunk-labels plan labels whole chunks for a chunked learner (act, flow_chunk, "
            f"mse_chunk, diffusion_unet, ...); --loss {setup.loss} predicts one action"
        )
    return horizon


def episode_source(config: DAggerJob, setup: Setup) -> EnvSource | RaySource | LeadSource:
    """Where the relabel rounds are played: ``setup.env`` in this process (on every rank
    alike with ``--nproc``), or ``--workers`` Ray workers each building the env as
    ``--env``/``--seed`` say (with ``--nproc``, rank 0's workers, their rows broadcast to
    every rank: :class:`~imitrl.algorithms.lead_source.LeadSource`)."""
    here = EnvSource(
        setup.playing(),
        generator=torch.Generator().manual_seed(config.seed),
        plans=config.chunk_labels == "plan",
    )
    if config.workers is None:  # exploration None: each round's learner acts as it says
        return here
    if not evaluating():  # a rank > 0 of --nproc: rank 0's workers play
        return LeadSource(here)
    env_fn = functools.partial(
        make_env,
        config.played_env(),
        seed=config.seed,
        max_episode_steps=config.max_episode_steps,
        env_kwargs=dict(config.env_kwargs),
    )
    ray = RaySource(env_fn, config.workers, seed=config.seed, address=config.address)
    return ray if rank_and_world()[1] == 1 else LeadSource(ray)


def report(results: dict) -> list[str]:
    """What ``imitrl dagger`` prints: one line per round, then the expert and the learner."""
    demos = results["demonstrations"]
    lines = [
        f"demonstrations: {demos['episodes']} episodes, {demos['rows']} rows ({demos['source']})"
    ]
    for r in results["rounds"]:
        lines.append(
            format_return(f"round {r['round']} ({r['rows_trained']} rows)", r["evaluation"])
        )
    if results["expert"] is not None:
        lines.append(format_return("expert", results["expert"]))
    lines.append(f"wrote {Path(results['files']['curves']).parent}")
    return lines
