"""The config of every training command, one frozen dataclass each, without torch.

Every field is a flag of the command (:mod:`imitrl.cli.flags`) whose help is the
field's docstring. A command's config is the library's own config extended by the
flags of a run: ``imitrl bc`` and ``imitrl dagger`` extend
:class:`~imitrl.configs.bc.BCConfig` (the fit: ``--steps``, ``--batch-size``,
``--lr-schedule``, ...), ``imitrl gail`` and ``imitrl airl``
:class:`~imitrl.configs.adversarial.GAILConfig` and ``AIRLConfig`` (the budget,
PPO and the discriminator), so that every hyperparameter is declared once, with one
default, for Python and the command line alike; :class:`RunFlags` are what every run
adds (the env, the demonstrations, the learner, the evaluation, the output).

The classes live here, apart from the functions that run them (:mod:`imitrl.jobs.bc`,
:mod:`~imitrl.jobs.dagger`, :mod:`~imitrl.jobs.gail`), and the library configs they
extend import no torch, so that ``imitrl bc --help`` builds its flags without importing
torch, TorchRL or the loss registry (``tests/jobs/test_names_imports.py``). Every number is
range-checked by the limits its field declares (:func:`~imitrl.limits.bounded`,
:func:`~imitrl.limits.widths` for ``--hidden``; ``--help`` shows them), named by its flag.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from imitrl.configs.adversarial import ADVERSARIAL_LR, AIRLConfig, GAILConfig
from imitrl.configs.bc import BCConfig
from imitrl.jobs.names import EXPERT_KINDS, LOGGERS
from imitrl.limits import (
    MAX_EPISODE_STEPS,
    MAX_EPISODES,
    MAX_EVAL_EPISODES,
    MAX_FPS,
    MAX_NPROC,
    MAX_NUM_ENVS,
    MAX_ROUNDS,
    MAX_SEED,
    MAX_WORKERS,
    bounded,
    check_bounds,
    widths,
)

__all__ = ["CHUNK_LABELS", "AIRLJob", "BCJob", "DAggerJob", "GAILJob", "RunFlags"]

CHUNK_LABELS = ("mask", "plan")
DATASET_FRAMES = ("all", "interventions")
"""``--chunk-labels``: a chunked learner's relabelled rows keep the expert's label at
their state alone (``mask``) or its plan from there (``plan``,
:class:`~imitrl.algorithms.expert_plan.ExpertPlanner`)"""


def check_nproc(nproc: int, device: str) -> None:
    """``--nproc`` ranks this machine can hold: at most one per CPU core on the CPU, one
    per GPU on CUDA (one line naming both otherwise)."""
    if nproc == 1:
        return
    from imitrl.system.device import resolve_device
    from imitrl.system.threads import cores

    target = resolve_device(device)
    if target.type == "cuda":
        import torch

        if nproc > torch.cuda.device_count():
            raise ValueError(
                f"--nproc {nproc}: this machine has {torch.cuda.device_count()} GPU(s), one "
                "rank each"
            )
    elif nproc > cores():
        raise ValueError(
            f"--nproc {nproc}: more CPU ranks than the {cores()} cores this process may use "
            "(each rank computes its share of every batch; more would only wait)"
        )


def _check_device(device: str) -> None:
    """``--device`` names a device this machine has (one line naming both otherwise); torch
    is imported here, when a job is configured, never for ``--help``."""
    from imitrl.system.device import resolve_device

    try:
        resolve_device(device)
    except ValueError as err:
        raise ValueError(f"--device: {err}") from None


def _library(config: object, cls: type) -> dict:
    """The fields of the library config ``cls`` that ``config`` (a command's, which
    extends it) holds."""
    return {f.name: getattr(config, f.name) for f in fields(cls)}


@dataclass(frozen=True)
class RunFlags:
    """What every training run takes besides its algorithm's settings."""

    env: str | None = "CartPole-v1"
    """gymnasium id, or module:Env-v0 (importing module registers Env-v0); none = no env
    (imitrl bc --dataset only: a dataset recorded on a robot is trained on alone, the
    learner built for its observations and the range of its actions, nothing evaluated)"""
    num_envs: int = bounded(1, 1, MAX_NUM_ENVS)
    """env copies stepped together (lanes) when collecting episodes"""
    env_kwargs: tuple[tuple[str, object], ...] = field(
        default=(), metadata={"repeat": "--env-kwarg"}
    )
    """a keyword argument of the env's constructor, name=value (gymnasium.make(env,
    name=value)), the value a Python literal where it is one (true, false and none too),
    else a string, e.g. --env-kwarg is_slippery=false for FrozenLake-v1, --env-kwarg
    obs_type=pixels_agent_pos for metaworld/<task>-v3"""
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
    dataset_frames: str = "all"
    """which frames of --dataset are trained on: all (as lerobot-train does: a LeRobot
    DAgger recording's autonomous frames too) or interventions (the frames whose
    intervention column is True, each streak an episode of its own: HG-DAgger's labels)"""
    demos: int = bounded(5, 0, MAX_EPISODES)
    """greedy expert demonstration episodes (when no --dataset)"""
    loss: str = "default"
    """a loss-registry name (listed below) or module:name, your own (importing module
    registers name with imitrl.learners.registry.register); default = cross_entropy for
    discrete actions (a logits table on integer states, an MLP otherwise), mse for
    continuous ones, for_env on images (a CNN): imitrl.learners.build(name, env) builds it"""
    hidden: tuple[int, ...] | None = widths()
    """hidden layer sizes of the learner's network; none = the network's own (64,64 for
    an MLP); refused where the learner is a logits table (integer states), which has none"""
    lr: float | None = bounded(None, 0, integer=False, low_open=True, none_ok=True)
    """Adam learning rate of the learner; none = the network's own: 0.1 for a logits
    table, 1e-3 for any other network, the recipe's rate for act and diffusion_unet
    (which refuse another --lr)"""
    eval_episodes: int = bounded(10, 1, MAX_EVAL_EPISODES)
    """evaluation episodes of the expert and of the learner"""
    eval_seed: int = bounded(10_000, 0, MAX_SEED)
    """seed of the evaluation env: the expert and every learner play the same initial states"""
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
    nproc: int = bounded(1, 1, MAX_NPROC)
    """processes (ranks) the training runs on, data-parallel on torch.distributed (gloo
    on CPUs, NCCL on GPUs; launched as torchrun does): every batch flag is each rank's
    (bc's and dagger's --batch-size: one process at N times it gives the same parameters;
    gail's and airl's --rollout-steps, --discriminator-batch and --minibatch-size, each
    rank playing its own lanes), so the global batch is N times it: scale --lr with it,
    or not; 1 = this process alone"""

    def played_env(self) -> str:
        """``--env``, for what plays in it (ValueError with ``--env none``)."""
        if self.env is None:
            raise ValueError("--env none trains on --dataset alone: nothing plays in an env")
        return self.env

    def _check_run(self) -> None:
        _paths(self, "out", "dataset")
        if self.env is None:
            if self.dataset is None:
                raise ValueError("--env none trains on --dataset alone: give --dataset")
            if self.expert not in (None, "auto"):
                raise ValueError(
                    f"--expert {self.expert} needs an env to act in: leave it out with --env none"
                )
        elif not self.env:
            raise ValueError("--env must name a gymnasium env (or none, with --dataset)")
        check_bounds(self)  # every number, the algorithm's too, named by its flag
        if self.dataset is None and (self.expert is None or self.demos < 1):
            raise ValueError("without --dataset, --expert must play --demos >= 1 episodes")
        if self.dataset_frames not in DATASET_FRAMES:
            raise ValueError(
                f"--dataset-frames must be one of {', '.join(DATASET_FRAMES)}, got "
                f"{self.dataset_frames!r}"
            )
        if self.dataset_frames != "all" and self.dataset is None:
            raise ValueError("--dataset-frames chooses frames of --dataset: give --dataset")
        if self.expert_kind not in EXPERT_KINDS:
            raise ValueError(
                f"--expert-kind must be one of {EXPERT_KINDS}, got {self.expert_kind!r}"
            )
        if self.logger not in LOGGERS:
            raise ValueError(f"--logger must be one of {', '.join(LOGGERS)}, got {self.logger!r}")
        _check_device(self.device)
        check_nproc(self.nproc, self.device)


def _paths(config: Any, *names: str) -> None:
    """``config``'s path fields as ``Path`` (a string from Python, as the command line's
    are; a hostile review: ``BCJob(out="results/x")`` ran the whole job, then failed on
    ``str / str`` before writing it); ValueError naming a field of another type."""
    for name in names:
        value = getattr(config, name)
        if isinstance(value, str):
            object.__setattr__(config, name, Path(value))
        elif value is not None and not isinstance(value, Path):
            raise ValueError(f"{name} must be a path (str or pathlib.Path), got {value!r}")


@dataclass(frozen=True)
class BCJob(BCConfig, RunFlags):
    """Behaviour cloning, evaluated against the expert on the same initial states: every
    field of the fit (:class:`~imitrl.configs.bc.BCConfig`) and of the run."""

    seed: int = bounded(0, 0, MAX_SEED)
    """seeds the env that plays the demonstrations, the learner's initialisation and
    the minibatch order"""

    def __post_init__(self) -> None:
        self._check_run()
        BCConfig.__post_init__(self)

    def fit(self) -> BCConfig:
        """The fit the flags describe (the library's :class:`BCConfig`)."""
        return BCConfig(**_library(self, BCConfig))


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
    beta_decay: float | None = bounded(None, 0, 1, integer=False, none_ok=True)
    """Ross et al.'s schedule instead of a constant --beta: the expert acts with
    probability P^(i-1) in relabel round i (round 1 all expert, then the learner more and
    more; measured better than 0 on Meta-World's object tasks: benchmarks/dagger_labels.py);
    none = --beta"""
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
    gate: float | None = bounded(None, 0, integer=False, none_ok=True)
    """a gated expert instead of --beta's coin: the expert takes over where the learner's
    action is farther than this from its own (Euclidean; discrete actions: where they
    differ); none = --beta decides"""
    label: str = "all"
    """which visited states the expert labels: all (DAgger) or interventions (HG-DAgger,
    with --gate: the frames it took over, each streak an episode of its own)"""
    save_lerobot: int | None = bounded(None, 1, MAX_FPS, none_ok=True)
    """write the demonstrations and every round, after each fit, as a LeRobot v3.0 dataset
    in LeRobot's DAgger schema (OUT/lerobot: intervention, the expert's action, the round,
    beta, the policy version) recorded at this many frames per second (the env's control
    rate; LeRobot's metaworld_mt50 has 80); none = not written"""
    chunk_labels: str = "mask"
    """a chunked learner's labels at the states its rounds visit: mask = the expert's
    label at each state, the rest of the chunk masked (windowing); plan = the expert's
    own next H actions from each state, played on the env from there and undone (whole
    chunks; H expert steps per visited state; one lane, in this process)"""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.env is None:
            raise ValueError("dagger plays the learner in an env: --env none is for imitrl bc")
        if self.expert is None:
            raise ValueError("dagger needs --expert to label the learner's states")
        if self.num_steps < 1:  # (bc takes 0: an untrained clone's evaluation)
            raise ValueError("dagger fits the learner every round: --steps must be >= 1")
        if self.address is not None and self.workers is None:
            raise ValueError("--address names the Ray cluster for --workers: give --workers too")
        if self.label not in ("all", "interventions"):
            raise ValueError(f"--label must be all or interventions, got {self.label!r}")
        if self.label == "interventions" and self.gate is None:
            raise ValueError(
                "--label interventions (HG-DAgger) labels what --gate hands the expert: give --gate"
            )
        if self.gate is not None and (self.beta > 0 or self.beta_decay is not None):
            raise ValueError(
                "--gate decides who acts instead of --beta's coin: leave --beta at 0 and "
                "--beta-decay out"
            )
        if self.beta_decay is not None and self.beta > 0:
            raise ValueError(
                "--beta-decay is a schedule of beta instead of the constant --beta: give one"
            )
        if self.chunk_labels not in CHUNK_LABELS:
            raise ValueError(
                f"--chunk-labels must be one of {', '.join(CHUNK_LABELS)}, got {self.chunk_labels!r}"
            )
        if self.chunk_labels == "plan" and (self.workers is not None or self.num_envs > 1):
            raise ValueError(
                "--chunk-labels plan plays the expert's plans on the env in this process, one "
                "lane: leave out --workers and --num-envs"
            )


@dataclass(frozen=True)
class GAILJob(GAILConfig, RunFlags):
    """GAIL from expert demonstrations or a dataset, evaluated against the expert: every
    field of :class:`~imitrl.configs.adversarial.GAILConfig` (budget, PPO,
    discriminator) and of the run."""

    num_envs: int = bounded(1, 1, MAX_NUM_ENVS)
    """env copies (lanes) the generator steps together, its policy batched over them;
    --rollout-steps must be a multiple of it"""
    demos: int = bounded(1, 0, MAX_EPISODES)
    """greedy expert demonstration episodes (when no --dataset): GAIL's protocol learns
    from one"""
    loss: str = "default"
    """the learner: a loss-registry name whose head is probabilistic (built with a value
    head for PPO); default = cross_entropy for discrete actions, gaussian_nll for
    continuous ones"""
    lr: float = bounded(ADVERSARIAL_LR, 0, integer=False, low_open=True)
    """Adam learning rate of the learner (PPO's policy and value steps)"""
    eval_episodes: int = bounded(20, 1, MAX_EVAL_EPISODES)
    """evaluation episodes of the expert and of the learner"""
    eval_every: int = bounded(10, 0)
    """evaluate the learner after every this many rounds (and after the last); 0 =
    after the last only"""
    seed: int = bounded(0, 0, MAX_SEED)
    """seeds the env, the learner's initialisation and every draw of the run"""
    out: Path = Path("results/gail")
    """output directory: results.json, config.json + learner.pt, curves.png, logs/"""

    def __post_init__(self) -> None:
        self._check_run()
        if self.env is None:
            raise ValueError(
                "gail and airl play the learner in an env: --env none is for imitrl bc"
            )
        GAILConfig.__post_init__(self)
        if self.rollout_steps % self.num_envs:
            raise ValueError(
                f"--rollout-steps ({self.rollout_steps}) must be a multiple of --num-envs "
                f"({self.num_envs}): each round steps every lane equally"
            )

    def algorithm_config(self) -> GAILConfig:
        """The :class:`GAILConfig` the flags describe."""
        return GAILConfig(**_library(self, GAILConfig))

    def bc_view(self, loss: str) -> BCJob:
        """The run's flags as a ``BCJob`` (what :func:`imitrl.jobs.bc.prepare` reads)."""
        run = _library(self, RunFlags)
        return BCJob(**{**run, "loss": loss}, num_steps=0, seed=self.seed)


@dataclass(frozen=True)
class AIRLJob(GAILJob, AIRLConfig):
    """AIRL (state-only reward g, shaping h): every flag of imitrl gail, and
    :class:`~imitrl.configs.adversarial.AIRLConfig`'s ``--entropy-weight``."""

    out: Path = Path("results/airl")
    """output directory: results.json, config.json + learner.pt, curves.png, logs/"""

    def algorithm_config(self) -> AIRLConfig:  # type: ignore[override]
        """The :class:`AIRLConfig` the flags describe."""
        return AIRLConfig(**_library(self, AIRLConfig))
