"""``imitrl gail`` and ``imitrl airl``: adversarial imitation from demonstrations, in one function.

``run_gail(GAILJob(...)) -> dict`` (``run_airl(AIRLJob(...))`` alike):

1. resolve the flags as ``imitrl bc`` does (:func:`imitrl.jobs.bc.prepare`: env, expert,
   dataset, logger); the learner is ``--loss`` of the loss registry, ``default`` meaning
   the categorical head for discrete actions and ``gaussian_nll`` (a tanh-normal head)
   for continuous ones: PPO needs ``log pi``, which the deterministic head lacks. The
   resolved name is what ``config.json`` records, so ``imitrl eval --checkpoint`` rebuilds
   the same learner;
2. demonstrations: ``--demos`` greedy expert episodes, or the rows of ``--dataset``;
3. evaluate the expert and the untrained learner on the ``--eval-seed`` initial states;
4. :func:`~imitrl.algorithms.adversarial.gail` / ``airl`` for ``--total-steps`` env steps;
5. evaluate the learner; write ``results.json`` (env steps, expert queries = the
   demonstration rows, the evaluations, one line per round), the checkpoint and
   ``curves.png`` into ``--out``.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

from imitrl.algorithms.adversarial import (
    AdversarialConfig,
    AIRLConfig,
    GAILConfig,
    airl,
    gail,
)
from imitrl.fs.lock import exclusive
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
from imitrl.jobs.evaluate import format_return
from imitrl.jobs.resolve import EXPERT_KINDS, learner_factory
from imitrl.policies import ActorCritic
from imitrl.policies.specs import action_space

__all__ = ["AIRLJob", "GAILJob", "report", "run_airl", "run_gail"]

_SHARED = ("env", "max_episode_steps", "expert", "expert_kind", "dataset", "demos", "hidden",
           "lr", "eval_episodes", "eval_seed", "seed", "out", "logger", "progress")  # fmt: skip


@dataclass(frozen=True)
class GAILJob:
    """GAIL from expert demonstrations or a dataset, evaluated against the expert."""

    env: str = "CartPole-v1"
    """gymnasium id, or module:Env-v0 (importing module registers Env-v0)"""
    max_episode_steps: int | None = None
    """override the env's time limit; none = its registered limit"""
    expert: str | None = "cartpole"
    """a built-in expert or module:function that plays the demonstrations; none = no
    expert (needs --dataset; nothing is compared with the learner)"""
    expert_kind: str = "builder"
    """what the function of --expert module:function is: builder or callable (as imitrl bc)"""
    dataset: Path | None = None
    """LeRobot or Minari directory of demonstrations; none = play --demos expert episodes"""
    demos: int = 1
    """greedy expert demonstration episodes (when no --dataset)"""
    loss: str = "default"
    """the learner: default (categorical head for discrete actions, gaussian_nll for
    continuous ones) or a loss-registry name whose head is probabilistic"""
    hidden: tuple[int, ...] = (64, 64)
    """hidden layer sizes of the learner's policy and value networks"""
    lr: float = 3e-4
    """Adam learning rate of the learner (PPO's policy and value steps)"""
    total_steps: int = 100_000
    """environment steps of the generator (the budget)"""
    rollout_steps: int = 2048
    """environment steps per round"""
    ppo_epochs: int = 10
    """PPO passes over each round's batch"""
    minibatch_size: int = 256
    """rows per PPO step"""
    discriminator_updates: int = 10
    """discriminator steps per round"""
    discriminator_batch: int = 256
    """expert (and as many policy) transitions per discriminator step"""
    discriminator_lr: float = 3e-4
    """Adam learning rate of the discriminator"""
    grad_penalty: float = 0.0
    """weight of the discriminator's gradient penalty; 0 = none"""
    gamma: float = 0.99
    """discount (GAE's, and AIRL's shaping)"""
    gae_lambda: float = 0.95
    """GAE's lambda"""
    entropy_coeff: float = 0.0
    """weight of PPO's entropy bonus"""
    absorbing: bool = False
    """absorbing states for terminated episodes (DAC), for tasks whose episodes end at a
    goal; off: a terminal step ends the learned reward (GAIL's reward pays for living)"""
    normalizer_warmup: int = 0
    """env steps of the untrained learner whose observations join the demonstrations'
    in the normaliser's statistics (counted); 0: the demonstrations' alone"""
    eval_episodes: int = 20
    """evaluation episodes of the expert and of the learner"""
    eval_seed: int = 10_000
    """seed of the evaluation env: expert and learner play the same initial states"""
    seed: int = 0
    """seeds the env, the learner's initialisation and every draw of the run"""
    out: Path = Path("results/gail")
    """output directory: results.json, config.json + learner.pt, curves.png, logs/"""
    logger: str = "csv"
    """csv, tensorboard or wandb (the CSV files are written in every case)"""
    progress: bool = True
    """progress bar on stderr"""

    def __post_init__(self) -> None:
        if self.dataset is None and (self.expert is None or self.demos < 1):
            raise ValueError("without --dataset, --expert must play --demos >= 1 episodes")
        if self.expert_kind not in EXPERT_KINDS:
            raise ValueError(
                f"--expert-kind must be one of {EXPERT_KINDS}, got {self.expert_kind!r}"
            )
        if self.eval_episodes < 1:
            raise ValueError(f"--eval-episodes must be >= 1, got {self.eval_episodes}")
        self.algorithm_config()  # the training flags fail here, naming the field

    def algorithm_config(self) -> AdversarialConfig:
        """The :class:`GAILConfig` the flags describe."""
        return GAILConfig(**self._training())

    def _training(self) -> dict:
        names = (
            "total_steps", "rollout_steps", "ppo_epochs", "minibatch_size",
            "discriminator_updates", "discriminator_batch", "discriminator_lr",
            "grad_penalty", "gamma", "gae_lambda", "entropy_coeff", "absorbing",
            "normalizer_warmup", "seed",
        )  # fmt: skip
        return {n: getattr(self, n) for n in names}

    def bc_view(self, loss: str) -> BCJob:
        """The shared flags as a ``BCJob`` (what :func:`imitrl.jobs.bc.prepare` reads)."""
        return BCJob(loss=loss, steps=0, **{n: getattr(self, n) for n in _SHARED})


@dataclass(frozen=True)
class AIRLJob(GAILJob):
    """AIRL (state-only reward g, shaping h): every flag of imitrl gail."""

    out: Path = Path("results/airl")
    """output directory: results.json, config.json + learner.pt, curves.png, logs/"""

    def algorithm_config(self) -> AdversarialConfig:
        """The :class:`AIRLConfig` the flags describe."""
        return AIRLConfig(**self._training())


def _loss(config: GAILJob, setup: Setup) -> str:
    """``--loss`` resolved for the env: a probabilistic head (module docstring)."""
    if config.loss != "default":
        return config.loss
    kind = action_space(setup.env.action_spec_unbatched).kind
    return "gaussian_nll" if kind == "continuous" else "default"


def _learner(config: GAILJob, setup: Setup, loss: str) -> ActorCritic:
    make = learner_factory(loss, setup.env, hidden=config.hidden, lr=config.lr, seed=config.seed)
    learner = make()
    if not isinstance(learner, ActorCritic) or learner.head == "deterministic":
        raise ValueError(
            f"--loss {loss} builds a learner without an action distribution; the generator "
            "(PPO) needs log pi: use default, cross_entropy or gaussian_nll"
        )
    return learner


def _run(config: GAILJob, name: str) -> dict:
    with exclusive(config.out, what="written by another imitrl run"):  # one run per --out
        return _train(config, name)


def _train(config: GAILJob, name: str) -> dict:
    start = time.perf_counter()
    setup = prepare(config.bc_view(config.loss), name)
    loss = _loss(config, setup)
    bc_view = config.bc_view(loss)
    learner = _learner(config, setup, loss)
    buffer = demonstrations(bc_view, setup)
    expert_ev = evaluate_expert(bc_view, setup)
    initial_ev = evaluate_learner(bc_view, learner)
    training, progress, logger = config.algorithm_config(), config.progress, setup.logger
    if name == "gail":
        result = gail(setup.env, learner, buffer, training, progress=progress, logger=logger)
    else:
        result, _ = airl(setup.env, learner, buffer, training, progress=progress, logger=logger)
    learner_ev = evaluate_learner(bc_view, learner)
    log_evaluation(setup.logger, 0, learner_ev, expert_ev)
    results = {
        "command": name,
        "env": config.env,
        "learner_loss": loss,
        "demonstrations": {
            "source": str(config.dataset) if config.dataset else f"expert {config.expert}",
            "episodes": buffer.num_episodes,
            "rows": len(buffer),
        },
        "env_steps": result.env_steps,
        "expert_queries": result.expert_queries,
        "expert": expert_ev,
        "initial_learner": initial_ev,
        "learner": learner_ev,
        "rounds": [dataclasses.asdict(r) for r in result.rounds],
        "seconds": time.perf_counter() - start,
    }
    finish(dataclasses.replace(config, loss=loss), name, learner, results, setup)
    return results


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
    ]
    if results["expert"] is not None:
        lines.append(format_return("expert", results["expert"]))
    lines.append(format_return("initial learner", results["initial_learner"]))
    lines.append(format_return("learner", results["learner"]))
    lines.append(f"wrote {Path(results['files']['curves']).parent}")
    return lines
