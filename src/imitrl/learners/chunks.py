"""What every chunked entry shares: ``H`` and ``k``, the execution modes, the tiled task.

A chunked learner predicts the expert's next :data:`CHUNK_HORIZON` actions at once (a
network over the tiled action spec ``[H * m]``, :func:`chunk_task`) and acts through a
:class:`~imitrl.policies.chunking.ChunkedPolicy` (:func:`chunked_learner`): receding
horizon (:data:`RECEDING`: execute :data:`CHUNK_EXECUTE` actions, then replan; a flow
holding its noise draw per episode: :data:`RECEDING_HELD`) or ACT's temporal ensembling
(:data:`ENSEMBLE`). Its rows need chunk labels and its envs ``is_init``; its
:class:`~imitrl.learners.registry.LossEntry` says so with ``horizon``.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded
from torchrl.envs.utils import ExplorationType

from imitrl.learners.learner import Learner
from imitrl.learners.task import TaskSpec
from imitrl.objectives.base import ImitationLoss
from imitrl.policies.chunking import ACT_ENSEMBLE_M, ChunkedPolicy, ChunkExecution, tile_spec
from imitrl.policies.normalization import ObservationNormalizer

__all__ = [
    "CHUNK_EXECUTE",
    "CHUNK_HORIZON",
    "ENSEMBLE",
    "ENSEMBLE_M",
    "RECEDING",
    "RECEDING_HELD",
    "chunk_task",
    "chunked_learner",
]

# H and k, measured on the two-way task (flow_chunk, BC, 200 held-out episodes per
# setting, seeds 0-1): k = 2-4 is best; k = 1 lets a sampling policy switch modes
# (0.77 against 0.94 on one seed); k = H = 8 executes a bad chunk to its end (0.86-0.93);
# H = 4 did about as well as H = 8, H = 16 worse (0.85-0.90). Euler steps (8, 16, 32)
# changed success by less than the seed-to-seed spread; what mattered was the labels seen
# in training (benchmarks/README.md).
CHUNK_HORIZON = 8
"""``H``: actions predicted per query"""
CHUNK_EXECUTE = 4
"""``k``: actions executed per query (receding horizon) before replanning"""
ENSEMBLE_M = ACT_ENSEMBLE_M
"""``m`` of ACT's temporal-ensembling weights ``exp(-m i)`` (the paper's value, declared
in :mod:`imitrl.policies.chunking`)"""
RECEDING = ChunkExecution(CHUNK_HORIZON, execute=CHUNK_EXECUTE)
"""receding horizon: ``k`` of ``H`` actions executed, then a new query"""
RECEDING_HELD = ChunkExecution(CHUNK_HORIZON, execute=CHUNK_EXECUTE, hold_noise=True)
"""the receding horizon of ``flow_chunk``: one noise draw per episode (a flow's map from
noise to chunk is deterministic, so an episode keeps the mode its draw chose)"""
ENSEMBLE = ChunkExecution(CHUNK_HORIZON, ensemble=ENSEMBLE_M)
"""ACT's temporal ensembling: a query every step, chunks averaged with ``exp(-m i)``"""


def chunk_task(task: TaskSpec) -> TaskSpec:
    """The task with its action tiled to a flat chunk ``[H * m]``."""
    return TaskSpec(
        action=tile_spec(task.action, CHUNK_HORIZON), observation_dim=task.observation_dim
    )


def chunked_learner(
    task: TaskSpec,
    network: TensorDictModuleBase,
    loss: ImitationLoss,
    opt: torch.optim.Optimizer,
    execution: ChunkExecution,
    *,
    exploration: ExplorationType,
    normalizer: ObservationNormalizer | None = None,
) -> Learner:
    """A :class:`Learner` acting through ``network``'s chunks as ``execution`` says."""
    assert isinstance(task.action, Bounded)  # a continuous entry's task: a Bounded [m] spec
    m = int(task.action.shape[0])
    policy = ChunkedPolicy(network, m, execution)
    return Learner(
        policy,
        loss,
        opt,
        exploration=exploration,
        normalizer=normalizer,
        horizon=execution.horizon,
    )
