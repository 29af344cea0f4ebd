"""The config of every training command, one frozen dataclass each, without torch.

Every field is a flag of the command (:mod:`imitrl.cli.flags`) whose help is the
field's docstring; the classes live here, apart from the functions that run them
(:mod:`imitrl.jobs.bc`, :mod:`~imitrl.jobs.dagger`, :mod:`~imitrl.jobs.gail`), so that
``imitrl bc --help`` builds its flags without importing torch, TorchRL or the loss
registry (``tests/test_imports.py``). Each ``__post_init__`` checks what can be checked
without them; the rest fails when the job starts, naming the flag. Every number is
range-checked here, by the limits its field declares (:func:`~imitrl.limits.bounded`,
:func:`~imitrl.limits.widths` for ``--hidden``; ``--help`` shows them).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from imitrl.jobs.names import EXPERT_KINDS, LOGGERS
from imitrl.limits import (
    MAX_BATCH,
    MAX_ENV_STEPS,
    MAX_EPISODE_STEPS,
    MAX_EPISODES,
    MAX_EVAL_EPISODES,
    MAX_NUM_ENVS,
    MAX_ROLLOUT_STEPS,
    MAX_ROUNDS,
    MAX_SEED,
    MAX_STEPS,
    MAX_UPDATES,
    MAX_WORKERS,
    bounded,
    check_bounds,
    widths,
)

if TYPE_CHECKING:
    from imitrl.algorithms.adversarial import AdversarialConfig

__all__ = ["AIRLJob", "BCJob", "DAggerJob", "GAILJob"]


def _check_device(device: str) -> None:
    """``--device`` names a device this machine has (one line naming both otherwise); torch
    is imported here, when a job is configured, never for ``--help``."""
    from imitrl.system.device import resolve_device

    try:
        resolve_device(device)
    except ValueError as err:
        raise ValueError(f"--device: {err}") from None


_SHARED = ("env", "num_envs", "max_episode_steps", "expert", "expert_kind", "dataset", "demos", "hidden",
           "lr", "eval_episodes", "eval_seed", "seed", "device", "out", "logger", "progress")  # fmt: skip
"""the GAIL/AIRL flags that ``imitrl bc``'s preparation reads (:meth:`GAILJob.bc_view`)"""


@dataclass(frozen=True)
class BCJob:
    """Behaviour cloning, evaluated against the expert on the same initial states."""

    env: str = "CartPole-v1"
    """gymnasium id, or module:Env-v0 (importing module registers Env-v0)"""
    num_envs: int = bounded(1, 1, MAX_NUM_ENVS)
    """env copies stepped together (lanes) when collecting episodes"""
    env_kwargs: tuple[tuple[str, object], ...] = field(
        default=(), metadata={"repeat": "--env-kwarg"}
    )
    """a keyword argument of the env's constructor, name=value (gymnasium.make(env,
    name=value)), e.g. --env-kwarg obs_type=pixels_agent_pos for metaworld/<task>-v3"""
    max_episode_steps: int | None = bounded(None, 1, MAX_EPISODE_STEPS, none_ok=True)
    """override the env's time limit; none = its registered limit"""
    expert: str | None = "auto"
    """auto = the built-in expert of --env (listed below; metaworld for every
    metaworld/<task>-v3, the task's scripted policy); a built-in name; or
    module:function; none = no expert (needs --dataset, and nothing is compared with
    the learner)"""
    expert_kind: str = "builder"
    """what the function of --expert module:function is: builder (function() returns
    an expert module writing expert_action) or callable (function(obs [N, d]) ->
    action, batched, wrapped with Expert.from_callable)"""
    dataset: Path | None = None
    """LeRobot (meta/info.json) or Minari (main_data.hdf5) directory of demonstrations;
    none = play --demos expert episodes"""
    demos: int = bounded(5, 0, MAX_EPISODES)
    """greedy expert demonstration episodes (when no --dataset)"""
    loss: str = "default"
    """a loss-registry name (listed below); default = cross_entropy for discrete actions
    (a logits table on integer states, an MLP otherwise), mse for continuous ones;
    for_env = ActorCritic.for_env's network (a one-hot MLP on integer states, a CNN on
    images: what default is where the registry builds nothing, as on images)"""
    hidden: tuple[int, ...] | None = widths()
    """hidden layer sizes of the learner's network; none = the network's own (64,64 for
    an MLP); refused where the learner is a logits table (integer states), which has none"""
    lr: float | None = bounded(None, 0, integer=False, low_open=True, none_ok=True)
    """Adam learning rate of the learner; none = the network's own: 0.1 for a logits
    table, 1e-3 for any other network, the recipe's rate for act and diffusion_unet
    (which refuse another --lr)"""
    steps: int = bounded(1000, 0, MAX_STEPS)
    """gradient steps of the behaviour-cloning fit (of every round's fit for dagger)"""
    batch_size: int | None = bounded(256, 1, MAX_BATCH, none_ok=True)
    """rows per gradient step; none = the full batch every step"""
    eval_episodes: int = bounded(10, 1, MAX_EVAL_EPISODES)
    """evaluation episodes of the expert and of the learner"""
    eval_seed: int = bounded(10_000, 0, MAX_SEED)
    """seed of the evaluation env: the expert and every learner play the same initial states"""
    seed: int = bounded(0, 0, MAX_SEED)
    """seeds the env that plays the demonstrations, the learner's initialisation and
    the minibatch order"""
    device: str = "auto"
    """where the learner computes: auto (CUDA when available, else the CPU), cpu, cuda
    or cuda:N; the env and the expert stay on the CPU"""
    out: Path = Path("results/bc")
    """output directory: results.json, config.json + learner.pt (the checkpoint that
    imitrl eval --checkpoint reads), curves.png, logs/"""
    overwrite: bool = False
    """replace a previous run in --out (without it, an --out holding one is refused)"""
    logger: str = "csv"
    """where the curves are logged: csv, tensorboard or wandb (the CSV files that
    curves.png is drawn from are written in every case)"""
    progress: bool = True
    """progress bars on stderr"""

    def __post_init__(self) -> None:
        if not self.env:
            raise ValueError("--env must name a gymnasium env")
        check_bounds(self)
        if self.dataset is None and (self.expert is None or self.demos < 1):
            raise ValueError("without --dataset, --expert must play --demos >= 1 episodes")
        if self.expert_kind not in EXPERT_KINDS:
            raise ValueError(
                f"--expert-kind must be one of {EXPERT_KINDS}, got {self.expert_kind!r}"
            )
        if self.logger not in LOGGERS:
            raise ValueError(f"--logger must be one of {', '.join(LOGGERS)}, got {self.logger!r}")
        _check_device(self.device)


@dataclass(frozen=True)
class DAggerJob(BCJob):
    """DAgger: every flag of imitrl bc, plus the rounds."""

    out: Path = Path("results/dagger")
    """output directory: results.json, config.json + learner.pt (the last round's
    learner, read by imitrl eval --checkpoint), curves.png, logs/"""
    rounds: int = bounded(4, 1, MAX_ROUNDS)
    """fits: round 0 is BC on the demonstrations, each later one refits on the
    aggregated buffer"""
    episodes_per_round: int = bounded(3, 1, MAX_EPISODES)
    """learner episodes rolled out and labelled by the expert after each fit but the last"""
    beta: float = bounded(0.0, 0, 1, integer=False)
    """probability of executing the expert's action in the relabel rounds (constant)"""
    warm_start: bool = False
    """keep training one learner across rounds instead of fitting a fresh one each round"""
    resume: bool = False
    """continue the run saved in OUT/run by an interrupted imitrl dagger with the same
    flags (bit-identical to an uninterrupted run); without it an OUT holding a run is refused"""
    workers: int | None = bounded(None, 1, MAX_WORKERS, none_ok=True)
    """Ray workers that play the relabel rounds, one env and the expert each (needs
    imitrl[distributed]); none = the rounds run in this process"""
    address: str | None = None
    """the Ray cluster for --workers (auto, or ray://HOST:10001); none = a local Ray
    instance with --workers CPUs"""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.expert is None:
            raise ValueError("dagger needs --expert to label the learner's states")
        if self.address is not None and self.workers is None:
            raise ValueError("--address names the Ray cluster for --workers: give --workers too")


@dataclass(frozen=True)
class GAILJob:
    """GAIL from expert demonstrations or a dataset, evaluated against the expert."""

    env: str = "CartPole-v1"
    """gymnasium id, or module:Env-v0 (importing module registers Env-v0)"""
    num_envs: int = bounded(1, 1, MAX_NUM_ENVS)
    """env copies (lanes) the generator steps together, its policy batched over them;
    --rollout-steps must be a multiple of it"""
    max_episode_steps: int | None = bounded(None, 1, MAX_EPISODE_STEPS, none_ok=True)
    """override the env's time limit; none = its registered limit"""
    expert: str | None = "auto"
    """auto = the built-in expert of --env; a built-in expert or module:function that
    plays the demonstrations; none = no expert (needs --dataset; nothing is compared
    with the learner)"""
    expert_kind: str = "builder"
    """what the function of --expert module:function is: builder or callable (as imitrl bc)"""
    dataset: Path | None = None
    """LeRobot or Minari directory of demonstrations; none = play --demos expert episodes"""
    demos: int = bounded(1, 0, MAX_EPISODES)
    """greedy expert demonstration episodes (when no --dataset)"""
    loss: str = "default"
    """the learner: a loss-registry name whose head is probabilistic; default =
    cross_entropy for discrete actions (a logits table on integer states, an MLP
    otherwise), gaussian_nll for continuous ones"""
    hidden: tuple[int, ...] | None = widths()
    """hidden layer sizes of the learner's policy and value networks; none = 64,64"""
    lr: float = bounded(3e-4, 0, integer=False, low_open=True)
    """Adam learning rate of the learner (PPO's policy and value steps)"""
    total_steps: int = bounded(102_400, 1, MAX_ENV_STEPS)
    """environment steps of the generator (the budget; whole rounds: 50 x 2048)"""
    rollout_steps: int = bounded(2048, 1, MAX_ROLLOUT_STEPS)
    """environment steps per round"""
    ppo_epochs: int = bounded(10, 1, MAX_UPDATES)
    """PPO passes over each round's batch"""
    minibatch_size: int = bounded(256, 1, MAX_BATCH)
    """rows per PPO step"""
    discriminator_updates: int = bounded(10, 0, MAX_UPDATES)
    """discriminator steps per round"""
    discriminator_batch: int = bounded(256, 1, MAX_BATCH)
    """expert (and as many policy) transitions per discriminator step"""
    discriminator_lr: float = bounded(3e-4, 0, integer=False, low_open=True)
    """Adam learning rate of the discriminator"""
    grad_penalty: float = bounded(0.0, 0, integer=False)
    """weight of the discriminator's gradient penalty; 0 = none"""
    gamma: float = bounded(0.99, 0, 1, integer=False)
    """discount (GAE's, and AIRL's shaping)"""
    gae_lambda: float = bounded(0.95, 0, 1, integer=False)
    """GAE's lambda"""
    entropy_coeff: float = bounded(0.0, 0, integer=False)
    """weight of PPO's entropy bonus"""
    anneal_lr: bool = False
    """the learner's learning rate falls linearly over the rounds, the first at --lr, the
    last at --lr/K of K rounds (CleanRL's PPO schedule); --discriminator-lr stays
    constant; off: constant. Measured on Pendulum AIRL (benchmarks/beyond_cloning.py): it
    holds the expert's return to the last round"""
    absorbing: bool | None = None
    """absorbing states for terminated episodes (DAC); none (default): on when a
    demonstration episode ends by termination (a goal: Acrobot, FrozenLake), off when
    every one is truncated (the expert survives: CartPole, Pendulum), where GAIL's
    reward pays for living. Measured on Acrobot (seed 0, one demonstration): GAIL ends
    at -82 with absorbing states (expert -80) and at -226 without"""
    normalizer_warmup: int = bounded(0, 0, MAX_ROLLOUT_STEPS)
    """env steps of the untrained learner whose observations join the demonstrations'
    in the normaliser's statistics (counted); 0: the demonstrations' alone"""
    eval_episodes: int = bounded(20, 1, MAX_EVAL_EPISODES)
    """evaluation episodes of the expert and of the learner"""
    eval_seed: int = bounded(10_000, 0, MAX_SEED)
    """seed of the evaluation env: expert and learner play the same initial states"""
    eval_every: int = bounded(10, 0)
    """evaluate the learner after every this many rounds (and after the last); 0 =
    after the last only"""
    seed: int = bounded(0, 0, MAX_SEED)
    """seeds the env, the learner's initialisation and every draw of the run"""
    device: str = "auto"
    """where the learner computes: auto (CUDA when available, else the CPU), cpu, cuda
    or cuda:N; the env and the expert stay on the CPU"""
    out: Path = Path("results/gail")
    """output directory: results.json, config.json + learner.pt, curves.png, logs/"""
    overwrite: bool = False
    """replace a previous run in --out (without it, an --out holding one is refused)"""
    logger: str = "csv"
    """csv, tensorboard or wandb (the CSV files are written in every case)"""
    progress: bool = True
    """progress bar on stderr"""

    def __post_init__(self) -> None:
        if int(self.num_envs) != self.num_envs or self.num_envs < 1:
            raise ValueError(f"--num-envs must be a positive integer, got {self.num_envs!r}")
        self.algorithm_config()  # the training flags' own checks first, naming the field
        check_bounds(self)  # then every flag's range (the training flags' upper limits)
        if self.dataset is None and (self.expert is None or self.demos < 1):
            raise ValueError("without --dataset, --expert must play --demos >= 1 episodes")
        if self.expert_kind not in EXPERT_KINDS:
            raise ValueError(
                f"--expert-kind must be one of {EXPERT_KINDS}, got {self.expert_kind!r}"
            )
        _check_device(self.device)
        if self.rollout_steps % self.num_envs:
            raise ValueError(
                f"--rollout-steps ({self.rollout_steps}) must be a multiple of --num-envs "
                f"({self.num_envs}): each round steps every lane equally"
            )

    def algorithm_config(self) -> AdversarialConfig:
        """The :class:`GAILConfig` the flags describe."""
        from imitrl.algorithms.adversarial import GAILConfig  # torch: not for --help

        return GAILConfig(**self._training())

    def _training(self) -> dict:
        names = (
            "total_steps", "rollout_steps", "ppo_epochs", "minibatch_size",
            "discriminator_updates", "discriminator_batch", "discriminator_lr",
            "grad_penalty", "gamma", "gae_lambda", "entropy_coeff", "anneal_lr",
            "absorbing", "normalizer_warmup", "seed",
        )  # fmt: skip
        fields = {n: getattr(self, n) for n in names}
        fields["absorbing"] = bool(self.absorbing)  # none: decided from the demonstrations
        return fields

    def bc_view(self, loss: str) -> BCJob:
        """The shared flags as a ``BCJob`` (what :func:`imitrl.jobs.bc.prepare` reads)."""
        return BCJob(loss=loss, steps=0, **{n: getattr(self, n) for n in _SHARED})


@dataclass(frozen=True)
class AIRLJob(GAILJob):
    """AIRL (state-only reward g, shaping h): every flag of imitrl gail."""

    out: Path = Path("results/airl")
    """output directory: results.json, config.json + learner.pt, curves.png, logs/"""
    entropy_weight: float = bounded(1.0, 0, integer=False)
    """weight w of -log pi in the generator's reward f - w log pi (1: the paper's log D -
    log(1 - D)). Measured (benchmarks/beyond_cloning.py, 5 seeds): on Pendulum, which
    never terminates, w = 0 ends at -152 to -156 where w = 1 ends at -275 to -836; on
    tasks that end on failure the term is the generator's living bonus, and at w = 0
    CartPole and InvertedPendulum collapse to 9- and 2-step episodes"""

    def algorithm_config(self) -> AdversarialConfig:
        """The :class:`AIRLConfig` the flags describe."""
        from imitrl.algorithms.adversarial import AIRLConfig  # torch: not for --help

        return AIRLConfig(**self._training(), entropy_weight=self.entropy_weight)
