"""DAgger: roll the learner (mixed with the expert), label every visited state, aggregate, refit.

Round ``k = 0, 1, ...``: fit a learner on everything in the buffer (from scratch, as
the section does, or warm-started), hand it to ``on_fit`` (evaluation), then collect
``episodes_per_round`` episodes with the behaviour policy
``TensorDictSequential(expert, learner, BetaMixer(beta_{k+1}))`` and extend the
buffer with them as round ``k + 1`` (after the last round the buffer started with: a
dataset of earlier rounds is continued). Round 0 of the buffer is the offline
demonstrations (``beta_0 = 1``). Every visited state is labelled by the expert, so
the number of expert queries is the number of rows in the buffer.

Beta schedules are tiny callables ``round -> beta`` (Ross et al. 2011 use
``beta_1 = 1`` and ``beta_i = p^{i-1}``; the section's miniature uses ``beta = 0``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, exploration_type, set_exploration_type
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from imitrl import checks, keys
from imitrl.algorithms.bc import BCConfig, BCResult, fit_bc
from imitrl.algorithms.beta_schedules import BetaSchedule, Constant, Exponential, Linear
from imitrl.algorithms.dagger_checkpoint import (
    RunState,
    generator_state,
    load_run,
    save_run,
    set_generator_state,
)
from imitrl.algorithms.expert_plan import ExpertPlanner
from imitrl.data.buffer import DemonstrationBuffer
from imitrl.data.interventions import intervention_segments
from imitrl.data.provenance import NO_BETA, with_provenance
from imitrl.envs.limits import episode_limit
from imitrl.envs.random_state import env_random_state, set_env_random_state
from imitrl.fs.lock import exclusive
from imitrl.learners.learner import Learner
from imitrl.limits import MAX_ROUNDS
from imitrl.policies.experts import Expert
from imitrl.policies.gate import ExpertGate
from imitrl.policies.mixture import BetaMixer, behaviour_policy
from imitrl.runtime import paths
from imitrl.runtime.rollout import rollout_episodes
from imitrl.system.device import acting
from imitrl.system.ranks import from_lead, rank_and_world

__all__ = [
    "Constant",
    "DAggerConfig",
    "DAggerResult",
    "EnvSource",
    "EpisodeSource",
    "Exponential",
    "Linear",
    "RoundRecord",
    "dagger",
]


class EpisodeSource(Protocol):
    """Where relabel rounds come from: plays a behaviour policy, returns buffer rows.

    ``check(expert, learner)`` runs before a learner's first round: it binds the expert
    to the actions the source takes and refuses a learner that cannot act there.
    ``state_dict()`` / ``load_state_dict(state)`` give and restore, as JSON-able data,
    the random state the next collection draws from (for resumable runs).
    """

    def check(self, expert: Expert, learner: Learner) -> None: ...

    def state_dict(self) -> dict: ...

    def load_state_dict(self, state: dict) -> None: ...

    def collect(
        self,
        behaviour: TensorDictModuleBase,
        num_episodes: int,
        *,
        round_index: int,
        first_episode: int,
    ) -> TensorDict: ...


@dataclass
class EnvSource:
    """Episodes from a TorchRL env (batched or not) via :func:`rollout_episodes`.

    ``collect`` plays a DAgger behaviour policy, or a bare
    :class:`~imitrl.policies.Expert` (demonstrations from the same expert object).

    Attributes:
        env: the env.
        exploration: how the learner acts in rollouts (``DETERMINISTIC`` = greedy);
            None = as the learner says (``dagger`` collects under ``learner.exploration``).
        max_steps: most steps ONE episode may take; None (default): the env's own time
            limit (:func:`~imitrl.envs.episode_limit`). An env without one needs it:
            the source refuses to be built otherwise.
        generator: source of the learner's sampling when ``exploration`` is
            ``RANDOM`` (seed it for reproducible rounds); None: torch's global RNG.
        plans: chunk-aware labels: at every visited state the expert's own next
            ``learner.horizon`` actions, played on the env from there and undone
            (:class:`~imitrl.algorithms.expert_plan.ExpertPlanner`; one lane, a chunked
            learner, demonstrations carrying plans too: :func:`with_plans`). The rounds
            then take the reference path (the planner drives the env through TorchRL).
    """

    env: EnvBase
    exploration: ExplorationType | None = None
    max_steps: int | None = None
    generator: torch.Generator | None = None
    plans: bool = False
    _episode_steps: int = field(init=False, repr=False)
    _planner: ExpertPlanner | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.max_steps is not None:
            if int(self.max_steps) != self.max_steps or self.max_steps < 1:
                raise ValueError(
                    f"max_steps must be a positive integer or None, got {self.max_steps!r}"
                )
            self._episode_steps = int(self.max_steps)
            return
        limit = episode_limit(self.env)  # looked up once, not at every round
        if limit is None:
            raise ValueError(
                f"{type(self.env).__name__} has no time limit of its own: pass "
                "EnvSource(env, max_steps=...) (the most steps one episode may take)"
            )
        self._episode_steps = limit

    def check(self, expert: Expert, learner: Learner) -> None:
        """Bind ``expert`` to the env's action spec; refuse a ``learner`` that does not fit
        the env (both before the first step, naming what differs)."""
        expert.bind(self.env.action_spec_unbatched)
        learner.check_env(self.env)
        if self.plans:
            if learner.horizon is None:
                raise ValueError(
                    "plans label whole chunks for a chunked learner (act, flow_chunk, "
                    "mse_chunk, diffusion_unet, ...); this learner predicts one action"
                )
            self._planner = ExpertPlanner(expert, self.env, learner.horizon)

    def state_dict(self) -> dict:
        """The env's random generators and the learner's sampling generator."""
        return {"env": env_random_state(self.env), "generator": generator_state(self.generator)}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` (the same kind of env and generator)."""
        set_env_random_state(self.env, state["env"])
        set_generator_state(self.generator, state["generator"])

    def collect(
        self,
        behaviour: TensorDictModuleBase,
        num_episodes: int,
        *,
        round_index: int,
        first_episode: int,
    ) -> TensorDict:
        """``num_episodes`` whole episodes of ``behaviour`` as buffer rows (see
        ``rollout_episodes``), with the expert's plans where ``plans`` is set."""
        planning = self.plans and not isinstance(behaviour, Expert)
        if planning:
            if self._planner is None:
                raise ValueError("plans: check(expert, learner) names the planner's horizon first")
            behaviour = TensorDictSequential(behaviour, self._planner)
        with paths.reference() if planning else contextlib.nullcontext():
            return rollout_episodes(
                self.env,
                behaviour,
                num_episodes,
                exploration=self.exploration or exploration_type(),
                max_steps=self._episode_steps,
                round_index=round_index,
                first_episode=first_episode,
                generator=self.generator,
            )


@dataclass(frozen=True)
class DAggerConfig:
    """DAgger loop."""

    rounds: int = 4
    """fits; a relabel round is collected after each fit but the last"""
    episodes_per_round: int = 3
    """episodes rolled out and relabelled per round"""
    beta: BetaSchedule = field(default_factory=lambda: Constant(0.0))
    """probability of executing the expert's action in relabel round i"""
    warm_start: bool = False
    """keep training one learner (True) or refit a fresh one each round (False, the section)"""
    bc: BCConfig = field(default_factory=BCConfig)
    """the behaviour-cloning fit of each round"""
    seed: int = 0
    """seed of the mixture's coin flips"""
    gate: ExpertGate | None = None
    """a gated expert (:class:`~imitrl.policies.gate.ExpertGate`) instead of ``beta``'s coin:
    the expert takes over where the gate's rule fires"""
    label: str = "all"
    """which visited states the expert labels: ``all`` (DAgger) or ``interventions``
    (HG-DAgger, with a gate: the frames it took over, each streak an episode,
    :func:`~imitrl.data.interventions.intervention_segments`)"""
    shared: dict = field(default_factory=dict)
    """what else a resumed run must share with the saved one: the caller's own settings,
    JSON data (``imitrl dagger``: the env and its evaluation protocol, so that one run's
    rounds are scored alike); ``{}``: nothing more"""

    def __post_init__(self) -> None:
        checks.integer(self.rounds, "DAggerConfig.rounds", minimum=1)
        if self.label not in ("all", "interventions"):
            raise ValueError(f"DAggerConfig.label must be all or interventions, got {self.label!r}")
        if self.label == "interventions" and self.gate is None:
            raise ValueError("label='interventions' (HG-DAgger) needs a gate: ExpertGate(rule)")
        if self.gate is not None and not isinstance(self.gate, ExpertGate):
            raise ValueError(f"DAggerConfig.gate must be an ExpertGate, got {self.gate!r}")
        checks.integer(self.episodes_per_round, "DAggerConfig.episodes_per_round", minimum=1)
        checks.boolean(self.warm_start, "DAggerConfig.warm_start")
        checks.integer(self.seed, "DAggerConfig.seed")
        if not callable(self.beta):
            raise ValueError(
                f"DAggerConfig.beta must be a schedule, round -> probability (Constant(0.5), "
                f"Linear(...)), got {self.beta!r}"
            )
        if not isinstance(self.bc, BCConfig):
            raise ValueError(f"DAggerConfig.bc must be a BCConfig, got {type(self.bc).__name__}")


@dataclass
class RoundRecord:
    """One DAgger round."""

    round: int
    rows_trained: int
    """rows the round's learner was fitted on"""
    expert_queries: int
    """expert labels used so far (= rows trained on)"""
    bc: BCResult
    """the round's fit"""
    beta_next: float | None = None
    """beta of the relabel round collected after this fit"""
    rows_collected: int = 0
    """rows the relabel round added to the buffer"""
    expert_executed_fraction: float | None = None
    interventions: int | None = None
    """visited states where a gate gave the expert control (None without a gate)"""
    info: dict | None = None
    """what ``on_fit`` returned for this round (e.g. its evaluation), kept in checkpoints"""


@dataclass
class DAggerResult:
    """What :func:`dagger` returns."""

    learner: Learner
    """the last round's learner"""
    rounds: list[RoundRecord]
    """one record per fit"""
    buffer: DemonstrationBuffer
    """the buffer, extended with every relabel round"""


def dagger(
    source: EpisodeSource,
    expert: Expert,
    make_learner: Callable[[], Learner],
    buffer: DemonstrationBuffer,
    config: DAggerConfig = DAggerConfig(),
    *,
    on_fit: Callable[[int, Learner], dict | None] | None = None,
    train: Callable[[Learner, DemonstrationBuffer], BCResult] | None = None,
    progress: bool = False,
    logger: Logger | None = None,
    checkpoint_dir: str | Path | None = None,
    resume: bool = False,
    on_resume: Callable[[int, int, list[RoundRecord]], None] | None = None,
) -> DAggerResult:
    """Run DAgger on top of the demonstrations already in ``buffer`` (extended in place).

    Args:
        source: plays the behaviour policy (an :class:`EnvSource` or a faithful stream).
        expert: writes ``EXPERT_ACTION`` for any observation.
        make_learner: builds a fresh :class:`~imitrl.learners.Learner` (``ActorCritic``,
            a registry learner; called once with ``warm_start``). Each round's learner
            acts in the rollouts as its ``exploration`` says.
        buffer: demonstrations (round 0), extended with every relabel round.
        config: rounds, episodes per round, beta schedule, fit.
        on_fit: called as ``on_fit(round, learner)`` after each fit, before collection;
            a dict it returns (JSON-able) is kept as the round record's ``info``
            (anything else it returns is ignored).
        train: fits a round's learner on the buffer, ``train(learner, buffer) -> BCResult``;
            None = ``fit_bc(learner, buffer, config.bc)``.
        progress: progress bar over rounds (on stderr).
        logger: a TorchRL logger: each round's fit losses (``bc/loss``, steps counted
            across rounds), rows and expert queries (``dagger/*``, step = round).
        checkpoint_dir: save everything the next round depends on there after every
            round (:mod:`imitrl.algorithms.dagger_checkpoint`); a directory that already
            holds a run is refused unless ``resume``. The run holds the directory's lock
            (:func:`imitrl.fs.exclusive`) until it returns: a second run (or any writer)
            of the same directory is refused at once instead of replacing its rounds.
        resume: continue the run saved in ``checkpoint_dir`` (a fresh start when it holds
            none): ``buffer`` must hold the run's demonstrations; the result is identical
            to the bit to an uninterrupted run.
        on_resume: with ``resume``, called as ``on_resume(next_round, bc_step, records)``
            once the saved run is restored (``(0, 0, [])`` when there was none), before
            anything is logged: the rounds, fit steps and round records the checkpoint
            holds. A logger that appends cuts back what the interrupted round logged
            (:func:`imitrl.jobs.curves.trim_scalars`); a caller checks what its ``on_fit``
            returned into the records (``info``), which the checkpoint carried.
    """
    _check_inputs(buffer, expert, make_learner, checkpoint_dir, resume)
    if getattr(source, "plans", False) and keys.EXPERT_PLAN not in buffer.data.keys():
        raise ValueError(
            "the source records the expert's plans (plans=True) and the demonstrations carry "
            "none: add them before the buffer takes the rows (buffer.extend(with_plans(rows, "
            "horizon)), imitrl.algorithms.expert_plan.with_plans), so both share one schema"
        )
    if checkpoint_dir is None:
        return _run(source, expert, make_learner, buffer, config, on_fit, train, progress, logger)
    # the folder is this run's until it returns: a second run of it is refused at once
    with exclusive(checkpoint_dir, what="used by a DAgger run"):
        _check_run(checkpoint_dir, resume)
        return _run(
            source, expert, make_learner, buffer, config, on_fit, train, progress, logger,
            checkpoint_dir=Path(checkpoint_dir), resume=resume, on_resume=on_resume,
        )  # fmt: skip


def _run(
    source, expert, make_learner, buffer, config, on_fit, train, progress, logger,
    *, checkpoint_dir: Path | None = None, resume: bool = False, on_resume=None,
) -> DAggerResult:  # fmt: skip
    """The rounds of :func:`dagger` (its arguments, checked)."""
    coins = torch.Generator().manual_seed(config.seed)
    mixer = BetaMixer(0.0, generator=coins)
    # rounds continue a dataset's (one written by save_dagger_lerobot): its last round + 1
    first = max(buffer.rounds())
    if first + config.rounds - 1 > MAX_ROUNDS:  # before any fit, not when a round is stored
        raise ValueError(
            f"the buffer's rows come from DAgger rounds up to {first}; {config.rounds - 1} "
            f"relabel rounds more would pass round {MAX_ROUNDS} (imitrl.limits.MAX_ROUNDS)"
        )
    run = RunState(next_round=0, records=[], bc_step=0, learner=None)
    if resume and checkpoint_dir is not None and _holds_run(checkpoint_dir):
        run = load_run(
            checkpoint_dir, buffer, make_learner, config=config,
            record_cls=RoundRecord, mixer_generator=coins, source=source,
        )  # fmt: skip
    if resume:
        _same_round_on_every_rank(run.next_round)
        if on_resume is not None:
            on_resume(run.next_round, run.bc_step, run.records)
    learner = run.learner
    last = run.records[-1] if run.records else None
    if last is not None and last.beta_next is None and run.next_round < config.rounds:
        # the saved run ended at its last round, which collects nothing; its rounds grew:
        # that round's relabel episodes now, as an uninterrupted run would have played them
        assert learner is not None
        _collect(run.next_round - 1, learner, expert, mixer, source, buffer, config, last, first)
    rounds = range(run.next_round, config.rounds)
    for k in tqdm(rounds, desc="dagger", disable=not progress, leave=False):
        if learner is None or not config.warm_start:
            learner = _fresh_learner(make_learner, source, expert)
        record = _fit(k, learner, buffer, config, train, logger, run.bc_step)
        run.bc_step += record.bc.losses.numel()
        run.records.append(record)
        if on_fit is not None:
            record.info = _info(on_fit(k, learner))
        if k + 1 < config.rounds:
            _collect(k, learner, expert, mixer, source, buffer, config, record, first)
        if checkpoint_dir is not None:
            save_run(
                checkpoint_dir, buffer, learner, next_round=k + 1, config=config,
                records=run.records, bc_step=run.bc_step, mixer_generator=coins, source=source,
            )  # fmt: skip
    assert learner is not None
    return DAggerResult(learner=learner, rounds=run.records, buffer=buffer)


def _same_round_on_every_rank(next_round: int) -> None:
    """ValueError on a data-parallel rank that resumed another round than rank 0 (its
    fits would all-reduce gradients of other rounds: a wrong learner, silently)."""
    lead = from_lead(next_round)
    if lead != next_round:
        raise ValueError(
            f"rank {rank_and_world()[0]} resumed at round {next_round}, rank 0 at round {lead}: "
            "every rank must continue the same checkpoint"
        )


def _check_inputs(buffer, expert, make_learner, checkpoint_dir, resume: bool) -> None:
    if isinstance(make_learner, torch.nn.Module) or not callable(make_learner):
        raise ValueError(  # a Learner is callable (a module): it failed inside torch
            f"make_learner must be a function of no arguments returning a fresh Learner, got "
            f"a {type(make_learner).__name__} (for one learner kept across rounds: "
            "lambda: learner, with DAggerConfig(warm_start=True))"
        )
    if len(buffer) == 0:
        raise ValueError("DAgger starts from demonstrations: the buffer is empty")
    if not isinstance(expert, Expert):
        raise ValueError(
            f"the expert must be an imitrl Expert, got {type(expert).__name__} "
            "(wrap a policy module with Expert.from_policy, a function with Expert.from_callable)"
        )
    if resume and checkpoint_dir is None:
        raise ValueError("resume=True needs the checkpoint_dir of the run to continue")


def _check_run(checkpoint_dir, resume: bool) -> None:
    if not resume and _holds_run(checkpoint_dir):
        raise ValueError(
            f"{checkpoint_dir} holds a saved DAgger run: pass resume=True to continue it, "
            "or give another checkpoint_dir"
        )


def _holds_run(checkpoint_dir) -> bool:
    return (Path(checkpoint_dir) / "manifest.json").exists()


def _info(value) -> dict | None:
    """What ``on_fit`` returned, kept when it is a dict (any other return is ignored)."""
    return value if isinstance(value, dict) else None


def _fresh_learner(make_learner, source, expert) -> Learner:
    learner = make_learner()
    if not isinstance(learner, Learner):
        raise ValueError(
            f"make_learner must return an imitrl Learner, got {type(learner).__name__}"
        )
    source.check(expert, learner)
    return learner


def _fit(k, learner, buffer, config, train, logger, bc_step) -> RoundRecord:
    """Round ``k``'s fit on the whole buffer, logged and recorded."""
    if train is None:
        result = fit_bc(learner, buffer, config.bc, logger=logger, log_step=bc_step)
    else:
        result = train(learner, buffer)
        if not isinstance(result, BCResult):
            raise ValueError(
                f"dagger's train callback must return the fit's BCResult (what fit_bc returns), "
                f"got {type(result).__name__} in round {k}: end it with `return fit_bc(...)`"
            )
    if logger is not None:
        logger.log_scalar("dagger/rows", float(len(buffer)), step=k)
        logger.log_scalar("dagger/final_loss", result.final_loss, step=k)
    return RoundRecord(round=k, rows_trained=len(buffer), expert_queries=len(buffer), bc=result)


def _collect(k, learner, expert, mixer, source, buffer, config, record, first: int) -> None:
    """Relabel round ``k + 1``: the behaviour policy's episodes, labelled, into the buffer
    (``ROUND`` = ``first + k + 1``: after the rounds the buffer started with)."""
    # envs and experts stay on the CPU; a learner elsewhere acts through OnDevice
    actor = acting(learner.policy, "cpu")
    if config.gate is None:
        mixer.beta = config.beta(k + 1)
        behaviour = behaviour_policy(expert, actor, mixer)
    else:  # the expert takes over where the gate fires
        behaviour = TensorDictSequential(expert, actor, config.gate)
    with set_exploration_type(learner.exploration):  # what EnvSource(exploration=None) uses
        rows = source.collect(
            behaviour,
            config.episodes_per_round,
            round_index=first + k + 1,
            first_episode=buffer.next_episode,
        )
    rows = _as_recorded(rows, buffer)
    beta = mixer.beta if config.gate is None else NO_BETA
    if keys.BETA in buffer.data.keys():  # rows of a dataset that records its rounds' betas
        rows = with_provenance(rows, beta, policy_version=first + k)
    executed = rows.get(keys.EXPERT_EXECUTED)
    if config.label == "interventions":  # HG-DAgger: the expert's frames alone
        rows = intervention_segments(rows, buffer.next_episode)
    if rows.shape[0]:
        buffer.extend(rows)
    record.beta_next = mixer.beta if config.gate is None else 0.0
    record.rows_collected = rows.shape[0]
    record.expert_executed_fraction = float(executed.float().mean())
    record.interventions = None if config.gate is None else int(executed.sum())


def _as_recorded(rows, buffer: DemonstrationBuffer):
    """A round's rows without the ``("next", ...)`` entries the demonstrations did not record
    (a LeRobot DAgger recording has no rewards): the buffer keeps one schema."""
    held = set(buffer.data.keys(include_nested=True, leaves_only=True))
    unrecorded = [
        k for k in rows.keys(include_nested=True, leaves_only=True)
        if k not in held and isinstance(k, tuple) and k[0] == keys.NEXT
    ]  # fmt: skip
    return rows.exclude(*unrecorded) if unrecorded else rows
