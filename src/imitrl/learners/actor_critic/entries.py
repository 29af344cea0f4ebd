"""The registry's table, MLP and CNN learners (:class:`ActorCritic`): one builder per entry.

Each builder takes ``(task, config)`` and returns a learner; the catalogue
(:mod:`imitrl.learners.catalogue`) registers them under their names, with their
summaries. Integer observations get a table of logits (``ActorCritic.tabular``), vector
observations an MLP (``ActorCritic.mlp``). The chunked entries (``mse_chunk``,
``l1_chunk``, ``l1_chunk_ensemble``, ``gaussian_nll_chunk``) are the same MLP over the
tiled action spec (:mod:`imitrl.learners.chunks`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType

from imitrl import keys
from imitrl.learners.actor_critic.learner import ActorCritic
from imitrl.learners.chunks import CHUNK_HORIZON, RECEDING, chunk_task, chunked_learner
from imitrl.learners.defaults import PIXEL_CHANNELS, PIXEL_HIDDEN, learning_rate
from imitrl.learners.learner import Learner
from imitrl.learners.registry import LearnerConfig
from imitrl.learners.task import TaskSpec
from imitrl.objectives.advantage_weighted import AdvantageWeightedLoss
from imitrl.objectives.base import ImitationLoss
from imitrl.objectives.bc import BehaviorCloningLoss
from imitrl.objectives.chunked import FLAT_CHUNK, ChunkRegressionLoss, FlatChunkLoss
from imitrl.objectives.regularized import RegularizedBCLoss
from imitrl.policies.chunking import ChunkExecution

__all__ = [
    "ENTROPY_COEF",
    "L2_COEF",
    "ForEnvOptions",
    "advantage_weighted",
    "chunk_regression",
    "cross_entropy",
    "cross_entropy_entropy",
    "for_env",
    "gaussian_nll",
    "gaussian_nll_chunk",
    "mlp",
    "mse_l2",
    "regression",
]

ENTROPY_COEF = 0.01
"""weight of the entropy bonus of ``cross_entropy_entropy``"""
L2_COEF = 1e-4
"""weight of the L2 penalty of ``mse_l2``"""

Build = Callable[[TaskSpec, LearnerConfig], Learner]


def mlp(
    task: TaskSpec,
    config: LearnerConfig,
    *,
    head: str | None = None,
    loss: str | ImitationLoss | None = None,
) -> ActorCritic:
    """The task's standard learner: a logits table for integer states, else an MLP with
    ``head``, trained with ``loss`` (a loss type of the head, None = its default), at
    ``config.lr`` or the network's default rate (:mod:`imitrl.learners.defaults`); a value
    head beside it when ``config.value``."""
    lr = learning_rate(None, task.num_states, config.lr)
    if task.num_states is not None:
        if task.actions != "discrete" or head not in (None, "categorical"):
            raise ValueError("integer-state tasks support a categorical policy only")
        if loss not in (None, "nll"):
            raise ValueError("a tabular policy is built with its cross-entropy loss")
        if config.hidden is not None:
            raise ValueError(
                f"hidden {','.join(map(str, config.hidden))}: on {task.num_states} integer "
                "states this entry builds a logits table, which has no hidden layers; leave "
                "hidden out, or take loss for_env (an MLP on one-hot states)"
            )
        return ActorCritic.tabular(task.num_states, task.action, lr=lr, value=config.value)
    return ActorCritic.mlp(
        task.observation_dim,
        task.action,
        head=head,
        loss=loss,
        hidden=config.width,
        lr=lr,
        seed=config.seed,
        normalize=config.normalize,
        value=config.value,
    )


@dataclass(frozen=True)
class ForEnvOptions:
    """``for_env``'s own settings: the head and, on images, the convolutions."""

    head: str | None = None
    """one of :data:`~imitrl.policies.heads.HEADS` that fits the action (None: its default:
    categorical, multi, or deterministic for continuous actions)"""
    loss: str | None = None
    """the head's loss type (None: its default, :data:`~imitrl.policies.heads.HEAD_LOSSES`)"""
    activation: type[nn.Module] | None = None
    """hidden activation (None: ``Tanh`` for an MLP, ``ReLU`` for a CNN)"""
    channels: tuple[int, ...] = PIXEL_CHANNELS
    """a CNN's convolutions (images)"""
    state: bool = False
    """a CNN learner reads the state beside the image (by default the state is the
    privileged expert's, and the learner sees the image alone)"""
    pixel_key: NestedKey | None = None
    """the image a CNN learner reads (None: ``pixels``; a nested camera key)"""


def for_env(task: TaskSpec, config: LearnerConfig) -> Learner:
    """``for_env``: the network the env's specs call for (a CNN on images, a one-hot MLP on
    integer states, an MLP on vectors; any action spec: categorical, one-hot,
    multi-discrete, bounded or unbounded), with its head's default loss (or
    ``ForEnvOptions``')."""
    options = config.options if config.options is not None else ForEnvOptions()
    observation, action = task.env_specs()
    pixels = options.pixel_key is not None or keys.PIXELS in observation.keys()
    assert config.lr is not None  # registry.make resolved it
    return ActorCritic.for_specs(
        observation,
        action,
        head=options.head,
        loss=options.loss,
        hidden=config.hidden if config.hidden is not None else (PIXEL_HIDDEN if pixels else None),
        activation=options.activation,
        lr=config.lr,
        seed=config.seed,
        normalize=config.normalize,
        state=options.state,
        channels=options.channels,
        pixel_key=options.pixel_key,
        value=config.value,
    )


def _with_loss(ac: ActorCritic, loss: ImitationLoss) -> ActorCritic:
    """``ac`` trained by ``loss`` (a loss over ``ac.policy``) instead of its default: every
    constructor argument carried over (a pixel learner's inputs, the action space)."""
    return ActorCritic(
        ac.policy,
        ac.value,
        head=ac.head,
        loss=loss,
        lr=ac.lr,
        num_states=ac.num_states,
        observation_shape=ac.observation_shape,
        normalizer=ac.normalizer,
        action=ac.action_space,
        pixel_inputs=ac.pixel_inputs,
    )


def cross_entropy(task: TaskSpec, config: LearnerConfig) -> Learner:
    """``cross_entropy``: the categorical head's negative log-likelihood."""
    return mlp(task, config)


def cross_entropy_entropy(task: TaskSpec, config: LearnerConfig) -> Learner:
    """``cross_entropy_entropy``: cross-entropy minus :data:`ENTROPY_COEF` times the
    policy's entropy."""
    ac = mlp(task, config)
    return _with_loss(ac, RegularizedBCLoss(ac.policy, loss_type="nll", entropy_coef=ENTROPY_COEF))


def advantage_weighted(task: TaskSpec, config: LearnerConfig) -> Learner:
    """``advantage_weighted``: ``-A(s, a*) log pi(a*|s)`` (``task.advantage``)."""
    ac = mlp(task, config)
    assert task.advantage is not None  # the entry requires it (registry.make checked)
    return _with_loss(ac, AdvantageWeightedLoss(ac.policy, task.advantage))


def gaussian_nll(task: TaskSpec, config: LearnerConfig) -> Learner:
    """``gaussian_nll``: the head chosen by a measured sweep (``benchmarks/README.md``,
    issue 31): on the loss benchmark's continuous tasks (5 seeds, BC / DAgger mean
    normalised score) ``tanh_normal_free`` 0.74 / 0.73, ``normal_free`` 0.63 / 0.68, the
    state-dependent ``tanh_normal`` this entry used before 0.25 / 0.17 and ``normal``
    0.22 / 0.15: a likelihood fit that may shrink its scale state by state chases the
    labels' noise. Labels on the bounds are refused, as by every tanh head
    (``normal_free`` takes them)."""
    return mlp(task, config, head="tanh_normal_free")


def regression(loss_type: str) -> Build:
    """``mse``, ``l1``, ``smooth_l1``: a deterministic (tanh) head fitted by ``loss_type``."""

    def build_regression(task: TaskSpec, config: LearnerConfig) -> Learner:
        return mlp(task, config, head="deterministic", loss=loss_type)

    return build_regression


def mse_l2(task: TaskSpec, config: LearnerConfig) -> Learner:
    """``mse_l2``: MSE plus :data:`L2_COEF` times the squared L2 norm of the weights."""
    ac = mlp(task, config, head="deterministic")
    return _with_loss(ac, RegularizedBCLoss(ac.policy, loss_type="mse", l2_coef=L2_COEF))


def chunk_regression(loss_type: str, execution: ChunkExecution) -> Build:
    """``mse_chunk``, ``l1_chunk``, ``l1_chunk_ensemble``: a deterministic MLP over the
    tiled chunk, fitted by the masked ``loss_type``, executed as ``execution`` says."""

    def build(task: TaskSpec, config: LearnerConfig) -> Learner:
        ac = mlp(chunk_task(task), config, head="deterministic")
        loss = ChunkRegressionLoss(ac.policy, horizon=CHUNK_HORIZON, loss_type=loss_type)
        det = ExplorationType.DETERMINISTIC
        return chunked_learner(
            task, ac.policy, loss, ac.opt_pi, execution, exploration=det, normalizer=ac.normalizer
        )

    return build


def gaussian_nll_chunk(task: TaskSpec, config: LearnerConfig) -> Learner:
    """``gaussian_nll_chunk``: the head as ``gaussian_nll``'s (one learned log-std per
    dimension): on the loss benchmark's continuous tasks (5 seeds) its BC / DAgger mean
    normalised score rose from 0.16 / 0.03 with the state-dependent scale to 0.31 / 0.35
    (corridor fell, 0.50 -> 0.08 as BC; Pendulum and the two-way task rose)."""
    ac = mlp(chunk_task(task), config, head="tanh_normal_free")
    inner = BehaviorCloningLoss(ac.policy, loss_type="nll")
    inner.set_keys(label=FLAT_CHUNK)
    assert isinstance(task.action, Bounded)  # a continuous entry's task: a Bounded [m] spec
    loss = FlatChunkLoss(inner, dim=CHUNK_HORIZON * int(task.action.shape[0]))
    det = ExplorationType.DETERMINISTIC
    return chunked_learner(
        task, ac.policy, loss, ac.opt_pi, RECEDING, exploration=det, normalizer=ac.normalizer
    )
