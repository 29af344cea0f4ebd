"""``imitrl gail`` and ``imitrl airl``: adversarial imitation from demonstrations, in one function.

``run_gail(GAILJob(...)) -> dict`` (``run_airl(AIRLJob(...))`` alike):

1. resolve the flags as ``imitrl bc`` does (:func:`imitrl.jobs.bc.prepare`: env, expert,
   dataset, logger); the learner is ``--loss`` of the loss registry, ``default`` meaning
   ``cross_entropy`` for discrete actions (a logits table on integer states, an MLP
   otherwise) and ``gaussian_nll`` (a tanh-normal head,
   its log-std a learned parameter per dimension, as PPO's Gaussian policies usually are)
   for continuous ones: PPO needs ``log pi``, which the deterministic head lacks. The
   resolved name is what ``config.json`` records, so ``imitrl eval --checkpoint`` rebuilds
   the same learner;
2. demonstrations: ``--demos`` greedy expert episodes, or the rows of ``--dataset``;
3. evaluate the expert and the untrained learner on the ``--eval-seed`` initial states;
4. :func:`~imitrl.algorithms.adversarial.gail` / ``airl`` for ``--total-steps`` env steps,
   evaluating the learner after every ``--eval-every`` rounds and after the last one
   (``eval/return`` at each point's env steps, the untrained learner's at step 0); the
   checkpoint is saved before the last evaluation, which keeps it if that fails;
5. write ``results.json`` (env steps, expert queries = the demonstration rows, the
   evaluations, one line per round), the checkpoint and ``curves.png`` (discriminator
   and PPO losses, return per env step) into ``--out``.

The default budget is 50 rounds of 2048 steps; a ``--total-steps`` that is not a
multiple of ``--rollout-steps`` is rounded up to whole rounds (``env_steps`` in
results.json says how many were taken). ``--num-envs N`` steps N copies of the env
together (the policy batched over them, ``--rollout-steps / N`` steps each per round);
a run's numbers depend on the seed and N. ``--nproc N`` trains on N data-parallel ranks
(:mod:`imitrl.algorithms.adversarial.loop`): each plays its own ``--num-envs`` lanes and
``--rollout-steps`` a round, so a round is N times as many env steps and
``--total-steps`` counts them all; rank 0 evaluates and writes ``--out``.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from imitrl.algorithms.adversarial import (
    airl,
    gail,
)
from imitrl.algorithms.adversarial.absorbing import demonstrations_terminate
from imitrl.algorithms.adversarial.transitions import NEXT_TERMINATED
from imitrl.configs.adversarial import AIRLConfig
from imitrl.jobs.bc import (
    BCJob,
    Setup,
    demonstrations,
    evaluate_expert,
    evaluate_learner,
    finish,
    log_evaluation,
    prepare,
)
from imitrl.jobs.checkpoint import save_checkpoint
from imitrl.jobs.configs import AIRLJob, GAILJob
from imitrl.jobs.evaluate import format_return
from imitrl.jobs.ranks import evaluating, lead, run_folder
from imitrl.learners import ActorCritic
from imitrl.system.ranks import rank_and_world

__all__ = ["AIRLJob", "GAILJob", "report", "run_airl", "run_gail"]


def _learner(setup: Setup) -> ActorCritic:
    """The learner ``--loss`` names, refused unless it has an action distribution."""
    learner = setup.make_learner()
    if not isinstance(learner, ActorCritic) or learner.head == "deterministic":
        raise ValueError(
            f"--loss {setup.loss} builds a learner without an action distribution; the "
            "generator (PPO) needs log pi: use default, cross_entropy or gaussian_nll"
        )
    return learner


def _evaluator(config: GAILJob, bc_view: BCJob, setup: Setup, evaluations: list):
    """The loop's ``on_round``: after every ``eval_every`` rounds, evaluate the learner,
    log ``eval/return`` at the round's env steps, append ``(env_steps, evaluation)`` to
    ``evaluations`` and return the evaluation (the round's ``info`` in results.json)."""

    def on_round(k: int, learner: ActorCritic, env_steps: int) -> dict | None:
        if config.eval_every == 0 or (k + 1) % config.eval_every or not evaluating():
            return None
        ev = evaluate_learner(bc_view, learner)
        log_evaluation(setup.logger, env_steps, ev, None)
        evaluations.append((env_steps, ev))
        return {"evaluation": ev}

    return on_round


def _run(config: GAILJob, name: str) -> dict:
    config = lead(config)  # as this rank runs it
    with run_folder(config) as folder:  # fs.run_folder's rule; a scratch on ranks > 0
        return _train(config, name, folder)


def _train(config: GAILJob, name: str, folder: Path) -> dict:
    start = time.perf_counter()
    setup = prepare(config.bc_view(config.loss), name, folder, probabilistic=True)
    try:
        loss = setup.loss  # --loss default: a head with log pi (imitrl.learners.defaults)
        bc_view = config.bc_view(loss)
        learner = _learner(setup)
        # the same rows on every rank, with each row's s' (a time limit's cut keeps its last)
        buffer = demonstrations(bc_view, setup, successors=True)
        training = _training(config, buffer)  # refused before anything is evaluated
        _own_lanes(config, setup)
        expert_ev = initial_ev = None
        if evaluating():  # rank 0 evaluates and reports (--nproc)
            expert_ev = evaluate_expert(bc_view, setup)
            initial_ev = evaluate_learner(bc_view, learner)
            log_evaluation(setup.logger, 0, initial_ev, expert_ev)  # env step 0
        evaluations: list[tuple[int, dict]] = []  # (env steps, evaluation)
        on_round = _evaluator(config, bc_view, setup, evaluations)
        progress, logger = config.progress, setup.logger
        if name == "gail":
            result = gail(setup.playing(), learner, buffer, training, progress=progress, logger=logger,
                          on_round=on_round)  # fmt: skip
        else:
            assert isinstance(training, AIRLConfig)  # an AIRLJob's (run_airl)
            result, _ = airl(setup.playing(), learner, buffer, training, progress=progress,
                             logger=logger, on_round=on_round)  # fmt: skip
        save_checkpoint(folder, name, dataclasses.replace(config, loss=loss), learner)
        if evaluating() and (not evaluations or evaluations[-1][0] != result.env_steps):
            ev = evaluate_learner(bc_view, learner)  # the last round's
            log_evaluation(setup.logger, result.env_steps, ev, None)
            evaluations.append((result.env_steps, ev))
        learner_ev = evaluations[-1][1] if evaluations else None
        results = {
            "command": name,
            "env": config.env,
            "learner_loss": loss,
            "demonstrations": {
                "source": str(config.dataset) if config.dataset else f"expert {config.expert}",
                "episodes": buffer.num_episodes,
                "rows": len(buffer),
            },
            "absorbing": {
                "on": training.absorbing,
                "why": _absorbing_why(config, buffer, training.absorbing),
            },
            "env_steps": result.env_steps,
            "expert_queries": result.expert_queries,
            "expert": expert_ev,
            "initial_learner": initial_ev,
            "learner": learner_ev,
            "rounds": [dataclasses.asdict(r) for r in result.rounds],
            "seconds": time.perf_counter() - start,
        }
        finish(dataclasses.replace(config, loss=loss), name, learner, results, setup, saved=True)
        return results
    finally:
        setup.close()  # the env and the logger, whatever happened


def _training(config: GAILJob, buffer):
    """The algorithm's config, its absorbing states decided (``--absorbing``, else whether
    a demonstration terminates); ValueError naming the flags where ``--gamma 1`` meets
    absorbing states (a review: refused after every evaluation, naming ``absorbing=``)."""
    absorbing = (
        demonstrations_terminate(buffer.data) if config.absorbing is None else config.absorbing
    )
    if absorbing and config.gamma >= 1.0:
        why = "--absorbing" if config.absorbing else "the demonstrations terminate"
        raise ValueError(
            f"--gamma {config.gamma:g} with absorbing states (on: {why}): their value is "
            "r_abs / (1 - gamma); give --gamma below 1, or --no-absorbing"
        )
    return dataclasses.replace(config.algorithm_config(), absorbing=absorbing)


def _own_lanes(config: GAILJob, setup: Setup) -> None:
    """On data-parallel ranks (``--nproc``), rank ``r > 0`` re-seeds its env's lanes
    ``seed + r * num_envs + i`` after the demonstrations (which every rank plays alike):
    each rank's generator plays its own episodes, rank 0's those of a single process."""
    rank = rank_and_world()[0]
    if rank > 0:
        setup.playing().set_seed(config.seed + rank * config.num_envs)


def _absorbing_why(config: GAILJob, buffer, absorbing: bool) -> str:
    """Why absorbing states are on or off, for results.json and the report."""
    if config.absorbing is not None:
        return "--absorbing" if absorbing else "--no-absorbing"
    if absorbing:
        return "a demonstration ends by termination"
    if NEXT_TERMINATED in buffer.data.keys(include_nested=True):
        return "every demonstration is truncated"
    return "the demonstrations do not record termination"


def run_gail(config: GAILJob) -> dict:
    """GAIL as ``config`` says (module docstring); returns what results.json holds."""
    if not isinstance(config, GAILJob) or isinstance(config, AIRLJob):
        raise ValueError(f"run_gail takes a GAILJob, got {type(config).__name__}")
    return _run(config, "gail")


def run_airl(config: AIRLJob) -> dict:
    """AIRL as ``config`` says (module docstring); returns what results.json holds."""
    if not isinstance(config, AIRLJob):
        raise ValueError(f"run_airl takes an AIRLJob, got {type(config).__name__}")
    return _run(config, "airl")


def report(results: dict) -> list[str]:
    """What ``imitrl gail`` / ``imitrl airl`` print."""
    demos = results["demonstrations"]
    lines = [
        f"demonstrations: {demos['episodes']} episodes, {demos['rows']} rows ({demos['source']})",
        f"env steps: {results['env_steps']}, expert queries: {results['expert_queries']}",
        f"absorbing states: {'on' if results['absorbing']['on'] else 'off'} "
        f"({results['absorbing']['why']})",
    ]
    if results["expert"] is not None:
        lines.append(format_return("expert", results["expert"]))
    for label, key in (("initial learner", "initial_learner"), ("learner", "learner")):
        if results[key] is not None:  # None on ranks > 0 (--nproc): rank 0 evaluates
            lines.append(format_return(label, results[key]))
    lines.append(f"wrote {Path(results['files']['curves']).parent}")
    return lines
